//! A training step's launches timed one by one ([`NglodTrainer::profile_step`]): where an
//! epoch's GPU time goes, for the benches (`NGLOD_BENCH_PROFILE`).

use super::NglodTrainer;
use crate::gpu::{PassProfiler, PassTime};
use crate::nglod::NglodError;

impl NglodTrainer<'_> {
    /// Runs one optimiser step on the first batch of the epoch's points, each launch in a pass
    /// of its own timed by `profiler`, and returns the launches' labels and GPU times in order:
    /// the rows' forward and backward (`train_rows` or `train_rows_sg`), `mlp_partial`,
    /// `mlp_reduce` and `adam`. With `draw` and [`super::SampleSource::Gpu`], the draw and
    /// labelling of a block of the pool (`draw`, the grouping's `bin_*`, `signed_distance`;
    /// once every `refresh_every` epochs in training) and an epoch's gather (`gather`) come
    /// first.
    ///
    /// It is a real step (the model and the optimiser move, and it counts in the steps done)
    /// on whatever the epoch buffers hold, outside any epoch: train an epoch first. A pass per launch adds a little to each; an epoch's GPU time is
    /// [`super::EpochStats::gpu_seconds`].
    pub fn profile_step(
        &mut self,
        profiler: &mut PassProfiler,
        draw: bool,
    ) -> Result<Vec<PassTime>, NglodError> {
        let gpu = self.gpu;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        if let (true, Some(source)) = (draw, &mut self.gpu_points) {
            source.profile_draw(gpu, &mut enc, &self.config, self.epochs_done, profiler)?;
        }
        let n = self.config.points_per_epoch() as u32;
        let batch = self.config.batch_size.min(n);
        self.kernels
            .record(gpu, &mut enc, (0, batch), Some(&mut *profiler))?;
        self.adam.record_step_in(
            gpu,
            &mut profiler.begin_pass(&mut enc, "adam"),
            1.0 / batch as f32,
        );
        // Its loss is no epoch's: leave the sum the next loss read takes from empty.
        enc.clear_buffer(&self.kernels.stats, 0, None);
        profiler.resolve(&mut enc);
        gpu.queue().submit([enc.finish()]);
        // Counted as Adam counts it, so that a checkpoint's step count stays the trainer's.
        self.steps_done += 1;
        Ok(profiler.read(gpu)?)
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use crate::{GpuContext, Nglod, NglodConfig, NglodTrainConfig, NglodTrainer};

    /// The profiled step's loss is no epoch's: the sum the next loss read takes is left empty.
    #[test]
    fn a_profiled_step_leaves_no_loss_behind() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let Some(mut profiler) = crate::gpu::PassProfiler::new(gpu, 8) else {
            return;
        };
        // A tetrahedron, its faces counter-clockwise seen from outside.
        let mesh = sdf_geom::Mesh {
            vertices: vec![
                Vec3::new(0.5, 0.5, 0.5),
                Vec3::new(-0.5, -0.5, 0.5),
                Vec3::new(-0.5, 0.5, -0.5),
                Vec3::new(0.5, -0.5, -0.5),
            ],
            triangles: vec![[0, 1, 3], [0, 2, 1], [0, 3, 2], [1, 2, 3]],
        };
        let config = NglodTrainConfig {
            epochs: 1,
            uniform_points: 500,
            near_points: 500,
            surface_points: 500,
            batch_size: 500,
            ..Default::default()
        };
        let model = Nglod::new(NglodConfig::small()).unwrap();
        let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
        trainer.train().unwrap();
        trainer.profile_step(&mut profiler, false).unwrap();
        let left: Vec<f32> = gpu.read_back(&trainer.kernels.stats).unwrap();
        assert_eq!(left, [0.0]);
    }
}
