//! SIREN's trainer in a run: the network from its preset or a checkpoint, the trainer's
//! configuration from the run's options, and the step loop with progress and stopping.

use std::sync::atomic::Ordering;

use sdf_nn::{Siren, SirenConfig, SirenTrainConfig, SirenTrainer};

use super::{Plan, Preset, Progress, RunError, Trained, check_trained, with_run_record};

/// Trains a SIREN to `plan.total` steps.
pub(super) fn train(
    plan: &Plan<'_>,
    mut progress: impl FnMut(&Progress),
) -> Result<Trained, RunError> {
    let (gpu, options, total) = (plan.gpu, plan.options, plan.total);
    let siren = match plan.resume {
        Some(c) => {
            let siren = Siren::from_model_file(&c.model_file())?;
            c.check_mesh(plan.normalization)?;
            siren
        }
        None => {
            let config = match options.preset {
                Preset::Default => SirenConfig::default(),
                Preset::Small => SirenConfig::small(),
            };
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
    let first_lr = train_config.lr;
    let per_step = (train_config.surface_per_step + train_config.box_per_step) as f64;
    let mut trainer = SirenTrainer::with_ground_truth(
        gpu,
        &siren,
        &plan.truth.mesh,
        &plan.truth.labels,
        train_config,
    )?;
    if let Some(c) = plan.resume {
        let lr = resumed_lr(c, first_lr).unwrap_or(trainer.lr());
        trainer.resume(gpu, &c.optimizer()?, c.done(), lr)?;
    }
    let first = trainer.steps_done();
    let mut loss = f32::NAN;
    let mut interrupted = false;
    while trainer.steps_done() < total {
        if plan.stop.load(Ordering::Relaxed) {
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
                points_per_second: plan.points_per_second(done - first, per_step),
            });
        }
    }
    let done = trainer.steps_done();
    let optimizer = trainer.optimizer_state(gpu)?;
    let lr = trainer.lr();
    let mut file = trainer.model_file(gpu)?;
    file.metadata.training = with_run_record(
        std::mem::take(&mut file.metadata.training),
        plan.training_json(done, loss),
    );
    // What a resume without `--steps` goes on to (else the adapter's default, which may be
    // fewer steps than were done: the run would end at once, reported finished).
    file.metadata.training["planned"] = total.into();
    file.metadata.normalization = plan.normalization;
    // The trainer checks each window's loss; the weights are checked here, since a run
    // shorter than a window reads no loss at all.
    check_trained(&file, done, "step")?;
    // The settings, as the grid models' reports give theirs (it was null for SIREN).
    let details = file.metadata.training.clone();
    Ok(Trained {
        file,
        train_seconds: plan.train_seconds(),
        done,
        final_loss: loss,
        interrupted,
        details,
        optimizer,
        lr,
    })
}

/// The rate a resumed SIREN goes on at: the checkpoint's, where its plateau schedule had
/// brought it, scaled by how the run's first rate (`--lr`, else the default) differs from the
/// one the checkpoint's run started at. So a resume with the same flags continues exactly, and
/// one with another `--lr` moves the whole schedule as it moves a grid model's cosine decay
/// (it was silently ignored). `None` where the checkpoint records no rate.
fn resumed_lr(c: &super::Checkpoint, first_lr: f32) -> Option<f32> {
    let now = c.lr()?;
    let started = c.training()["config"]["lr"].as_f64().map(|x| x as f32);
    Some(match started {
        Some(started) if started > 0.0 && started.is_finite() => now * (first_lr / started),
        _ => now,
    })
}
