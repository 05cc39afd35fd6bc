//! The `render` binary as a user runs it: a PNG of the requested size from a model file, and
//! clear errors with non-zero exits (never a panic) for bad arguments and bad model files.

use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::OnceLock;

use hwsdf::nn::{Nglod, Normalization, Siren, SirenConfig};

fn render() -> Command {
    Command::new(env!("CARGO_BIN_EXE_render"))
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hwsdf-render-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// An untrained but exact sphere: one 16³ level holding |x| − 0.5, passed through the MLP.
fn sphere_model() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let path = scratch("sphere.safetensors");
        Nglod::from_sdf(16, |p| p.length() - 0.5)
            .unwrap()
            .to_model_file(Normalization::identity(), serde_json::Value::Null)
            .save(&path)
            .unwrap();
        path
    })
}

fn assert_clean_failure(o: &Output, needle: &str) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "expected failure; stderr: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    assert!(
        err.to_lowercase().contains(&needle.to_lowercase()),
        "{needle:?} not in: {err}"
    );
}

#[test]
fn renders_a_png_of_the_requested_size() {
    let out = scratch("sphere.png");
    let o = render()
        .arg(sphere_model())
        .args(["--size", "48x32", "--lod", "1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    // IHDR: width and height, big-endian, right after the chunk header.
    assert_eq!(&bytes[12..16], b"IHDR");
    assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 48);
    assert_eq!(u32::from_be_bytes(bytes[20..24].try_into().unwrap()), 32);
}

#[test]
fn bad_arguments_and_files_fail_clearly() {
    let model = sphere_model();
    let out = scratch("never.png");
    let run = |args: &[&str], model: &PathBuf| {
        render()
            .arg(model)
            .args(args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    assert_clean_failure(&run(&["--size", "0x10"], model), "1..=16384");
    assert_clean_failure(&run(&["--size", "big"], model), "WIDTHxHEIGHT");
    assert_clean_failure(&run(&["--lod", "2"], model), "level of detail 2");
    assert_clean_failure(&run(&["--pitch", "90"], model), "pitch");

    let missing = scratch("missing.safetensors");
    assert_clean_failure(&run(&[], &missing), "cannot load the model");
    let corrupt = scratch("corrupt.safetensors");
    std::fs::write(&corrupt, b"not a model").unwrap();
    assert_clean_failure(&run(&[], &corrupt), "cannot load the model");

    let siren = scratch("siren.safetensors");
    Siren::new(
        SirenConfig {
            width: 8,
            hidden_layers: 1,
            omega0: 30.0,
        },
        0,
    )
    .unwrap()
    .to_model_file(Normalization::identity(), serde_json::Value::Null)
    .save(&siren)
    .unwrap();
    assert_clean_failure(&run(&["--lod", "1"], &siren), "levels of detail");
    // A SIREN renders through the single-model tracer (its bounds would take seconds to
    // measure): a PNG, no error.
    let png = scratch("siren.png");
    let o = render()
        .arg(&siren)
        .args(["--size", "8x6", "--out"])
        .arg(&png)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(&std::fs::read(&png).unwrap()[..4], b"\x89PNG");

    let o = render()
        .arg(model)
        .args(["--out", "/no/such/dir/x.png"])
        .output()
        .unwrap();
    assert_clean_failure(&o, "does not exist");
    let o = render().arg(model).output().unwrap();
    assert_clean_failure(&o, "--out");
    assert!(!out.exists(), "no output on failure");
}
