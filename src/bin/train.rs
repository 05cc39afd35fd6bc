//! Trains a neural SDF on a mesh on the GPU, saves it, evaluates it and writes a JSON report.
//!
//! ```sh
//! cargo run --release --bin train -- tests/data/spot.obj --model nglod
//! ```
//!
//! Ctrl-C stops after the current step (SIREN) or epoch (NGLOD) and saves what was learnt as a
//! checkpoint next to the output; `--resume CHECKPOINT` continues from it.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Parser, ValueEnum};
use hwsdf::eval::metrics::DEFAULT_EVAL_POINTS;
use hwsdf::eval::run::{self, ModelKind, NglodArchitecture, Preset, Progress, TrainOptions};
use hwsdf::geom::io;
use hwsdf::nn::{DistanceMode, GpuContext, LossWeights, NeuralSdf};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Model {
    Siren,
    Nglod,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum DistanceArg {
    Signed,
    Unsigned,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PresetArg {
    Default,
    Small,
}

/// Fit a neural signed distance function to a mesh on the GPU.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Mesh to fit (OBJ, glTF or GLB).
    mesh: PathBuf,
    /// glTF: also follow buffer URIs outside the mesh's folder (absolute paths, `..`, symbolic links).
    #[arg(long)]
    allow_external_uris: bool,
    /// Architecture.
    #[arg(long, value_enum, default_value = "nglod")]
    model: Model,
    /// Size preset (default: `default`).
    #[arg(long, value_enum)]
    preset: Option<PresetArg>,
    /// SIREN training steps (default: 10000 on a GPU, a few hundred on a CPU adapter).
    #[arg(long, conflicts_with = "epochs")]
    steps: Option<usize>,
    /// NGLOD epochs of 5·10^5 points (default: 100 on a GPU, 12 on a CPU adapter).
    #[arg(long)]
    epochs: Option<usize>,
    /// Seed of initialisation and sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output model file (default: MESH's name with `.<model>.safetensors`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// JSON report (default: the output's name with `.json`).
    #[arg(long)]
    report: Option<PathBuf>,
    /// Continue from a checkpoint written by an interrupted run.
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Points in each evaluation set.
    #[arg(long, default_value_t = DEFAULT_EVAL_POINTS)]
    eval_points: usize,
    /// Initial learning rate (default: 1e-4 for SIREN, 1e-3 for NGLOD).
    #[arg(long)]
    lr: Option<f32>,
    /// NGLOD: final learning rate as a fraction of the first, by cosine decay over the run
    /// (1 keeps it constant).
    #[arg(long)]
    lr_final: Option<f32>,
    /// NGLOD: progressive levels of detail, one more every this many epochs (0: all at once).
    #[arg(long)]
    grow_every: Option<usize>,
    /// NGLOD: blocks of one epoch's worth of labelled points in the sample pool, and epochs
    /// between fresh blocks once it is full, as BLOCKS,EVERY (default 4,4; 1,1 samples fresh
    /// points every epoch).
    #[arg(long, value_parser = parse_pool)]
    pool: Option<(usize, usize)>,
    /// Fit the signed distance, or the unsigned one |d| for meshes without an inside (flat or
    /// open sheets, two-sided triangle soups); unsigned is scored by distance error and Chamfer
    /// distance, not F1. NGLOD only.
    #[arg(long, value_enum, default_value = "signed")]
    distance: DistanceArg,
    /// NGLOD: cells per axis of each level of detail, coarse to fine, comma-separated
    /// (`default`: 6,12,24,48; `small`: 4,8,16).
    #[arg(long, value_delimiter = ',', help_heading = "NGLOD architecture")]
    resolutions: Option<Vec<u32>>,
    /// NGLOD: how many of the finest levels keep features only near the surface, at most 255
    /// cells each (`default`: 1; `small`: 0).
    #[arg(long, help_heading = "NGLOD architecture")]
    sparse_levels: Option<usize>,
    /// NGLOD: features per grid vertex (`default`: 8; `small`: 4).
    #[arg(long, help_heading = "NGLOD architecture")]
    features: Option<u32>,
    /// NGLOD: hidden width of the MLP (`default`: 128; `small`: 32).
    #[arg(long, help_heading = "NGLOD architecture")]
    hidden: Option<u32>,
    /// SIREN loss: weight of the on-surface |Φ| term (default 3000).
    #[arg(long, help_heading = "SIREN loss")]
    surface_weight: Option<f32>,
    /// SIREN loss: weight of the off-surface exp(−α|Φ|) term (default 100).
    #[arg(long, help_heading = "SIREN loss")]
    off_surface_weight: Option<f32>,
    /// SIREN loss: weight of the normal term 1 − cos(∇Φ, n) (default 100).
    #[arg(long, help_heading = "SIREN loss")]
    normal_weight: Option<f32>,
    /// SIREN loss: weight of the eikonal term |‖∇Φ‖ − 1| (default 5; the SIREN code uses 50).
    #[arg(long, help_heading = "SIREN loss")]
    eikonal_weight: Option<f32>,
    /// SIREN loss: sharpness α of the off-surface term (default 100).
    #[arg(long, help_heading = "SIREN loss")]
    alpha: Option<f32>,
}

impl Args {
    /// The NGLOD architecture flags given.
    fn nglod_architecture(&self) -> NglodArchitecture {
        NglodArchitecture {
            resolutions: self.resolutions.clone(),
            sparse_levels: self.sparse_levels,
            feature_dim: self.features,
            hidden: self.hidden,
        }
    }

    /// The SIREN loss weights, if any flag sets one (the others keep their defaults).
    fn siren_weights(&self) -> Option<LossWeights> {
        let flags = [
            self.surface_weight,
            self.off_surface_weight,
            self.normal_weight,
            self.eikonal_weight,
            self.alpha,
        ];
        if flags.iter().all(Option::is_none) {
            return None;
        }
        let d = LossWeights::default();
        Some(LossWeights {
            surface: self.surface_weight.unwrap_or(d.surface),
            off_surface: self.off_surface_weight.unwrap_or(d.off_surface),
            normal: self.normal_weight.unwrap_or(d.normal),
            eikonal: self.eikonal_weight.unwrap_or(d.eikonal),
            alpha: self.alpha.unwrap_or(d.alpha),
        })
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    match train(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn train(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    if args.eval_points == 0 {
        return Err("--eval-points must be at least 1".into());
    }
    if args.steps == Some(0) || args.epochs == Some(0) {
        return Err("--steps and --epochs must be at least 1".into());
    }
    let model = match args.model {
        Model::Siren => ModelKind::Siren,
        Model::Nglod => ModelKind::Nglod,
    };
    if model == ModelKind::Siren && args.epochs.is_some() {
        return Err("--epochs applies to NGLOD; SIREN trains for --steps".into());
    }
    if model == ModelKind::Nglod && args.steps.is_some() {
        return Err("--steps applies to SIREN; NGLOD trains for --epochs".into());
    }
    run::check_eval_points(args.eval_points)?;
    // The trainers check these again; here they fail before the mesh and the GPU are set up.
    if let Some(lr) = args.lr {
        hwsdf::nn::AdamConfig::check_lr(lr)?;
    }
    if let Some(w) = args.siren_weights() {
        w.validate()?;
    }
    let architecture = args.nglod_architecture();
    // NGLOD's preset is `default` on every adapter unless one is asked for.
    let nglod_preset = match args.preset {
        Some(PresetArg::Small) => Preset::Small,
        _ => Preset::Default,
    };
    architecture.check(model, nglod_preset)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| default_out(&args.mesh, model));
    let report_path = args
        .report
        .clone()
        .unwrap_or_else(|| out.with_extension("json"));
    let checkpoint = checkpoint_path(&out);
    // Before any work: no output may replace the mesh, the checkpoint resumed from or another
    // output, and each folder must take a new file. The checkpoint an interrupted run writes
    // may replace the one it resumed from: that is the same run, further on.
    let mut inputs = vec![args.mesh.as_path()];
    inputs.extend(args.resume.as_deref());
    io::check_outputs(&inputs, &[&out, &report_path])?;
    io::check_outputs(&[&args.mesh], &[&out, &report_path, &checkpoint])?;
    // Load the mesh and the checkpoint before the GPU: bad input is reported at once.
    let uris = hwsdf::geom::LoadOptions::with_external_uris(args.allow_external_uris);
    let (mesh, normalization) = run::load_normalized_with(&args.mesh, &uris)?;
    let resume = match &args.resume {
        Some(path) => Some(run::Checkpoint::load(path)?),
        None => None,
    };
    let gpu = GpuContext::new()?;
    let preset = match args.preset {
        Some(PresetArg::Default) => Preset::Default,
        Some(PresetArg::Small) => Preset::Small,
        None => {
            let preset = Preset::for_adapter(gpu.is_cpu(), model);
            if gpu.is_cpu() {
                let length = match model {
                    _ if args.epochs.is_some() || args.steps.is_some() => "",
                    ModelKind::Nglod => {
                        " and as many epochs as about a minute of training buys here"
                    }
                    ModelKind::Siren => " and a shorter default run",
                };
                eprintln!(
                    "note: CPU adapter; using the `{}` preset{length} (pass --preset/--epochs/--steps to override)",
                    preset.name()
                );
            }
            preset
        }
    };
    if options_distance(args) == DistanceMode::Signed
        && let Some(reason) = run::no_inside_check(&mesh)?
    {
        eprintln!(
            "warning: {}: {reason}. Its F1 will be reported as null (n/a); sign accuracy and \
             distance errors are still reported. To fit it anyway, try --distance unsigned \
             (fits the unsigned distance |d|, scored by distance error and Chamfer distance).",
            args.mesh.display()
        );
    }
    let options = TrainOptions {
        model,
        preset,
        steps: args.steps,
        epochs: args.epochs,
        seed: args.seed,
        lr: args.lr,
        siren_weights: args.siren_weights(),
        lr_final: args.lr_final,
        grow_every: args.grow_every,
        distance: options_distance(args),
        pool: args.pool,
        nglod_architecture: architecture,
    };
    // A changed architecture is named against its preset's: "resolutions 8,16,32, not 6,12,24".
    let changed = match model {
        ModelKind::Nglod => options
            .nglod_architecture
            .differences(&NglodArchitecture::default().config(preset, args.seed)?),
        ModelKind::Siren => Vec::new(),
    };
    eprintln!(
        "training {} ({}{}) on {} with {}",
        model.name(),
        preset.name(),
        changed.iter().map(|c| format!("; {c}")).collect::<String>(),
        args.mesh.display(),
        gpu.describe()
    );

    let stop = Arc::new(AtomicBool::new(false));
    let evaluating = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        let evaluating = evaluating.clone();
        ctrlc::set_handler(move || {
            // The model is saved by then; the evaluation has nothing to keep.
            if evaluating.load(Ordering::Relaxed) {
                eprintln!(
                    "\ninterrupted during the evaluation; the model is saved, no report written"
                );
                std::process::exit(130);
            }
            if stop.swap(true, Ordering::Relaxed) {
                // A second Ctrl-C means now.
                std::process::exit(130);
            }
            eprintln!("\nstopping after the current step; Ctrl-C again to abort without saving");
        })?;
    }

    let mut reporter = Reporter::new();
    let trained = run::train(
        &gpu,
        &mesh,
        normalization,
        &options,
        resume.as_ref(),
        &stop,
        |p| reporter.update(p),
    )?;
    reporter.finish();

    if trained.interrupted {
        trained.checkpoint().save(&checkpoint)?;
        eprintln!(
            "interrupted after {} {}s; checkpoint written to {}. Continue with:\n  train {} --model {} --resume {}",
            trained.done,
            if model == ModelKind::Siren {
                "step"
            } else {
                "epoch"
            },
            checkpoint.display(),
            args.mesh.display(),
            model.name(),
            checkpoint.display()
        );
        return Ok(());
    }

    trained.file.save(&out)?;
    let file_bytes = std::fs::metadata(&out)?.len();
    eprintln!("saved {} ({} bytes); evaluating", out.display(), file_bytes);
    evaluating.store(true, Ordering::Relaxed);
    if stop.load(Ordering::Relaxed) {
        // Ctrl-C came after the last step but before the evaluation began.
        eprintln!("interrupted; the model is saved, no report written");
        std::process::exit(130);
    }
    let sdf = NeuralSdf::from_model_file(trained.file.clone())?;
    let eval = run::evaluate(&gpu, &sdf, &mesh, args.eval_points)?;
    // The report's atomic write is not cut short by a late Ctrl-C.
    evaluating.store(false, Ordering::Relaxed);
    let report = run::Report::new(
        &args.mesh,
        &options,
        &trained,
        file_bytes,
        &eval,
        gpu.describe(),
    );
    report.write(&report_path)?;
    let f4 = |x: Option<f64>| x.map_or_else(|| "n/a".to_owned(), |v| format!("{v:.4}"));
    let chamfer = report
        .chamfer_l1
        .map(|c| format!(", Chamfer-L1 {c:.5} (level set {})", run::UNSIGNED_LEVEL))
        .unwrap_or_default();
    println!(
        "{} {}: F1 box {}, near surface {}, mean {}; |Φ−d| near {:.5}{chamfer}; {:.1} ns/point, {:.0} µs per 3000; {} params, {} bytes; trained in {:.1} s",
        args.mesh.display(),
        model.name(),
        f4(report.f1_bbox),
        f4(report.f1_near_surface),
        f4(report.f1_mean),
        report.near_surface_mean_abs_error,
        report.per_point_ns,
        report.batch3000_us,
        report.params,
        report.file_bytes,
        report.train_seconds
    );
    eprintln!("report written to {}", report_path.display());
    Ok(())
}

fn options_distance(args: &Args) -> DistanceMode {
    match args.distance {
        DistanceArg::Signed => DistanceMode::Signed,
        DistanceArg::Unsigned => DistanceMode::Unsigned,
    }
}

fn parse_pool(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("expected BLOCKS,EVERY, not {s:?}"))?;
    let parse = |x: &str| match x.trim().parse::<usize>() {
        Ok(v) if v > 0 => Ok(v),
        _ => Err(format!("{x:?} is not a positive integer")),
    };
    Ok((parse(a)?, parse(b)?))
}

fn default_out(mesh: &Path, model: ModelKind) -> PathBuf {
    let stem = mesh.file_stem().map(|s| s.to_string_lossy().into_owned());
    PathBuf::from(format!(
        "{}.{}.safetensors",
        stem.as_deref().unwrap_or("model"),
        model.name()
    ))
}

fn checkpoint_path(out: &Path) -> PathBuf {
    out.with_extension("checkpoint.safetensors")
}

/// A progress bar on a terminal, plain log lines otherwise.
struct Reporter {
    bar: Option<ProgressBar>,
    last_line: std::time::Instant,
}

impl Reporter {
    fn new() -> Self {
        Reporter {
            bar: None,
            last_line: std::time::Instant::now(),
        }
    }

    fn update(&mut self, p: &Progress) {
        let msg = format!(
            "loss {:.5}  lr {:.1e}  {:.0} points/s",
            p.loss, p.lr, p.points_per_second
        );
        if std::io::stderr().is_terminal() {
            let bar = self.bar.get_or_insert_with(|| {
                let bar = ProgressBar::new(p.total as u64);
                bar.set_style(
                    ProgressStyle::with_template(
                        "{prefix} {bar:30} {pos}/{len} {msg}  [{elapsed_precise}, ETA {eta}]",
                    )
                    .expect("static template"),
                );
                bar.set_prefix(format!("{}s", p.unit));
                bar
            });
            bar.set_position(p.done as u64);
            bar.set_message(msg);
        } else if self.last_line.elapsed().as_secs_f64() >= 5.0 || p.done == p.total {
            self.last_line = std::time::Instant::now();
            eprintln!("{} {}/{}  {msg}", p.unit, p.done, p.total);
        }
    }

    fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish();
        }
    }
}
