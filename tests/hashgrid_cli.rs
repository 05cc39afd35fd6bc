//! The hash grid (issue 39) through the commands a user runs: `train --model hashgrid` writes a
//! `"hashgrid"` model file and its report; `eval`, `render`, `extract` and `query` read it (and
//! refuse a level of detail short of all its levels); a Ctrl-C checkpoint resumes, into a hash
//! grid only; `corpus --model hashgrid` tabulates it and `--model all` counts it; and every
//! option that does not apply to it is a typed error naming the flag, before any work.

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;

use common::{bin, data, stderr};
use hwsdf::nn::nglod::Encoding;
use hwsdf::nn::{ModelFile, NeuralSdf, NglodConfig, NglodTrainConfig};

fn scratch(name: &str) -> PathBuf {
    common::scratch_in("hashgrid", name)
}

/// Fails with a clear message, no panic, non-zero exit.
fn assert_clean_failure(o: &Output, needle: &str) {
    let err = stderr(o);
    assert!(
        !o.status.success(),
        "expected failure, got success; stderr: {err}"
    );
    assert!(!err.contains("panicked"), "panicked: {err}");
    assert!(err.contains("error"), "no error line: {err}");
    assert!(err.contains(needle), "{needle:?} not in: {err}");
}

/// One epoch of the small hash grid on suzanne (about 5 s of training on lavapipe), trained by
/// the `train` binary and shared by the tests that read a model: its file and its report. On a
/// CPU adapter without `--model` and `--preset`, the defaults there.
fn trained() -> &'static (PathBuf, serde_json::Value, String) {
    static TRAINED: OnceLock<(PathBuf, serde_json::Value, String)> = OnceLock::new();
    TRAINED.get_or_init(|| {
        let out = scratch("suzanne.hashgrid.safetensors");
        let mut args = vec!["--epochs", "1", "--eval-points", "2000"];
        if !common::cpu_adapter() {
            args.extend(["--model", "hashgrid", "--preset", "small"]);
        }
        let (json, log) = common::train_with_report("suzanne.obj", &args, &out);
        (out, json, log)
    })
}

#[test]
fn train_writes_a_hash_grid_model_and_its_report() {
    let (model, report, log) = trained();
    assert!(log.contains("training hashgrid (small)"), "{log}");
    if common::cpu_adapter() {
        // The CPU adapter's default model, named with how to choose another.
        assert!(
            log.contains("note: CPU adapter; using the hash grid (--model to choose;")
                && log.contains("the `small` preset (--preset and --epochs to override)"),
            "{log}"
        );
    }
    let file = ModelFile::load(model).unwrap();
    assert_eq!(file.metadata.architecture, "hashgrid");
    let config = &file.metadata.config;
    // `small`: NglodConfig::hashgrid_small.
    let small: NglodConfig = serde_json::from_value(config.clone()).unwrap();
    assert_eq!(small, NglodConfig::hashgrid_small(), "{config}");
    assert!(matches!(small.encoding, Encoding::Hashed { .. }));
    // Trained on the hash grid's own schedule (learning rate 1e-2, Adam's β2 0.99, batch
    // 4096 as it landed), recorded as a hash-grid run.
    let schedule = NglodTrainConfig::hashgrid();
    let t = &file.metadata.training;
    assert_eq!(t["model"], "hashgrid", "{t}");
    assert_eq!(t["preset"], "small", "{t}");
    assert_eq!(t["done"], 1, "{t}");
    assert_eq!(t["lr"].as_f64().unwrap() as f32, schedule.adam.lr, "{t}");
    assert_ne!(schedule.adam.lr, NglodTrainConfig::default().adam.lr);
    assert_eq!(t["batch_size"], schedule.batch_size, "{t}");
    assert_eq!(
        t["beta2"].as_f64().unwrap() as f32,
        schedule.adam.beta2,
        "{t}"
    );
    assert_eq!(t["grow_every"], serde_json::Value::Null, "{t}");
    // The report: the model's name, its size, and the rate decayed along a cosine.
    assert_eq!(report["model"], "hashgrid", "{report}");
    assert_eq!(report["preset"], "small", "{report}");
    assert_eq!(report["architecture"], *config, "{report}");
    assert_eq!(report["params"], file.param_count(), "{report}");
    assert_eq!(
        report["file_bytes"].as_u64().unwrap(),
        std::fs::metadata(model).unwrap().len()
    );
    let lr = report["final_lr"].as_f64().unwrap() as f32;
    let end = schedule.adam.lr * schedule.lr_final.unwrap_or(1.0);
    assert!(lr >= 0.99 * end && lr < schedule.adam.lr, "{report}");
    // One epoch already gets most of the box right.
    let f1 = report["f1_bbox"].as_f64().unwrap();
    assert!(f1 > 0.8 && f1 <= 1.0, "{report}");
}

#[test]
fn eval_render_extract_and_query_read_a_hash_grid() {
    let (model, report, _) = trained();
    // eval: the same evaluation sets as the report's, the same scores.
    let o = bin("eval")
        .arg(model)
        .arg(data("suzanne.obj"))
        .args(["--points", "2000", "--surface-resolution", "0", "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(json["f1_bbox"], report["f1_bbox"], "{json}");
    assert_eq!(json["sign_errors_bbox"], report["sign_errors_bbox"]);

    let png = scratch("hashgrid.png");
    let o = bin("render")
        .arg(model)
        .args(["--size", "24", "--out"])
        .arg(&png)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("hashgrid model"), "{}", stderr(&o));
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));

    // extract, with all 16 levels named as the level of detail: the whole model.
    let extract = |extra: &[&str], name: &str| {
        let obj = scratch(name);
        let o = bin("extract")
            .arg(model)
            .args(["--resolution", "32", "--out"])
            .arg(&obj)
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        std::fs::read_to_string(&obj).unwrap()
    };
    let whole = extract(&[], "hashgrid.obj");
    assert!(whole.lines().filter(|l| l.starts_with("f ")).count() > 100);
    assert_eq!(extract(&["--lod", "16"], "hashgrid-lod16.obj"), whole);

    // query on the GPU agrees with NeuralSdf's CPU evaluation, in mesh coordinates.
    let sdf = NeuralSdf::load(model).unwrap();
    let frame = sdf.normalization();
    let points: Vec<glam::Vec3> = (0..64)
        .map(|i| {
            let t = i as f32 / 63.0;
            frame.to_original(glam::Vec3::new(
                2.4 * t - 1.2,
                0.7 - t,
                0.3 * (9.0 * t).sin(),
            ))
        })
        .collect();
    let (input, output) = (scratch("hashgrid-points.npy"), scratch("hashgrid-d.npy"));
    hwsdf::geom::npy::write_points(&input, &points).unwrap();
    let o = bin("query")
        .arg(model)
        .arg("--points")
        .arg(&input)
        .arg("--out")
        .arg(&output)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let gpu = hwsdf::geom::npy::read_f32(&output).unwrap();
    let cpu = sdf.eval_cpu(&points);
    assert_eq!(gpu.len(), cpu.len());
    for (i, (g, c)) in gpu.iter().zip(&cpu).enumerate() {
        assert!((g - c).abs() <= 1e-4 * c.abs().max(1.0), "{i}: {g} vs {c}");
    }

    // A level of detail short of all 16 levels is the typed error, in every reader.
    let needle = "levels of detail exist only for NGLOD models";
    let o = bin("eval")
        .arg(model)
        .arg(data("suzanne.obj"))
        .args(["--lod", "3"])
        .output()
        .unwrap();
    assert_clean_failure(&o, needle);
    for (name, out) in [("render", "never.png"), ("extract", "never.obj")] {
        let o = bin(name)
            .arg(model)
            .args(["--lod", "1", "--out"])
            .arg(scratch(out))
            .output()
            .unwrap();
        assert_clean_failure(&o, needle);
        assert!(!scratch(out).exists());
    }
}

/// Runs `train` on suzanne with `args` until its first progress line, presses Ctrl-C, and
/// returns its log once it has exited with 130.
fn interrupt_train(args: &[&str], out: &Path) -> String {
    let child = bin("train")
        .arg(data("suzanne.obj"))
        .args(args)
        .arg("--out")
        .arg(out)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (log, status) = common::interrupt_after_first_epoch(child);
    assert_eq!(status.code(), Some(130), "{log}");
    log
}

#[test]
fn a_hash_grids_checkpoint_resumes_into_a_hash_grid() {
    let out = scratch("resumed.hashgrid.safetensors");
    let report = out.with_extension("json");
    // Far more epochs than it will run: on a fast GPU the first progress line comes after 5 s
    // of training, which must not be the end of the run.
    let log = interrupt_train(
        &[
            "--model", "hashgrid", "--preset", "small", "--epochs", "1000",
        ],
        &out,
    );
    let checkpoint = out.with_extension("checkpoint.safetensors");
    assert!(log.contains("checkpoint written to"), "{log}");
    assert!(!out.exists(), "an interrupted run writes a checkpoint");
    let saved = hwsdf::eval::run::Checkpoint::load(&checkpoint).unwrap();
    assert_eq!(
        saved.options(),
        (Some("hashgrid".into()), Some("small".into()))
    );
    assert_eq!(saved.planned(), Some(1000));
    // A length asked for: no time budget left to plan with on a resume.
    assert!(!saved.plan_pending());
    assert_eq!(saved.model_file().metadata.architecture, "hashgrid");
    let done = saved.done();
    assert!(done >= 1, "{log}");

    let resume = |extra: &[&str]| {
        bin("train")
            .arg(data("suzanne.obj"))
            .args(extra)
            .args(["--eval-points", "2000", "--out"])
            .arg(&out)
            .arg("--resume")
            .arg(&checkpoint)
            .output()
            .unwrap()
    };
    // Not into another model, nor another preset.
    let o = resume(&["--model", "nglod", "--preset", "small"]);
    assert_clean_failure(&o, "the checkpoint is of a hashgrid model, not nglod");
    let o = resume(&["--model", "hashgrid", "--preset", "default"]);
    assert_clean_failure(&o, "the checkpoint uses the small preset, not default");
    // As many epochs as it has done: nothing to train, evaluated as it is, with the
    // checkpoint's loss and rate (the trainer's empty report gave a loss of 0 and the starting
    // rate). A copy of the checkpoint, which the finished run leaves alone.
    let copy = scratch("resumed-copy.checkpoint.safetensors");
    std::fs::copy(&checkpoint, &copy).unwrap();
    let as_is = scratch("as-is.hashgrid.safetensors");
    let o = bin("train")
        .arg(data("suzanne.obj"))
        .args(["--preset", "small", "--epochs", &done.to_string()])
        .args(["--eval-points", "2000", "--out"])
        .arg(&as_is)
        .arg("--resume")
        .arg(&copy)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(as_is.with_extension("json")).unwrap()).unwrap();
    assert_eq!(json["trained"], done, "{json}");
    let recorded = |key: &str| saved.training()[key].as_f64().unwrap() as f32;
    assert_eq!(
        json["final_loss"].as_f64().unwrap() as f32,
        recorded("final_loss"),
        "{json}"
    );
    assert_eq!(
        json["final_lr"].as_f64().unwrap() as f32,
        recorded("lr"),
        "{json}"
    );
    assert!(recorded("final_loss") > 0.0, "{json}");

    // One more epoch than it has done; without --model, the checkpoint's model (not the
    // adapter's default).
    let total = (done + 1).to_string();
    let o = resume(&["--preset", "small", "--epochs", &total]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["trained"], done + 1, "{json}");
    assert_eq!(json["model"], "hashgrid", "{json}");
    let file = ModelFile::load(&out).unwrap();
    assert_eq!(file.metadata.architecture, "hashgrid");
    assert_eq!(file.metadata.training["done"], done + 1);
}

#[test]
fn corpus_tabulates_the_hash_grid() {
    let dir = scratch("corpus-in");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data("suzanne.obj"), dir.join("suzanne.obj")).unwrap();
    let out = scratch("corpus.md");
    let o = bin("corpus")
        .arg(&dir)
        .args(["--model", "hashgrid", "--preset", "small", "--epochs", "1"])
        .args(["--eval-points", "2000", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let table = std::fs::read_to_string(&out).unwrap();
    assert!(table.contains("### Hash grid"), "{table}");
    let small = NglodConfig::hashgrid_small();
    let Encoding::Hashed { log2_table_size } = small.encoding else {
        panic!("hashgrid_small is not hashed")
    };
    let settings = format!(
        "Settings: architecture resolutions {}, table 2^{log2_table_size}, features {}, hidden \
         {}; batch {}; distance signed; epochs 1; lr {}; ",
        small
            .resolutions
            .iter()
            .map(u32::to_string)
            .collect::<Vec<_>>()
            .join(","),
        small.feature_dim,
        small.hidden,
        NglodTrainConfig::hashgrid().batch_size,
        NglodTrainConfig::hashgrid().adam.lr
    );
    assert!(table.contains(&settings), "{settings} not in {table}");
    let row = table
        .lines()
        .find(|l| l.starts_with("| suzanne.obj |"))
        .unwrap_or_else(|| panic!("no suzanne row: {table}"));
    assert!(!row.contains("failed"), "{row}");
    assert!(
        table.contains("| design document, NGLOD (50 meshes) | 0.98 | 0.94 |"),
        "{table}"
    );
    let state = hwsdf::eval::corpus::StateDir::for_table(&out, &[]);
    let model = state.model_file("suzanne.obj", hwsdf::eval::run::ModelKind::Hashgrid);
    assert_eq!(
        ModelFile::load(&model).unwrap().metadata.architecture,
        "hashgrid"
    );
    // `--model all` counts the hash grid among its three models.
    let o = bin("corpus")
        .arg(&dir)
        .args(["--model", "all", "--merge", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("1 of 3 done, 0 failed, 2 not yet run"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn options_that_do_not_apply_to_a_hash_grid_are_typed_errors() {
    let never = scratch("never.hashgrid.safetensors");
    let train = |extra: &[&str]| {
        bin("train")
            .arg(data("suzanne.obj"))
            .args(["--model", "hashgrid", "--out"])
            .arg(&never)
            .args(extra)
            .output()
            .unwrap()
    };
    for (extra, needle) in [
        (
            &["--grow-every", "2"][..],
            "--grow-every adds NGLOD's levels",
        ),
        (&["--grow-every", "0"], "--grow-every"),
        (
            &["--sparse-levels", "1"],
            "--sparse-levels sets NGLOD's sparse levels; a hash grid has none",
        ),
        (
            &["--band-cells", "1"],
            "--band-cells sets NGLOD's sparse levels",
        ),
        (
            &["--steps", "3"],
            "--steps applies to SIREN; the hash grid trains for --epochs",
        ),
        (&["--plateau-patience", "5"], "--plateau-patience"),
        (&["--eikonal-weight", "1"], "loss weights apply to SIREN"),
        (
            &[
                "--resolutions",
                "8,12,16,24,32,48,64,96,128",
                "--features",
                "4",
            ],
            "hash grid: invalid configuration: 9 levels of 4 features concatenate to 36 MLP inputs",
        ),
        (&["--resolutions", "8,5000"], "resolution 5000"),
        (&["--lr", "0"], "learning rate"),
        (&["--epochs", "0"], "--epochs"),
    ] {
        let o = train(extra);
        assert_clean_failure(&o, needle);
        // Refused before any work.
        assert!(
            !stderr(&o).contains("training"),
            "{extra:?}: {}",
            stderr(&o)
        );
    }
    assert!(!never.exists());
    let corpus = |extra: &[&str]| {
        bin("corpus")
            .arg(data("."))
            .arg("--out")
            .arg(scratch("never.md"))
            .args(extra)
            .output()
            .unwrap()
    };
    for (extra, needle) in [
        (
            &["--model", "hashgrid", "--grow-every", "1"][..],
            "--grow-every",
        ),
        (
            &["--model", "all", "--lr", "1e-3"],
            "--lr sets one model's learning rate",
        ),
        (
            &["--model", "all", "--hidden", "16"],
            "--resolutions, --features and --hidden describe NGLOD's architecture",
        ),
    ] {
        assert_clean_failure(&corpus(extra), needle);
    }
    assert!(!scratch("never.md").exists());
}
