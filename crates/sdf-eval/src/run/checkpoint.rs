//! Checkpoints: what an interrupted run saves (the model so far, the optimiser's moments, the
//! progress counters) and the checks a resume makes before it continues from one.

use std::path::Path;

use sdf_nn::nglod::Encoding;
use sdf_nn::{AdamState, ModelFile, NeuralSdf, Nglod};

use super::{ModelKind, NglodArchitecture, Preset, RunError, TrainOptions, Trained};

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
        Self::from_file(Self::read(path)?, path)
    }

    /// The file at `path`, read but not yet checked: [`Self::model_of`] names its model before
    /// [`Self::from_file`] makes it a checkpoint, without a second read.
    pub fn read(path: &Path) -> Result<ModelFile, RunError> {
        Ok(ModelFile::load(path)?)
    }

    /// [`Self::load`] of a file already read from `path`.
    pub fn from_file(file: ModelFile, path: &Path) -> Result<Self, RunError> {
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
            let unit = c.model().map_or("step or epoch", ModelKind::unit);
            return Err(bad(format!(
                "{} {unit}s done of {planned} planned",
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

    /// The run's record (the model file's `training` metadata): its settings and progress.
    pub fn training(&self) -> &serde_json::Value {
        &self.file.metadata.training
    }

    /// Steps or epochs done when it was written.
    pub fn done(&self) -> usize {
        self.file.metadata.training["done"].as_u64().unwrap_or(0) as usize
    }

    /// The steps or epochs its run planned (NGLOD's and the hash grid's with the CPU time
    /// budget, more than the default), which a resume without `--steps` or `--epochs` goes on
    /// to. Absent from SIREN checkpoints written before 2026-11-28.
    pub fn planned(&self) -> Option<usize> {
        self.file.metadata.training["planned"]
            .as_u64()
            .map(|p| p as usize)
    }

    /// Whether its run's CPU time budget had yet to plan the run's length (stopped before two
    /// epochs ran whole): a resume then keeps what is left of the budget instead of stopping at
    /// the least length ([`Self::planned`]), which is all that run had recorded.
    pub fn plan_pending(&self) -> bool {
        self.file.metadata.training["plan_pending"] == serde_json::Value::Bool(true)
    }

    /// Seconds its runs trained (`train_seconds` in the run record; 0 where absent or not a
    /// finite, non-negative number: checkpoints from before 2026-11-28 have none).
    pub fn train_seconds(&self) -> f64 {
        self.seconds("train_seconds").unwrap_or(0.0)
    }

    /// Seconds of its runs' time budget spent: the trainers' own time (`budget_seconds`, which
    /// the budget counts, without the setup `train_seconds` includes), else `train_seconds`.
    pub fn budget_seconds(&self) -> f64 {
        self.seconds("budget_seconds")
            .unwrap_or_else(|| self.train_seconds())
    }

    /// The run record's `key`, where it is a finite, non-negative number of seconds.
    fn seconds(&self, key: &str) -> Option<f64> {
        self.file.metadata.training[key]
            .as_f64()
            .filter(|s| s.is_finite() && *s >= 0.0)
    }

    /// NGLOD and the hash grid: optimiser steps done within the unfinished epoch `done()`, which a resume finishes.
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

    /// The model a checkpoint's `file` names, without the checks of [`Self::from_file`]
    /// (`None` where it names none this build trains): what a resume fits when no model is
    /// asked for, known before the other checks of the command line run.
    pub fn model_of(file: &ModelFile) -> Option<ModelKind> {
        file.metadata.training["model"]
            .as_str()
            .and_then(ModelKind::from_name)
    }

    /// The model it is of: what a resume fits when no model is asked for.
    pub fn model(&self) -> Result<ModelKind, RunError> {
        Self::model_of(&self.file).ok_or_else(|| {
            self.refusal(format!(
                "the checkpoint names no model this build trains ({})",
                self.options().0.as_deref().unwrap_or("none")
            ))
        })
    }

    /// The preset it was trained with: what a resume keeps when no preset is asked for.
    pub fn preset(&self) -> Result<Preset, RunError> {
        let has = self.options().1;
        has.as_deref().and_then(Preset::from_name).ok_or_else(|| {
            self.refusal(format!(
                "the checkpoint names no preset this build has ({})",
                has.as_deref().unwrap_or("none")
            ))
        })
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

    /// Errors unless a run of `options` may continue this checkpoint: the same model and preset
    /// (the architecture is checked when the model is built from it).
    pub fn check_resumes(&self, options: &TrainOptions) -> Result<(), RunError> {
        self.check_model(options.model)?;
        let preset = self.options().1;
        if preset.as_deref() != Some(options.preset.name()) {
            return Err(self.refusal(format!(
                "the checkpoint uses the {} preset, not {}",
                preset.as_deref().unwrap_or("unknown"),
                options.preset.name()
            )));
        }
        Ok(())
    }

    /// Errors unless this checkpoint was trained on a mesh normalised as `normalization` (the
    /// mesh of the run resuming it): a resume continues the fit of one mesh, and a mesh
    /// normalised otherwise is another one (or this one changed), whose points the checkpoint's
    /// model does not describe. Checked once the checkpoint's model is known to be sound.
    pub fn check_mesh(&self, normalization: sdf_geom::Normalization) -> Result<(), RunError> {
        let was = self.file.metadata.normalization;
        if was == normalization {
            return Ok(());
        }
        Err(self.refusal(format!(
            "the checkpoint was trained on another mesh (normalised about centre {}, scale {}; \
             this mesh: centre {}, scale {}): resume with the mesh it was trained on",
            was.center, was.scale, normalization.center, normalization.scale
        )))
    }

    /// A refusal to resume from this checkpoint, naming its file where it was loaded from one.
    pub(super) fn refusal(&self, why: String) -> RunError {
        RunError::Options(match &self.path {
            Some(path) => format!("{}: {why}", path.display()),
            None => why,
        })
    }

    /// What of `options`' model, preset and architecture this checkpoint does not have, as
    /// `name asked, not checkpoint's` lines (empty when a run of `options` may resume it). An
    /// NGLOD or hash-grid checkpoint must have every value of the architecture `options` resolve
    /// to (a hash grid's table size too), not only those given on the command line: `corpus`
    /// resumes into a table of one set of settings.
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
        if out.is_empty() && options.model.is_grid() {
            let resolved =
                options
                    .nglod_architecture
                    .config(options.model, options.preset, options.seed)?;
            let model = Nglod::from_model_file(&self.model_file())
                .map_err(|e| super::grid_error(options.model, e))?;
            let has = model.config();
            if has.encoding != resolved.encoding {
                out.push(format!(
                    "{}, not {}",
                    encoding_name(resolved.encoding),
                    encoding_name(has.encoding)
                ));
            }
            let every = NglodArchitecture {
                resolutions: Some(resolved.resolutions),
                sparse_levels: Some(resolved.sparse_levels),
                feature_dim: Some(resolved.feature_dim),
                hidden: Some(resolved.hidden),
                band_cells: Some(resolved.band_cells),
            };
            out.extend(every.differences(has));
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

/// How a grid model's levels reach its MLP, as [`Checkpoint::differences`] names it.
fn encoding_name(encoding: Encoding) -> String {
    match encoding {
        Encoding::Summed => "summed levels (NGLOD)".to_owned(),
        Encoding::Hashed { log2_table_size } => format!("hash tables of 2^{log2_table_size}"),
    }
}

const OPTIMIZER_PREFIX: &str = "optimizer.";

/// The most steps or epochs a checkpoint may claim done or planned.
pub const MAX_CHECKPOINT_PROGRESS: u64 = 1 << 30;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Preset;
    use sdf_nn::NglodConfig;

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

    /// A resume keeps what is left of the CPU time budget only where its run stopped before
    /// the budget planned the length; otherwise it goes on to the length that run planned.
    #[test]
    fn a_resume_plans_with_the_rest_of_a_pending_budget() {
        let budget = Some(crate::run::CPU_TIME_BUDGET);
        let mut trained = interrupted(
            Nglod::new(NglodConfig::small())
                .unwrap()
                .to_model_file(sdf_geom::Normalization::identity(), serde_json::Value::Null),
            "nglod",
            0,
            1,
        );
        trained.file.metadata.training["train_seconds"] = 20.0.into();
        // The budget counts the trainer's time, not the setup before it.
        trained.file.metadata.training["budget_seconds"] = 18.0.into();
        let planned = trained.checkpoint();
        assert!(!planned.plan_pending());
        assert_eq!(crate::run::resumed_budget(budget, Some(&planned)), None);
        trained.file.metadata.training["plan_pending"] = true.into();
        let pending = trained.checkpoint();
        assert!(pending.plan_pending());
        let left = crate::run::resumed_budget(budget, Some(&pending)).unwrap();
        assert_eq!(left.seconds, crate::run::CPU_TIME_BUDGET.seconds - 18.0);
        assert_eq!(left.max_epochs, crate::run::CPU_TIME_BUDGET.max_epochs);
        // A length asked for (no budget) or a fresh run are as before.
        assert_eq!(crate::run::resumed_budget(None, Some(&pending)), None);
        assert_eq!(crate::run::resumed_budget(budget, None), budget);
    }

    /// A hash grid's checkpoint resumes only into a hash-grid run of its preset, and one whose
    /// run record says "hashgrid" over NGLOD's tensors (or the reverse) is named for what it
    /// holds.
    #[test]
    fn hash_grid_checkpoints_name_their_model_and_table() {
        let grid = Nglod::new(NglodConfig::hashgrid_small()).unwrap();
        let file = grid.to_model_file(sdf_geom::Normalization::identity(), Default::default());
        assert_eq!(file.metadata.architecture, "hashgrid");
        let c = interrupted(file, "hashgrid", grid.param_count(), 2).checkpoint();
        let small = TrainOptions::new(ModelKind::Hashgrid, Preset::Small);
        assert!(c.differences(&small).unwrap().is_empty());
        c.check_resumes(&small).unwrap();
        assert_eq!(c.optimizer().unwrap().m.len(), grid.param_count());
        let nglod = TrainOptions::new(ModelKind::Nglod, Preset::Small);
        assert_eq!(
            c.differences(&nglod).unwrap(),
            ["model nglod, not hashgrid"]
        );
        assert!(c.check_model(ModelKind::Nglod).is_err());
        let default = TrainOptions::new(ModelKind::Hashgrid, Preset::Default);
        assert_eq!(
            c.differences(&default).unwrap(),
            ["preset default, not small"]
        );
        let mut fewer = small.clone();
        fewer.nglod_architecture.resolutions = Some(vec![8, 64]);
        let d = c.differences(&fewer).unwrap();
        assert_eq!(d.len(), 1, "{d:?}");
        assert!(d[0].starts_with("resolutions 8,64, not 8,"), "{d:?}");
        // An NGLOD's tensors under a hash grid's run record.
        let nglod_model = Nglod::new(NglodConfig::small()).unwrap();
        let file =
            nglod_model.to_model_file(sdf_geom::Normalization::identity(), Default::default());
        let mislabelled = interrupted(file, "hashgrid", nglod_model.param_count(), 1).checkpoint();
        let d = mislabelled.differences(&small).unwrap();
        let tables = encoding_name(NglodConfig::hashgrid_small().encoding);
        assert!(tables.starts_with("hash tables of 2^"), "{tables}");
        assert!(
            d.contains(&format!("{tables}, not summed levels (NGLOD)")),
            "{d:?}"
        );
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
                "5 steps done of 3 planned",
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
}
