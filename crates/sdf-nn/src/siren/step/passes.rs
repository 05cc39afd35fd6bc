//! [`TrainPasses`]: the buffers and recorded launches of one training step for a batch of a
//! fixed size, from whichever builder the network's options pick.

use super::super::kernels::{Launch, WG};
use super::super::loss::LossWeights;
use super::reverse_over_reverse::{self, GPU_HEAD_LANES, HEAD_WG};
use super::{StepNet, tangents};
use crate::gpu::{GpuContext, GpuError};

/// The buffers and recorded launches of one training step's forward and backward passes for a
/// batch of `n` points whose input streams the caller writes into [`TrainPasses::x_streams`].
#[derive(Debug)]
pub(crate) struct TrainPasses {
    pub(crate) n: u32,
    n_surface: u32,
    pub(crate) x_streams: wgpu::Buffer,
    pub(crate) normals: wgpu::Buffer,
    pub(crate) loss_partial: wgpu::Buffer,
    pub(crate) loss_groups: u32,
    launches: Vec<Launch>,
    _keep: Vec<wgpu::Buffer>,
}

impl TrainPasses {
    /// Everything for a batch of `n` points, `n_surface` of them on the surface.
    pub(crate) fn new(
        gpu: &GpuContext,
        net: &StepNet<'_>,
        n: u32,
        n_surface: u32,
        weights: &LossWeights,
    ) -> Result<Self, GpuError> {
        let x_streams = gpu.storage_zeroed("siren x streams", u64::from(4 * n) * 3 * 4)?;
        // Every point's: the normal on the surface, (side, 0, 0) off it.
        let normals = gpu.storage_zeroed("siren batch normals", u64::from(n) * 3 * 4)?;
        // A sum per workgroup of the head, whichever step: the reverse-over-reverse head's
        // workgroups take the fewest points, in its GPU layout (passes rebuilt on these
        // buffers may have the other layout).
        let head_groups = n.div_ceil(WG.min(HEAD_WG / GPU_HEAD_LANES));
        let loss_partial = gpu.storage_zeroed("siren loss partial", u64::from(head_groups) * 16)?;
        let io = Io {
            x_streams,
            normals,
            loss_partial,
        };
        Self::with_io(gpu, net, n, n_surface, weights, io)
    }

    /// The passes rebuilt for `net`'s current kernels, on the same input and loss buffers (so
    /// launches bound to those stay valid).
    pub(crate) fn rebuilt(
        &self,
        gpu: &GpuContext,
        net: &StepNet<'_>,
        weights: &LossWeights,
    ) -> Result<Self, GpuError> {
        let io = Io {
            x_streams: self.x_streams.clone(),
            normals: self.normals.clone(),
            loss_partial: self.loss_partial.clone(),
        };
        Self::with_io(gpu, net, self.n, self.n_surface, weights, io)
    }

    fn with_io(
        gpu: &GpuContext,
        net: &StepNet<'_>,
        n: u32,
        n_surface: u32,
        weights: &LossWeights,
        io: Io,
    ) -> Result<Self, GpuError> {
        let (x, nrm, loss) = (&io.x_streams, &io.normals, &io.loss_partial);
        let step = if net.reverse_over_reverse {
            reverse_over_reverse::build(gpu, net, n, n_surface, weights, x, nrm, loss)?
        } else {
            tangents::build(gpu, &net.net, n, n_surface, weights, x, nrm, loss)?
        };
        Ok(TrainPasses {
            n,
            n_surface,
            x_streams: io.x_streams,
            normals: io.normals,
            loss_partial: io.loss_partial,
            loss_groups: step.loss_groups,
            launches: step.launches,
            _keep: step.keep,
        })
    }

    /// Records forward, loss and backward (accumulating into the gradient buffer).
    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        for l in &self.launches {
            l.record(pass);
        }
    }

    /// The launches [`TrainPasses::record`] records, in order.
    pub(crate) fn launches(&self) -> &[Launch] {
        &self.launches
    }
}

/// The buffers a step reads and writes that outlive a rebuild.
struct Io {
    x_streams: wgpu::Buffer,
    normals: wgpu::Buffer,
    loss_partial: wgpu::Buffer,
}
