//! Host side of `shaders/siren_dense.wgsl`: SIREN's hidden layers as row-blocked kernels whose
//! weights sit in 16 KiB uniform-buffer windows.
//!
//! A hidden layer qualifies when its fan-out is a multiple of 16 and either its fan-in is 3
//! (the first layer, which has kernels of its own) or its fan-in is a multiple of 16, at most
//! 256, and its weight rows split into windows of at most 16 KiB at offsets the device's
//! uniform-offset alignment allows. The output layer (fan-out 1) always runs on the GEMM
//! kernels.

use std::num::NonZeroU64;

use super::Launch;
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;
use crate::siren::LayerLayout;

/// The uniform window size every device supports (WebGPU's minimum
/// `max_uniform_buffer_binding_size`); the shader's `w` array has exactly this size.
const WINDOW_BYTES: u64 = 16 * 1024;
/// The override that compiles the reverse-over-reverse epilogues into a pipeline.
const ROR: (&str, f64) = ("ROR", 1.0);
/// Invocations per workgroup (`WG` in the shader); each owns four rows.
const WG: u32 = 64;
/// Invocations per weight-gradient tile: each sums every `SPLITS`-th point.
pub(crate) const SPLITS: u32 = 64;
/// Largest reduction length of one launch (`MAX4` vec4s in the shader).
const MAX_REDUCTION: usize = 256;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct DenseUniforms {
    rows: u32,
    a_stride4: u32,
    a_first4: u32,
    out_stride4: u32,
    out_first4: u32,
    mode: u32,
    bias_off: u32,
    omega: f32,
    out1_first4: u32,
    z_first4: u32,
    t_first4: u32,
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct WgradUniforms {
    points: u32,
    splits: u32,
    z_stride4: u32,
    x_stride4: u32,
    tiles_k: u32,
    fan_out: u32,
    fan_in: u32,
    pbias_off: u32,
}

/// Where one qualifying layer's weights live in the packed uniform buffer.
#[derive(Clone, Copy, Debug)]
struct PackedLayer {
    layout: LayerLayout,
    /// Byte offset of `W` in the packed buffer.
    offset: u64,
    /// Rows of `W` per window.
    window_rows: u32,
}

impl PackedLayer {
    fn windows(&self) -> u32 {
        self.layout.fan_out as u32 / self.window_rows
    }

    fn window_offset(&self, w: u32) -> u64 {
        self.offset + u64::from(w) * u64::from(self.window_rows) * self.layout.fan_in as u64 * 4
    }

    /// Window `w`, bound at the full size the shader declares (what lies past the window's
    /// rows is never read).
    fn window_binding<'a>(&self, buffer: &'a wgpu::Buffer, w: u32) -> wgpu::BindingResource<'a> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer,
            offset: self.window_offset(w),
            size: NonZeroU64::new(WINDOW_BYTES),
        })
    }
}

/// What `dense_fwd` does with a layer's pre-activations.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Epilogue<'a> {
    /// Inference: store `sin(ω0 (z + b))`.
    Sine { omega: f32 },
    /// Training or inference with tangents (four rows per point): store `z + b` (value row)
    /// and the tangent rows in `out`, their activations and tangents in `act`.
    SineWithTangents { omega: f32, act: &'a wgpu::Buffer },
}

/// The reverse-over-reverse epilogues of the row-blocked kernels (see `siren_dense.wgsl`).
#[derive(Clone, Copy, Debug)]
pub(crate) enum RorEpilogue {
    /// `z = C + b`, `sin(ω0 z)`.
    Forward { omega: f32 },
    /// `Ḡ = D(z) ⊙ C`, G replaced by `T = D'(z) ⊙ G ⊙ C`.
    GradAdjoint { omega: f32 },
    /// `G = C`, `H = D(z) ⊙ G`.
    GradBackward { omega: f32 },
    /// `Z̄ = D(z) ⊙ C + T`.
    ValueAdjoint { omega: f32 },
}

/// Operands of a reverse-over-reverse product, offsets and strides in floats: the input `a`
/// (row stride `a_stride`, first column `a_first`), the output `out` and the auxiliary matrix
/// `aux`, both with row stride `stride`, at `out_first`, and at `out1_first` (second output
/// or G / T in place), `z_first` (z) and `t_first` (T).
#[derive(Clone, Copy, Debug)]
pub(crate) struct RorIo<'a> {
    pub(crate) a: &'a wgpu::Buffer,
    pub(crate) a_stride: u32,
    pub(crate) a_first: u32,
    pub(crate) out: &'a wgpu::Buffer,
    pub(crate) aux: &'a wgpu::Buffer,
    pub(crate) stride: u32,
    pub(crate) out_first: u32,
    pub(crate) out1_first: u32,
    pub(crate) z_first: u32,
    pub(crate) t_first: u32,
}

/// The buffers of a `first_fwd` / `dense_fwd` launch: its input, its output and the
/// epilogue's second matrix (binding 10).
struct FwdIo<'a> {
    a: &'a wgpu::Buffer,
    out: &'a wgpu::Buffer,
    aux: &'a wgpu::Buffer,
}

/// The packed weight buffer and the layers that use it.
#[derive(Debug)]
pub(crate) struct RowBlockedPlan {
    packed: wgpu::Buffer,
    /// Bound where an entry point declares a buffer that a launch does not use.
    dummy: wgpu::Buffer,
    /// The same for read-write bindings (a buffer must not be bound both ways in a launch).
    dummy_rw: wgpu::Buffer,
    /// Indexed like the network's layers; `None` for layers on the GEMM.
    layers: Vec<Option<PackedLayer>>,
}

impl RowBlockedPlan {
    /// The plan for `layers`, or `None` when no layer qualifies.
    pub(crate) fn new(gpu: &GpuContext, layers: &[LayerLayout]) -> Result<Option<Self>, GpuError> {
        let align = u64::from(gpu.limits().min_uniform_buffer_offset_alignment).max(4);
        let mut offset = 0u64;
        let mut packed = Vec::with_capacity(layers.len());
        for lay in layers {
            let (fan_in, fan_out) = (lay.fan_in, lay.fan_out);
            let row_bytes = fan_in as u64 * 4;
            let window_rows = if fan_in == 3 {
                // The first layer: one window, read as floats by first_fwd / first_wgrad.
                fan_out
            } else {
                (WINDOW_BYTES / row_bytes).min(fan_out as u64) as usize / 4 * 4
            };
            let ok = if fan_in == 3 {
                fan_out % 16 == 0 && fan_out as u64 * row_bytes <= WINDOW_BYTES
            } else {
                fan_in % 16 == 0
                    && fan_in <= MAX_REDUCTION
                    && fan_out % 16 == 0
                    && (4..=MAX_REDUCTION).contains(&window_rows)
                    && fan_out % window_rows == 0
                    && (window_rows as u64 * row_bytes).is_multiple_of(align)
            };
            if ok {
                packed.push(Some(PackedLayer {
                    layout: *lay,
                    offset,
                    window_rows: window_rows as u32,
                }));
                offset = (offset + fan_out as u64 * row_bytes).next_multiple_of(align);
            } else {
                packed.push(None);
            }
        }
        let Some(end) = packed
            .iter()
            .flatten()
            .map(|p| p.window_offset(p.windows() - 1) + WINDOW_BYTES)
            .max()
        else {
            return Ok(None);
        };
        let buffer = gpu.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("siren packed weights"),
            size: end.max(offset),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Some(RowBlockedPlan {
            packed: buffer,
            dummy: gpu.storage_zeroed("siren dense dummy", 16)?,
            dummy_rw: gpu.storage_zeroed("siren dense dummy rw", 16)?,
            layers: packed,
        }))
    }

    /// Whether layer `l` runs on the row-blocked kernels.
    pub(crate) fn covers(&self, l: usize) -> bool {
        self.layers.get(l).is_some_and(Option::is_some)
    }

    /// Copies the current weights of every covered layer from `params` into the packed buffer.
    /// Must be recorded before any launch of this plan reads them.
    pub(crate) fn record_pack(&self, enc: &mut wgpu::CommandEncoder, params: &wgpu::Buffer) {
        for p in self.layers.iter().flatten() {
            let bytes = (p.layout.fan_out * p.layout.fan_in) as u64 * 4;
            enc.copy_buffer_to_buffer(
                params,
                p.layout.weight as u64 * 4,
                &self.packed,
                p.offset,
                bytes,
            );
        }
    }

    fn layer(&self, l: usize) -> &PackedLayer {
        self.layers[l]
            .as_ref()
            .expect("layer runs on the row-blocked kernels")
    }

    fn groups(gpu: &GpuContext, rows: u32) -> (u32, u32, u32) {
        let (x, y) = gpu.dispatch_size(rows.div_ceil(4).div_ceil(WG).max(1));
        (x, y, 1)
    }

    /// `z = act · Wᵀ` for layer `l` over `rows` rows, finished by `epilogue` into `out`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward(
        &self,
        gpu: &GpuContext,
        l: usize,
        rows: u32,
        epilogue: Epilogue<'_>,
        act: &wgpu::Buffer,
        params: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let p = self.layer(l);
        let (fan_in, fan_out) = (p.layout.fan_in as u32, p.layout.fan_out as u32);
        let (mode, omega, act_out) = match epilogue {
            Epilogue::Sine { omega } => (1, omega, &self.dummy),
            Epilogue::SineWithTangents { omega, act } => (2, omega, act),
        };
        let io = FwdIo {
            a: act,
            out,
            aux: act_out,
        };
        self.fwd_windows(
            gpu,
            l,
            rows,
            false,
            "siren dense forward",
            &io,
            params,
            |o0| DenseUniforms {
                rows,
                a_stride4: fan_in / 4,
                a_first4: 0,
                out_stride4: fan_out / 4,
                out_first4: o0 / 4,
                mode,
                bias_off: p.layout.bias as u32 + o0,
                omega,
                ..Default::default()
            },
        )
    }

    /// The launches of `first_fwd` (the first layer) or `dense_fwd` for layer `l` over `rows`
    /// rows, one per weight window, with the reverse-over-reverse epilogues compiled in when
    /// `ror`; `uniforms(o0)` gives the window's uniforms from its first output `o0`.
    #[allow(clippy::too_many_arguments)]
    fn fwd_windows(
        &self,
        gpu: &GpuContext,
        l: usize,
        rows: u32,
        ror: bool,
        label: &str,
        io: &FwdIo<'_>,
        params: &wgpu::Buffer,
        uniforms: impl Fn(u32) -> DenseUniforms,
    ) -> Result<Vec<Launch>, GpuError> {
        let p = self.layer(l);
        let (fan_in, fan_out) = (p.layout.fan_in as u32, p.layout.fan_out as u32);
        let first = fan_in == 3;
        let mut constants = if first {
            vec![("OUT4", f64::from(fan_out / 4))]
        } else {
            vec![
                ("RED4", f64::from(fan_in / 4)),
                ("OUT4", f64::from(p.window_rows / 4)),
            ]
        };
        if ror {
            constants.push(ROR);
        }
        let entry_point = if first { "first_fwd" } else { "dense_fwd" };
        let pipeline = gpu.pipeline(&shaders::SIREN_DENSE, entry_point, &constants)?;
        Ok((0..p.windows())
            .map(|w| {
                let u = gpu.uniform(label, &uniforms(w * p.window_rows));
                // first_fwd reads the points as floats at binding 12.
                let input = if first {
                    entry(12, io.a)
                } else {
                    entry(1, io.a)
                };
                Launch::new(
                    gpu,
                    &pipeline,
                    label,
                    &[
                        entry(0, &u),
                        input,
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: p.window_binding(&self.packed, w),
                        },
                        entry(3, io.out),
                        entry(4, params),
                        entry(10, io.aux),
                    ],
                    Self::groups(gpu, rows),
                )
            })
            .collect())
    }

    /// `out = z̄ · W` for layer `l` (the gradient with respect to its input activations);
    /// with `sine_below = (ω0, z)`, carried on through the sine of the layer below (whose
    /// pre-activations are `z`) to that layer's `z̄`.
    pub(crate) fn backward(
        &self,
        gpu: &GpuContext,
        l: usize,
        rows: u32,
        zbar: &wgpu::Buffer,
        out: &wgpu::Buffer,
        sine_below: Option<(f32, &wgpu::Buffer)>,
    ) -> Result<Vec<Launch>, GpuError> {
        let p = self.layer(l);
        let (fan_in, fan_out) = (p.layout.fan_in as u32, p.layout.fan_out as u32);
        let pipeline = gpu.pipeline(
            &shaders::SIREN_DENSE,
            "dense_bwd",
            &[
                ("RED4", f64::from(p.window_rows / 4)),
                ("OUT4", f64::from(fan_in / 4)),
            ],
        )?;
        Ok((0..p.windows())
            .map(|w| {
                let u = gpu.uniform(
                    "siren dense backward",
                    &DenseUniforms {
                        rows,
                        a_stride4: fan_out / 4,
                        a_first4: w * p.window_rows / 4,
                        out_stride4: fan_in / 4,
                        out_first4: 0,
                        mode: u32::from(w > 0)
                            | (u32::from(sine_below.is_some() && w + 1 == p.windows()) << 1),
                        omega: sine_below.map_or(0.0, |(omega, _)| omega),
                        ..Default::default()
                    },
                );
                Launch::new(
                    gpu,
                    &pipeline,
                    "siren dense backward",
                    &[
                        entry(0, &u),
                        entry(1, zbar),
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: p.window_binding(&self.packed, w),
                        },
                        entry(3, out),
                        entry(10, &self.dummy_rw),
                        entry(11, sine_below.map_or(&self.dummy, |(_, z)| z)),
                    ],
                    Self::groups(gpu, rows),
                )
            })
            .collect())
    }

    /// The weight-gradient partials of layer `l` for `points` points into `partial`
    /// (`[SPLITS, fan_out, fan_in]`, then `[SPLITS, fan_out]` bias partials from the returned
    /// offset), for `reduce_wgrad` with `SPLITS` splits. With `pairs`, the stacked rows of the
    /// reverse-over-reverse step (`zbar`: (Z̄, H) per point; `x`: (A, Ḡ) per point, or (x, ḡ)
    /// for the first layer); without, the tangent step's four rows per point.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn weight_gradient(
        &self,
        gpu: &GpuContext,
        l: usize,
        points: u32,
        zbar: &wgpu::Buffer,
        x: &wgpu::Buffer,
        partial: &wgpu::Buffer,
        pairs: bool,
    ) -> Result<(Launch, u32), GpuError> {
        let p = self.layer(l);
        let (fan_in, fan_out) = (p.layout.fan_in as u32, p.layout.fan_out as u32);
        let first = fan_in == 3;
        let pipeline = match (first, pairs) {
            (true, false) => gpu.pipeline(&shaders::SIREN_DENSE, "first_wgrad", &[])?,
            (true, true) => gpu.pipeline(&shaders::SIREN_DENSE, "first_wgrad_pairs", &[])?,
            (false, _) => {
                let rows = ("ROWS_PER_POINT", if pairs { 2.0 } else { 4.0 });
                gpu.pipeline(&shaders::SIREN_DENSE, "dense_wgrad", &[rows])?
            }
        };
        let pbias_off = SPLITS * fan_out * fan_in;
        let u = gpu.uniform(
            "siren dense wgrad",
            &WgradUniforms {
                points,
                splits: SPLITS,
                z_stride4: fan_out / 4,
                x_stride4: fan_in / 4,
                tiles_k: fan_in / 16,
                fan_out,
                fan_in,
                pbias_off,
            },
        );
        let (tiles, entries) = if first {
            let e = [
                entry(5, &u),
                entry(6, zbar),
                entry(12, x),
                entry(13, partial),
            ];
            (fan_out / 16, e)
        } else {
            let e = [entry(5, &u), entry(6, zbar), entry(7, x), entry(8, partial)];
            ((fan_out / 16) * (fan_in / 16), e)
        };
        let launch = Launch::new(
            gpu,
            &pipeline,
            "siren dense wgrad",
            &entries,
            (SPLITS.div_ceil(WG), tiles, 1),
        );
        Ok((launch, pbias_off))
    }

    /// A reverse-over-reverse product `C = A W_lᵀ` of layer `l` over `rows` points
    /// (`siren::step::reverse_over_reverse`): `Forward` (mode 3) or `GradAdjoint` (mode 4)
    /// epilogue. Offsets and strides in `io` are
    /// in floats.
    pub(crate) fn ror_times_wt(
        &self,
        gpu: &GpuContext,
        l: usize,
        rows: u32,
        epilogue: RorEpilogue,
        io: &RorIo<'_>,
        params: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let p = self.layer(l);
        let first = p.layout.fan_in == 3;
        let (mode, omega) = match epilogue {
            RorEpilogue::Forward { omega } => (3, omega),
            RorEpilogue::GradAdjoint { omega } => (4, omega),
            _ => unreachable!("ror_times_wt takes the Wᵀ epilogues"),
        };
        // first_fwd reads the input as floats, dense_fwd as vec4.
        let (a_stride4, a_first4) = if first {
            (io.a_stride, io.a_first)
        } else {
            (io.a_stride / 4, io.a_first / 4)
        };
        let fwd = FwdIo {
            a: io.a,
            out: io.out,
            aux: io.aux,
        };
        self.fwd_windows(
            gpu,
            l,
            rows,
            true,
            "siren dense ror fwd",
            &fwd,
            params,
            |o0| DenseUniforms {
                rows,
                a_stride4,
                a_first4,
                out_stride4: io.stride / 4,
                out_first4: (io.out_first + o0) / 4,
                mode,
                bias_off: p.layout.bias as u32 + o0,
                omega,
                out1_first4: (io.out1_first + o0) / 4,
                z_first4: (io.z_first + o0) / 4,
                t_first4: 0,
                _pad: 0,
            },
        )
    }

    /// A reverse-over-reverse product `C = A W_l` of layer `l` over `rows` points:
    /// `GradBackward` (bit 2: `aux` holds z and receives G) or `ValueAdjoint` (bit 3: `aux`
    /// holds z and T) on the last window.
    pub(crate) fn ror_times_w(
        &self,
        gpu: &GpuContext,
        l: usize,
        rows: u32,
        epilogue: RorEpilogue,
        io: &RorIo<'_>,
    ) -> Result<Vec<Launch>, GpuError> {
        let p = self.layer(l);
        let fan_in = p.layout.fan_in as u32;
        let (bit, omega, grad_backward) = match epilogue {
            RorEpilogue::GradBackward { omega } => (4, omega, true),
            RorEpilogue::ValueAdjoint { omega } => (8, omega, false),
            _ => unreachable!("ror_times_w takes the W epilogues"),
        };
        let pipeline = gpu.pipeline(
            &shaders::SIREN_DENSE,
            "dense_bwd",
            &[
                ("RED4", f64::from(p.window_rows / 4)),
                ("OUT4", f64::from(fan_in / 4)),
                ROR,
            ],
        )?;
        Ok((0..p.windows())
            .map(|w| {
                let last = w + 1 == p.windows();
                let u = gpu.uniform(
                    "siren dense ror bwd",
                    &DenseUniforms {
                        rows,
                        a_stride4: io.a_stride / 4,
                        a_first4: (io.a_first + w * p.window_rows) / 4,
                        out_stride4: io.stride / 4,
                        out_first4: io.out_first / 4,
                        mode: u32::from(w > 0) | if last { bit } else { 0 },
                        omega,
                        out1_first4: io.out1_first / 4,
                        z_first4: io.z_first / 4,
                        t_first4: io.t_first / 4,
                        ..Default::default()
                    },
                );
                let (act, z) = if grad_backward {
                    (io.aux, &self.dummy)
                } else {
                    (&self.dummy_rw, io.aux)
                };
                Launch::new(
                    gpu,
                    &pipeline,
                    "siren dense ror bwd",
                    &[
                        entry(0, &u),
                        entry(1, io.a),
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: p.window_binding(&self.packed, w),
                        },
                        entry(3, io.out),
                        entry(10, act),
                        entry(11, z),
                    ],
                    Self::groups(gpu, rows),
                )
            })
            .collect())
    }

    /// Floats of the partial buffer [`RowBlockedPlan::weight_gradient`] needs for layer `l`.
    pub(crate) fn partial_len(&self, l: usize) -> u64 {
        let p = self.layer(l);
        u64::from(SPLITS) * (p.layout.fan_out as u64) * (p.layout.fan_in as u64 + 1)
    }
}

#[cfg(test)]
mod uniform_layout {
    /// DenseUniforms, WgradUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::DenseUniforms,
            crate::shaders::SIREN_DENSE,
            "Dense",
            [
                rows,
                a_stride4,
                a_first4,
                out_stride4,
                out_first4,
                mode,
                bias_off,
                omega,
                out1_first4,
                z_first4,
                t_first4
            ]
        );
        crate::shaders::assert_mirrors!(
            super::WgradUniforms,
            crate::shaders::SIREN_DENSE,
            "Wgrad",
            [
                points, splits, z_stride4, x_stride4, tiles_k, fan_out, fan_in, pbias_off
            ]
        );
    }
}
