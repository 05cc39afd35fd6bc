//! The training step's launches: the SIREN loss and its gradient with respect to every
//! parameter, recorded for a batch of a fixed size. Two builders, [`reverse_over_reverse`] (one
//! row per point) and [`tangents`] (four), chosen by [`TrainStep`]; `passes.rs`'s `TrainPasses`
//! holds the one that runs. This module has what both builders share: the view of the network
//! they get (`StepNet`), what they return (`StepLaunches`) and the weight gradients' reduction.
//!
//! The builders get the network as a borrowed view (`siren/net.rs`) and never see
//! [`super::SirenGpu`]: `gpu.rs` depends on this module, not the reverse.

use super::LayerLayout;
use super::kernels::Launch;
use super::net::NetView;
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;

pub(crate) mod passes;
pub mod reverse_over_reverse;
pub mod tangents;

/// How a training step computes the loss's dependence on ∇ₓΦ.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TrainStep {
    /// [`TrainStep::ReverseOverReverse`] wherever it runs (the tiled kernels, GPUs' default,
    /// and the row-blocked kernels covering every hidden layer, CPU adapters' default, where
    /// it measured 1.6× faster on lavapipe for the `small` preset: docs/benchmarks);
    /// [`TrainStep::Tangents`] otherwise (the plain GEMM family, or row-blocked kernels that
    /// leave a layer to the GEMM).
    #[default]
    Auto,
    /// Forward-mode tangents: four rows per point (the point and e_x, e_y, e_z) in every
    /// product, 12n row-products per hidden layer.
    Tangents,
    /// Reverse over reverse (see [`reverse_over_reverse`]): 6n row-products per hidden
    /// layer. Runs on the tiled kernels, and on the row-blocked kernels when they cover every
    /// hidden layer; with other kernels the step falls back to [`TrainStep::Tangents`].
    ReverseOverReverse,
}

/// What a step builder needs of the network: its layers on the GPU, and the choices the
/// network's options resolved to on this adapter.
#[derive(Clone, Copy)]
pub(crate) struct StepNet<'a> {
    /// The parameters, gradients and kernels.
    pub(crate) net: NetView<'a>,
    /// Whether the step runs reverse over reverse (else it carries tangents).
    pub(crate) reverse_over_reverse: bool,
    /// Whether the reverse-over-reverse step takes its GPU layout (see
    /// [`super::SirenGpuOptions::step_layout`]).
    pub(crate) gpu_layout: bool,
}

/// The launches of one training step's loss and gradient (from [`reverse_over_reverse::build`]
/// or [`tangents::build`]), the buffers they use, and the loss partials' count.
pub(crate) struct StepLaunches {
    pub(crate) launches: Vec<Launch>,
    pub(crate) keep: Vec<wgpu::Buffer>,
    pub(crate) loss_groups: u32,
}

/// `reduce_wgrad`'s uniforms (`siren_train.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ReduceUniforms {
    m: u32,
    n: u32,
    splits: u32,
    w_off: u32,
    b_off: u32,
    pbias_off: u32,
    _pad0: u32,
    _pad1: u32,
}

/// The sum of a weight gradient's split partials into the gradient buffer, as both steps
/// record it after each layer's weight-gradient product.
pub(crate) struct WgradReduce<'a> {
    /// An invocation per output.
    per_output: wgpu::ComputePipeline,
    /// A workgroup per output, where [`WgradReduce::push`] is told to use it.
    by_output: Option<wgpu::ComputePipeline>,
    partial: &'a wgpu::Buffer,
    grads: &'a wgpu::Buffer,
    /// `"siren"` or `"siren ror"`: the start of the launches' and buffers' labels.
    label: &'static str,
}

impl<'a> WgradReduce<'a> {
    /// The reduction from `partial` into `grads` (`by_output`: also compile the workgroup per
    /// output kernel).
    pub(crate) fn new(
        gpu: &GpuContext,
        label: &'static str,
        partial: &'a wgpu::Buffer,
        grads: &'a wgpu::Buffer,
        by_output: bool,
    ) -> Result<Self, GpuError> {
        let pipeline = |name| gpu.pipeline(&shaders::SIREN_TRAIN, name, &[]);
        Ok(WgradReduce {
            per_output: pipeline("reduce_wgrad")?,
            by_output: by_output
                .then(|| pipeline("reduce_wgrad_by_output"))
                .transpose()?,
            partial,
            grads,
            label,
        })
    }

    /// Records the sum of `lay`'s `splits` partials (the bias's from `pbias_off` on) into
    /// `launches`, keeping its uniforms in `keep`; with `by_output` (and the kernel compiled) a
    /// workgroup per output.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn push(
        &self,
        gpu: &GpuContext,
        launches: &mut Vec<Launch>,
        keep: &mut Vec<wgpu::Buffer>,
        lay: &LayerLayout,
        splits: u32,
        pbias_off: u32,
        by_output: bool,
    ) {
        let (m, k) = (lay.fan_out as u32, lay.fan_in as u32);
        let rub = gpu.uniform(
            &format!("{} reduce", self.label),
            &ReduceUniforms {
                m,
                n: k,
                splits,
                w_off: lay.weight as u32,
                b_off: lay.bias as u32,
                pbias_off,
                ..Default::default()
            },
        );
        let outputs = m * k + m;
        let entries = [entry(5, &rub), entry(6, self.partial), entry(7, self.grads)];
        launches.push(match self.by_output.as_ref().filter(|_| by_output) {
            Some(pipeline) => {
                let (x, y) = gpu.dispatch_size(outputs);
                let label = format!("{} reduce wgrad by output", self.label);
                Launch::new(gpu, pipeline, &label, &entries, (x, y, 1))
            }
            None => {
                let label = format!("{} reduce wgrad", self.label);
                Launch::flat(gpu, &self.per_output, &label, &entries, outputs)
            }
        });
        keep.push(rub);
    }
}

#[cfg(test)]
mod uniform_layout {
    /// ReduceUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::ReduceUniforms,
            crate::shaders::SIREN_TRAIN,
            "Reduce",
            [m, n, splits, w_off, b_off, pbias_off]
        );
    }
}
