//! The training flags `train` and `corpus` share: one definition, so that both binaries take the
//! same options with the same meaning, defaults and checks. They become [`TrainOptions`], whose
//! [`TrainOptions::validate`] is their one check and whose [`TrainOptions::length`] settles the
//! default length.

use clap::ValueEnum;
use sdf_eval::metrics::DEFAULT_EVAL_POINTS;
use sdf_eval::run::{ModelKind, NglodArchitecture, Preset, RunError, TrainOptions};
use sdf_nn::{DistanceMode, LossWeights};

/// `--preset`.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum PresetArg {
    /// The design document's architectures.
    Default,
    /// Small networks for CPU-only machines and tests.
    Small,
}

/// `--distance`.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DistanceArg {
    /// The signed distance.
    Signed,
    /// The unsigned distance |d|.
    Unsigned,
}

/// How long to train, on what, and with which architecture and loss.
#[derive(clap::Args, Debug)]
pub struct TrainingFlags {
    /// Size preset (default: `default`; SIREN's is `small` on a CPU adapter).
    #[arg(long, value_enum)]
    pub preset: Option<PresetArg>,
    /// SIREN training steps (default: 10000 on a GPU, a few hundred on a CPU adapter).
    #[arg(long)]
    pub steps: Option<usize>,
    /// NGLOD epochs of 5·10^5 points (default: 100 on a GPU; on a CPU adapter as many as about
    /// a minute of training buys, at least 12).
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Seed of initialisation and sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Points in each evaluation set.
    #[arg(long, default_value_t = DEFAULT_EVAL_POINTS)]
    pub eval_points: usize,
    /// Initial learning rate (default: 1e-4 for SIREN, 1e-3 for NGLOD).
    // The float flags take negative numbers, so that the checks say what is wrong with
    // `--lr -1` (clap would read `-1` as an unknown flag).
    #[arg(long, allow_negative_numbers = true)]
    pub lr: Option<f32>,
    /// NGLOD: final learning rate as a fraction of the first, by cosine decay over the run
    /// (default 0.1; 1 keeps it constant).
    #[arg(long, allow_negative_numbers = true)]
    pub lr_final: Option<f32>,
    /// SIREN: steps without a 0.1 % improvement of the loss before the learning rate is
    /// divided by 10 (default 500; 0 keeps it constant, as the SIREN reference code trains).
    #[arg(long)]
    pub plateau_patience: Option<usize>,
    /// NGLOD: progressive levels of detail, one more every this many epochs (0: all at once).
    #[arg(long)]
    pub grow_every: Option<usize>,
    /// NGLOD: blocks of one epoch's worth of labelled points in the sample pool, and epochs
    /// between fresh blocks once it is full, as BLOCKS,EVERY (default 4,4; 1,1 samples fresh
    /// points every epoch).
    #[arg(long, value_parser = parse_pool)]
    pub pool: Option<(usize, usize)>,
    /// Fit the signed distance, or the unsigned one |d| for meshes without an inside (flat or
    /// open sheets, two-sided triangle soups); unsigned is scored by distance error and Chamfer
    /// distance, not F1. NGLOD only.
    #[arg(long, value_enum, default_value = "signed")]
    pub distance: DistanceArg,
    /// NGLOD: cells per axis of each level of detail, coarse to fine, comma-separated
    /// (`default`: 6,12,24,48; `small`: 4,8,16).
    #[arg(long, value_delimiter = ',', help_heading = "NGLOD architecture")]
    pub resolutions: Option<Vec<u32>>,
    /// NGLOD: how many of the finest levels keep features only near the surface, at most 255
    /// cells each (`default`: 1; `small`: 0).
    #[arg(long, help_heading = "NGLOD architecture")]
    pub sparse_levels: Option<usize>,
    /// NGLOD: how far the sparse levels reach beyond the cells the surface passes through, in
    /// cells, at most 4 (default 0; 1, the default before, makes files 18-43 % larger for F1
    /// within 0.001 on average, docs/benchmarks/2026-11-23-nglod-band-width.md).
    #[arg(long, help_heading = "NGLOD architecture")]
    pub band_cells: Option<u32>,
    /// NGLOD: features per grid vertex (`default`: 8; `small`: 4).
    #[arg(long, help_heading = "NGLOD architecture")]
    pub features: Option<u32>,
    /// NGLOD: hidden width of the MLP (`default`: 128; `small`: 32).
    #[arg(long, help_heading = "NGLOD architecture")]
    pub hidden: Option<u32>,
    /// SIREN loss: weight of the on-surface |Φ| term (default 3000).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub surface_weight: Option<f32>,
    /// SIREN loss: weight of the off-surface exp(−α|Φ|) term (default 100).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub off_surface_weight: Option<f32>,
    /// SIREN loss: weight of the normal term 1 − cos(∇Φ, n) (default 100).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub normal_weight: Option<f32>,
    /// SIREN loss: weight of the eikonal term |‖∇Φ‖ − 1| (default 5; the SIREN code uses 50).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub eikonal_weight: Option<f32>,
    /// SIREN loss: sharpness α of the off-surface term (default 100).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub alpha: Option<f32>,
    /// SIREN loss: weight of the sign term max(0, −s Φ) on box points, s = −1 inside and +1
    /// outside by the ground truth's winding number (default 1000; 0 trains on the design
    /// document's four terms alone).
    #[arg(long, help_heading = "SIREN loss", allow_negative_numbers = true)]
    pub sign_weight: Option<f32>,
}

impl TrainingFlags {
    /// The preset asked for, if any.
    pub fn preset(&self) -> Option<Preset> {
        self.preset.map(|p| match p {
            PresetArg::Default => Preset::Default,
            PresetArg::Small => Preset::Small,
        })
    }

    /// The preset of `model`'s runs: the one asked for, else the adapter's.
    pub fn preset_for(&self, model: ModelKind, cpu_adapter: bool) -> Preset {
        self.preset()
            .unwrap_or_else(|| Preset::for_adapter(cpu_adapter, model))
    }

    /// Every model's options for a run of `models`, each flag checked once, before the GPU is
    /// opened or a mesh is read: the evaluation's size, then [`TrainOptions::validate`] of each
    /// model's options. Their preset is the one asked for, else `default` until the adapter is
    /// open: [`TrainOptions::with_preset`] then sets the adapter's ([`Self::preset_for`]).
    pub fn options(&self, models: &[ModelKind]) -> Result<Vec<TrainOptions>, RunError> {
        super::check_eval_points("--eval-points", self.eval_points)?;
        let preset = self.preset().unwrap_or(Preset::Default);
        models
            .iter()
            .map(|&model| self.model_options(model, preset, models))
            .collect()
    }

    /// The options of `model`'s runs in a run of `models`, validated. A flag that applies to one
    /// model only goes to that model when both run (`--steps` to SIREN, `--epochs` and the
    /// NGLOD flags to NGLOD, the loss weights to SIREN), and is an error when only the other
    /// runs. `--lr` is refused when both run: their defaults differ tenfold.
    fn model_options(
        &self,
        model: ModelKind,
        preset: Preset,
        models: &[ModelKind],
    ) -> Result<TrainOptions, RunError> {
        let both = models.contains(&ModelKind::Siren) && models.contains(&ModelKind::Nglod);
        if both && self.lr.is_some() {
            return Err(RunError::Options(
                "--lr sets one model's learning rate (SIREN's default is 1e-4, NGLOD's 1e-3); \
                 with both models, run each with its own --model"
                    .into(),
            ));
        }
        // With both models, a flag of the other model is not this one's.
        let keep = |of: ModelKind| !both || of == model;
        let options = TrainOptions {
            model,
            preset,
            steps: self.steps.filter(|_| keep(ModelKind::Siren)),
            epochs: self.epochs.filter(|_| keep(ModelKind::Nglod)),
            seed: self.seed,
            lr: self.lr,
            siren_weights: self.siren_weights().filter(|_| keep(ModelKind::Siren)),
            plateau_patience: self.plateau_patience.filter(|_| keep(ModelKind::Siren)),
            lr_final: self.lr_final.filter(|_| keep(ModelKind::Nglod)),
            grow_every: self.grow_every.filter(|_| keep(ModelKind::Nglod)),
            distance: match self.distance {
                DistanceArg::Signed => DistanceMode::Signed,
                DistanceArg::Unsigned => DistanceMode::Unsigned,
            },
            pool: self.pool.filter(|_| keep(ModelKind::Nglod)),
            nglod_architecture: if keep(ModelKind::Nglod) {
                self.nglod_architecture()
            } else {
                NglodArchitecture::default()
            },
        };
        options.validate()?;
        Ok(options)
    }

    /// The NGLOD architecture flags given.
    fn nglod_architecture(&self) -> NglodArchitecture {
        NglodArchitecture {
            resolutions: self.resolutions.clone(),
            sparse_levels: self.sparse_levels,
            feature_dim: self.features,
            hidden: self.hidden,
            band_cells: self.band_cells,
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
            self.sign_weight,
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
            sign: self.sign_weight.unwrap_or(d.sign),
        })
    }
}

fn parse_pool(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("expected BLOCKS,EVERY, not {s:?}"))?;
    // Zeros parse: TrainOptions::validate refuses them, for the library's callers too.
    let parse = |x: &str| {
        x.trim()
            .parse::<usize>()
            .map_err(|_| format!("{x:?} is not a positive integer"))
    };
    Ok((parse(a)?, parse(b)?))
}
