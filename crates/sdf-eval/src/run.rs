//! One experiment, as `train` and `corpus` run it: load and normalise a mesh, train a model on
//! the GPU, save it, evaluate it (F1, distance error, latency, storage) and write a JSON report.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::Vec3;
use sdf_geom::extract::{ExtractError, ExtractOptions, ExtractStats, extract_surface};
use sdf_geom::{Mesh, SignedDistance};
use sdf_nn::model_file::write_atomic;
use sdf_nn::{
    AdamState, DistanceMode, GpuContext, LossWeights, ModelFile, NeuralSdf, Nglod, NglodConfig,
    NglodTrainConfig, NglodTrainer, Siren, SirenConfig, SirenTrainConfig, SirenTrainer,
};
use serde::{Deserialize, Serialize};

use crate::metrics::{EVAL_SEED, EvalSets, Scores};
use crate::timing::{Latency, MEASURE_FOR, WARM_UP, measure_latency_timed};

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
    /// Building or evaluating the trained model failed.
    #[error(transparent)]
    Model(#[from] sdf_nn::NeuralSdfError),
    /// A model file could not be written or read.
    #[error(transparent)]
    ModelFile(#[from] sdf_nn::ModelFileError),
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
    /// `--distance unsigned` with SIREN, whose loss (eikonal, normal alignment, the off-surface
    /// term pushing |Φ| up away from the surface) assumes a signed field.
    #[error(
        "unsigned distance is supported for NGLOD only: SIREN's loss (normals, eikonal and \
         off-surface terms) fits a signed field; use --model nglod"
    )]
    UnsignedSiren,
}

const GIB: f64 = (1u64 << 30) as f64;

/// The most SIREN steps a run may ask for: a thousand times the default (about 4.5 hours on
/// an H100), so that a mistyped length is refused instead of running for ever.
pub const MAX_STEPS: usize = 10_000_000;

/// The most NGLOD epochs a run may ask for: a thousand times the default (about 2 hours on an
/// H100).
pub const MAX_EPOCHS: usize = 100_000;

/// Memory an evaluation holds per point of `--points` / `--eval-points`, in bytes: the two sets'
/// points and truths, the Poisson-disk candidates of the near-surface set, predictions, and the
/// GPU's buffers (host memory on a CPU adapter). Measured with `eval --surface-resolution 0` on
/// lavapipe: peak RSS 295 MB at 2·10^5 points and 1168 MB at 10^6, 1.09 kB per point; rounded up.
pub const EVAL_BYTES_PER_POINT: u64 = 1200;

/// Memory budget of one evaluation, in bytes (4 GiB).
pub const EVAL_MEMORY_BUDGET: u64 = 4 << 30;

/// Refuses, before any work, an evaluation whose sets would pass [`EVAL_MEMORY_BUDGET`], with
/// the estimate.
pub fn check_eval_points(points: usize) -> Result<(), RunError> {
    let need = (points as u64).saturating_mul(EVAL_BYTES_PER_POINT);
    if need > EVAL_MEMORY_BUDGET {
        return Err(RunError::OverBudget {
            what: format!("evaluating on {points} points per set"),
            need,
            budget: EVAL_MEMORY_BUDGET,
            hint: format!(
                "use at most {} points",
                EVAL_MEMORY_BUDGET / EVAL_BYTES_PER_POINT
            ),
        });
    }
    Ok(())
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

/// Which architecture to train.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// SIREN.
    Siren,
    /// NGLOD.
    Nglod,
}

impl ModelKind {
    /// `"siren"` or `"nglod"`.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Siren => "siren",
            ModelKind::Nglod => "nglod",
        }
    }
}

/// Size preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// The design document's architecture (for NGLOD with a sparse fourth level near the surface:
    /// `NglodConfig::default_preset`).
    Default,
    /// A small network for CPU-only machines and tests.
    Small,
}

impl Preset {
    /// The preset used when none is asked for: `small` on a CPU adapter (lavapipe), where the
    /// design document's networks train too slowly, `default` on a GPU.
    /// NGLOD: `default` everywhere (`small` is capacity-bound and no longer saves time on
    /// lavapipe: issue 14, BENCHMARKS.md). SIREN: `small` on a CPU adapter, `default` on a GPU.
    pub fn for_adapter(cpu_adapter: bool, model: ModelKind) -> Self {
        if cpu_adapter && model == ModelKind::Siren {
            Preset::Small
        } else {
            Preset::Default
        }
    }

    /// `"default"` or `"small"`.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Default => "default",
            Preset::Small => "small",
        }
    }
}

/// What to train and for how long.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Architecture.
    pub model: ModelKind,
    /// Size preset.
    pub preset: Preset,
    /// SIREN steps (`None`: the preset's default for the adapter).
    pub steps: Option<usize>,
    /// NGLOD epochs (`None`: the preset's default for the adapter).
    pub epochs: Option<usize>,
    /// Seed of initialisation and sampling.
    pub seed: u64,
    /// Initial learning rate (`None`: the model's default, 1e-4 for SIREN and 1e-3 for NGLOD).
    pub lr: Option<f32>,
    /// SIREN loss weights (`None`: the design document's). An error for NGLOD.
    pub siren_weights: Option<LossWeights>,
    /// SIREN: steps without progress of the loss before the learning rate is divided by 10
    /// (`None`: the trainer's 500; 0 keeps it constant). An error for NGLOD.
    pub plateau_patience: Option<usize>,
    /// NGLOD: final learning rate as a fraction of the first, reached by cosine decay (`None`:
    /// the trainer's default; 1 keeps it constant).
    pub lr_final: Option<f32>,
    /// NGLOD: add a level of detail every this many epochs (`None`: the trainer's default; 0
    /// trains all levels from the start).
    pub grow_every: Option<usize>,
    /// Signed or unsigned distance (unsigned: NGLOD only).
    pub distance: DistanceMode,
    /// NGLOD sample pool: `(blocks, refresh_every)` (`None`: the trainer's default; `(1, 1)`
    /// draws fresh points every epoch as before the pool).
    pub pool: Option<(usize, usize)>,
    /// NGLOD: an architecture other than the preset's (each value given replaces the preset's).
    /// An error for SIREN unless empty.
    pub nglod_architecture: NglodArchitecture,
}

impl TrainOptions {
    /// A run of `model` over `preset` with every other option at its default (seed 0).
    pub fn new(model: ModelKind, preset: Preset) -> Self {
        TrainOptions {
            model,
            preset,
            steps: None,
            epochs: None,
            seed: 0,
            lr: None,
            siren_weights: None,
            plateau_patience: None,
            lr_final: None,
            grow_every: None,
            distance: DistanceMode::Signed,
            pool: None,
            nglod_architecture: NglodArchitecture::default(),
        }
    }

    /// Checks what can be checked without a mesh or a GPU, so that a bad option is a typed error
    /// before any work: lengths of at least 1, every option given to the model it applies to, a
    /// usable learning rate, final ratio, loss weights and NGLOD architecture. [`train`] runs it
    /// too.
    pub fn validate(&self) -> Result<(), RunError> {
        let refuse = |why: &str| Err(RunError::Options(why.to_owned()));
        if self.steps == Some(0) || self.epochs == Some(0) {
            return refuse("--steps and --epochs must be at least 1");
        }
        if self.steps.is_some_and(|s| s > MAX_STEPS) || self.epochs.is_some_and(|e| e > MAX_EPOCHS)
        {
            return Err(RunError::Options(format!(
                "--steps is at most {MAX_STEPS} and --epochs at most {MAX_EPOCHS} (a thousand \
                 times the defaults: hours on a GPU)"
            )));
        }
        match self.model {
            ModelKind::Siren => {
                if self.epochs.is_some() {
                    return refuse("--epochs applies to NGLOD; SIREN trains for --steps");
                }
                if self.distance == DistanceMode::Unsigned {
                    return Err(RunError::UnsignedSiren);
                }
                if self.lr_final.is_some() || self.grow_every.is_some() || self.pool.is_some() {
                    return refuse(
                        "--lr-final, --grow-every and --pool apply to NGLOD; SIREN samples its \
                         batch every step and divides its learning rate by 10 when its loss \
                         plateaus (--plateau-patience)",
                    );
                }
                if let Some(w) = self.siren_weights {
                    w.validate()?;
                }
            }
            ModelKind::Nglod => {
                if self.steps.is_some() {
                    return refuse("--steps applies to SIREN; NGLOD trains for --epochs");
                }
                if self.siren_weights.is_some() {
                    return refuse(
                        "loss weights apply to SIREN; NGLOD's loss is the squared error",
                    );
                }
                if self.plateau_patience.is_some() {
                    return refuse(
                        "--plateau-patience applies to SIREN; NGLOD's learning rate decays \
                         along a cosine (--lr-final)",
                    );
                }
                if let Some(f) = self.lr_final
                    && !(f.is_finite() && f >= 0.0)
                {
                    return Err(RunError::Options(format!(
                        "--lr-final must be finite and non-negative, not {f}"
                    )));
                }
                if matches!(self.pool, Some((0, _) | (_, 0))) {
                    return refuse("--pool takes two positive integers, BLOCKS,EVERY");
                }
            }
        }
        if let Some(lr) = self.lr {
            sdf_nn::AdamConfig::check_lr(lr).map_err(RunError::Options)?;
        }
        self.nglod_architecture.check(self.model, self.preset)
    }

    /// What this run asks for, as `name → value` with every default resolved to what it stands
    /// for, so that two runs that train alike have equal settings however their options were
    /// spelt (`--epochs 100` on a GPU and no `--epochs` there are the same run). The length
    /// defaults depend on the adapter, hence `cpu_adapter`. A corpus run keeps these beside its
    /// results and refuses to mix results of other settings into one table.
    pub fn settings(&self, cpu_adapter: bool) -> Result<RunSettings, RunError> {
        self.validate()?;
        let mut s = BTreeMap::new();
        let mut put = |k: &str, v: String| s.insert(k.to_owned(), v);
        put("preset", self.preset.name().to_owned());
        put("seed", self.seed.to_string());
        let asked = match self.model {
            ModelKind::Siren => self.steps,
            ModelKind::Nglod => self.epochs,
        };
        let length = match asked {
            Some(n) => n.to_string(),
            None if self.model == ModelKind::Nglod && cpu_adapter => format!(
                "about {} s of training ({} to {})",
                CPU_TIME_BUDGET.seconds,
                default_length(self.model, self.preset, true),
                CPU_TIME_BUDGET.max_epochs
            ),
            None => default_length(self.model, self.preset, cpu_adapter).to_string(),
        };
        match self.model {
            ModelKind::Siren => {
                let d = SirenTrainConfig::default();
                let w = self.siren_weights.unwrap_or(d.weights);
                put("steps", length);
                put("lr", self.lr.unwrap_or(d.lr).to_string());
                put(
                    "plateau patience",
                    self.plateau_patience
                        .unwrap_or(d.plateau_patience)
                        .to_string(),
                );
                put(
                    "loss weights",
                    format!(
                        "surface {}, off-surface {}, normal {}, eikonal {}, alpha {}, sign {}",
                        w.surface, w.off_surface, w.normal, w.eikonal, w.alpha, w.sign
                    ),
                );
            }
            ModelKind::Nglod => {
                let d = NglodTrainConfig::default();
                let c = self.nglod_architecture.config(self.preset, self.seed)?;
                put("epochs", length);
                put("lr", self.lr.unwrap_or(d.adam.lr).to_string());
                let lr_final = self.lr_final.or(d.lr_final).unwrap_or(1.0);
                put("lr final", lr_final.to_string());
                let grow = self.grow_every.or(d.grow_every).unwrap_or(0);
                put("grow every", grow.to_string());
                let (blocks, every) = self.pool.unwrap_or((d.pool_blocks, d.refresh_every));
                put("pool", format!("{blocks},{every}"));
                put("distance", self.distance.name().to_owned());
                put(
                    "architecture",
                    format!(
                        "resolutions {}, sparse levels {}, band cells {}, features {}, hidden {}",
                        comma_list(&c.resolutions),
                        c.sparse_levels,
                        c.band_cells,
                        c.feature_dim,
                        c.hidden
                    ),
                );
            }
        }
        Ok(RunSettings(s))
    }
}

/// What a run asks for: [`TrainOptions::settings`].
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct RunSettings(pub BTreeMap<String, String>);

impl RunSettings {
    /// The settings these have that `recorded` has otherwise, as `name value, not recorded`
    /// lines (empty when they agree; a name only one side has counts too).
    pub fn differences(&self, recorded: &RunSettings) -> Vec<String> {
        let names: BTreeSet<&String> = self.0.keys().chain(recorded.0.keys()).collect();
        names
            .into_iter()
            .filter_map(|k| {
                let (a, r) = (self.0.get(k), recorded.0.get(k));
                let show = |v: Option<&String>| v.map_or("unset", String::as_str).to_owned();
                (a != r).then(|| format!("{k} {}, not {}", show(a), show(r)))
            })
            .collect()
    }
}

impl std::fmt::Display for RunSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let parts: Vec<String> = self.0.iter().map(|(k, v)| format!("{k} {v}")).collect();
        f.write_str(&parts.join("; "))
    }
}

/// Resolutions as the flags and the logs write them: `6,12,24,48`.
fn comma_list(resolutions: &[u32]) -> String {
    resolutions
        .iter()
        .map(u32::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// NGLOD architecture values over a preset (`train --resolutions --sparse-levels --band-cells
/// --features --hidden`): each one given replaces the preset's, the others stay. The result is
/// checked by [`NglodConfig::validate`], so a bad combination is a typed error before any work.
///
/// ```
/// use sdf_eval::run::{NglodArchitecture, Preset};
///
/// // Two sparse levels of 32 and 64 cells under dense ones of 8 and 16.
/// let fine = NglodArchitecture {
///     resolutions: Some(vec![8, 16, 32, 64]),
///     sparse_levels: Some(2),
///     ..Default::default()
/// };
/// let config = fine.config(Preset::Default, 0).unwrap();
/// assert_eq!((config.feature_dim, config.hidden), (8, 128)); // the preset's
/// ```
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct NglodArchitecture {
    /// Cells per axis of each level of detail, coarse to fine.
    pub resolutions: Option<Vec<u32>>,
    /// How many of the finest levels keep features only near the surface.
    pub sparse_levels: Option<usize>,
    /// Features per grid vertex, F.
    pub feature_dim: Option<u32>,
    /// Hidden width of the MLP, H.
    pub hidden: Option<u32>,
    /// How far sparse levels reach beyond the cells the surface passes through, in cells.
    pub band_cells: Option<u32>,
}

impl NglodArchitecture {
    /// Whether no value is given (the preset's architecture).
    pub fn is_preset(&self) -> bool {
        *self == Self::default()
    }

    /// Checks these values for a run of `model` over `preset`: for SIREN none may be given, for
    /// NGLOD the configuration they make must be valid.
    pub fn check(&self, model: ModelKind, preset: Preset) -> Result<(), RunError> {
        match model {
            ModelKind::Siren if !self.is_preset() => Err(RunError::Options(
                "--resolutions, --sparse-levels, --band-cells, --features and --hidden set \
                 NGLOD's architecture; SIREN's comes from its preset"
                    .into(),
            )),
            ModelKind::Siren => Ok(()),
            ModelKind::Nglod => self.config(preset, 0).map(drop),
        }
    }

    /// The preset's configuration with these values over it, seeded and validated.
    pub fn config(&self, preset: Preset, seed: u64) -> Result<NglodConfig, RunError> {
        let base = match preset {
            Preset::Default => NglodConfig::default_preset(),
            Preset::Small => NglodConfig::small(),
        };
        let config = NglodConfig {
            resolutions: self.resolutions.clone().unwrap_or(base.resolutions),
            sparse_levels: self.sparse_levels.unwrap_or(base.sparse_levels),
            feature_dim: self.feature_dim.unwrap_or(base.feature_dim),
            hidden: self.hidden.unwrap_or(base.hidden),
            seed,
            band_cells: self.band_cells.unwrap_or(base.band_cells),
        };
        config.validate()?;
        Ok(config)
    }

    /// The values given that `config` does not have, as `name: asked, config's` lines (empty
    /// when it agrees with every value given).
    pub fn differences(&self, config: &NglodConfig) -> Vec<String> {
        let mut out = Vec::new();
        let mut check = |name: &str, asked: Option<String>, has: String| {
            if let Some(a) = asked.filter(|a| *a != has) {
                out.push(format!("{name} {a}, not {has}"));
            }
        };
        check(
            "resolutions",
            self.resolutions.as_deref().map(comma_list),
            comma_list(&config.resolutions),
        );
        check(
            "sparse levels",
            self.sparse_levels.map(|s| s.to_string()),
            config.sparse_levels.to_string(),
        );
        check(
            "features",
            self.feature_dim.map(|f| f.to_string()),
            config.feature_dim.to_string(),
        );
        check(
            "hidden",
            self.hidden.map(|h| h.to_string()),
            config.hidden.to_string(),
        );
        check(
            "band cells",
            self.band_cells.map(|b| b.to_string()),
            config.band_cells.to_string(),
        );
        out
    }
}

/// Progress of a training run, for progress bars and logs.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    /// Steps (SIREN) or epochs (NGLOD) done.
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

/// What an interrupted run saves: the model so far, the optimiser's moments and the progress
/// counters, in one model file (extra tensors `optimizer.m` and `optimizer.v`; metadata
/// `training.checkpoint = true`). `train --resume` continues from it.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    file: ModelFile,
    /// The file it was loaded from, which its refusals name.
    path: Option<std::path::PathBuf>,
}

impl Checkpoint {
    /// Reads a checkpoint, rejecting plain model files.
    pub fn load(path: &Path) -> Result<Self, RunError> {
        let file = ModelFile::load(path)?;
        if file.metadata.training.get("checkpoint") != Some(&serde_json::Value::Bool(true)) {
            return Err(RunError::Options(format!(
                "{} is a model file, not a checkpoint of an interrupted run",
                path.display()
            )));
        }
        let c = Checkpoint {
            file,
            path: Some(path.to_owned()),
        };
        // The hyperparameters it carries get the checks the command line's get.
        let bad = |e: String| RunError::Options(format!("checkpoint {}: {e}", path.display()));
        c.optimizer()?.validate().map_err(bad)?;
        if let Some(lr) = c.lr() {
            sdf_nn::AdamConfig::check_lr(lr).map_err(bad)?;
        }
        // Progress it claims: a resume must neither run for ever nor report an untrained model
        // as finished.
        let t = &c.file.metadata.training;
        for key in ["done", "planned", "epoch_steps_done"] {
            match &t[key] {
                serde_json::Value::Null => {}
                v if v.as_u64().is_some_and(|x| x <= MAX_CHECKPOINT_PROGRESS) => {}
                v => {
                    return Err(bad(format!(
                        "{key} is {v}, not a count of at most {MAX_CHECKPOINT_PROGRESS}"
                    )));
                }
            }
        }
        if let Some(planned) = c.planned()
            && c.done() > planned
        {
            return Err(bad(format!(
                "{} epochs done of {planned} planned",
                c.done()
            )));
        }
        Ok(c)
    }

    /// Writes the checkpoint atomically.
    pub fn save(&self, path: &Path) -> Result<(), RunError> {
        Ok(self.file.save(path)?)
    }

    /// The model part, as a plain model file.
    pub fn model_file(&self) -> ModelFile {
        let mut f = self.file.clone();
        f.tensors.retain(|t| !t.name.starts_with(OPTIMIZER_PREFIX));
        f
    }

    /// Steps or epochs done when it was written.
    pub fn done(&self) -> usize {
        self.file.metadata.training["done"].as_u64().unwrap_or(0) as usize
    }

    /// NGLOD: the epochs its run planned (with the CPU time budget, more than the default), which
    /// a resume without `--epochs` goes on to.
    pub fn planned(&self) -> Option<usize> {
        self.file.metadata.training["planned"]
            .as_u64()
            .map(|p| p as usize)
    }

    /// NGLOD: optimiser steps done within the unfinished epoch `done()`, which a resume finishes.
    pub fn epoch_steps_done(&self) -> usize {
        self.file.metadata.training["epoch_steps_done"]
            .as_u64()
            .unwrap_or(0) as usize
    }

    /// The optimiser's moments and step counter.
    pub fn optimizer(&self) -> Result<AdamState, RunError> {
        // The network's parameters, rebuilt from the file (which checks it): a tensor the
        // network does not read is no parameter, and the moments are checked against the real
        // count here, not first by the GPU.
        let n = NeuralSdf::from_model_file(self.model_file())?.param_count();
        let m = self.file.tensor("optimizer.m", &[n])?.to_vec();
        let v = self.file.tensor("optimizer.v", &[n])?.to_vec();
        let step = self.file.metadata.training["adam_step"]
            .as_u64()
            .and_then(|s| u32::try_from(s).ok())
            .ok_or_else(|| self.refusal("the checkpoint has no optimiser step count".into()))?;
        Ok(AdamState { m, v, step })
    }

    /// The learning rate when it was written (`None` if absent; a value that is not a number
    /// reads as NaN, which the checks refuse).
    pub fn lr(&self) -> Option<f32> {
        let v = &self.file.metadata.training["lr"];
        (!v.is_null()).then(|| v.as_f64().map_or(f32::NAN, |x| x as f32))
    }

    /// Errors unless this checkpoint is of a `model` model: the check a resume can make before
    /// the adapter (which may choose the preset) is open.
    pub fn check_model(&self, model: ModelKind) -> Result<(), RunError> {
        let has = self.options().0;
        if has.as_deref() == Some(model.name()) {
            return Ok(());
        }
        Err(self.refusal(format!(
            "the checkpoint is of a {} model, not {}",
            has.as_deref().unwrap_or("unknown"),
            model.name()
        )))
    }

    /// A refusal to resume from this checkpoint, naming its file where it was loaded from one.
    fn refusal(&self, why: String) -> RunError {
        RunError::Options(match &self.path {
            Some(path) => format!("{}: {why}", path.display()),
            None => why,
        })
    }

    /// What of `options`' model, preset and architecture this checkpoint does not have, as
    /// `name asked, not checkpoint's` lines (empty when a run of `options` may resume it). A
    /// NGLOD checkpoint must have every value of the architecture `options` resolve to, not only
    /// those given on the command line: `corpus` resumes into a table of one set of settings.
    pub fn differences(&self, options: &TrainOptions) -> Result<Vec<String>, RunError> {
        let mut out = Vec::new();
        let (model, preset) = self.options();
        for (name, asked, has) in [
            ("model", options.model.name(), model),
            ("preset", options.preset.name(), preset),
        ] {
            if has.as_deref() != Some(asked) {
                out.push(format!(
                    "{name} {asked}, not {}",
                    has.as_deref().unwrap_or("unknown")
                ));
            }
        }
        if out.is_empty() && options.model == ModelKind::Nglod {
            let resolved = options
                .nglod_architecture
                .config(options.preset, options.seed)?;
            let every = NglodArchitecture {
                resolutions: Some(resolved.resolutions),
                sparse_levels: Some(resolved.sparse_levels),
                feature_dim: Some(resolved.feature_dim),
                hidden: Some(resolved.hidden),
                band_cells: Some(resolved.band_cells),
            };
            let model = Nglod::from_model_file(&self.model_file())?;
            out.extend(every.differences(model.config()));
        }
        Ok(out)
    }

    /// Which architecture and preset it was trained with.
    pub fn options(&self) -> (Option<String>, Option<String>) {
        let t = &self.file.metadata.training;
        (
            t["model"].as_str().map(str::to_owned),
            t["preset"].as_str().map(str::to_owned),
        )
    }
}

const OPTIMIZER_PREFIX: &str = "optimizer.";

/// The most steps or epochs a checkpoint may claim done or planned.
pub const MAX_CHECKPOINT_PROGRESS: u64 = 1 << 30;

/// A trained model and what training cost.
#[derive(Clone, Debug)]
pub struct Trained {
    /// The model file contents.
    pub file: ModelFile,
    /// Wall time of training: sampling, the trainer's setup and its steps or epochs, not the
    /// ground truth's BVH (built before, [`GroundTruth`]; reports before it included one).
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

impl Trained {
    /// The checkpoint of this (interrupted) run: the model file with the optimiser's state. Like
    /// every model file it stores NGLOD's grid features as f16, so a resumed run continues from
    /// them rounded (by at most 2^-11 relative, far below one Adam step's change).
    pub fn checkpoint(&self) -> Checkpoint {
        let mut file = self.file.clone();
        let n = self.optimizer.m.len();
        for (name, data) in [
            ("optimizer.m", &self.optimizer.m),
            ("optimizer.v", &self.optimizer.v),
        ] {
            file.tensors
                .push(sdf_nn::model_file::Tensor::f32(name, vec![n], data.clone()));
        }
        let t = &mut file.metadata.training;
        t["checkpoint"] = true.into();
        t["adam_step"] = self.optimizer.step.into();
        t["lr"] = f64::from(self.lr).into();
        t["done"] = self.done.into();
        Checkpoint { file, path: None }
    }
}

/// NGLOD's default run on a CPU adapter: as many epochs as about a minute of training buys
/// there (issue 14: "the best fit that about a minute buys"), planned from the first epoch,
/// between [`default_length`]'s and 100. On the 2-core box that is ~13 epochs with Debian 12's
/// Mesa 22.3 and ~35 with Mesa 26.1 (BENCHMARKS.md).
pub const CPU_TIME_BUDGET: sdf_nn::nglod::TimeBudget = sdf_nn::nglod::TimeBudget {
    seconds: 55.0,
    max_epochs: 100,
};

/// Default SIREN steps and NGLOD epochs: what converges on a GPU for the design document's
/// presets, and a budget of a few minutes on a CPU adapter (lavapipe); for NGLOD there, the
/// least of [`CPU_TIME_BUDGET`].
pub fn default_length(model: ModelKind, preset: Preset, cpu_adapter: bool) -> usize {
    match (model, preset, cpu_adapter) {
        (ModelKind::Siren, _, false) => SirenTrainConfig::default().steps,
        (ModelKind::Siren, Preset::Small, true) => 300,
        (ModelKind::Siren, Preset::Default, true) => 100,
        (ModelKind::Nglod, _, false) => NglodTrainConfig::default().epochs,
        (ModelKind::Nglod, Preset::Small, true) => 4,
        // About a minute on the 2-core box with lavapipe (8 epochs: 31-77 s of training under load).
        (ModelKind::Nglod, Preset::Default, true) => 12,
    }
}

/// Loads a mesh and normalises it into `[-1, 1]³`.
pub fn load_normalized(path: &Path) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    load_normalized_with(path, &sdf_geom::LoadOptions::default())
}

/// [`load_normalized`] with explicit [`sdf_geom::LoadOptions`] (the bins' `--allow-external-uris`).
pub fn load_normalized_with(
    path: &Path,
    options: &sdf_geom::LoadOptions,
) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    let (mesh, _report) =
        sdf_geom::load_mesh_with(path, options).map_err(|source| RunError::Mesh {
            path: path.to_owned(),
            source,
        })?;
    Ok(mesh.normalized())
}

/// A normalised mesh with its exact signed distance, built once per run: the no-inside check,
/// the trainers' samplers and the evaluation all read the same BVH (1.3–1.6 s to build for a
/// 1.4 M-triangle scan on 2 cores, once instead of three times).
#[derive(Clone, Debug)]
pub struct GroundTruth {
    /// The mesh, in the normalised cube.
    pub mesh: Mesh,
    /// Its exact signed distance.
    pub sdf: Arc<SignedDistance>,
}

impl GroundTruth {
    /// Builds the signed distance of `mesh` (already normalised, as [`load_normalized`] gives it),
    /// loaded from `path` (for errors).
    pub fn new(mesh: Mesh, path: &Path) -> Result<Self, RunError> {
        let sdf = SignedDistance::new(&mesh).map_err(|source| RunError::Mesh {
            path: path.to_owned(),
            source,
        })?;
        Ok(GroundTruth {
            mesh,
            sdf: Arc::new(sdf),
        })
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
    mut progress: impl FnMut(&Progress),
) -> Result<Trained, RunError> {
    if let Some(c) = resume {
        c.check_model(options.model)?;
        let preset = c.options().1;
        if preset.as_deref() != Some(options.preset.name()) {
            return Err(c.refusal(format!(
                "the checkpoint uses the {} preset, not {}",
                preset.as_deref().unwrap_or("unknown"),
                options.preset.name()
            )));
        }
    }
    options.validate()?;
    let start = Instant::now();
    let asked = match options.model {
        ModelKind::Siren => options.steps,
        ModelKind::Nglod => options.epochs,
    };
    if let (Some(c), Some(asked)) = (resume, asked)
        && asked < c.done()
    {
        let unit = match options.model {
            ModelKind::Siren => "steps",
            ModelKind::Nglod => "epochs",
        };
        return Err(c.refusal(format!(
            "the checkpoint has done {} {unit} already, more than the {asked} asked for: \
             ask for more, or leave the length out to finish the run it planned",
            c.done()
        )));
    }
    // A resumed run goes on to the length its first run planned.
    let total = asked
        .or_else(|| resume.and_then(Checkpoint::planned))
        .unwrap_or_else(|| default_length(options.model, options.preset, gpu.is_cpu()));
    // NGLOD's CPU default fills a time budget instead (`default_length` is then its least).
    let time_budget =
        (options.model == ModelKind::Nglod && asked.is_none() && resume.is_none() && gpu.is_cpu())
            .then_some(CPU_TIME_BUDGET);
    let training_json = |done: usize, loss: f32| {
        serde_json::json!({
            "model": options.model.name(),
            "preset": options.preset.name(),
            "seed": options.seed,
            "done": done,
            "final_loss": loss,
        })
    };
    match options.model {
        ModelKind::Siren => {
            let config = match options.preset {
                Preset::Default => SirenConfig::default(),
                Preset::Small => SirenConfig::small(),
            };
            let siren = match resume {
                Some(c) => Siren::from_model_file(&c.model_file())?,
                None => {
                    Siren::new(config, options.seed).map_err(sdf_nn::siren::TrainError::from)?
                }
            };
            let defaults = SirenTrainConfig::default();
            let train_config = SirenTrainConfig {
                steps: total,
                seed: options.seed,
                lr: options.lr.unwrap_or(defaults.lr),
                weights: options.siren_weights.unwrap_or(defaults.weights),
                plateau_patience: options
                    .plateau_patience
                    .unwrap_or(defaults.plateau_patience),
                ..defaults
            };
            let per_step = (train_config.surface_per_step + train_config.box_per_step) as f64;
            let mut trainer = SirenTrainer::with_ground_truth(
                gpu,
                &siren,
                &truth.mesh,
                &truth.sdf,
                train_config,
            )?;
            if let Some(c) = resume {
                let lr = c.lr().unwrap_or(trainer.lr());
                trainer.resume(gpu, &c.optimizer()?, c.done(), lr)?;
            }
            let first = trainer.steps_done();
            let mut loss = f32::NAN;
            let mut interrupted = false;
            while trainer.steps_done() < total {
                if stop.load(Ordering::Relaxed) {
                    interrupted = true;
                    break;
                }
                if let Some(l) = trainer.step(gpu)? {
                    loss = l.total();
                    let done = trainer.steps_done();
                    progress(&Progress {
                        done,
                        total,
                        unit: "step",
                        loss,
                        lr: trainer.lr(),
                        points_per_second: (done - first) as f64 * per_step
                            / start.elapsed().as_secs_f64().max(1e-9),
                    });
                }
            }
            let done = trainer.steps_done();
            let optimizer = trainer.optimizer_state(gpu)?;
            let lr = trainer.lr();
            let mut file = trainer.model_file(gpu)?;
            file.metadata.training = with_run_record(
                std::mem::take(&mut file.metadata.training),
                training_json(done, loss),
            );
            file.metadata.normalization = normalization;
            // The trainer checks each window's loss; the weights are checked here, since a run
            // shorter than a window reads no loss at all.
            check_trained(&file, done, "step")?;
            Ok(Trained {
                file,
                train_seconds: start.elapsed().as_secs_f64(),
                done,
                final_loss: loss,
                interrupted,
                details: serde_json::Value::Null,
                optimizer,
                lr,
            })
        }
        ModelKind::Nglod => {
            let model = match resume {
                Some(c) => {
                    // A checkpoint brings its own architecture; values asked for must agree.
                    let model = Nglod::from_model_file(&c.model_file())?;
                    let differences = options.nglod_architecture.differences(model.config());
                    if !differences.is_empty() {
                        return Err(c.refusal(format!(
                            "the checkpoint's architecture differs: {}",
                            differences.join("; ")
                        )));
                    }
                    model
                }
                None => Nglod::new(
                    options
                        .nglod_architecture
                        .config(options.preset, options.seed)?,
                )?,
            };
            let first = resume.map_or(0, Checkpoint::done).min(total);
            let mut train_config = NglodTrainConfig {
                epochs: total - first,
                seed: options.seed,
                ..Default::default()
            };
            if let Some(lr) = options.lr {
                train_config.adam.lr = lr;
            }
            if let Some(f) = options.lr_final {
                train_config.lr_final = (f != 1.0).then_some(f);
            }
            if let Some(g) = options.grow_every {
                train_config.grow_every = (g > 0).then_some(g);
            }
            train_config.distance = options.distance;
            train_config.time_budget = time_budget;
            if let Some((blocks, every)) = options.pool {
                train_config.pool_blocks = blocks;
                train_config.refresh_every = every;
            }
            let per_epoch = (train_config.uniform_points
                + train_config.near_points
                + train_config.surface_points) as f64;
            let mut trainer = NglodTrainer::with_ground_truth(
                gpu,
                &model,
                &truth.mesh,
                truth.sdf.clone(),
                train_config,
            )?;
            trainer.set_stop_flag(stop.clone());
            if let Some(c) = resume {
                trainer.resume(&c.optimizer()?, first, c.epoch_steps_done())?;
            }
            let mut planned = total;
            let report = trainer.train_with(|e| {
                let done = e.epoch + 1;
                planned = first + e.planned;
                progress(&Progress {
                    done,
                    total: planned,
                    unit: "epoch",
                    loss: e.loss,
                    lr: e.lr,
                    points_per_second: (done - first) as f64 * per_epoch
                        / start.elapsed().as_secs_f64().max(1e-9),
                });
            })?;
            let trained = trainer.model()?;
            let optimizer = trainer.optimizer_state()?;
            let done = trainer.epochs_done();
            let lr = report
                .epochs
                .last()
                .map_or(trainer.config().adam.lr, |e| e.lr);
            let mut training = with_run_record(
                trainer.training_json(Some(&report)),
                training_json(done, report.final_loss),
            );
            training["planned"] = planned.into();
            training["stall_seconds"] = report.stall_seconds.into();
            let file = trained.to_model_file(normalization, training.clone());
            check_trained(&file, done, "epoch")?;
            Ok(Trained {
                file,
                train_seconds: start.elapsed().as_secs_f64(),
                done,
                final_loss: report.final_loss,
                interrupted: report.stopped_early && stop.load(Ordering::Relaxed),
                details: training,
                optimizer,
                lr,
            })
        }
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

/// Evaluation results of one model on one mesh.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Evaluation {
    /// F1 and distance errors.
    pub scores: Scores,
    /// Latency.
    pub latency: Latency,
    /// Points in each evaluation set.
    pub eval_points: usize,
    /// Unsigned fields: the mesh against the level set Φ = [`UNSIGNED_LEVEL`].
    pub chamfer: Option<crate::metrics::SurfaceMetrics>,
}

/// The level set of an unsigned field that stands for its surface (|d| has no zero crossing for
/// marching cubes to find): one cell of the [`UNSIGNED_EXTRACT_RESOLUTION`] grid, in normalised
/// units.
pub const UNSIGNED_LEVEL: f32 = 2.0 / UNSIGNED_EXTRACT_RESOLUTION as f32;
/// Cells per axis of the extraction behind an unsigned field's Chamfer distance.
pub const UNSIGNED_EXTRACT_RESOLUTION: u32 = 128;

/// Whether a model file holds an unsigned distance field (`training.distance`).
pub fn is_unsigned(file: &ModelFile) -> bool {
    file.metadata
        .training
        .get("distance")
        .and_then(|d| d.as_str())
        == Some(DistanceMode::Unsigned.name())
}

/// Why F1 would be undefined for `truth`'s mesh: (almost) no inside among a quick sample
/// of box and near-surface points (same bounds as the evaluation,
/// [`crate::metrics::no_inside_reason`]). For a warning before training.
pub fn no_inside_check(truth: &GroundTruth) -> Option<String> {
    let (mesh, sdf) = (&truth.mesh, &truth.sdf);
    let clear = |points: Vec<Vec3>| {
        let signed = sdf.signed_distance_batch(&points);
        crate::metrics::clear_inside_fraction(sdf, &points, &signed)
    };
    let b = clear(sdf_geom::sample::uniform_box(20_000, EVAL_SEED));
    let n = clear(sdf_geom::sample::near_surface(
        mesh,
        20_000,
        crate::metrics::NEAR_SURFACE_SIGMA,
        EVAL_SEED ^ 1,
    ));
    crate::metrics::no_inside_reason(b, n)
}

/// Scores and times `model` against `truth`, the exact SDF of the normalised mesh.
pub fn evaluate(
    gpu: &GpuContext,
    model: &NeuralSdf,
    truth: &GroundTruth,
    points: usize,
) -> Result<Evaluation, RunError> {
    check_eval_points(points)?;
    let mesh = &truth.mesh;
    let sets = EvalSets::new(mesh, &truth.sdf, points, EVAL_SEED);
    let unsigned = is_unsigned(model.model_file());
    let predict = |p: &[Vec3]| finite_values(p, model.eval_normalized(gpu, p)?);
    let scores = if unsigned {
        sets.score_unsigned(predict)?
    } else {
        sets.score(predict)?
    };
    let chamfer = if unsigned {
        let options = ExtractOptions::new(UNSIGNED_EXTRACT_RESOLUTION);
        let (level_set, _) = extract_normalized(gpu, model, &options)?;
        // An empty level set (the model never gets that close to 0) has no Chamfer distance.
        crate::metrics::SurfaceMetrics::between(
            &level_set,
            mesh,
            &truth.sdf,
            points.min(20_000),
            EVAL_SEED,
        )
        .ok()
    } else {
        None
    };
    // Wall time through the public call, and kernel time from timestamp queries (where the
    // adapter has them) in separate, alternating calls, so that the timestamps never slow the
    // wall figures and both see the same state of the GPU.
    let latency = measure_latency_timed(
        &sets.bbox.points,
        10,
        WARM_UP,
        MEASURE_FOR,
        |p| model.eval_normalized(gpu, p),
        |p| model.eval_normalized_timed(gpu, p),
    )?;
    Ok(Evaluation {
        scores,
        latency,
        eval_points: points,
        chamfer,
    })
}

/// `values` (of `points`), or [`RunError::NonFiniteModel`] at the first NaN or ∞: scores of
/// such a model would count its NaNs as outside and say nothing true.
pub fn finite_values(points: &[Vec3], values: Vec<f32>) -> Result<Vec<f32>, RunError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(RunError::NonFiniteModel {
            point: points[i],
            value: values[i],
        }),
        None => Ok(values),
    }
}

/// Extracts the model's surface at `resolution` cells per axis, evaluating on the GPU, and
/// returns it in the original mesh's coordinates. The surface is the zero level set, or for an
/// unsigned field ([`is_unsigned`]) the level set Φ = [`UNSIGNED_LEVEL`], since |d| has no zero
/// crossing to find.
pub fn extract_mesh(
    gpu: &GpuContext,
    model: &NeuralSdf,
    resolution: u32,
) -> Result<(Mesh, ExtractStats), RunError> {
    extract_mesh_with(gpu, model, &ExtractOptions::new(resolution))
}

/// [`extract_mesh`] with explicit options (memory budget, domain, bound factor).
pub fn extract_mesh_with(
    gpu: &GpuContext,
    model: &NeuralSdf,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), RunError> {
    let (mut mesh, stats) = extract_normalized(gpu, model, options)?;
    let n = model.normalization();
    for v in &mut mesh.vertices {
        *v = n.to_original(*v);
    }
    Ok((mesh, stats))
}

/// The surface of [`extract_mesh_with`] in normalised coordinates.
fn extract_normalized(
    gpu: &GpuContext,
    model: &NeuralSdf,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), RunError> {
    let level = if is_unsigned(model.model_file()) {
        UNSIGNED_LEVEL
    } else {
        0.0
    };
    extract_surface(
        |p: &[Vec3]| {
            let d = model.eval_normalized(gpu, p)?;
            Ok::<_, sdf_nn::NeuralSdfError>(d.into_iter().map(|x| x - level).collect::<Vec<_>>())
        },
        options,
    )
    .map_err(|e| match e {
        ExtractError::Eval(e) => RunError::Model(e),
        other => RunError::Options(other.to_string()),
    })
}

/// The JSON report of `train` (and of each `corpus` entry).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    /// Mesh file.
    pub mesh: String,
    /// `"siren"` or `"nglod"`.
    pub model: String,
    /// `"default"` or `"small"`.
    pub preset: String,
    /// The model's hyperparameters as its file records them (the preset's, or the
    /// [`NglodArchitecture`] asked for over it).
    #[serde(default)]
    pub architecture: serde_json::Value,
    /// Parameter count.
    pub params: usize,
    /// Model file size in bytes.
    pub file_bytes: u64,
    /// F1 of the inside class, uniform box points (null when undefined: `f1_null_reason`).
    pub f1_bbox: Option<f64>,
    /// F1 of the inside class, near-surface points.
    pub f1_near_surface: Option<f64>,
    /// Mean of the two.
    pub f1_mean: Option<f64>,
    /// Why the F1 fields are null: a mesh without an inside, or an unsigned field.
    #[serde(default)]
    pub f1_null_reason: Option<String>,
    /// `"signed"` or `"unsigned"`: what the model fits.
    #[serde(default)]
    pub distance: Option<DistanceMode>,
    /// Sign accuracy, box points (null for an unsigned field).
    pub sign_accuracy_bbox: Option<f64>,
    /// Sign accuracy, near-surface points.
    pub sign_accuracy_near_surface: Option<f64>,
    /// Where the box points' sign errors lie: which way each is wrong and how far from the
    /// surface (null for an unsigned field, and in reports written before it existed).
    #[serde(default)]
    pub sign_errors_bbox: Option<crate::SignErrors>,
    /// Where the near-surface points' sign errors lie.
    #[serde(default)]
    pub sign_errors_near_surface: Option<crate::SignErrors>,
    /// Exact fraction of the box points inside the mesh.
    #[serde(default)]
    pub inside_fraction_bbox: f64,
    /// Mean |Φ − SDF| on the box points, normalised units (|Φ − |SDF|| for an unsigned field).
    #[serde(default)]
    pub bbox_mean_abs_error: f64,
    /// Unsigned fields: symmetric Chamfer-L1 distance between the mesh and the extracted
    /// level set Φ = [`UNSIGNED_LEVEL`] (normalised units; an exact |d| scores about that level).
    #[serde(default)]
    pub chamfer_l1: Option<f64>,
    /// Mean |Φ − SDF| near the surface, normalised units.
    pub near_surface_mean_abs_error: f64,
    /// Max |Φ − SDF| near the surface, normalised units.
    pub near_surface_max_abs_error: f64,
    /// Median wall time per point of a 50000-point batch through `NeuralSdf::eval_normalized`
    /// (upload, kernels, readback, host work), ns.
    pub per_point_ns: f64,
    /// Median wall time of a 3000-point batch through `NeuralSdf::eval_normalized`, µs.
    pub batch3000_us: f64,
    /// Kernel time per point of the 50000 batch from GPU timestamps (separate, timed calls),
    /// where the adapter has them, ns.
    pub gpu_per_point_ns: Option<f64>,
    /// Kernel time of the 3000 batch from GPU timestamps (separate, timed calls), µs.
    #[serde(default)]
    pub gpu_batch3000_us: Option<f64>,
    /// Training wall time, s.
    pub train_seconds: f64,
    /// Steps (SIREN) or epochs (NGLOD) run.
    pub trained: usize,
    /// Final training loss.
    pub final_loss: f32,
    /// Learning rate at the end of training (null in reports written before it existed).
    #[serde(default)]
    pub final_lr: Option<f32>,
    /// Points per evaluation set.
    pub eval_points: usize,
    /// Adapter the run used.
    pub adapter: String,
    /// hwsdf version.
    pub hwsdf_version: String,
    /// Training details (e.g. NGLOD's GPU/sampling time split).
    pub training: serde_json::Value,
}

impl Report {
    /// Assembles a report.
    pub fn new(
        mesh: &Path,
        options: &TrainOptions,
        trained: &Trained,
        file_bytes: u64,
        eval: &Evaluation,
        adapter: String,
    ) -> Self {
        let s = &eval.scores;
        Report {
            mesh: mesh.display().to_string(),
            model: options.model.name().into(),
            preset: options.preset.name().into(),
            architecture: trained.file.metadata.config.clone(),
            params: trained.file.param_count(),
            file_bytes,
            f1_bbox: s.f1_bbox,
            f1_near_surface: s.f1_near_surface,
            f1_mean: s.f1_mean,
            f1_null_reason: s.f1_null_reason.clone(),
            distance: Some(options.distance),
            sign_accuracy_bbox: s.sign_accuracy_bbox,
            sign_accuracy_near_surface: s.sign_accuracy_near_surface,
            sign_errors_bbox: s.sign_errors_bbox,
            sign_errors_near_surface: s.sign_errors_near_surface,
            inside_fraction_bbox: s.inside_fraction_bbox,
            bbox_mean_abs_error: s.bbox_error.mean_abs,
            chamfer_l1: eval.chamfer.map(|c| c.chamfer_l1),
            near_surface_mean_abs_error: s.near_surface_error.mean_abs,
            near_surface_max_abs_error: s.near_surface_error.max_abs,
            per_point_ns: eval.latency.per_point_ns,
            batch3000_us: eval.latency.batch3000_us,
            gpu_per_point_ns: eval.latency.gpu_per_point_ns,
            gpu_batch3000_us: eval.latency.gpu_batch3000_us,
            train_seconds: trained.train_seconds,
            trained: trained.done,
            final_loss: trained.final_loss,
            final_lr: Some(trained.lr),
            eval_points: eval.eval_points,
            adapter,
            hwsdf_version: sdf_nn::model_file::HWSDF_VERSION.into(),
            training: trained.details.clone(),
        }
    }

    /// Writes the report as pretty JSON, atomically.
    pub fn write(&self, path: &Path) -> Result<(), RunError> {
        let json = serde_json::to_vec_pretty(self).expect("report serialises");
        write_atomic(path, &json).map_err(|source| RunError::Write {
            path: path.to_owned(),
            source,
        })
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
/// report.
#[allow(clippy::too_many_arguments)]
pub fn run(
    gpu: &GpuContext,
    mesh_path: &Path,
    options: &TrainOptions,
    out: &Path,
    eval_points: usize,
    resume: Option<&Checkpoint>,
    stop: &Arc<AtomicBool>,
    progress: impl FnMut(&Progress),
) -> Result<RunOutcome, RunError> {
    let (mesh, normalization) = load_normalized(mesh_path)?;
    let truth = GroundTruth::new(mesh, mesh_path)?;
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
    );
    Ok(RunOutcome::Finished(Box::new(report), Box::new(trained)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run of `model`'s `small` preset interrupted after `done` steps or epochs, with zero
    /// optimiser moments for its `n` parameters.
    fn interrupted(mut file: ModelFile, model: &str, n: usize, done: usize) -> Trained {
        file.metadata.training = serde_json::json!({"model": model, "preset": "small"});
        Trained {
            file,
            train_seconds: 1.0,
            done,
            final_loss: 0.1,
            interrupted: true,
            details: serde_json::Value::Null,
            optimizer: AdamState {
                m: vec![0.0; n],
                v: vec![0.0; n],
                step: done as u32,
            },
            lr: 1e-3,
        }
    }

    /// A checkpoint resumes only into a run of its own model, preset and whole architecture.
    #[test]
    fn checkpoint_differences_name_every_setting_it_lacks() {
        let nglod = Nglod::new(NglodConfig::small()).unwrap();
        let file = nglod.to_model_file(sdf_geom::Normalization::identity(), Default::default());
        let c = interrupted(file, "nglod", nglod.param_count(), 1).checkpoint();
        let small = TrainOptions::new(ModelKind::Nglod, Preset::Small);
        assert!(c.differences(&small).unwrap().is_empty());
        let default = TrainOptions::new(ModelKind::Nglod, Preset::Default);
        assert_eq!(
            c.differences(&default).unwrap(),
            ["preset default, not small"]
        );
        let siren = TrainOptions::new(ModelKind::Siren, Preset::Small);
        assert_eq!(c.differences(&siren).unwrap(), ["model siren, not nglod"]);
        let mut wider = small.clone();
        wider.nglod_architecture.hidden = Some(NglodConfig::small().hidden * 2);
        let d = c.differences(&wider).unwrap();
        assert_eq!(d.len(), 1, "{d:?}");
        assert!(d[0].starts_with("hidden "), "{d:?}");
    }

    /// A checkpoint's claimed progress is checked when it loads: counts beyond any run, more
    /// epochs done than planned, or an optimiser step at u32::MAX (which used to overflow on the
    /// first resumed step) never reach training.
    #[test]
    fn checkpoints_claiming_impossible_progress_are_refused() {
        let siren = sdf_nn::Siren::new(sdf_nn::SirenConfig::small(), 1).unwrap();
        let n = siren.params().len();
        let file = siren.to_model_file(sdf_geom::Normalization::identity(), Default::default());
        let trained = interrupted(file, "siren", n, 5);
        let dir = std::env::temp_dir().join(format!("hwsdf-ckpt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let save = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
            let mut c = trained.checkpoint();
            edit(&mut c.file.metadata.training);
            let path = dir.join(name);
            c.save(&path).unwrap();
            Checkpoint::load(&path)
        };
        let ok = save("ok.safetensors", &|_| {}).unwrap();
        // A tensor the network does not read changes nothing.
        let mut extra = trained.checkpoint();
        extra.file.tensors.push(sdf_nn::model_file::Tensor::f32(
            "junk",
            vec![4],
            vec![0.0; 4],
        ));
        extra.save(&dir.join("extra.safetensors")).unwrap();
        let extra = Checkpoint::load(&dir.join("extra.safetensors")).unwrap();
        assert_eq!(extra.optimizer().unwrap().m.len(), n);
        assert_eq!((ok.done(), ok.optimizer().unwrap().step), (5, 5));
        // The step counter saturates instead of overflowing.
        let max = save("step-max.safetensors", &|t| {
            t["adam_step"] = u32::MAX.into()
        })
        .unwrap();
        let mut adam = sdf_nn::AdamCpu::new(n, sdf_nn::AdamConfig::default());
        adam.step = max.optimizer().unwrap().step;
        let mut p = vec![0.0f64; n];
        adam.step(&mut p, &vec![1.0; n], 1.0);
        assert!(p.iter().all(|x| x.is_finite()));
        for (name, edit, says) in [
            (
                "done-huge.safetensors",
                &(|t: &mut serde_json::Value| t["done"] = u64::MAX.into())
                    as &dyn Fn(&mut serde_json::Value),
                "done is",
            ),
            (
                "planned-huge.safetensors",
                &|t: &mut serde_json::Value| t["planned"] = u64::MAX.into(),
                "planned is",
            ),
            (
                "done-past-planned.safetensors",
                &|t: &mut serde_json::Value| t["planned"] = 3.into(),
                "5 epochs done of 3 planned",
            ),
            (
                "negative.safetensors",
                &|t: &mut serde_json::Value| t["epoch_steps_done"] = (-1).into(),
                "epoch_steps_done is -1",
            ),
        ] {
            let e = save(name, edit).map(|_| ()).unwrap_err().to_string();
            assert!(e.contains(says), "{name}: {e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn options_go_to_the_model_they_apply_to() {
        let siren = TrainOptions::new(ModelKind::Siren, Preset::Small);
        let nglod = TrainOptions::new(ModelKind::Nglod, Preset::Default);
        assert!(siren.validate().is_ok() && nglod.validate().is_ok());
        let refused = |o: TrainOptions, says: &str| {
            let e = o.validate().unwrap_err().to_string();
            assert!(e.contains(says), "{says:?} not in {e:?}");
        };
        refused(
            TrainOptions {
                epochs: Some(3),
                ..siren.clone()
            },
            "--epochs applies to NGLOD",
        );
        refused(
            TrainOptions {
                steps: Some(0),
                ..siren.clone()
            },
            "at least 1",
        );
        refused(
            TrainOptions {
                pool: Some((2, 2)),
                ..siren.clone()
            },
            "apply to NGLOD",
        );
        refused(
            TrainOptions {
                distance: DistanceMode::Unsigned,
                ..siren.clone()
            },
            "NGLOD only",
        );
        refused(
            TrainOptions {
                lr: Some(f32::NAN),
                ..siren.clone()
            },
            "learning rate",
        );
        refused(
            TrainOptions {
                steps: Some(10),
                ..nglod.clone()
            },
            "--steps applies to SIREN",
        );
        refused(
            TrainOptions {
                siren_weights: Some(LossWeights::default()),
                ..nglod.clone()
            },
            "loss weights apply to SIREN",
        );
        refused(
            TrainOptions {
                plateau_patience: Some(500),
                ..nglod.clone()
            },
            "--plateau-patience applies to SIREN",
        );
        assert!(
            TrainOptions {
                plateau_patience: Some(0),
                ..siren.clone()
            }
            .validate()
            .is_ok()
        );
        refused(
            TrainOptions {
                lr_final: Some(-0.5),
                ..nglod.clone()
            },
            "--lr-final",
        );
        refused(
            TrainOptions {
                pool: Some((0, 4)),
                ..nglod.clone()
            },
            "--pool",
        );
        refused(
            TrainOptions {
                nglod_architecture: NglodArchitecture {
                    hidden: Some(0),
                    ..Default::default()
                },
                ..nglod.clone()
            },
            "hidden",
        );
    }

    #[test]
    fn settings_resolve_every_default() {
        let nglod = TrainOptions::new(ModelKind::Nglod, Preset::Default);
        let spelt_out = TrainOptions {
            epochs: Some(100),
            lr: Some(1e-3),
            lr_final: Some(0.1),
            grow_every: Some(0),
            pool: Some((4, 4)),
            nglod_architecture: NglodArchitecture {
                resolutions: Some(vec![6, 12, 24, 48]),
                feature_dim: Some(8),
                ..Default::default()
            },
            ..nglod.clone()
        };
        let gpu = nglod.settings(false).unwrap();
        assert_eq!(gpu, spelt_out.settings(false).unwrap());
        assert_eq!(
            gpu.to_string(),
            "architecture resolutions 6,12,24,48, sparse levels 1, band cells 0, features 8, \
             hidden 128; \
             distance signed; epochs 100; grow every 0; lr 0.001; lr final 0.1; pool 4,4; \
             preset default; seed 0"
        );
        // The length a default stands for depends on the adapter.
        let cpu = nglod.settings(true).unwrap();
        assert_eq!(
            cpu.differences(&gpu),
            ["epochs about 55 s of training (12 to 100), not 100"]
        );
        let finer = TrainOptions {
            nglod_architecture: NglodArchitecture {
                hidden: Some(64),
                ..Default::default()
            },
            seed: 1,
            ..nglod
        };
        assert_eq!(
            finer.settings(false).unwrap().differences(&gpu),
            [
                "architecture resolutions 6,12,24,48, sparse levels 1, band cells 0, features 8, \
                 hidden 64, not resolutions 6,12,24,48, sparse levels 1, band cells 0, features 8, \
                 hidden 128",
                "seed 1, not 0"
            ]
        );
        let siren = TrainOptions::new(ModelKind::Siren, Preset::Small);
        let s = siren.settings(true).unwrap().to_string();
        assert!(s.contains("steps 300"), "{s}");
        assert!(s.contains("plateau patience 500"), "{s}");
        let constant = TrainOptions {
            plateau_patience: Some(0),
            ..siren.clone()
        };
        assert_eq!(
            constant
                .settings(true)
                .unwrap()
                .differences(&siren.settings(true).unwrap()),
            ["plateau patience 0, not 500"]
        );
        assert!(
            s.contains(
                "loss weights surface 3000, off-surface 100, normal 100, eikonal 5, alpha 100, sign 1000"
            ),
            "{s}"
        );
        // Invalid options have no settings.
        let bad = TrainOptions {
            epochs: Some(0),
            ..TrainOptions::new(ModelKind::Nglod, Preset::Small)
        };
        assert!(bad.settings(false).is_err());
    }

    #[test]
    fn an_nglod_architecture_replaces_only_the_values_given() {
        let none = NglodArchitecture::default();
        assert!(none.is_preset());
        let seeded = NglodConfig {
            seed: 7,
            ..NglodConfig::default_preset()
        };
        assert_eq!(none.config(Preset::Default, 7).unwrap(), seeded);
        assert_eq!(none.config(Preset::Small, 0).unwrap(), NglodConfig::small());
        let fine = NglodArchitecture {
            resolutions: Some(vec![8, 16, 32, 64]),
            sparse_levels: Some(2),
            ..Default::default()
        };
        assert!(!fine.is_preset());
        // SIREN takes no NGLOD architecture; NGLOD takes a valid one.
        assert!(none.check(ModelKind::Siren, Preset::Small).is_ok());
        assert!(matches!(
            fine.check(ModelKind::Siren, Preset::Small),
            Err(RunError::Options(_))
        ));
        assert!(fine.check(ModelKind::Nglod, Preset::Small).is_ok());
        let c = fine.config(Preset::Small, 3).unwrap();
        assert_eq!(c.resolutions, [8, 16, 32, 64]);
        assert_eq!(
            (c.sparse_levels, c.feature_dim, c.hidden, c.seed),
            (2, 4, 32, 3)
        );
        // Agreeing with every value given is no difference; the values not given are free.
        assert!(fine.differences(&c).is_empty());
        assert!(
            fine.differences(&NglodConfig {
                hidden: 7,
                ..c.clone()
            })
            .is_empty()
        );
        assert_eq!(
            fine.differences(&NglodConfig::default_preset()),
            [
                "resolutions 8,16,32,64, not 6,12,24,48",
                "sparse levels 2, not 1"
            ]
        );
    }

    #[test]
    fn a_bad_nglod_architecture_is_a_typed_error() {
        for bad in [
            // More sparse levels than levels.
            NglodArchitecture {
                sparse_levels: Some(5),
                ..Default::default()
            },
            // A sparse level above 255 cells (the default's finest level is sparse).
            NglodArchitecture {
                resolutions: Some(vec![8, 300]),
                ..Default::default()
            },
            NglodArchitecture {
                resolutions: Some(vec![]),
                ..Default::default()
            },
            NglodArchitecture {
                feature_dim: Some(0),
                ..Default::default()
            },
            NglodArchitecture {
                hidden: Some(0),
                ..Default::default()
            },
        ] {
            assert!(
                bad.check(ModelKind::Nglod, Preset::Default).is_err(),
                "{bad:?}"
            );
            let e = bad.config(Preset::Default, 0).unwrap_err();
            assert!(
                matches!(e, RunError::Nglod(sdf_nn::NglodError::InvalidConfig(_))),
                "{bad:?}: {e}"
            );
        }
    }
}
