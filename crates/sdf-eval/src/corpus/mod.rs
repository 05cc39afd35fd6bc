//! Corpus runs: which meshes a corpus holds, which of them one shard takes, where each mesh's
//! result lives in the shared `<out>.d/` folder, and the table merged from those results.
//!
//! Scale-out rides on the engines people already run (Slurm job arrays, Kubernetes Indexed
//! Jobs): the engine hands every task its index, [`Shard`] turns the index into a fixed subset of
//! the meshes, every task writes one file per mesh and model into the same folder (atomically,
//! under a name no other mesh shares), and [`merge`] builds the table from that folder alone.
//! There is no queue, lock or protocol of our own: a shard that is run again skips what is done.
//!
//! ```
//! use sdf_eval::corpus::{CorpusMesh, Shard};
//!
//! let meshes: Vec<CorpusMesh> = ["a.obj", "sub/b.glb", "c.gltf"]
//!     .iter()
//!     .map(|rel| CorpusMesh::new(std::path::Path::new("/data"), rel))
//!     .collect();
//! // Every mesh lands in exactly one of three shards, by a hash of its relative path.
//! let total: usize = (0..3)
//!     .map(|k| Shard::new(k, 3).unwrap().select(&meshes).len())
//!     .sum();
//! assert_eq!(total, meshes.len());
//! ```

mod shard;
mod state;
mod table;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

pub use shard::{Shard, stable_hash};
pub use state::{CorpusSettings, Entry, Record, StateDir};
pub use table::{Merge, f1_cell, merge};

/// File extensions a corpus walk picks up (case-insensitive).
pub const MESH_EXTENSIONS: [&str; 3] = ["obj", "gltf", "glb"];

/// Errors of corpus bookkeeping. Every one is raised before any training starts.
#[derive(Debug, thiserror::Error)]
pub enum CorpusError {
    /// A folder or list could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The corpus holds no mesh.
    #[error("{0} holds no .obj, .gltf or .glb file")]
    Empty(PathBuf),
    /// A shard specification that cannot be used.
    #[error("bad shard {value:?} (from {source_name}): {reason}")]
    BadShard {
        /// The value as given.
        value: String,
        /// Where it came from (`--shard`, `SLURM_ARRAY_TASK_ID`, ...).
        source_name: String,
        /// Why it is refused.
        reason: String,
    },
    /// The results folder holds results of other settings; one table never mixes them.
    #[error(
        "{} holds results of other settings ({}); give another --out, or delete that folder to start over",
        .dir.display(), .differences.join("; ")
    )]
    OtherSettings {
        /// The results folder.
        dir: PathBuf,
        /// `name asked, not recorded` for each setting that differs.
        differences: Vec<String>,
    },
    /// The results folder's settings record does not parse.
    #[error(
        "{}: not a settings record ({reason}); delete it only if every result in its folder was made with this run's settings",
        .path.display()
    )]
    BadSettings {
        /// The record.
        path: PathBuf,
        /// The parse error.
        reason: String,
    },
}

/// One mesh of a corpus: where it is, and its path relative to the corpus root, which names it
/// in the table, in the result files and in the shard hash.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct CorpusMesh {
    /// Relative path with `/` separators (the key of everything else).
    pub rel: String,
    /// The file to load.
    pub path: PathBuf,
}

impl CorpusMesh {
    /// The mesh at `rel` under `root` (`rel` may also be absolute; it is then its own key).
    pub fn new(root: &Path, rel: &str) -> Self {
        let rel = rel.trim().replace('\\', "/");
        let rel = rel.trim_start_matches("./").to_owned();
        CorpusMesh {
            path: root.join(&rel),
            rel,
        }
    }
}

fn is_mesh_name(name: &str) -> bool {
    Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| MESH_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// Every OBJ, glTF and GLB file under `root`, recursively, sorted by relative path.
///
/// Hidden entries (names starting with `.`) are skipped, and so are symbolic links to folders,
/// so that a link cycle cannot make the walk endless; links to files are followed.
pub fn walk(root: &Path) -> Result<Vec<CorpusMesh>, CorpusError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| CorpusError::Io { path, source }
    };
    let mut out = Vec::new();
    let mut stack = vec![(root.to_owned(), String::new())];
    while let Some((dir, prefix)) = stack.pop() {
        for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
            let entry = entry.map_err(io(&dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let rel = format!("{prefix}{name}");
            let kind = entry.file_type().map_err(io(&entry.path()))?;
            if kind.is_dir() {
                stack.push((entry.path(), format!("{rel}/")));
            } else if is_mesh_name(&name)
                && std::fs::metadata(entry.path()).is_ok_and(|m| m.is_file())
            {
                out.push(CorpusMesh {
                    path: entry.path(),
                    rel,
                });
            }
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(CorpusError::Empty(root.to_owned()));
    }
    Ok(out)
}

/// The largest mesh list [`read_list`] reads (about a million paths).
pub const MAX_LIST_BYTES: u64 = 64 << 20;

/// The meshes named in a list file: one path a line, relative to the list's folder (or
/// absolute); blank lines and lines starting with `#` are skipped, repeats are dropped.
pub fn read_list(list: &Path) -> Result<Vec<CorpusMesh>, CorpusError> {
    // A regular file of at most 64 MiB: a FIFO would block, /dev/zero would fill the memory.
    let io = |source| CorpusError::Io {
        path: list.to_owned(),
        source,
    };
    let bytes = sdf_geom::io::read_regular_file(list, MAX_LIST_BYTES).map_err(io)?;
    let text = String::from_utf8(bytes).map_err(|e| {
        io(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("not UTF-8 text: {e}"),
        ))
    })?;
    let root = list.parent().unwrap_or(Path::new("."));
    let set: BTreeSet<CorpusMesh> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| CorpusMesh::new(root, l))
        .collect();
    if set.is_empty() {
        return Err(CorpusError::Empty(list.to_owned()));
    }
    Ok(set.into_iter().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walk_recurses_and_a_list_is_relative_to_itself() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-walk-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for f in [
            "a.obj",
            "sub/b.GLB",
            "sub/deep/c.gltf",
            "sub/notes.txt",
            ".hidden/d.obj",
        ] {
            let p = root.join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, "").unwrap();
        }
        let rels: Vec<String> = walk(&root).unwrap().into_iter().map(|m| m.rel).collect();
        assert_eq!(rels, ["a.obj", "sub/b.GLB", "sub/deep/c.gltf"]);
        std::fs::write(
            root.join("sub/list.txt"),
            "# meshes\nb.GLB\n\n./deep/c.gltf\nb.GLB\n",
        )
        .unwrap();
        let listed = read_list(&root.join("sub/list.txt")).unwrap();
        assert_eq!(listed.len(), 2);
        assert_eq!(listed[0].rel, "b.GLB");
        assert_eq!(listed[0].path, root.join("sub/b.GLB"));
        assert_eq!(listed[1].rel, "deep/c.gltf");
        // Special files are refused unread (a FIFO would block, /dev/zero fill the memory).
        #[cfg(unix)]
        {
            let fifo = root.join("list.fifo");
            let made = std::process::Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .unwrap()
                .success();
            assert!(made);
            for special in [fifo.as_path(), Path::new("/dev/zero")] {
                match read_list(special) {
                    Err(e @ CorpusError::Io { .. }) => {
                        assert!(e.to_string().contains("not a regular file"), "{e}")
                    }
                    other => panic!("{special:?}: {other:?}"),
                }
            }
        }
        assert!(matches!(
            walk(&root.join("sub/deep/nothing")),
            Err(CorpusError::Io { .. })
        ));
        std::fs::create_dir_all(root.join("empty")).unwrap();
        assert!(matches!(
            walk(&root.join("empty")),
            Err(CorpusError::Empty(_))
        ));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
