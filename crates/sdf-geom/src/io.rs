//! Output files, written so that a crash or Ctrl-C never leaves a partial file behind.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::Mesh;

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, synced, then
/// renamed over `path`. Readers see the old file or the new one, never a partial write.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().ok_or_else(|| {
        std::io::Error::new(std::io::ErrorKind::InvalidInput, "path has no file name")
    })?;
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    tmp_name.push(format!(".{}.tmp", std::process::id()));
    let tmp = dir.join(tmp_name);
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// The mesh as Wavefront OBJ text: shared vertices (`v`), then 1-based triangles (`f`).
pub fn obj_string(mesh: &Mesh) -> String {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(mesh.vertices.len() * 40 + mesh.triangles.len() * 24);
    let _ = writeln!(
        s,
        "# {} vertices, {} triangles, written by hwsdf",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    for v in &mesh.vertices {
        let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// Writes the mesh as OBJ, atomically.
pub fn write_obj(mesh: &Mesh, path: &Path) -> std::io::Result<()> {
    write_atomic(path, obj_string(mesh).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn obj_round_trips_through_the_loader() {
        let mesh = Mesh {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        };
        let dir = std::env::temp_dir().join(format!("hwsdf-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.obj");
        write_obj(&mesh, &path).unwrap();
        let (back, _) = crate::load_mesh(&path).unwrap();
        // The loader (tobj) numbers vertices by first use, so compare the triangles' corners.
        let corners = |m: &Mesh| -> Vec<[Vec3; 3]> {
            m.triangles.iter().map(|t| m.corners(t).unwrap()).collect()
        };
        assert_eq!(corners(&back), corners(&mesh));
        assert_eq!(back.vertices.len(), mesh.vertices.len());
        // Only the file itself: the temporary was renamed away.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
