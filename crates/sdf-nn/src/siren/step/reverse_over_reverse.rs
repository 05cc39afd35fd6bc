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

use super::super::LayerLayout;
use super::super::kernels::Launch;
use super::super::kernels::products::{GemmUniforms, gemm_wgrad, splits_for, times_w, times_wt};
use super::super::kernels::row_blocked::{RorEpilogue, RorIo, RowBlockedPlan, SPLITS};
use super::super::kernels::tiled::{RorOffsets, TiledEpilogue, TiledKernels};
use super::super::loss::LossWeights;
use super::super::net::NetView;
use super::{StepLaunches, StepNet, WgradReduce};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;

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
/// ([`super::super::SirenGpuOptions::step_layout`]), for few outputs of many splits,
/// the output layer's and the first layer's (a hidden layer's 65 792 outputs of 40 splits keep
/// the invocation each).
fn reduce_by_output(gpu_layout: bool, outputs: u32, splits: u32) -> bool {
    gpu_layout && splits >= 64 && outputs <= 4096
}

/// Invocations per point of `ror_head` in the step's GPU layout
/// ([`super::super::SirenGpuOptions::step_layout`]; 1 in the CPU layout).
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

/// Per hidden layer the three pair matrices of the module docs (`P_l`, `X_l`, `Y_l`), `X_0`,
/// and φ̄ per point.
struct Buffers {
    p: Vec<wgpu::Buffer>,
    x: Vec<wgpu::Buffer>,
    y: Vec<wgpu::Buffer>,
    x0: wgpu::Buffer,
    dphi: wgpu::Buffer,
}

impl Buffers {
    fn new(gpu: &GpuContext, n: u32, width: u32, l_hidden: usize) -> Result<Self, GpuError> {
        let pair_bytes = u64::from(n) * u64::from(2 * width) * 4;
        let mut b = Buffers {
            p: Vec::new(),
            x: Vec::new(),
            y: Vec::new(),
            x0: gpu.storage_zeroed("siren ror X0", u64::from(n) * 6 * 4)?,
            dphi: gpu.storage_zeroed("siren ror dphi", u64::from(n) * 4)?,
        };
        for _ in 0..l_hidden {
            b.p.push(gpu.storage_zeroed("siren ror P", pair_bytes)?);
            b.x.push(gpu.storage_zeroed("siren ror X", pair_bytes)?);
            b.y.push(gpu.storage_zeroed("siren ror Y", pair_bytes)?);
        }
        Ok(b)
    }
}

/// One step being recorded: what every phase reads, and the launches so far. Each phase of
/// [`build`] is a method named for what it records, in the order they run.
struct Recorder<'a> {
    gpu: &'a GpuContext,
    net: NetView<'a>,
    family: Family<'a>,
    gpu_layout: bool,
    n: u32,
    width: u32,
    b: Buffers,
    /// The step's uniforms, and those of the tiled family's first-layer weight gradient.
    ru: wgpu::Buffer,
    ru_first: wgpu::Buffer,
    out_splits: u32,
    first_splits: u32,
    x_streams: &'a wgpu::Buffer,
    launches: Vec<Launch>,
    keep: Vec<wgpu::Buffer>,
}

/// Builds the step for `n` points (`n_surface` on the surface) reading the input streams
/// (twelve floats per point, the point first) and normals, writing the loss partials.
#[allow(clippy::too_many_arguments)]
pub(crate) fn build(
    gpu: &GpuContext,
    step: &StepNet<'_>,
    n: u32,
    n_surface: u32,
    weights: &LossWeights,
    x_streams: &wgpu::Buffer,
    normals: &wgpu::Buffer,
    loss_partial: &wgpu::Buffer,
) -> Result<StepLaunches, GpuError> {
    let net = step.net;
    let family = match (net.tiled, net.dense_ror_plan()) {
        (Some(t), _) => Family::Tiled(t),
        (None, Some(d)) => Family::RowBlocked(d),
        (None, None) => {
            unreachable!("the reverse-over-reverse step needs tiled or row-blocked kernels")
        }
    };
    let layers = net.layers;
    let l_hidden = net.config.hidden_layers;
    let width = net.config.width as u32;
    let gpu_layout = step.gpu_layout;
    let (out_splits, first_rows) = if gpu_layout {
        (GPU_OUT_SPLITS, GPU_FIRST_WGRAD_ROWS)
    } else {
        (OUT_SPLITS, FIRST_WGRAD_ROWS)
    };
    let first_splits = (2 * n).div_ceil(first_rows);
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
        omega: net.config.omega0,
        w_sign: weights.sign,
        b1_off: layers[0].bias as u32,
        first_rows,
        _pad: [0; 2],
    };
    let mut r = Recorder {
        gpu,
        net,
        family,
        gpu_layout,
        n,
        width,
        b: Buffers::new(gpu, n, width, l_hidden)?,
        ru: gpu.uniform("siren ror uniforms", &ror_uniforms),
        // The first layer's weight gradient on the tiled family: its own splits.
        ru_first: gpu.uniform(
            "siren ror first-layer uniforms",
            &RorUniforms {
                splits: first_splits,
                pbias_off: first_splits * width * 3,
                ..ror_uniforms
            },
        ),
        out_splits,
        first_splits,
        x_streams,
        launches: Vec::new(),
        keep: Vec::new(),
    };
    let partial = gpu.storage_zeroed("siren ror wgrad partial", r.partial_len() * 4)?;
    r.forward()?;
    r.input_gradient()?;
    let loss_groups = r.head(normals, loss_partial)?;
    r.input_gradient_adjoint()?;
    let reduce = WgradReduce::new(gpu, "siren ror", &partial, net.grads, true)?;
    r.output_layer_gradient(&partial, &reduce)?;
    r.downwards(&partial, &reduce)?;
    let Recorder {
        launches,
        mut keep,
        b,
        ru,
        ru_first,
        ..
    } = r;
    keep.push(ru);
    keep.push(ru_first);
    keep.extend(b.p);
    keep.extend(b.x);
    keep.extend(b.y);
    keep.push(b.x0);
    keep.push(b.dphi);
    keep.push(partial);
    Ok(StepLaunches {
        launches,
        keep,
        loss_groups,
    })
}

impl Recorder<'_> {
    fn omega(&self) -> f32 {
        self.net.config.omega0
    }

    fn l_hidden(&self) -> usize {
        self.net.config.hidden_layers
    }

    /// A kernel of `siren_ror.wgsl` without overrides.
    fn pipe(&self, name: &str) -> Result<wgpu::ComputePipeline, GpuError> {
        self.gpu.pipeline(&shaders::SIREN_ROR, name, &[])
    }

    /// The weight gradients' split-K products over the 2n stacked rows of each hidden layer.
    fn wgrad(&self, l: usize) -> GemmUniforms {
        gemm_wgrad(&self.net.layers[l], 2 * self.n)
    }

    /// Floats of the weight gradients' partials buffer: the most any layer's sum needs.
    fn partial_len(&self) -> u64 {
        let rows2 = 2 * self.n;
        (0..self.l_hidden())
            .map(|l| match &self.family {
                Family::RowBlocked(d) => d.partial_len(l),
                Family::Tiled(_) => {
                    let u = self.wgrad(l);
                    u64::from(u.pbias_off) + u64::from(splits_for(rows2) * u.m)
                }
            })
            .chain([
                u64::from(self.out_splits) * u64::from(self.width + 1),
                u64::from(self.first_splits) * u64::from(self.width) * 4,
            ])
            .max()
            .unwrap_or(1)
    }

    /// The product of layer `l` over the batch on the family (see [`Family::product`]).
    fn product(
        &self,
        l: usize,
        transposed: bool,
        epilogue: RorEpilogue,
        io: &RorIo<'_>,
    ) -> Result<Vec<Launch>, GpuError> {
        let net = &self.net;
        let (gpu, layers, n) = (self.gpu, net.layers, self.n);
        self.family
            .product(gpu, layers, l, n, transposed, epilogue, io, net.params)
    }

    /// On the tiled family the first layer's two products with fan-in 3 run elementwise
    /// (`ror_first_forward`, `ror_first_grad_adjoint`), not as GEMM tiles padded from 3
    /// columns: one invocation per (point, feature) of P_1 and X_1, reading `input`.
    fn first_layer(
        &self,
        entry_point: &str,
        label: &str,
        input: wgpu::BindGroupEntry<'_>,
    ) -> Result<Launch, GpuError> {
        Ok(Launch::flat(
            self.gpu,
            &self.pipe(entry_point)?,
            label,
            &[
                entry(0, &self.ru),
                entry(1, self.net.params),
                entry(2, &self.b.p[0]),
                entry(3, &self.b.x[0]),
                input,
            ],
            self.n * self.width,
        ))
    }

    /// Forward: P_l ← Z_l, X_l ← A_l.
    fn forward(&mut self) -> Result<(), GpuError> {
        let first_tiled = matches!(self.family, Family::Tiled(_));
        let w2 = 2 * self.width;
        for l in 0..self.l_hidden() {
            if l == 0 && first_tiled {
                let launch = self.first_layer(
                    "ror_first_forward",
                    "siren ror first-layer forward",
                    entry(6, self.x_streams),
                )?;
                self.launches.push(launch);
                continue;
            }
            let b = &self.b;
            let (src, a_rs) = if l == 0 {
                (self.x_streams, 12)
            } else {
                (&b.x[l - 1], w2)
            };
            let io = RorIo {
                a: src,
                a_stride: a_rs,
                a_first: 0,
                out: &b.p[l],
                aux: &b.x[l],
                stride: w2,
                out_first: 0,
                out1_first: 0,
                z_first: 0,
                t_first: 0,
            };
            let e = RorEpilogue::Forward {
                omega: self.omega(),
            };
            let launches = self.product(l, true, e, &io)?;
            self.launches.extend(launches);
        }
        Ok(())
    }

    /// G_L = w, H_L = D(Z_L) ⊙ w; then the input-gradient chain: G_{l-1} = H_l W_l into
    /// P_{l-1}, H_{l-1} into Y_{l-1}.
    fn input_gradient(&mut self) -> Result<(), GpuError> {
        let top = self.l_hidden() - 1;
        let launch = Launch::flat(
            self.gpu,
            &self.pipe("ror_top")?,
            "siren ror top",
            &[
                entry(0, &self.ru),
                entry(1, self.net.params),
                entry(2, &self.b.p[top]),
                entry(3, &self.b.y[top]),
            ],
            self.n * self.width,
        );
        self.launches.push(launch);
        let (width, w2) = (self.width, 2 * self.width);
        for l in (1..self.l_hidden()).rev() {
            let b = &self.b;
            let io = RorIo {
                a: &b.y[l],
                a_stride: w2,
                a_first: width,
                out: &b.y[l - 1],
                aux: &b.p[l - 1],
                stride: w2,
                out_first: width,
                out1_first: width,
                z_first: 0,
                t_first: 0,
            };
            let e = RorEpilogue::GradBackward {
                omega: self.omega(),
            };
            let launches = self.product(l, false, e, &io)?;
            self.launches.extend(launches);
        }
        Ok(())
    }

    /// Φ, ∇ₓΦ = H_1 W_1, the loss (its partials into `loss_partial`) and its seeds φ̄ and ḡ;
    /// returns the count of loss partials.
    fn head(
        &mut self,
        normals: &wgpu::Buffer,
        loss_partial: &wgpu::Buffer,
    ) -> Result<u32, GpuError> {
        let gpu = self.gpu;
        let head_lanes = if self.gpu_layout { GPU_HEAD_LANES } else { 1 };
        let loss_groups = self.n.div_ceil(HEAD_WG / head_lanes);
        let (hx, hy) = gpu.dispatch_size(loss_groups);
        let head = gpu.pipeline(
            &shaders::SIREN_ROR,
            "ror_head",
            &[
                ("LOSS_WG", f64::from(HEAD_WG)),
                ("HEAD_LANES", f64::from(head_lanes)),
            ],
        )?;
        let top = self.l_hidden() - 1;
        let b = &self.b;
        let launch = Launch::new(
            gpu,
            &head,
            "siren ror head",
            &[
                entry(0, &self.ru),
                entry(1, self.net.params),
                entry(4, &b.x[top]),
                entry(5, &b.y[0]),
                entry(6, self.x_streams),
                entry(7, normals),
                entry(8, &b.x0),
                entry(9, &b.dphi),
                entry(10, loss_partial),
            ],
            (hx, hy, 1),
        );
        self.launches.push(launch);
        Ok(loss_groups)
    }

    /// The adjoint of the input-gradient chain: H̄_l = Ḡ_{l-1} W_lᵀ, Ḡ_l into X_l, T_l into
    /// P_l.
    fn input_gradient_adjoint(&mut self) -> Result<(), GpuError> {
        let first_tiled = matches!(self.family, Family::Tiled(_));
        let (width, w2) = (self.width, 2 * self.width);
        for l in 0..self.l_hidden() {
            if l == 0 && first_tiled {
                let launch = self.first_layer(
                    "ror_first_grad_adjoint",
                    "siren ror first-layer input-gradient adjoint",
                    entry(8, &self.b.x0),
                )?;
                self.launches.push(launch);
                continue;
            }
            let b = &self.b;
            let (src, a_off, a_rs) = if l == 0 {
                (&b.x0, 3, 6)
            } else {
                (&b.x[l - 1], width, w2)
            };
            let io = RorIo {
                a: src,
                a_stride: a_rs,
                a_first: a_off,
                out: &b.x[l],
                aux: &b.p[l],
                stride: w2,
                out_first: width,
                out1_first: width,
                z_first: 0,
                t_first: 0,
            };
            let e = RorEpilogue::GradAdjoint {
                omega: self.omega(),
            };
            let launches = self.product(l, true, e, &io)?;
            self.launches.extend(launches);
        }
        Ok(())
    }

    /// The sum of `lay`'s `splits` partials into the gradients (by output in the GPU layout
    /// where few outputs have many splits).
    fn reduce(&mut self, reduce: &WgradReduce<'_>, lay: &LayerLayout, splits: u32, pbias: u32) {
        let outputs = (lay.fan_out * lay.fan_in + lay.fan_out) as u32;
        let by_output = reduce_by_output(self.gpu_layout, outputs, splits);
        let (launches, keep) = (&mut self.launches, &mut self.keep);
        reduce.push(self.gpu, launches, keep, lay, splits, pbias, by_output);
    }

    /// Z̄_L = D(Z_L) ⊙ φ̄ wᵀ + T_L; then the output layer: w̄ = Σ φ̄ A_L + Ḡ_L, b̄ = Σ φ̄.
    fn output_layer_gradient(
        &mut self,
        partial: &wgpu::Buffer,
        reduce: &WgradReduce<'_>,
    ) -> Result<(), GpuError> {
        let top = self.l_hidden() - 1;
        let (gpu, b) = (self.gpu, &self.b);
        let top_back = Launch::flat(
            gpu,
            &self.pipe("ror_top_back")?,
            "siren ror top back",
            &[
                entry(0, &self.ru),
                entry(1, self.net.params),
                entry(2, &b.p[top]),
                entry(3, &b.y[top]),
                entry(11, &b.dphi),
            ],
            self.n * self.width,
        );
        let out_grad = Launch::flat(
            gpu,
            &self.pipe("ror_out_grad")?,
            "siren ror output gradient",
            &[
                entry(0, &self.ru),
                entry(4, &b.x[top]),
                entry(11, &b.dphi),
                entry(12, partial),
            ],
            self.out_splits * (self.width + 1),
        );
        self.launches.push(top_back);
        self.launches.push(out_grad);
        let last = *self.net.layers.last().expect("at least one layer");
        let out_splits = self.out_splits;
        self.reduce(reduce, &last, out_splits, out_splits * self.width);
        Ok(())
    }

    /// Downwards: W̄_l from the stacked rows, then Z̄_{l-1} = D(Z_{l-1}) ⊙ Z̄_l W_l + T_{l-1}.
    fn downwards(
        &mut self,
        partial: &wgpu::Buffer,
        reduce: &WgradReduce<'_>,
    ) -> Result<(), GpuError> {
        let (width, w2) = (self.width, 2 * self.width);
        for l in (0..self.l_hidden()).rev() {
            self.weight_gradient(l, partial, reduce)?;
            if l > 0 {
                let b = &self.b;
                let io = RorIo {
                    a: &b.y[l],
                    a_stride: w2,
                    a_first: 0,
                    out: &b.y[l - 1],
                    aux: &b.p[l - 1],
                    stride: w2,
                    out_first: 0,
                    out1_first: 0,
                    z_first: 0,
                    t_first: width,
                };
                let e = RorEpilogue::ValueAdjoint {
                    omega: self.omega(),
                };
                let launches = self.product(l, false, e, &io)?;
                self.launches.extend(launches);
            }
        }
        Ok(())
    }

    /// W̄_l = [Z̄_l; H_l]ᵀ [A_{l-1}; Ḡ_{l-1}] into the partials, and their sum.
    fn weight_gradient(
        &mut self,
        l: usize,
        partial: &wgpu::Buffer,
        reduce: &WgradReduce<'_>,
    ) -> Result<(), GpuError> {
        let gpu = self.gpu;
        let lay = self.net.layers[l];
        let b = &self.b;
        let below = if l == 0 { &b.x0 } else { &b.x[l - 1] };
        let (launch, splits, pbias_off) = match &self.family {
            // Fan-in 3: a GEMM tile would compute 64 columns for 3.
            Family::Tiled(_) if l == 0 => {
                let launch = Launch::flat(
                    gpu,
                    &self.pipe("ror_first_wgrad")?,
                    "siren ror first-layer weight gradient",
                    &[
                        entry(0, &self.ru_first),
                        entry(5, &b.y[0]),
                        entry(8, &b.x0),
                        entry(12, partial),
                    ],
                    self.first_splits * self.width,
                );
                let splits = self.first_splits;
                (launch, splits, splits * self.width * 3)
            }
            Family::Tiled(t) => {
                let u = self.wgrad(l);
                let e = TiledEpilogue::WeightGradientPairs;
                let launch = t.gemm(gpu, &u, e, &b.y[l], below, partial);
                (launch, splits_for(2 * self.n), u.pbias_off)
            }
            Family::RowBlocked(d) => {
                let (launch, pbias_off) =
                    d.weight_gradient(gpu, l, self.n, &b.y[l], below, partial, true)?;
                (launch, SPLITS, pbias_off)
            }
        };
        self.launches.push(launch);
        self.reduce(reduce, &lay, splits, pbias_off);
        Ok(())
    }
}

#[cfg(test)]
mod uniform_layout {
    /// RorUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::RorUniforms,
            crate::shaders::SIREN_ROR,
            "Ror",
            [
                n_points,
                n_surface,
                width,
                w_out_off,
                b_out_off,
                w1_off,
                splits,
                pbias_off,
                w_surface,
                w_off_surface,
                w_normal,
                w_eikonal,
                alpha,
                inv_n,
                omega,
                w_sign,
                b1_off,
                first_rows
            ]
        );
    }
}
