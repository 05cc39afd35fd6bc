//! A training step's launches timed one by one ([`NglodTrainer::profile_step`]): where an
//! epoch's GPU time goes, for the benches (`NGLOD_BENCH_PROFILE`).

use super::NglodTrainer;
use super::gpu_points::GpuPoints;
use crate::gpu::{PassProfiler, PassTime};
use crate::nglod::NglodError;

impl NglodTrainer<'_> {
    /// Runs one optimiser step on the first batch of the epoch's points, each launch in a pass
    /// of its own timed by `profiler`, and returns the launches' labels and GPU times in order:
    /// the rows' forward and backward (`train_rows` or `train_rows_sg`), `mlp_partial`,
    /// `mlp_reduce` and `adam`. With `draw` and [`super::SampleSource::Gpu`], the draw and
    /// labelling of the next epoch's points (`draw`, `signed_distance`, `gather`) come first.
    ///
    /// It is a real step (the model and the optimiser move) on whatever the epoch buffers hold:
    /// train an epoch first. A pass per launch adds a little to each; an epoch's GPU time is
    /// [`super::EpochStats::gpu_seconds`].
    pub fn profile_step(
        &mut self,
        profiler: &mut PassProfiler,
        draw: bool,
    ) -> Result<Vec<PassTime>, NglodError> {
        let gpu = self.gpu;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        if let (true, Some(source)) = (draw, &self.gpu_points) {
            let spec = GpuPoints::spec(&self.config, self.epochs_done);
            source
                .draw
                .record_with(gpu, &mut enc, &spec, Some(&mut *profiler))?;
        }
        let n = self.config.points_per_epoch() as u32;
        let batch = self.config.batch_size.min(n);
        self.kernels
            .record_profiled(gpu, &mut enc, profiler, 0, batch)?;
        self.adam.record_step_in(
            gpu,
            &mut profiler.begin_pass(&mut enc, "adam"),
            1.0 / batch as f32,
        );
        profiler.resolve(&mut enc);
        gpu.queue().submit([enc.finish()]);
        Ok(profiler.read(gpu)?)
    }
}
