//! Trains and evaluates every mesh of a corpus and writes the design document's table.
//!
//! ```sh
//! cargo run --release --bin corpus -- ../shared/meshes --model both --out results.md
//! cargo run --release --bin corpus -- ../shared/meshes --model all --out results.md
//! ```
//!
//! The corpus is a folder (walked recursively) or a list file (`--list`, one path a line,
//! relative to the list). Each mesh's result is kept in `<out>.d/` as it finishes; a rerun skips
//! the meshes that have one, and a failed mesh is recorded with its error (and retried next time).
//!
//! Across many GPUs (docs/distributed.md): `--shard K/N` (or the engine's own variables:
//! `SLURM_ARRAY_TASK_ID`, or `JOB_COMPLETION_INDEX` with `--shards N`) takes one deterministic
//! share of the meshes, and `--merge` builds the table from `<out>.d/` alone, without a GPU.
//!
//! Training takes `train`'s flags (`--preset`, `--epochs`, `--lr`, `--resolutions`, ...). The
//! first run records them in `<out>.d/settings.json`; a later run or shard with other settings is
//! refused before any work, so one table never mixes results of different settings.
//!
//! SIGINT, SIGTERM and SIGHUP (Ctrl-C, `scancel`, a time limit, preemption) stop the mesh in
//! training at its next step, write its checkpoint to `<out>.d/`, and exit with 130; the next run
//! resumes that mesh from the checkpoint and goes on with the rest.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Parser, ValueEnum};
use hwsdf::cli::{GpuFlags, GroundTruthFlags, TrainingFlags};
use hwsdf::eval::corpus::{self, CorpusMesh, CorpusSettings, Entry, Record, Shard, StateDir};
use hwsdf::eval::run::{self, Checkpoint, ModelKind, RunOutcome, TrainOptions};
use hwsdf::geom::io::write_atomic;
use hwsdf::nn::GpuContext;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Models {
    /// SIREN.
    Siren,
    /// NGLOD.
    Nglod,
    /// instant-ngp's multiresolution hash grid.
    Hashgrid,
    /// SIREN and NGLOD, the design document's two.
    Both,
    /// SIREN, NGLOD and the hash grid.
    All,
}

/// Train and evaluate every OBJ, glTF and GLB mesh of a corpus.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Folder of meshes (walked recursively; hidden entries are skipped).
    #[arg(required_unless_present = "list", conflicts_with = "list")]
    dir: Option<PathBuf>,
    /// A list of meshes instead of a folder: one path a line, relative to the list's folder.
    #[arg(long)]
    list: Option<PathBuf>,
    /// Which architectures: one, `both` (SIREN and NGLOD) or `all` (SIREN, NGLOD and the hash
    /// grid). Default: `both`; with --merge, the models the results folder has settings for.
    #[arg(long, value_enum)]
    model: Option<Models>,
    /// Markdown table to write; per-mesh results go to `<out>.d/`.
    #[arg(long, default_value = "results.md")]
    out: PathBuf,
    /// Take shard K of N (0-based), e.g. `--shard 3/8`. Without it, the engine's variables
    /// decide (`SLURM_ARRAY_TASK_ID`, `JOB_COMPLETION_INDEX`), else every mesh is taken.
    #[arg(long, conflicts_with = "merge")]
    shard: Option<String>,
    /// The number of shards when `JOB_COMPLETION_INDEX` gives the index (else `HWSDF_SHARDS`).
    #[arg(long)]
    shards: Option<u32>,
    /// Build the table from `<out>.d/` alone (no GPU, no training); works while shards run.
    #[arg(long)]
    merge: bool,
    #[command(flatten)]
    gpu: GpuFlags,
    #[command(flatten)]
    ground_truth: GroundTruthFlags,
    /// Every mesh's training, as `train` takes it.
    #[command(flatten)]
    training: TrainingFlags,
}

type BoxError = Box<dyn std::error::Error>;

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    match corpus(&args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn corpus(args: &Args) -> Result<ExitCode, BoxError> {
    let meshes = match (&args.list, &args.dir) {
        (Some(list), _) => corpus::read_list(list)?,
        (None, Some(dir)) => corpus::walk(dir)?,
        (None, None) => return Err("give a folder of meshes or --list FILE".into()),
    };
    // The table must not replace a mesh, and its folder must take it: checked before hours of
    // training, not after.
    let inputs: Vec<&std::path::Path> = meshes.iter().map(|m| m.path.as_path()).collect();
    hwsdf::geom::io::check_outputs(&inputs, &[&args.out])?;
    let state = StateDir::for_table(&args.out, &meshes);
    let models: Vec<ModelKind> = match args.model {
        Some(Models::Siren) => vec![ModelKind::Siren],
        Some(Models::Nglod) => vec![ModelKind::Nglod],
        Some(Models::Hashgrid) => vec![ModelKind::Hashgrid],
        Some(Models::All) => ModelKind::ALL.to_vec(),
        Some(Models::Both) => vec![ModelKind::Siren, ModelKind::Nglod],
        // A merge of a run of other models (`--model nglod` on every shard) lists those: with
        // `both` it counted a SIREN row missing for every mesh, and dropped the hash grid's.
        None if args.merge => recorded_models(&state),
        None => vec![ModelKind::Siren, ModelKind::Nglod],
    };
    if args.merge {
        return merge(args, &state, &meshes, &models);
    }
    let flags = &args.training;
    // Every check that can fail runs before the GPU is opened or a mesh is trained.
    let options = flags.options(&models)?;
    let shard = match &args.shard {
        Some(s) => Some((Shard::parse(s)?, "--shard".to_owned())),
        None => Shard::from_env(|k| std::env::var(k).ok(), args.shards)?,
    };
    let mine: Vec<&CorpusMesh> = match &shard {
        Some((s, _)) => s.select(&meshes),
        None => meshes.iter().collect(),
    };
    match &shard {
        Some((s, from)) => eprintln!(
            "shard {s} ({from}): {} of the corpus's {} meshes",
            mine.len(),
            meshes.len()
        ),
        None => eprintln!("all {} meshes (no shard)", meshes.len()),
    }
    state.create()?;
    let gpu = args.gpu.open()?;
    // Each model's preset as `train` picks it: the one asked for, else the adapter's (SIREN's
    // and the hash grid's `small` on a CPU adapter, NGLOD's `default` everywhere).
    let options = options
        .into_iter()
        .map(|o| {
            let preset = flags.preset_for(o.model, gpu.is_cpu());
            o.with_preset(preset)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let options = claim(&state, flags.eval_points, options, gpu.is_cpu())?;
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::Relaxed) {
                std::process::exit(130);
            }
            eprintln!("\nstopping: the mesh in training is checkpointed; finished meshes are kept");
        })?;
    }
    eprintln!(
        "{} meshes × {} models ({}), on {}",
        mine.len(),
        models.len(),
        options
            .iter()
            .map(|o| format!("{} {}", o.model.label(), o.preset.name()))
            .collect::<Vec<_>>()
            .join(", "),
        gpu.describe()
    );

    let pairs = mine
        .iter()
        .flat_map(|m| options.iter().map(move |o| (*m, o)));
    for (mesh, options) in pairs {
        if stop.load(Ordering::Relaxed)
            || train_one(&gpu, &state, mesh, options, args, &stop)? == Trained::Interrupted
        {
            eprintln!("stopped; run the same command again to resume");
            return Ok(ExitCode::from(130));
        }
    }
    match shard {
        // No shard writes the table: the merge is its only writer.
        Some((s, _)) => {
            let m = corpus::merge(&state, &meshes, &models);
            eprintln!(
                "shard {s} finished; corpus: {}. Build the table with: corpus {} --merge --out {}",
                m.status(),
                source_arg(args),
                args.out.display()
            );
            Ok(ExitCode::SUCCESS)
        }
        None => merge(args, &state, &meshes, &models),
    }
}

/// The models the results folder has settings for, in the usual order; SIREN and NGLOD where it
/// has none yet (or they cannot be read: the merge then warns).
fn recorded_models(state: &StateDir) -> Vec<ModelKind> {
    let recorded = state.read_settings().ok().flatten().map(|s| s.models);
    match recorded {
        Some(names) if !names.is_empty() => ModelKind::ALL
            .into_iter()
            .filter(|m| names.contains_key(m.name()))
            .collect(),
        _ => vec![ModelKind::Siren, ModelKind::Nglod],
    }
}

/// Every model's options (their presets resolved), with their settings checked against those
/// the results folder was made with (and recorded there by its first run), before any mesh is
/// trained.
fn claim(
    state: &StateDir,
    eval_points: usize,
    options: Vec<TrainOptions>,
    cpu_adapter: bool,
) -> Result<Vec<TrainOptions>, BoxError> {
    let mut settings = CorpusSettings {
        eval_points,
        ..Default::default()
    };
    for o in &options {
        settings
            .models
            .insert(o.model.name().to_owned(), o.settings(cpu_adapter)?);
    }
    state.claim(&settings)?;
    Ok(options)
}

/// How one mesh's run ended, as far as the corpus goes on.
#[derive(PartialEq, Eq)]
enum Trained {
    /// Done, done earlier, or failed (and recorded): the next one follows.
    Recorded,
    /// Stopped by a signal; its checkpoint is written.
    Interrupted,
}

/// Trains, evaluates and records one mesh with one model's `options`, unless its result is
/// there already; resumes from its checkpoint where one of the same settings is.
fn train_one(
    gpu: &GpuContext,
    state: &StateDir,
    mesh: &CorpusMesh,
    options: &TrainOptions,
    args: &Args,
    stop: &Arc<AtomicBool>,
) -> Result<Trained, BoxError> {
    let model = options.model;
    let (rel, tag) = (&mesh.rel, model.name());
    match state.read(rel, model) {
        Record::Entry(Entry::Done(_)) => {
            eprintln!("{rel} {tag}: done earlier, skipped");
            return Ok(Trained::Recorded);
        }
        Record::Corrupt(why) => {
            eprintln!(
                "warning: ignoring a result that does not parse ({why}); {rel} {tag} is redone"
            )
        }
        Record::Unreadable(why) => {
            // An I/O error, not a broken file: the result may be there, and a retraining that
            // failed would replace it with a failure.
            eprintln!("warning: cannot read {rel} {tag}'s result ({why}); not redone in this run");
            return Ok(Trained::Recorded);
        }
        Record::Missing | Record::Entry(Entry::Failed { .. }) => {}
    }
    let checkpoint_path = state.checkpoint(rel, model);
    let checkpoint = resumable(&checkpoint_path, options, rel, tag);
    eprintln!("{rel} {tag}: training");
    let outcome = run::run(
        gpu,
        &mesh.path,
        options,
        args.ground_truth.device(),
        &state.model_file(rel, model),
        args.training.eval_points,
        checkpoint.as_ref(),
        stop,
        |_| {},
    );
    let entry = match outcome {
        Ok(RunOutcome::Interrupted(trained)) => {
            trained.checkpoint().save(&checkpoint_path)?;
            eprintln!(
                "{rel} {tag}: interrupted after {}; checkpoint written to {}",
                trained.done,
                checkpoint_path.display()
            );
            return Ok(Trained::Interrupted);
        }
        Ok(RunOutcome::Finished(report, _)) => {
            eprintln!(
                "{rel} {tag}: F1 box {}, near {} ({}), {:.0} s (ground truth on the {})",
                corpus::f1_cell(report.f1_bbox),
                corpus::f1_cell(report.f1_near_surface),
                report.ambiguity_summary(),
                report.train_seconds,
                report
                    .ground_truth
                    .map_or("CPU".to_owned(), |p| p.name().to_uppercase())
            );
            Entry::Done(report)
        }
        Err(e) => {
            eprintln!("{rel} {tag}: failed: {e}");
            Entry::Failed {
                mesh: mesh.path.display().to_string(),
                model: tag.into(),
                error: e.to_string(),
            }
        }
    };
    let done = matches!(entry, Entry::Done(_));
    state.write(rel, model, &entry)?;
    if checkpoint_path.exists() {
        if done {
            // The result supersedes the checkpoint it was resumed from.
            let _ = std::fs::remove_file(&checkpoint_path);
        } else {
            // A failure (a full disk, a lost device) must not cost the training done.
            eprintln!(
                "{rel} {tag}: its checkpoint {} is kept for the next run",
                checkpoint_path.display()
            );
        }
    }
    Ok(Trained::Recorded)
}

/// The checkpoint at `path` if a run of `options` may resume it; else (none, unreadable, or
/// of other settings, which would put a fit of those in this table) `None`, with a warning.
fn resumable(path: &Path, options: &TrainOptions, rel: &str, tag: &str) -> Option<Checkpoint> {
    if !path.exists() {
        return None;
    }
    match Checkpoint::load(path).and_then(|c| Ok((c.differences(options)?, c))) {
        Ok((differences, _)) if !differences.is_empty() => {
            eprintln!(
                "warning: {rel} {tag}: its checkpoint has other settings ({}); starting over",
                differences.join("; ")
            );
            None
        }
        Ok((_, c)) => {
            eprintln!(
                "{rel} {tag}: resuming from its checkpoint ({} done)",
                c.done()
            );
            Some(c)
        }
        Err(e) => {
            eprintln!("warning: {rel} {tag}: unusable checkpoint ({e}); starting over");
            None
        }
    }
}

fn source_arg(args: &Args) -> String {
    match (&args.list, &args.dir) {
        (Some(list), _) => format!("--list {}", list.display()),
        (None, Some(dir)) => dir.display().to_string(),
        (None, None) => String::new(),
    }
}

/// Builds the table from `<out>.d/`, writes it and prints it with the progress.
fn merge(
    args: &Args,
    state: &StateDir,
    meshes: &[CorpusMesh],
    models: &[ModelKind],
) -> Result<ExitCode, BoxError> {
    let m = corpus::merge(state, meshes, models);
    for why in &m.corrupt {
        eprintln!(
            "warning: ignoring a result that does not parse ({why}); its mesh will be redone"
        );
    }
    for why in &m.unreadable {
        eprintln!("warning: cannot read a result ({why}); left out of the table");
    }
    if let Err(e) = &m.settings {
        eprintln!("warning: {e}; the table does not state its settings");
    }
    let table = m.markdown();
    write_atomic(&args.out, table.as_bytes())
        .map_err(|e| format!("{}: {e}", args.out.display()))?;
    print!("{table}");
    eprintln!("{}", m.status());
    for (rel, model, error) in m.failed() {
        eprintln!("  failed: {rel} {model}: {error}");
    }
    eprintln!("table written to {}", args.out.display());
    // A table with some failed rows is a result; a finished one in which every run failed is
    // not, and a script running `corpus && …` must be able to tell.
    if m.complete() && m.done() == 0 && !m.failed().is_empty() {
        eprintln!("error: every run failed; the table lists why");
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}
