//! One experiment, as `train` and `corpus` run it: load and normalise a mesh, train a model on
//! the GPU, save it, evaluate it (F1, distance error, latency, storage) and write a JSON report.
//!
//! - [`options`](TrainOptions): what a run is asked for, its validation and its defaults;
//! - [`GroundTruth`]: the normalised mesh and its exact SDF;
//! - [`train`]: one trainer per model family (`train_siren`; `train_nglod`, which trains NGLOD
//!   and the hash grid), stopped and resumed through a [`Checkpoint`];
//! - [`evaluate`] and [`Report`]: the scores and the JSON report;
//! - [`run`]: all of it for one mesh.

mod checkpoint;
mod evaluate;
mod ground_truth;
mod options;
mod report;
mod train_nglod;
mod train_siren;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use glam::Vec3;
use sdf_nn::nglod::TimeBudget;
use sdf_nn::{AdamState, GpuContext, GroundTruthDevice, ModelFile, NeuralSdf};

pub use checkpoint::{Checkpoint, MAX_CHECKPOINT_PROGRESS};
pub use evaluate::{
    EVAL_BYTES_PER_POINT, EVAL_MEMORY_BUDGET, Evaluation, UNSIGNED_EXTRACT_RESOLUTION,
    UNSIGNED_LEVEL, check_eval_points, evaluate, evaluate_scores, extract_mesh,
    extract_mesh_normalized, extract_mesh_with, extract_scene_mesh, finite_values, is_unsigned,
};
pub use ground_truth::{
    GroundTruth, duration, estimate_line, labelling_estimate, load_normalized,
    load_normalized_with, no_inside_check, planned_labels,
};
pub use options::{
    CPU_TIME_BUDGET, HASHGRID_CPU_TIME_BUDGET, Length, MAX_BATCH, MAX_EPOCHS, MAX_STEPS, ModelKind,
    NglodArchitecture, Preset, RunSettings, TrainOptions, cpu_time_budget, default_length,
};
pub use report::Report;

/// Errors of a run. Each names what failed so a corpus run can record it and go on.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The mesh could not be loaded or used.
    #[error("mesh {path}: {source}")]
    Mesh {
        /// The mesh file.
        path: PathBuf,
        /// Why.
        source: sdf_geom::GeomError,
    },
    /// SIREN training failed.
    #[error("SIREN training: {0}")]
    Siren(#[from] sdf_nn::siren::TrainError),
    /// NGLOD training failed.
    #[error("NGLOD: {0}")]
    Nglod(#[from] sdf_nn::NglodError),
    /// The hash grid's configuration or training failed (NGLOD's code, under the model's own
    /// name: [`grid_error`]).
    #[error("hash grid: {0}")]
    Hashgrid(sdf_nn::NglodError),
    /// Building or evaluating the trained model failed.
    #[error(transparent)]
    Model(#[from] sdf_nn::NeuralSdfError),
    /// A model file could not be written or read.
    #[error(transparent)]
    ModelFile(#[from] sdf_nn::ModelFileError),
    /// A scene could not be compiled or queried on the GPU.
    #[error(transparent)]
    Scene(#[from] sdf_nn::serve::scene::SceneGpuError),
    /// The report could not be written.
    #[error("writing {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Options that cannot work together.
    #[error("{0}")]
    Options(String),
    /// Training produced a NaN or infinite weight. Nothing is saved: a checkpoint resumed from
    /// stays as it was, the last good state.
    #[error(
        "training diverged: after {done} {unit}s, value {index} of `{tensor}` is {value}; nothing was saved (try a lower learning rate or smaller loss weights)"
    )]
    Diverged {
        /// Steps or epochs done.
        done: usize,
        /// `"step"` or `"epoch"`.
        unit: &'static str,
        /// The first tensor with a bad value.
        tensor: String,
        /// Index of the value.
        index: usize,
        /// The value.
        value: f32,
    },
    /// The request would need more memory than the budget; refused before any work.
    #[error(
        "{what} would need about {:.1} GiB of memory, over the {:.1} GiB budget; {hint}",
        *.need as f64 / GIB, *.budget as f64 / GIB
    )]
    OverBudget {
        /// What was asked.
        what: String,
        /// Estimated bytes.
        need: u64,
        /// The budget in bytes.
        budget: u64,
        /// What to do instead.
        hint: String,
    },
    /// The model evaluates to NaN or ∞ somewhere (weights that overflow f32 in the sums):
    /// nothing it predicts can be scored or shown.
    #[error(
        "the model evaluates to {value} at {point} (normalised coordinates): it does not give finite distances, so it cannot be scored"
    )]
    NonFiniteModel {
        /// The first point with a non-finite value.
        point: Vec3,
        /// Its value.
        value: f32,
    },
    /// Labelling on the GPU failed, or the mesh does not fit it (`--ground-truth gpu`).
    #[error("ground truth: {0}")]
    GroundTruth(#[from] sdf_nn::GroundTruthError),
    /// `--distance unsigned` with SIREN, whose loss (eikonal, normal alignment, the off-surface
    /// term pushing |Φ| up away from the surface) assumes a signed field.
    #[error(
        "unsigned distance is supported for NGLOD and the hash grid only: SIREN's loss \
         (normals, eikonal and off-surface terms) fits a signed field; use --model nglod or \
         --model hashgrid"
    )]
    UnsignedSiren,
}

const GIB: f64 = (1u64 << 30) as f64;

/// An error of NGLOD's code in a run of `model`, named after the model: [`RunError::Hashgrid`]
/// for the hash grid, [`RunError::Nglod`] otherwise.
pub fn grid_error(model: ModelKind, e: sdf_nn::NglodError) -> RunError {
    match model {
        ModelKind::Hashgrid => RunError::Hashgrid(e),
        _ => RunError::Nglod(e),
    }
}

/// Errors with [`RunError::Diverged`] on the first NaN or infinite value of a trained model.
fn check_trained(file: &ModelFile, done: usize, unit: &'static str) -> Result<(), RunError> {
    match file.check_finite() {
        Err(sdf_nn::ModelFileError::NonFinite {
            name, index, value, ..
        }) => Err(RunError::Diverged {
            done,
            unit,
            tensor: name,
            index,
            value,
        }),
        other => Ok(other?),
    }
}

/// Progress of a training run, for progress bars and logs.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    /// Steps (SIREN) or epochs (NGLOD, the hash grid) done.
    pub done: usize,
    /// Total planned.
    pub total: usize,
    /// `"step"` or `"epoch"`.
    pub unit: &'static str,
    /// Latest loss.
    pub loss: f32,
    /// Current learning rate.
    pub lr: f32,
    /// Training points processed per second so far.
    pub points_per_second: f64,
}

/// A trained model and what training cost.
#[derive(Clone, Debug)]
pub struct Trained {
    /// The model file contents.
    pub file: ModelFile,
    /// Wall time of training: sampling, the trainer's setup and its steps or epochs, not the
    /// ground truth's BVH (built before, [`GroundTruth`]; reports before it included one).
    /// A resumed run adds the seconds its checkpoint records (`train_seconds` in its run
    /// record; checkpoints from before 2026-11-28 have none, and count as 0).
    pub train_seconds: f64,
    /// Steps or epochs done.
    pub done: usize,
    /// Final loss.
    pub final_loss: f32,
    /// Whether training stopped early (Ctrl-C).
    pub interrupted: bool,
    /// Extra training figures (NGLOD's GPU/sampling split).
    pub details: serde_json::Value,
    /// Optimiser state at the end, for checkpoints.
    pub optimizer: AdamState,
    /// Learning rate at the end.
    pub lr: f32,
}

/// What both trainers get: the run's inputs and the length it plans, settled by [`train`].
struct Plan<'a> {
    gpu: &'a GpuContext,
    truth: &'a GroundTruth<'a>,
    normalization: sdf_geom::Normalization,
    options: &'a TrainOptions,
    resume: Option<&'a Checkpoint>,
    stop: &'a Arc<AtomicBool>,
    /// Steps or epochs to reach in all (counted from the start of the first run).
    total: usize,
    /// NGLOD's default on a CPU adapter plans from its first epochs instead (`total` is then
    /// the least it runs).
    time_budget: Option<TimeBudget>,
    start: Instant,
}

impl Plan<'_> {
    /// The run's own record for the model file: model, preset, seed, progress, final loss.
    fn training_json(&self, done: usize, loss: f32) -> serde_json::Value {
        serde_json::json!({
            "model": self.options.model.name(),
            "preset": self.options.preset.name(),
            "seed": self.options.seed,
            "done": done,
            "final_loss": loss,
            "train_seconds": self.train_seconds(),
        })
    }

    /// Seconds of training so far: this run's, and those of the runs its checkpoint continues.
    fn train_seconds(&self) -> f64 {
        let earlier = self.resume.map_or(0.0, Checkpoint::train_seconds);
        earlier + self.start.elapsed().as_secs_f64()
    }

    /// Training points per second since the start, `units` steps or epochs of `per_unit` points
    /// each having run.
    fn points_per_second(&self, units: usize, per_unit: f64) -> f64 {
        units as f64 * per_unit / self.start.elapsed().as_secs_f64().max(1e-9)
    }
}

/// Trains `options.model` on a normalised mesh and its ground truth. `stop` is polled between
/// steps or epochs: when it is set the run ends early and what was learnt so far is returned.
pub fn train(
    gpu: &GpuContext,
    truth: &GroundTruth,
    normalization: sdf_geom::Normalization,
    options: &TrainOptions,
    resume: Option<&Checkpoint>,
    stop: &Arc<AtomicBool>,
    progress: impl FnMut(&Progress),
) -> Result<Trained, RunError> {
    if let Some(c) = resume {
        c.check_resumes(options)?;
    }
    // Callers of the library may build options by hand; the binaries' were validated when
    // their flags were read, and this is the same check.
    options.validate()?;
    let start = Instant::now();
    let length = options.length(gpu.is_cpu());
    if let (Some(c), Some(asked)) = (resume, length.asked)
        && asked < c.done()
    {
        return Err(c.refusal(format!(
            "the checkpoint has done {} {}s already, more than the {asked} asked for: \
             ask for more, or leave the length out to finish the run it planned",
            c.done(),
            options.model.unit()
        )));
    }
    let plan = Plan {
        gpu,
        truth,
        normalization,
        options,
        resume,
        stop,
        // A resumed run goes on to the length its first run planned.
        total: length
            .asked
            .or_else(|| resume.and_then(Checkpoint::planned))
            .unwrap_or(length.default),
        time_budget: resumed_budget(length.time_budget, resume),
        start,
    };
    match options.model {
        ModelKind::Siren => train_siren::train(&plan, progress),
        ModelKind::Nglod | ModelKind::Hashgrid => train_nglod::train(&plan, progress),
    }
}

/// The time budget of a run whose fresh form has `budget`: a resume keeps it only where its
/// checkpoint's run stopped before the budget planned the length ([`Checkpoint::plan_pending`]),
/// less the seconds of it spent ([`Checkpoint::budget_seconds`]); any other resume goes on to
/// the length its run planned.
fn resumed_budget(budget: Option<TimeBudget>, resume: Option<&Checkpoint>) -> Option<TimeBudget> {
    match resume {
        None => budget,
        Some(c) if c.plan_pending() => budget.map(|b| TimeBudget {
            seconds: (b.seconds - c.budget_seconds()).max(0.0),
            ..b
        }),
        Some(_) => None,
    }
}

/// A trainer's record for the model file (its configuration: learning rate, loss weights, batch,
/// ...) with the run's own record (model, preset, seed, steps done, final loss) added over it.
fn with_run_record(trainer: serde_json::Value, run: serde_json::Value) -> serde_json::Value {
    match (trainer, run) {
        (serde_json::Value::Object(mut t), serde_json::Value::Object(r)) => {
            t.extend(r);
            serde_json::Value::Object(t)
        }
        (_, run) => run,
    }
}

/// How [`run`] ended.
#[derive(Debug)]
pub enum RunOutcome {
    /// Trained to the end, saved, evaluated.
    Finished(Box<Report>, Box<Trained>),
    /// The stop flag ended training early: nothing was saved or evaluated, and
    /// [`Trained::checkpoint`] continues it.
    Interrupted(Box<Trained>),
}

/// The whole experiment for one mesh: train (from `resume` if given), save to `out`, evaluate,
/// report. The samples' and the evaluation's labels come from `ground_truth`'s path
/// ([`GroundTruth::on`]); a fallback of `auto` to the CPU is printed as a warning. A `resume`
/// of another mesh (the file changed since the checkpoint was written: its normalisation
/// differs) is set aside with a warning and training starts over: a corpus rerun would
/// otherwise fail on that mesh every time.
#[allow(clippy::too_many_arguments)]
pub fn run(
    gpu: &GpuContext,
    mesh_path: &Path,
    options: &TrainOptions,
    ground_truth: GroundTruthDevice,
    out: &Path,
    eval_points: usize,
    resume: Option<&Checkpoint>,
    stop: &Arc<AtomicBool>,
    progress: impl FnMut(&Progress),
) -> Result<RunOutcome, RunError> {
    // Before the training it would follow.
    check_eval_points(eval_points)?;
    let (mesh, normalization) = load_normalized(mesh_path)?;
    let truth = GroundTruth::on(gpu, mesh, mesh_path, ground_truth)?;
    if let Some(why) = truth.labels.fallback() {
        eprintln!("warning: {}: {why}", mesh_path.display());
    }
    let resume = resume.filter(|c| match c.check_mesh(normalization) {
        Ok(()) => true,
        Err(e) => {
            eprintln!("warning: {e}; starting over");
            false
        }
    });
    let trained = train(gpu, &truth, normalization, options, resume, stop, progress)?;
    if trained.interrupted {
        return Ok(RunOutcome::Interrupted(Box::new(trained)));
    }
    trained.file.save(out)?;
    let file_bytes = std::fs::metadata(out)
        .map_err(|source| RunError::Write {
            path: out.to_owned(),
            source,
        })?
        .len();
    let model = NeuralSdf::from_model_file(trained.file.clone())?;
    let eval = evaluate(gpu, &model, &truth, eval_points)?;
    let report = Report::new(
        mesh_path,
        options,
        &trained,
        file_bytes,
        &eval,
        gpu.describe(),
        truth.labels.path(),
    );
    Ok(RunOutcome::Finished(Box::new(report), Box::new(trained)))
}
