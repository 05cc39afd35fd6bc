//! The strided GEMM of `siren_gemm.wgsl` and its elementwise sine kernels: the family that runs
//! every product where neither the row-blocked nor the tiled kernels do
//! ([`super::LayerKernels::Gemm`], and the layers the row-blocked kernels leave). Its shapes are
//! in [`super::products`].

use super::Launch;
use super::products::{GemmUniforms, splits_for};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;

/// The widest hidden layer the GEMM (`siren_gemm.wgsl`) evaluates correctly on Debian 12's
/// lavapipe (Mesa 22.3, LLVM 15): from a fan-in of 500 on (vec4 loads; 497–499 take scalar loads
/// and pass) its results are wrong by 1e-2 and more there, with a threshold that moves with its K
/// chunk (KC = 128 moved it between 1500 and 2000, KC = 64 between 1024 and 1500). The same
/// shader is right at every width to 2048 on Mesa 26.1 (LLVM 19), so it is the older driver's
/// compiler; the tiled kernels are right on both. See [`gemm_trusted_wide`].
pub(crate) const GEMM_CPU_MAX_FAN_IN: usize = 496;

/// Whether the GEMM may run layers wider than [`GEMM_CPU_MAX_FAN_IN`] on `gpu`: on a GPU, and on
/// llvmpipe built with LLVM 19 or newer (measured right); not on llvmpipe with an older or
/// unknown LLVM (LLVM 15 measured wrong, 16–18 not measured).
pub(crate) fn gemm_trusted_wide(gpu: &GpuContext) -> bool {
    if !gpu.is_cpu() {
        return true;
    }
    let info = &gpu.adapter_info().driver_info;
    let llvm_major = info
        .split("LLVM ")
        .nth(1)
        .and_then(|v| v.split('.').next())
        .and_then(|m| m.parse::<u32>().ok());
    llvm_major.is_some_and(|m| m >= 19)
}

/// Rows per GEMM workgroup (see `siren_gemm.wgsl`).
const GEMM_ROWS: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ElementwiseUniforms {
    n_points: u32,
    width: u32,
    bias_off: u32,
    _pad0: u32,
    omega: f32,
    _pad1: [f32; 3],
}

/// The elementwise kernels' view of a hidden layer: its width, bias offset and ω0.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SineLayer {
    /// Outputs of the layer.
    pub(crate) width: u32,
    /// Offset of its bias in the flat parameters.
    pub(crate) bias: u32,
    /// ω0.
    pub(crate) omega: f32,
}

/// The GEMM's and the sine kernels' pipelines.
#[derive(Debug, Clone)]
pub(crate) struct GemmKernels {
    gemm: wgpu::ComputePipeline,
    sine_forward: wgpu::ComputePipeline,
    sine_backward: wgpu::ComputePipeline,
}

impl GemmKernels {
    /// Compiles (or fetches from the context's cache) the pipelines.
    pub(crate) fn new(gpu: &GpuContext) -> Result<Self, GpuError> {
        Ok(GemmKernels {
            gemm: gpu.pipeline(&shaders::SIREN_GEMM, "gemm", &[])?,
            sine_forward: gpu.pipeline(&shaders::SIREN_GEMM, "sine_forward", &[])?,
            sine_backward: gpu.pipeline(&shaders::SIREN_GEMM, "sine_backward", &[])?,
        })
    }

    /// The product `u` of `a` and `b` (the parameters bound beside them) into `out`.
    pub(crate) fn launch(
        &self,
        gpu: &GpuContext,
        u: &GemmUniforms,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        params: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Launch {
        let u = &u.with_load_styles();
        let ub = gpu.uniform("siren gemm uniforms", u);
        let z = if u.mode == 2 { splits_for(u.k) } else { 1 };
        let (x, y) = gpu.dispatch_size(u.m.div_ceil(GEMM_ROWS));
        Launch::new(
            gpu,
            &self.gemm,
            "siren gemm",
            &[
                entry(0, &ub),
                entry(1, a),
                entry(2, b),
                entry(3, params),
                entry(4, out),
                entry(5, a),
                entry(6, b),
            ],
            (x, y, z),
        )
    }

    fn elementwise_uniforms(gpu: &GpuContext, layer: SineLayer, n: u32) -> wgpu::Buffer {
        gpu.uniform(
            "siren elementwise uniforms",
            &ElementwiseUniforms {
                n_points: n,
                width: layer.width,
                bias_off: layer.bias,
                omega: layer.omega,
                ..Default::default()
            },
        )
    }

    /// Bias, sine and tangents of `layer` over `n` points: `z` (pre-activations) into `act`.
    pub(crate) fn sine_forward(
        &self,
        gpu: &GpuContext,
        layer: SineLayer,
        n: u32,
        params: &wgpu::Buffer,
        z: &wgpu::Buffer,
        act: &wgpu::Buffer,
    ) -> Launch {
        let u = Self::elementwise_uniforms(gpu, layer, n);
        Launch::flat(
            gpu,
            &self.sine_forward,
            "siren sine forward",
            &[
                entry(10, &u),
                entry(11, params),
                entry(12, z),
                entry(13, act),
            ],
            n * layer.width,
        )
    }

    /// The sine's derivative of `layer` over `n` points applied to `grad` in place.
    pub(crate) fn sine_backward(
        &self,
        gpu: &GpuContext,
        layer: SineLayer,
        n: u32,
        grad: &wgpu::Buffer,
        z: &wgpu::Buffer,
    ) -> Launch {
        let u = Self::elementwise_uniforms(gpu, layer, n);
        Launch::flat(
            gpu,
            &self.sine_backward,
            "siren sine backward",
            &[entry(10, &u), entry(14, grad), entry(15, z)],
            n * layer.width,
        )
    }
}

#[cfg(test)]
mod uniform_layout {
    /// ElementwiseUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::ElementwiseUniforms,
            crate::shaders::SIREN_GEMM,
            "Elementwise",
            [n_points, width, bias_off, omega]
        );
    }
}
