//! The trainer's other source of points: every epoch drawn and labelled on the GPU
//! ([`crate::ground_truth::LabelledDraw`]) straight into the buffers the training step reads,
//! recorded in the epoch's first submission, so that no point crosses to the host.

use std::time::Instant;

use sdf_geom::{Mesh, SignedDistance};

use super::{
    DistanceMode, EpochData, EpochStats, EpochSteps, NglodTrainer, Stepper, TrainReport,
    stop_requested,
};
use crate::gpu::GpuContext;
use crate::ground_truth::{
    GpuGroundTruth, GpuSampler, LabelKind, LabelledDraw, SampleSpec, SampleTable,
};
use crate::nglod::{NglodError, NglodTrainConfig};

/// Where the trainer's points and their labels come from ([`NglodTrainConfig::sample_source`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SampleSource {
    /// The pool of blocks drawn and labelled on CPU threads, partly redrawn every few epochs
    /// ([`NglodTrainConfig::pool_blocks`], [`NglodTrainConfig::refresh_every`]).
    #[default]
    CpuPool,
    /// Fresh points every epoch, drawn and labelled on the GPU
    /// ([`crate::ground_truth::GpuSampler`], [`crate::ground_truth::GpuGroundTruth`]): the same
    /// mixture of uniform, near-surface (σ) and surface points as a pool block, spread over the
    /// epoch by a random permutation; `pool_blocks` and `refresh_every` do not apply. Epoch `e`'s
    /// points are a function of the seed and `e` (a resume redraws them). As in the pool, the
    /// surface points are labelled 0 without a query.
    Gpu,
}

impl SampleSource {
    /// `"cpu-pool"` or `"gpu"`.
    pub fn name(self) -> &'static str {
        match self {
            SampleSource::CpuPool => "cpu-pool",
            SampleSource::Gpu => "gpu",
        }
    }
}

/// The mesh's sampler and ground truth on the GPU, bound to the trainer's epoch buffers.
pub(super) struct GpuPoints {
    pub(super) draw: LabelledDraw,
    /// Kept alive for the draw's bind groups (wgpu handles are shared, this is for clarity).
    _sampler: GpuSampler,
    _ground_truth: GpuGroundTruth,
}

impl GpuPoints {
    /// Uploads `mesh`'s sample table and `sdf`'s trees and binds them to `points` and `targets`.
    pub(super) fn new(
        gpu: &GpuContext,
        mesh: &Mesh,
        sdf: &SignedDistance,
        config: &NglodTrainConfig,
        (points, targets): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<Self, NglodError> {
        let table = SampleTable::new(mesh)?;
        let sampler = GpuSampler::new(gpu, &table)?;
        let gt = GpuGroundTruth::new(gpu, sdf)?;
        let labels = match config.distance {
            DistanceMode::Signed => LabelKind::Signed,
            DistanceMode::Unsigned => LabelKind::Unsigned,
        };
        let draw = LabelledDraw::new(gpu, &sampler, &gt, points, targets, labels)?;
        Ok(GpuPoints {
            draw,
            _sampler: sampler,
            _ground_truth: gt,
        })
    }

    /// The draw of epoch `epoch`.
    pub(super) fn spec(config: &NglodTrainConfig, epoch: usize) -> SampleSpec {
        // `check` bounds the points per epoch by u32::MAX.
        SampleSpec {
            uniform: config.uniform_points as u32,
            near: config.near_points as u32,
            surface: config.surface_points as u32,
            sigma: config.sigma,
            seed: config.seed,
            stream: epoch as u32,
            shuffle: true,
        }
    }
}

impl NglodTrainer<'_> {
    /// [`NglodTrainer::train_with`] with [`SampleSource::Gpu`]: each epoch's first submission
    /// draws and labels its points on the GPU, then its steps run on them.
    pub(super) fn train_on_gpu_points(
        &mut self,
        mut on_epoch: impl FnMut(&EpochStats),
    ) -> Result<TrainReport, NglodError> {
        let start = Instant::now();
        let mut report = TrainReport::default();
        let levels = self.model.config().levels();
        let config = &self.config;
        let Some(source) = &self.gpu_points else {
            unreachable!("called with SampleSource::Gpu only")
        };
        let first_epoch = self.epochs_done;
        let mut end_epoch = first_epoch + config.epochs;
        let n = config.points_per_epoch() as u32;
        let batch = config.batch_size.min(n);
        let mut stepper = Stepper {
            gpu: self.gpu,
            points: &self.points,
            targets: &self.targets,
            adam: &mut self.adam,
            kernels: &mut self.kernels,
            stager: &mut self.stager,
            config,
            n,
            batch,
            steps_per_epoch: n.div_ceil(batch) as usize,
        };
        let stop_flag = self.stop.as_deref();
        let should_stop = || stop_requested(config, start, stop_flag);
        let mut e = first_epoch;
        let mut epoch_began = 0.0;
        while e < end_epoch {
            let lod = config.levels_at(e, levels);
            let skip = if e == first_epoch {
                self.epoch_steps_done
            } else {
                0
            };
            let data = EpochData::Gpu(&source.draw, GpuPoints::spec(config, e));
            let run = EpochSteps::run(
                &mut stepper,
                (e, lod, end_epoch),
                data,
                skip,
                &mut self.steps_done,
                should_stop,
            )?;
            if let Some(b) = run.plans_length(config, first_epoch, e) {
                let elapsed = start.elapsed().as_secs_f64();
                end_epoch = b.epochs(config.epochs, e + 1, elapsed, elapsed - epoch_began);
            }
            // Drawn in the epoch's first submission: no sampling or stall of its own.
            let stats = run.stats(e, lod, end_epoch - first_epoch, (0.0, 0.0));
            on_epoch(&stats);
            report.add(stats, run.last_loss);
            (self.epochs_done, self.epoch_steps_done) = run.done_after(e);
            if run.stop {
                report.stopped_early = true;
                break;
            }
            e += 1;
            epoch_began = start.elapsed().as_secs_f64();
        }
        report.total_seconds = start.elapsed().as_secs_f64();
        Ok(report)
    }
}
