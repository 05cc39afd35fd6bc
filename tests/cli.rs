//! The binaries as a user runs them: `train` end to end with its report, `eval` and `extract`
//! on the result, `corpus` resuming, and clear errors with non-zero exits on bad input.

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;

use common::{bin, data, stderr};

fn scratch(name: &str) -> PathBuf {
    common::scratch_in("cli", name)
}

/// Fails with a clear message, no panic, non-zero exit.
fn assert_clean_failure(o: &Output, needle: &str) {
    let err = stderr(o);
    assert!(
        !o.status.success(),
        "expected failure, got success; stderr: {err}"
    );
    assert!(!err.contains("panicked"), "panicked: {err}");
    assert!(
        err.to_lowercase().contains(&needle.to_lowercase()),
        "{needle:?} not in: {err}"
    );
}

/// One small NGLOD trained by the `train` binary, shared by the tests that need a model.
fn trained() -> &'static (PathBuf, serde_json::Value) {
    static TRAINED: OnceLock<(PathBuf, serde_json::Value)> = OnceLock::new();
    TRAINED.get_or_init(|| {
        let out = scratch("suzanne.nglod.safetensors");
        let (json, _) = common::train_with_report(
            "suzanne.obj",
            &[
                "--model",
                "nglod",
                "--preset",
                "small",
                "--epochs",
                "2",
                "--eval-points",
                "3000",
            ],
            &out,
        );
        (out, json)
    })
}

#[test]
fn train_writes_a_model_and_a_complete_report() {
    let (model, report) = trained();
    assert!(model.exists());
    for key in [
        "mesh",
        "model",
        "preset",
        "params",
        "file_bytes",
        "f1_bbox",
        "f1_near_surface",
        "f1_mean",
        "per_point_ns",
        "batch3000_us",
        "train_seconds",
        "final_lr",
        "adapter",
    ] {
        assert!(report.get(key).is_some(), "report lacks {key}: {report}");
    }
    assert_eq!(report["model"], "nglod");
    assert_eq!(report["preset"], "small");
    // `--ground-truth auto`: the GPU's kernels unless the adapter is a CPU (lavapipe).
    let cpu_adapter = report["adapter"].as_str().unwrap().contains("(Cpu,");
    assert_eq!(
        report["ground_truth"],
        if cpu_adapter { "cpu" } else { "gpu" },
        "{report}"
    );
    assert_eq!(
        report["file_bytes"].as_u64().unwrap(),
        std::fs::metadata(model).unwrap().len()
    );
    // NGLOD's rate decays from 1e-3 along a cosine.
    let lr = report["final_lr"].as_f64().unwrap();
    assert!(lr > 0.0 && lr < 1e-3, "{report}");
    // Two epochs of the small NGLOD already get most of the box right.
    let f1 = report["f1_bbox"].as_f64().unwrap();
    assert!(f1 > 0.8 && f1 <= 1.0, "{report}");
    let mean = report["f1_mean"].as_f64().unwrap();
    let expect = 0.5 * (f1 + report["f1_near_surface"].as_f64().unwrap());
    assert!((mean - expect).abs() < 1e-9);
}

#[test]
fn eval_and_extract_use_the_trained_model() {
    let (model, report) = trained();
    let o = bin("eval")
        .arg(model)
        .arg(data("suzanne.obj"))
        .args(["--points", "3000", "--surface-resolution", "48", "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // Same model, same evaluation sets: the same F1, and the same sign errors, which are
    // exactly the signs the accuracy counts wrong.
    assert_eq!(json["f1_bbox"], report["f1_bbox"]);
    assert_eq!(json["sign_errors_bbox"], report["sign_errors_bbox"]);
    // And the same ambiguous fractions (suzanne is open: some of its near-surface points).
    assert_eq!(json["ambiguous_bbox"], report["ambiguous_bbox"]);
    assert_eq!(
        json["ambiguous_near_surface"],
        report["ambiguous_near_surface"]
    );
    assert!(
        json["ambiguous_near_surface"].as_f64().unwrap() > 0.0,
        "{json}"
    );
    assert_eq!(json["ground_truth"], report["ground_truth"]);
    for set in ["bbox", "near_surface"] {
        let errors: hwsdf::eval::SignErrors =
            serde_json::from_value(json[format!("sign_errors_{set}")].clone()).unwrap();
        let accuracy = json[format!("sign_accuracy_{set}")].as_f64().unwrap();
        let wrong = ((1.0 - accuracy) * 3000.0).round() as u64;
        assert_eq!(errors.total(), wrong, "{set}: {json}");
    }
    let chamfer = json["chamfer_l1"].as_f64().unwrap();
    assert!(chamfer > 0.0 && chamfer < 0.1, "{json}");

    let obj = scratch("suzanne.extracted.obj");
    let o = bin("extract")
        .arg(model)
        .args(["--resolution", "48", "--out"])
        .arg(&obj)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let (mesh, _) = hwsdf::geom::load_mesh(&obj).unwrap();
    assert!(mesh.triangles.len() > 100);
    // Written in the original mesh's coordinates: its bounds match the source mesh's.
    let (source, _) = hwsdf::geom::load_mesh(data("suzanne.obj")).unwrap();
    let (a, b) = (mesh.bounds(), source.bounds());
    let diag = b.diagonal();
    assert!((a.min - b.min).length() < 0.1 * diag && (a.max - b.max).length() < 0.1 * diag);
}

#[test]
fn corpus_records_failures_and_skips_finished_meshes() {
    let dir = scratch("corpus-in");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data("suzanne.obj"), dir.join("suzanne.obj")).unwrap();
    std::fs::write(dir.join("broken.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
    let out = scratch("corpus.md");
    let run = || {
        bin("corpus")
            .arg(&dir)
            .args([
                "--model",
                "nglod",
                "--epochs",
                "1",
                "--eval-points",
                "2000",
                "--out",
            ])
            .arg(&out)
            .output()
            .unwrap()
    };
    let first = run();
    assert!(first.status.success(), "{}", stderr(&first));
    let table = std::fs::read_to_string(&out).unwrap();
    let row = table
        .lines()
        .find(|l| l.starts_with("| suzanne.obj |"))
        .unwrap_or_else(|| panic!("no suzanne row: {table}"));
    assert!(!row.contains("failed"), "{row}");
    assert!(table.contains("| broken.obj | failed:"), "{table}");
    assert!(table.contains("design document"), "{table}");
    let second = run();
    assert!(second.status.success());
    assert!(stderr(&second).contains("suzanne.obj nglod: done earlier, skipped"));
}

/// A corpus of several models gives each its preset as `train` would: on a CPU adapter SIREN's
/// `small` beside NGLOD's `default` (not one `small` for the whole table), `default` for both
/// on a GPU; the table's sections record them.
#[test]
fn corpus_gives_each_model_its_own_preset() {
    let dir = scratch("corpus-presets");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data("suzanne.obj"), dir.join("suzanne.obj")).unwrap();
    let out = scratch("corpus-presets.md");
    let o = bin("corpus")
        .arg(&dir)
        .args(["--model", "both", "--steps", "1", "--epochs", "1"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    // Both ran and were recorded (a record that did not read back would be "not yet run").
    assert!(
        stderr(&o).contains("2 of 2 done, 0 failed"),
        "{}",
        stderr(&o)
    );
    let siren = if common::cpu_adapter() {
        "small"
    } else {
        "default"
    };
    let line = format!("1 meshes × 2 models (SIREN {siren}, NGLOD default)");
    assert!(stderr(&o).contains(&line), "{line} not in {}", stderr(&o));
    let table = std::fs::read_to_string(&out).unwrap();
    let header = match siren {
        "small" => "Presets SIREN `small`, NGLOD `default`, adapter",
        _ => "Preset `default`, adapter",
    };
    assert!(table.starts_with(header), "{header} does not open {table}");
    let settings = |heading: &str| {
        let section = &table[table.find(heading).unwrap_or_else(|| panic!("{table}"))..];
        section
            .lines()
            .find(|l| l.starts_with("Settings:"))
            .unwrap()
            .to_owned()
    };
    assert!(
        settings("### SIREN").contains(&format!("preset {siren};")),
        "{table}"
    );
    assert!(settings("### NGLOD").contains("preset default;"), "{table}");
}

/// A corpus in which every run fails still writes its table, and exits non-zero.
#[test]
fn corpus_where_every_run_fails_exits_non_zero() {
    let dir = scratch("corpus-broken");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("broken.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
    std::fs::write(dir.join("empty.obj"), "").unwrap();
    let out = scratch("corpus-broken.md");
    let o = bin("corpus")
        .arg(&dir)
        .args(["--model", "nglod", "--epochs", "1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("every run failed"), "{}", stderr(&o));
    let table = std::fs::read_to_string(&out).unwrap();
    assert!(table.contains("| broken.obj | failed:"), "{table}");
    assert!(table.contains("| empty.obj | failed:"), "{table}");
}

#[test]
fn bad_input_gives_clear_errors() {
    let missing = bin("train").arg("/nonexistent/mesh.obj").output().unwrap();
    assert_clean_failure(&missing, "/nonexistent/mesh.obj");

    let unknown = scratch("mesh.xyz");
    std::fs::write(&unknown, "hello").unwrap();
    assert_clean_failure(&bin("train").arg(&unknown).output().unwrap(), "xyz");

    let bad_model = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "resnet"])
        .output()
        .unwrap();
    assert_clean_failure(&bad_model, "resnet");

    let wrong_length = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "nglod", "--steps", "10"])
        .output()
        .unwrap();
    assert_clean_failure(&wrong_length, "--epochs");
    // Without --model: the adapter's default model (the hash grid on a CPU), or NGLOD where a
    // flag describes its architecture; the refusal names the one chosen.
    let default = if common::cpu_adapter() {
        "the hash grid"
    } else {
        "NGLOD"
    };
    for (flags, model) in [
        (&["--steps", "10"][..], default),
        (&["--hidden", "64", "--steps", "10"][..], "NGLOD"),
        (&["--sparse-levels", "0", "--steps", "10"][..], "NGLOD"),
    ] {
        let o = bin("train")
            .arg(data("suzanne.obj"))
            .args(flags)
            .output()
            .unwrap();
        assert_clean_failure(&o, &format!("--steps applies to SIREN; {model} trains for"));
    }

    let corrupt = scratch("corrupt.safetensors");
    std::fs::write(&corrupt, b"\x10\0\0\0\0\0\0\0{not json}").unwrap();
    let o = bin("eval")
        .arg(&corrupt)
        .arg(data("suzanne.obj"))
        .output()
        .unwrap();
    assert_clean_failure(&o, "corrupt.safetensors");

    let (model, _) = trained();
    let o = bin("extract")
        .arg(model)
        .args(["--resolution", "100000", "--out"])
        .arg(scratch("never.obj"))
        .output()
        .unwrap();
    assert_clean_failure(&o, "resolution");
    assert!(!scratch("never.obj").exists());

    let o = bin("eval")
        .arg(model)
        .arg(data("suzanne.obj"))
        .args(["--lod", "9"])
        .output()
        .unwrap();
    assert_clean_failure(&o, "level");

    let o = bin("eval")
        .arg(model)
        .arg(data("suzanne.obj"))
        .args(["--siren-kernels", "coop"])
        .output()
        .unwrap();
    assert_clean_failure(&o, "SIREN");
}

#[test]
fn unknown_adapter_name_is_a_clear_error_not_a_panic() {
    let o = bin("gpu-info")
        .env("WGPU_ADAPTER_NAME", "no-such-adapter-hwsdf")
        .output()
        .unwrap();
    assert_clean_failure(&o, "no-such-adapter-hwsdf");
    assert!(stderr(&o).contains("WGPU_ADAPTER_NAME"));
}

/// A small, untrained NGLOD model file: enough for the binaries that read a model to reach
/// their GPU.
fn untrained_model() -> PathBuf {
    let path = scratch("untrained.nglod.safetensors");
    let model = hwsdf::nn::Nglod::new(hwsdf::nn::NglodConfig::small()).unwrap();
    model
        .to_model_file(hwsdf::geom::Normalization::identity(), Default::default())
        .save(&path)
        .unwrap();
    path
}

/// On a machine without a display (no `XDG_RUNTIME_DIR`), the binaries print only their own
/// output: not libwayland's `XDG_RUNTIME_DIR is invalid` lines, which Mesa's device-selection
/// layer (installed with lavapipe, so on CI) used to cause two to four times per run.
#[test]
fn headless_runs_print_no_window_system_errors() {
    let model = untrained_model();
    let png = scratch("headless.png");
    let mut render = bin("render");
    render.arg(&model).args(["--size", "16", "--out"]).arg(&png);
    for mut cmd in [bin("gpu-info"), render] {
        let o = cmd
            .env_remove("XDG_RUNTIME_DIR")
            .env_remove("NODEVICE_SELECT")
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(!stderr(&o).contains("XDG_RUNTIME_DIR"), "{}", stderr(&o));
    }
}

/// Every binary that runs on a GPU takes `--adapter`, and opens its GPU through it: an adapter
/// that is not there is the "no adapter matches" error naming the flag, before any work.
#[test]
fn every_gpu_binary_takes_adapter() {
    let model = untrained_model();
    let mesh = data("suzanne.obj");
    let cases: [(&str, Vec<&std::ffi::OsStr>); 5] = [
        (
            "train",
            vec![mesh.as_os_str(), "--epochs".as_ref(), "1".as_ref()],
        ),
        ("eval", vec![model.as_os_str(), mesh.as_os_str()]),
        ("extract", vec![model.as_os_str(), "--out".as_ref()]),
        ("render", vec![model.as_os_str(), "--out".as_ref()]),
        ("gpu-info", vec![]),
    ];
    for (name, args) in cases {
        let mut cmd = bin(name);
        cmd.args(args);
        match name {
            "train" => cmd.arg("--out").arg(scratch("adapter.nglod.safetensors")),
            "extract" => cmd.arg(scratch("adapter.obj")),
            "render" => cmd.arg(scratch("adapter.png")),
            _ => &mut cmd,
        };
        let o = cmd.args(["--adapter", "no-such-gpu"]).output().unwrap();
        assert_clean_failure(&o, "no adapter matches \"no-such-gpu\" (from --adapter");
        assert!(
            !stderr(&o).contains("training"),
            "{name} started work: {}",
            stderr(&o)
        );
    }
    // The first adapter by its index: what `gpu-info --adapter 0` shows, `render` runs on.
    let info = bin("gpu-info").args(["--adapter", "0"]).output().unwrap();
    assert!(info.status.success(), "{}", stderr(&info));
    let listed = stderr(&info)
        .lines()
        .find_map(|l| l.trim().strip_prefix("0: ").map(str::to_owned))
        .unwrap();
    let shown = String::from_utf8_lossy(&info.stdout)
        .lines()
        .next()
        .unwrap()
        .to_owned();
    assert!(listed.starts_with(&shown), "{listed} vs {shown}");
    let png = scratch("adapter-0.png");
    let o = bin("render")
        .arg(&model)
        .args(["--size", "16", "--adapter", "0", "--out"])
        .arg(&png)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains(&shown), "{}", stderr(&o));
}

/// Every binary's help opens with what that binary does (a bare `about` gave all eight the
/// package's description, so `sdf --help` spoke of training).
#[test]
fn every_binary_describes_itself() {
    for (name, opening) in [
        ("train", "Fit a neural signed distance function"),
        ("eval", "Score a trained neural SDF"),
        ("corpus", "Train and evaluate every"),
        ("sdf", "Exact signed distance from a triangle mesh"),
        ("query", "Distances, normals, ray hits"),
        ("render", "Render a neural SDF model"),
        ("extract", "Extract the zero level set"),
        ("gpu-info", "Show the adapter"),
    ] {
        let o = bin(name).arg("--help").output().unwrap();
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let help = String::from_utf8_lossy(&o.stdout);
        assert!(help.starts_with(opening), "{name} --help: {help}");
    }
}

/// The environment's GPU settings are checked as the GPU opens: a value no setting takes is an
/// error naming the ones it does.
#[test]
fn an_unknown_step_layout_names_the_allowed_ones() {
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--epochs", "1", "--out"])
        .arg(scratch("layout.nglod.safetensors"))
        .env("HWSDF_STEP_LAYOUT", "sideways")
        .output()
        .unwrap();
    assert_clean_failure(&o, "HWSDF_STEP_LAYOUT");
    assert!(stderr(&o).contains("gpu, cpu"), "{}", stderr(&o));
}

#[test]
fn ctrl_c_writes_a_checkpoint_that_resume_continues() {
    let out = scratch("interrupted.nglod.safetensors");
    let report = scratch("interrupted.nglod.json");
    let child = bin("train")
        .arg(data("suzanne.obj"))
        // The default preset: a sparse level's band goes through the checkpoint too.
        .args(["--model", "nglod", "--preset", "default", "--epochs", "200"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (log, status) = common::interrupt_after_first_epoch(child);
    // As a shell reports SIGINT: `train … && eval …` must not go on.
    assert_eq!(status.code(), Some(130), "{log}");
    let checkpoint = out.with_extension("checkpoint.safetensors");
    assert!(log.contains("checkpoint written to"), "{log}");
    // The command it prints continues the same run: every flag, its --out, the checkpoint.
    let hint = format!(
        "--eval-points 2000 --out {} --report {} --resume {}",
        out.display(),
        report.display(),
        checkpoint.display()
    );
    assert!(log.contains(&hint), "{hint} not in\n{log}");
    assert!(checkpoint.exists(), "{log}");
    assert!(
        !out.exists(),
        "an interrupted run writes a checkpoint, not a model"
    );
    // It remembers the length its run planned, which a resume without --epochs goes on to.
    let saved = hwsdf::eval::run::Checkpoint::load(&checkpoint).unwrap();
    assert_eq!(saved.planned(), Some(200));
    // And the seconds it trained, which the resumed run's report adds to its own.
    let seconds_before = saved.training()["train_seconds"].as_f64().unwrap();
    assert!(seconds_before > 0.0);
    // `--resume` continues to the requested total; without `--model`, with the checkpoint's
    // model (an NGLOD one, where a CPU adapter's default is the hash grid). A report already
    // there (an earlier model's) is removed once the new model is saved, and the checkpoint
    // the run finished is removed after its report (a copy serves the refusals below).
    let spare = out.with_extension("spare-checkpoint.safetensors");
    std::fs::copy(&checkpoint, &spare).unwrap();
    std::fs::write(&report, "{\"an\": \"earlier model's report\"}").unwrap();
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--preset", "default", "--epochs", "3"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .arg("--resume")
        .arg(&checkpoint)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["trained"], 3, "{json}");
    assert!(
        json["train_seconds"].as_f64().unwrap() > seconds_before,
        "{json}"
    );
    let log = stderr(&o);
    assert!(log.contains("the report of an earlier model"), "{log}");
    assert!(log.contains("the checkpoint this run finished"), "{log}");
    assert!(!checkpoint.exists(), "{log}");
    let checkpoint = spare;
    // Resuming with another architecture is refused.
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "siren", "--preset", "small", "--resume"])
        .arg(&checkpoint)
        .output()
        .unwrap();
    assert_clean_failure(&o, "checkpoint");
    // So is another NGLOD architecture than the checkpoint's.
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args([
            "--model",
            "nglod",
            "--preset",
            "default",
            "--resolutions",
            "4,8",
        ])
        .arg("--resume")
        .arg(&checkpoint)
        .output()
        .unwrap();
    // Named with its file: `train` may be one of many runs of a corpus script.
    assert_clean_failure(
        &o,
        &format!(
            "{}: the checkpoint's architecture differs: resolutions 4,8, not 6,12,24,48",
            checkpoint.display()
        ),
    );
    // So are another distance and another batch: the fit would go on as another one (an
    // unsigned fit resumed as a signed one), or skip the wrong points of its epoch.
    for (flags, says) in [
        (
            ["--distance", "unsigned"],
            "fits signed distances, not unsigned: resume with --distance signed",
        ),
        (
            ["--batch", "1024"],
            "batches of 2048, not 1024: resume with --batch 2048",
        ),
    ] {
        let o = bin("train")
            .arg(data("suzanne.obj"))
            .args(["--eval-points", "2000"])
            .args(flags)
            .arg("--resume")
            .arg(&checkpoint)
            .arg("--out")
            .arg(scratch("refused.nglod.safetensors"))
            .output()
            .unwrap();
        assert_clean_failure(&o, says);
    }
    // A plain model file is not a checkpoint.
    let (model, _) = trained();
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "nglod", "--preset", "small", "--resume"])
        .arg(model)
        .output()
        .unwrap();
    assert_clean_failure(&o, "not a checkpoint");
}

/// A SIREN resume goes on at the rate the checkpoint's plateau schedule had reached, scaled by
/// how `--lr` differs from the rate that run started at (a changed `--lr` was ignored).
#[test]
fn a_siren_resume_goes_on_at_the_checkpoints_rate_scaled_by_lr() {
    use hwsdf::eval::run::{Trained, load_normalized};
    use hwsdf::nn::{AdamState, Siren, SirenConfig};
    let (_, normalization) = load_normalized(&data("suzanne.obj")).unwrap();
    let siren = Siren::new(SirenConfig::small(), 0).unwrap();
    let n = siren.params().len();
    // Started at 1e-4 (the default), divided by ten once by the plateau rule.
    let training = serde_json::json!({
        "model": "siren", "preset": "small", "config": {"lr": 1e-4}, "planned": 1,
    });
    let checkpoint = Trained {
        file: siren.to_model_file(normalization, training),
        train_seconds: 1.0,
        done: 0,
        final_loss: f32::NAN,
        interrupted: true,
        details: serde_json::Value::Null,
        optimizer: AdamState {
            m: vec![0.0; n],
            v: vec![0.0; n],
            step: 0,
        },
        lr: 1e-5,
    }
    .checkpoint();
    let path = scratch("rate.siren.checkpoint.safetensors");
    let final_lr = |lr: &[&str]| {
        // A finished run removes the checkpoint it continued.
        checkpoint.save(&path).unwrap();
        let out = scratch("rate.siren.safetensors");
        let o = bin("train")
            .arg(data("suzanne.obj"))
            .args(["--model", "siren", "--preset", "small", "--steps", "1"])
            .args(lr)
            .args(["--eval-points", "2000", "--resume"])
            .arg(&path)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "train failed: {}", stderr(&o));
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap()).unwrap();
        report["final_lr"].as_f64().unwrap() as f32
    };
    let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b;
    let same = final_lr(&[]);
    assert!(close(same, 1e-5), "{same}");
    let moved = final_lr(&["--lr", "5e-4"]);
    assert!(close(moved, 5e-5), "{moved}");
}

#[test]
fn siren_loss_and_learning_rate_flags_reach_the_model_file() {
    let out = scratch("spot.siren.safetensors");
    let o = bin("train")
        .arg(data("spot.obj"))
        .args(["--model", "siren", "--preset", "small", "--steps", "2"])
        .args(["--lr", "5e-4", "--eikonal-weight", "50", "--alpha", "80"])
        .args(["--sign-weight", "20"])
        .args(["--eval-points", "3000", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "train failed: {}", stderr(&o));
    let file = hwsdf::nn::ModelFile::load(&out).unwrap();
    let t = &file.metadata.training;
    let weights = &t["config"]["weights"];
    assert_eq!(weights["eikonal"], 50.0, "{t}");
    assert_eq!(weights["alpha"], 80.0, "{t}");
    assert_eq!(weights["sign"], 20.0, "{t}");
    assert_eq!(weights["surface"], 3000.0, "{t}");
    assert_eq!(t["config"]["lr"].as_f64().unwrap() as f32, 5e-4, "{t}");
    // The run's own record sits beside the trainer's, with the length it planned (which a
    // resume of its checkpoint without --steps goes on to).
    assert_eq!(t["done"], 2, "{t}");
    assert_eq!(t["planned"], 2, "{t}");
    assert_eq!(t["model"], "siren", "{t}");
    // The report gives the same settings (it gave null for SIREN), and how many repetitions
    // its latency medians took.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap()).unwrap();
    assert_eq!(
        report["training"]["config"]["weights"], *weights,
        "{report}"
    );
    assert!(report["latency_reps"].as_u64().unwrap() >= 3, "{report}");

    // eval on other kernels: the same signs up to f32 rounding, the kernels named in the
    // report.
    let eval = |kernels: &str| {
        let o = bin("eval")
            .arg(&out)
            .arg(data("spot.obj"))
            .args(["--points", "3000", "--surface-resolution", "0", "--json"])
            .args(["--siren-kernels", kernels])
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "eval --siren-kernels {kernels}: {}",
            stderr(&o)
        );
        serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap()
    };
    let (auto, tiled) = (eval("auto"), eval("tiled"));
    assert_eq!(tiled["siren_kernels"], "tiled");
    let f1 = |j: &serde_json::Value| j["f1_bbox"].as_f64().unwrap();
    assert!((f1(&auto) - f1(&tiled)).abs() < 2e-3, "{auto} vs {tiled}");

    let train = |extra: &[&str]| {
        bin("train")
            .arg(data("suzanne.obj"))
            .args(["--preset", "small", "--out"])
            .arg(scratch("never.safetensors"))
            .args(extra)
            .output()
            .unwrap()
    };
    let o = train(&["--model", "siren", "--steps", "1", "--eikonal-weight=-1"]);
    assert_clean_failure(
        &o,
        "the eikonal loss weight must be finite and non-negative, not -1",
    );
    let o = train(&["--model", "siren", "--steps", "1", "--lr", "0"]);
    assert_clean_failure(&o, "learning rate");
    let o = train(&["--model", "nglod", "--epochs", "1", "--lr", "0"]);
    assert_clean_failure(&o, "learning rate");
    let o = train(&["--model", "nglod", "--epochs", "1", "--normal-weight", "1"]);
    assert_clean_failure(&o, "SIREN");
    assert!(!scratch("never.safetensors").exists());
}

#[test]
fn nglod_architecture_flags_build_the_model_asked_for() {
    let out = scratch("suzanne.custom.safetensors");
    let report = scratch("suzanne.custom.json");
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--model", "nglod", "--epochs", "1", "--eval-points", "2000"])
        .args(["--resolutions", "3,6", "--features", "2", "--hidden", "8"])
        .args(["--band-cells", "1"])
        .arg("--out")
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "train failed: {}", stderr(&o));
    // The log names what differs from the preset.
    assert!(
        stderr(&o)
            .contains("resolutions 3,6, not 6,12,24,48; features 2, not 8; hidden 8, not 128; band cells 1, not 0"),
        "{}",
        stderr(&o)
    );
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let a = &json["architecture"];
    assert_eq!(a["resolutions"], serde_json::json!([3, 6]), "{json}");
    // The preset's sparse finest level stays unless --sparse-levels says otherwise.
    assert_eq!(a["sparse_levels"], 1, "{json}");
    assert_eq!(
        (a["feature_dim"].clone(), a["hidden"].clone()),
        (2.into(), 8.into())
    );
    let model =
        hwsdf::nn::Nglod::from_model_file(&hwsdf::nn::ModelFile::load(&out).unwrap()).unwrap();
    let c = model.config();
    assert_eq!(
        (c.resolutions.as_slice(), c.sparse_levels),
        (&[3, 6][..], 1)
    );
    // 4³ dense vertices and the band's, 2 features each, and an MLP of 8·2 + 2·8 + 1.
    let band = model.bands()[0].len();
    assert!(band > 0 && band < 7 * 7 * 7, "band of {band} vertices");
    assert_eq!(json["params"], 2 * (64 + band) + 33, "{json}");
    // The band is the cells the surface passes through and a ring of one cell around them:
    // exactly the band that `--band-cells 1` places around the normalised mesh, and larger than
    // the default's.
    assert_eq!((a["band_cells"].clone(), c.band_cells), (1.into(), 1));
    let (mesh, _) = hwsdf::eval::run::load_normalized(&data("suzanne.obj")).unwrap();
    let sdf = hwsdf::geom::SignedDistance::new(&mesh).unwrap();
    let around = |b| hwsdf::nn::nglod::Band::around(6, b, |p| sdf.unsigned_distance(p)).unwrap();
    assert_eq!(model.bands()[0].vertices(), around(1).vertices());
    assert!(around(0).len() < band, "{} vs {band}", around(0).len());

    let fails = |extra: &[&str], needle: &str| {
        let never = scratch("never-arch.safetensors");
        let o = bin("train")
            .arg(data("suzanne.obj"))
            .arg("--out")
            .arg(&never)
            .args(extra)
            .output()
            .unwrap();
        assert_clean_failure(&o, needle);
        assert!(!never.exists(), "{extra:?} wrote a model");
    };
    fails(
        &["--model", "siren", "--steps", "1", "--hidden", "64"],
        "SIREN",
    );
    fails(
        &["--epochs", "1", "--resolutions", "8,300"],
        "at most 255 cells",
    );
    fails(
        &[
            "--epochs",
            "1",
            "--resolutions",
            "4,8",
            "--sparse-levels",
            "3",
        ],
        "sparse levels",
    );
    fails(&["--epochs", "1", "--resolutions", "4,x"], "--resolutions");
    fails(&["--epochs", "1", "--features", "0"], "feature_dim");
    fails(&["--epochs", "1", "--band-cells", "5"], "a band of 5 cells");
}

/// OBJ text of an open `n`×`n` grid over [-1, 1]² lifted by `z(x, y)`.
fn sheet_obj(n: u32, z: impl Fn(f32, f32) -> f32) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, y) = (
                i as f32 / n as f32 * 2.0 - 1.0,
                j as f32 / n as f32 * 2.0 - 1.0,
            );
            let _ = writeln!(s, "v {x} {y} {}", z(x, y));
        }
    }
    let id = |i: u32, j: u32| j * (n + 1) + i + 1;
    for j in 0..n {
        for i in 0..n {
            let _ = writeln!(s, "f {} {} {}", id(i, j), id(i + 1, j), id(i + 1, j + 1));
            let _ = writeln!(s, "f {} {} {}", id(i, j), id(i + 1, j + 1), id(i, j + 1));
        }
    }
    s
}

/// A mesh's OBJ with every face stored twice, once per orientation (winding number 0).
fn two_sided_obj(obj: &str) -> String {
    let mut s = String::new();
    for line in obj.lines() {
        s.push_str(line);
        s.push('\n');
        if let Some(rest) = line.strip_prefix("f ") {
            let v: Vec<&str> = rest.split_whitespace().collect();
            s.push_str(&format!(
                "f {}\n",
                v.iter().rev().copied().collect::<Vec<_>>().join(" ")
            ));
        }
    }
    s
}

/// Fixtures without an inside: a flat z = 0 sheet, an open wavy sheet, a two-sided soup of a
/// closed mesh (spot).
fn no_inside_fixtures(dir: &Path) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    let files = [
        ("flat.obj", sheet_obj(6, |_, _| 0.0)),
        (
            "wavy.obj",
            sheet_obj(12, |x, y| 0.15 * (2.0 * x).sin() * (1.5 * y).cos()),
        ),
        (
            "two-sided.obj",
            two_sided_obj(&std::fs::read_to_string(data("spot.obj")).unwrap()),
        ),
    ];
    files
        .into_iter()
        .map(|(name, text)| {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            p
        })
        .collect()
}

#[test]
fn meshes_without_an_inside_warn_report_null_f1_and_corpus_leaves_them_out() {
    let dir = scratch("no-inside");
    let fixtures = no_inside_fixtures(&dir);
    std::fs::copy(data("suzanne.obj"), dir.join("suzanne.obj")).unwrap();
    // `train` warns in plain words, suggests the unsigned mode, and reports F1 as null.
    let report = scratch("flat.nglod.json");
    let o = bin("train")
        .arg(&fixtures[0])
        .args(["--model", "nglod", "--preset", "small", "--epochs", "1"])
        .args(["--eval-points", "2000", "--out"])
        .arg(scratch("flat.nglod.safetensors"))
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("warning:") && err.contains("no inside"),
        "{err}"
    );
    assert!(err.contains("--distance unsigned"), "{err}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    for k in ["f1_bbox", "f1_near_surface", "f1_mean"] {
        assert!(json[k].is_null(), "{k}: {json}");
    }
    assert!(
        json["f1_null_reason"]
            .as_str()
            .unwrap()
            .contains("no inside"),
        "{json}"
    );
    // Sign accuracy and distance errors are still there; the sheet has no inside, and the
    // model learns that.
    assert!(json["sign_accuracy_bbox"].as_f64().unwrap() > 0.9, "{json}");
    assert!(json["near_surface_mean_abs_error"].as_f64().is_some());
    assert!(String::from_utf8_lossy(&o.stdout).contains("n/a"));

    // `corpus`: n/a for the three, an average over suzanne alone, saying what it left out.
    let out = scratch("no-inside.md");
    let o = bin("corpus")
        .arg(&dir)
        .args([
            "--model",
            "nglod",
            "--epochs",
            "1",
            "--eval-points",
            "2000",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let table = std::fs::read_to_string(&out).unwrap();
    for name in ["flat.obj", "wavy.obj", "two-sided.obj"] {
        let row = table
            .lines()
            .find(|l| l.starts_with(&format!("| {name} |")))
            .unwrap_or_else(|| panic!("no {name} row: {table}"));
        assert!(
            row.starts_with(&format!("| {name} | n/a | n/a | n/a |")),
            "{row}"
        );
    }
    assert!(
        table.contains("n/a: 3 mesh(es) without an inside"),
        "{table}"
    );
    assert!(table.contains("**average (1 meshes)**"), "{table}");
}

#[test]
fn unsigned_mode_fits_a_flat_sheet_and_reports_distance_and_chamfer() {
    let dir = scratch("unsigned");
    let flat = no_inside_fixtures(&dir).remove(0);
    let report = scratch("flat-unsigned.json");
    let o = bin("train")
        .arg(&flat)
        .args(["--model", "nglod", "--preset", "small", "--epochs", "1"])
        .args(["--distance", "unsigned", "--eval-points", "2000", "--out"])
        .arg(scratch("flat-unsigned.safetensors"))
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    // No warning: the user already chose the unsigned mode.
    assert!(!stderr(&o).contains("warning:"), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["distance"], "unsigned", "{json}");
    assert!(
        json["f1_bbox"].is_null()
            && json["sign_accuracy_bbox"].is_null()
            && json["sign_errors_bbox"].is_null(),
        "{json}"
    );
    assert!(
        json["f1_null_reason"]
            .as_str()
            .unwrap()
            .contains("unsigned"),
        "{json}"
    );
    assert_eq!(json["training"]["distance"], "unsigned", "{json}");
    // One epoch of the small model already fits |d| closely, and the extracted level set lies
    // near the sheet (an exact |d| scores about the level, 2/128).
    let err = json["near_surface_mean_abs_error"].as_f64().unwrap();
    assert!(err < 0.02, "{json}");
    let chamfer = json["chamfer_l1"].as_f64().unwrap();
    assert!(chamfer < 0.05, "{json}");
    // `eval` extracts the same level set for its surface figures (|d| has no zero crossing).
    let o = bin("eval")
        .arg(scratch("flat-unsigned.safetensors"))
        .arg(&flat)
        .args(["--points", "2000", "--surface-resolution", "64", "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let eval: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let chamfer = eval["chamfer_l1"].as_f64().unwrap();
    assert!(chamfer < 0.05, "{eval}");
    // SIREN has no unsigned mode: a clear error.
    let o = bin("train")
        .arg(&flat)
        .args(["--model", "siren", "--preset", "small", "--steps", "1"])
        .args(["--distance", "unsigned"])
        .output()
        .unwrap();
    assert_clean_failure(
        &o,
        "unsigned distance is supported for NGLOD and the hash grid only",
    );
}

/// A model that never changes sign (Φ ≡ 0.5: a SIREN with zero weights and a head bias) has no
/// surface: `eval` still reports everything else, with the surface figures null and the reason
/// given, instead of failing on the empty extracted mesh.
#[test]
fn eval_reports_a_model_without_a_surface() {
    use hwsdf::nn::{Siren, SirenConfig};
    let cfg = SirenConfig::small();
    let mut params = vec![0.0; cfg.param_count()];
    *params.last_mut().unwrap() = 0.5;
    let file = Siren::from_params(cfg, params).unwrap().to_model_file(
        hwsdf::geom::Normalization::identity(),
        serde_json::json!({}),
    );
    let model = scratch("constant.safetensors");
    file.save(&model).unwrap();
    for json in [true, false] {
        let mut cmd = bin("eval");
        cmd.arg(&model).arg(data("suzanne.obj")).args([
            "--points",
            "500",
            "--surface-resolution",
            "16",
        ]);
        if json {
            cmd.arg("--json");
        }
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let out = String::from_utf8_lossy(&o.stdout);
        if json {
            let report: serde_json::Value = serde_json::from_str(&out).unwrap();
            assert!(report["chamfer_l1"].is_null(), "{report}");
            assert!(report["normal_consistency"].is_null(), "{report}");
            let reason = report["surface_null_reason"].as_str().unwrap();
            assert!(reason.contains("does not change sign"), "{reason}");
            assert_eq!(
                report["sign_accuracy_bbox"].as_f64().map(|a| a > 0.0),
                Some(true)
            );
        } else {
            assert!(out.contains("surface          n/a:"), "{out}");
        }
    }
}

/// `--ground-truth gpu` labels the training samples and the evaluation sets on the GPU's
/// kernels, on any adapter (lavapipe included), and the report says so; an unknown value is
/// clap's error naming the allowed ones.
#[test]
fn train_takes_the_ground_truth_path_asked_for() {
    let out = scratch("gt-gpu.nglod.safetensors");
    let report = scratch("gt-gpu.nglod.json");
    let o = bin("train")
        .arg(data("spot.obj"))
        .args(["--model", "nglod", "--preset", "small", "--epochs", "1"])
        .args(["--eval-points", "2000", "--ground-truth", "gpu"])
        .args(["--label-estimate-after", "0", "--out"])
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "train failed: {}", stderr(&o));
    assert!(
        stderr(&o).contains("ground truth on the GPU"),
        "{}",
        stderr(&o)
    );
    // The labelling estimate (forced by the hidden threshold): 40 000 for the no-inside
    // check, one pool block of 300 000, 4 × 2000 for the evaluation.
    assert!(
        stderr(&o).contains("labelling: about 348 k exact distances on the GPU, estimated "),
        "{}",
        stderr(&o)
    );
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["ground_truth"], "gpu", "{json}");
    let f1 = json["f1_bbox"].as_f64().unwrap();
    assert!(f1 > 0.5, "{json}");
    // spot is closed: nothing ambiguous, which the report and the summary line say.
    assert_eq!(json["ambiguous_bbox"], 0.0, "{json}");
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(
        summary.contains("(ambiguous box 0.0%, near 0.0%)"),
        "{summary}"
    );

    let o = bin("train")
        .arg(data("spot.obj"))
        .args(["--ground-truth", "tpu"])
        .output()
        .unwrap();
    assert_clean_failure(&o, "possible values: gpu, cpu, auto");
}

/// spot moved 10⁷ away (a georeferenced file): `train` keeps its shape (no "no inside"
/// warning, a defined F1), and the model file's normalisation maps back to the file's
/// coordinates through an f64 centre.
#[test]
fn train_keeps_the_shape_of_a_mesh_far_from_the_origin() {
    let (spot, _) = hwsdf::geom::load_mesh(data("spot.obj")).unwrap();
    let offset = glam::DVec3::new(1e7, -2e7, 3e7);
    let mut obj = String::new();
    for v in &spot.vertices {
        let p = v.as_dvec3() + offset;
        obj.push_str(&format!("v {} {} {}\n", p.x, p.y, p.z));
    }
    for t in &spot.triangles {
        obj.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
    }
    let mesh = scratch("far_spot.obj");
    std::fs::write(&mesh, obj).unwrap();
    let out = scratch("far_spot.nglod.safetensors");
    let o = bin("train")
        .arg(&mesh)
        .args(["--model", "nglod", "--preset", "small", "--epochs", "1"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = stderr(&o);
    assert!(o.status.success(), "train failed: {err}");
    assert!(!err.contains("no inside"), "{err}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap()).unwrap();
    assert!(report["f1_bbox"].as_f64().is_some(), "{report}");
    let file = hwsdf::nn::ModelFile::load(&out).unwrap();
    let (_, n0) = spot.normalized();
    let center = file.metadata.normalization.center;
    assert!(
        (center - (n0.center + offset)).abs().max_element() < 1e-6,
        "{center}"
    );
}
