//! The reverse-over-reverse training step: the SIREN loss and its parameter gradient with one
//! row per point in every product, instead of the four rows (point and three tangents) of the
//! forward-mode step.
//!
//! # The math
//!
//! Hidden layers l = 1..L, rows are points: `Z_l = A_{l-1} W_lᵀ + b_l`, `A_l = sin(ω Z_l)`,
//! `A_0 = x`, `Φ = A_L w + b`. With `D(z) = ω cos(ωz)` and `D'(z) = −ω² sin(ωz)`:
//!
//! ```text
//! input gradient (reverse, n rows)   G_L = w (broadcast)            G_l = ∂Φ/∂A_l
//!                                    H_l = D(Z_l) ⊙ G_l             H_l = ∂Φ/∂Z_l
//!                                    G_{l-1} = H_l W_l              ∇ₓΦ = G_0 = H_1 W_1
//! head                               φ̄ = ∂L/∂Φ, ḡ = ∂L/∂∇ₓΦ per point (already / N)
//! its adjoint (upwards, n rows)      Ḡ_0 = ḡ
//!                                    H̄_l = Ḡ_{l-1} W_lᵀ            (a product with Wᵀ)
//!                                    Ḡ_l = D(Z_l) ⊙ H̄_l
//!                                    T_l = D'(Z_l) ⊙ G_l ⊙ H̄_l      (Z_l's share from ∇ₓΦ)
//!                                    w̄ += Σ_p Ḡ_L
//! the forward's adjoint (downwards)  Ā_L = φ̄ wᵀ,  w̄ += Σ_p φ̄ A_L,  b̄ = Σ_p φ̄
//!                                    Z̄_l = D(Z_l) ⊙ Ā_l + T_l
//!                                    Ā_{l-1} = Z̄_l W_l              (a product with W)
//! weight gradients                   W̄_l = Z̄_lᵀ A_{l-1} + H_lᵀ Ḡ_{l-1},  b̄_l = Σ_p Z̄_l
//! ```
//!
//! (`W̄_l`'s second term is the adjoint of `G_{l-1} = H_l W_l`; `T_l` couples the two
//! adjoint chains through the sine's second derivative.) The weight gradient is one split-K
//! product over 2n stacked rows: `[Z̄_l; H_l]ᵀ [A_{l-1}; Ḡ_{l-1}]`, the bias summed over the
//! first row of each pair.
//!
//! Per hidden layer that is four products over n rows (forward, `G`, `H̄`, `Ā`) and one over
//! 2n rows (weights): 6n row-products, against 12n for the tangent step (forward, backward and
//! weights over 4n rows). The first layer's `G_0 = H_1 W_1` (fan-in 3) is computed in the head
//! kernel and `Ā_0` is not needed.
//!
//! # Layout
//!
//! Per hidden layer three matrices of two streams per point, row stride 2·width, so the two
//! stacked operands of the weight gradient are contiguous: `P_l = (Z_l, G_l → T_l)`,
//! `X_l = (A_l, Ḡ_l)`, `Y_l = (Z̄_l, H_l)`; `X_0 = (x, ḡ)`, six floats per point.

use super::gpu::{ReduceUniforms, SirenGpu, SirenGpuError, StepLaunches};
use super::kernels::Launch;
use super::kernels::products::{GemmUniforms, gemm_wgrad, splits_for, times_w, times_wt};
use super::kernels::row_blocked::{RorEpilogue, RorIo, RowBlockedPlan, SPLITS};
use super::kernels::tiled::{RorOffsets, TiledEpilogue, TiledKernels};
use super::{LayerLayout, LossWeights};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;

/// How a training step computes the loss's dependence on ∇ₓΦ.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TrainStep {
    /// [`TrainStep::ReverseOverReverse`] wherever it runs (the tiled kernels, GPUs' default,
    /// and the row-blocked kernels covering every hidden layer, CPU adapters' default, where
    /// it measured 1.6× faster on lavapipe for the `small` preset: BENCHMARKS.md);
    /// [`TrainStep::Tangents`] otherwise (the plain GEMM family, or row-blocked kernels that
    /// leave a layer to the GEMM).
    #[default]
    Auto,
    /// Forward-mode tangents: four rows per point (the point and e_x, e_y, e_z) in every
    /// product, 12n row-products per hidden layer.
    Tangents,
    /// Reverse over reverse (see [`self`](crate::siren::ror)): 6n row-products per hidden
    /// layer. Runs on the tiled kernels, and on the row-blocked kernels when they cover every
    /// hidden layer; with other kernels the step falls back to [`TrainStep::Tangents`].
    ReverseOverReverse,
}

/// Splits of the output layer's gradient: (width + 1) · 256 invocations, 257 workgroups at
/// the `default` width, enough for every SM of a large GPU (64 splits made 65). The same time
/// on lavapipe (7.3 against 7.5 ms for `small`, the reduction 0.1 ms more).
const OUT_SPLITS: u32 = 256;
/// [`OUT_SPLITS`] in the step's GPU layout: at 256 the H100 ran the kernel at 620 GB/s (33 µs
/// for 10⁴ points; a quarter of its invocation slots, 39 dependent loads each), so four
/// times the invocations for a quarter of the loads each.
const GPU_OUT_SPLITS: u32 = 1024;
/// Stacked rows per split of the first layer's weight gradient on the tiled family
/// (`first_rows` of `siren_ror.wgsl`'s uniforms; even, so that a split holds whole pairs).
const FIRST_WGRAD_ROWS: u32 = 128;
/// [`FIRST_WGRAD_ROWS`] in the step's GPU layout: 128 gave 40 192 invocations of 64 row pairs
/// for 10⁴ points, 35 µs on an H100 (590 GB/s); 32 gives four times the invocations.
const GPU_FIRST_WGRAD_ROWS: u32 = 32;
/// Invocations per workgroup of `ror_head` (`HEAD_LANES` per point, the loss summed per
/// workgroup): 64, so that a batch of 10⁴ points spreads over 625 workgroups on a GPU (4 lanes
/// per point: every SM busy).
pub(crate) const HEAD_WG: u32 = 64;
/// Whether a weight gradient's split partials are summed by a workgroup per output
/// (`reduce_wgrad_by_output`) rather than an invocation per output: in the step's GPU layout
/// ([`SirenGpu::set_gpu_step_layout`]), for few outputs of many splits,
/// the output layer's and the first layer's (a hidden layer's 65 792 outputs of 40 splits keep
/// the invocation each).
fn reduce_by_output(gpu_layout: bool, outputs: u32, splits: u32) -> bool {
    gpu_layout && splits >= 64 && outputs <= 4096
}

/// Invocations per point of `ror_head` in the step's GPU layout
/// ([`SirenGpu::set_gpu_step_layout`]; 1 in the CPU layout).
pub(crate) const GPU_HEAD_LANES: u32 = 4;

/// `siren_ror.wgsl`'s uniforms.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct RorUniforms {
    n_points: u32,
    n_surface: u32,
    width: u32,
    w_out_off: u32,
    b_out_off: u32,
    w1_off: u32,
    splits: u32,
    pbias_off: u32,
    w_surface: f32,
    w_off_surface: f32,
    w_normal: f32,
    w_eikonal: f32,
    alpha: f32,
    inv_n: f32,
    omega: f32,
    w_sign: f32,
    b1_off: u32,
    /// Stacked rows per split of `ror_first_wgrad`.
    first_rows: u32,
    _pad: [u32; 2],
}

/// Which kernels run the hidden layers' products.
enum Family<'a> {
    Tiled(&'a TiledKernels),
    RowBlocked(&'a RowBlockedPlan),
}

impl Family<'_> {
    /// The launches of the product `io.a · W_lᵀ` (`transposed`) or `io.a · W_l` with
    /// `epilogue`, on this family: one description of each product for both families.
    #[allow(clippy::too_many_arguments)]
    fn product(
        &self,
        gpu: &GpuContext,
        layers: &[LayerLayout],
        l: usize,
        rows: u32,
        transposed: bool,
        epilogue: RorEpilogue,
        io: &RorIo<'_>,
        params: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        match self {
            Family::Tiled(t) => {
                let uniforms = if transposed { times_wt } else { times_w };
                let u = uniforms(&layers[l], rows, io.a_first, io.a_stride, io.stride);
                let offsets = RorOffsets {
                    out: io.out_first,
                    out1: io.out1_first,
                    z: io.z_first,
                    t: io.t_first,
                };
                let p = io.aux;
                let e = match epilogue {
                    RorEpilogue::Forward { omega } => TiledEpilogue::RorForward {
                        omega,
                        act: p,
                        offsets,
                    },
                    RorEpilogue::GradBackward { omega } => {
                        TiledEpilogue::RorGradBackward { omega, p, offsets }
                    }
                    RorEpilogue::GradAdjoint { omega } => {
                        TiledEpilogue::RorGradAdjoint { omega, p, offsets }
                    }
                    RorEpilogue::ValueAdjoint { omega } => {
                        TiledEpilogue::RorValueAdjoint { omega, p, offsets }
                    }
                };
                Ok(vec![t.gemm(gpu, &u, e, io.a, params, io.out)])
            }
            Family::RowBlocked(d) if transposed => {
                d.ror_times_wt(gpu, l, rows, epilogue, io, params)
            }
            Family::RowBlocked(d) => d.ror_times_w(gpu, l, rows, epilogue, io),
        }
    }
}

/// Builds the step for `n` points (`n_surface` on the surface) reading the input streams
/// (twelve floats per point, the point first) and normals, writing the loss partials.
#[allow(clippy::too_many_arguments)]
pub(crate) fn build(
    gpu: &GpuContext,
    net: &SirenGpu,
    n: u32,
    n_surface: u32,
    weights: &LossWeights,
    x_streams: &wgpu::Buffer,
    normals: &wgpu::Buffer,
    loss_partial: &wgpu::Buffer,
) -> Result<StepLaunches, SirenGpuError> {
    let family = match (net.tiled_kernels(), net.dense_ror_plan()) {
        (Some(t), _) => Family::Tiled(t),
        (None, Some(d)) => Family::RowBlocked(d),
        (None, None) => {
            unreachable!("the reverse-over-reverse step needs tiled or row-blocked kernels")
        }
    };
    let cfg = *net.config();
    let layers = net.layer_layouts();
    let params = net.params_buffer();
    let grads = net.grads_buffer();
    let omega = cfg.omega0;
    let l_hidden = cfg.hidden_layers;
    let width = cfg.width as u32;
    let w2 = 2 * width;
    let pair_bytes = u64::from(n) * u64::from(w2) * 4;
    let mut p = Vec::new();
    let mut x = Vec::new();
    let mut y = Vec::new();
    for _ in 0..l_hidden {
        p.push(gpu.storage_zeroed("siren ror P", pair_bytes)?);
        x.push(gpu.storage_zeroed("siren ror X", pair_bytes)?);
        y.push(gpu.storage_zeroed("siren ror Y", pair_bytes)?);
    }
    let x0 = gpu.storage_zeroed("siren ror X0", u64::from(n) * 6 * 4)?;
    let dphi = gpu.storage_zeroed("siren ror dphi", u64::from(n) * 4)?;
    let rows2 = 2 * n;
    let gpu_layout = net.gpu_step_layout(gpu);
    let (out_splits, first_rows) = if gpu_layout {
        (GPU_OUT_SPLITS, GPU_FIRST_WGRAD_ROWS)
    } else {
        (OUT_SPLITS, FIRST_WGRAD_ROWS)
    };
    let first_splits = rows2.div_ceil(first_rows);
    let wgrads: Vec<GemmUniforms> = layers[..l_hidden]
        .iter()
        .map(|l| gemm_wgrad(l, rows2))
        .collect();
    let partial_len = wgrads
        .iter()
        .enumerate()
        .map(|(l, u)| match &family {
            Family::RowBlocked(d) => d.partial_len(l),
            Family::Tiled(_) => u64::from(u.pbias_off) + u64::from(splits_for(rows2) * u.m),
        })
        .chain([
            u64::from(out_splits) * u64::from(width + 1),
            u64::from(first_splits) * u64::from(width) * 4,
        ])
        .max()
        .unwrap_or(1);
    let partial = gpu.storage_zeroed("siren ror wgrad partial", partial_len * 4)?;
    let reduce = gpu.pipeline(&shaders::SIREN_TRAIN, "reduce_wgrad", &[])?;
    let reduce_by_output_pipeline =
        gpu.pipeline(&shaders::SIREN_TRAIN, "reduce_wgrad_by_output", &[])?;
    let last = layers.last().expect("at least one layer");
    let ror_uniforms = RorUniforms {
        n_points: n,
        n_surface,
        width,
        w_out_off: last.weight as u32,
        b_out_off: last.bias as u32,
        w1_off: layers[0].weight as u32,
        splits: out_splits,
        pbias_off: out_splits * width,
        w_surface: weights.surface,
        w_off_surface: weights.off_surface,
        w_normal: weights.normal,
        w_eikonal: weights.eikonal,
        alpha: weights.alpha,
        inv_n: 1.0 / n as f32,
        omega,
        w_sign: weights.sign,
        b1_off: layers[0].bias as u32,
        first_rows,
        _pad: [0; 2],
    };
    let ru = gpu.uniform("siren ror uniforms", &ror_uniforms);
    // The first layer's weight gradient on the tiled family: its own splits.
    let ru_first = gpu.uniform(
        "siren ror first-layer uniforms",
        &RorUniforms {
            splits: first_splits,
            pbias_off: first_splits * width * 3,
            ..ror_uniforms
        },
    );
    let pipe = |name: &str| gpu.pipeline(&shaders::SIREN_ROR, name, &[]);
    let mut launches = Vec::new();
    let mut keep = Vec::new();
    let top = l_hidden - 1;
    // On the tiled family the first layer's two products with fan-in 3 run elementwise
    // (`ror_first_forward`, `ror_first_grad_adjoint`), not as GEMM tiles padded from 3
    // columns: one invocation per (point, feature) of P_1 and X_1, reading `input`.
    let first_tiled = matches!(family, Family::Tiled(_));
    let first_layer = |entry_point: &str, label: &str, input: wgpu::BindGroupEntry<'_>| {
        Ok::<_, GpuError>(Launch::flat(
            gpu,
            &pipe(entry_point)?,
            label,
            &[
                entry(0, &ru),
                entry(1, params),
                entry(2, &p[0]),
                entry(3, &x[0]),
                input,
            ],
            n * width,
        ))
    };

    // Forward: P_l ← Z_l, X_l ← A_l.
    for l in 0..l_hidden {
        if l == 0 && first_tiled {
            launches.push(first_layer(
                "ror_first_forward",
                "siren ror first-layer forward",
                entry(6, x_streams),
            )?);
            continue;
        }
        let (src, a_rs) = if l == 0 {
            (x_streams, 12)
        } else {
            (&x[l - 1], w2)
        };
        let io = RorIo {
            a: src,
            a_stride: a_rs,
            a_first: 0,
            out: &p[l],
            aux: &x[l],
            stride: w2,
            out_first: 0,
            out1_first: 0,
            z_first: 0,
            t_first: 0,
        };
        let e = RorEpilogue::Forward { omega };
        launches.extend(family.product(gpu, layers, l, n, true, e, &io, params)?);
    }
    // G_L = w, H_L = D(Z_L) ⊙ w.
    launches.push(Launch::flat(
        gpu,
        &pipe("ror_top")?,
        "siren ror top",
        &[
            entry(0, &ru),
            entry(1, params),
            entry(2, &p[top]),
            entry(3, &y[top]),
        ],
        n * width,
    ));
    // The input-gradient chain: G_{l-1} = H_l W_l into P_{l-1}, H_{l-1} into Y_{l-1}.
    for l in (1..l_hidden).rev() {
        let io = RorIo {
            a: &y[l],
            a_stride: w2,
            a_first: width,
            out: &y[l - 1],
            aux: &p[l - 1],
            stride: w2,
            out_first: width,
            out1_first: width,
            z_first: 0,
            t_first: 0,
        };
        let e = RorEpilogue::GradBackward { omega };
        launches.extend(family.product(gpu, layers, l, n, false, e, &io, params)?);
    }
    // Φ, ∇ₓΦ = H_1 W_1, the loss and its seeds φ̄ and ḡ.
    let head_lanes = if gpu_layout { GPU_HEAD_LANES } else { 1 };
    let loss_groups = n.div_ceil(HEAD_WG / head_lanes);
    let (hx, hy) = gpu.dispatch_size(loss_groups);
    let head = gpu.pipeline(
        &shaders::SIREN_ROR,
        "ror_head",
        &[
            ("LOSS_WG", f64::from(HEAD_WG)),
            ("HEAD_LANES", f64::from(head_lanes)),
        ],
    )?;
    launches.push(Launch::new(
        gpu,
        &head,
        "siren ror head",
        &[
            entry(0, &ru),
            entry(1, params),
            entry(4, &x[top]),
            entry(5, &y[0]),
            entry(6, x_streams),
            entry(7, normals),
            entry(8, &x0),
            entry(9, &dphi),
            entry(10, loss_partial),
        ],
        (hx, hy, 1),
    ));
    // The adjoint of the input-gradient chain: H̄_l = Ḡ_{l-1} W_lᵀ, Ḡ_l into X_l, T_l into P_l.
    for l in 0..l_hidden {
        if l == 0 && first_tiled {
            launches.push(first_layer(
                "ror_first_grad_adjoint",
                "siren ror first-layer input-gradient adjoint",
                entry(8, &x0),
            )?);
            continue;
        }
        let (src, a_off, a_rs) = if l == 0 {
            (&x0, 3, 6)
        } else {
            (&x[l - 1], width, w2)
        };
        let io = RorIo {
            a: src,
            a_stride: a_rs,
            a_first: a_off,
            out: &x[l],
            aux: &p[l],
            stride: w2,
            out_first: width,
            out1_first: width,
            z_first: 0,
            t_first: 0,
        };
        let e = RorEpilogue::GradAdjoint { omega };
        launches.extend(family.product(gpu, layers, l, n, true, e, &io, params)?);
    }
    // Z̄_L = D(Z_L) ⊙ φ̄ wᵀ + T_L.
    launches.push(Launch::flat(
        gpu,
        &pipe("ror_top_back")?,
        "siren ror top back",
        &[
            entry(0, &ru),
            entry(1, params),
            entry(2, &p[top]),
            entry(3, &y[top]),
            entry(11, &dphi),
        ],
        n * width,
    ));
    let push_reduce = |launches: &mut Vec<Launch>,
                       keep: &mut Vec<wgpu::Buffer>,
                       lay: &LayerLayout,
                       splits: u32,
                       pbias_off: u32| {
        let (m, k) = (lay.fan_out as u32, lay.fan_in as u32);
        let rub = gpu.uniform(
            "siren ror reduce",
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
        let entries = [entry(5, &rub), entry(6, &partial), entry(7, grads)];
        launches.push(if reduce_by_output(gpu_layout, outputs, splits) {
            let (x, y) = gpu.dispatch_size(outputs);
            Launch::new(
                gpu,
                &reduce_by_output_pipeline,
                "siren ror reduce wgrad by output",
                &entries,
                (x, y, 1),
            )
        } else {
            Launch::flat(gpu, &reduce, "siren ror reduce wgrad", &entries, outputs)
        });
        keep.push(rub);
    };
    // The output layer: w̄ = Σ φ̄ A_L + Ḡ_L, b̄ = Σ φ̄.
    launches.push(Launch::flat(
        gpu,
        &pipe("ror_out_grad")?,
        "siren ror output gradient",
        &[
            entry(0, &ru),
            entry(4, &x[top]),
            entry(11, &dphi),
            entry(12, &partial),
        ],
        out_splits * (width + 1),
    ));
    push_reduce(
        &mut launches,
        &mut keep,
        last,
        out_splits,
        out_splits * width,
    );
    // Downwards: W̄_l from the stacked rows, then Z̄_{l-1} = D(Z_{l-1}) ⊙ Z̄_l W_l + T_{l-1}.
    for l in (0..l_hidden).rev() {
        let below = if l == 0 { &x0 } else { &x[l - 1] };
        match &family {
            // Fan-in 3: a GEMM tile would compute 64 columns for 3.
            Family::Tiled(_) if l == 0 => {
                launches.push(Launch::flat(
                    gpu,
                    &pipe("ror_first_wgrad")?,
                    "siren ror first-layer weight gradient",
                    &[
                        entry(0, &ru_first),
                        entry(5, &y[0]),
                        entry(8, &x0),
                        entry(12, &partial),
                    ],
                    first_splits * width,
                ));
                push_reduce(
                    &mut launches,
                    &mut keep,
                    &layers[0],
                    first_splits,
                    first_splits * width * 3,
                );
            }
            Family::Tiled(t) => {
                let u = wgrads[l];
                let e = TiledEpilogue::WeightGradientPairs;
                launches.push(t.gemm(gpu, &u, e, &y[l], below, &partial));
                push_reduce(
                    &mut launches,
                    &mut keep,
                    &layers[l],
                    splits_for(rows2),
                    u.pbias_off,
                );
            }
            Family::RowBlocked(d) => {
                let (launch, pbias_off) =
                    d.weight_gradient(gpu, l, n, &y[l], below, &partial, true)?;
                launches.push(launch);
                push_reduce(&mut launches, &mut keep, &layers[l], SPLITS, pbias_off);
            }
        }
        if l > 0 {
            let io = RorIo {
                a: &y[l],
                a_stride: w2,
                a_first: 0,
                out: &y[l - 1],
                aux: &p[l - 1],
                stride: w2,
                out_first: 0,
                out1_first: 0,
                z_first: 0,
                t_first: width,
            };
            let e = RorEpilogue::ValueAdjoint { omega };
            launches.extend(family.product(gpu, layers, l, n, false, e, &io, params)?);
        }
    }
    keep.push(ru);
    keep.push(ru_first);
    keep.extend(p);
    keep.extend(x);
    keep.extend(y);
    keep.push(x0);
    keep.push(dphi);
    keep.push(partial);
    Ok(StepLaunches {
        launches,
        keep,
        loss_groups,
    })
}
