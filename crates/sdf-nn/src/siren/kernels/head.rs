//! The output layer's kernels (`siren_head.wgsl`), which every family shares: the head of an
//! inference, and the head, loss and first backward step of the tangent training step.

use crate::gpu::{GpuContext, GpuError};
use crate::shaders;

/// `siren_head.wgsl`'s uniforms.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct HeadUniforms {
    pub(crate) mode: u32,
    pub(crate) n_points: u32,
    pub(crate) n_surface: u32,
    pub(crate) width: u32,
    pub(crate) w_off: u32,
    pub(crate) b_off: u32,
    pub(crate) _pad0: u32,
    pub(crate) _pad1: u32,
    pub(crate) w_surface: f32,
    pub(crate) w_off_surface: f32,
    pub(crate) w_normal: f32,
    pub(crate) w_eikonal: f32,
    pub(crate) alpha: f32,
    pub(crate) inv_n: f32,
    pub(crate) omega: f32,
    pub(crate) w_sign: f32,
}

/// The head's pipelines.
#[derive(Debug, Clone)]
pub(crate) struct HeadKernels {
    /// The output layer and the loss (training).
    pub(crate) forward: wgpu::ComputePipeline,
    /// `forward` without the loss reduction, for inference.
    pub(crate) eval: wgpu::ComputePipeline,
    /// The loss's gradient through the output layer (training).
    pub(crate) backward: wgpu::ComputePipeline,
}

impl HeadKernels {
    /// Compiles (or fetches from the context's cache) the pipelines.
    pub(crate) fn new(gpu: &GpuContext) -> Result<Self, GpuError> {
        Ok(HeadKernels {
            forward: gpu.pipeline(&shaders::SIREN_HEAD, "head_forward", &[])?,
            eval: gpu.pipeline(&shaders::SIREN_HEAD, "head_eval", &[])?,
            backward: gpu.pipeline(&shaders::SIREN_HEAD, "head_backward", &[])?,
        })
    }
}

#[cfg(test)]
mod uniform_layout {
    /// HeadUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::HeadUniforms,
            crate::shaders::SIREN_HEAD,
            "Head",
            [
                mode,
                n_points,
                n_surface,
                width,
                w_off,
                b_off,
                w_surface,
                w_off_surface,
                w_normal,
                w_eikonal,
                alpha,
                inv_n,
                omega,
                w_sign
            ]
        );
    }
}
