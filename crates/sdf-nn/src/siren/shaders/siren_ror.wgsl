// The elementwise and per-point kernels of SIREN's reverse-over-reverse training step
// (`siren::ror`, where the math is). Per hidden layer l the step keeps three matrices of two
// streams per point, row stride 2·width: P_l = (Z_l, G_l then T_l), X_l = (A_l, Ḡ_l) and
// Y_l = (Z̄_l, H_l); X_0 = (x, ḡ) has row stride 6. D(z) = ω0 cos(ω0 z).
//
// ror_top:      last hidden layer L: G_L = w (the output weights) into P_L's second stream and
//               H_L = D(Z_L) ⊙ w into Y_L's.
// ror_head:     per point: Φ = w · A_L + b, ∇Φ = W_1ᵀ H_1 (the first layer's product of the
//               input-gradient chain, fan-in 3), the four loss terms (as `siren_head.wgsl`),
//               dL/dΦ / N into `dphi`, and (x, dL/d∇Φ / N) into X_0.
// ror_top_back: Z̄_L = D(Z_L) ⊙ (dL/dΦ w) + T_L into Y_L's first stream.
// ror_out_grad: split partials of the output layer's gradient w̄ = Σ_p dphi_p A_L[p] + Ḡ_L[p],
//               b̄ = Σ_p dphi_p, in the layout `reduce_wgrad` reads (M = 1).
// ror_first_wgrad: split partials of the first layer's weight gradient (fan-in 3) from the
//               stacked rows W̄_1 = [Z̄_1; H_1]ᵀ [x; ḡ], b̄_1 = Σ_p Z̄_1[p], one invocation per
//               (split, output feature), in the layout `reduce_wgrad` reads: a 3-column product
//               that the tiled GEMM would pad to 64 columns.
// ror_first_forward: the first layer's forward (fan-in 3), one invocation per (point, feature):
//               Z_1 = x W_1ᵀ + b_1 into P_1's first stream, A_1 = sin(ω0 Z_1) into X_1's.
// ror_first_grad_adjoint: the first layer's step of the input-gradient chain's adjoint (fan-in
//               3): H̄_1 = ḡ W_1ᵀ, Ḡ_1 = D(Z_1) ⊙ H̄_1 into X_1's second stream, and P_1's second
//               stream G_1 replaced by T_1 = D'(Z_1) ⊙ G_1 ⊙ H̄_1 (D'(z) = −ω0² sin(ω0 z)).
//               Both are what the tiled GEMM's modes 5 and 7 compute, without a 64-column tile
//               padded from 3 and its workgroup-memory staging: on an H100 those two products
//               took 41 µs each, twice an elementwise pass over the same rows (`ror_top`).

struct Ror {
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
    // The first layer's bias (ror_first_forward).
    b1_off: u32,
    // Stacked rows per split of ror_first_wgrad (even).
    first_rows: u32,
    _pad1: u32,
    _pad2: u32,
}

const WG: u32 = 256u;

@group(0) @binding(0) var<uniform> r: Ror;
@group(0) @binding(1) var<storage, read> params: array<f32>;
// ror_top: P_L (written); ror_top_back: P_L (read).
@group(0) @binding(2) var<storage, read_write> p_last: array<f32>;
// ror_top, ror_top_back: Y_L; ror_first_forward, ror_first_grad_adjoint: X_1 (and P_1 as
// `p_last`).
@group(0) @binding(3) var<storage, read_write> y_last: array<f32>;
// ror_head: X_L (A_L) and Y_1 (H_1); ror_out_grad: X_L.
@group(0) @binding(4) var<storage, read> x_last: array<f32>;
@group(0) @binding(5) var<storage, read> y_first: array<f32>;
// ror_head: the input streams (twelve floats per point, the point first), X_0, dL/dΦ / N and
// the loss sums per workgroup.
@group(0) @binding(6) var<storage, read> x_streams: array<f32>;
@group(0) @binding(7) var<storage, read> normals: array<f32>;
@group(0) @binding(8) var<storage, read_write> x0: array<f32>;
@group(0) @binding(9) var<storage, read_write> dphi: array<f32>;
@group(0) @binding(10) var<storage, read_write> loss_partial: array<f32>;
// ror_top_back, ror_out_grad: dL/dΦ / N.
@group(0) @binding(11) var<storage, read> dphi_in: array<f32>;
// ror_out_grad: the partials.
@group(0) @binding(12) var<storage, read_write> partial: array<f32>;


fn flat_id(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.y * nwg.x + wid.x) * WG + lid;
}

// Row o of the first layer's weights W_1 (fan-in 3).
fn w1_row(o: u32) -> vec3<f32> {
    let w = r.w1_off + 3u * o;
    return vec3<f32>(params[w], params[w + 1u], params[w + 2u]);
}

// x · W_1[o]: the first layer's product of one (point, feature), in one fma order for both
// kernels that take it.
fn w1_dot(x: vec3<f32>, o: u32) -> f32 {
    let w = w1_row(o);
    let z = x.x * w.x;
    return fma(x.z, w.z, fma(x.y, w.y, z));
}

// The (point, feature) an elementwise kernel's invocation owns, one per feature of every point
// (`Launch::flat` over n_points · width), and the element's index in a matrix of two streams
// per point (row stride 2·width, the first stream's); `valid` is false past the end.
struct Element {
    p: u32,
    o: u32,
    i: u32,
    valid: bool,
}

fn element(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> Element {
    let t = flat_id(wid, nwg, lid);
    let p = t / r.width;
    let o = t % r.width;
    return Element(p, o, 2u * p * r.width + o, t < r.n_points * r.width);
}

@compute @workgroup_size(256)
fn ror_top(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let e = element(wid, nwg, lid);
    if !e.valid {
        return;
    }
    let i = e.i;
    let w = params[r.w_out_off + e.o];
    p_last[i + r.width] = w;
    y_last[i + r.width] = r.omega * cos(r.omega * p_last[i]) * w;
}

@compute @workgroup_size(256)
fn ror_top_back(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let e = element(wid, nwg, lid);
    if !e.valid {
        return;
    }
    let i = e.i;
    let abar = dphi_in[e.p] * params[r.w_out_off + e.o];
    y_last[i] = r.omega * cos(r.omega * p_last[i]) * abar + p_last[i + r.width];
}

// Invocations per point in ror_head: 4 in the step's GPU layout (`SirenGpu::set_gpu_step_layout`),
// where lane j sums features j, j + 4, ..., so that one load instruction of a subgroup reads 4
// consecutive floats of each point's row, not one float from each of 32 rows 2·width apart (on
// an H100 the one-point-per-invocation head took 63 µs for 10⁴ points); 1 in the CPU layout,
// which lavapipe measured faster (18.4 against 24.6 ms).
override HEAD_LANES: u32 = 4u;
var<workgroup> head_red: array<vec4<f32>, LOSS_WG>;

@compute @workgroup_size(LOSS_WG)
fn ror_head(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let group = wid.y * nwg.x + wid.x;
    let per_group = LOSS_WG / HEAD_LANES;
    // Workgroup-uniform: the groups a folded 2D dispatch adds past the end write nothing.
    if group * per_group >= r.n_points {
        return;
    }
    let p = group * per_group + lid / HEAD_LANES;
    let lane = lid % HEAD_LANES;
    // (Σ w·A_L, Σ H_1 W_1) over this lane's features.
    var acc = vec4<f32>(0.0);
    if p < r.n_points {
        let row = 2u * p * r.width;
        for (var i = lane; i < r.width; i += HEAD_LANES) {
            let h = y_first[row + r.width + i];
            acc = vec4<f32>(
                fma(params[r.w_out_off + i], x_last[row + i], acc.x),
                fma(vec3<f32>(h), w1_row(i), acc.yzw),
            );
        }
    }
    head_red[lid] = acc;
    workgroupBarrier();
    var terms = vec4<f32>(0.0);
    if lane == 0u && p < r.n_points {
        var sum = head_red[lid];
        for (var j = 1u; j < HEAD_LANES; j++) {
            sum += head_red[lid + j];
        }
        let phi = params[r.b_out_off] + sum.x;
        let gr = sum.yzw;
        let on_surface = p < r.n_surface;
        // On the surface the normal, off it the known side in `.x`.
        let n = vec3<f32>(normals[3u * p], normals[3u * p + 1u], normals[3u * p + 2u]);
        let weights = vec4<f32>(r.w_surface, r.w_off_surface, r.w_normal, r.w_eikonal);
        let l = point_loss(phi, gr, on_surface, n, weights, r.alpha, r.w_sign);
        terms = l.terms;
        let d = l.dphi;
        let dg = l.dgrad;
        dphi[p] = d * r.inv_n;
        let xs = 12u * p;
        let o = 6u * p;
        x0[o] = x_streams[xs];
        x0[o + 1u] = x_streams[xs + 1u];
        x0[o + 2u] = x_streams[xs + 2u];
        x0[o + 3u] = dg.x * r.inv_n;
        x0[o + 4u] = dg.y * r.inv_n;
        x0[o + 5u] = dg.z * r.inv_n;
    }
    store_loss_sum(lid, terms * r.inv_n, group);
}

// One invocation per (split, column): columns 0..width are w̄, column `width` is b̄.
@compute @workgroup_size(256)
fn ror_out_grad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = flat_id(wid, nwg, lid);
    let cols = r.width + 1u;
    if t >= r.splits * cols {
        return;
    }
    let split = t / cols;
    let i = t % cols;
    var s = 0.0;
    if i < r.width {
        for (var p = split; p < r.n_points; p += r.splits) {
            let row = 2u * p * r.width;
            s += dphi_in[p] * x_last[row + i] + x_last[row + r.width + i];
        }
        partial[split * r.width + i] = s;
    } else {
        for (var p = split; p < r.n_points; p += r.splits) {
            s += dphi_in[p];
        }
        partial[r.pbias_off + split] = s;
    }
}

// One invocation per (split, output feature o): `r.splits` splits of `r.first_rows` stacked
// rows each (few, so that the width × splits invocations fill a GPU: a hidden layer's split-K
// GEMM has tiles to do that). Stacked row 2p is (Z̄_1[p], x[p]), row 2p + 1 is (H_1[p], ḡ[p]): Y_1's and X_0's
// rows as they lie (row strides `width` and 3).
@compute @workgroup_size(256)
fn ror_first_wgrad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = flat_id(wid, nwg, lid);
    let w = r.width;
    if t >= r.splits * w {
        return;
    }
    let split = t / w;
    let o = t % w;
    let first = split * r.first_rows;
    let end = min(first + r.first_rows, 2u * r.n_points);
    var g = vec3<f32>(0.0);
    var b = 0.0;
    // Rows in pairs (`first` is even): the bias takes the first of each.
    for (var row = first; row < end; row += 2u) {
        let zbar = y_first[row * w + o];
        let h = y_first[(row + 1u) * w + o];
        let q = 3u * row;
        g = fma(vec3<f32>(zbar), vec3<f32>(x0[q], x0[q + 1u], x0[q + 2u]), g);
        g = fma(vec3<f32>(h), vec3<f32>(x0[q + 3u], x0[q + 4u], x0[q + 5u]), g);
        b += zbar;
    }
    let base = split * w * 3u + o * 3u;
    partial[base] = g.x;
    partial[base + 1u] = g.y;
    partial[base + 2u] = g.z;
    partial[r.pbias_off + split * w + o] = b;
}

@compute @workgroup_size(256)
fn ror_first_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let e = element(wid, nwg, lid);
    if !e.valid {
        return;
    }
    let q = 12u * e.p;
    let x = vec3<f32>(x_streams[q], x_streams[q + 1u], x_streams[q + 2u]);
    let z = w1_dot(x, e.o) + params[r.b1_off + e.o];
    p_last[e.i] = z;
    y_last[e.i] = sin(r.omega * z);
}

@compute @workgroup_size(256)
fn ror_first_grad_adjoint(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let e = element(wid, nwg, lid);
    if !e.valid {
        return;
    }
    // ḡ of the point (X_0's second stream) times W_1[o].
    let q = 6u * e.p + 3u;
    let c = w1_dot(vec3<f32>(x0[q], x0[q + 1u], x0[q + 2u]), e.o);
    let i = e.i;
    let wz = r.omega * p_last[i];
    let g = p_last[i + r.width];
    y_last[i + r.width] = r.omega * cos(wz) * c;
    p_last[i + r.width] = -r.omega * r.omega * sin(wz) * g * c;
}
