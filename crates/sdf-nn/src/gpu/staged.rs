//! Uniform values for several dispatches of one submission: a queue write of a uniform buffer
//! takes effect before the submission, so every dispatch in it would see the last value
//! written. A [`UniformStager`] instead collects each dispatch's value in a staging buffer and
//! records a copy into the uniform buffer just before the dispatch; one queue write of the
//! staging buffer per submission ([`UniformStager::flush`]) carries them all.

use bytemuck::Pod;

use super::{GpuContext, GpuError};

/// A staging buffer of uniform values and the bytes staged since the last flush.
#[derive(Debug)]
pub(crate) struct UniformStager {
    buffer: wgpu::Buffer,
    data: Vec<u8>,
}

impl UniformStager {
    /// A stager for at most `capacity` bytes per submission.
    pub(crate) fn new(gpu: &GpuContext, label: &str, capacity: u64) -> Self {
        let buffer = gpu.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: capacity
                .max(4)
                .next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
            usage: wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        UniformStager {
            buffer,
            data: Vec::new(),
        }
    }

    /// Stages `value` and records its copy to the start of `target` into `enc`: the passes
    /// recorded after it (until the next copy into `target`) read `value`.
    ///
    /// # Errors
    /// [`GpuError::BufferTooLarge`] when the submission's values exceed the capacity.
    pub(crate) fn stage<T: Pod>(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        target: &wgpu::Buffer,
        value: &T,
    ) -> Result<(), GpuError> {
        let bytes = bytemuck::bytes_of(value);
        let offset = self.data.len() as u64;
        let size = (bytes.len() as u64).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
        if offset + size > self.buffer.size() || size > target.size() {
            return Err(GpuError::BufferTooLarge {
                label: "staged uniforms".into(),
                requested: offset + size,
                limit_name: "the stager's capacity (or the uniform's size)",
                limit: self.buffer.size().min(target.size()),
            });
        }
        self.data.extend_from_slice(bytes);
        self.data.resize((offset + size) as usize, 0);
        enc.copy_buffer_to_buffer(&self.buffer, offset, target, 0, size);
        Ok(())
    }

    /// Writes the staged values through the queue (before the submission that holds their
    /// copies) and starts afresh.
    pub(crate) fn flush(&mut self, gpu: &GpuContext) {
        if !self.data.is_empty() {
            gpu.queue().write_buffer(&self.buffer, 0, &self.data);
            self.data.clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::UniformStager;
    use crate::{Adam, AdamConfig, GpuContext};

    /// Three Adam steps in one submission, each with its own staged gradients and uniforms
    /// (step count, bias corrections, learning rate), give the parameters of three steps in
    /// three submissions, bit for bit; staging the last values for every step would not.
    #[test]
    fn staged_steps_in_one_submission_match_steps_in_their_own() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let start: Vec<f32> = (0..8).map(|i| i as f32 * 0.25 - 1.0).collect();
        let grads: Vec<[f32; 8]> = (0..3)
            .map(|k| std::array::from_fn(|i| ((i * 7 + k * 3) % 5) as f32 - 2.0))
            .collect();
        let lrs = [1e-2, 5e-3, 2e-2];
        let run = |staged: bool| {
            let params = gpu.storage_from_slice("params", &start).unwrap();
            let g = gpu.storage_zeroed("grads", 32).unwrap();
            let mut adam = Adam::new(gpu, &params, &g, 8, AdamConfig::default()).unwrap();
            let mut stager = UniformStager::new(gpu, "test stager", 1024);
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            for (grad, lr) in grads.iter().zip(lrs) {
                adam.config.lr = lr;
                if staged {
                    stager.stage(&mut enc, &g, grad).unwrap();
                    adam.record_step_staged(gpu, &mut enc, &mut stager, 0.5)
                        .unwrap();
                } else {
                    gpu.write(&g, grad).unwrap();
                    adam.step(gpu, 0.5);
                }
            }
            stager.flush(gpu);
            gpu.queue().submit([enc.finish()]);
            gpu.read_back::<f32>(&params).unwrap()
        };
        let (separate, together) = (run(false), run(true));
        assert_ne!(separate, start);
        assert_eq!(separate, together);
    }
}
