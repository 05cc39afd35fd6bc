//! The trainer's other source of points: drawn and labelled on the GPU
//! ([`crate::ground_truth::LabelledDraw`]) into a pool of blocks kept there, on the CPU pool's
//! schedule ([`super::PoolSchedule`]), and gathered into the buffers the training step reads,
//! all recorded in the epoch's first submission, so that no point crosses to the host.

use std::time::Instant;

use sdf_geom::{Mesh, SignedDistance};

use super::{
    DistanceMode, EpochData, EpochStats, EpochSteps, NglodTrainer, Stepper, TrainReport,
    stop_requested,
};
use crate::gpu::{GpuContext, PassProfiler};
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
    /// The pool drawn and labelled on the GPU ([`crate::ground_truth::GpuSampler`],
    /// [`crate::ground_truth::GpuGroundTruth`]) and kept there: blocks of the same mixture of
    /// uniform, near-surface (σ) and surface points on the same schedule
    /// ([`NglodTrainConfig::pool_blocks`], [`NglodTrainConfig::refresh_every`]; both 1: fresh
    /// points every epoch), each epoch's points drawn from the whole pool in a random order.
    /// Block `k` and epoch `e`'s order are functions of the seed and `k` or `e` (a resume
    /// redraws its pool). As in the CPU pool, the surface points are labelled 0 without a query.
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

/// The mesh's sampler and ground truth on the GPU, bound to the trainer's epoch buffers, and
/// the blocks its pool holds.
pub(super) struct GpuPoints {
    pub(super) draw: LabelledDraw,
    /// The block each slot of the pool holds (block `k` goes to slot `k % pool_blocks`).
    slots: Vec<Option<usize>>,
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
        let blocks = u32::try_from(config.pool_blocks).unwrap_or(u32::MAX);
        let draw = LabelledDraw::with_pool(gpu, &sampler, &gt, points, targets, labels, blocks)?;
        Ok(GpuPoints {
            slots: vec![None; config.pool_blocks],
            draw,
            _sampler: sampler,
            _ground_truth: gt,
        })
    }

    /// The order of epoch `epoch`'s points over the pool (its `stream`), or block `epoch`'s
    /// draw without `shuffle`.
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

    /// Brings the pool to epoch `epoch`'s blocks ([`super::PoolSchedule::blocks_at`]): every
    /// missing block but the newest drawn in a submission of its own now (a resume's, or a
    /// profile's leftovers), the newest returned with its slot for the epoch's first
    /// submission (its slot holds no block until [`GpuPoints::placed`]), and the epoch's
    /// gather: its order and the blocks the pool then holds.
    pub(super) fn epoch_draw(
        &mut self,
        gpu: &GpuContext,
        config: &NglodTrainConfig,
        epoch: usize,
    ) -> Result<GpuEpoch, NglodError> {
        let blocks = config.pool().blocks_at(epoch);
        let held = blocks.len() as u32;
        let p = self.slots.len();
        let missing: Vec<usize> = blocks.filter(|&k| self.slots[k % p] != Some(k)).collect();
        let (newest, older) = match missing.split_last() {
            Some((&newest, older)) => (Some(newest), older),
            None => (None, &[][..]),
        };
        for &k in older {
            self.slots[k % p] = None;
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            self.draw
                .record_block(gpu, &mut enc, &Self::block(config, k), (k % p) as u32)?;
            gpu.queue().submit([enc.finish()]);
            self.slots[k % p] = Some(k);
        }
        // Its slot's block is overwritten from here on.
        if let Some(k) = newest {
            self.slots[k % p] = None;
        }
        Ok(GpuEpoch {
            block: newest.map(|k| (Self::block(config, k), (k % p) as u32)),
            gather: (Self::spec(config, epoch), held),
        })
    }

    /// Notes that `epoch`'s new block was recorded (and submitted) into its slot.
    pub(super) fn placed(&mut self, epoch: &GpuEpoch) {
        if let Some((spec, slot)) = epoch.block {
            self.slots[slot as usize] = Some(spec.stream as usize);
        }
    }

    /// Records a block's draw and labelling and epoch `epoch`'s gather for a profile, each
    /// launch timed: the block goes to slot 0, which then holds no block of the schedule
    /// (the next epoch draws it again).
    pub(super) fn profile_draw(
        &mut self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        config: &NglodTrainConfig,
        epoch: usize,
        profiler: &mut PassProfiler,
    ) -> Result<(), NglodError> {
        let spec = Self::spec(config, epoch);
        self.draw.record_with(gpu, enc, &spec, Some(profiler))?;
        self.slots[0] = None;
        Ok(())
    }

    /// Block `k` of the pool: drawn without its shuffle (the gather spreads it).
    fn block(config: &NglodTrainConfig, k: usize) -> SampleSpec {
        SampleSpec {
            shuffle: false,
            ..Self::spec(config, k)
        }
    }
}

/// What an epoch's first submission records on the GPU before its steps: the pool's new block
/// (its draw and slot), then the gather of the epoch's points from the blocks held.
#[derive(Clone, Copy, Debug)]
pub(super) struct GpuEpoch {
    pub(super) block: Option<(SampleSpec, u32)>,
    pub(super) gather: (SampleSpec, u32),
}

impl GpuEpoch {
    /// Records the block's draw and the gather into `enc`.
    pub(super) fn record(
        &self,
        gpu: &GpuContext,
        draw: &LabelledDraw,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), NglodError> {
        if let Some((spec, slot)) = &self.block {
            draw.record_block(gpu, enc, spec, *slot)?;
        }
        draw.record_gather(gpu, enc, &self.gather.0, self.gather.1)?;
        Ok(())
    }
}

impl NglodTrainer<'_> {
    /// [`NglodTrainer::train_with`] with [`SampleSource::Gpu`]: each epoch's first submission
    /// draws and labels the pool's new block on the GPU (when one is due) and gathers the
    /// epoch's points from the pool, then its steps run on them.
    pub(super) fn train_on_gpu_points(
        &mut self,
        mut on_epoch: impl FnMut(&EpochStats),
    ) -> Result<TrainReport, NglodError> {
        let start = Instant::now();
        let mut report = TrainReport::default();
        let levels = self.model.config().levels();
        let config = &self.config;
        let Some(source) = &mut self.gpu_points else {
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
            let epoch = source.epoch_draw(self.gpu, config, e)?;
            let data = EpochData::Gpu(&source.draw, epoch);
            let run = EpochSteps::run(
                &mut stepper,
                (e, lod, end_epoch),
                data,
                skip,
                &mut self.steps_done,
                should_stop,
            )?;
            source.placed(&epoch);
            let elapsed = start.elapsed().as_secs_f64();
            let plans = &mut report.length_plans;
            let least = first_epoch + config.epochs;
            if let Some(end) =
                run.planned_end(config, plans, least, e, elapsed, elapsed - epoch_began)
            {
                end_epoch = end;
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

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use super::*;
    use crate::ground_truth::{GpuSampler, SampleTable};
    use crate::{Nglod, NglodConfig, NglodTrainer};

    /// Each epoch gathers its points from exactly the blocks its schedule names (a pool of 2,
    /// refreshed every 2 epochs: blocks {0}, {0, 1}, {0, 1}, {1, 2}, {1, 2}, {2, 3}, ...),
    /// including while the pool fills and after a profile took slot 0.
    #[test]
    fn each_epoch_gathers_from_the_blocks_of_its_schedule() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let mesh = Mesh::icosphere(0.5, 1);
        let config = NglodTrainConfig {
            uniform_points: 40,
            near_points: 40,
            surface_points: 40,
            batch_size: 120,
            pool_blocks: 2,
            refresh_every: 2,
            sample_source: SampleSource::Gpu,
            ..Default::default()
        };
        let model = Nglod::new(NglodConfig::small()).unwrap();
        let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config.clone()).unwrap();
        let sampler = GpuSampler::new(gpu, &SampleTable::new(&mesh).unwrap()).unwrap();
        let key = |p: &[f32]| [p[0].to_bits(), p[1].to_bits(), p[2].to_bits()];
        let source = trainer.gpu_points.as_mut().unwrap();
        for (i, e) in [0, 1, 2, 3, 4, 5, 5, 6].into_iter().enumerate() {
            if i == 6 {
                // What a profile leaves: slot 0 (block 2) holds no block of the schedule.
                assert_eq!(source.slots[0], Some(2));
                source.slots[0] = None;
            }
            let epoch = source.epoch_draw(gpu, &config, e).unwrap();
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            epoch.record(gpu, &source.draw, &mut enc).unwrap();
            gpu.queue().submit([enc.finish()]);
            source.placed(&epoch);
            let mut want = HashSet::new();
            for k in config.pool().blocks_at(e) {
                let block = sampler.draw(gpu, &GpuPoints::block(&config, k)).unwrap();
                want.extend(block.iter().map(|p| key(&p.to_array())));
            }
            let got: Vec<f32> = gpu.read_back(&trainer.points).unwrap();
            let got: HashSet<_> = got.chunks(3).map(key).collect();
            assert_eq!(got.len(), 120, "epoch {e}: distinct points");
            assert!(
                got.is_subset(&want),
                "epoch {e}: a point of no scheduled block"
            );
        }
    }
}
