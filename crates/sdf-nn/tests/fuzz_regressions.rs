//! Replays the committed fuzz corpus `fuzz/regressions/safetensors` through
//! `ModelFile::from_bytes` (what the `safetensors` fuzz target calls), on stable: every input ends
//! in a typed result, never a panic, and files named `ok-*` load.

use std::path::{Path, PathBuf};

use sdf_nn::model_file::ModelFile;

#[test]
fn safetensors_corpus() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/safetensors");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no corpus in {}", dir.display());
    for p in files {
        let bytes = std::fs::read(&p).unwrap();
        let r = ModelFile::from_bytes(&bytes, &p);
        let ok = p
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with("ok-"));
        if ok {
            assert!(r.is_ok(), "{}: {:?}", p.display(), r.err());
        }
    }
}
