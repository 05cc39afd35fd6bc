//! Inference's buffers and launches: the workspace of a forward pass (input, activations and
//! values for a fixed capacity of points), the layer-by-layer launches over it, and
//! [`QueryLaunch`], a one-dispatch kernel bound to a caller's query buffers. [`super::SirenGpu`]
//! decides which of them runs (its kernel families and knobs); this module only builds them.

use glam::Vec3;

use super::kernels::head::HeadUniforms;
use super::kernels::{Launch, OneDispatch};
use super::net::NetView;
use crate::gpu::{GpuContext, GpuError, entry};

/// A point's four input rows: the point, then the unit tangents e_x, e_y, e_z.
pub(crate) fn stream_rows(p: Vec3) -> [f32; 12] {
    [p.x, p.y, p.z, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
}

/// Buffers of the forward pass for a fixed capacity of points, and the launches for the
/// batch size they were last built for.
#[derive(Debug)]
pub(crate) struct EvalWorkspace {
    pub(crate) capacity: u32,
    pub(crate) tangents: bool,
    pub(crate) input: wgpu::Buffer,
    act: [wgpu::Buffer; 2],
    /// Pre-activations (tangent mode only).
    z: wgpu::Buffer,
    pub(crate) values: wgpu::Buffer,
    pub(crate) launches: Vec<Launch>,
    /// The launches were built for this many points.
    pub(crate) built_for: Option<u32>,
}

impl EvalWorkspace {
    /// The buffers for `capacity` points of a network `width` wide (`tangents`: four rows per
    /// point and the pre-activations).
    pub(crate) fn new(
        gpu: &GpuContext,
        width: usize,
        capacity: u32,
        tangents: bool,
    ) -> Result<Self, GpuError> {
        let per = if tangents { 4u64 } else { 1 };
        let rows = u64::from(capacity) * per;
        let width = width as u64;
        Ok(EvalWorkspace {
            capacity,
            tangents,
            input: gpu.storage_zeroed("siren eval input", rows * 3 * 4)?,
            act: [
                gpu.storage_zeroed("siren eval act 0", rows * width * 4)?,
                gpu.storage_zeroed("siren eval act 1", rows * width * 4)?,
            ],
            z: gpu.storage_zeroed("siren eval z", if tangents { rows * width * 4 } else { 4 })?,
            values: gpu.storage_zeroed("siren eval values", rows * 4)?,
            launches: Vec::new(),
            built_for: None,
        })
    }

    /// The launches of a forward pass of `net` over `n` points, layer by layer, from `input`
    /// (three floats per point, or with tangents the twelve of [`stream_rows`]) into `values`
    /// (Φ per point, or Φ and ∇Φ), this workspace's activations as scratch (sized for at least
    /// `n` points). Recorded in one compute pass, in order.
    pub(crate) fn layer_launches(
        &self,
        gpu: &GpuContext,
        net: &NetView<'_>,
        n: u32,
        input: &wgpu::Buffer,
        values: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let cfg = &net.config;
        let mut launches = Vec::new();
        for l in 0..cfg.hidden_layers {
            let src = if l == 0 {
                input
            } else {
                &self.act[(l - 1) % 2]
            };
            let dst = &self.act[l % 2];
            launches.extend(net.hidden_forward(gpu, l, n, self.tangents, src, &self.z, dst)?);
        }
        let last = net.layers.last().expect("at least one layer");
        let head = HeadUniforms {
            mode: self.tangents as u32,
            n_points: n,
            width: cfg.width as u32,
            w_off: last.weight as u32,
            b_off: last.bias as u32,
            omega: cfg.omega0,
            ..Default::default()
        };
        let hu = gpu.uniform("siren head uniforms", &head);
        launches.push(Launch::flat(
            gpu,
            &net.head.eval,
            "siren eval head",
            &[
                entry(0, &hu),
                entry(1, &self.act[(cfg.hidden_layers - 1) % 2]),
                entry(2, net.params),
                entry(4, values),
            ],
            n,
        ));
        Ok(launches)
    }
}

/// A network's two workspaces, of values and of values with gradients, each allocated on first
/// use and kept while the kernels and knobs stay.
#[derive(Debug, Default)]
pub(crate) struct EvalSlots {
    values: Option<EvalWorkspace>,
    gradients: Option<EvalWorkspace>,
}

impl EvalSlots {
    /// Takes the workspace of `tangents` out (put it back with [`EvalSlots::put`]), if any.
    pub(crate) fn take(&mut self, tangents: bool) -> Option<EvalWorkspace> {
        if tangents {
            self.gradients.take()
        } else {
            self.values.take()
        }
    }

    /// Puts `ws` back in its slot.
    pub(crate) fn put(&mut self, ws: EvalWorkspace) {
        if ws.tangents {
            self.gradients = Some(ws);
        } else {
            self.values = Some(ws);
        }
    }

    /// Drops both (the launches they hold are stale).
    pub(crate) fn clear(&mut self) {
        *self = EvalSlots::default();
    }
}

/// A network's one-dispatch kernel bound to a caller's query buffers
/// ([`super::SirenGpu::query_launch`]): a query of any count up to the buffers' capacity writes
/// the count into the uniforms (through the queue, when it changes) instead of building a new
/// launch.
#[derive(Debug)]
pub(crate) struct QueryLaunch {
    kernel: BoundDispatch,
    /// With [`super::LayerKernels::Auto`] and a smallest batch for the cooperative-matrix
    /// kernels: that many points, and the kernel that batches of values of at least as many
    /// run on.
    large: Option<(u32, BoundDispatch)>,
    /// Rows per point: 1, or 4 with normals.
    rows_per_point: u32,
}

/// A one-dispatch kernel and the row count its uniforms hold.
#[derive(Debug)]
struct BoundDispatch {
    kernel: OneDispatch,
    written: u32,
}

impl QueryLaunch {
    /// `kernel` (and `large`, from its batch size on) bound for `capacity` points of
    /// `rows_per_point` rows each: the count their uniforms were built with.
    pub(crate) fn new(
        kernel: OneDispatch,
        large: Option<(u32, OneDispatch)>,
        capacity: u32,
        rows_per_point: u32,
    ) -> Self {
        let written = capacity * rows_per_point;
        QueryLaunch {
            kernel: BoundDispatch { kernel, written },
            large: large.map(|(min, kernel)| (min, BoundDispatch { kernel, written })),
            rows_per_point,
        }
    }

    /// Records the query of `n` points into `pass`; a new count takes effect at the next
    /// submission, so record it at most once per submission.
    pub(crate) fn record(&mut self, gpu: &GpuContext, pass: &mut wgpu::ComputePass<'_>, n: u32) {
        let rows = n * self.rows_per_point;
        let bound = match self.large.as_mut() {
            Some((min, large)) if n >= *min => large,
            _ => &mut self.kernel,
        };
        if rows != bound.written {
            gpu.queue()
                .write_buffer(&bound.kernel.uniforms, 0, bytemuck::bytes_of(&rows));
            bound.written = rows;
        }
        let (x, y) = gpu.dispatch_size(rows.div_ceil(bound.kernel.group_rows).max(1));
        bound.kernel.launch.record_groups(pass, (x, y, 1));
    }
}
