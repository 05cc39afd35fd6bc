//! The NGLOD training loop: a pool of labelled points, drawn from in a fresh order every epoch
//! and partly redrawn every few epochs on CPU threads while the GPU trains; MSE; the shared Adam
//! kernel; optional cosine learning-rate decay and progressive levels of detail.
//!
//! Why a pool: sampling and labelling 5·10⁵ points costs 0.15 s on 16 cores and seconds on 2,
//! while an epoch of kernels takes 0.03–0.04 s on an H100, so fresh points every epoch left the
//! GPU waiting. The pool holds `pool_blocks` blocks of one epoch's worth of points each; an epoch
//! draws its points without replacement from the whole pool, and once the pool is full one new
//! block replaces the oldest every `refresh_every` epochs, so sampling costs `1/refresh_every` of
//! what it did per epoch.
//!
//! With [`SampleSource::Gpu`] the pool is kept on the GPU: its new block is drawn and labelled
//! there, and the epoch's points gathered from the whole pool, in the epoch's first submission
//! (a resume's older blocks each in a submission of their own first; `train/gpu_points.rs`).
//! Either way the steps up to the next loss read-back (at most [`STEPS_PER_SUBMISSION`]) share
//! one submission, each with its own staged uniforms, and a read-back is waited for only once
//! the next submission is on its way: the GPU trains while the host records the next steps
//! (about 12 ms an epoch of `default` on the 2-core CI box, time a GPU would otherwise sit
//! idle).

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance};
use serde::{Deserialize, Serialize};

use super::gpu::TrainKernels;
use super::pool::{Block, Pool, PoolSchedule, sample_block};
use super::{Nglod, NglodError, NglodGpu, Objective, ScatterMode};
use crate::adam::{Adam, AdamConfig};
use crate::gpu::{GpuContext, PendingRead, QueryKernel, UniformStager};
use crate::ground_truth::{LabelledDraw, Labeller};

mod checkpoint;
mod gpu_points;
mod profile;

/// Optimiser steps recorded into one submission at most (fewer where a loss read-back is due
/// sooner): a submission costs tens of µs on a GPU, where a small step takes about as long.
const STEPS_PER_SUBMISSION: usize = 32;
/// Bytes of uniforms a step stages: the training kernels' and Adam's (both multiples of the
/// copy alignment, 4 bytes).
const STAGED_BYTES_PER_STEP: u64 =
    super::gpu::TRAIN_UNIFORM_BYTES + crate::adam::ADAM_UNIFORM_BYTES;

pub use gpu_points::SampleSource;

/// What the network is fitted to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DistanceMode {
    /// The signed distance (negative inside).
    #[default]
    Signed,
    /// The unsigned distance |d|: for meshes without an inside (flat or open sheets, two-sided
    /// triangle soups), where the sign carries no information.
    Unsigned,
}

impl DistanceMode {
    /// `"signed"` or `"unsigned"`.
    pub fn name(self) -> &'static str {
        match self {
            DistanceMode::Signed => "signed",
            DistanceMode::Unsigned => "unsigned",
        }
    }
}

/// Epochs of a run by default ([`NglodTrainConfig::default`]), and of `train`'s and `corpus`'s
/// runs on a GPU (their CPU time budget stops there too). 100: the default preset on the 20
/// shared meshes, 12 epochs 0.993 / 0.963 F1 (box / near the surface), 100 epochs 0.997 / 0.982
/// (0.997 / 0.981 with today's band of 0 cells); on six of them 50 epochs 0.969 near, 100
/// epochs 0.976 (docs/benchmarks, measured on lavapipe). The pool makes it cheap.
pub const DEFAULT_EPOCHS: usize = 100;

/// Training settings. The defaults are the design document's, plus the sample pool.
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
    /// Seed of the samplers (each block of the pool and each epoch's draw derive their own).
    pub seed: u64,
    /// Read the loss back every this many steps (each read waits for the GPU).
    pub loss_every: usize,
    /// Grid-gradient kernel.
    pub scatter: ScatterMode,
    /// One row per invocation or per subgroup (`None`: [`GpuContext::train_kernel`]'s choice).
    pub kernel: Option<QueryKernel>,
    /// Adam leaves a grid or table entry that no point of the step touched alone, moments
    /// included ([`Adam::set_lazy_prefix`]); the MLP's weights are always updated.
    pub lazy_adam: bool,
    /// Stop after the first loss read-back past this many seconds of training.
    pub max_seconds: Option<f64>,
    /// Blocks of one epoch's worth of labelled points in the sample pool (4). 1 with
    /// `refresh_every` 1 is the old behaviour: fresh points every epoch.
    pub pool_blocks: usize,
    /// Once the pool is full, a fresh block replaces the oldest every this many epochs (4).
    pub refresh_every: usize,
    /// Cosine decay of the learning rate over the run, per step, from `adam.lr` down to
    /// `adam.lr × lr_final` at the last step (`None`: constant).
    pub lr_final: Option<f32>,
    /// Progressive levels of detail as NGLOD trains them: only the coarsest level at first, one
    /// more every this many epochs (`None`: all levels from the start).
    pub grow_every: Option<usize>,
    /// Signed or unsigned distance targets.
    pub distance: DistanceMode,
    /// Plan the run's length from its first epoch instead of `epochs` alone (`None`: `epochs`).
    pub time_budget: Option<TimeBudget>,
    /// Where the pool is drawn and labelled and kept: on CPU threads (default) or on the GPU.
    pub sample_source: SampleSource,
}

/// A training time to fill ([`NglodTrainConfig::time_budget`]): after each of the first two
/// epochs that run whole, the trainer plans as many epochs as fit in `seconds` at the pace of
/// the epoch just done, at least `epochs` (counted from the resumed epoch after
/// [`NglodTrainer::resume`]) and at most `max_epochs`. The first epoch waits for
/// its samples, so its plan is a cautious one; the second runs at the pace the rest will. So
/// the same command gives the best fit a given time buys on machines (and drivers) of very
/// different speeds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TimeBudget {
    /// Seconds of training, sampling included.
    pub seconds: f64,
    /// The most epochs to plan.
    pub max_epochs: usize,
}

impl TimeBudget {
    /// Epochs to plan in all after `done` epochs and `elapsed` seconds, the last epoch having
    /// taken `last_epoch_seconds`: those done and as many more as fit in what is left of the
    /// budget, clamped to `least ..= max_epochs` (`least` wins over `max_epochs`).
    pub fn epochs(
        &self,
        least: usize,
        done: usize,
        elapsed: f64,
        last_epoch_seconds: f64,
    ) -> usize {
        let more = (self.seconds - elapsed).max(0.0) / last_epoch_seconds.max(1e-9);
        let fit = done as f64 + more.min(self.max_epochs as f64);
        (fit.min(self.max_epochs as f64) as usize).max(least)
    }
}

impl Default for NglodTrainConfig {
    fn default() -> Self {
        NglodTrainConfig {
            epochs: DEFAULT_EPOCHS,
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
            kernel: None,
            lazy_adam: false,
            max_seconds: None,
            pool_blocks: 4,
            refresh_every: 4,
            // Cosine decay to 0.1: on lavapipe, 8 epochs of `default`, spot/fandisk/rocker-arm
            // near-surface F1 0.943/0.934/0.942 constant, 0.957/0.951/0.939 decayed
            // (docs/benchmarks). Progressive levels did not help there, so they stay off.
            lr_final: Some(0.1),
            grow_every: None,
            distance: DistanceMode::Signed,
            time_budget: None,
            sample_source: SampleSource::CpuPool,
        }
    }
}

/// Epochs of a hash-grid run by default ([`NglodTrainConfig::hashgrid`]).
pub const HASHGRID_EPOCHS: usize = 50;

impl NglodTrainConfig {
    /// The hash grid's schedule ([`crate::nglod::Encoding::Hashed`]): NGLOD's sampling and
    /// pool, with instant-ngp's β2 = 0.99 and ε = 1e-15 (a table entry sees gradient only from
    /// the points in its cells, and a large ε would stall the rarely touched ones), a learning
    /// rate of 2.5e-3 (the best of 1e-3, 2.5e-3 and 5e-3 near the surface on spot and on the
    /// CAD parts idler-riser and adis16480 after 10 epochs of `small` on lavapipe, and
    /// instant-ngp's 1e-2 worse still; docs/hashgrid.md), cosine decay to 0.1, NGLOD's batch
    /// of 2048 (against 4096 there: 0.9783 against 0.9762 on average, at about the same time
    /// per epoch) and [`HASHGRID_EPOCHS`].
    pub fn hashgrid() -> Self {
        NglodTrainConfig {
            epochs: HASHGRID_EPOCHS,
            batch_size: 2048,
            adam: AdamConfig {
                lr: 2.5e-3,
                beta1: 0.9,
                beta2: 0.99,
                eps: 1e-15,
            },
            ..Self::default()
        }
    }

    pub(super) fn points_per_epoch(&self) -> usize {
        self.uniform_points + self.near_points + self.surface_points
    }

    /// The pool's schedule.
    pub(super) fn pool(&self) -> PoolSchedule {
        PoolSchedule {
            blocks: self.pool_blocks,
            refresh_every: self.refresh_every,
        }
    }

    /// Learning rate at fractional position `t` (0 = first step, 1 = end) of the run.
    pub fn lr_at(&self, t: f64) -> f32 {
        let lr = f64::from(self.adam.lr);
        match self.lr_final {
            None => self.adam.lr,
            Some(f) => {
                let f = f64::from(f);
                let c = 0.5 * (1.0 + (std::f64::consts::PI * t.clamp(0.0, 1.0)).cos());
                (lr * (f + (1.0 - f) * c)) as f32
            }
        }
    }

    /// Levels of detail trained in epoch `epoch` of a model with `levels` levels.
    pub fn levels_at(&self, epoch: usize, levels: usize) -> usize {
        match self.grow_every {
            Some(g) if g > 0 => (1 + epoch / g).min(levels),
            _ => levels,
        }
    }
}

/// What one epoch cost and achieved.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpochStats {
    /// Epoch index (0-based).
    pub epoch: usize,
    /// Optimiser steps run in this epoch (by this call: a resumed epoch counts the rest).
    pub steps: usize,
    /// Mean loss over the epoch's read-back intervals.
    pub loss: f32,
    /// Wall time of the GPU training loop for this epoch (uploads, steps, final wait).
    pub gpu_seconds: f64,
    /// CPU time spent on this epoch's points: sampling and labelling the pool blocks that enter
    /// the pool at this epoch (overlapped with earlier epochs' GPU work, except at the start),
    /// plus drawing the epoch from the pool.
    pub sampling_seconds: f64,
    /// Time the GPU loop waited for samples (the part of sampling not hidden).
    pub stall_seconds: f64,
    /// Learning rate at the epoch's last step.
    pub lr: f32,
    /// Levels of detail trained in this epoch.
    pub levels: usize,
    /// Epochs the run plans in all (counted from its first epoch); with a
    /// [`NglodTrainConfig::time_budget`], set after the first epoch.
    pub planned: usize,
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
    /// Whether `max_seconds` or the stop flag stopped the run early.
    pub stopped_early: bool,
    /// How many times the [`TimeBudget`] planned the run's length (two at most; fewer when the
    /// run stopped before two epochs ran whole, and a resume then goes on planning).
    pub length_plans: usize,
    /// Fraction of the first pool block's uniform box points labelled inside (negative): close
    /// to 0 for a mesh without an inside. `None` for unsigned targets or when no block was drawn.
    pub inside_fraction: Option<f64>,
}

impl TrainReport {
    /// Counts an epoch in, `last_loss` its last read-back.
    fn add(&mut self, epoch: EpochStats, last_loss: f32) {
        self.steps += epoch.steps;
        self.gpu_seconds += epoch.gpu_seconds;
        self.sampling_seconds += epoch.sampling_seconds;
        self.stall_seconds += epoch.stall_seconds;
        self.final_loss = last_loss;
        self.epochs.push(epoch);
    }
}

/// Trains an [`Nglod`] on a mesh on the GPU.
pub struct NglodTrainer<'g> {
    gpu: &'g GpuContext,
    model: NglodGpu,
    adam: Adam,
    mesh: Mesh,
    labels: Labeller<'g>,
    config: NglodTrainConfig,
    points: wgpu::Buffer,
    targets: wgpu::Buffer,
    kernels: TrainKernels,
    /// The sampler and ground truth on the GPU, with [`SampleSource::Gpu`].
    gpu_points: Option<gpu_points::GpuPoints>,
    /// The uniforms of the steps of one submission.
    stager: UniformStager,
    epochs_done: usize,
    epoch_steps_done: usize,
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
    /// A model whose sparse levels are all empty ([`Nglod::needs_bands`]) first gets the bands
    /// around `mesh` ([`Nglod::place_bands`]).
    pub fn new(
        gpu: &'g GpuContext,
        model: &Nglod,
        mesh: &Mesh,
        config: NglodTrainConfig,
    ) -> Result<Self, NglodError> {
        // Bad settings are refused before the BVH is built.
        let n = Self::check(mesh, &config)?;
        let labels = Labeller::cpu(Arc::new(SignedDistance::new(mesh)?));
        Self::checked(gpu, model, mesh, labels, config, n)
    }

    /// [`NglodTrainer::new`] with the exact ground truth of `mesh` already built: `labels`
    /// must label `SignedDistance::new(mesh)`, on the path the run chose
    /// ([`Labeller::choose`]: the sample pool's labels come from it). A caller that also checks
    /// or evaluates against the mesh builds its BVH once (1.3–1.6 s for 1.4 M triangles on 2
    /// cores).
    pub fn with_ground_truth(
        gpu: &'g GpuContext,
        model: &Nglod,
        mesh: &Mesh,
        labels: Labeller<'g>,
        config: NglodTrainConfig,
    ) -> Result<Self, NglodError> {
        let n = Self::check(mesh, &config)?;
        Self::checked(gpu, model, mesh, labels, config, n)
    }

    /// The trainer, once [`NglodTrainer::check`] has passed and given `n32` points per epoch.
    fn checked(
        gpu: &'g GpuContext,
        model: &Nglod,
        mesh: &Mesh,
        labels: Labeller<'g>,
        config: NglodTrainConfig,
        n32: u32,
    ) -> Result<Self, NglodError> {
        let n = n32 as usize;
        // A fresh model's sparse levels take the band around this mesh.
        let placed;
        let model = if model.needs_bands() {
            let mut m = model.clone();
            m.place_bands(|p| labels.sdf().unsigned_distance(p))?;
            placed = m;
            &placed
        } else {
            model
        };
        let mut gm = NglodGpu::new(gpu, model, config.scatter)?;
        gm.set_train_kernel(gpu, config.kernel)?;
        let mut adam = Adam::new(
            gpu,
            gm.params_buffer(),
            gm.grads_buffer(),
            gm.param_count() as u32,
            config.adam,
        )?;
        if config.lazy_adam {
            adam.set_lazy_prefix(model.layout().w0 as u32);
        }
        let points = gpu.storage_zeroed("nglod epoch points", n as u64 * 12)?;
        let targets = gpu.storage_zeroed("nglod epoch targets", n as u64 * 4)?;
        let batch = config.batch_size.min(n32);
        let kernels = TrainKernels::new(gpu, &gm, &points, &targets, batch, config.objective)?;
        let gpu_points = match config.sample_source {
            SampleSource::CpuPool => None,
            SampleSource::Gpu => Some(gpu_points::GpuPoints::new(
                gpu,
                mesh,
                labels.sdf(),
                &config,
                (&points, &targets),
            )?),
        };
        Ok(NglodTrainer {
            gpu,
            model: gm,
            adam,
            mesh: mesh.clone(),
            labels,
            config,
            points,
            targets,
            kernels,
            gpu_points,
            stager: UniformStager::new(
                gpu,
                "nglod staged uniforms",
                STEPS_PER_SUBMISSION as u64 * STAGED_BYTES_PER_STEP,
            ),
            epochs_done: 0,
            epoch_steps_done: 0,
            steps_done: 0,
            stop: None,
        })
    }

    /// The points per epoch of `config`, or why `config` or `mesh` cannot be trained on.
    fn check(mesh: &Mesh, config: &NglodTrainConfig) -> Result<u32, NglodError> {
        let n = config.points_per_epoch();
        if n == 0
            || config.batch_size == 0
            || config.loss_every == 0
            || config.pool_blocks == 0
            || config.refresh_every == 0
            || config.grow_every == Some(0)
        {
            return Err(NglodError::InvalidConfig(
                "points per epoch, batch size, loss_every, pool_blocks, refresh_every and \
                 grow_every must be positive"
                    .into(),
            ));
        }
        if let Some(f) = config.lr_final
            && !(f.is_finite() && f >= 0.0)
        {
            return Err(NglodError::InvalidConfig(format!(
                "the final learning-rate ratio must be finite and non-negative, not {f}"
            )));
        }
        config.adam.check().map_err(NglodError::InvalidConfig)?;
        let n32 = u32::try_from(n)
            .map_err(|_| NglodError::InvalidConfig(format!("{n} points per epoch is too many")))?;
        // The pool's coordinates, three a point, are indexed in u32 (the GPU's draw refuses
        // the same).
        if (config.pool_blocks as u64).saturating_mul(u64::from(n32)) > u64::from(u32::MAX / 3) {
            return Err(NglodError::InvalidConfig(format!(
                "a pool of {} blocks of {n} points is more than 2^32 / 3 points: use fewer blocks",
                config.pool_blocks
            )));
        }
        // NaN area (non-finite vertices) is rejected too.
        if mesh.triangles.is_empty()
            || mesh.area().partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
        {
            return Err(NglodError::BadMesh("it has no triangles with area".into()));
        }
        Ok(n32)
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
            "epoch_steps_done": self.epoch_steps_done,
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
            "pool_blocks": c.pool_blocks,
            "refresh_every": c.refresh_every,
            "lr_final": c.lr_final,
            "grow_every": c.grow_every,
            "time_budget": c.time_budget,
            "distance": c.distance,
            "sample_source": c.sample_source.name(),
            "train_kernel": self.kernels.kernel().name(),
            "lazy_adam": c.lazy_adam,
        });
        if let Some(r) = report {
            v["final_loss"] = serde_json::json!(r.final_loss);
            v["seconds"] = serde_json::json!(r.total_seconds);
            v["gpu_seconds"] = serde_json::json!(r.gpu_seconds);
            v["sampling_seconds"] = serde_json::json!(r.sampling_seconds);
            v["inside_fraction"] = serde_json::json!(r.inside_fraction);
        }
        v
    }

    /// Runs `config.epochs` epochs, or with a [`NglodTrainConfig::time_budget`] the number it
    /// plans after the first (or until `max_seconds`); after [`NglodTrainer::resume`], the rest
    /// of the interrupted epoch counts as the first.
    pub fn train(&mut self) -> Result<TrainReport, NglodError> {
        self.train_with(|_| {})
    }

    /// Like [`NglodTrainer::train`], calling `on_epoch` after every epoch.
    // rooms: one thread scope owns the sampler threads and the epoch loop that joins them; the
    // pool, the pending block and the stall clock live across epochs inside it. The GPU steps
    // of an epoch are `EpochSteps::run`.
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
        if self.gpu_points.is_some() {
            return self.train_on_gpu_points(on_epoch);
        }
        let levels = self.model.config().levels();
        let NglodTrainer {
            gpu,
            model: _,
            adam,
            mesh,
            labels,
            config,
            points,
            targets,
            kernels,
            gpu_points: _,
            stager,
            epochs_done,
            epoch_steps_done,
            steps_done,
            stop: stop_flag,
        } = self;
        let gpu: &GpuContext = gpu;
        let (mesh, labels, config) = (&*mesh, &*labels, &*config);
        let first_epoch = *epochs_done;
        let mut end_epoch = first_epoch + epochs;
        let n = config.points_per_epoch() as u32;
        let batch = config.batch_size.min(n);
        let steps_per_epoch = n.div_ceil(batch) as usize;
        let schedule = config.pool();
        let mut stepper = Stepper {
            gpu,
            points,
            targets,
            adam,
            kernels,
            stager,
            config,
            n,
            batch,
            steps_per_epoch,
        };
        let should_stop = || stop_requested(config, start, stop_flag.as_deref());

        std::thread::scope(|scope| -> Result<(), NglodError> {
            let spawn = |k: usize| scope.spawn(move || sample_block(mesh, labels, config, k));
            let join = |h: std::thread::ScopedJoinHandle<'_, Result<Block, _>>| match h.join() {
                Ok(b) => b,
                // A panic in the sampler is a bug in sdf-geom, not bad input: re-raise it.
                Err(p) => std::panic::resume_unwind(p),
            };
            // The blocks of the first epoch; after a resume, several at once, in parallel.
            let wait = Instant::now();
            let initial = schedule.blocks_at(first_epoch);
            let mut pool = Pool {
                blocks: VecDeque::new(),
                cap: schedule.blocks.max(1),
            };
            let firsts: Vec<_> = initial.clone().map(spawn).collect();
            let mut new_sampling = 0.0;
            for (k, h) in initial.clone().zip(firsts) {
                let b = join(h)?;
                new_sampling += b.seconds;
                pool.push(k, b);
            }
            report.inside_fraction = pool.inside_fraction(config);
            let mut stall = wait.elapsed().as_secs_f64();
            let mut next_block = initial.end;
            let mut pending = (schedule.due(next_block) < end_epoch).then(|| spawn(next_block));
            let mut e = first_epoch;
            // When the current epoch began, in seconds from `start` (the first one: at 0, so
            // that its wait for the first samples counts).
            let mut epoch_began = 0.0;
            while e < end_epoch {
                let wait = Instant::now();
                while schedule.due(next_block) <= e {
                    let Some(h) = pending.take() else {
                        unreachable!("the next due block is always pending")
                    };
                    let b = join(h)?;
                    new_sampling += b.seconds;
                    pool.push(next_block, b);
                    next_block += 1;
                    if schedule.due(next_block) < end_epoch {
                        pending = Some(spawn(next_block));
                    }
                }
                stall += wait.elapsed().as_secs_f64();
                let draw = Instant::now();
                let (p, t) = pool.draw(n as usize, config.seed, e);
                let sampling = new_sampling + draw.elapsed().as_secs_f64();
                new_sampling = 0.0;
                let lod = config.levels_at(e, levels);
                // A resumed epoch skips the steps it had done.
                let skip = (e == first_epoch).then_some(*epoch_steps_done);
                let run = EpochSteps::run(
                    &mut stepper,
                    (e, lod, end_epoch),
                    EpochData::Host(p, t),
                    skip.unwrap_or(0),
                    steps_done,
                    should_stop,
                )?;
                let elapsed = start.elapsed().as_secs_f64();
                let plans = &mut report.length_plans;
                let least = first_epoch + epochs;
                if let Some(end) =
                    run.planned_end(config, plans, least, e, elapsed, elapsed - epoch_began)
                {
                    end_epoch = end;
                    if pending.is_none() && schedule.due(next_block) < end_epoch {
                        pending = Some(spawn(next_block));
                    }
                }
                let stats = run.stats(e, lod, end_epoch - first_epoch, (sampling, stall));
                stall = 0.0;
                on_epoch(&stats);
                report.add(stats, run.last_loss);
                (*epochs_done, *epoch_steps_done) = run.done_after(e);
                if run.stop {
                    report.stopped_early = true;
                    // Let the pending sampler finish (scope joins it); its work is discarded.
                    break;
                }
                e += 1;
                epoch_began = start.elapsed().as_secs_f64();
            }
            Ok(())
        })?;
        report.total_seconds = start.elapsed().as_secs_f64();
        Ok(report)
    }
}

/// What the GPU side of an epoch works with: the epoch's points are uploaded; its optimiser
/// steps run on them.
struct Stepper<'a> {
    gpu: &'a GpuContext,
    points: &'a wgpu::Buffer,
    targets: &'a wgpu::Buffer,
    adam: &'a mut Adam,
    kernels: &'a mut TrainKernels,
    stager: &'a mut UniformStager,
    config: &'a NglodTrainConfig,
    /// Points per epoch.
    n: u32,
    /// Points per step.
    batch: u32,
    steps_per_epoch: usize,
}

/// An epoch's points and labels: drawn on the host (uploaded first), or drawn and labelled
/// on the GPU in the epoch's first submission.
enum EpochData<'a> {
    Host(Vec<Vec3>, Vec<f32>),
    Gpu(&'a LabelledDraw, gpu_points::GpuEpoch),
}

/// What one epoch's optimiser steps did.
#[derive(Clone, Copy)]
struct EpochSteps {
    /// Steps run (those a resume skipped not counted).
    steps: usize,
    /// Mean of the loss read-backs.
    mean_loss: f32,
    /// The last loss read back.
    last_loss: f32,
    /// Learning rate of the last step.
    lr: f32,
    /// The first point not trained on: `n` once the epoch is done.
    first: u32,
    /// Steps done within the epoch, skipped ones included.
    step_in_epoch: usize,
    /// Whether `should_stop` ended the epoch part-way.
    stop: bool,
    /// Wall time of the upload, the steps and the final wait.
    gpu_seconds: f64,
    /// Points per epoch (the epoch is done when `first` reaches it).
    n: u32,
}

/// Whether a run started at `start` should stop: past `config.max_seconds`, or asked to by
/// `flag` (Ctrl-C, SIGTERM, a caller's flag).
fn stop_requested(config: &NglodTrainConfig, start: Instant, flag: Option<&AtomicBool>) -> bool {
    config
        .max_seconds
        .is_some_and(|m| start.elapsed().as_secs_f64() >= m)
        || flag.is_some_and(|f| f.load(Ordering::Relaxed))
}

impl EpochSteps {
    /// The run's end as the time budget plans it after this epoch, epoch `e`, `elapsed`
    /// seconds into the run and `epoch_seconds` into the epoch: after each of the run's first
    /// two epochs (a resumed one too, which may be the last its provisional length holds) that
    /// ended rather than stopped, at least `least`; `plans` counts the plans made. The pace is
    /// a whole epoch's: a resumed epoch ran only the steps its checkpoint had not, and would
    /// look faster than it is.
    fn planned_end(
        &self,
        config: &NglodTrainConfig,
        plans: &mut usize,
        least: usize,
        e: usize,
        elapsed: f64,
        epoch_seconds: f64,
    ) -> Option<usize> {
        let budget = config
            .time_budget
            .filter(|_| *plans < 2 && !self.stop && self.first >= self.n && self.steps > 0)?;
        *plans += 1;
        let pace = epoch_seconds * self.step_in_epoch as f64 / self.steps as f64;
        Some(budget.epochs(least, e + 1, elapsed, pace))
    }

    /// The record of this epoch, epoch `e` on `levels` levels of a run planned to `planned`
    /// epochs, with its `(sampling, stall)` seconds.
    fn stats(
        &self,
        e: usize,
        levels: usize,
        planned: usize,
        (sampling_seconds, stall_seconds): (f64, f64),
    ) -> EpochStats {
        EpochStats {
            epoch: e,
            steps: self.steps,
            loss: self.mean_loss,
            gpu_seconds: self.gpu_seconds,
            sampling_seconds,
            stall_seconds,
            lr: self.lr,
            levels,
            planned,
        }
    }

    /// `(epochs done, steps done in the unfinished epoch)` after this epoch, epoch `e`: an
    /// epoch stopped part-way stays unfinished, with its steps recorded, so that a resume runs
    /// the rest of it instead of skipping it.
    fn done_after(&self, e: usize) -> (usize, usize) {
        if self.first >= self.n {
            (e + 1, 0)
        } else {
            (e, self.step_in_epoch)
        }
    }

    /// Uploads epoch `e`'s points and targets (or records their draw) and runs the epoch on its first `lod` levels, in a
    /// run planned to `end_epoch`, from its step `skip` on, reading the loss
    /// back every `loss_every` steps and at the end, and stopping after a read-back once
    /// `should_stop` says so. `steps_done` counts every step of the run.
    fn run(
        s: &mut Stepper<'_>,
        (e, lod, end_epoch): (usize, usize, usize),
        data: EpochData<'_>,
        skip: usize,
        steps_done: &mut usize,
        should_stop: impl Fn() -> bool,
    ) -> Result<Self, NglodError> {
        let start = Instant::now();
        let Stepper {
            gpu,
            points: points_buffer,
            targets: targets_buffer,
            ref mut adam,
            ref mut kernels,
            ref mut stager,
            config,
            n,
            batch,
            steps_per_epoch,
        } = *s;
        let mut draw = match data {
            EpochData::Host(points, targets) => {
                gpu.write(points_buffer, bytemuck::cast_slice::<Vec3, f32>(&points))?;
                gpu.write(targets_buffer, &targets)?;
                None
            }
            EpochData::Gpu(draw, epoch) => Some((draw, epoch)),
        };
        kernels.set_lod(config.objective, lod);
        let mut steps = 0;
        let (mut loss_sum, mut loss_reads) = (0.0f64, 0usize);
        let mut since_read = 0u32;
        let mut last_loss = f32::NAN;
        let mut stop = false;
        let mut lr = config.adam.lr;
        let mut first = (skip as u32).saturating_mul(batch).min(n);
        let mut step_in_epoch = skip;
        // The loss read of the last submission that holds one: waited for only after the next
        // submission is on its way, so that the GPU works while the host records.
        let mut pending: Option<(PendingRead, u32, usize)> = None;
        let mut settle = |(read, points, step): (PendingRead, u32, usize)| {
            let loss = read.wait::<f32>(gpu)?[0] / points as f32;
            if !loss.is_finite() {
                return Err(NglodError::Diverged {
                    epoch: e,
                    step,
                    loss,
                });
            }
            last_loss = loss;
            loss_sum += f64::from(loss);
            loss_reads += 1;
            Ok(())
        };
        while first < n {
            // The steps up to the next loss read-back (at most STEPS_PER_SUBMISSION) share a
            // submission, the epoch's draw (if on the GPU) leading the first.
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            if let Some((draw, epoch)) = draw.take() {
                epoch.record(gpu, draw, &mut enc)?;
            }
            let mut read_due = false;
            for _ in 0..STEPS_PER_SUBMISSION {
                let nb = batch.min(n - first);
                lr = config.lr_at(
                    (e as f64 + step_in_epoch as f64 / steps_per_epoch as f64) / end_epoch as f64,
                );
                adam.config.lr = lr;
                kernels.record_staged(gpu, &mut enc, stager, first, nb)?;
                adam.record_step_staged(gpu, &mut enc, stager, 1.0 / nb as f32)?;
                first += nb;
                steps += 1;
                step_in_epoch += 1;
                since_read += nb;
                *steps_done += 1;
                read_due = steps % config.loss_every == 0 || first >= n;
                if read_due {
                    break;
                }
            }
            stager.flush(gpu);
            if !read_due {
                gpu.queue().submit([enc.finish()]);
                continue;
            }
            let copy = gpu.record_read(&mut enc, &kernels.stats, 0, 4);
            enc.clear_buffer(&kernels.stats, 0, None);
            let read = (gpu.submit_with_read(enc, copy), since_read, *steps_done - 1);
            since_read = 0;
            if let Some(previous) = pending.replace(read) {
                settle(previous)?;
            }
            // Polled where the loss is read, as before the reads overlapped the next steps.
            if should_stop() {
                stop = true;
                break;
            }
        }
        if let Some(last) = pending.take() {
            settle(last)?;
        }
        gpu.wait()?;
        Ok(EpochSteps {
            gpu_seconds: start.elapsed().as_secs_f64(),
            steps,
            mean_loss: (loss_sum / loss_reads.max(1) as f64) as f32,
            last_loss,
            lr,
            first,
            step_in_epoch,
            stop,
            n,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_time_budget_fits_epochs_between_its_bounds() {
        let b = TimeBudget {
            seconds: 60.0,
            max_epochs: 100,
        };
        // After the first epoch (4.5 s, 1.6 s), then after the second (from 2 s in all).
        assert_eq!(b.epochs(12, 1, 4.5, 4.5), 13);
        assert_eq!(b.epochs(12, 1, 1.6, 1.6), 37);
        assert_eq!(b.epochs(12, 2, 3.0, 1.2), 49);
        assert_eq!(
            b.epochs(12, 1, 10.0, 10.0),
            12,
            "never fewer than the least"
        );
        assert_eq!(b.epochs(12, 2, 70.0, 1.0), 12, "past the budget");
        assert_eq!(b.epochs(12, 1, 0.1, 0.1), 100, "never more than max_epochs");
        assert_eq!(
            b.epochs(120, 1, 0.1, 0.1),
            120,
            "the least wins over max_epochs"
        );
        assert_eq!(b.epochs(3, 1, 0.0, 0.0), 100, "an epoch of no time");
    }

    #[test]
    fn lr_decay_and_level_growth() {
        let c = NglodTrainConfig {
            lr_final: Some(0.1),
            grow_every: Some(3),
            ..Default::default()
        };
        assert_eq!(c.lr_at(0.0), 1e-3);
        assert!((c.lr_at(1.0) - 1e-4).abs() < 1e-9);
        assert!((c.lr_at(0.5) - 5.5e-4).abs() < 1e-9);
        let constant = NglodTrainConfig {
            lr_final: None,
            ..Default::default()
        };
        assert_eq!(constant.lr_at(0.7), 1e-3);
        // The default decays by a cosine to a tenth (docs/benchmarks, the NGLOD schedule study).
        let d = NglodTrainConfig::default();
        assert_eq!(d.lr_at(0.0), 1e-3);
        assert!((d.lr_at(1.0) - 1e-4).abs() < 1e-9);
        assert_eq!(
            (0..9).map(|e| c.levels_at(e, 3)).collect::<Vec<_>>(),
            [1, 1, 1, 2, 2, 2, 3, 3, 3]
        );
        assert_eq!(NglodTrainConfig::default().levels_at(0, 3), 3);
    }
}
