//! Output files, written so that a crash or Ctrl-C never leaves a partial file behind, and
//! checked before any work so that no output ever replaces an input or another output.

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{DVec3, Vec3};

use crate::Mesh;

/// Writes `bytes` to `path` atomically: a temporary file with a random name, created exclusively
/// (`O_EXCL`) in the target's folder, synced, then renamed over `path`. Readers see the old file
/// or the new one, never a partial write; a link planted under a guessable temporary name cannot
/// redirect the write, and on error the temporary file is removed. Through a symbolic link (a
/// chain, or a dangling one) it writes the file the link leads to and keeps the link, as `cp`
/// and a shell's `>` do.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_via_temp(path, bytes, true)
}

/// [`write_atomic`] that never replaces a file: it fails with
/// [`std::io::ErrorKind::AlreadyExists`] if `path` exists, also when another process creates it
/// at the same moment (the temporary file is linked into place, not renamed over it).
pub fn create_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_via_temp(path, bytes, false)
}

fn write_via_temp(path: &Path, bytes: &[u8], replace: bool) -> std::io::Result<()> {
    // Through a link, write its target and leave the link a link, as `cp` and `>` do.
    let target =
        write_target(path).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
    let dir = parent_dir(&target);
    let mut builder = tempfile::Builder::new();
    // A short fixed prefix, not one built from the file name: the temporary must never need a
    // longer name than the target, or a name [`check_outputs`] accepted would fail here.
    builder.prefix(TEMP_PREFIX).suffix(".tmp");
    // tempfile creates files 0600; a model or a mesh is an ordinary file (0666 less the umask).
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    // Dropping `tmp` on any error below deletes it.
    let mut tmp = builder.tempfile_in(&dir)?;
    // A file replaced keeps its mode (a private model stays 0600), as `cp` and `>` keep it.
    if replace && let Ok(existing) = std::fs::metadata(&target) {
        tmp.as_file().set_permissions(existing.permissions())?;
    }
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    if replace {
        tmp.persist(&target).map_err(|e| e.error)?;
    } else {
        tmp.persist_noclobber(&target).map_err(|e| e.error)?;
    }
    Ok(())
}

/// How every temporary file of this module starts.
const TEMP_PREFIX: &str = ".hwsdf-";

/// The most links followed in a row, as Linux's own limit (`ELOOP`).
const MAX_LINKS: usize = 40;

/// The file a write to `path` creates or replaces: `path`, or where its chain of symbolic links
/// ends (a target that does not exist yet is created). Relative targets are joined to the link's
/// folder unnormalised, so the OS resolves `..` the way it does when following the link.
fn write_target(path: &Path) -> Result<PathBuf, OutputPathError> {
    let mut target = path.to_owned();
    for _ in 0..=MAX_LINKS {
        if target.file_name().is_none() {
            return Err(OutputPathError::NoFileName(target));
        }
        // `x/` and `x/.` have the file name `x` but can only be folders.
        if names_a_folder(&target) {
            return Err(OutputPathError::FolderName(target));
        }
        match std::fs::symlink_metadata(&target) {
            Ok(meta) if meta.file_type().is_symlink() => {}
            // Not a link, or nothing there yet; or unreadable, which the checks after report.
            _ => return Ok(target),
        }
        let link = std::fs::read_link(&target).map_err(|source| OutputPathError::ReadLink {
            path: target.clone(),
            source,
        })?;
        target = match target.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir.join(link),
            _ => link,
        };
    }
    Err(OutputPathError::LinkLoop(path.to_owned()))
}

/// Whether `path` ends with a separator or a `.` component.
fn names_a_folder(path: &Path) -> bool {
    let b = path.as_os_str().as_encoded_bytes();
    let sep = |c: u8| std::path::is_separator(char::from(c));
    match b {
        [.., last] if sep(*last) => true,
        [.., before, b'.'] => sep(*before),
        [b'.'] => true,
        _ => false,
    }
}

/// The folder a file named by `path` lives in (`.` for a bare name).
fn parent_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
        _ => PathBuf::from("."),
    }
}

/// Why an output path cannot be used. Checked by [`check_outputs`] before any work starts.
#[derive(Debug, thiserror::Error)]
pub enum OutputPathError {
    /// The output names the same file as an input: writing it would destroy the input.
    #[error("output {output} is the same file as the input {input}; choose another output path")]
    SameAsInput {
        /// The output as given.
        output: PathBuf,
        /// The input it aliases.
        input: PathBuf,
    },
    /// Two outputs name the same file: one would be written over the other.
    #[error("outputs {first} and {second} are the same file; give them different paths")]
    SameOutput {
        /// One output.
        first: PathBuf,
        /// The other.
        second: PathBuf,
    },
    /// The path has no file name (`/`, `..`, or an empty path).
    #[error("output {0} does not name a file")]
    NoFileName(PathBuf),
    /// The output's folder does not exist.
    #[error("cannot write {path}: folder {dir} does not exist")]
    MissingFolder {
        /// The output.
        path: PathBuf,
        /// Its folder.
        dir: PathBuf,
    },
    /// A file cannot be created in the output's folder (read-only, no permission, ...).
    #[error("cannot write {path}: folder {dir} is not writable: {source}")]
    NotWritable {
        /// The output.
        path: PathBuf,
        /// Its folder.
        dir: PathBuf,
        /// The OS error from a trial file.
        source: std::io::Error,
    },
    /// The output exists and is not a regular file (a folder, a FIFO, a device).
    #[error("cannot write {0}: it exists and is not a regular file")]
    NotAFile(PathBuf),
    /// The path ends with `/` (or `/.`): it can only name a folder.
    #[error("output {0} ends with '/' so it names a folder; give a file name")]
    FolderName(PathBuf),
    /// The file name is longer than the folder's filesystem allows (`NAME_MAX`, 255 bytes on
    /// most): the final rename would fail after all the work.
    #[error("cannot write {path}: file name too long ({len} bytes) for the filesystem of {dir}")]
    NameTooLong {
        /// The file that would be written (a link's target).
        path: PathBuf,
        /// Its file name's length in bytes.
        len: usize,
        /// Its folder.
        dir: PathBuf,
    },
    /// The output is a symbolic link in a loop, or more than 40 links in a row.
    #[error("cannot write {0}: too many levels of symbolic links (a link loop?)")]
    LinkLoop(PathBuf),
    /// A symbolic link on the output's way cannot be read.
    #[error("cannot read the symbolic link {path}: {source}")]
    ReadLink {
        /// The link.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// Where a path leads: its canonical form, and for an existing file its device and inode (so
/// hard links and bind mounts compare equal too).
#[derive(Debug, PartialEq, Eq)]
struct FileId {
    canonical: PathBuf,
    #[cfg(unix)]
    inode: Option<(u64, u64)>,
}

impl FileId {
    /// `None` when neither the path nor its folder resolves (nothing there to alias).
    fn of(path: &Path) -> Option<FileId> {
        let canonical = match std::fs::canonicalize(path) {
            Ok(c) => c,
            // A file not created yet can only alias something through its folder and name.
            Err(_) => std::fs::canonicalize(parent_dir(path))
                .ok()?
                .join(path.file_name()?),
        };
        #[cfg(unix)]
        let inode = {
            use std::os::unix::fs::MetadataExt;
            std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
        };
        Some(FileId {
            canonical,
            #[cfg(unix)]
            inode,
        })
    }

    fn same(&self, other: &FileId) -> bool {
        #[cfg(unix)]
        if let (Some(a), Some(b)) = (self.inode, other.inode) {
            return a == b;
        }
        self.canonical == other.canonical
    }
}

/// Checks, before any work starts, that every output can be written and destroys nothing: its
/// folder exists and accepts a new file with a name as long as the output's, it is not an
/// existing folder or special file, and it is not the same file as any input or as another
/// output (canonical paths, and device and inode where the file exists). An output that is a
/// symbolic link is checked as the file it leads to, which is what [`write_atomic`] writes.
pub fn check_outputs(inputs: &[&Path], outputs: &[&Path]) -> Result<(), OutputPathError> {
    let input_ids: Vec<(&Path, Option<FileId>)> =
        inputs.iter().map(|&p| (p, FileId::of(p))).collect();
    let mut seen: Vec<(&Path, FileId)> = Vec::new();
    for &out in outputs {
        let target = write_target(out)?;
        let dir = parent_dir(&target);
        if !dir.is_dir() {
            return Err(OutputPathError::MissingFolder {
                path: out.to_owned(),
                dir,
            });
        }
        if let Ok(meta) = std::fs::metadata(&target)
            && !meta.is_file()
        {
            return Err(OutputPathError::NotAFile(out.to_owned()));
        }
        // `write_target` returned a path with a file name.
        let len = target.file_name().map_or(0, |n| n.len());
        if let Err(source) = probe_folder(&dir, len) {
            if source.kind() == std::io::ErrorKind::InvalidFilename {
                return Err(OutputPathError::NameTooLong {
                    path: target,
                    len,
                    dir,
                });
            }
            return Err(OutputPathError::NotWritable {
                path: out.to_owned(),
                dir,
                source,
            });
        }
        let Some(id) = FileId::of(&target) else {
            continue;
        };
        if let Some((input, _)) = input_ids
            .iter()
            .find(|(_, i)| i.as_ref().is_some_and(|i| i.same(&id)))
        {
            return Err(OutputPathError::SameAsInput {
                output: out.to_owned(),
                input: input.to_path_buf(),
            });
        }
        if let Some((first, _)) = seen.iter().find(|(_, s)| s.same(&id)) {
            return Err(OutputPathError::SameOutput {
                first: first.to_path_buf(),
                second: out.to_owned(),
            });
        }
        seen.push((out, id));
    }
    Ok(())
}

/// Creates, then removes, a file in `dir` whose name is `name_len` bytes long (at least
/// [`TEMP_PREFIX`] and six random characters). Only creating a file shows that the folder is
/// writable (ACLs, read-only mounts) and that its filesystem takes a name that long; the name is
/// random and created exclusively, so nothing is overwritten.
fn probe_folder(dir: &Path, name_len: usize) -> std::io::Result<()> {
    let random = name_len.saturating_sub(TEMP_PREFIX.len()).max(6);
    tempfile::Builder::new()
        .prefix(TEMP_PREFIX)
        .rand_bytes(random)
        .tempfile_in(dir)
        .map(drop)
}

/// Reads a whole file that must be a regular file (not a FIFO, a device or a folder) of at most
/// `max_bytes`; both are checked before anything is read or allocated. The same checks as the
/// mesh readers' [`crate::read_input_file`], with an I/O error for callers outside sdf-geom.
pub fn read_regular_file(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    crate::load::read_file_within(path, max_bytes).map_err(|e| match e {
        crate::GeomError::Io { source, .. } => source,
        other => std::io::Error::new(std::io::ErrorKind::InvalidInput, other.to_string()),
    })
}

/// The mesh as Wavefront OBJ text: shared vertices (`v`), then 1-based triangles (`f`).
pub fn obj_string(mesh: &Mesh) -> String {
    obj_text(mesh, |s, v| {
        use std::fmt::Write as _;
        let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
    })
}

/// The OBJ text of `mesh`, each vertex's line written by `vertex`.
fn obj_text(mesh: &Mesh, vertex: impl Fn(&mut String, Vec3)) -> String {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(mesh.vertices.len() * 40 + mesh.triangles.len() * 24);
    let _ = writeln!(
        s,
        "# {} vertices, {} triangles, written by hwsdf",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    for v in &mesh.vertices {
        vertex(&mut s, *v);
    }
    // 1-based, in u64: an index of u32::MAX (a hand-built mesh's, out of range) must not wrap.
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| u64::from(i) + 1);
        let _ = writeln!(s, "f {a} {b} {c}");
    }
    s
}

/// Writes the mesh as OBJ, atomically; an error, with nothing written, where a triangle names
/// a vertex the mesh does not have (a hand-built mesh's; the file would name it too).
pub fn write_obj(mesh: &Mesh, path: &Path) -> std::io::Result<()> {
    check_obj_indices(mesh)?;
    write_atomic(path, obj_string(mesh).as_bytes())
}

fn check_obj_indices(mesh: &Mesh) -> std::io::Result<()> {
    crate::mesh::check_indices(&mesh.triangles, mesh.vertices.len())
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string()))
}

/// Writes the mesh moved by `offset` as OBJ, atomically: a mesh computed relative to a centre
/// far from the origin, its vertices written as `vertex + offset` in f64 (f32 would round them
/// onto a grid as coarse as a unit at 10⁷). A zero offset writes what [`write_obj`] writes.
pub fn write_obj_offset(mesh: &Mesh, offset: DVec3, path: &Path) -> std::io::Result<()> {
    if offset == DVec3::ZERO {
        return write_obj(mesh, path);
    }
    check_obj_indices(mesh)?;
    let text = obj_text(mesh, |s, v| {
        use std::fmt::Write as _;
        let p = v.as_dvec3() + offset;
        let _ = writeln!(s, "v {} {} {}", p.x, p.y, p.z);
    });
    write_atomic(path, text.as_bytes())
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

    /// A hand-built mesh naming a vertex it lacks is refused, nothing written (u32::MAX + 1
    /// overflowed in debug builds and wrote index 0 in release ones).
    #[test]
    fn obj_of_a_mesh_with_bad_indices_is_refused() {
        let dir = scratch("bad-index");
        let path = dir.join("bad.obj");
        for bad in [u32::MAX, 3] {
            let mesh = Mesh {
                vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
                triangles: vec![[0, 1, 2], [bad, 0, 1]],
            };
            let e = write_obj(&mesh, &path).unwrap_err();
            assert!(e.to_string().contains("triangle 1"), "{e}");
            assert!(write_obj_offset(&mesh, DVec3::X * 1e7, &path).is_err());
            assert!(obj_string(&mesh).contains(&format!("f {} 1 2", u64::from(bad) + 1)));
        }
        assert!(!path.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Replacing a file keeps its mode: a private model stays private.
    #[cfg(unix)]
    #[test]
    fn replaced_files_keep_their_mode() {
        use std::os::unix::fs::PermissionsExt;
        let dir = scratch("mode");
        let path = dir.join("private.bin");
        write_atomic(&path, b"old").unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        write_atomic(&path, b"new").unwrap();
        let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("hwsdf-io-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn atomic_writes_leave_no_temporary_behind() {
        // (A link planted at a temporary's name cannot redirect a write: the random names are
        // created with O_EXCL by tempfile.)
        let dir = scratch("planted");
        let victim = dir.join("victim.txt");
        std::fs::write(&victim, b"precious").unwrap();
        let out = dir.join("out.txt");
        write_atomic(&out, b"old").unwrap();
        write_atomic(&out, b"new").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
        assert_eq!(std::fs::read(&out).unwrap(), b"new");
        // The victim and the output; no temporary left.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 2);
        // Failing writes leave nothing behind either.
        assert!(write_atomic(&dir.join("missing/x.txt"), b"x").is_err());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn create_atomic_never_replaces_a_file() {
        let dir = scratch("create");
        let out = dir.join("settings.json");
        create_atomic(&out, b"first").unwrap();
        let again = create_atomic(&out, b"second").unwrap_err();
        assert_eq!(again.kind(), std::io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read(&out).unwrap(), b"first");
        // The refused write left no temporary behind.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn outputs_that_alias_inputs_or_each_other_are_refused() {
        let dir = scratch("alias");
        let input = dir.join("mesh.obj");
        std::fs::write(&input, b"v 0 0 0").unwrap();
        let other = dir.join("other.obj");
        let err = |inputs: &[&Path], outputs: &[&Path]| check_outputs(inputs, outputs).err();
        assert!(err(&[&input], &[&other, &dir.join("r.json")]).is_none());
        // The same file by name, through `..`, through a symlink, and through a hard link.
        let dotted = dir.join("sub/../mesh.obj");
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let hard = dir.join("hard.obj");
        std::fs::hard_link(&input, &hard).unwrap();
        let mut aliases = vec![input.clone(), dotted, hard];
        #[cfg(unix)]
        {
            let link = dir.join("link.obj");
            std::os::unix::fs::symlink(&input, &link).unwrap();
            aliases.push(link);
        }
        for alias in &aliases {
            assert!(
                matches!(
                    err(&[&input], &[alias]),
                    Some(OutputPathError::SameAsInput { .. })
                ),
                "{}",
                alias.display()
            );
        }
        // Two outputs that do not exist yet but name the same file.
        assert!(matches!(
            err(&[&input], &[&other, &dir.join("sub/../other.obj")]),
            Some(OutputPathError::SameOutput { .. })
        ));
        assert!(matches!(
            err(&[], &[&dir.join("missing/x.obj")]),
            Some(OutputPathError::MissingFolder { .. })
        ));
        assert!(matches!(
            err(&[], &[&dir.join("sub")]),
            Some(OutputPathError::NotAFile(_))
        ));
        assert!(matches!(
            err(&[], &[Path::new("/")]),
            Some(OutputPathError::NoFileName(_))
        ));
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let ro = dir.join("ro");
            std::fs::create_dir_all(&ro).unwrap();
            std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
            // root ignores the mode; only check where the mode means something.
            if std::fs::write(ro.join("probe"), b"").is_err() {
                assert!(matches!(
                    err(&[], &[&ro.join("x.obj")]),
                    Some(OutputPathError::NotWritable { .. })
                ));
            }
            std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
        }
        // The checks leave no trial files behind.
        assert!(std::fs::read_dir(&dir).unwrap().all(|e| {
            !e.unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with(TEMP_PREFIX)
        }));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A file name of `len` bytes.
    fn name_of_len(len: usize) -> String {
        format!("{}.obj", "n".repeat(len - 4))
    }

    #[test]
    fn a_name_too_long_for_the_filesystem_is_refused_before_any_work() {
        // temp_dir() is on a filesystem with NAME_MAX 255 (ext4, tmpfs, xfs, btrfs).
        let dir = scratch("long");
        for len in [200, 250, 255] {
            let out = dir.join(name_of_len(len));
            assert!(check_outputs(&[], &[&out]).is_ok(), "{len} bytes");
            // The temporary's name is short, so what the check accepts can be written.
            write_atomic(&out, b"x").unwrap();
            assert_eq!(std::fs::read(&out).unwrap(), b"x");
        }
        for len in [256, 300] {
            let out = dir.join(name_of_len(len));
            let err = check_outputs(&[], &[&out]).unwrap_err();
            assert!(
                matches!(&err, OutputPathError::NameTooLong { path, len: l, .. }
                    if *path == out && *l == len),
                "{err}"
            );
            assert!(err.to_string().contains("file name too long"), "{err}");
            // The check agrees with the write itself.
            assert!(write_atomic(&out, b"x").is_err());
        }
        // Only the three files written: no trial or temporary file left.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 3);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_path_ending_with_a_slash_is_refused() {
        let dir = scratch("slash");
        for out in ["x.obj/", "x.obj/."] {
            let out = PathBuf::from(format!("{}/{out}", dir.display()));
            assert!(
                matches!(
                    check_outputs(&[], &[&out]),
                    Err(OutputPathError::FolderName(_))
                ),
                "{}",
                out.display()
            );
            assert!(write_atomic(&out, b"x").is_err());
        }
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn writing_through_a_link_writes_its_target_and_keeps_the_link() {
        use std::os::unix::fs::symlink;
        let dir = scratch("link");
        let real = dir.join("real.obj");
        std::fs::write(&real, b"old").unwrap();
        let link = dir.join("link.obj");
        symlink("real.obj", &link).unwrap();
        // A chain, with a target relative to the second link's own folder.
        std::fs::create_dir(dir.join("sub")).unwrap();
        let chain = dir.join("sub/chain.obj");
        symlink("../link.obj", &chain).unwrap();
        for (out, bytes) in [(&link, b"one"), (&chain, b"two")] {
            check_outputs(&[], &[out]).unwrap();
            write_atomic(out, bytes).unwrap();
            assert_eq!(std::fs::read(&real).unwrap(), bytes);
        }
        assert_eq!(std::fs::read_link(&link).unwrap(), Path::new("real.obj"));
        assert_eq!(
            std::fs::read_link(&chain).unwrap(),
            Path::new("../link.obj")
        );
        // The link's target exists, so creating through the link is refused.
        let again = create_atomic(&link, b"three").unwrap_err();
        assert_eq!(again.kind(), std::io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read(&real).unwrap(), b"two");
        // Two outputs that reach the same file through links.
        assert!(matches!(
            check_outputs(&[], &[&real, &chain]),
            Err(OutputPathError::SameOutput { .. })
        ));
        // real.obj, link.obj, sub: no temporary left.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 3);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn a_dangling_link_gets_its_target_created() {
        use std::os::unix::fs::symlink;
        let dir = scratch("dangling");
        std::fs::create_dir(dir.join("sub")).unwrap();
        let link = dir.join("link.obj");
        symlink("sub/new.obj", &link).unwrap();
        check_outputs(&[], &[&link]).unwrap();
        write_atomic(&link, b"new").unwrap();
        assert_eq!(std::fs::read(dir.join("sub/new.obj")).unwrap(), b"new");
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        // create_atomic through a dangling link creates the target too.
        let fresh = dir.join("fresh.obj");
        symlink("sub/fresh.obj", &fresh).unwrap();
        create_atomic(&fresh, b"fresh").unwrap();
        assert_eq!(std::fs::read(dir.join("sub/fresh.obj")).unwrap(), b"fresh");
        // A link into a missing folder is checked as its target.
        let lost = dir.join("lost.obj");
        symlink("missing/x.obj", &lost).unwrap();
        assert!(matches!(
            check_outputs(&[], &[&lost]),
            Err(OutputPathError::MissingFolder { .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn a_link_loop_is_an_error_not_a_hang() {
        use std::os::unix::fs::symlink;
        let dir = scratch("loop");
        let (a, b, own) = (dir.join("a.obj"), dir.join("b.obj"), dir.join("own.obj"));
        symlink("b.obj", &a).unwrap();
        symlink("a.obj", &b).unwrap();
        symlink("own.obj", &own).unwrap();
        for out in [&a, &own] {
            assert!(matches!(
                check_outputs(&[], &[out]),
                Err(OutputPathError::LinkLoop(_))
            ));
            assert!(write_atomic(out, b"x").is_err());
        }
        // Nothing but the three links.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 3);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn only_regular_files_within_the_limit_are_read() {
        let dir = scratch("regular");
        let f = dir.join("f.bin");
        std::fs::write(&f, [7u8; 100]).unwrap();
        assert_eq!(read_regular_file(&f, 100).unwrap().len(), 100);
        assert!(read_regular_file(&f, 99).is_err());
        assert!(read_regular_file(&dir, 1 << 20).is_err());
        #[cfg(unix)]
        {
            assert!(read_regular_file(Path::new("/dev/zero"), 1 << 20).is_err());
            let fifo = dir.join("fifo");
            let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
            // Returns at once (no writer is ever coming) with an error.
            assert!(read_regular_file(&fifo, 1 << 20).is_err());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
