//! A borrowed view of a SIREN on the GPU: its parameters and the kernels that run its layers.
//! The code that records launches (inference in [`super::eval`], the training steps in
//! [`super::step`]) takes this view rather than [`super::SirenGpu`], so that it never depends on
//! the type that calls it.

use super::kernels::Launch;
use super::kernels::gemm::{GemmKernels, SineLayer};
use super::kernels::head::HeadKernels;
use super::kernels::products::gemm_forward;
use super::kernels::row_blocked::{Epilogue, RowBlockedPlan};
use super::kernels::tiled::{TiledEpilogue, TiledKernels};
use super::{LayerLayout, SirenConfig};
use crate::gpu::{GpuContext, GpuError};

/// A network's parameters, gradients and kernels on the GPU (see the module docs).
#[derive(Clone, Copy)]
pub(crate) struct NetView<'a> {
    /// The architecture.
    pub(crate) config: SirenConfig,
    /// The layers' parameter layout.
    pub(crate) layers: &'a [LayerLayout],
    /// The flat parameters.
    pub(crate) params: &'a wgpu::Buffer,
    /// The flat gradients, same layout.
    pub(crate) grads: &'a wgpu::Buffer,
    /// The strided GEMM and the sine kernels.
    pub(crate) gemm: &'a GemmKernels,
    /// The output layer's kernels.
    pub(crate) head: &'a HeadKernels,
    /// The row-blocked kernels, for the hidden layers they cover.
    pub(crate) dense: Option<&'a RowBlockedPlan>,
    /// The tiled kernels, when they run every product.
    pub(crate) tiled: Option<&'a TiledKernels>,
}

impl<'a> NetView<'a> {
    /// The row-blocked kernels of hidden layer `l`, if they cover it.
    pub(crate) fn dense_for(&self, l: usize) -> Option<&'a RowBlockedPlan> {
        self.dense.filter(|d| d.covers(l))
    }

    /// The row-blocked kernels, when they cover every hidden layer (what the
    /// reverse-over-reverse step needs of them).
    pub(crate) fn dense_ror_plan(&self) -> Option<&'a RowBlockedPlan> {
        let hidden = self.config.hidden_layers;
        self.dense.filter(|d| (0..hidden).all(|l| d.covers(l)))
    }

    /// Hidden layer `l` as the elementwise sine kernels see it.
    pub(crate) fn sine_layer(&self, l: usize) -> SineLayer {
        SineLayer {
            width: self.config.width as u32,
            bias: self.layers[l].bias as u32,
            omega: self.config.omega0,
        }
    }

    /// The launches of hidden layer `l`'s forward pass over `n` points from `src` into `act`,
    /// on whichever family runs the layer. With `tangents` (four rows per point) the
    /// pre-activations go into `z` and the sine with its tangents into `act`; without, `z` is
    /// not touched.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn hidden_forward(
        &self,
        gpu: &GpuContext,
        l: usize,
        n: u32,
        tangents: bool,
        src: &wgpu::Buffer,
        z: &wgpu::Buffer,
        act: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let omega = self.config.omega0;
        let rows = if tangents { 4 * n } else { n };
        let params = self.params;
        if let Some(d) = self.dense_for(l) {
            let (epilogue, out) = if tangents {
                (Epilogue::SineWithTangents { omega, act }, z)
            } else {
                (Epilogue::Sine { omega }, act)
            };
            return d.forward(gpu, l, rows, epilogue, src, params, out);
        }
        if let Some(t) = self.tiled {
            let u = gemm_forward(&self.layers[l], rows, false, omega);
            return Ok(vec![if tangents {
                let epilogue = TiledEpilogue::SineWithTangents { omega, act };
                t.gemm(gpu, &u, epilogue, src, params, z)
            } else {
                t.gemm(gpu, &u, TiledEpilogue::Sine { omega }, src, params, act)
            }]);
        }
        Ok(if tangents {
            let u = gemm_forward(&self.layers[l], rows, false, omega);
            vec![
                self.gemm.launch(gpu, &u, src, params, params, z),
                self.gemm
                    .sine_forward(gpu, self.sine_layer(l), n, params, z, act),
            ]
        } else {
            // The GEMM adds the bias and takes the sine itself when no tangents follow.
            let u = gemm_forward(&self.layers[l], rows, true, omega);
            vec![self.gemm.launch(gpu, &u, src, params, params, act)]
        })
    }
}
