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
    /// Size preset (default: `default`; SIREN's and the hash grid's are `small` on a CPU
    /// adapter; `train --resume` keeps its checkpoint's).
    #[arg(long, value_enum)]
    pub preset: Option<PresetArg>,
    /// SIREN training steps (default: 10000 on a GPU; on a CPU adapter 300 for `small`, 100
    /// for `default`).
    #[arg(long)]
    pub steps: Option<usize>,
    /// NGLOD and hash-grid epochs of 5·10^5 points (default on a GPU: 100 for NGLOD, 50 for the
    /// hash grid; on a CPU adapter as many as about a minute of training buys, at least 12 for
    /// NGLOD `default`, 4 for NGLOD `small` and the hash grid's `small`, 2 for its `default`).
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Seed of initialisation and sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Points in each evaluation set.
    #[arg(long, default_value_t = DEFAULT_EVAL_POINTS)]
    pub eval_points: usize,
    /// Initial learning rate (default: 1e-4 for SIREN, 1e-3 for NGLOD, 2.5e-3 for the hash grid).
    /// A resume goes on where the checkpoint's schedule had brought the rate, scaled by how this
    /// first rate differs from its run's.
    // The float flags take negative numbers, so that the checks say what is wrong with
    // `--lr -1` (clap would read `-1` as an unknown flag).
    #[arg(long, allow_negative_numbers = true)]
    pub lr: Option<f32>,
    /// NGLOD and the hash grid: final learning rate as a fraction of the first, by cosine decay
    /// over the run (default 0.1; 1 keeps it constant).
    #[arg(long, allow_negative_numbers = true)]
    pub lr_final: Option<f32>,
    /// NGLOD and the hash grid: points per optimiser step (default 2048).
    #[arg(long)]
    pub batch: Option<u32>,
    /// SIREN: steps without a 0.1 % improvement of the loss before the learning rate is
    /// divided by 10 (default 500; 0 keeps it constant, as the SIREN reference code trains).
    #[arg(long)]
    pub plateau_patience: Option<usize>,
    /// NGLOD only: progressive levels of detail, one more every this many epochs (0: all at
    /// once). A hash grid has no levels of detail.
    #[arg(long)]
    pub grow_every: Option<usize>,
    /// NGLOD and the hash grid: blocks of one epoch's worth of labelled points in the sample
    /// pool, and epochs between fresh blocks once it is full, as BLOCKS,EVERY (default 4,4; 1,1
    /// samples fresh points every epoch).
    #[arg(long, value_parser = parse_pool)]
    pub pool: Option<(usize, usize)>,
    /// Fit the signed distance, or the unsigned one |d| for meshes without an inside (flat or
    /// open sheets, two-sided triangle soups); unsigned is scored by distance error and Chamfer
    /// distance, not F1. NGLOD and the hash grid only.
    #[arg(long, value_enum, default_value = "signed")]
    pub distance: DistanceArg,
    /// Cells per axis of each level, coarse to fine, comma-separated (NGLOD `default`:
    /// 6,12,24,48; `small`: 4,8,16. Hash grid: one level per value, `default` 16 levels from 16
    /// to 512 cells, `small` from 8 to 256).
    #[arg(
        long,
        value_delimiter = ',',
        help_heading = "NGLOD and hash grid architecture"
    )]
    pub resolutions: Option<Vec<u32>>,
    /// NGLOD only: how many of the finest levels keep features only near the surface, at most
    /// 255 cells each (`default`: 1; `small`: 0).
    #[arg(long, help_heading = "NGLOD and hash grid architecture")]
    pub sparse_levels: Option<usize>,
    /// NGLOD only: how far the sparse levels reach beyond the cells the surface passes through,
    /// in cells, at most 4 (default 0; 1, the default before, makes files 18-43 % larger for F1
    /// within 0.001 on average, docs/benchmarks/2026-11-23-nglod-band-width.md).
    #[arg(long, help_heading = "NGLOD and hash grid architecture")]
    pub band_cells: Option<u32>,
    /// Features per grid vertex (NGLOD `default`: 8; `small`: 4. Hash grid: per level, 2; its
    /// levels' features together are at most 32).
    #[arg(long, help_heading = "NGLOD and hash grid architecture")]
    pub features: Option<u32>,
    /// Hidden width of the MLP (NGLOD `default`: 128; `small`: 32. Hash grid `default`: 64;
    /// `small`: 32).
    #[arg(long, help_heading = "NGLOD and hash grid architecture")]
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

    /// Whether a flag describes NGLOD's architecture or schedule (`--grow-every`,
    /// `--sparse-levels`, `--band-cells`, which only NGLOD has, or `--resolutions`, `--features`
    /// and `--hidden`, which mean other things for the hash grid): `train` without `--model`
    /// then fits NGLOD, as such command lines did before its default depended on the adapter.
    pub fn describes_nglod(&self) -> bool {
        self.grow_every.is_some()
            || self.sparse_levels.is_some()
            || self.band_cells.is_some()
            || self.resolutions.is_some()
            || self.features.is_some()
            || self.hidden.is_some()
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

    /// The options of `model`'s runs in a run of `models`, validated. With one model every flag
    /// goes to it, and one that does not apply to it is an error. With several, a flag goes to
    /// the models it applies to (`--steps` and the loss weights to SIREN; `--epochs`,
    /// `--lr-final`, `--pool` and the architecture flags to NGLOD and the hash grid;
    /// `--grow-every`, `--sparse-levels` and `--band-cells` to NGLOD). `--lr` is refused when
    /// several run, their defaults differ tenfold; so are `--resolutions`, `--features` and
    /// `--hidden` when both NGLOD and the hash grid run, whose architectures they describe
    /// differently.
    fn model_options(
        &self,
        model: ModelKind,
        preset: Preset,
        models: &[ModelKind],
    ) -> Result<TrainOptions, RunError> {
        let several = models.iter().any(|&m| m != model);
        if several && self.lr.is_some() {
            return Err(RunError::Options(
                "--lr sets one model's learning rate (SIREN's default is 1e-4, NGLOD's 1e-3, \
                 the hash grid's 2.5e-3); with several models, run each with its own --model"
                    .into(),
            ));
        }
        let both_grids =
            models.contains(&ModelKind::Nglod) && models.contains(&ModelKind::Hashgrid);
        if both_grids
            && (self.resolutions.is_some() || self.features.is_some() || self.hidden.is_some())
        {
            return Err(RunError::Options(
                "--resolutions, --features and --hidden describe NGLOD's architecture and the \
                 hash grid's differently; with both models, run each with its own --model"
                    .into(),
            ));
        }
        // With several models, a flag goes only to the models it applies to.
        const SIREN: &[ModelKind] = &[ModelKind::Siren];
        const GRIDS: &[ModelKind] = &[ModelKind::Nglod, ModelKind::Hashgrid];
        const NGLOD: &[ModelKind] = &[ModelKind::Nglod];
        let keep = |to: &[ModelKind]| !several || to.contains(&model);
        let options = TrainOptions {
            model,
            preset,
            steps: self.steps.filter(|_| keep(SIREN)),
            epochs: self.epochs.filter(|_| keep(GRIDS)),
            seed: self.seed,
            lr: self.lr,
            siren_weights: self.siren_weights().filter(|_| keep(SIREN)),
            plateau_patience: self.plateau_patience.filter(|_| keep(SIREN)),
            lr_final: self.lr_final.filter(|_| keep(GRIDS)),
            batch: self.batch.filter(|_| keep(GRIDS)),
            grow_every: self.grow_every.filter(|_| keep(NGLOD)),
            // SIREN fits signed distances only: with other models, `unsigned` is theirs.
            distance: match self.distance {
                DistanceArg::Unsigned if keep(GRIDS) => DistanceMode::Unsigned,
                _ => DistanceMode::Signed,
            },
            pool: self.pool.filter(|_| keep(GRIDS)),
            nglod_architecture: NglodArchitecture {
                resolutions: self.resolutions.clone().filter(|_| keep(GRIDS)),
                sparse_levels: self.sparse_levels.filter(|_| keep(NGLOD)),
                feature_dim: self.features.filter(|_| keep(GRIDS)),
                hidden: self.hidden.filter(|_| keep(GRIDS)),
                band_cells: self.band_cells.filter(|_| keep(NGLOD)),
            },
        };
        options.validate()?;
        Ok(options)
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Flags {
        #[command(flatten)]
        training: TrainingFlags,
    }

    fn flags(args: &[&str]) -> TrainingFlags {
        Flags::parse_from(std::iter::once("test").chain(args.iter().copied())).training
    }

    /// With several models a flag goes to those it applies to; with one, to it (and is refused
    /// where it does not apply).
    #[test]
    fn flags_go_to_the_models_they_apply_to() {
        let all = ModelKind::ALL;
        let f = flags(&["--epochs", "3", "--grow-every", "2", "--steps", "5"]);
        let options = f.options(&all).unwrap();
        let of = |m: ModelKind| options.iter().find(|o| o.model == m).unwrap();
        assert_eq!(of(ModelKind::Siren).steps, Some(5));
        assert_eq!(of(ModelKind::Siren).epochs, None);
        assert_eq!(of(ModelKind::Nglod).grow_every, Some(2));
        assert_eq!(of(ModelKind::Hashgrid).epochs, Some(3));
        assert_eq!(of(ModelKind::Hashgrid).grow_every, None);
        // `unsigned` goes to the grid models (SIREN, which fits signed distances only, refused
        // it and with it the whole run); alone, SIREN still refuses it.
        let unsigned = flags(&["--distance", "unsigned"]);
        let options = unsigned.options(&all).unwrap();
        let distances: Vec<DistanceMode> = options.iter().map(|o| o.distance).collect();
        assert_eq!(
            distances,
            [
                DistanceMode::Signed,
                DistanceMode::Unsigned,
                DistanceMode::Unsigned
            ]
        );
        assert!(unsigned.options(&[ModelKind::Siren]).is_err());
        assert!(
            flags(&["--grow-every", "2"])
                .options(&[ModelKind::Hashgrid])
                .is_err()
        );
        // NGLOD's sparse levels go to NGLOD; the hash grid keeps its preset.
        let f = flags(&["--sparse-levels", "0", "--band-cells", "1"]);
        let options = f.options(&all).unwrap();
        assert!(options[2].nglod_architecture.is_preset());
        assert_eq!(options[1].nglod_architecture.band_cells, Some(1));
        // Both grid models: the shared architecture flags would mean two things.
        for flag in [
            ["--resolutions", "4,8"],
            ["--features", "1"],
            ["--hidden", "16"],
        ] {
            let e = flags(&flag).options(&all).unwrap_err().to_string();
            assert!(e.contains("run each with its own --model"), "{e}");
            for one in [ModelKind::Nglod, ModelKind::Hashgrid] {
                assert!(flags(&flag).options(&[one]).is_ok(), "{flag:?} {one:?}");
            }
            let both = flags(&flag)
                .options(&[ModelKind::Siren, ModelKind::Nglod])
                .unwrap();
            assert!(
                both[0].nglod_architecture.is_preset() && !both[1].nglod_architecture.is_preset()
            );
        }
        let e = flags(&["--lr", "1e-3"])
            .options(&all)
            .unwrap_err()
            .to_string();
        assert!(e.contains("the hash grid's 2.5e-3"), "{e}");
        assert!(
            flags(&["--lr", "1e-3"])
                .options(&[ModelKind::Hashgrid])
                .is_ok()
        );
    }

    /// Each model's preset is the one asked for, else its adapter's (`train` and `corpus`
    /// alike): `small` for SIREN and the hash grid on a CPU adapter, `default` otherwise.
    #[test]
    fn each_model_gets_its_adapters_preset_unless_one_is_asked() {
        let none = flags(&[]);
        for (model, cpu, preset) in [
            (ModelKind::Siren, true, Preset::Small),
            (ModelKind::Hashgrid, true, Preset::Small),
            (ModelKind::Nglod, true, Preset::Default),
            (ModelKind::Siren, false, Preset::Default),
            (ModelKind::Hashgrid, false, Preset::Default),
        ] {
            assert_eq!(none.preset_for(model, cpu), preset, "{model:?}, cpu {cpu}");
        }
        let asked = flags(&["--preset", "small"]);
        assert_eq!(asked.preset_for(ModelKind::Nglod, false), Preset::Small);
    }

    /// The flags that describe NGLOD's architecture or schedule, and only they, keep NGLOD as
    /// `train`'s model without `--model`.
    #[test]
    fn architecture_flags_describe_nglod() {
        for flag in [
            &["--resolutions", "4,8"][..],
            &["--features", "4"],
            &["--hidden", "16"],
            &["--sparse-levels", "0"],
            &["--band-cells", "1"],
            &["--grow-every", "2"],
        ] {
            assert!(flags(flag).describes_nglod(), "{flag:?}");
        }
        for flag in [
            &[][..],
            &["--epochs", "3"],
            &["--lr", "1e-3"],
            &["--batch", "1024"],
            &["--preset", "default"],
            &["--pool", "2,2"],
        ] {
            assert!(!flags(flag).describes_nglod(), "{flag:?}");
        }
    }
}
