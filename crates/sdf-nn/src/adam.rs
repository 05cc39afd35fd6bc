//! The Adam optimiser on the GPU (`shaders/adam.wgsl`), shared by every model, and its CPU
//! reference.
//!
//! Models keep all their parameters in one flat `f32` buffer and their gradients in another of
//! the same length, so one dispatch updates everything. The kernel zeroes the gradient as it
//! consumes it, ready for the next step's accumulation.

use crate::gpu::{GpuContext, GpuError, UniformStager, entry};
use crate::shaders;

/// Adam hyperparameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Learning rate.
    pub lr: f32,
    /// First-moment decay β1.
    pub beta1: f32,
    /// Second-moment decay β2.
    pub beta2: f32,
    /// ε added to the denominator.
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            lr: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct AdamUniforms {
    step_size: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    inv_sqrt_bc2: f32,
    grad_scale: f32,
    len: u32,
    lazy_len: u32,
}

/// Bytes of an Adam step's uniforms, as a stager stages them.
pub(crate) const ADAM_UNIFORM_BYTES: u64 = std::mem::size_of::<AdamUniforms>() as u64;

const WORKGROUP: u32 = 256;

impl AdamConfig {
    /// Errors unless `lr` is finite and positive: the one check shared by the trainers, their
    /// resume paths and checkpoints read from disk.
    pub fn check_lr(lr: f32) -> Result<(), String> {
        if lr.is_finite() && lr > 0.0 {
            Ok(())
        } else {
            Err(format!(
                "the learning rate must be finite and positive, not {lr}"
            ))
        }
    }

    /// Errors unless every setting can run: the learning rate ([`AdamConfig::check_lr`]), both
    /// betas in `[0, 1)` (at 1 the bias correction divides by zero and every update is NaN)
    /// and `eps` finite and positive.
    pub fn check(&self) -> Result<(), String> {
        Self::check_lr(self.lr)?;
        for (name, beta) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&beta) {
                return Err(format!("Adam's {name} must lie in [0, 1), not {beta}"));
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(format!(
                "Adam's eps must be finite and positive, not {}",
                self.eps
            ));
        }
        Ok(())
    }
}

impl AdamState {
    /// Errors unless the state can continue a run: moments of one length, finite, and second
    /// moments non-negative (Adam divides by their square root).
    pub fn validate(&self) -> Result<(), String> {
        if self.m.len() != self.v.len() {
            return Err(format!(
                "{} first moments but {} second moments",
                self.m.len(),
                self.v.len()
            ));
        }
        if let Some(i) = self.m.iter().position(|x| !x.is_finite()) {
            return Err(format!("first moment {i} is {}", self.m[i]));
        }
        if let Some(i) = self.v.iter().position(|x| !(x.is_finite() && *x >= 0.0)) {
            return Err(format!(
                "second moment {i} is {}; it must be finite and non-negative",
                self.v[i]
            ));
        }
        Ok(())
    }
}

/// Adam's moments and step counter on the host, as checkpoints store them.
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState {
    /// First moments.
    pub m: Vec<f32>,
    /// Second moments.
    pub v: Vec<f32>,
    /// Steps taken.
    pub step: u32,
}

/// Adam state (moments and step counter) for one flat parameter buffer.
#[derive(Debug)]
pub struct Adam {
    /// Hyperparameters; the learning rate may be changed between steps (e.g. on plateaus).
    pub config: AdamConfig,
    len: u32,
    /// Parameters below this index skip a zero gradient ([`Adam::set_lazy_prefix`]).
    lazy_len: u32,
    step: u32,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    pipeline: wgpu::ComputePipeline,
}

impl Adam {
    /// Adam over `len` f32 parameters in `params` with gradients in `grads` (both at least
    /// `len` elements).
    pub fn new(
        gpu: &GpuContext,
        params: &wgpu::Buffer,
        grads: &wgpu::Buffer,
        len: u32,
        config: AdamConfig,
    ) -> Result<Self, GpuError> {
        let bytes = u64::from(len) * 4;
        for (name, b) in [("params", params), ("grads", grads)] {
            if b.size() < bytes {
                return Err(GpuError::BufferTooLarge {
                    label: format!("adam {name}"),
                    requested: bytes,
                    limit_name: "size of the buffer given to Adam",
                    limit: b.size(),
                });
            }
        }
        let m = gpu.storage_zeroed("adam m", bytes)?;
        let v = gpu.storage_zeroed("adam v", bytes)?;
        let uniforms = gpu.uniform("adam uniforms", &AdamUniforms::zeroed_for(len));
        let pipeline = gpu.pipeline(&shaders::ADAM, "adam_step", &[])?;
        let bind_group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("adam"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                entry(0, &uniforms),
                entry(1, params),
                entry(2, grads),
                entry(3, &m),
                entry(4, &v),
            ],
        });
        Ok(Adam {
            config,
            len,
            lazy_len: 0,
            step: 0,
            m,
            v,
            uniforms,
            bind_group,
            pipeline,
        })
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> u32 {
        self.step
    }

    /// Restores the step counter (when resuming from a checkpoint together with the moments).
    pub fn set_step_count(&mut self, step: u32) {
        self.step = step;
    }

    /// Reads the moments and step counter back, for checkpoints.
    pub fn export_state(&self, gpu: &GpuContext) -> Result<AdamState, GpuError> {
        let n = u64::from(self.len);
        Ok(AdamState {
            m: gpu.read_back_range(&self.m, 0, n)?,
            v: gpu.read_back_range(&self.v, 0, n)?,
            step: self.step,
        })
    }

    /// Restores moments and step counter saved by [`Adam::export_state`].
    pub fn import_state(&mut self, gpu: &GpuContext, state: &AdamState) -> Result<(), GpuError> {
        for (name, data) in [("m", &state.m), ("v", &state.v)] {
            if data.len() != self.len as usize {
                return Err(GpuError::BufferTooLarge {
                    label: format!("adam {name} from checkpoint"),
                    requested: data.len() as u64 * 4,
                    limit_name: "optimiser state size",
                    limit: u64::from(self.len) * 4,
                });
            }
        }
        gpu.write(&self.m, &state.m)?;
        gpu.write(&self.v, &state.v)?;
        self.step = state.step;
        Ok(())
    }

    /// Makes the first `n` parameters lazy (none by default): a step leaves one whose gradient
    /// is exactly zero unchanged, moments included, rather than decaying its moments and moving
    /// it by their remainder. Made for a model's grid or hash-table entries, of which a batch
    /// touches a few (instant-ngp's optimiser treats its tables so); the bias correction stays
    /// the global step's (TensorFlow's lazy Adam). [`AdamCpu::lazy_len`] is its reference.
    pub fn set_lazy_prefix(&mut self, n: u32) {
        self.lazy_len = n.min(self.len);
    }

    /// First- and second-moment buffers, for checkpoints.
    pub fn moments(&self) -> (&wgpu::Buffer, &wgpu::Buffer) {
        (&self.m, &self.v)
    }

    /// Records one Adam step into `encoder`. `grad_scale` multiplies the gradients first
    /// (e.g. `1/batch` when the backward kernels accumulate sums).
    ///
    /// The uniforms are written through the queue, which applies them before the next
    /// submission: submit the encoder before recording another step.
    pub fn record_step(
        &mut self,
        gpu: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grad_scale: f32,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("adam"),
            timestamp_writes: None,
        });
        self.record_step_in(gpu, &mut pass, grad_scale);
    }

    /// [`Adam::record_step`] into a compute pass of the caller's (one that a
    /// [`crate::gpu::PassProfiler`] times, say).
    pub fn record_step_in(
        &mut self,
        gpu: &GpuContext,
        pass: &mut wgpu::ComputePass<'_>,
        grad_scale: f32,
    ) {
        self.step = self.step.saturating_add(1);
        let u = self.uniforms_for_step(grad_scale);
        gpu.queue()
            .write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        self.dispatch(gpu, pass);
    }

    /// [`Adam::record_step`] with its uniforms staged in `stager` (flush it before the
    /// submission), so that several steps can share one submission.
    pub(crate) fn record_step_staged(
        &mut self,
        gpu: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        stager: &mut UniformStager,
        grad_scale: f32,
    ) -> Result<(), GpuError> {
        self.step = self.step.saturating_add(1);
        stager.stage(encoder, &self.uniforms, &self.uniforms_for_step(grad_scale))?;
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("adam"),
            timestamp_writes: None,
        });
        self.dispatch(gpu, &mut pass);
        Ok(())
    }

    /// The step's dispatch, its uniforms in place.
    fn dispatch(&self, gpu: &GpuContext, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        let (x, y) = gpu.dispatch_size(self.len.div_ceil(WORKGROUP));
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records one step and submits it (does not wait).
    pub fn step(&mut self, gpu: &GpuContext, grad_scale: f32) {
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        self.record_step(gpu, &mut enc, grad_scale);
        gpu.queue().submit([enc.finish()]);
    }

    fn uniforms_for_step(&self, grad_scale: f32) -> AdamUniforms {
        let c = &self.config;
        let t = f64::from(self.step);
        let bc1 = 1.0 - f64::from(c.beta1).powf(t);
        let bc2 = 1.0 - f64::from(c.beta2).powf(t);
        AdamUniforms {
            step_size: (f64::from(c.lr) / bc1) as f32,
            beta1: c.beta1,
            beta2: c.beta2,
            eps: c.eps,
            inv_sqrt_bc2: (1.0 / bc2.sqrt()) as f32,
            grad_scale,
            len: self.len,
            lazy_len: self.lazy_len,
        }
    }
}

impl AdamUniforms {
    fn zeroed_for(len: u32) -> Self {
        AdamUniforms {
            len,
            ..bytemuck::Zeroable::zeroed()
        }
    }
}

/// CPU reference of Adam in f64: the same update as the kernel, for tests and for CPU training.
#[derive(Clone, Debug)]
pub struct AdamCpu {
    /// Hyperparameters.
    pub config: AdamConfig,
    /// First moments.
    pub m: Vec<f64>,
    /// Second moments.
    pub v: Vec<f64>,
    /// Steps taken.
    pub step: u32,
    /// Parameters below this index skip a zero gradient ([`Adam::set_lazy_prefix`]; 0).
    pub lazy_len: usize,
}

impl AdamCpu {
    /// Zero state for `len` parameters.
    pub fn new(len: usize, config: AdamConfig) -> Self {
        AdamCpu {
            config,
            m: vec![0.0; len],
            v: vec![0.0; len],
            step: 0,
            lazy_len: 0,
        }
    }

    /// One step: updates `params` in place from `grads` scaled by `grad_scale`.
    pub fn step(&mut self, params: &mut [f64], grads: &[f64], grad_scale: f64) {
        self.step = self.step.saturating_add(1);
        let c = &self.config;
        let (b1, b2) = (f64::from(c.beta1), f64::from(c.beta2));
        let t = f64::from(self.step);
        let step_size = f64::from(c.lr) / (1.0 - b1.powf(t));
        let inv_sqrt_bc2 = 1.0 / (1.0 - b2.powf(t)).sqrt();
        for (i, (((p, &g), m), v)) in params
            .iter_mut()
            .zip(grads)
            .zip(&mut self.m)
            .zip(&mut self.v)
            .enumerate()
        {
            if i < self.lazy_len && g == 0.0 {
                continue;
            }
            let g = g * grad_scale;
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            *p -= step_size * *m / (v.sqrt() * inv_sqrt_bc2 + f64::from(c.eps));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::AdamConfig;

    /// Settings that would make every update NaN or infinite are refused by name.
    #[test]
    fn unusable_settings_are_refused() {
        let good = AdamConfig::default();
        assert!(good.check().is_ok());
        for (bad, says) in [
            (AdamConfig { beta1: 1.0, ..good }, "beta1"),
            (AdamConfig { beta2: 1.0, ..good }, "beta2"),
            (
                AdamConfig {
                    beta2: -0.1,
                    ..good
                },
                "beta2",
            ),
            (
                AdamConfig {
                    beta1: f32::NAN,
                    ..good
                },
                "beta1",
            ),
            (AdamConfig { eps: 0.0, ..good }, "eps"),
            (
                AdamConfig {
                    eps: f32::INFINITY,
                    ..good
                },
                "eps",
            ),
            (AdamConfig { lr: 0.0, ..good }, "learning rate"),
        ] {
            let e = bad.check().unwrap_err();
            assert!(e.contains(says), "{bad:?}: {e}");
        }
    }

    /// The optimiser's uniforms have the layout `adam.wgsl` reads.
    #[test]
    fn adam_uniforms_mirror_the_shader() {
        crate::shaders::assert_mirrors!(
            super::AdamUniforms,
            crate::shaders::ADAM,
            "AdamUniforms",
            [
                step_size,
                beta1,
                beta2,
                eps,
                inv_sqrt_bc2,
                grad_scale,
                len,
                lazy_len
            ]
        );
    }
}
