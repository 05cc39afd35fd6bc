//! Helpers the CLI test binaries share: the built binaries, the test meshes, a scratch folder per
//! test process, a training run with its report, a process's stderr, and Ctrl-C after a run's
//! first epoch.
#![allow(dead_code)] // each test binary uses its own subset

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output};

/// A command for one of the package's binaries, as `cargo test` built it.
pub fn bin(name: &str) -> Command {
    Command::new(match name {
        "train" => env!("CARGO_BIN_EXE_train"),
        "eval" => env!("CARGO_BIN_EXE_eval"),
        "extract" => env!("CARGO_BIN_EXE_extract"),
        "corpus" => env!("CARGO_BIN_EXE_corpus"),
        "gpu-info" => env!("CARGO_BIN_EXE_gpu-info"),
        "render" => env!("CARGO_BIN_EXE_render"),
        "query" => env!("CARGO_BIN_EXE_query"),
        "sdf" => env!("CARGO_BIN_EXE_sdf"),
        other => panic!("no binary {other}"),
    })
}

/// Whether the adapter the binaries open (`HWSDF_ADAPTER` or the best one) is a CPU, as
/// `gpu-info` describes it: the defaults that depend on the adapter (model, preset, length,
/// ground truth) are checked against it.
pub fn cpu_adapter() -> bool {
    static CPU: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *CPU.get_or_init(|| {
        let o = bin("gpu-info").output().unwrap();
        assert!(o.status.success(), "gpu-info failed: {}", stderr(&o));
        let adapter = String::from_utf8_lossy(&o.stdout)
            .lines()
            .next()
            .unwrap_or("")
            .to_owned();
        adapter.contains("(Cpu,")
    })
}

/// A file of `tests/data`.
pub fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// `name` in this process's scratch folder `hwsdf-<tag>-<pid>` under the temp folder.
pub fn scratch_in(tag: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hwsdf-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Runs `train` on `mesh` (a file of `tests/data`) with `args`, writing the model to `out` and
/// its report beside it (`.json`); fails the test with train's stderr unless it succeeds.
/// Returns the report and the stderr.
pub fn train_with_report(mesh: &str, args: &[&str], out: &Path) -> (serde_json::Value, String) {
    let report = out.with_extension("json");
    let o = bin("train")
        .arg(data(mesh))
        .args(args)
        .arg("--out")
        .arg(out)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "train failed: {}", stderr(&o));
    let json = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    (json, stderr(&o))
}

/// The process's stderr as text.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Waits for `child`'s first `epoch ` progress line (its stderr piped), presses Ctrl-C (SIGINT),
/// and returns all it wrote to stderr and how it exited.
pub fn interrupt_after_first_epoch(mut child: Child) -> (String, ExitStatus) {
    let mut lines = BufReader::new(child.stderr.take().expect("stderr piped")).lines();
    let mut log = String::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        log.push_str(&line);
        log.push('\n');
        if line.starts_with("epoch ") {
            break;
        }
    }
    let pid = child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-INT", &pid])
            .status()
            .unwrap()
            .success(),
        "the run ended before its first epoch: {log}"
    );
    for line in lines {
        log.push_str(&line.unwrap());
        log.push('\n');
    }
    (log, child.wait().unwrap())
}
