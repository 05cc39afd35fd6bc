//! Host side of the tiled family for GPUs ([`super::super::LayerKernels::Tiled`]):
//! `shaders/siren_tiled_layer.wgsl` (one tiled GEMM per layer product, epilogues fused) and
//! `shaders/siren_tiled_fused.wgsl` (every layer of an inference in one dispatch).

use super::products::GemmUniforms;
use super::{Launch, OneDispatch, TiledBlock, point_stride};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;
use crate::siren::SirenConfig;

/// Rows and columns of C per workgroup of the tiled GEMM with 4 × 4 register blocks (the
/// tile is `TILE·MB` × `TILE·NB` in the shader).
const TILE: u32 = 64;
/// Workgroup memory of the tiled GEMM with `(MB, NB)` blocks: a (64·MB) × 16 and a
/// 16 × (64·NB) f32 tile.
fn gemm_workgroup_bytes((mb, nb): (u32, u32)) -> u32 {
    (mb + nb) * TILE * 16 * 4
}
/// Invocations per workgroup of both kernels.
const INVOCATIONS: u32 = 256;

/// What the tiled GEMM does with the product (the shader's `mode`).
#[derive(Clone, Copy, Debug)]
pub(crate) enum TiledEpilogue<'a> {
    /// Inference: `sin(ω0 (C + b))`; B must be the parameter buffer.
    Sine { omega: f32 },
    /// Four rows per point: store `z` (bias added to the value row) in `out` and the
    /// activations with their tangents in `act`; B must be the parameter buffer.
    SineWithTangents { omega: f32, act: &'a wgpu::Buffer },
    /// Four rows per point: turn Ā of the layer below's activations into its Z̄ through its
    /// sine, whose pre-activations are `z`.
    SineBelow { omega: f32, z: &'a wgpu::Buffer },
    /// Split-K weight-gradient partials with the bias partials (see `siren_gemm.wgsl` mode 2).
    WeightGradient,
    /// [`TiledEpilogue::WeightGradient`] over the stacked rows of the reverse-over-reverse
    /// step (two per point, the bias summed over the first of each pair).
    WeightGradientPairs,
    /// Reverse-over-reverse forward (mode 5): `z = C + b` into `out`, `sin(ω0 z)` into `act`;
    /// B must be the parameter buffer.
    RorForward {
        omega: f32,
        act: &'a wgpu::Buffer,
        offsets: RorOffsets,
    },
    /// Input-gradient chain (mode 6): `C = G` into `p`, `D(z) ⊙ G` into `out`; z read from `p`.
    RorGradBackward {
        omega: f32,
        p: &'a wgpu::Buffer,
        offsets: RorOffsets,
    },
    /// Its adjoint (mode 7): `C = H̄`, `D(z) ⊙ H̄` into `out`, G in `p` replaced by
    /// `D'(z) ⊙ G ⊙ H̄`; z read from `p`.
    RorGradAdjoint {
        omega: f32,
        p: &'a wgpu::Buffer,
        offsets: RorOffsets,
    },
    /// The forward's adjoint (mode 8): `C = Ā`, `D(z) ⊙ Ā + T` into `out`, z and T read from
    /// `p`.
    RorValueAdjoint {
        omega: f32,
        p: &'a wgpu::Buffer,
        offsets: RorOffsets,
    },
}

impl TiledEpilogue<'_> {
    /// A short name, for launch labels and profiles.
    fn name(&self) -> &'static str {
        match self {
            TiledEpilogue::Sine { .. } => "sine",
            TiledEpilogue::SineWithTangents { .. } => "sine with tangents",
            TiledEpilogue::SineBelow { .. } => "sine below",
            TiledEpilogue::WeightGradient => "weight gradient",
            TiledEpilogue::WeightGradientPairs => "weight gradient (pairs)",
            TiledEpilogue::RorForward { .. } => "ror forward",
            TiledEpilogue::RorGradBackward { .. } => "ror input-gradient chain",
            TiledEpilogue::RorGradAdjoint { .. } => "ror input-gradient adjoint",
            TiledEpilogue::RorValueAdjoint { .. } => "ror forward's adjoint",
        }
    }
}

/// Element offsets of the reverse-over-reverse epilogues' matrices (all with row stride
/// `ldc`): `out` of the output, `out1` of the second output (or of G / T in place), `z` and
/// `t` of the auxiliary inputs.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct RorOffsets {
    pub(crate) out: u32,
    pub(crate) out1: u32,
    pub(crate) z: u32,
    pub(crate) t: u32,
}

/// Floats of activations the fused kernel keeps in workgroup memory per register block of its
/// invocations (`act` in the shader holds `RB` times as many): 16 KiB, what every device has.
const FUSED_ACT_FLOATS: u32 = 4096;

/// The fused kernel's `Fused` uniforms.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct FusedUniforms {
    rows: u32,
    group_rows: u32,
    width: u32,
    hidden_layers: u32,
    tangents: u32,
    point_stride: u32,
    omega: f32,
    query: u32,
    map: [f32; 4],
}

/// How the fused inference kernel splits a batch ([`TiledKernels::fused_layout`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct FusedLayout {
    /// Register blocks of four rows per invocation (`RB`).
    pub(crate) row_blocks: u32,
    /// Rows per workgroup.
    pub(crate) group_rows: u32,
    /// Workgroup memory of the activations, in vec4s (`ACT4`).
    act_vec4s: u32,
}

/// The tiled GEMM's pipelines for one register block.
#[derive(Debug)]
struct GemmPipelines {
    /// 4-row and 4-column blocks per invocation (`MB`, `NB`).
    blocks: (u32, u32),
    gemm: wgpu::ComputePipeline,
    /// `gemm` with the reverse-over-reverse epilogues (and the pairs' bias step) compiled in.
    gemm_ror: wgpu::ComputePipeline,
}

impl GemmPipelines {
    fn new(gpu: &GpuContext, (mb, nb): (u32, u32)) -> Result<Self, GpuError> {
        let (mb_f, nb_f) = (f64::from(mb), f64::from(nb));
        Ok(GemmPipelines {
            blocks: (mb, nb),
            gemm: gpu.pipeline(
                &shaders::SIREN_TILED_LAYER,
                "tiled_gemm",
                &[("MB", mb_f), ("NB", nb_f)],
            )?,
            gemm_ror: gpu.pipeline(
                &shaders::SIREN_TILED_LAYER,
                "tiled_gemm",
                &[("ROR", 1.0), ("BIAS_STEP", 2.0), ("MB", mb_f), ("NB", nb_f)],
            )?,
        })
    }
}

/// The tiled kernels' pipelines.
#[derive(Debug)]
pub(crate) struct TiledKernels {
    /// The GEMM's pipelines for the register blocks its [`TiledBlock`] names (for
    /// [`TiledBlock::Auto`], 4 × 4 on GPUs and 8 × 8 on CPUs).
    gemms: GemmPipelines,
    /// The fused inference kernel's transposed weights, where the network fits it.
    fused: Option<FusedWeights>,
    /// Bound where a mode does not use a binding.
    dummy: wgpu::Buffer,
    dummy_rw: wgpu::Buffer,
}

/// The hidden layers' weights after the first, transposed for the fused kernel (`wt4` in the
/// shader: a subgroup's invocations then read consecutive vec4s of one row of Wᵀ instead of
/// one weight row each), and the launch that writes them from the parameters.
#[derive(Debug)]
struct FusedWeights {
    transposed: wgpu::Buffer,
    /// `None` with a single hidden layer (no width × width weights).
    pack: Option<Launch>,
}

impl TiledKernels {
    /// The kernels for `cfg`, whose parameters are `params`, or `None` when the device's limits
    /// do not fit them (read from the device, which [`GpuContext`] opened with the adapter's
    /// limits).
    pub(crate) fn new(
        gpu: &GpuContext,
        cfg: &SirenConfig,
        params: &wgpu::Buffer,
        block: TiledBlock,
    ) -> Result<Option<Self>, GpuError> {
        let limits = gpu.limits();
        let Some(blocks) = register_blocks(
            block,
            gpu.is_cpu(),
            limits.max_compute_workgroup_storage_size,
        ) else {
            return Ok(None);
        };
        if limits.max_compute_invocations_per_workgroup < INVOCATIONS {
            return Ok(None);
        }
        let fused = match Self::fused_group_rows(gpu, cfg) {
            Some(_) => Some(FusedWeights::new(gpu, cfg, params)?),
            None => None,
        };
        Ok(Some(TiledKernels {
            gemms: GemmPipelines::new(gpu, blocks)?,
            fused,
            dummy: gpu.storage_zeroed("siren tiled dummy", 16)?,
            dummy_rw: gpu.storage_zeroed("siren tiled dummy rw", 16)?,
        }))
    }

    /// Records the transposition of the fused kernel's weights (after every change of the
    /// parameters, before an evaluation that may run it).
    pub(crate) fn record_pack(&self, enc: &mut wgpu::CommandEncoder) {
        if let Some(pack) = self.fused.as_ref().and_then(|f| f.pack.as_ref()) {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("siren fused pack"),
                timestamp_writes: None,
            });
            pack.record(&mut pass);
        }
    }

    /// Rows per workgroup of the fused inference kernel for `cfg` with one register block per
    /// invocation, or `None` when the network does not fit it (width not a multiple of 4, or
    /// too wide for 4 rows of activations in its workgroup memory, or the device's workgroup
    /// memory too small).
    pub(crate) fn fused_group_rows(gpu: &GpuContext, cfg: &SirenConfig) -> Option<u32> {
        Self::fused_layout(gpu, cfg, 1).map(|l| l.group_rows)
    }

    /// The fused kernel's layout for `cfg` with up to `row_blocks` (1 to 3) register blocks per
    /// invocation. Where the device's workgroup memory holds fewer than `row_blocks` full
    /// blocks, each block gets fewer rows (and some invocations idle: on 32 KiB at width 256,
    /// 3 blocks of 8 rows, which lavapipe still ran faster than 2 of 16); fewer blocks only
    /// where not even 4 rows each fit. `None` where one block does not (see
    /// [`TiledKernels::fused_group_rows`]).
    pub(crate) fn fused_layout(
        gpu: &GpuContext,
        cfg: &SirenConfig,
        row_blocks: u32,
    ) -> Option<FusedLayout> {
        let limits = gpu.limits();
        let w = cfg.width as u32;
        if !w.is_multiple_of(4)
            || limits.max_compute_workgroup_storage_size < FUSED_ACT_FLOATS * 4
            || limits.max_compute_invocations_per_workgroup < INVOCATIONS
        {
            return None;
        }
        // Rows between an invocation's blocks: group_rows / RB · width ≤ 4096 (one 4 × 4 block
        // per invocation in each), at most one head row per invocation, and the activations of
        // all the blocks within the device's workgroup memory.
        let bytes_per_row = w * 4;
        (1..=row_blocks.clamp(1, 3)).rev().find_map(|rb| {
            let fits = limits.max_compute_workgroup_storage_size / (bytes_per_row * rb);
            let span = (FUSED_ACT_FLOATS / w).min(INVOCATIONS).min(fits) / 4 * 4;
            (span >= 4).then(|| FusedLayout {
                row_blocks: rb,
                group_rows: span * rb,
                act_vec4s: span * rb * w / 4,
            })
        })
    }

    /// The fused inference launch over `rows` rows (points, or four rows per point with
    /// `tangents`) from `input` into `values` (one float per row). Without `query`, `input`
    /// holds the network's rows (three floats per point, or twelve with tangents: the point and
    /// the unit tangents) and `values` receives Φ (and ∇Φ); with `query` (the map into the
    /// cube: the centre in xyz, the scale in w), `input` holds a caller's vec4 points in mesh
    /// coordinates and `values` receives `NeuralSdf`'s distances (and unit normals).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn fused_forward(
        &self,
        gpu: &GpuContext,
        cfg: &SirenConfig,
        layout: FusedLayout,
        rows: u32,
        tangents: bool,
        query: Option<glam::Vec4>,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        values: &wgpu::Buffer,
    ) -> Result<OneDispatch, GpuError> {
        let group_rows = layout.group_rows;
        let transposed = &self
            .fused
            .as_ref()
            .expect("built where the network fits")
            .transposed;
        // Compiled on first use (the context caches pipelines).
        let pipeline = gpu.pipeline(
            &shaders::SIREN_TILED_FUSED,
            "fused_forward",
            &[
                ("RB", f64::from(layout.row_blocks)),
                ("ACT4", f64::from(layout.act_vec4s)),
            ],
        )?;
        let u = gpu.uniform(
            "siren fused uniforms",
            &FusedUniforms {
                rows,
                group_rows,
                width: cfg.width as u32,
                hidden_layers: cfg.hidden_layers as u32,
                tangents: u32::from(tangents),
                point_stride: point_stride(query.is_some(), tangents),
                omega: cfg.omega0,
                query: u32::from(query.is_some()),
                map: query.unwrap_or(glam::Vec4::W).to_array(),
            },
        );
        let (x, y) = gpu.dispatch_size(rows.div_ceil(group_rows).max(1));
        let launch = Launch::new(
            gpu,
            &pipeline,
            "siren fused forward",
            &[
                entry(0, &u),
                entry(1, input),
                entry(2, params),
                entry(3, params),
                entry(4, values),
                entry(5, transposed),
            ],
            (x, y, 1),
        );
        Ok(OneDispatch {
            launch,
            uniforms: u,
            group_rows,
        })
    }

    /// The launch of the product `u` describes (operands `a`, `b` as in
    /// [`GemmUniforms`]; its `mode` is ignored) with `epilogue`, into `out`.
    pub(crate) fn gemm(
        &self,
        gpu: &GpuContext,
        u: &GemmUniforms,
        epilogue: TiledEpilogue<'_>,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Launch {
        let none = RorOffsets::default();
        let (mode, omega, out1, z_in, offs) = match epilogue {
            TiledEpilogue::Sine { omega } => (1, omega, &self.dummy_rw, &self.dummy, none),
            TiledEpilogue::SineWithTangents { omega, act } => (2, omega, act, &self.dummy, none),
            TiledEpilogue::SineBelow { omega, z } => (3, omega, &self.dummy_rw, z, none),
            TiledEpilogue::WeightGradient | TiledEpilogue::WeightGradientPairs => {
                (4, 0.0, &self.dummy_rw, &self.dummy, none)
            }
            TiledEpilogue::RorForward {
                omega,
                act,
                offsets,
            } => (5, omega, act, &self.dummy, offsets),
            TiledEpilogue::RorGradBackward { omega, p, offsets } => {
                (6, omega, p, &self.dummy, offsets)
            }
            TiledEpilogue::RorGradAdjoint { omega, p, offsets } => {
                (7, omega, p, &self.dummy, offsets)
            }
            TiledEpilogue::RorValueAdjoint { omega, p, offsets } => {
                (8, omega, &self.dummy_rw, p, offsets)
            }
        };
        let z = if mode == 4 {
            u.k.div_ceil(u.k_chunk).max(1)
        } else {
            1
        };
        let gemms = &self.gemms;
        let pipeline = if mode >= 5 || matches!(epilogue, TiledEpilogue::WeightGradientPairs) {
            &gemms.gemm_ror
        } else {
            &gemms.gemm
        };
        let four = |x: u32| x.is_multiple_of(4);
        // Which way each operand is contiguous, and whether its vec4 loads are aligned.
        let a_fast_m = u.a_rs == 1 && u.a_cs != 1;
        let a_aligned = four(u.a_off)
            && if a_fast_m {
                four(u.a_cs)
            } else {
                u.a_cs == 1 && four(u.a_rs)
            };
        let b_fast_n = u.b_cs == 1 && u.b_rs != 1;
        let b_aligned = four(u.b_off)
            && if b_fast_n {
                four(u.b_rs)
            } else {
                u.b_rs == 1 && four(u.b_cs)
            };
        let uniforms = TiledUniforms {
            mode,
            m: u.m,
            n: u.n,
            k: u.k,
            a_off: u.a_off,
            a_rs: u.a_rs,
            a_cs: u.a_cs,
            b_off: u.b_off,
            b_rs: u.b_rs,
            b_cs: u.b_cs,
            ldc: u.ldc,
            bias_off: u.bias_off,
            k_chunk: u.k_chunk,
            pbias_off: u.pbias_off,
            omega,
            flags: u32::from(a_fast_m)
                | u32::from(a_aligned) << 1
                | u32::from(b_fast_n) << 2
                | u32::from(b_aligned) << 3,
            out_off: offs.out,
            out1_off: offs.out1,
            z_off: offs.z,
            t_off: offs.t,
        };
        // The bias partial walks value rows as every fourth row of each 16-row slice.
        debug_assert!(mode != 4 || u.k_chunk.is_multiple_of(16));
        let ub = gpu.uniform("siren tiled uniforms", &uniforms);
        let (x, y) = gpu.dispatch_size(workgroups(gemms.blocks, u.m, u.n));
        // Named by shape and epilogue: a profile's rows tell the products apart.
        let label = format!(
            "siren tiled gemm {}x{}x{} {}",
            u.m,
            u.n,
            u.k,
            epilogue.name()
        );
        Launch::new(
            gpu,
            pipeline,
            &label,
            &[
                entry(0, &ub),
                entry(1, a),
                entry(2, b),
                entry(3, a),
                entry(4, b),
                entry(5, out),
                entry(6, out1),
                entry(7, z_in),
            ],
            (x, y, z),
        )
    }
}

/// Workgroups of the tiled GEMM with `(MB, NB)` blocks over an `m` × `n` product (per split).
fn workgroups((mb, nb): (u32, u32), m: u32, n: u32) -> u32 {
    m.div_ceil(TILE * mb)
        .saturating_mul(n.div_ceil(TILE * nb))
        .max(1)
}

/// The GEMM's register blocks `(MB, NB)` for `block` on a CPU or GPU adapter with
/// `workgroup_bytes` of workgroup memory, or `None` where not even 4 × 4 fits.
///
/// [`TiledBlock::Auto`] is 4 × 4 on GPUs and 8 × 8 on CPUs, each measured fastest for every
/// product of the `default` preset there (docs/benchmarks "Tiled GEMM register blocks"): on an H100,
/// 8 × 8 took 19 % more time for 50 000 points of inference and 36 % more per training step
/// (its fewer, larger workgroups keep fewer warps in flight per multiprocessor); on lavapipe it
/// took 31 % and 12 % less. Auto falls back to 4 × 4 where 8 × 8's tiles do not fit; a forced
/// block that does not fit gives `None`.
fn register_blocks(block: TiledBlock, cpu: bool, workgroup_bytes: u32) -> Option<(u32, u32)> {
    let candidates = match block.blocks() {
        Some(forced) => vec![forced],
        None if cpu => vec![(2, 2), (1, 1)],
        None => vec![(1, 1)],
    };
    candidates
        .into_iter()
        .find(|&b| gemm_workgroup_bytes(b) <= workgroup_bytes)
}

impl FusedWeights {
    fn new(gpu: &GpuContext, cfg: &SirenConfig, params: &wgpu::Buffer) -> Result<Self, GpuError> {
        let w = cfg.width as u64;
        let weights = (cfg.hidden_layers as u64).saturating_sub(1) * w * w;
        let transposed =
            gpu.storage_zeroed("siren fused transposed weights", weights.max(4) * 4)?;
        let pack = if weights == 0 {
            None
        } else {
            let pipeline = gpu.pipeline(&shaders::SIREN_TILED_FUSED, "fused_pack", &[])?;
            let u = gpu.uniform(
                "siren fused pack uniforms",
                &FusedUniforms {
                    width: cfg.width as u32,
                    hidden_layers: cfg.hidden_layers as u32,
                    ..Default::default()
                },
            );
            Some(Launch::flat(
                gpu,
                &pipeline,
                "siren fused pack",
                &[entry(0, &u), entry(2, params), entry(6, &transposed)],
                weights as u32,
            ))
        };
        Ok(FusedWeights { transposed, pack })
    }
}

/// The shader's `Tiled` uniforms.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct TiledUniforms {
    mode: u32,
    m: u32,
    n: u32,
    k: u32,
    a_off: u32,
    a_rs: u32,
    a_cs: u32,
    b_off: u32,
    b_rs: u32,
    b_cs: u32,
    ldc: u32,
    bias_off: u32,
    k_chunk: u32,
    pbias_off: u32,
    omega: f32,
    flags: u32,
    out_off: u32,
    out1_off: u32,
    z_off: u32,
    t_off: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_blocks_are_the_measured_ones_and_fit() {
        let (gpu, cpu) = (false, true);
        let room = 48 * 1024;
        assert_eq!(register_blocks(TiledBlock::Auto, gpu, room), Some((1, 1)));
        assert_eq!(register_blocks(TiledBlock::Auto, cpu, room), Some((2, 2)));
        // A forced block is kept on either adapter.
        assert_eq!(
            register_blocks(TiledBlock::Block8x4, gpu, room),
            Some((2, 1))
        );
        assert_eq!(
            register_blocks(TiledBlock::Block4x4, cpu, room),
            Some((1, 1))
        );
        // Too little workgroup memory for 8 × 8 falls back to 4 × 4, and for 4 × 4 to none.
        let small = gemm_workgroup_bytes((1, 1));
        assert!(gemm_workgroup_bytes((2, 2)) > small);
        assert_eq!(register_blocks(TiledBlock::Auto, cpu, small), Some((1, 1)));
        assert_eq!(register_blocks(TiledBlock::Block8x8, gpu, small), None);
        assert_eq!(register_blocks(TiledBlock::Auto, gpu, small - 1), None);
        // Degenerate shapes still dispatch one workgroup.
        assert_eq!(workgroups((2, 2), 0, 0), 1);
        assert_eq!(workgroups((1, 2), 129, 65), 3);
        assert_eq!(workgroups((2, 1), 129, 65), 4);
    }
}

#[cfg(test)]
mod uniform_layout {
    /// FusedUniforms, TiledUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::FusedUniforms,
            crate::shaders::SIREN_TILED_FUSED,
            "Fused",
            [
                rows,
                group_rows,
                width,
                hidden_layers,
                tangents,
                point_stride,
                omega,
                query,
                map
            ]
        );
        crate::shaders::assert_mirrors!(
            super::TiledUniforms,
            crate::shaders::SIREN_TILED_LAYER,
            "Tiled",
            [
                mode, m, n, k, a_off, a_rs, a_cs, b_off, b_rs, b_cs, ldc, bias_off, k_chunk,
                pbias_off, omega, flags, out_off, out1_off, z_off, t_off
            ]
        );
    }
}
