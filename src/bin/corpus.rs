//! Trains and evaluates every mesh in a folder and writes the design document's table.
//!
//! ```sh
//! cargo run --release --bin corpus -- ../shared/meshes --model both --out results.md
//! ```
//!
//! Resumable: each mesh's report is kept in `<out>.d/` as it finishes, and a rerun skips the
//! meshes that have one. A mesh that fails is recorded with its error (and retried on the next
//! run); the others go on.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Parser, ValueEnum};
use hwsdf::eval::metrics::DEFAULT_EVAL_POINTS;
use hwsdf::eval::run::{self, ModelKind, Preset, Report, TrainOptions};
use hwsdf::geom::io::write_atomic;
use hwsdf::nn::GpuContext;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Models {
    Siren,
    Nglod,
    Both,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PresetArg {
    Default,
    Small,
}

/// Train and evaluate every OBJ, glTF and GLB mesh in a folder.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Folder of meshes.
    dir: PathBuf,
    /// Which architectures.
    #[arg(long, value_enum, default_value = "both")]
    model: Models,
    /// Size preset (default: `default` on a GPU, `small` on a CPU adapter).
    #[arg(long, value_enum)]
    preset: Option<PresetArg>,
    /// SIREN steps per mesh (default: the preset's for the adapter).
    #[arg(long)]
    steps: Option<usize>,
    /// NGLOD epochs per mesh (default: the preset's for the adapter).
    #[arg(long)]
    epochs: Option<usize>,
    /// Markdown table to write; per-mesh results go to `<out>.d/`.
    #[arg(long, default_value = "results.md")]
    out: PathBuf,
    /// Points in each evaluation set.
    #[arg(long, default_value_t = DEFAULT_EVAL_POINTS)]
    eval_points: usize,
    /// Seed of every run.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// One mesh × model outcome, as kept on disk.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum Entry {
    Done(Box<Report>),
    Failed {
        mesh: String,
        model: String,
        error: String,
    },
}

fn main() -> ExitCode {
    let args = Args::parse();
    match corpus(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn meshes_in(dir: &Path) -> Result<Vec<PathBuf>, Box<dyn std::error::Error>> {
    let mut meshes: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "obj" | "gltf" | "glb"))
        })
        .collect();
    meshes.sort();
    if meshes.is_empty() {
        return Err(format!("{} holds no .obj, .gltf or .glb file", dir.display()).into());
    }
    Ok(meshes)
}

fn corpus(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    let meshes = meshes_in(&args.dir)?;
    let models: Vec<ModelKind> = match args.model {
        Models::Siren => vec![ModelKind::Siren],
        Models::Nglod => vec![ModelKind::Nglod],
        Models::Both => vec![ModelKind::Siren, ModelKind::Nglod],
    };
    let gpu = GpuContext::new()?;
    let preset = match args.preset {
        Some(PresetArg::Default) => Preset::Default,
        Some(PresetArg::Small) => Preset::Small,
        // SIREN's CPU preset wins when both run: one preset for the whole table.
        None => Preset::for_adapter(
            gpu.is_cpu(),
            if models.contains(&ModelKind::Siren) {
                ModelKind::Siren
            } else {
                ModelKind::Nglod
            },
        ),
    };
    let state_dir = PathBuf::from(format!("{}.d", args.out.display()));
    std::fs::create_dir_all(&state_dir).map_err(|e| format!("{}: {e}", state_dir.display()))?;
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::Relaxed) {
                std::process::exit(130);
            }
            eprintln!("\nstopping after the current mesh; finished meshes are kept");
        })?;
    }
    eprintln!(
        "{} meshes × {} models, {} preset, on {}",
        meshes.len(),
        models.len(),
        preset.name(),
        gpu.describe()
    );

    for mesh in &meshes {
        for &model in &models {
            if stop.load(Ordering::Relaxed) {
                break;
            }
            let (name, record) = record_path(&state_dir, mesh, model);
            if matches!(read_entry(&record), Some(Entry::Done(_))) {
                eprintln!("{name} {}: done earlier, skipped", model.name());
                continue;
            }
            let options = TrainOptions {
                model,
                preset,
                steps: args.steps,
                epochs: args.epochs,
                seed: args.seed,
                lr: None,
                siren_weights: None,
                lr_final: None,
                grow_every: None,
                distance: hwsdf::nn::DistanceMode::Signed,
                pool: None,
            };
            let model_path = state_dir.join(format!("{name}.{}.safetensors", model.name()));
            eprintln!("{name} {}: training", model.name());
            let entry = match run::run(
                &gpu,
                mesh,
                &options,
                &model_path,
                args.eval_points,
                &stop,
                |_| {},
            ) {
                Ok((_, trained)) if trained.interrupted => break,
                Ok((report, _)) => {
                    eprintln!(
                        "{name} {}: F1 box {}, near {}, {:.0} s",
                        model.name(),
                        f3(report.f1_bbox),
                        f3(report.f1_near_surface),
                        report.train_seconds
                    );
                    Entry::Done(Box::new(report))
                }
                Err(e) => {
                    eprintln!("{name} {}: failed: {e}", model.name());
                    Entry::Failed {
                        mesh: mesh.display().to_string(),
                        model: model.name().into(),
                        error: e.to_string(),
                    }
                }
            };
            write_atomic(&record, &serde_json::to_vec_pretty(&entry)?)
                .map_err(|e| format!("{}: {e}", record.display()))?;
        }
    }

    let mut entries = BTreeMap::new();
    for mesh in &meshes {
        for &model in &models {
            let (name, record) = record_path(&state_dir, mesh, model);
            if let Some(e) = read_entry(&record) {
                entries.insert((model.name(), name), e);
            }
        }
    }
    let table = markdown(&entries, preset, &gpu.describe());
    write_atomic(&args.out, table.as_bytes())
        .map_err(|e| format!("{}: {e}", args.out.display()))?;
    print!("{table}");
    eprintln!("table written to {}", args.out.display());
    Ok(())
}

/// The mesh's file name and where its result for `model` is kept.
fn record_path(state_dir: &Path, mesh: &Path, model: ModelKind) -> (String, PathBuf) {
    let name = mesh
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let record = state_dir.join(format!("{name}.{}.json", model.name()));
    (name, record)
}

/// An F1 to three decimals, or "n/a" where it is undefined (a mesh without an inside).
fn f3(x: Option<f64>) -> String {
    x.map_or_else(|| "n/a".to_owned(), |v| format!("{v:.3}"))
}

fn read_entry(path: &Path) -> Option<Entry> {
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// The design document's averages (F1 in the box, F1 near the surface).
fn reference(model: &str) -> (f64, f64) {
    match model {
        "siren" => (0.90, 0.89),
        _ => (0.98, 0.94),
    }
}

fn markdown(entries: &BTreeMap<(&str, String), Entry>, preset: Preset, adapter: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "Preset `{}`, adapter {adapter}.\n", preset.name());
    for model in ["siren", "nglod"] {
        let rows: Vec<_> = entries.iter().filter(|((m, _), _)| *m == model).collect();
        if rows.is_empty() {
            continue;
        }
        let _ = writeln!(s, "### {}\n", model.to_uppercase());
        let _ = writeln!(
            s,
            "| mesh | F1 in bounding box | F1 near surface | mean | train s | ns/point | µs/3000 | params | file bytes |"
        );
        let _ = writeln!(s, "| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
        let (mut fb, mut fnr, mut n, mut left_out) = (0.0, 0.0, 0usize, 0usize);
        for ((_, mesh), e) in &rows {
            match e {
                Entry::Done(r) => {
                    let _ = writeln!(
                        s,
                        "| {mesh} | {} | {} | {} | {:.0} | {:.0} | {:.0} | {} | {} |",
                        f3(r.f1_bbox),
                        f3(r.f1_near_surface),
                        f3(r.f1_mean),
                        r.train_seconds,
                        r.per_point_ns,
                        r.batch3000_us,
                        r.params,
                        r.file_bytes
                    );
                    // A mesh without an inside has no F1: left out of the averages.
                    if let (Some(b), Some(near)) = (r.f1_bbox, r.f1_near_surface) {
                        fb += b;
                        fnr += near;
                        n += 1;
                    } else {
                        left_out += 1;
                    }
                }
                Entry::Failed { error, .. } => {
                    let _ = writeln!(
                        s,
                        "| {mesh} | failed: {} | | | | | | | |",
                        error.replace('|', "/")
                    );
                }
            }
        }
        if left_out > 0 {
            let _ = writeln!(
                s,
                "| n/a: {left_out} mesh(es) without an inside (F1 undefined), left out of the average | | | | | | | | |"
            );
        }
        if n > 0 {
            let (rb, rn) = reference(model);
            let _ = writeln!(
                s,
                "| **average ({n} meshes)** | **{:.3}** | **{:.3}** | **{:.3}** | | | | | |",
                fb / n as f64,
                fnr / n as f64,
                0.5 * (fb + fnr) / n as f64
            );
            let _ = writeln!(
                s,
                "| design document (50 meshes) | {rb:.2} | {rn:.2} | {:.3} | | | | | |",
                0.5 * (rb + rn)
            );
        }
        let _ = writeln!(s);
    }
    s
}
