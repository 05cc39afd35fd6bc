//! Replays the committed fuzz corpus (`fuzz/regressions/{obj,gltf,npy}`) through the same reader
//! functions the `cargo fuzz` targets call, on stable: every input ends in a typed result, never a
//! panic (for the mesh loaders, never [`GeomError::ReaderPanic`], their `catch_unwind` guard), and
//! files named `ok-*` load. Add a fuzzer's crash file here (minimised) together with its fix.

use std::path::{Path, PathBuf};

use sdf_geom::{GeomError, npy, parse_mesh};

fn corpus(target: &str) -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz/regressions")
        .join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no corpus in {}", dir.display());
    files
}

fn must_load(p: &Path) -> bool {
    p.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.starts_with("ok-"))
}

fn replay_meshes(target: &str) {
    for p in corpus(target) {
        let bytes = std::fs::read(&p).unwrap();
        let t = std::time::Instant::now();
        let r = parse_mesh(&bytes, target, &p);
        assert!(
            t.elapsed().as_secs() < 20,
            "{}: {:?}",
            p.display(),
            t.elapsed()
        );
        match r {
            Err(e @ GeomError::ReaderPanic { .. }) => panic!("{}: {e}", p.display()),
            Err(e) if must_load(&p) => panic!("{}: {e}", p.display()),
            _ => {}
        }
    }
}

#[test]
fn obj_corpus() {
    replay_meshes("obj");
}

#[test]
fn gltf_corpus() {
    replay_meshes("gltf");
}

#[test]
fn npy_corpus() {
    for p in corpus("npy") {
        let bytes = std::fs::read(&p).unwrap();
        let r = npy::parse_points(&p, &bytes);
        if must_load(&p) {
            assert!(r.is_ok(), "{}: {r:?}", p.display());
        }
    }
}
