// SIREN's hidden layers as row-blocked kernels with the weights in a uniform buffer.
//
// Every invocation owns four consecutive rows (with tangents: one point's value row and its
// three tangent rows), so each weight it loads feeds four FMAs. The weights come from a uniform
// buffer window of at most 16 KiB: on lavapipe a storage load is a per-lane loop with bounds
// checks, while a uniform load is a plain gather, which made this layout ~20x faster than a
// storage-buffer GEMM there. The reduction loops have trip counts fixed by override constants,
// so the compiler unrolls them and the private row arrays are indexed with constants
// (dynamically indexed private arrays become per-lane gathers on lavapipe).
//
// dense_fwd:   out[r, o] = Σ_i a[r, i] W[o, i] over one window of outputs; W rows in `w`.
//              mode 1 applies the inference epilogue sin(ω0 (z + b)); mode 2 (four rows per
//              point) adds the bias to `out` and writes the activations and their tangents
//              to `act_out`.
// dense_bwd:   out[r, k] (+)= Σ_n a[r, n] W[n, k] over one window of n; W rows in `w`.
//              mode bit 0 accumulates into `out` (windows after the first); bit 1 (the last
//              window) turns Ā into Z̄ of the layer below through its sine (`z_in`).
// first_fwd:   the first layer (fan-in 3) straight from the points: with tangents (mode 2)
//              the tangent rows of its pre-activations are the columns of W, so it needs no
//              GEMM; W ([fan_out, 3]) is read from `w` as floats.
// first_wgrad: the first layer's weight-gradient partials, W̄[o, j] = Σ_p z̄_v[p, o] x_pj +
//              z̄_j[p, o] (the tangent rows' inputs are unit vectors) and b̄[o] = Σ_p z̄_v[p, o].
// dense_wgrad: per-invocation partial sums of W̄[n, k] = Σ_r z̄[r, n] x[r, k] (and of the bias
//              gradient Σ over value rows of z̄[r, n]) over a strided subset of the points, for
//              one 16 × 16 tile; `reduce_wgrad` in siren_train.wgsl sums the partials. A point
//              owns ROWS_PER_POINT rows (4 with tangents, 2 in the reverse-over-reverse step),
//              the first its value row.
//
// The reverse-over-reverse step (`siren::ror`; one row per point, four points per invocation;
// every matrix with row stride out_stride4 and its own first vec4 column; D(z) = ω0 cos(ω0 z),
// D'(z) = −ω0² sin(ω0 z)):
//   dense_fwd / first_fwd mode 3: z = C + b → out, sin(ω0 z) → act_out (at out1_first4).
//   dense_fwd / first_fwd mode 4: C = H̄; D(z) ⊙ H̄ → out; act_out holds z (z_first4) and G
//                                 (out1_first4), G replaced by D'(z) ⊙ G ⊙ H̄.
//   first_fwd modes 3 and 4 read three floats per point at a_first4 + a_stride4 · point
//   (floats, not vec4s, here).
//   dense_bwd bit 2 (last window): C = G → act_out (out1_first4), D(z) ⊙ G → out, z from
//                                  act_out (z_first4).
//   dense_bwd bit 3 (last window): C = Ā; D(z) ⊙ Ā + T → out, z and T from z_in (z_first4,
//                                  t_first4).
//   first_wgrad_pairs: the first layer's partials over the stacked rows (Z̄_1, H_1) of each
//                      point against (x, ḡ) (six floats per point in `points`).
// Those epilogues are compiled only into pipelines made with ROR = 1: the inference and
// tangent-step pipelines (ROR = 0) keep the code, and the speed, they had without them.

struct Dense {
    rows: u32,
    // vec4 stride of a row of `a` and the first vec4 column read.
    a_stride4: u32,
    a_first4: u32,
    // vec4 stride of a row of `out` and the first vec4 column written.
    out_stride4: u32,
    out_first4: u32,
    mode: u32,
    bias_off: u32,
    omega: f32,
    // Reverse-over-reverse epilogues: first vec4 columns of the auxiliary matrices.
    out1_first4: u32,
    z_first4: u32,
    t_first4: u32,
    _pad: u32,
}

struct Wgrad {
    // Points (four rows each).
    points: u32,
    // Invocations per tile: each sums the points p ≡ split (mod splits).
    splits: u32,
    // vec4 strides of z̄ rows (fan_out / 4) and x rows (fan_in / 4).
    z_stride4: u32,
    x_stride4: u32,
    // Tiles along k (fan_in / (4 TK4)).
    tiles_k: u32,
    fan_out: u32,
    fan_in: u32,
    pbias_off: u32,
}

// Reduction length / 4 of one launch (≤ MAX4) and output vec4s of one launch.
override RED4: u32 = 16u;
override OUT4: u32 = 16u;
// 1: the pipeline runs the reverse-over-reverse epilogues (modes 3 and 4 of dense_fwd and
// first_fwd, bits 2 and 3 of dense_bwd); 0: they are compiled out.
override ROR: u32 = 0u;
// Rows per point of dense_wgrad: 4 with tangents, 2 in the reverse-over-reverse step. A constant
// so that the loop over them unrolls.
override ROWS_PER_POINT: u32 = 4u;
const MAX4: u32 = 64u;
const WG: u32 = 64u;

@group(0) @binding(0) var<uniform> d: Dense;
@group(0) @binding(1) var<storage, read> a: array<vec4<f32>>;
@group(0) @binding(2) var<uniform> w: array<vec4<f32>, 1024>;
@group(0) @binding(3) var<storage, read_write> out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> params: array<f32>;
// dense_fwd mode 2: the activations (value and tangent rows) next to the pre-activations.
@group(0) @binding(10) var<storage, read_write> act_out: array<vec4<f32>>;
// dense_bwd with the sine epilogue: the pre-activations of the layer below.
@group(0) @binding(11) var<storage, read> z_in: array<vec4<f32>>;

@group(0) @binding(5) var<uniform> g: Wgrad;
@group(0) @binding(6) var<storage, read> zbar: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> x: array<vec4<f32>>;
// Weight partials, then from `pbias_off` (a multiple of 4) the bias partials.
@group(0) @binding(8) var<storage, read_write> partial: array<vec4<f32>>;
// first_fwd: the input points (three floats per row, or twelve per point with tangents);
// first_wgrad: the training input streams (twelve floats per point) and the partials as
// floats.
@group(0) @binding(12) var<storage, read> points: array<f32>;
@group(0) @binding(13) var<storage, read_write> partial_f: array<f32>;

// Row r of `a` into `row`: RED4 vec4s from column a_first4. Rows past the end repeat the last
// one; their results are not stored.
fn load_row(r: u32, row: ptr<function, array<vec4<f32>, MAX4>>) {
    let b = min(r, d.rows - 1u) * d.a_stride4 + d.a_first4;
    for (var j = 0u; j < RED4; j++) {
        (*row)[j] = a[b + j];
    }
}

// The reverse-over-reverse epilogue (modes 3 and 4) of row r at output vec4 column o4.
fn ror_fwd_row(r: u32, o4: u32, acc: vec4<f32>) {
    if r >= d.rows {
        return;
    }
    let w0 = d.omega;
    let row = r * d.out_stride4 + o4;
    if d.mode == 3u {
        let o = d.bias_off + 4u * o4;
        let z = acc + vec4<f32>(params[o], params[o + 1u], params[o + 2u], params[o + 3u]);
        out[row + d.out_first4] = z;
        act_out[row + d.out1_first4] = sin(w0 * z);
    } else {
        let z = act_out[row + d.z_first4];
        let g = act_out[row + d.out1_first4];
        out[row + d.out_first4] = w0 * cos(w0 * z) * acc;
        act_out[row + d.out1_first4] = -w0 * w0 * sin(w0 * z) * g * acc;
    }
}

@compute @workgroup_size(64)
fn dense_fwd(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r0 = 4u * ((wid.y * nwg.x + wid.x) * WG + lid);
    if r0 >= d.rows {
        return;
    }
    var x0: array<vec4<f32>, MAX4>;
    var x1: array<vec4<f32>, MAX4>;
    var x2: array<vec4<f32>, MAX4>;
    var x3: array<vec4<f32>, MAX4>;
    load_row(r0, &x0);
    load_row(r0 + 1u, &x1);
    load_row(r0 + 2u, &x2);
    load_row(r0 + 3u, &x3);
    for (var o4 = 0u; o4 < OUT4; o4++) {
        var acc0 = vec4<f32>(0.0);
        var acc1 = vec4<f32>(0.0);
        var acc2 = vec4<f32>(0.0);
        var acc3 = vec4<f32>(0.0);
        for (var c = 0u; c < 4u; c++) {
            let wb = (4u * o4 + c) * RED4;
            var s0 = vec4<f32>(0.0);
            var s1 = vec4<f32>(0.0);
            var s2 = vec4<f32>(0.0);
            var s3 = vec4<f32>(0.0);
            for (var j = 0u; j < RED4; j++) {
                let wv = w[wb + j];
                s0 = fma(x0[j], wv, s0);
                s1 = fma(x1[j], wv, s1);
                s2 = fma(x2[j], wv, s2);
                s3 = fma(x3[j], wv, s3);
            }
            acc0[c] = s0.x + s0.y + s0.z + s0.w;
            acc1[c] = s1.x + s1.y + s1.z + s1.w;
            acc2[c] = s2.x + s2.y + s2.z + s2.w;
            acc3[c] = s3.x + s3.y + s3.z + s3.w;
        }
        if ROR != 0u && d.mode >= 3u {
            ror_fwd_row(r0, o4, acc0);
            ror_fwd_row(r0 + 1u, o4, acc1);
            ror_fwd_row(r0 + 2u, o4, acc2);
            ror_fwd_row(r0 + 3u, o4, acc3);
            continue;
        }
        let ob = r0 * d.out_stride4 + d.out_first4 + o4;
        if d.mode != 0u {
            let o = d.bias_off + 4u * o4;
            let b = vec4<f32>(params[o], params[o + 1u], params[o + 2u], params[o + 3u]);
            if d.mode == 1u {
                acc0 = sin(d.omega * (acc0 + b));
                acc1 = sin(d.omega * (acc1 + b));
                acc2 = sin(d.omega * (acc2 + b));
                acc3 = sin(d.omega * (acc3 + b));
            } else {
                // z = (value, ∂x, ∂y, ∂z) rows; a = sin(ω0 z_v), a_j = ω0 cos(ω0 z_v) z_j.
                let os = d.out_stride4;
                acc0 += b;
                let wc = d.omega * cos(d.omega * acc0);
                out[ob] = acc0;
                out[ob + os] = acc1;
                out[ob + 2u * os] = acc2;
                out[ob + 3u * os] = acc3;
                act_out[ob] = sin(d.omega * acc0);
                act_out[ob + os] = wc * acc1;
                act_out[ob + 2u * os] = wc * acc2;
                act_out[ob + 3u * os] = wc * acc3;
                continue;
            }
        }
        out[ob] = acc0;
        if r0 + 1u < d.rows {
            out[ob + d.out_stride4] = acc1;
        }
        if r0 + 2u < d.rows {
            out[ob + 2u * d.out_stride4] = acc2;
        }
        if r0 + 3u < d.rows {
            out[ob + 3u * d.out_stride4] = acc3;
        }
    }
}

// The reverse-over-reverse epilogues of dense_bwd (mode bits 2 and 3) of row r.
fn ror_bwd_row(r: u32, o4: u32, acc: vec4<f32>) {
    if r >= d.rows {
        return;
    }
    let w0 = d.omega;
    let row = r * d.out_stride4 + o4;
    if (d.mode & 4u) != 0u {
        let z = act_out[row + d.z_first4];
        act_out[row + d.out1_first4] = acc;
        out[row + d.out_first4] = w0 * cos(w0 * z) * acc;
    } else {
        let z = z_in[row + d.z_first4];
        out[row + d.out_first4] = w0 * cos(w0 * z) * acc + z_in[row + d.t_first4];
    }
}

@compute @workgroup_size(64)
fn dense_bwd(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r0 = 4u * ((wid.y * nwg.x + wid.x) * WG + lid);
    if r0 >= d.rows {
        return;
    }
    var z0: array<vec4<f32>, MAX4>;
    var z1: array<vec4<f32>, MAX4>;
    var z2: array<vec4<f32>, MAX4>;
    var z3: array<vec4<f32>, MAX4>;
    load_row(r0, &z0);
    load_row(r0 + 1u, &z1);
    load_row(r0 + 2u, &z2);
    load_row(r0 + 3u, &z3);
    let os = d.out_stride4;
    for (var o4 = 0u; o4 < OUT4; o4++) {
        let ob = r0 * os + d.out_first4 + o4;
        var acc0 = vec4<f32>(0.0);
        var acc1 = vec4<f32>(0.0);
        var acc2 = vec4<f32>(0.0);
        var acc3 = vec4<f32>(0.0);
        for (var j = 0u; j < RED4; j++) {
            for (var c = 0u; c < 4u; c++) {
                let wv = w[(4u * j + c) * OUT4 + o4];
                acc0 = fma(vec4<f32>(z0[j][c]), wv, acc0);
                acc1 = fma(vec4<f32>(z1[j][c]), wv, acc1);
                acc2 = fma(vec4<f32>(z2[j][c]), wv, acc2);
                acc3 = fma(vec4<f32>(z3[j][c]), wv, acc3);
            }
        }
        let add = (d.mode & 1u) != 0u;
        if ROR != 0u && (d.mode & 12u) != 0u {
            if add {
                acc0 += out[ob];
                if r0 + 1u < d.rows {
                    acc1 += out[ob + os];
                }
                if r0 + 2u < d.rows {
                    acc2 += out[ob + 2u * os];
                }
                if r0 + 3u < d.rows {
                    acc3 += out[ob + 3u * os];
                }
            }
            ror_bwd_row(r0, o4, acc0);
            ror_bwd_row(r0 + 1u, o4, acc1);
            ror_bwd_row(r0 + 2u, o4, acc2);
            ror_bwd_row(r0 + 3u, o4, acc3);
            continue;
        }
        if (d.mode & 2u) != 0u {
            // Four rows per point: t̄ = (h̄, t̄x, t̄y, t̄z) of the activations below become
            // z̄_j = ω0 cos · t̄_j and z̄_v = ω0 cos · h̄ − ω0² sin · Σ_j t̄_j z_j.
            if add {
                acc0 += out[ob];
                acc1 += out[ob + os];
                acc2 += out[ob + 2u * os];
                acc3 += out[ob + 3u * os];
            }
            let w0 = d.omega;
            let zv = z_in[ob];
            let s = sin(w0 * zv);
            let wc = w0 * cos(w0 * zv);
            let mix = acc1 * z_in[ob + os] + acc2 * z_in[ob + 2u * os] + acc3 * z_in[ob + 3u * os];
            out[ob] = wc * acc0 - w0 * w0 * s * mix;
            out[ob + os] = wc * acc1;
            out[ob + 2u * os] = wc * acc2;
            out[ob + 3u * os] = wc * acc3;
            continue;
        }
        if add {
            acc0 += out[ob];
        }
        out[ob] = acc0;
        if r0 + 1u < d.rows {
            if add {
                acc1 += out[ob + os];
            }
            out[ob + os] = acc1;
        }
        if r0 + 2u < d.rows {
            if add {
                acc2 += out[ob + 2u * os];
            }
            out[ob + 2u * os] = acc2;
        }
        if r0 + 3u < d.rows {
            if add {
                acc3 += out[ob + 3u * os];
            }
            out[ob + 3u * os] = acc3;
        }
    }
}

// Column c of outer(z, x) is x · z[c]: the products of output n = c with the four inputs k.
fn outer(z: vec4<f32>, x: vec4<f32>) -> mat4x4<f32> {
    return mat4x4<f32>(x * z.x, x * z.y, x * z.z, x * z.w);
}

// Tiles are 16 outputs n by 16 inputs k; four rows per point, the first the value row. The
// sixteen 4 × 4 blocks of the tile are named variables, not an array, so nothing depends on
// the compiler unrolling loops.
@compute @workgroup_size(64)
fn dense_wgrad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let split = wid.x * WG + lid;
    if split >= g.splits {
        return;
    }
    let tile = wid.y;
    let tn4 = (tile / g.tiles_k) * 4u;
    let tk4 = (tile % g.tiles_k) * 4u;
    var a00 = mat4x4<f32>();
    var a01 = mat4x4<f32>();
    var a02 = mat4x4<f32>();
    var a03 = mat4x4<f32>();
    var a10 = mat4x4<f32>();
    var a11 = mat4x4<f32>();
    var a12 = mat4x4<f32>();
    var a13 = mat4x4<f32>();
    var a20 = mat4x4<f32>();
    var a21 = mat4x4<f32>();
    var a22 = mat4x4<f32>();
    var a23 = mat4x4<f32>();
    var a30 = mat4x4<f32>();
    var a31 = mat4x4<f32>();
    var a32 = mat4x4<f32>();
    var a33 = mat4x4<f32>();
    var bias = mat4x4<f32>();
    for (var p = split; p < g.points; p += g.splits) {
        for (var t = 0u; t < ROWS_PER_POINT; t++) {
            let r = ROWS_PER_POINT * p + t;
            let zb = r * g.z_stride4 + tn4;
            let xb = r * g.x_stride4 + tk4;
            let z0 = zbar[zb];
            let z1 = zbar[zb + 1u];
            let z2 = zbar[zb + 2u];
            let z3 = zbar[zb + 3u];
            let x0 = x[xb];
            let x1 = x[xb + 1u];
            let x2 = x[xb + 2u];
            let x3 = x[xb + 3u];
            if t == 0u {
                bias += mat4x4<f32>(z0, z1, z2, z3);
            }
            a00 += outer(z0, x0);
            a01 += outer(z0, x1);
            a02 += outer(z0, x2);
            a03 += outer(z0, x3);
            a10 += outer(z1, x0);
            a11 += outer(z1, x1);
            a12 += outer(z1, x2);
            a13 += outer(z1, x3);
            a20 += outer(z2, x0);
            a21 += outer(z2, x1);
            a22 += outer(z2, x2);
            a23 += outer(z2, x3);
            a30 += outer(z3, x0);
            a31 += outer(z3, x1);
            a32 += outer(z3, x2);
            a33 += outer(z3, x3);
        }
    }
    // partial[split][n][k], row-major over the whole layer as reduce_wgrad expects.
    let row4 = g.x_stride4;
    let base = split * g.fan_out * row4 + (4u * tn4) * row4 + tk4;
    store_block(base, row4, 0u, a00, a01, a02, a03);
    store_block(base, row4, 4u, a10, a11, a12, a13);
    store_block(base, row4, 8u, a20, a21, a22, a23);
    store_block(base, row4, 12u, a30, a31, a32, a33);
    if tk4 == 0u {
        let pb = (g.pbias_off + split * g.fan_out) / 4u + tn4;
        partial[pb] = bias[0];
        partial[pb + 1u] = bias[1];
        partial[pb + 2u] = bias[2];
        partial[pb + 3u] = bias[3];
    }
}

// Rows n0..n0+3 of the tile (one z vec4) against its four k vec4s.
fn store_block(
    base: u32,
    row4: u32,
    n0: u32,
    b0: mat4x4<f32>,
    b1: mat4x4<f32>,
    b2: mat4x4<f32>,
    b3: mat4x4<f32>,
) {
    for (var c = 0u; c < 4u; c++) {
        let o = base + (n0 + c) * row4;
        partial[o] = b0[c];
        partial[o + 1u] = b1[c];
        partial[o + 2u] = b2[c];
        partial[o + 3u] = b3[c];
    }
}

fn w_scalar(i: u32) -> f32 {
    return w[i / 4u][i % 4u];
}

// Modes as dense_fwd: 1 inference (one row per point, four points per invocation), 2 four
// rows per point (one point per invocation). OUT4 = fan_out / 4.
@compute @workgroup_size(64)
fn first_fwd(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let lane = (wid.y * nwg.x + wid.x) * WG + lid;
    let os = d.out_stride4;
    if ROR != 0u && d.mode >= 3u {
        // Four points, three floats each at a_first4 + a_stride4 · point (floats).
        let r0 = 4u * lane;
        if r0 >= d.rows {
            return;
        }
        let last = d.rows - 1u;
        let q0 = d.a_first4 + d.a_stride4 * r0;
        let q1 = d.a_first4 + d.a_stride4 * min(r0 + 1u, last);
        let q2 = d.a_first4 + d.a_stride4 * min(r0 + 2u, last);
        let q3 = d.a_first4 + d.a_stride4 * min(r0 + 3u, last);
        let p0 = vec3<f32>(points[q0], points[q0 + 1u], points[q0 + 2u]);
        let p1 = vec3<f32>(points[q1], points[q1 + 1u], points[q1 + 2u]);
        let p2 = vec3<f32>(points[q2], points[q2 + 1u], points[q2 + 2u]);
        let p3 = vec3<f32>(points[q3], points[q3 + 1u], points[q3 + 2u]);
        for (var o4 = 0u; o4 < OUT4; o4++) {
            var z0: vec4<f32>;
            var z1: vec4<f32>;
            var z2: vec4<f32>;
            var z3: vec4<f32>;
            for (var c = 0u; c < 4u; c++) {
                let wo = 3u * (4u * o4 + c);
                let wr = vec3<f32>(w_scalar(wo), w_scalar(wo + 1u), w_scalar(wo + 2u));
                z0[c] = dot(wr, p0);
                z1[c] = dot(wr, p1);
                z2[c] = dot(wr, p2);
                z3[c] = dot(wr, p3);
            }
            ror_fwd_row(r0, o4, z0);
            ror_fwd_row(r0 + 1u, o4, z1);
            ror_fwd_row(r0 + 2u, o4, z2);
            ror_fwd_row(r0 + 3u, o4, z3);
        }
        return;
    }
    if d.mode == 2u {
        let r0 = 4u * lane;
        if r0 >= d.rows {
            return;
        }
        let pb = 12u * lane;
        let p = vec3<f32>(points[pb], points[pb + 1u], points[pb + 2u]);
        for (var o4 = 0u; o4 < OUT4; o4++) {
            var zv: vec4<f32>;
            var zx: vec4<f32>;
            var zy: vec4<f32>;
            var zz: vec4<f32>;
            for (var c = 0u; c < 4u; c++) {
                let wo = 3u * (4u * o4 + c);
                let wr = vec3<f32>(w_scalar(wo), w_scalar(wo + 1u), w_scalar(wo + 2u));
                zv[c] = dot(wr, p) + params[d.bias_off + 4u * o4 + c];
                zx[c] = wr.x;
                zy[c] = wr.y;
                zz[c] = wr.z;
            }
            let ob = r0 * os + o4;
            let wc = d.omega * cos(d.omega * zv);
            out[ob] = zv;
            out[ob + os] = zx;
            out[ob + 2u * os] = zy;
            out[ob + 3u * os] = zz;
            act_out[ob] = sin(d.omega * zv);
            act_out[ob + os] = wc * zx;
            act_out[ob + 2u * os] = wc * zy;
            act_out[ob + 3u * os] = wc * zz;
        }
        return;
    }
    let r0 = 4u * lane;
    if r0 >= d.rows {
        return;
    }
    let last = d.rows - 1u;
    let q0 = 3u * r0;
    let q1 = 3u * min(r0 + 1u, last);
    let q2 = 3u * min(r0 + 2u, last);
    let q3 = 3u * min(r0 + 3u, last);
    let p0 = vec3<f32>(points[q0], points[q0 + 1u], points[q0 + 2u]);
    let p1 = vec3<f32>(points[q1], points[q1 + 1u], points[q1 + 2u]);
    let p2 = vec3<f32>(points[q2], points[q2 + 1u], points[q2 + 2u]);
    let p3 = vec3<f32>(points[q3], points[q3 + 1u], points[q3 + 2u]);
    for (var o4 = 0u; o4 < OUT4; o4++) {
        var z0: vec4<f32>;
        var z1: vec4<f32>;
        var z2: vec4<f32>;
        var z3: vec4<f32>;
        for (var c = 0u; c < 4u; c++) {
            let wo = 3u * (4u * o4 + c);
            let wr = vec3<f32>(w_scalar(wo), w_scalar(wo + 1u), w_scalar(wo + 2u));
            let b = params[d.bias_off + 4u * o4 + c];
            z0[c] = dot(wr, p0) + b;
            z1[c] = dot(wr, p1) + b;
            z2[c] = dot(wr, p2) + b;
            z3[c] = dot(wr, p3) + b;
        }
        let ob = r0 * os + o4;
        out[ob] = sin(d.omega * z0);
        if r0 + 1u < d.rows {
            out[ob + os] = sin(d.omega * z1);
        }
        if r0 + 2u < d.rows {
            out[ob + 2u * os] = sin(d.omega * z2);
        }
        if r0 + 3u < d.rows {
            out[ob + 3u * os] = sin(d.omega * z3);
        }
    }
}

// The first layer's weight-gradient partials of one split for the 16 outputs from 4 tn4:
// partials [split][o][3] (gx, gy, gz along x, y, z), then [split][o] bias partials (gb) from
// pbias_off.
fn store_first_partials(
    split: u32,
    tn4: u32,
    gx: mat4x4<f32>,
    gy: mat4x4<f32>,
    gz: mat4x4<f32>,
    gb: mat4x4<f32>,
) {
    let m = g.fan_out;
    for (var j = 0u; j < 4u; j++) {
        for (var c = 0u; c < 4u; c++) {
            let o = 4u * (tn4 + j) + c;
            let q = 3u * (split * m + o);
            partial_f[q] = gx[j][c];
            partial_f[q + 1u] = gy[j][c];
            partial_f[q + 2u] = gz[j][c];
            partial_f[g.pbias_off + split * m + o] = gb[j][c];
        }
    }
}

// Tiles of 16 outputs (wid.y); z_stride4 = fan_out / 4; partials [split][o][3], then
// [split][o] bias partials from pbias_off.
@compute @workgroup_size(64)
fn first_wgrad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let split = wid.x * WG + lid;
    if split >= g.splits {
        return;
    }
    let tn4 = wid.y * 4u;
    var gx = mat4x4<f32>();
    var gy = mat4x4<f32>();
    var gz = mat4x4<f32>();
    var gb = mat4x4<f32>();
    let zs = g.z_stride4;
    for (var p = split; p < g.points; p += g.splits) {
        let pb = 12u * p;
        let x = vec3<f32>(points[pb], points[pb + 1u], points[pb + 2u]);
        let r = 4u * p * zs + tn4;
        for (var j = 0u; j < 4u; j++) {
            let zv = zbar[r + j];
            gx[j] += zv * x.x + zbar[r + zs + j];
            gy[j] += zv * x.y + zbar[r + 2u * zs + j];
            gz[j] += zv * x.z + zbar[r + 3u * zs + j];
            gb[j] += zv;
        }
    }
    store_first_partials(split, tn4, gx, gy, gz, gb);
}

// Tiles of 16 outputs (wid.y); zbar rows (Z̄_1, H_1) per point with z_stride4 = fan_out / 4;
// `points` holds (x, ḡ) per point; partials [split][o][3], then [split][o] bias partials from
// pbias_off.
@compute @workgroup_size(64)
fn first_wgrad_pairs(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let split = wid.x * WG + lid;
    if split >= g.splits {
        return;
    }
    let tn4 = wid.y * 4u;
    var gx = mat4x4<f32>();
    var gy = mat4x4<f32>();
    var gz = mat4x4<f32>();
    var gb = mat4x4<f32>();
    let zs = g.z_stride4;
    for (var p = split; p < g.points; p += g.splits) {
        let pb = 6u * p;
        let x = vec3<f32>(points[pb], points[pb + 1u], points[pb + 2u]);
        let gbar = vec3<f32>(points[pb + 3u], points[pb + 4u], points[pb + 5u]);
        let r = 2u * p * zs + tn4;
        for (var j = 0u; j < 4u; j++) {
            let zv = zbar[r + j];
            let h = zbar[r + zs + j];
            gx[j] += zv * x.x + h * gbar.x;
            gy[j] += zv * x.y + h * gbar.y;
            gz[j] += zv * x.z + h * gbar.z;
            gb[j] += zv;
        }
    }
    store_first_partials(split, tn4, gx, gy, gz, gb);
}
