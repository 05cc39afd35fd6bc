//! Host side of the cooperative-matrix family ([`super::super::LayerKernels::CoopF16`]):
//! `shaders/siren_coop.wgsl`, SIREN inference with the hidden layers' products on f16
//! cooperative matrices with f32 accumulators (tensor cores), every layer in one dispatch.
//!
//! Inference runs here, with the input gradient (normals) as three tangent rows per point.
//! Training stays on the tiled f32 kernels, which are also the fallback where the device or the
//! network does not fit.
//!
//! Precision: the hidden layers' weights (times ω0) and activations are rounded to f16; the
//! sums, the first layer, the sines' arguments and the head are f32. The tests state the
//! error against the f64 reference.

use super::{Launch, OneDispatch, point_stride};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders::{self, Shader};
use crate::siren::SirenConfig;

/// What each tile file fixes (see `siren_coop_16x16.wgsl`, `siren_coop_8x8.wgsl`).
#[derive(Clone, Copy, Debug)]
struct TileShape {
    shader: Shader,
    /// Side of a tile.
    tile: u32,
    /// f16 activations of a workgroup (`ACT`).
    act: u32,
    /// The most subgroups per workgroup, two column tiles each (`SLOTS`).
    slots: u32,
}

impl TileShape {
    fn for_tile(tile: u32) -> Option<Self> {
        match tile {
            16 => Some(TileShape {
                shader: shaders::SIREN_COOP_16,
                tile,
                act: 16896,
                slots: 8,
            }),
            8 => Some(TileShape {
                shader: shaders::SIREN_COOP_8,
                tile,
                act: 8448,
                slots: 16,
            }),
            _ => None,
        }
    }

    /// Workgroup memory of the forward kernel: the activations and the scratch.
    fn workgroup_bytes(&self) -> u32 {
        self.act * 2 + self.slots * self.tile * self.tile * 4
    }

    /// Rows per workgroup (`GROUP_ROWS`): four row tiles.
    fn group_rows(&self) -> u32 {
        4 * self.tile
    }
}

/// The shader's `Coop` uniforms.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct CoopUniforms {
    rows: u32,
    width: u32,
    hidden_layers: u32,
    omega: f32,
    tangents: u32,
    point_stride: u32,
    act_stride: u32,
    query: u32,
    map: [f32; 4],
}

/// f16s of padding after each row of activations in workgroup memory (16 bytes: a tile's rows
/// then start in different banks).
const ACT_PAD: u32 = 8;

/// The cooperative-matrix kernels of one network, with its packed f16 weights.
#[derive(Debug)]
pub(crate) struct CoopKernels {
    shape: TileShape,
    forward: wgpu::ComputePipeline,
    /// Writes `packed` from the parameters; recorded before evaluations whenever they may
    /// have changed.
    pack: Launch,
    /// ω0 · W of the hidden layers after the first, f16.
    packed: wgpu::Buffer,
}

impl CoopKernels {
    /// The kernels for `cfg` on `gpu`, or `None` where they do not apply: no f16 cooperative
    /// matrices, no fixed subgroup size, too little workgroup memory or too few invocations, a
    /// width that is not a multiple of the tile or wider than the shader's activations
    /// (256), or no hidden width × width layer.
    pub(crate) fn new(
        gpu: &GpuContext,
        cfg: &SirenConfig,
        params: &wgpu::Buffer,
    ) -> Result<Option<Self>, GpuError> {
        let (Some(shape), Some(subgroup)) = (
            gpu.coop_f16_tile().and_then(TileShape::for_tile),
            gpu.fixed_subgroup_size(),
        ) else {
            return Ok(None);
        };
        let limits = gpu.limits();
        let w = cfg.width as u32;
        // A subgroup per two column tiles (the shader's eight accumulators).
        let subgroups = (w / shape.tile).div_ceil(2);
        let invocations = subgroups * subgroup;
        if limits.max_compute_workgroup_storage_size < shape.workgroup_bytes()
            || limits.max_compute_invocations_per_workgroup < invocations
            || limits.max_compute_workgroup_size_x < invocations
            || w == 0
            || !w.is_multiple_of(shape.tile)
            || subgroups > shape.slots
            // The head's partial sums, one per invocation, go through the scratch.
            || invocations > shape.slots * shape.tile * shape.tile
            || shape.group_rows() * (w + ACT_PAD) > shape.act
            || cfg.hidden_layers < 2
        {
            return Ok(None);
        }
        let forward = gpu.pipeline(
            &shape.shader,
            "coop_forward",
            &[("WG", f64::from(invocations))],
        )?;
        let weights = (cfg.hidden_layers as u64 - 1) * u64::from(w) * u64::from(w);
        // f16, padded to whole u32s.
        let packed = gpu.storage_zeroed("siren coop packed weights", weights.div_ceil(2) * 4)?;
        let u = gpu.uniform(
            "siren coop pack uniforms",
            &CoopUniforms {
                width: w,
                hidden_layers: cfg.hidden_layers as u32,
                omega: cfg.omega0,
                ..Default::default()
            },
        );
        let pack_pipeline = gpu.pipeline(&shape.shader, "coop_pack", &[])?;
        let pack = Launch::flat(
            gpu,
            &pack_pipeline,
            "siren coop pack",
            &[entry(0, &u), entry(2, params), entry(5, &packed)],
            weights as u32,
        );
        Ok(Some(CoopKernels {
            shape,
            forward,
            pack,
            packed,
        }))
    }

    /// The side of the tiles.
    pub(crate) fn tile(&self) -> u32 {
        self.shape.tile
    }

    /// Records the packing of the weights into f16 (after every change of the parameters).
    pub(crate) fn record_pack(&self, enc: &mut wgpu::CommandEncoder) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("siren coop pack"),
            timestamp_writes: None,
        });
        self.pack.record(&mut pass);
    }

    /// The inference launch over `rows` rows (points, or four rows per point with `tangents`)
    /// from `input` into `values` (one float per row), reading the first layer, the biases and
    /// the head from `params`. `input` and `values` are as in the tiled fused kernel's
    /// `fused_forward`: the network's rows, or with `query` (the map into the cube) a caller's
    /// points and `NeuralSdf`'s answers.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward(
        &self,
        gpu: &GpuContext,
        cfg: &SirenConfig,
        rows: u32,
        tangents: bool,
        query: Option<glam::Vec4>,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        values: &wgpu::Buffer,
    ) -> OneDispatch {
        let u = gpu.uniform(
            "siren coop uniforms",
            &CoopUniforms {
                rows,
                width: cfg.width as u32,
                hidden_layers: cfg.hidden_layers as u32,
                omega: cfg.omega0,
                tangents: u32::from(tangents),
                point_stride: point_stride(query.is_some(), tangents),
                act_stride: cfg.width as u32 + ACT_PAD,
                query: u32::from(query.is_some()),
                map: query.unwrap_or(glam::Vec4::W).to_array(),
            },
        );
        let group_rows = self.shape.group_rows();
        let (x, y) = gpu.dispatch_size(rows.div_ceil(group_rows).max(1));
        let launch = Launch::new(
            gpu,
            &self.forward,
            "siren coop forward",
            &[
                entry(0, &u),
                entry(1, input),
                entry(2, params),
                entry(3, &self.packed),
                entry(4, values),
            ],
            (x, y, 1),
        );
        OneDispatch {
            launch,
            uniforms: u,
            group_rows,
        }
    }
}

#[cfg(test)]
mod uniform_layout {
    /// CoopUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::CoopUniforms,
            crate::shaders::SIREN_COOP_16,
            "Coop",
            [
                rows,
                width,
                hidden_layers,
                omega,
                tangents,
                point_stride,
                act_stride,
                query,
                map
            ]
        );
        crate::shaders::assert_mirrors!(
            super::CoopUniforms,
            crate::shaders::SIREN_COOP_8,
            "Coop",
            [
                rows,
                width,
                hidden_layers,
                omega,
                tangents,
                point_stride,
                act_stride,
                query,
                map
            ]
        );
    }
}
