//! Trains a neural SDF on a mesh on the GPU, saves it, evaluates it and writes a JSON report.
//!
//! ```sh
//! cargo run --release --bin train -- tests/data/spot.obj --model nglod
//! cargo run --release --bin train -- tests/data/spot.obj --model hashgrid
//! ```
//!
//! Ctrl-C stops after the current step (SIREN) or at the next loss read-back within an epoch
//! (NGLOD, the hash grid) and saves what was learnt as a checkpoint next to the output; `--resume CHECKPOINT` continues from it.

use std::ffi::OsString;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Parser, ValueEnum};
use hwsdf::cli::{GpuFlags, GroundTruthFlags, LabelFlags, TrainingFlags, format_loss};
use hwsdf::eval::run::{self, ModelKind, NglodArchitecture, Progress};
use hwsdf::geom::io;
use hwsdf::nn::{DistanceMode, ModelFile, NeuralSdf, Normalization};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Model {
    /// SIREN: a sine MLP, trained for --steps.
    Siren,
    /// NGLOD: levels of feature grids summed into a small MLP, trained for --epochs.
    Nglod,
    /// instant-ngp's multiresolution hash grid: 16 hashed levels concatenated into a small
    /// MLP, trained for --epochs.
    Hashgrid,
}

/// Fit a neural signed distance function to a mesh on the GPU.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Mesh to fit (OBJ, glTF or GLB).
    mesh: PathBuf,
    /// glTF: also follow buffer URIs outside the mesh's folder (absolute paths, `..`, symbolic links).
    #[arg(long)]
    allow_external_uris: bool,
    /// Architecture (default: with --resume, the checkpoint's; NGLOD where an NGLOD-only or
    /// architecture flag is given; else NGLOD on a GPU and the hash grid on a CPU adapter,
    /// where it fits better in the same minute).
    #[arg(long, value_enum)]
    model: Option<Model>,
    /// Output model file (default: MESH's name with `.<model>.safetensors`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// JSON report (default: the output's name with `.json`).
    #[arg(long)]
    report: Option<PathBuf>,
    /// Continue from a checkpoint written by an interrupted run.
    #[arg(long)]
    resume: Option<PathBuf>,
    #[command(flatten)]
    training: TrainingFlags,
    #[command(flatten)]
    gpu: GpuFlags,
    #[command(flatten)]
    ground_truth: GroundTruthFlags,
    #[command(flatten)]
    labelling: LabelFlags,
}

/// The exit status of a run stopped by Ctrl-C or SIGTERM (its checkpoint written), as a shell
/// reports a process ended by SIGINT: `train … && eval …` must not go on.
const INTERRUPTED: u8 = 130;

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    match train(&args) {
        Ok(Outcome::Finished) => ExitCode::SUCCESS,
        Ok(Outcome::Interrupted) => ExitCode::from(INTERRUPTED),
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// How a run without errors ended.
enum Outcome {
    Finished,
    /// Stopped early; the checkpoint is written.
    Interrupted,
}

fn train(args: &Args) -> Result<Outcome, Box<dyn std::error::Error>> {
    let flags = &args.training;
    // Without --model a resume's checkpoint is read first (once): its model decides the checks.
    let early = match (args.model, &args.resume) {
        (None, Some(path)) => Some(run::Checkpoint::read(path)?),
        _ => None,
    };
    let known = known_model(args, early.as_ref())?;
    // Every check that needs no GPU, before it opens: for each model the adapter may still
    // choose (their flags and default output names), then the mesh and the checkpoint.
    let candidates = match known {
        Some(model) => vec![model],
        None => vec![ModelKind::for_adapter(false), ModelKind::for_adapter(true)],
    };
    let mut paths = check_flags_and_paths(args, &candidates)?;
    let uris = hwsdf::geom::LoadOptions::with_external_uris(args.allow_external_uris);
    let (mesh, normalization) = run::load_normalized_with(&args.mesh, &uris)?;
    let resume = read_resume(early, args.resume.as_deref(), normalization)?;
    // A resume's model is known (asked for or its checkpoint's) and so is its preset (asked
    // for or its checkpoint's, on whatever adapter it continues): both checked before the GPU.
    let resume_preset = match (&resume, known) {
        (Some(c), Some(model)) => {
            let preset = flags.preset().map_or_else(|| c.preset(), Ok)?;
            c.check_resumes(&flags.options(&[model])?.remove(0).with_preset(preset)?)?;
            Some(preset)
        }
        _ => None,
    };
    let gpu = args.gpu.open()?;
    let model = known.unwrap_or_else(|| ModelKind::for_adapter(gpu.is_cpu()));
    // The paths checked above for this model: the adapter's is one of the candidates.
    let chosen = candidates.iter().position(|&m| m == model);
    let paths = paths.swap_remove(chosen.expect("the model is a candidate"));
    let preset = resume_preset.unwrap_or_else(|| flags.preset_for(model, gpu.is_cpu()));
    let options = flags.options(&[model])?.remove(0).with_preset(preset)?;
    if gpu.is_cpu()
        && let Some(note) = cpu_note(known.is_none(), flags, &options, resume.is_some())
    {
        eprintln!("{note}");
    }
    // The exact SDF once, for the check below, the trainer's samples and the evaluation; after
    // every cheap check, since on a scan of millions of triangles it takes seconds.
    let mut truth = run::GroundTruth::on(&gpu, mesh, &args.mesh, args.ground_truth.device())?;
    if let Some(why) = truth.labels.fallback() {
        eprintln!("warning: {}: {why}", args.mesh.display());
    }
    // No minutes of silence on a mesh that labels slowly: the estimate first, then progress.
    let planned = run::planned_labels(&options, gpu.is_cpu(), flags.eval_points);
    if let Some(line) =
        run::labelling_estimate(&truth, planned, args.labelling.label_estimate_after)?
    {
        eprintln!("{line}");
    }
    truth.labels = truth.labels.with_progress(args.labelling.progress());
    if options.distance == DistanceMode::Signed
        && let Some(reason) = run::no_inside_check(&truth)?
    {
        eprintln!(
            "warning: {}: {reason}. Its F1 will be reported as null (n/a); sign accuracy and \
             distance errors are still reported. To fit it anyway, try --distance unsigned \
             (fits the unsigned distance |d|, scored by distance error and Chamfer distance).",
            args.mesh.display()
        );
    }
    // A changed architecture is named against its preset's: "resolutions 8,16,32, not 6,12,24".
    let changed = match model {
        ModelKind::Nglod | ModelKind::Hashgrid => {
            options
                .nglod_architecture
                .differences(&NglodArchitecture::default().config(
                    model,
                    options.preset,
                    flags.seed,
                )?)
        }
        ModelKind::Siren => Vec::new(),
    };
    eprintln!(
        "training {} ({}{}) on {} with {}; ground truth on the {}",
        model.name(),
        options.preset.name(),
        changed.iter().map(|c| format!("; {c}")).collect::<String>(),
        args.mesh.display(),
        gpu.describe(),
        truth.labels.path().name().to_uppercase()
    );

    let signals = Signals::install()?;
    let mut reporter = Reporter::new();
    let trained = run::train(
        &gpu,
        &truth,
        normalization,
        &options,
        resume.as_ref(),
        &signals.stop,
        |p| reporter.update(p),
    )?;
    reporter.finish();

    if trained.interrupted {
        save_checkpoint(&trained, model, &paths.checkpoint)?;
        return Ok(Outcome::Interrupted);
    }

    trained.file.save(&paths.out)?;
    let file_bytes = std::fs::metadata(&paths.out)?.len();
    eprintln!(
        "saved {} ({} bytes); evaluating",
        paths.out.display(),
        file_bytes
    );
    // A report already beside the model describes an earlier one: gone, so that a run stopped
    // during the evaluation leaves no report rather than a wrong one.
    remove_if_present(&paths.report, "the report of an earlier model")?;
    signals.evaluating.store(true, Ordering::Relaxed);
    if signals.stop.load(Ordering::Relaxed) {
        // Ctrl-C came after the last step but before the evaluation began.
        eprintln!("interrupted; the model is saved, no report written");
        std::process::exit(INTERRUPTED.into());
    }
    let sdf = NeuralSdf::from_model_file(trained.file.clone())?;
    let eval = run::evaluate(&gpu, &sdf, &truth, flags.eval_points)?;
    // The report's atomic write is not cut short by a late Ctrl-C.
    signals.evaluating.store(false, Ordering::Relaxed);
    let report = run::Report::new(
        &args.mesh,
        &options,
        &trained,
        file_bytes,
        &eval,
        gpu.describe(),
        truth.labels.path(),
    );
    report.write(&paths.report)?;
    print_summary(&args.mesh, model, &report);
    eprintln!("report written to {}", paths.report.display());
    // A checkpoint this run resumed from and finished is spent.
    if let Some(resumed) = &args.resume
        && same_file(resumed, &paths.checkpoint)
    {
        remove_if_present(&paths.checkpoint, "the checkpoint this run finished")?;
    }
    Ok(Outcome::Finished)
}

/// The checkpoint of `--resume` (`early`: its file, when already read), checked against the
/// mesh (`normalization`) before the GPU and the ground truth (seconds for a large scan).
fn read_resume(
    early: Option<ModelFile>,
    path: Option<&Path>,
    normalization: Normalization,
) -> Result<Option<run::Checkpoint>, run::RunError> {
    let checkpoint = match (early, path) {
        (Some(file), Some(path)) => run::Checkpoint::from_file(file, path)?,
        (_, Some(path)) => run::Checkpoint::load(path)?,
        (_, None) => return Ok(None),
    };
    checkpoint.check_mesh(normalization)?;
    Ok(Some(checkpoint))
}

/// Writes an interrupted run's checkpoint and says how to continue.
fn save_checkpoint(
    trained: &run::Trained,
    model: ModelKind,
    path: &Path,
) -> Result<(), run::RunError> {
    trained.checkpoint().save(path)?;
    eprintln!(
        "interrupted after {} {}s; checkpoint written to {}. Continue with:\n  {}",
        trained.done,
        model.unit(),
        path.display(),
        resume_command(std::env::args_os(), path)
    );
    Ok(())
}

/// Removes `path` (`what` it holds, for the message) if it exists, saying so.
fn remove_if_present(path: &Path, what: &str) -> std::io::Result<()> {
    match std::fs::remove_file(path) {
        Ok(()) => {
            eprintln!("removed {}, {what}", path.display());
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
    }
}

/// Whether `a` and `b` name one existing file.
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

/// The model, where the command line tells it without the adapter: the one asked for, else
/// the checkpoint's (`checkpoint`: its file, read when no model is asked for; only its name is
/// read here, `Checkpoint::from_file` checks the rest), else NGLOD where a flag describes its
/// architecture (such command lines meant NGLOD before the default depended on the adapter).
/// `None`: the adapter's (`ModelKind::for_adapter`).
fn known_model(
    args: &Args,
    checkpoint: Option<&ModelFile>,
) -> Result<Option<ModelKind>, run::RunError> {
    Ok(match (args.model, checkpoint, &args.resume) {
        (Some(Model::Siren), ..) => Some(ModelKind::Siren),
        (Some(Model::Nglod), ..) => Some(ModelKind::Nglod),
        (Some(Model::Hashgrid), ..) => Some(ModelKind::Hashgrid),
        (None, Some(file), Some(path)) => match run::Checkpoint::model_of(file) {
            Some(model) => Some(model),
            // Naming no model: the checkpoint's checks, then its refusal, say why.
            None => Some(run::Checkpoint::from_file(file.clone(), path)?.model()?),
        },
        _ => args.training.describes_nglod().then_some(ModelKind::Nglod),
    })
}

/// The flags and output paths of each model in `candidates`, checked before the GPU opens; its
/// paths, in the candidates' order. A refused flag is named for the model the adapter would
/// choose, where the GPU opens: the candidates (NGLOD and the hash grid, no flag of NGLOD's
/// alone among the flags) take the same flags, only the refusal's words differ.
fn check_flags_and_paths(
    args: &Args,
    candidates: &[ModelKind],
) -> Result<Vec<Paths>, Box<dyn std::error::Error>> {
    let refusals: Vec<(ModelKind, String)> = candidates
        .iter()
        .filter_map(|&m| Some((m, args.training.options(&[m]).err()?.to_string())))
        .collect();
    if let Some((_, first)) = refusals.first() {
        // Refusals in the same words need no adapter; else the adapter's model's, where the
        // GPU opens (and none where that model takes the flags).
        let same = refusals.len() == candidates.len() && refusals.iter().all(|(_, r)| r == first);
        let chosen = (!same)
            .then(|| args.gpu.open().ok())
            .flatten()
            .map(|g| ModelKind::for_adapter(g.is_cpu()));
        match chosen {
            Some(m) => {
                if let Some((_, r)) = refusals.iter().find(|(k, _)| *k == m) {
                    return Err(r.clone().into());
                }
            }
            None => return Err(first.clone().into()),
        }
    }
    candidates
        .iter()
        .map(|&model| Paths::new(args, model))
        .collect()
}

/// What a run on a CPU adapter tells the user it chose for them: the model, where the adapter
/// chose it, and the preset and length where none was asked for (a resume has its
/// checkpoint's).
fn cpu_note(
    adapter_chose_model: bool,
    flags: &TrainingFlags,
    options: &run::TrainOptions,
    resuming: bool,
) -> Option<String> {
    let mut chosen = Vec::new();
    if adapter_chose_model {
        chosen.push(format!(
            "the {} (--model to choose; it fits better than NGLOD in the same minute here)",
            options.model.label()
        ));
    }
    if flags.preset.is_none() && !resuming {
        let length = options.length(true);
        let length = if length.asked.is_some() {
            ""
        } else if length.time_budget.is_some() {
            " and as many epochs as about a minute of training buys here"
        } else {
            " and a shorter default run"
        };
        chosen.push(format!(
            "the `{}` preset{length} (--preset and --{}s to override)",
            options.preset.name(),
            options.model.unit()
        ));
    }
    (!chosen.is_empty()).then(|| format!("note: CPU adapter; using {}", chosen.join(", ")))
}

/// Where a run writes: the model, its report, and the checkpoint an interruption leaves.
struct Paths {
    out: PathBuf,
    report: PathBuf,
    checkpoint: PathBuf,
}

impl Paths {
    /// The paths `args` ask for or default to, checked before any work: no output may replace
    /// the mesh, the checkpoint resumed from or another output, and each folder must take a new
    /// file. The checkpoint an interrupted run writes may replace the one it resumed from: that
    /// is the same run, further on.
    fn new(args: &Args, model: ModelKind) -> Result<Self, Box<dyn std::error::Error>> {
        let out = args
            .out
            .clone()
            .unwrap_or_else(|| default_out(&args.mesh, model));
        let report = args
            .report
            .clone()
            .unwrap_or_else(|| out.with_extension("json"));
        if args.report.is_none() && report == out {
            return Err(format!(
                "--out {} would also be the report's default name (the model's with .json): give \
                 the model another name, or the report one with --report",
                out.display()
            )
            .into());
        }
        let checkpoint = checkpoint_path(&out);
        let mut inputs = vec![args.mesh.as_path()];
        inputs.extend(args.resume.as_deref());
        io::check_outputs(&inputs, &[&out, &report])?;
        io::check_outputs(&[&args.mesh], &[&out, &report, &checkpoint])?;
        hwsdf::cli::check_out_format("--out", &out, "safetensors", "a model file (safetensors)")?;
        hwsdf::cli::check_out_format("--report", &report, "json", "JSON")?;
        Ok(Paths {
            out,
            report,
            checkpoint,
        })
    }
}

/// What Ctrl-C and SIGTERM have asked: `stop` after the current step, and whether the
/// evaluation (which has nothing to keep) has begun.
struct Signals {
    stop: Arc<AtomicBool>,
    evaluating: Arc<AtomicBool>,
}

impl Signals {
    fn install() -> Result<Self, ctrlc::Error> {
        let signals = Signals {
            stop: Arc::new(AtomicBool::new(false)),
            evaluating: Arc::new(AtomicBool::new(false)),
        };
        let stop = signals.stop.clone();
        let evaluating = signals.evaluating.clone();
        ctrlc::set_handler(move || {
            // The model is saved by then; the evaluation has nothing to keep.
            if evaluating.load(Ordering::Relaxed) {
                eprintln!(
                    "\ninterrupted during the evaluation; the model is saved, no report written"
                );
                std::process::exit(INTERRUPTED.into());
            }
            if stop.swap(true, Ordering::Relaxed) {
                // A second Ctrl-C means now.
                std::process::exit(INTERRUPTED.into());
            }
            eprintln!("\nstopping after the current step; Ctrl-C again to abort without saving");
        })?;
        Ok(signals)
    }
}

/// The run's one line of figures (and its sign errors) on stdout.
fn print_summary(mesh: &Path, model: ModelKind, report: &run::Report) {
    let f4 = |x: Option<f64>| x.map_or_else(|| "n/a".to_owned(), |v| format!("{v:.4}"));
    let chamfer = report
        .chamfer_l1
        .map(|c| format!(", Chamfer-L1 {c:.5} (level set {})", run::UNSIGNED_LEVEL))
        .unwrap_or_default();
    println!(
        "{} {}: F1 box {}, near surface {}, mean {} ({}); |Φ−d| near {:.5}{chamfer}; {:.1} ns/point, {:.0} µs per 3000; {} params, {} bytes; trained in {:.1} s",
        mesh.display(),
        model.name(),
        f4(report.f1_bbox),
        f4(report.f1_near_surface),
        f4(report.f1_mean),
        report.ambiguity_summary(),
        report.near_surface_mean_abs_error,
        report.per_point_ns,
        report.batch3000_us,
        report.params,
        report.file_bytes,
        report.train_seconds
    );
    if let Some(e) = report.sign_errors_bbox.filter(|e| e.total() > 0) {
        println!("sign errors in the box: {e}");
    }
}

/// The command that continues this run: its own arguments (every flag, `--out` and the preset
/// included, so the resumed run trains and saves alike), any `--resume` replaced by
/// `checkpoint`, each argument quoted for a POSIX shell where it needs to be.
fn resume_command(argv: impl IntoIterator<Item = OsString>, checkpoint: &Path) -> String {
    let mut argv = argv.into_iter();
    let program = argv
        .next()
        .map(PathBuf::from)
        .and_then(|p| p.file_name().map(|n| n.to_os_string()))
        .unwrap_or_else(|| "train".into());
    let mut words = vec![program];
    let mut skip_value = false;
    for a in argv {
        if std::mem::take(&mut skip_value) {
            continue;
        }
        match a.to_str() {
            Some("--resume") => skip_value = true,
            Some(s) if s.starts_with("--resume=") => {}
            _ => words.push(a),
        }
    }
    words.push("--resume".into());
    words.push(checkpoint.as_os_str().to_os_string());
    words
        .iter()
        .map(|w| shell_quote(&w.to_string_lossy()))
        .collect::<Vec<_>>()
        .join(" ")
}

/// `word` as one POSIX shell word: unchanged when it has only safe characters, else in single
/// quotes (a `'` inside written as `'\''`).
fn shell_quote(word: &str) -> String {
    let safe = |c: char| c.is_ascii_alphanumeric() || "-_./=,:+@%".contains(c);
    if !word.is_empty() && word.chars().all(safe) {
        word.to_owned()
    } else {
        format!("'{}'", word.replace('\'', "'\\''"))
    }
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
            "loss {}  lr {:.1e}  {:.0} points/s",
            format_loss(p.loss),
            p.lr,
            p.points_per_second
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
            // A CPU time budget plans the run's length again after its first epochs.
            bar.set_length(p.total as u64);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_resume_command_keeps_every_flag_and_replaces_resume() {
        let argv = [
            "/usr/bin/train",
            "my mesh.obj",
            "--preset",
            "small",
            "--out",
            "o/m.safetensors",
            "--resume",
            "old.ckpt",
            "--resume=older.ckpt",
            "--lr",
            "1e-4",
        ]
        .map(OsString::from);
        let got = resume_command(argv, Path::new("o/m.checkpoint.safetensors"));
        assert_eq!(
            got,
            "train 'my mesh.obj' --preset small --out o/m.safetensors --lr 1e-4 \
             --resume o/m.checkpoint.safetensors"
        );
        assert_eq!(shell_quote("it's"), "'it'\\''s'");
        assert_eq!(shell_quote(""), "''");
    }
}
