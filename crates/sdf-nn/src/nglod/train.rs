//! The NGLOD training loop: fresh samples every epoch, computed on CPU threads for epoch `e+1`
//! while the GPU trains on epoch `e`; MSE; the shared Adam kernel.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_geom::{Mesh, SignedDistance};
use serde::{Deserialize, Serialize};

use super::gpu::TrainKernels;
use super::{Nglod, NglodError, NglodGpu, Objective, ScatterMode};
use crate::adam::{Adam, AdamConfig};
use crate::gpu::GpuContext;

/// Training settings. The defaults are the design document's.
#[derive(Clone, Debug, PartialEq)]
pub struct NglodTrainConfig {
    /// Epochs to run.
    pub epochs: usize,
    /// Points per optimiser step. Default 2048 (~245 Adam steps per 5·10⁵-point epoch).
    ///
    /// Measured on lavapipe, `default` preset, the bunny, 30 s of training each: batch 512
    /// (NGLOD's reference setting) reached 87.8% correct signs near the surface, 1024 90.6%,
    /// 2048 91.3%, 4096 91.6%. A step's cost is ~9 ms of kernels per 512 points plus ~12 ms of
    /// Adam over all 146 601 parameters whatever the batch, so small batches spend most of their
    /// time in Adam. 2048 takes most of the gain while keeping a few hundred steps per epoch,
    /// which the grid features need (a vertex only gets gradient from points in its cells).
    pub batch_size: u32,
    /// Adam hyperparameters (learning rate 1e-3).
    pub adam: AdamConfig,
    /// Full-model MSE, or NGLOD's sum over every level prefix.
    pub objective: Objective,
    /// Points per epoch uniform in the box `[-1, 1]³` (10⁵).
    pub uniform_points: usize,
    /// Points per epoch near the surface (2·10⁵).
    pub near_points: usize,
    /// Standard deviation of the near-surface offsets, normalised units (0.01).
    pub sigma: f32,
    /// Points per epoch on the surface (2·10⁵), labelled 0.
    pub surface_points: usize,
    /// Seed of the samplers (each epoch derives its own).
    pub seed: u64,
    /// Read the loss back every this many steps (each read waits for the GPU).
    pub loss_every: usize,
    /// Grid-gradient kernel.
    pub scatter: ScatterMode,
    /// Stop after the first loss read-back past this many seconds of training.
    pub max_seconds: Option<f64>,
}

impl Default for NglodTrainConfig {
    fn default() -> Self {
        NglodTrainConfig {
            epochs: 20,
            batch_size: 2048,
            adam: AdamConfig::default(),
            objective: Objective::Full,
            uniform_points: 100_000,
            near_points: 200_000,
            sigma: 0.01,
            surface_points: 200_000,
            seed: 0,
            loss_every: 16,
            scatter: ScatterMode::Auto,
            max_seconds: None,
        }
    }
}

impl NglodTrainConfig {
    fn points_per_epoch(&self) -> usize {
        self.uniform_points + self.near_points + self.surface_points
    }
}

/// What one epoch cost and achieved.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpochStats {
    /// Epoch index (0-based).
    pub epoch: usize,
    /// Optimiser steps run in this epoch.
    pub steps: usize,
    /// Mean loss over the epoch's read-back intervals.
    pub loss: f32,
    /// Wall time of the GPU training loop for this epoch (uploads, steps, final wait).
    pub gpu_seconds: f64,
    /// Time the CPU threads spent sampling and labelling this epoch's points (overlapped with
    /// the previous epoch's GPU work, except for epoch 0).
    pub sampling_seconds: f64,
    /// Time the GPU loop waited for this epoch's samples (the part of sampling not hidden).
    pub stall_seconds: f64,
}

/// Summary of a training run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// Per-epoch statistics.
    pub epochs: Vec<EpochStats>,
    /// Total optimiser steps.
    pub steps: usize,
    /// Wall time of the whole run.
    pub total_seconds: f64,
    /// Sum of the epochs' GPU loop times.
    pub gpu_seconds: f64,
    /// Sum of the sampling times (mostly overlapped with GPU work).
    pub sampling_seconds: f64,
    /// Sum of the stalls waiting for samples.
    pub stall_seconds: f64,
    /// The last read-back loss.
    pub final_loss: f32,
    /// Whether `max_seconds` stopped the run early.
    pub stopped_early: bool,
}

/// One epoch of labelled, shuffled points.
struct EpochData {
    points: Vec<Vec3>,
    targets: Vec<f32>,
    seconds: f64,
}

/// Draws and labels the points of one epoch (on the calling thread plus rayon's pool).
fn sample_epoch(
    mesh: &Mesh,
    sdf: &SignedDistance,
    c: &NglodTrainConfig,
    epoch: usize,
) -> EpochData {
    let t = Instant::now();
    let seed = c.seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut points = sdf_geom::sample::uniform_box(c.uniform_points, seed);
    points.extend(sdf_geom::sample::near_surface(
        mesh,
        c.near_points,
        c.sigma,
        seed ^ 1,
    ));
    let mut targets = sdf.signed_distance_batch(&points);
    // Surface samples lie on the mesh by construction: their exact distance is 0, so the
    // distance query is skipped for them (40% of the points).
    let surface = sdf_geom::sample::surface(mesh, c.surface_points, seed ^ 2).points;
    targets.resize(points.len() + surface.len(), 0.0);
    points.extend(surface);
    // The three kinds must mix within every batch.
    let mut rng = Pcg64::seed_from_u64(seed ^ 3);
    for i in (1..points.len()).rev() {
        let j = rng.random_range(0..=i);
        points.swap(i, j);
        targets.swap(i, j);
    }
    EpochData {
        points,
        targets,
        seconds: t.elapsed().as_secs_f64(),
    }
}

/// Trains an [`Nglod`] on a mesh on the GPU.
pub struct NglodTrainer<'g> {
    gpu: &'g GpuContext,
    model: NglodGpu,
    adam: Adam,
    mesh: Mesh,
    sdf: SignedDistance,
    config: NglodTrainConfig,
    points: wgpu::Buffer,
    targets: wgpu::Buffer,
    kernels: TrainKernels,
    epochs_done: usize,
    steps_done: usize,
    stop: Option<Arc<AtomicBool>>,
}

impl std::fmt::Debug for NglodTrainer<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NglodTrainer")
            .field("model", &self.model)
            .field("config", &self.config)
            .field("epochs_done", &self.epochs_done)
            .finish_non_exhaustive()
    }
}

impl<'g> NglodTrainer<'g> {
    /// A trainer for `model` on `mesh`, which must already be in normalised coordinates
    /// (`mesh.normalized()`); the model learns the SDF of the box `[-1, 1]³`.
    pub fn new(
        gpu: &'g GpuContext,
        model: &Nglod,
        mesh: &Mesh,
        config: NglodTrainConfig,
    ) -> Result<Self, NglodError> {
        let n = config.points_per_epoch();
        if n == 0 || config.batch_size == 0 || config.loss_every == 0 {
            return Err(NglodError::InvalidConfig(
                "points per epoch, batch size and loss_every must be positive".into(),
            ));
        }
        if !(config.adam.lr.is_finite() && config.adam.lr > 0.0) {
            return Err(NglodError::InvalidConfig(format!(
                "the learning rate must be positive, not {}",
                config.adam.lr
            )));
        }
        let n32 = u32::try_from(n)
            .map_err(|_| NglodError::InvalidConfig(format!("{n} points per epoch is too many")))?;
        // NaN area (non-finite vertices) is rejected too.
        if mesh.triangles.is_empty()
            || mesh.area().partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
        {
            return Err(NglodError::BadMesh("it has no triangles with area".into()));
        }
        let sdf = SignedDistance::new(mesh)?;
        let gm = NglodGpu::new(gpu, model, config.scatter)?;
        let adam = Adam::new(
            gpu,
            gm.params_buffer(),
            gm.grads_buffer(),
            gm.param_count() as u32,
            config.adam,
        )?;
        let points = gpu.storage_zeroed("nglod epoch points", n as u64 * 12)?;
        let targets = gpu.storage_zeroed("nglod epoch targets", n as u64 * 4)?;
        let batch = config.batch_size.min(n32);
        let kernels = TrainKernels::new(gpu, &gm, &points, &targets, batch, config.objective)?;
        Ok(NglodTrainer {
            gpu,
            model: gm,
            adam,
            mesh: mesh.clone(),
            sdf,
            config,
            points,
            targets,
            kernels,
            epochs_done: 0,
            steps_done: 0,
            stop: None,
        })
    }

    /// The settings.
    pub fn config(&self) -> &NglodTrainConfig {
        &self.config
    }

    /// The model on the GPU (for evaluation between runs).
    pub fn gpu_model(&self) -> &NglodGpu {
        &self.model
    }

    /// Reads the current parameters back into a host model.
    pub fn model(&self) -> Result<Nglod, NglodError> {
        self.model.to_model(self.gpu)
    }

    /// The settings and, given a report, its summary, as JSON for a model file's `training`
    /// metadata ([`Nglod::to_model_file`]).
    pub fn training_json(&self, report: Option<&TrainReport>) -> serde_json::Value {
        let c = &self.config;
        let mut v = serde_json::json!({
            "epochs_done": self.epochs_done,
            "steps_done": self.steps_done,
            "batch_size": c.batch_size,
            "lr": c.adam.lr,
            "beta1": c.adam.beta1,
            "beta2": c.adam.beta2,
            "eps": c.adam.eps,
            "objective": c.objective,
            "uniform_points": c.uniform_points,
            "near_points": c.near_points,
            "sigma": c.sigma,
            "surface_points": c.surface_points,
            "seed": c.seed,
            "loss": "mse",
        });
        if let Some(r) = report {
            v["final_loss"] = serde_json::json!(r.final_loss);
            v["seconds"] = serde_json::json!(r.total_seconds);
            v["gpu_seconds"] = serde_json::json!(r.gpu_seconds);
            v["sampling_seconds"] = serde_json::json!(r.sampling_seconds);
        }
        v
    }

    /// Runs `config.epochs` epochs (or until `max_seconds`).
    pub fn train(&mut self) -> Result<TrainReport, NglodError> {
        self.train_with(|_| {})
    }

    /// Like [`NglodTrainer::train`], calling `on_epoch` after every epoch.
    pub fn train_with(
        &mut self,
        mut on_epoch: impl FnMut(&EpochStats),
    ) -> Result<TrainReport, NglodError> {
        let start = Instant::now();
        let mut report = TrainReport::default();
        let epochs = self.config.epochs;
        if epochs == 0 {
            return Ok(report);
        }
        let NglodTrainer {
            gpu,
            model: _,
            adam,
            mesh,
            sdf,
            config,
            points,
            targets,
            kernels,
            epochs_done,
            steps_done,
            stop: stop_flag,
        } = self;
        let gpu: &GpuContext = gpu;
        let (mesh, sdf, config) = (&*mesh, &*sdf, &*config);
        let first_epoch = *epochs_done;
        let n = config.points_per_epoch() as u32;
        let batch = config.batch_size.min(n);

        std::thread::scope(|scope| -> Result<(), NglodError> {
            let spawn = |e: usize| scope.spawn(move || sample_epoch(mesh, sdf, config, e));
            let mut pending = Some(spawn(first_epoch));
            for e in first_epoch..first_epoch + epochs {
                let wait = Instant::now();
                let data = match pending.take().map(|h| h.join()) {
                    Some(Ok(d)) => d,
                    // A panic in the sampler is a bug in sdf-geom, not bad input: re-raise it.
                    Some(Err(p)) => std::panic::resume_unwind(p),
                    None => unreachable!("a sampling thread is always pending"),
                };
                let stall = wait.elapsed().as_secs_f64();
                let gpu_start = Instant::now();
                gpu.write(points, bytemuck::cast_slice::<Vec3, f32>(&data.points))?;
                gpu.write(targets, &data.targets)?;
                if e + 1 < first_epoch + epochs {
                    pending = Some(spawn(e + 1));
                }
                let mut steps = 0;
                let (mut loss_sum, mut loss_reads) = (0.0f64, 0usize);
                let mut since_read = 0u32;
                let mut last_loss = f32::NAN;
                let mut stop = false;
                let mut first = 0u32;
                while first < n {
                    let nb = batch.min(n - first);
                    let mut enc = gpu.device().create_command_encoder(&Default::default());
                    kernels.record(gpu, &mut enc, first, nb)?;
                    adam.record_step(gpu, &mut enc, 1.0 / nb as f32);
                    gpu.queue().submit([enc.finish()]);
                    first += nb;
                    steps += 1;
                    since_read += nb;
                    *steps_done += 1;
                    if steps % config.loss_every == 0 || first >= n {
                        let s: Vec<f32> = gpu.read_back_range(&kernels.stats, 0, 1)?;
                        gpu.zero(&kernels.stats);
                        let loss = s[0] / since_read as f32;
                        since_read = 0;
                        if !loss.is_finite() {
                            return Err(NglodError::Diverged {
                                epoch: e,
                                step: *steps_done - 1,
                                loss,
                            });
                        }
                        last_loss = loss;
                        loss_sum += f64::from(loss);
                        loss_reads += 1;
                        if config
                            .max_seconds
                            .is_some_and(|m| start.elapsed().as_secs_f64() >= m)
                            || stop_flag
                                .as_ref()
                                .is_some_and(|f| f.load(Ordering::Relaxed))
                        {
                            stop = true;
                            break;
                        }
                    }
                }
                gpu.wait()?;
                let stats = EpochStats {
                    epoch: e,
                    steps,
                    loss: (loss_sum / loss_reads.max(1) as f64) as f32,
                    gpu_seconds: gpu_start.elapsed().as_secs_f64(),
                    sampling_seconds: data.seconds,
                    stall_seconds: stall,
                };
                on_epoch(&stats);
                report.steps += steps;
                report.gpu_seconds += stats.gpu_seconds;
                report.sampling_seconds += stats.sampling_seconds;
                report.stall_seconds += stats.stall_seconds;
                report.final_loss = last_loss;
                report.epochs.push(stats);
                *epochs_done = e + 1;
                if stop {
                    report.stopped_early = true;
                    // Let the pending sampler finish (scope joins it); its work is discarded.
                    break;
                }
            }
            Ok(())
        })?;
        report.total_seconds = start.elapsed().as_secs_f64();
        Ok(report)
    }
}

/// Checkpoints: what an interrupted run saves besides the weights, and how it resumes.
impl NglodTrainer<'_> {
    /// The optimiser's moments and step counter.
    pub fn optimizer_state(&self) -> Result<crate::AdamState, NglodError> {
        Ok(self.adam.export_state(self.gpu)?)
    }

    /// Continues a run: restores the optimiser state and the epoch count (which also seeds each
    /// epoch's samples). The weights come with the [`Nglod`] the trainer was built from.
    pub fn resume(
        &mut self,
        state: &crate::AdamState,
        epochs_done: usize,
    ) -> Result<(), NglodError> {
        self.adam.import_state(self.gpu, state)?;
        self.epochs_done = epochs_done;
        Ok(())
    }

    /// A flag polled at every loss read-back: once set, training stops as `max_seconds` does
    /// (the epoch in progress counts as done), e.g. on Ctrl-C.
    pub fn set_stop_flag(&mut self, flag: Arc<AtomicBool>) {
        self.stop = Some(flag);
    }

    /// Epochs done so far.
    pub fn epochs_done(&self) -> usize {
        self.epochs_done
    }
}
