//! What a run is asked for and what it resolves to: the model, the size preset, the training
//! options of `train`'s and `corpus`'s flags with their one validation
//! ([`TrainOptions::validate`]), the defaults they fall back on ([`TrainOptions::length`],
//! [`default_length`], [`CPU_TIME_BUDGET`]), and the settings a corpus records.

use std::collections::{BTreeMap, BTreeSet};

use sdf_nn::nglod::{DEFAULT_EPOCHS, Encoding, HASHGRID_EPOCHS, TimeBudget};
use sdf_nn::{DistanceMode, LossWeights, NglodConfig, NglodTrainConfig, SirenTrainConfig};
use serde::{Deserialize, Serialize};

use super::RunError;

/// The most SIREN steps a run may ask for: a thousand times the default (about 4.5 hours on
/// an H100), so that a mistyped length is refused instead of running for ever.
pub const MAX_STEPS: usize = 10_000_000;

/// The most NGLOD or hash-grid epochs a run may ask for: a thousand times NGLOD's default
/// (about 2 hours on an H100).
pub const MAX_EPOCHS: usize = 100_000;

/// The largest `--batch`: 32 times NGLOD's default, whose rows of a step then take tens of
/// megabytes of GPU memory.
pub const MAX_BATCH: u32 = 1 << 16;

/// Which architecture to train.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// SIREN.
    Siren,
    /// NGLOD.
    Nglod,
    /// instant-ngp's multiresolution hash grid: NGLOD's model family with hashed, concatenated
    /// levels ([`Encoding::Hashed`]), trained by NGLOD's trainer on its own schedule
    /// ([`NglodTrainConfig::hashgrid`]).
    Hashgrid,
}

impl ModelKind {
    /// Every model, in the order tables list them.
    pub const ALL: [ModelKind; 3] = [ModelKind::Siren, ModelKind::Nglod, ModelKind::Hashgrid];

    /// The model `train` fits when none is asked for: NGLOD on a GPU, where its fits are the
    /// ones measured (100 epochs of spot in 3.7–4.5 s on an H200, F1 0.997 / 0.982 over the
    /// first 20 shared meshes), and the hash grid on a CPU adapter, which in the same minute of
    /// training fits better near the surface on every shared mesh tried but one open mesh
    /// (docs/benchmarks/2026-11-28-session-31-cpu-default-model.md).
    pub fn for_adapter(cpu_adapter: bool) -> Self {
        if cpu_adapter {
            ModelKind::Hashgrid
        } else {
            ModelKind::Nglod
        }
    }

    /// The model named `name` (as [`Self::name`] writes it), if any.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }

    /// `"siren"`, `"nglod"` or `"hashgrid"`: the `--model` value, the model file's
    /// architecture and the name reports and corpus tables record.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Siren => "siren",
            ModelKind::Nglod => "nglod",
            ModelKind::Hashgrid => "hashgrid",
        }
    }

    /// As messages and table headings write it: `"SIREN"`, `"NGLOD"` or `"hash grid"`.
    pub fn label(self) -> &'static str {
        match self {
            ModelKind::Siren => "SIREN",
            ModelKind::Nglod => "NGLOD",
            ModelKind::Hashgrid => "hash grid",
        }
    }

    /// What its length counts: `"step"` (SIREN) or `"epoch"` (NGLOD, the hash grid).
    pub fn unit(self) -> &'static str {
        match self {
            ModelKind::Siren => "step",
            ModelKind::Nglod | ModelKind::Hashgrid => "epoch",
        }
    }

    /// Whether NGLOD's trainer trains it (NGLOD and the hash grid: grids of features and an
    /// MLP, trained for epochs).
    pub fn is_grid(self) -> bool {
        self != ModelKind::Siren
    }

    /// The NGLOD trainer's defaults a run of this model starts from:
    /// [`NglodTrainConfig::hashgrid`] for the hash grid (learning rate 2.5e-3, batch 2048,
    /// [`HASHGRID_EPOCHS`]), [`NglodTrainConfig::default`] for NGLOD; `None` for SIREN, which
    /// has its own trainer.
    pub fn grid_schedule(self) -> Option<NglodTrainConfig> {
        match self {
            ModelKind::Siren => None,
            ModelKind::Nglod => Some(NglodTrainConfig::default()),
            ModelKind::Hashgrid => Some(NglodTrainConfig::hashgrid()),
        }
    }

    /// Its default learning rate: 1e-4 (SIREN), 1e-3 (NGLOD), 2.5e-3 (the hash grid).
    pub fn default_lr(self) -> f32 {
        match self.grid_schedule() {
            Some(c) => c.adam.lr,
            None => SirenTrainConfig::default().lr,
        }
    }
}

/// Size preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// The design document's architecture (for NGLOD with a sparse fourth level near the surface:
    /// `NglodConfig::default_preset`; for the hash grid `NglodConfig::hashgrid_default`).
    Default,
    /// A small network for CPU-only machines and tests (the hash grid's:
    /// `NglodConfig::hashgrid_small`).
    Small,
}

impl Preset {
    /// The preset used when none is asked for: `small` on a CPU adapter (lavapipe), where the
    /// design document's networks train too slowly, `default` on a GPU.
    /// NGLOD: `default` everywhere (`small` is capacity-bound and no longer saves time on
    /// lavapipe: issue 14, docs/benchmarks). SIREN and the hash grid: `small` on a CPU adapter,
    /// `default` on a GPU (the hash grid's default tables are 16 times its small ones, and every
    /// Adam step on lavapipe walks all of them).
    pub fn for_adapter(cpu_adapter: bool, model: ModelKind) -> Self {
        if cpu_adapter && model != ModelKind::Nglod {
            Preset::Small
        } else {
            Preset::Default
        }
    }

    /// The preset named `name` (as [`Self::name`] writes it), if any.
    pub fn from_name(name: &str) -> Option<Self> {
        [Preset::Default, Preset::Small]
            .into_iter()
            .find(|p| p.name() == name)
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
    /// NGLOD and hash-grid epochs (`None`: the preset's default for the adapter).
    pub epochs: Option<usize>,
    /// Seed of initialisation and sampling.
    pub seed: u64,
    /// Initial learning rate (`None`: the model's default, [`ModelKind::default_lr`]: 1e-4 for
    /// SIREN, 1e-3 for NGLOD, 2.5e-3 for the hash grid).
    pub lr: Option<f32>,
    /// SIREN loss weights (`None`: the design document's). An error for the grid models.
    pub siren_weights: Option<LossWeights>,
    /// SIREN: steps without progress of the loss before the learning rate is divided by 10
    /// (`None`: the trainer's 500; 0 keeps it constant). An error for the grid models.
    pub plateau_patience: Option<usize>,
    /// NGLOD and the hash grid: final learning rate as a fraction of the first, reached by
    /// cosine decay (`None`: the trainer's default; 1 keeps it constant).
    pub lr_final: Option<f32>,
    /// NGLOD and the hash grid: points per optimiser step (`None`: the trainer's default,
    /// `NglodTrainConfig::batch_size`). An error for SIREN.
    pub batch: Option<u32>,
    /// NGLOD: add a level of detail every this many epochs (`None`: the trainer's default; 0
    /// trains all levels from the start). An error for the hash grid, which has no levels of
    /// detail.
    pub grow_every: Option<usize>,
    /// Signed or unsigned distance (unsigned: NGLOD and the hash grid only).
    pub distance: DistanceMode,
    /// NGLOD's and the hash grid's sample pool: `(blocks, refresh_every)` (`None`: the
    /// trainer's default; `(1, 1)` draws fresh points every epoch as before the pool).
    pub pool: Option<(usize, usize)>,
    /// NGLOD and the hash grid: an architecture other than the preset's (each value given
    /// replaces the preset's). An error for SIREN unless empty.
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
            batch: None,
            grow_every: None,
            distance: DistanceMode::Signed,
            pool: None,
            nglod_architecture: NglodArchitecture::default(),
        }
    }

    /// Checks what can be checked without a mesh or a GPU, so that a bad option is a typed error
    /// before any work: lengths of at least 1, every option given to the model it applies to, a
    /// usable learning rate, final ratio, loss weights and NGLOD architecture. [`train`](super::train) runs it
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
                    return refuse(
                        "--epochs applies to NGLOD and the hash grid; SIREN trains for --steps",
                    );
                }
                if self.distance == DistanceMode::Unsigned {
                    return Err(RunError::UnsignedSiren);
                }
                if self.lr_final.is_some() || self.grow_every.is_some() || self.pool.is_some() {
                    return refuse(
                        "--lr-final, --grow-every and --pool apply to NGLOD (and the first and \
                         last to the hash grid); SIREN samples its batch every step and divides \
                         its learning rate by 10 when its loss plateaus (--plateau-patience)",
                    );
                }
                if self.batch.is_some() {
                    return refuse(
                        "--batch applies to NGLOD and the hash grid; SIREN's batch is its \
                         preset's (surface and box points every step)",
                    );
                }
                if let Some(w) = self.siren_weights {
                    w.validate()?;
                }
            }
            ModelKind::Nglod | ModelKind::Hashgrid => {
                let model = match self.model {
                    ModelKind::Hashgrid => "the hash grid",
                    _ => "NGLOD",
                };
                if self.steps.is_some() {
                    return Err(RunError::Options(format!(
                        "--steps applies to SIREN; {model} trains for --epochs"
                    )));
                }
                if self.siren_weights.is_some() {
                    return Err(RunError::Options(format!(
                        "loss weights apply to SIREN; {model}'s loss is the squared error"
                    )));
                }
                if self.plateau_patience.is_some() {
                    return Err(RunError::Options(format!(
                        "--plateau-patience applies to SIREN; {model}'s learning rate decays \
                         along a cosine (--lr-final)"
                    )));
                }
                if self.model == ModelKind::Hashgrid && self.grow_every.is_some() {
                    return refuse(
                        "--grow-every adds NGLOD's levels of detail one at a time; a hash grid \
                         has no levels of detail (its MLP reads every level's features at \
                         once), so it trains them all from the start",
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
                if let Some(b) = self.batch
                    && !(1..=MAX_BATCH).contains(&b)
                {
                    return Err(RunError::Options(format!(
                        "--batch must lie in 1..={MAX_BATCH}, not {b}"
                    )));
                }
            }
        }
        if let Some(lr) = self.lr {
            sdf_nn::AdamConfig::check_lr(lr).map_err(RunError::Options)?;
        }
        self.nglod_architecture.check(self.model, self.preset)
    }

    /// These options over `preset` instead, e.g. the adapter's once it is open. Only the grid
    /// models' architecture depends on the preset, so only it is checked again.
    pub fn with_preset(self, preset: Preset) -> Result<Self, RunError> {
        if preset != self.preset {
            self.nglod_architecture.check(self.model, preset)?;
        }
        Ok(TrainOptions { preset, ..self })
    }

    /// How long this run trains on a CPU adapter or not: the steps or epochs asked for, else
    /// [`default_length`] (for NGLOD and the hash grid on a CPU adapter, [`cpu_time_budget`]
    /// from it). The one
    /// place a run's length is settled: [`super::train`], [`TrainOptions::settings`] and the
    /// binaries' notes read it.
    pub fn length(&self, cpu_adapter: bool) -> Length {
        let asked = match self.model {
            ModelKind::Siren => self.steps,
            ModelKind::Nglod | ModelKind::Hashgrid => self.epochs,
        };
        Length {
            asked,
            default: default_length(self.model, self.preset, cpu_adapter),
            time_budget: cpu_time_budget(self.model).filter(|_| asked.is_none() && cpu_adapter),
        }
    }

    /// What this run asks for, as `name → value` with every default resolved to what it stands
    /// for, so that two runs that train alike have equal settings however their options were
    /// spelt (`--epochs 100` on a GPU and no `--epochs` there are the same run). The length
    /// defaults depend on the adapter, hence `cpu_adapter`. A corpus run keeps these beside its
    /// results and refuses to mix results of other settings into one table. The options are
    /// taken as [`TrainOptions::validate`] passed them; the NGLOD or hash-grid architecture they
    /// resolve to is checked as it is built.
    pub fn settings(&self, cpu_adapter: bool) -> Result<RunSettings, RunError> {
        let mut s = BTreeMap::new();
        let mut put = |k: &str, v: String| s.insert(k.to_owned(), v);
        put("preset", self.preset.name().to_owned());
        put("seed", self.seed.to_string());
        let length = self.length(cpu_adapter).to_string();
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
            ModelKind::Nglod | ModelKind::Hashgrid => {
                let d = self.model.grid_schedule().unwrap_or_default();
                let c = self
                    .nglod_architecture
                    .config(self.model, self.preset, self.seed)?;
                put("epochs", length);
                put("lr", self.lr.unwrap_or(d.adam.lr).to_string());
                let lr_final = self.lr_final.or(d.lr_final).unwrap_or(1.0);
                put("lr final", lr_final.to_string());
                put("batch", self.batch.unwrap_or(d.batch_size).to_string());
                let (blocks, every) = self.pool.unwrap_or((d.pool_blocks, d.refresh_every));
                put("pool", format!("{blocks},{every}"));
                put("distance", self.distance.name().to_owned());
                let architecture = match c.encoding {
                    Encoding::Summed => {
                        let grow = self.grow_every.or(d.grow_every).unwrap_or(0);
                        put("grow every", grow.to_string());
                        format!(
                            "resolutions {}, sparse levels {}, band cells {}, features {}, \
                             hidden {}",
                            comma_list(&c.resolutions),
                            c.sparse_levels,
                            c.band_cells,
                            c.feature_dim,
                            c.hidden
                        )
                    }
                    Encoding::Hashed { log2_table_size } => format!(
                        "resolutions {}, table 2^{log2_table_size}, features {}, hidden {}",
                        comma_list(&c.resolutions),
                        c.feature_dim,
                        c.hidden
                    ),
                };
                put("architecture", architecture);
            }
        }
        Ok(RunSettings(s))
    }
}

/// How long a run trains: [`TrainOptions::length`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Length {
    /// The steps or epochs asked for (`--steps`, `--epochs`).
    pub asked: Option<usize>,
    /// The preset's default for the adapter, when none is asked for ([`default_length`]).
    pub default: usize,
    /// NGLOD's and the hash grid's default on a CPU adapter: a time to fill, with `default` the
    /// least it trains.
    pub time_budget: Option<TimeBudget>,
}

/// As the settings write it: the count asked for, else the default it stands for.
impl std::fmt::Display for Length {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.asked, self.time_budget) {
            (Some(n), _) => write!(f, "{n}"),
            (None, Some(b)) => write!(
                f,
                "about {} s of training ({} to {})",
                b.seconds, self.default, b.max_epochs
            ),
            (None, None) => write!(f, "{}", self.default),
        }
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

/// NGLOD or hash-grid architecture values over a preset (`train --resolutions --sparse-levels
/// --band-cells --features --hidden`): each one given replaces the preset's, the others stay. The
/// result is checked by [`NglodConfig::validate`], so a bad combination is a typed error before
/// any work. A hash grid takes `--resolutions` (one level per value, its table size the
/// preset's), `--features` (per level) and `--hidden`; it has no sparse levels, so
/// `--sparse-levels` and `--band-cells` are refused for it.
///
/// ```
/// use sdf_eval::run::{ModelKind, NglodArchitecture, Preset};
///
/// // Two sparse levels of 32 and 64 cells under dense ones of 8 and 16.
/// let fine = NglodArchitecture {
///     resolutions: Some(vec![8, 16, 32, 64]),
///     sparse_levels: Some(2),
///     ..Default::default()
/// };
/// let config = fine.config(ModelKind::Nglod, Preset::Default, 0).unwrap();
/// assert_eq!((config.feature_dim, config.hidden), (8, 128)); // the preset's
/// // A hash grid of four levels, with the preset's 2 features per level and 2^18 tables.
/// let grid = NglodArchitecture {
///     resolutions: Some(vec![16, 64, 256, 1024]),
///     ..Default::default()
/// };
/// let config = grid.config(ModelKind::Hashgrid, Preset::Default, 0).unwrap();
/// assert_eq!((config.architecture(), config.input_dim()), ("hashgrid", 8));
/// assert!(fine.config(ModelKind::Hashgrid, Preset::Default, 0).is_err()); // sparse levels
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
    /// NGLOD and the hash grid the configuration they make must be valid
    /// ([`NglodArchitecture::config`]).
    pub fn check(&self, model: ModelKind, preset: Preset) -> Result<(), RunError> {
        match model {
            ModelKind::Siren if !self.is_preset() => Err(RunError::Options(
                "--resolutions, --sparse-levels, --band-cells, --features and --hidden set \
                 NGLOD's and the hash grid's architecture; SIREN's comes from its preset"
                    .into(),
            )),
            ModelKind::Siren => Ok(()),
            ModelKind::Nglod | ModelKind::Hashgrid => self.config(model, preset, 0).map(drop),
        }
    }

    /// The configuration of `model`'s `preset` ([`NglodConfig::default_preset`] and
    /// [`NglodConfig::small`] for NGLOD, [`NglodConfig::hashgrid_default`] and
    /// [`NglodConfig::hashgrid_small`] for the hash grid; SIREN, which has none, gets NGLOD's)
    /// with these values over it, seeded and validated. For the hash grid, `--sparse-levels`
    /// and `--band-cells` are an error ([`RunError::Options`]) and an invalid configuration is
    /// [`RunError::Hashgrid`].
    pub fn config(
        &self,
        model: ModelKind,
        preset: Preset,
        seed: u64,
    ) -> Result<NglodConfig, RunError> {
        let base = match (model, preset) {
            (ModelKind::Hashgrid, Preset::Default) => NglodConfig::hashgrid_default(),
            (ModelKind::Hashgrid, Preset::Small) => NglodConfig::hashgrid_small(),
            (_, Preset::Default) => NglodConfig::default_preset(),
            (_, Preset::Small) => NglodConfig::small(),
        };
        if model == ModelKind::Hashgrid {
            let given: Vec<&str> = [
                ("--sparse-levels", self.sparse_levels.is_some()),
                ("--band-cells", self.band_cells.is_some()),
            ]
            .into_iter()
            .filter_map(|(flag, given)| given.then_some(flag))
            .collect();
            if !given.is_empty() {
                return Err(RunError::Options(format!(
                    "{} set{} NGLOD's sparse levels; a hash grid has none (its fine levels are \
                     hashed into tables): leave {} out, or use --model nglod",
                    given.join(" and "),
                    if given.len() == 1 { "s" } else { "" },
                    if given.len() == 1 { "it" } else { "them" },
                )));
            }
        }
        let config = NglodConfig {
            resolutions: self.resolutions.clone().unwrap_or(base.resolutions),
            sparse_levels: self.sparse_levels.unwrap_or(base.sparse_levels),
            feature_dim: self.feature_dim.unwrap_or(base.feature_dim),
            hidden: self.hidden.unwrap_or(base.hidden),
            seed,
            band_cells: self.band_cells.unwrap_or(base.band_cells),
            encoding: base.encoding,
        };
        config.validate().map_err(|e| super::grid_error(model, e))?;
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

/// NGLOD's default run on a CPU adapter: as many epochs as about a minute of training buys
/// there (issue 14: "the best fit that about a minute buys"), planned from the first epoch,
/// between [`default_length`]'s and a GPU's default. On the 2-core box that is ~13 epochs with Debian 12's
/// Mesa 22.3 and ~35 with Mesa 26.1 (docs/benchmarks).
pub const CPU_TIME_BUDGET: sdf_nn::nglod::TimeBudget = sdf_nn::nglod::TimeBudget {
    seconds: 55.0,
    max_epochs: DEFAULT_EPOCHS,
};

/// The hash grid's default run on a CPU adapter: as [`CPU_TIME_BUDGET`], about a minute of
/// training, up to its GPU default [`HASHGRID_EPOCHS`].
pub const HASHGRID_CPU_TIME_BUDGET: sdf_nn::nglod::TimeBudget = sdf_nn::nglod::TimeBudget {
    seconds: CPU_TIME_BUDGET.seconds,
    max_epochs: HASHGRID_EPOCHS,
};

/// The time a grid model's default run fills on a CPU adapter: [`CPU_TIME_BUDGET`] (NGLOD),
/// [`HASHGRID_CPU_TIME_BUDGET`] (the hash grid); `None` for SIREN, which trains a fixed number
/// of steps.
pub fn cpu_time_budget(model: ModelKind) -> Option<TimeBudget> {
    match model {
        ModelKind::Siren => None,
        ModelKind::Nglod => Some(CPU_TIME_BUDGET),
        ModelKind::Hashgrid => Some(HASHGRID_CPU_TIME_BUDGET),
    }
}

/// The least a hash grid's `small` run trains on a CPU adapter by default (its time budget
/// plans more where they fit): an epoch takes about 5 s on the 2-core box with Debian 12's
/// lavapipe (suzanne; 2 epochs already give F1 0.995 in the box, 0.95 near the surface), so
/// about 20 s, and the budget plans about 11.
const HASHGRID_CPU_SMALL_EPOCHS: usize = 4;

/// The least a hash grid's `default` run trains on a CPU adapter by default: an epoch of its
/// 5.8 M parameters takes about 18 s there, so about 36 s (and the budget plans about 3).
const HASHGRID_CPU_DEFAULT_EPOCHS: usize = 2;

/// Default SIREN steps and NGLOD and hash-grid epochs: what converges on a GPU for the design
/// document's presets (the trainers' own defaults, [`SirenTrainConfig`]'s steps,
/// [`DEFAULT_EPOCHS`] and [`HASHGRID_EPOCHS`]), and a budget of a few minutes on a CPU adapter
/// (lavapipe); for the grid models there, the least of their [`cpu_time_budget`]. Runs read it
/// through [`TrainOptions::length`].
pub fn default_length(model: ModelKind, preset: Preset, cpu_adapter: bool) -> usize {
    match (model, preset, cpu_adapter) {
        (ModelKind::Siren, _, false) => SirenTrainConfig::default().steps,
        (ModelKind::Siren, Preset::Small, true) => 300,
        (ModelKind::Siren, Preset::Default, true) => 100,
        (ModelKind::Nglod, _, false) => DEFAULT_EPOCHS,
        (ModelKind::Nglod, Preset::Small, true) => 4,
        // About a minute on the 2-core box with lavapipe (8 epochs: 31-77 s of training under load).
        (ModelKind::Nglod, Preset::Default, true) => 12,
        (ModelKind::Hashgrid, _, false) => HASHGRID_EPOCHS,
        (ModelKind::Hashgrid, Preset::Small, true) => HASHGRID_CPU_SMALL_EPOCHS,
        (ModelKind::Hashgrid, Preset::Default, true) => HASHGRID_CPU_DEFAULT_EPOCHS,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
            "NGLOD and the hash grid only",
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
        for batch in [0, MAX_BATCH + 1] {
            refused(
                TrainOptions {
                    batch: Some(batch),
                    ..nglod.clone()
                },
                "--batch must lie in",
            );
        }
        refused(
            TrainOptions {
                batch: Some(4096),
                ..siren.clone()
            },
            "--batch applies to NGLOD",
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
            batch: Some(2048),
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
             batch 2048; distance signed; epochs 100; grow every 0; lr 0.001; lr final 0.1; \
             pool 4,4; preset default; seed 0"
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
        // An architecture that does not resolve has no settings.
        let bad = TrainOptions {
            nglod_architecture: NglodArchitecture {
                hidden: Some(0),
                ..Default::default()
            },
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
        assert_eq!(
            none.config(ModelKind::Nglod, Preset::Default, 7).unwrap(),
            seeded
        );
        assert_eq!(
            none.config(ModelKind::Nglod, Preset::Small, 0).unwrap(),
            NglodConfig::small()
        );
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
        let c = fine.config(ModelKind::Nglod, Preset::Small, 3).unwrap();
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
            let e = bad
                .config(ModelKind::Nglod, Preset::Default, 0)
                .unwrap_err();
            assert!(
                matches!(e, RunError::Nglod(sdf_nn::NglodError::InvalidConfig(_))),
                "{bad:?}: {e}"
            );
        }
    }

    #[test]
    fn the_hash_grid_has_its_presets_schedule_and_length() {
        let hashgrid = ModelKind::Hashgrid;
        assert_eq!((hashgrid.name(), hashgrid.unit()), ("hashgrid", "epoch"));
        assert!(hashgrid.is_grid() && ModelKind::Nglod.is_grid() && !ModelKind::Siren.is_grid());
        // Every place that defaults to a learning rate reads the model's own.
        assert_eq!(
            ModelKind::ALL.map(ModelKind::default_lr),
            [1e-4, 1e-3, NglodTrainConfig::hashgrid().adam.lr]
        );
        assert_ne!(hashgrid.default_lr(), ModelKind::Nglod.default_lr());
        assert_eq!(hashgrid.grid_schedule(), Some(NglodTrainConfig::hashgrid()));
        // Its presets: `small` on a CPU adapter (as SIREN's), `default` on a GPU.
        assert_eq!(Preset::for_adapter(true, hashgrid), Preset::Small);
        assert_eq!(Preset::for_adapter(false, hashgrid), Preset::Default);
        assert_eq!(Preset::for_adapter(true, ModelKind::Nglod), Preset::Default);
        let none = NglodArchitecture::default();
        assert_eq!(
            none.config(hashgrid, Preset::Default, 0).unwrap(),
            NglodConfig::hashgrid_default()
        );
        assert_eq!(
            none.config(hashgrid, Preset::Small, 0).unwrap(),
            NglodConfig::hashgrid_small()
        );
        // Its length: HASHGRID_EPOCHS on a GPU, its own time budget on a CPU adapter.
        let options = TrainOptions::new(hashgrid, Preset::Small);
        let gpu = options.length(false);
        assert_eq!(
            (gpu.asked, gpu.default, gpu.time_budget),
            (None, HASHGRID_EPOCHS, None)
        );
        let cpu = options.length(true);
        assert_eq!(cpu.time_budget, Some(HASHGRID_CPU_TIME_BUDGET));
        assert_eq!(HASHGRID_CPU_TIME_BUDGET.max_epochs, HASHGRID_EPOCHS);
        assert!(cpu.default >= 1 && cpu.default <= HASHGRID_EPOCHS);
        let asked = TrainOptions {
            epochs: Some(3),
            ..options.clone()
        };
        assert_eq!(asked.length(true).time_budget, None);
        // Its settings: its schedule's rate and its table, no levels of detail.
        let settings = TrainOptions::new(hashgrid, Preset::Default)
            .settings(false)
            .unwrap();
        let (c, d) = (
            NglodConfig::hashgrid_default(),
            NglodTrainConfig::hashgrid(),
        );
        let Encoding::Hashed { log2_table_size } = c.encoding else {
            panic!("hashgrid_default is not hashed")
        };
        assert_eq!(
            settings.to_string(),
            format!(
                "architecture resolutions {}, table 2^{log2_table_size}, features {}, hidden {}; \
                 batch {}; distance signed; epochs {HASHGRID_EPOCHS}; lr {}; lr final {}; \
                 pool {},{}; preset default; seed 0",
                comma_list(&c.resolutions),
                c.feature_dim,
                c.hidden,
                d.batch_size,
                d.adam.lr,
                d.lr_final.unwrap_or(1.0),
                d.pool_blocks,
                d.refresh_every
            )
        );
        assert_eq!(
            options.settings(true).unwrap().0["epochs"],
            format!(
                "about 55 s of training ({} to {HASHGRID_EPOCHS})",
                cpu.default
            )
        );
    }

    #[test]
    fn options_that_do_not_apply_to_a_hash_grid_are_refused() {
        let hashgrid = TrainOptions::new(ModelKind::Hashgrid, Preset::Small);
        assert!(hashgrid.validate().is_ok());
        // What applies to NGLOD applies to it.
        let nglod_like = TrainOptions {
            epochs: Some(2),
            lr: Some(3e-3),
            lr_final: Some(1.0),
            pool: Some((1, 1)),
            distance: DistanceMode::Unsigned,
            nglod_architecture: NglodArchitecture {
                resolutions: Some(vec![8, 16, 32, 64]),
                feature_dim: Some(4),
                hidden: Some(16),
                ..Default::default()
            },
            ..hashgrid.clone()
        };
        nglod_like.validate().unwrap();
        let c = nglod_like
            .nglod_architecture
            .config(ModelKind::Hashgrid, Preset::Small, 0)
            .unwrap();
        assert_eq!(
            (c.architecture(), c.input_dim(), c.hidden),
            ("hashgrid", 16, 16)
        );
        let refused = |o: TrainOptions, says: &str| {
            let e = o.validate().unwrap_err();
            assert!(matches!(e, RunError::Options(_)), "{e:?}");
            let e = e.to_string();
            assert!(e.contains(says), "{says:?} not in {e:?}");
        };
        for grow in [0, 2] {
            refused(
                TrainOptions {
                    grow_every: Some(grow),
                    ..hashgrid.clone()
                },
                "--grow-every adds NGLOD's levels of detail",
            );
        }
        refused(
            TrainOptions {
                nglod_architecture: NglodArchitecture {
                    sparse_levels: Some(0),
                    ..Default::default()
                },
                ..hashgrid.clone()
            },
            "--sparse-levels sets NGLOD's sparse levels; a hash grid has none",
        );
        refused(
            TrainOptions {
                nglod_architecture: NglodArchitecture {
                    band_cells: Some(1),
                    ..Default::default()
                },
                ..hashgrid.clone()
            },
            "--band-cells sets NGLOD's sparse levels",
        );
        refused(
            TrainOptions {
                steps: Some(3),
                ..hashgrid.clone()
            },
            "--steps applies to SIREN; the hash grid trains for --epochs",
        );
        refused(
            TrainOptions {
                siren_weights: Some(LossWeights::default()),
                ..hashgrid.clone()
            },
            "loss weights apply to SIREN",
        );
        refused(
            TrainOptions {
                plateau_patience: Some(3),
                ..hashgrid.clone()
            },
            "--plateau-patience applies to SIREN",
        );
        // An architecture the kernels cannot take is the model's own typed error: 9 levels of
        // 4 features are 36 MLP inputs.
        let wide = TrainOptions {
            nglod_architecture: NglodArchitecture {
                resolutions: Some(vec![8, 12, 16, 24, 32, 48, 64, 96, 128]),
                feature_dim: Some(4),
                ..Default::default()
            },
            ..hashgrid
        };
        let e = wide.validate().unwrap_err();
        assert!(
            matches!(e, RunError::Hashgrid(sdf_nn::NglodError::InvalidConfig(_))),
            "{e:?}"
        );
        assert!(e.to_string().starts_with("hash grid: "), "{e}");
    }
}
