//! NGLOD's trainer in a run of NGLOD or the hash grid: the model from its architecture or a
//! checkpoint (whose architecture must agree with the one asked for), the trainer's
//! configuration from the model's schedule and the run's options, and the epochs with progress,
//! stopping and the record of what they planned.

use std::sync::atomic::Ordering;

use sdf_nn::{Nglod, NglodTrainConfig, NglodTrainer};

use super::{
    Checkpoint, Plan, Progress, RunError, Trained, check_trained, grid_error, with_run_record,
};

/// Trains an NGLOD or a hash grid to `plan.total` epochs (or what its time budget plans).
pub(super) fn train(
    plan: &Plan<'_>,
    mut progress: impl FnMut(&Progress),
) -> Result<Trained, RunError> {
    let (gpu, total) = (plan.gpu, plan.total);
    // NGLOD's code, named after the model it trains.
    let named = |e| grid_error(plan.options.model, e);
    let model = model(plan)?;
    let first = plan.resume.map_or(0, Checkpoint::done).min(total);
    let train_config = config(plan, total - first);
    if let Some(c) = plan.resume {
        check_schedule(c, &train_config)?;
    }
    let per_epoch = (train_config.uniform_points
        + train_config.near_points
        + train_config.surface_points) as f64;
    let mut trainer = NglodTrainer::with_ground_truth(
        gpu,
        &model,
        &plan.truth.mesh,
        plan.truth.labels.clone(),
        train_config,
    )
    .map_err(named)?;
    trainer.set_stop_flag(plan.stop.clone());
    if let Some(c) = plan.resume {
        trainer
            .resume(&c.optimizer()?, first, c.epoch_steps_done())
            .map_err(named)?;
    }
    let mut planned = total;
    let report = trainer
        .train_with(|e| {
            let done = e.epoch + 1;
            planned = first + e.planned;
            progress(&Progress {
                done,
                total: planned,
                unit: "epoch",
                loss: e.loss,
                lr: e.lr,
                points_per_second: plan.points_per_second(done - first, per_epoch),
            });
        })
        .map_err(named)?;
    let trained = trainer.model().map_err(named)?;
    let optimizer = trainer.optimizer_state().map_err(named)?;
    let done = trainer.epochs_done();
    // A resume asked for no more epochs than were done trains none: its rate and loss are the
    // checkpoint's (the trainer's empty report has a loss of 0 and the starting rate).
    let (lr, final_loss) = match (report.epochs.last(), plan.resume) {
        (Some(e), _) => (e.lr, report.final_loss),
        (None, Some(c)) => (
            c.lr().unwrap_or(trainer.config().adam.lr),
            c.training()["final_loss"]
                .as_f64()
                .map_or(f32::NAN, |l| l as f32),
        ),
        (None, None) => (trainer.config().adam.lr, f32::NAN),
    };
    let mut training = with_run_record(
        trainer.training_json(Some(&report)),
        plan.training_json(done, final_loss),
    );
    training["planned"] = planned.into();
    // A run stopped before its time budget planned the length twice: `planned` is provisional.
    training["plan_pending"] = (plan.time_budget.is_some() && report.length_plans < 2).into();
    // The trainers' own seconds, which a budget counts (`train_seconds` adds the setup).
    let spent = plan.resume.map_or(0.0, Checkpoint::budget_seconds) + report.total_seconds;
    training["budget_seconds"] = spent.into();
    training["stall_seconds"] = report.stall_seconds.into();
    let file = trained.to_model_file(plan.normalization, training.clone());
    check_trained(&file, done, "epoch")?;
    Ok(Trained {
        file,
        train_seconds: plan.train_seconds(),
        done,
        final_loss,
        // A stop that lands after the last planned epoch's last step leaves nothing to resume.
        interrupted: report.stopped_early && plan.stop.load(Ordering::Relaxed) && done < planned,
        details: training,
        optimizer,
        lr,
    })
}

/// The model to train: the checkpoint's, which must be of the model asked for and have every
/// architecture value asked for, or a fresh one of the asked architecture over the preset.
fn model(plan: &Plan<'_>) -> Result<Nglod, RunError> {
    let options = plan.options;
    let named = |e| grid_error(options.model, e);
    let Some(c) = plan.resume else {
        let config =
            options
                .nglod_architecture
                .config(options.model, options.preset, options.seed)?;
        // The parameters' buffer must fit the device before the host fills gigabytes of them
        // (a summed level of 1000³ cells passes the configuration's own bound).
        let bytes = config.fixed_param_count() as u64 * 4;
        let what = format!("{} parameters", options.model.label());
        plan.gpu
            .check_storage_size(&what, bytes)
            .map_err(|e| named(e.into()))?;
        return Nglod::new(config).map_err(named);
    };
    let model = Nglod::from_model_file(&c.model_file()).map_err(named)?;
    // Its run record names the model (checked before), and its tensors must be one.
    let holds = model.config().architecture();
    if holds != options.model.name() {
        return Err(c.refusal(format!(
            "the checkpoint holds a {holds} model, not {}",
            options.model.name()
        )));
    }
    let differences = options.nglod_architecture.differences(model.config());
    if !differences.is_empty() {
        return Err(c.refusal(format!(
            "the checkpoint's architecture differs: {}",
            differences.join("; ")
        )));
    }
    c.check_mesh(plan.normalization)?;
    Ok(model)
}

/// Errors unless `config` continues the checkpoint's fit: the same distance (an unsigned fit
/// resumed without `--distance unsigned` went on as a signed one) and batch (the steps done in
/// the interrupted epoch count batches). Other settings (learning rate, pool, seed) may change
/// between runs, as their flags say.
fn check_schedule(c: &Checkpoint, config: &NglodTrainConfig) -> Result<(), RunError> {
    let recorded = c.training();
    let distance = recorded["distance"].as_str();
    if distance.is_some_and(|d| d != config.distance.name()) {
        let d = distance.unwrap_or_default();
        return Err(c.refusal(format!(
            "the checkpoint fits {d} distances, not {}: resume with --distance {d}",
            config.distance.name()
        )));
    }
    let batch = recorded["batch_size"].as_u64();
    if batch.is_some_and(|b| b != u64::from(config.batch_size)) {
        let b = batch.unwrap_or_default();
        return Err(c.refusal(format!(
            "the checkpoint trained in batches of {b}, not {}: resume with --batch {b}",
            config.batch_size
        )));
    }
    Ok(())
}

/// The trainer's configuration for `epochs` more epochs: the model's schedule
/// ([`super::ModelKind::grid_schedule`]: NGLOD's defaults, or the hash grid's) with the run's
/// options over it.
fn config(plan: &Plan<'_>, epochs: usize) -> NglodTrainConfig {
    let options = plan.options;
    let mut c = NglodTrainConfig {
        epochs,
        seed: options.seed,
        distance: options.distance,
        time_budget: plan.time_budget,
        ..options.model.grid_schedule().unwrap_or_default()
    };
    if let Some(lr) = options.lr {
        c.adam.lr = lr;
    }
    if let Some(f) = options.lr_final {
        c.lr_final = (f != 1.0).then_some(f);
    }
    if let Some(b) = options.batch {
        c.batch_size = b;
    }
    if let Some(g) = options.grow_every {
        c.grow_every = (g > 0).then_some(g);
    }
    if let Some((blocks, every)) = options.pool {
        c.pool_blocks = blocks;
        c.refresh_every = every;
    }
    // Ground truth on the GPU: the epochs' points are drawn and labelled there too, so that no
    // epoch waits for the CPU (issue 38).
    if plan.truth.labels.path() == sdf_nn::ground_truth::GroundTruthPath::Gpu {
        c.sample_source = sdf_nn::nglod::SampleSource::Gpu;
    }
    c
}
