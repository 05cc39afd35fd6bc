//! Training a SIREN on the GPU: the dataset (Poisson-disk surface samples with normals, and box
//! points with their side of the surface) is uploaded once; every step samples its batch on the
//! GPU, runs forward, loss and double backward, then Adam, all in one command buffer. The loss
//! goes into a small history buffer that the host reads only every
//! [`SirenTrainConfig::loss_every`] steps.

use std::time::{Duration, Instant};

use glam::{Vec3, Vec4};
use serde::{Deserialize, Serialize};

use super::gpu::{SirenGpu, SirenGpuError};
use super::kernels::Launch;
use super::loss::{LossTerms, LossWeights};
use super::options::SirenGpuOptions;
use super::step::passes::TrainPasses;
use super::{Siren, SirenConfigError};
use crate::adam::{Adam, AdamConfig};
use crate::gpu::{GpuContext, GpuError, PassProfiler, PassTime, entry};
use crate::ground_truth::{GroundTruthError, Labeller};
use crate::model_file::{self, ModelFile};
use crate::shaders;

/// Hyperparameters of SIREN training.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SirenTrainConfig {
    /// Steps to run in [`SirenTrainer::train`]. The default, 10 000, is the order the SIREN
    /// reference code runs for a shape (its 10k epochs of one batch each); on a GPU that
    /// converges the reference network.
    pub steps: usize,
    /// Surface points per step (5000).
    pub surface_per_step: usize,
    /// Box points per step (5000).
    pub box_per_step: usize,
    /// Poisson-disk surface samples in the dataset (10^5).
    pub dataset_size: usize,
    /// Box points whose side of the surface [`SirenTrainer::from_mesh`] labels once, for the
    /// sign term; each step draws its box points from them (at most `steps × box_per_step`
    /// are labelled). 0, a sign weight of 0 or a mesh without an inside draws fresh uniform
    /// points of unknown side instead (no sign term); so do the configurations of model files
    /// written before it.
    #[serde(default)]
    pub box_pool: usize,
    /// Loss weights.
    pub weights: LossWeights,
    /// Initial Adam learning rate (1e-4).
    pub lr: f32,
    /// Steps without a relative improvement of [`Self::plateau_threshold`] in the (windowed)
    /// loss before the learning rate is divided by 10 (the design document's "divide by 10
    /// when the loss plateaus"). 0 never divides it: a constant rate, as the SIREN reference
    /// code trains.
    pub plateau_patience: usize,
    /// Relative improvement that counts as progress (1e-3).
    pub plateau_threshold: f32,
    /// The learning rate is never reduced below this.
    pub min_lr: f32,
    /// Steps between loss readbacks (the GPU queue drains only then).
    pub loss_every: usize,
    /// Seed of the dataset sampling and of the per-step batches.
    pub seed: u64,
}

impl Default for SirenTrainConfig {
    fn default() -> Self {
        SirenTrainConfig {
            steps: 10_000,
            surface_per_step: 5000,
            box_per_step: 5000,
            dataset_size: 100_000,
            box_pool: BOX_POOL,
            weights: LossWeights::default(),
            lr: 1e-4,
            plateau_patience: 500,
            plateau_threshold: 1e-3,
            min_lr: 1e-7,
            loss_every: 25,
            seed: 0,
        }
    }
}

impl LossWeights {
    /// Errors unless every weight is finite and non-negative and α finite and positive.
    pub fn validate(&self) -> Result<(), TrainError> {
        let w = self;
        for (name, x) in [
            ("surface", w.surface),
            ("off-surface", w.off_surface),
            ("normal", w.normal),
            ("eikonal", w.eikonal),
            ("sign", w.sign),
        ] {
            if !(x.is_finite() && x >= 0.0) {
                return Err(TrainError::BadTrainConfig(format!(
                    "the {name} loss weight must be finite and non-negative, not {x}"
                )));
            }
        }
        if !(w.alpha.is_finite() && w.alpha > 0.0) {
            return Err(TrainError::BadTrainConfig(format!(
                "alpha, the sharpness of the off-surface term exp(−α|Φ|), must be finite and positive, not {}",
                w.alpha
            )));
        }
        Ok(())
    }
}

/// Training failures.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The device failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The mesh cannot be queried for the sides of the box points.
    #[error(transparent)]
    Geom(#[from] sdf_geom::GeomError),
    /// The network configuration is unusable.
    #[error(transparent)]
    Config(#[from] SirenConfigError),
    /// Labelling the box pool on the GPU failed.
    #[error("ground truth: {0}")]
    GroundTruth(#[from] crate::ground_truth::GroundTruthError),
    /// The training configuration is unusable.
    #[error("invalid training configuration: {0}")]
    BadTrainConfig(String),
    /// No surface samples (a mesh without area, or an empty dataset).
    #[error("the training dataset has no surface points (does the mesh have any area?)")]
    EmptyDataset,
    /// The loss became NaN or infinite.
    #[error(
        "training diverged at step {step}: loss is {loss} (try a lower learning rate or other loss weights)"
    )]
    Diverged {
        /// The step whose loss was not finite.
        step: usize,
        /// That loss.
        loss: f32,
    },
}

impl From<SirenGpuError> for TrainError {
    fn from(e: SirenGpuError) -> Self {
        match e {
            SirenGpuError::Gpu(g) => TrainError::Gpu(g),
            SirenGpuError::Config(c) => TrainError::Config(c),
            e @ SirenGpuError::KernelsUnsupported { .. } => {
                TrainError::BadTrainConfig(e.to_string())
            }
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct SampleUniforms {
    n_points: u32,
    n_surface: u32,
    n_data: u32,
    seed: u32,
    n_pool: u32,
    _pad: [u32; 3],
}

/// Default of [`SirenTrainConfig::box_pool`]: 2^20 points, one per 0.02³ of the cube, each
/// drawn about 50 times in 10⁴ steps of 5000.
pub const BOX_POOL: usize = 1 << 20;

/// Box points in `[-1, 1]³` with their side of the surface of the normalised mesh `sdf` was
/// built on: `(x, y, z, s)` with `s` = −1 inside (a winding number of at least 1/2), +1
/// outside: the sign the evaluation's ground truth gives, also on open meshes.
pub fn sided_box_points(sdf: &sdf_geom::SignedDistance, n: usize, seed: u64) -> Vec<Vec4> {
    let points = sdf_geom::sample::uniform_box(n, seed);
    let inside = sdf.is_inside_batch(&points);
    sided(&points, inside)
}

/// [`sided_box_points`] with the sides from `labels` (the path the run chose: CPU or GPU).
///
/// # Errors
/// The GPU's, where `labels` runs there.
pub fn sided_box_points_with(
    labels: &Labeller<'_>,
    n: usize,
    seed: u64,
) -> Result<Vec<Vec4>, GroundTruthError> {
    let points = sdf_geom::sample::uniform_box(n, seed);
    let inside = labels.is_inside_batch(&points)?;
    Ok(sided(&points, inside))
}

/// `(x, y, z, s)`, `s` = −1 where `inside`, else +1.
fn sided(points: &[Vec3], inside: Vec<bool>) -> Vec<Vec4> {
    points
        .iter()
        .zip(inside)
        .map(|(p, inside)| p.extend(if inside { -1.0 } else { 1.0 }))
        .collect()
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct LossReduceUniforms {
    n_partials: u32,
    slot: u32,
    _pad: [u32; 2],
}

/// What [`SirenTrainer::train`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainSummary {
    /// Steps run.
    pub steps: usize,
    /// Mean loss over the last readback window.
    pub final_loss: LossTerms,
    /// Learning rate at the end.
    pub final_lr: f32,
    /// Wall time.
    pub elapsed: Duration,
}

/// Trains a SIREN on the GPU.
#[derive(Debug)]
pub struct SirenTrainer {
    config: SirenTrainConfig,
    net: SirenGpu,
    adam: Adam,
    passes: TrainPasses,
    sample: Launch,
    sample_uniforms: wgpu::Buffer,
    loss_reduce: Launch,
    loss_uniforms: wgpu::Buffer,
    history: wgpu::Buffer,
    _dataset: [wgpu::Buffer; 3],
    normalization: model_file::Normalization,
    step: usize,
    plateau: Plateau,
    last_loss: Option<LossTerms>,
    /// Points in the box pool (0: uniform box points).
    n_pool: u32,
}

/// Reduce-on-plateau over the windowed loss ([`SirenTrainConfig::plateau_patience`]).
#[derive(Clone, Copy, Debug)]
struct Plateau {
    /// The loss that later windows must beat.
    best: f32,
    /// Steps since it was set.
    since_best: usize,
}

impl Plateau {
    fn new() -> Self {
        Plateau {
            best: f32::INFINITY,
            since_best: 0,
        }
    }

    /// The learning rate after a readback window whose mean loss is `loss`, at rate `lr`:
    /// divided by 10 (to no less than `min_lr`) after `plateau_patience` steps without a
    /// relative improvement of `plateau_threshold`; the window that cuts it is the next best.
    fn next_lr(&mut self, c: &SirenTrainConfig, loss: f32, lr: f32) -> f32 {
        if loss < self.best * (1.0 - c.plateau_threshold) {
            self.best = loss;
            self.since_best = 0;
            return lr;
        }
        self.since_best += c.loss_every;
        if c.plateau_patience == 0 || self.since_best < c.plateau_patience {
            return lr;
        }
        self.since_best = 0;
        self.best = loss;
        // Never up: a rate already under the floor (a resume with a lower `--lr` scales the
        // checkpoint's) stays where it is.
        (lr / 10.0).max(c.min_lr.min(lr))
    }
}

/// Mixes a seed and a step into a 32-bit kernel seed.
fn step_seed(seed: u64, step: usize) -> u32 {
    let mut x = seed ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x as u32
}

impl SirenTrainer {
    /// A trainer for `siren` on a normalised mesh (see `sdf_geom::Mesh::normalized`), whose
    /// normalisation is recorded for the model file: samples the Poisson-disk dataset.
    pub fn from_mesh(
        gpu: &GpuContext,
        siren: &Siren,
        mesh: &sdf_geom::Mesh,
        config: SirenTrainConfig,
    ) -> Result<Self, TrainError> {
        Self::sampled(gpu, siren, mesh, None, config)
    }

    /// [`SirenTrainer::from_mesh`] with the exact ground truth of `mesh` (normalised, as
    /// there) already built: `labels` must label `SignedDistance::new(mesh)`, on the path the
    /// run chose ([`Labeller::choose`]). It labels the box pool, so a caller that also evaluates
    /// against the mesh builds its BVH once. (`from_mesh` labels with the SDF of `mesh`
    /// normalised once more, which can differ from `mesh` by an ulp: a label within about 1e-7
    /// of the surface may differ between the two.)
    pub fn with_ground_truth(
        gpu: &GpuContext,
        siren: &Siren,
        mesh: &sdf_geom::Mesh,
        labels: &Labeller<'_>,
        config: SirenTrainConfig,
    ) -> Result<Self, TrainError> {
        Self::sampled(gpu, siren, mesh, Some(labels), config)
    }

    /// The dataset and the box pool sampled from `mesh` (the pool labelled by `labels`, or by one
    /// built here where it is `None` and the run needs a pool).
    fn sampled(
        gpu: &GpuContext,
        siren: &Siren,
        mesh: &sdf_geom::Mesh,
        labels: Option<&Labeller<'_>>,
        config: SirenTrainConfig,
    ) -> Result<Self, TrainError> {
        let (normalized, norm) = mesh.normalized();
        let samples =
            sdf_geom::sample::poisson_disk(&normalized, config.dataset_size, config.seed).samples;
        // Never more points than the run will draw: a short run labels fewer.
        let pool_size = config
            .box_pool
            .min(config.steps.saturating_mul(config.box_per_step));
        let mut pool = if pool_size > 0 && config.weights.sign > 0.0 {
            match labels {
                Some(labels) => sided_box_points_with(labels, pool_size, config.seed ^ 0x51DE)?,
                None => {
                    let sdf = sdf_geom::SignedDistance::new(&normalized)?;
                    sided_box_points(&sdf, pool_size, config.seed ^ 0x51DE)
                }
            }
        } else {
            Vec::new()
        };
        // A mesh with no inside (a sheet, a two-sided soup): "outside" everywhere would fight
        // the zero crossing the surface terms make, so it trains on the design's loss alone.
        if !pool.iter().any(|b| b.w < 0.0) {
            pool.clear();
        }
        Self::new(
            gpu,
            siren,
            &samples.points,
            &samples.normals,
            &pool,
            norm,
            config,
        )
    }

    /// A trainer for `siren` on a dataset of surface points and unit normals, already in the
    /// normalised cube. The box points are drawn from `box_pool` (points with their side, as
    /// [`sided_box_points`] makes them), or, where it is empty, uniformly from `[-1, 1]³` with
    /// no sign term.
    pub fn new(
        gpu: &GpuContext,
        siren: &Siren,
        points: &[Vec3],
        normals: &[Vec3],
        box_pool: &[Vec4],
        normalization: model_file::Normalization,
        config: SirenTrainConfig,
    ) -> Result<Self, TrainError> {
        if points.is_empty() {
            return Err(TrainError::EmptyDataset);
        }
        if points.len() != normals.len() {
            return Err(TrainError::BadTrainConfig(format!(
                "{} points but {} normals",
                points.len(),
                normals.len()
            )));
        }
        let n = config.surface_per_step + config.box_per_step;
        if n == 0 || n > (1 << 22) {
            return Err(TrainError::BadTrainConfig(format!(
                "batch of {n} points; it must be between 1 and 4194304"
            )));
        }
        if config.loss_every == 0 || config.loss_every > 4096 {
            return Err(TrainError::BadTrainConfig(
                "loss_every must be in 1..=4096".into(),
            ));
        }
        crate::AdamConfig::check_lr(config.lr).map_err(TrainError::BadTrainConfig)?;
        config.weights.validate()?;
        let net = SirenGpu::new(gpu, siren)?;
        let passes = TrainPasses::new(
            gpu,
            &net.step_net(gpu),
            n as u32,
            config.surface_per_step as u32,
            &config.weights,
        )?;
        let adam = Adam::new(
            gpu,
            net.params_buffer(),
            net.grads_buffer(),
            siren.params().len() as u32,
            AdamConfig {
                lr: config.lr,
                ..AdamConfig::default()
            },
        )?;
        let flat_p: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
        let flat_n: Vec<f32> = normals.iter().flat_map(|p| p.to_array()).collect();
        let data_p = gpu.storage_from_slice("siren dataset points", &flat_p)?;
        let data_n = gpu.storage_from_slice("siren dataset normals", &flat_n)?;
        if box_pool.len() > u32::MAX as usize
            || box_pool
                .iter()
                .any(|b| !b.is_finite() || ![-1.0, 0.0, 1.0].contains(&b.w))
        {
            return Err(TrainError::BadTrainConfig(
                "the box pool's points must be finite, with sides −1, 0 or +1".into(),
            ));
        }
        let pool_data: Vec<f32> = if box_pool.is_empty() {
            vec![0.0; 4]
        } else {
            box_pool.iter().flat_map(|b| b.to_array()).collect()
        };
        let pool = gpu.storage_from_slice("siren box pool", &pool_data)?;
        let sample_uniforms = gpu.uniform(
            "siren sample",
            &SampleUniforms {
                n_points: n as u32,
                n_surface: config.surface_per_step as u32,
                n_data: points.len() as u32,
                seed: 0,
                n_pool: box_pool.len() as u32,
                _pad: [0; 3],
            },
        );
        let sample_pipeline = gpu.pipeline(&shaders::SIREN_TRAIN, "sample", &[])?;
        let sample = Launch::flat(
            gpu,
            &sample_pipeline,
            "siren sample",
            &[
                entry(0, &sample_uniforms),
                entry(1, &data_p),
                entry(2, &data_n),
                entry(3, &passes.x_streams),
                entry(4, &passes.normals),
                entry(11, &pool),
            ],
            n as u32,
        );
        let loss_uniforms = gpu.uniform("siren loss reduce", &LossReduceUniforms::default());
        let history = gpu.storage_zeroed("siren loss history", config.loss_every as u64 * 16)?;
        let reduce_pipeline = gpu.pipeline(&shaders::SIREN_TRAIN, "reduce_loss", &[])?;
        let loss_reduce = Launch::new(
            gpu,
            &reduce_pipeline,
            "siren loss reduce",
            &[
                entry(8, &loss_uniforms),
                entry(9, &passes.loss_partial),
                entry(10, &history),
            ],
            (1, 1, 1),
        );
        Ok(SirenTrainer {
            config,
            net,
            adam,
            passes,
            sample,
            sample_uniforms,
            loss_reduce,
            loss_uniforms,
            history,
            _dataset: [data_p, data_n, pool],
            normalization,
            step: 0,
            plateau: Plateau::new(),
            last_loss: None,
            n_pool: box_pool.len() as u32,
        })
    }

    /// The training configuration.
    pub fn config(&self) -> &SirenTrainConfig {
        &self.config
    }

    /// Steps taken so far.
    pub fn steps_done(&self) -> usize {
        self.step
    }

    /// The current learning rate.
    pub fn lr(&self) -> f32 {
        self.adam.config.lr
    }

    /// Box points in the labelled pool that steps draw from (0: uniform box points of unknown
    /// side, no sign term; see [`SirenTrainConfig::box_pool`]).
    pub fn box_pool_len(&self) -> usize {
        self.n_pool as usize
    }

    /// The most recent loss read back (mean over the last window).
    pub fn last_loss(&self) -> Option<LossTerms> {
        self.last_loss
    }

    /// Changes the network's knobs ([`SirenGpu::set_options`]: its kernels, their blocking,
    /// the training step) and rebuilds the training passes for them.
    pub fn set_net_options(
        &mut self,
        gpu: &GpuContext,
        options: &SirenGpuOptions,
    ) -> Result<(), TrainError> {
        self.net.set_options(gpu, options)?;
        let net = self.net.step_net(gpu);
        self.passes = self.passes.rebuilt(gpu, &net, &self.config.weights)?;
        Ok(())
    }

    /// The network on the GPU (e.g. for evaluation between steps). Change its options with
    /// [`SirenTrainer::set_net_options`], which also rebuilds the training passes.
    pub fn net(&mut self) -> &mut SirenGpu {
        &mut self.net
    }

    /// The normalisation of the mesh the dataset came from.
    pub fn normalization(&self) -> model_file::Normalization {
        self.normalization
    }

    /// The trained network on the host.
    pub fn siren(&self, gpu: &GpuContext) -> Result<Siren, TrainError> {
        Ok(self.net.download(gpu)?)
    }

    /// The model file of the network as trained so far, with the training configuration in its
    /// metadata.
    pub fn model_file(&self, gpu: &GpuContext) -> Result<ModelFile, TrainError> {
        let siren = self.siren(gpu)?;
        let training = serde_json::json!({
            "config": self.config,
            "steps_done": self.step,
            "final_lr": self.lr(),
            "last_loss": self.last_loss,
        });
        Ok(siren.to_model_file(self.normalization, training))
    }

    /// Records forward, loss, backward and Adam for one step and submits them. Every
    /// `loss_every` steps it reads the loss history back, checks for divergence, applies the
    /// plateau schedule and returns the window's mean loss.
    pub fn step(&mut self, gpu: &GpuContext) -> Result<Option<LossTerms>, TrainError> {
        let k = self.config.loss_every;
        let slot = self.write_step_uniforms(gpu)?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        self.net.record_pack(&mut enc);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("siren step"),
                timestamp_writes: None,
            });
            self.sample.record(&mut pass);
            self.passes.record(&mut pass);
            self.loss_reduce.record(&mut pass);
        }
        // The backward kernels accumulate the gradient of the mean loss already.
        self.adam.record_step(gpu, &mut enc, 1.0);
        gpu.queue().submit([enc.finish()]);
        self.step += 1;
        if slot + 1 < k {
            return Ok(None);
        }
        self.read_loss_window(gpu).map(Some)
    }

    /// One training step, as [`SirenTrainer::step`], with every launch in its own compute pass
    /// timed by `profiler` (sampling, each product and elementwise kernel of the loss and its
    /// gradient, the loss reduction, Adam; the row-blocked kernels' weight copy, where there
    /// is one, runs untimed). It waits for the step and returns the launches' GPU times in
    /// order. The step counts as one of training's; the loss of a window that ends on it is not
    /// read back, so use it for profiles, not for training.
    pub fn profile_step(
        &mut self,
        gpu: &GpuContext,
        profiler: &mut PassProfiler,
    ) -> Result<Vec<PassTime>, TrainError> {
        self.write_step_uniforms(gpu)?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        self.net.record_pack(&mut enc);
        for l in std::iter::once(&self.sample)
            .chain(self.passes.launches())
            .chain([&self.loss_reduce])
        {
            l.record(&mut profiler.begin_pass(&mut enc, l.label()));
        }
        self.adam
            .record_step_in(gpu, &mut profiler.begin_pass(&mut enc, "adam"), 1.0);
        profiler.resolve(&mut enc);
        gpu.queue().submit([enc.finish()]);
        self.step += 1;
        Ok(profiler.read(gpu)?)
    }

    /// Writes the per-step uniforms (the batch's seed, the loss history's slot) and returns
    /// the slot.
    fn write_step_uniforms(&self, gpu: &GpuContext) -> Result<usize, TrainError> {
        let k = self.config.loss_every;
        let slot = self.step % k;
        gpu.write(
            &self.sample_uniforms,
            &[SampleUniforms {
                n_points: self.passes.n,
                n_surface: self.config.surface_per_step as u32,
                n_data: (self._dataset[0].size() / 12) as u32,
                seed: step_seed(self.config.seed, self.step),
                n_pool: self.n_pool,
                _pad: [0; 3],
            }],
        )?;
        gpu.write(
            &self.loss_uniforms,
            &[LossReduceUniforms {
                n_partials: self.passes.loss_groups,
                slot: slot as u32,
                _pad: [0; 2],
            }],
        )?;
        Ok(slot)
    }

    /// Reads the loss history of the window that just ended, checks it for divergence, applies
    /// the plateau schedule and returns the window's mean loss terms.
    fn read_loss_window(&mut self, gpu: &GpuContext) -> Result<LossTerms, TrainError> {
        let k = self.config.loss_every;
        let hist: Vec<f32> = gpu.read_back_range(&self.history, 0, k as u64 * 4)?;
        let mut mean = [0.0f32; 4];
        for (i, row) in hist.chunks_exact(4).enumerate() {
            let total: f32 = row.iter().sum();
            if !total.is_finite() {
                return Err(TrainError::Diverged {
                    step: self.step - k + i,
                    loss: total,
                });
            }
            for t in 0..4 {
                mean[t] += row[t] / k as f32;
            }
        }
        let terms = LossTerms::from_slice(&mean);
        let lr = self.adam.config.lr;
        self.adam.config.lr = self.plateau.next_lr(&self.config, terms.total(), lr);
        self.last_loss = Some(terms);
        Ok(terms)
    }

    /// Runs `steps` steps (rounded up to whole readback windows), calling `progress` with the
    /// step count and the loss at every readback.
    pub fn train(
        &mut self,
        gpu: &GpuContext,
        steps: usize,
        mut progress: impl FnMut(usize, &LossTerms),
    ) -> Result<TrainSummary, TrainError> {
        let start = Instant::now();
        let k = self.config.loss_every;
        let target = self.step + steps.div_ceil(k) * k;
        // Align to the readback window so the final loss is read.
        while self.step < target || !self.step.is_multiple_of(k) {
            if let Some(l) = self.step(gpu)? {
                progress(self.step, &l);
            }
        }
        Ok(TrainSummary {
            steps: self.step,
            final_loss: self.last_loss.unwrap_or_default(),
            final_lr: self.lr(),
            elapsed: start.elapsed(),
        })
    }
}

/// Checkpoints: what an interrupted run saves besides the weights, and how it resumes.
impl SirenTrainer {
    /// The optimiser's moments and step counter.
    pub fn optimizer_state(&self, gpu: &GpuContext) -> Result<crate::AdamState, TrainError> {
        Ok(self.adam.export_state(gpu)?)
    }

    /// Continues a run: restores the optimiser state, the step count (which also seeds the
    /// per-step batches) and the learning rate. The weights come with the [`Siren`] the trainer
    /// was built from.
    pub fn resume(
        &mut self,
        gpu: &GpuContext,
        state: &crate::AdamState,
        steps_done: usize,
        lr: f32,
    ) -> Result<(), TrainError> {
        // A checkpoint's values get the checks a new run's configuration gets.
        crate::AdamConfig::check_lr(lr).map_err(TrainError::BadTrainConfig)?;
        state.validate().map_err(TrainError::BadTrainConfig)?;
        self.adam.import_state(gpu, state)?;
        self.adam.config.lr = lr;
        self.step = steps_done;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The learning rates after each window of `losses` under `c`, from 1e-4.
    fn rates(c: &SirenTrainConfig, losses: &[f32]) -> Vec<f32> {
        let mut p = Plateau::new();
        let mut lr = 1e-4;
        losses
            .iter()
            .map(|&l| {
                lr = p.next_lr(c, l, lr);
                lr
            })
            .collect()
    }

    #[test]
    fn plateau_divides_the_rate_after_patience_steps_without_progress() {
        let c = SirenTrainConfig {
            loss_every: 25,
            plateau_patience: 100,
            min_lr: 2e-6,
            ..SirenTrainConfig::default()
        };
        // Falling by 1 % a window: never a plateau.
        let falling: Vec<f32> = (0..20).map(|i| 0.99f32.powi(i)).collect();
        assert!(rates(&c, &falling).iter().all(|&r| r == 1e-4));
        // Flat after the first window: cut at the fourth window after it (100 steps), again
        // 100 steps later, then held at the floor.
        let flat = [1.0; 14];
        let r = rates(&c, &flat);
        let expect = |i: usize| match i {
            0..=3 => 1e-4,
            4..=7 => 1e-5,
            _ => 2e-6,
        };
        for (i, &ri) in r.iter().enumerate() {
            assert!(
                (ri - expect(i)).abs() <= 1e-6 * expect(i),
                "window {i}: {r:?}"
            );
        }
        // Improvements under the threshold (0.1 %) do not count as progress.
        let creeping: Vec<f32> = (0..5).map(|i| 1.0 - 1e-4 * i as f32).collect();
        assert!((rates(&c, &creeping)[4] - 1e-5).abs() < 1e-11);
        // A window that beats the best by more than the threshold restarts the count.
        let r = rates(&c, &[1.0, 1.0, 1.0, 1.0, 0.9, 0.9, 0.9, 0.9]);
        assert!(r.iter().all(|&x| x == 1e-4), "{r:?}");
        // A rate under the floor is never raised to it.
        let mut p = Plateau::new();
        let mut lr = 1e-6;
        for _ in 0..8 {
            lr = p.next_lr(&c, 1.0, lr);
            assert_eq!(lr, 1e-6);
        }
    }

    #[test]
    fn box_points_take_the_side_that_the_ground_truth_gives() {
        let sphere = sdf_geom::SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 3)).unwrap();
        let pool = sided_box_points(&sphere, 4000, 3);
        assert_eq!(pool.len(), 4000);
        let mut inside = 0;
        for b in &pool {
            assert!(b.truncate().abs().max_element() <= 1.0);
            let r = b.truncate().length();
            // The icosphere lies between radius 0.49 and 0.5.
            if r < 0.48 {
                assert_eq!(b.w, -1.0, "{b}");
            } else if r > 0.51 {
                assert_eq!(b.w, 1.0, "{b}");
            }
            inside += usize::from(b.w == -1.0);
        }
        // A sphere of radius 1/2 fills 6.5 % of the cube.
        assert!((150..400).contains(&inside), "{inside} inside");
        // An open mesh, a cup (the sphere's lower half): its generalised winding number is
        // fractional, and the side is what the evaluation takes, inside from 1/2 on.
        let mut cup = sdf_geom::Mesh::icosphere(0.8, 3);
        cup.triangles
            .retain(|t| t.iter().all(|&v| cup.vertices[v as usize].z < 0.1));
        let cup = sdf_geom::SignedDistance::new(&cup).unwrap();
        let pool = sided_box_points(&cup, 4000, 4);
        let inside = pool.iter().filter(|b| b.w == -1.0).count();
        assert!(inside > 100, "{inside} inside the cup");
        for b in &pool {
            let truth = if cup.is_inside(b.truncate()) {
                -1.0
            } else {
                1.0
            };
            assert_eq!(b.w, truth, "{b}");
        }
    }

    #[test]
    fn plateau_patience_zero_keeps_the_rate_constant() {
        let c = SirenTrainConfig {
            plateau_patience: 0,
            ..SirenTrainConfig::default()
        };
        assert!(rates(&c, &[1.0; 100]).iter().all(|&r| r == 1e-4));
    }
}

#[cfg(test)]
mod uniform_layout {
    /// SampleUniforms, LossReduceUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::SampleUniforms,
            crate::shaders::SIREN_TRAIN,
            "Sample",
            [n_points, n_surface, n_data, seed, n_pool]
        );
        crate::shaders::assert_mirrors!(
            super::LossReduceUniforms,
            crate::shaders::SIREN_TRAIN,
            "LossReduce",
            [n_partials, slot]
        );
    }
}
