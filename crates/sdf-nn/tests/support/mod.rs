//! What the GPU test binaries share. They also run on machines other than the one that built
//! them (scripts/gpu-compare.sh's `checks` stage carries them to a GPU host), so nothing here
//! may lean on the build machine's paths alone. Each binary uses part of it.
#![allow(dead_code)]

/// A file of `tests/data`: from `HWSDF_TEST_DATA` where set (a test binary carried to another
/// machine, see scripts/gpu-compare.sh), else from the source tree.
pub fn test_data(name: &str) -> std::path::PathBuf {
    std::env::var_os("HWSDF_TEST_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/data").into())
        .join(name)
}

/// A model file of `examples/scene`: beside `HWSDF_TEST_DATA` (`tests/data`) where it is set,
/// as in gpu-compare's pack, else in the source tree.
pub fn example_model(name: &str) -> std::path::PathBuf {
    std::env::var_os("HWSDF_TEST_DATA")
        .map(|data| std::path::PathBuf::from(data).join("../../examples/scene"))
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/../../examples/scene").into())
        .join(name)
}
