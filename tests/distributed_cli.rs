//! `corpus` and `train` as a cluster runs them: shard values checked before any work, the merge
//! of a results folder without a GPU, SIGTERM (Slurm's `scancel`, Kubernetes' eviction) leaving a
//! checkpoint that the next run resumes, and adapters chosen by index. The full Slurm run is
//! `scripts/slurm-smoke.sh`.

mod common;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

use common::{bin, data, stderr};

fn scratch(name: &str) -> PathBuf {
    common::scratch_in("dist", name)
}

/// Reads `child`'s stderr until a line contains `needle`, then sends it `signal`; returns the
/// whole log and the exit status.
fn signal_when(mut child: Child, needle: &str, signal: &str) -> (String, std::process::ExitStatus) {
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let mut log = String::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        log.push_str(&line);
        log.push('\n');
        if line.contains(needle) {
            break;
        }
    }
    assert!(log.contains(needle), "never saw {needle:?}: {log}");
    let pid = child.id().to_string();
    assert!(
        Command::new("kill")
            .args([signal, &pid])
            .status()
            .unwrap()
            .success()
    );
    for line in lines {
        log.push_str(&line.unwrap());
        log.push('\n');
    }
    let status = child.wait().unwrap();
    (log, status)
}

#[test]
fn bad_shards_stop_before_any_work() {
    let dir = scratch("shard-corpus");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data("suzanne.obj"), dir.join("suzanne.obj")).unwrap();
    let out = scratch("shard.md");
    for (args, env, needle) in [
        (vec!["--shard", "3/3"], vec![], "not below the count"),
        (vec!["--shard", "0/0"], vec![], "at least 1"),
        (vec!["--shard", "a/b"], vec![], "whole number"),
        (
            vec![],
            vec![("SLURM_ARRAY_TASK_ID", "x")],
            "SLURM_ARRAY_TASK_ID",
        ),
        (vec![], vec![("JOB_COMPLETION_INDEX", "2")], "--shards"),
        (
            vec!["--shards", "2"],
            vec![("JOB_COMPLETION_INDEX", "2")],
            "not below",
        ),
    ] {
        let mut cmd = bin("corpus");
        cmd.arg(&dir).args(&args).arg("--out").arg(&out);
        for (k, v) in &env {
            cmd.env(k, v);
        }
        let o = cmd.output().unwrap();
        let err = stderr(&o);
        assert!(!o.status.success(), "{args:?} {env:?} succeeded: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(
            err.contains(needle),
            "{args:?} {env:?}: {needle:?} not in {err}"
        );
        // Refused before the GPU was opened or anything was written.
        assert!(!err.contains("training"), "{err}");
        assert!(!scratch("shard.md.d").exists());
    }
    let o = bin("corpus")
        .args(["--list"])
        .arg(scratch("no-such-list.txt"))
        .output()
        .unwrap();
    assert!(!o.status.success() && stderr(&o).contains("no-such-list.txt"));
}

#[test]
fn sigterm_checkpoints_the_mesh_in_training_and_the_rerun_resumes_it() {
    let dir = scratch("term-corpus");
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    std::fs::copy(data("suzanne.obj"), dir.join("sub/suzanne.obj")).unwrap();
    let out = scratch("term.md");
    let corpus = |epochs: &str| {
        let mut c = bin("corpus");
        c.arg(&dir)
            .args(["--model", "nglod", "--preset", "small", "--epochs", epochs])
            .args(["--eval-points", "2000", "--out"])
            .arg(&out);
        c
    };
    // Eight epochs: long enough to be stopped in training, short enough to finish on resume.
    let child = corpus("8").stderr(Stdio::piped()).spawn().unwrap();
    let (log, status) = signal_when(child, "sub/suzanne.obj nglod: training", "-TERM");
    assert_eq!(status.code(), Some(130), "{log}");
    assert!(log.contains("checkpoint written to"), "{log}");
    let state = scratch("term.md.d");
    let names: Vec<String> = std::fs::read_dir(&state)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    let checkpoint = names
        .iter()
        .find(|n| n.ends_with(".nglod.checkpoint.safetensors"))
        .unwrap_or_else(|| panic!("no checkpoint in {names:?}: {log}"));
    assert!(
        checkpoint.starts_with("sub_suzanne.obj-"),
        "the name keeps the folder: {checkpoint}"
    );
    assert!(
        !names.iter().any(|n| n.ends_with(".nglod.json")),
        "an interrupted fit leaves no result: {names:?}"
    );
    // A rerun with other settings is refused before any work: it would mix them in one table.
    let o = corpus("3").output().unwrap();
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("holds results of other settings (nglod epochs 3, not 8)"),
        "{err}"
    );
    assert!(state.join(checkpoint).exists(), "{err}");
    // A resumed fit that fails (here its model file cannot be written: a folder is in the way)
    // keeps the checkpoint it started from: a failure must not cost the training already done.
    let blocker = state.join(checkpoint.replace(".checkpoint.safetensors", ".safetensors"));
    std::fs::create_dir(&blocker).unwrap();
    let o = corpus("8").output().unwrap();
    let err = stderr(&o);
    assert!(err.contains("resuming from its checkpoint"), "{err}");
    assert!(err.contains("sub/suzanne.obj nglod: failed"), "{err}");
    assert!(
        state.join(checkpoint).exists(),
        "the checkpoint is kept: {err}"
    );
    std::fs::remove_dir(&blocker).unwrap();
    let kept = std::fs::read(state.join(checkpoint)).unwrap();
    // The rerun resumes that mesh, finishes it and drops the checkpoint.
    let o = corpus("8").output().unwrap();
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("resuming from its checkpoint"), "{err}");
    assert!(!state.join(checkpoint).exists(), "{err}");
    let table = std::fs::read_to_string(&out).unwrap();
    assert!(table.contains("| sub/suzanne.obj |"), "{table}");
    assert!(table.contains("1 of 1 done, 0 failed"), "{table}");
    // The table states what produced it.
    assert!(
        table.contains("Settings: architecture resolutions 4,8,16, sparse levels 0, band cells 0, features 4, hidden 32; batch 2048; distance signed; epochs 8;"),
        "{table}"
    );
    // The merge needs no GPU and writes the same table; without --model it lists the models
    // the folder has settings for (NGLOD alone here, not the default SIREN and NGLOD).
    let merged = bin("corpus")
        .arg(&dir)
        .args(["--merge", "--out"])
        .arg(scratch("term.md"))
        .env("WGPU_ADAPTER_NAME", "no-such-adapter-hwsdf")
        .output()
        .unwrap();
    assert!(merged.status.success(), "{}", stderr(&merged));
    assert_eq!(std::fs::read_to_string(&out).unwrap(), table);
    // A shard that holds no mesh finishes at once, says so, and leaves the table alone.
    let empty_shard = (0..2)
        .find(|k| {
            let rel = "sub/suzanne.obj";
            !hwsdf::eval::corpus::Shard::new(*k, 2)
                .unwrap()
                .contains(rel)
        })
        .unwrap();
    let o = corpus("8")
        .args(["--shard", &format!("{empty_shard}/2")])
        .output()
        .unwrap();
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains(&format!(
            "shard {empty_shard}/2 (--shard): 0 of the corpus's 1 meshes"
        )),
        "{err}"
    );
    assert!(err.contains("--merge"), "{err}");
    // A checkpoint of the mesh before its file changed (re-exported at twice the size) is set
    // aside: the mesh trains from the start, where a refusal failed it on every rerun.
    let result = state.join(checkpoint.replace(".checkpoint.safetensors", ".json"));
    std::fs::remove_file(&result).unwrap();
    std::fs::write(state.join(checkpoint), &kept).unwrap();
    let obj = std::fs::read_to_string(data("suzanne.obj")).unwrap();
    let doubled: String = obj
        .lines()
        .map(|l| match l.strip_prefix("v ") {
            Some(xyz) => {
                let v: Vec<f64> = xyz.split_whitespace().map(|x| x.parse().unwrap()).collect();
                format!("v {} {} {}\n", 2.0 * v[0], 2.0 * v[1], 2.0 * v[2])
            }
            None => format!("{l}\n"),
        })
        .collect();
    std::fs::write(dir.join("sub/suzanne.obj"), doubled).unwrap();
    let o = corpus("8").output().unwrap();
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("trained on another mesh"), "{err}");
    assert!(err.contains("starting over"), "{err}");
    assert!(!state.join(checkpoint).exists(), "{err}");
    assert!(result.exists(), "{err}");
}

#[test]
fn sigterm_stops_train_with_a_checkpoint() {
    let out = scratch("term-train.nglod.safetensors");
    let child = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "nglod", "--preset", "small", "--epochs", "200"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (log, status) = signal_when(child, "epoch ", "-TERM");
    // Stopped, not finished: 130, as for Ctrl-C, so that `train … && eval …` does not go on.
    assert_eq!(status.code(), Some(130), "{log}");
    assert!(log.contains("checkpoint written to"), "{log}");
    assert!(
        out.with_extension("checkpoint.safetensors").exists(),
        "{log}"
    );
    assert!(!out.exists());
}

#[test]
fn gpu_info_lists_indices_and_adapter_takes_one() {
    let o = bin("gpu-info").output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("  0: "), "{err}");
    assert!(err.contains("PCI"), "{err}");
    let chosen = String::from_utf8_lossy(&o.stdout)
        .lines()
        .next()
        .unwrap()
        .to_owned();
    // Index 0 is a real adapter; HWSDF_ADAPTER takes it.
    let by_index = bin("gpu-info").env("HWSDF_ADAPTER", "0").output().unwrap();
    assert!(by_index.status.success(), "{}", stderr(&by_index));
    let first = err
        .lines()
        .find_map(|l| l.trim().strip_prefix("0: "))
        .unwrap()
        .to_owned();
    let picked = String::from_utf8_lossy(&by_index.stdout)
        .lines()
        .next()
        .unwrap()
        .to_owned();
    assert!(
        first.starts_with(&picked),
        "{first} vs {picked} (default {chosen})"
    );
    let o = bin("gpu-info").env("HWSDF_ADAPTER", "97").output().unwrap();
    let err = stderr(&o);
    assert!(!o.status.success() && !err.contains("panicked"), "{err}");
    assert!(
        err.contains("\"97\"") && err.contains("HWSDF_ADAPTER"),
        "{err}"
    );
    // The corpus flag says where the value came from.
    let o = bin("corpus")
        .arg(data(""))
        .args(["--adapter", "97", "--out"])
        .arg(scratch("adapter.md"))
        .output()
        .unwrap();
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("--adapter"), "{err}");
}
