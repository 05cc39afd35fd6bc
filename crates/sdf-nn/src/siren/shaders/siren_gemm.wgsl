// SIREN's matrix kernel and its elementwise companions: the general path (every layer shape,
// and the hidden layers on GPUs, `LayerKernels::Gemm`). On CPU adapters the hidden layers run on
// siren_dense.wgsl instead, which avoids the per-lane storage loads this kernel makes.
//
// gemm: C[m, n] = Σ_k A[m, k] B[k, n], one invocation per row m. The invocation copies its
// row of A, 256 values of k at a time, into a private array, then sweeps every column n,
// four at a time; the B values it reads depend only on (k, n), which are the same for every
// invocation.
//
// Operands are read through (offset, row stride, column stride), so one kernel does every
// product SIREN needs:
//   mode 0: C = A · B stored in out0 (forward Z = A_prev · Wᵀ, backward Ā = Z̄ · W)
//   mode 1: out0 = sin(ω0 (A · B + b)) (inference, value rows only)
//   mode 2: split-K weight gradient: partial[split] = Z̄ᵀ · A_prev over one chunk of batch rows,
//           plus the bias partial Σ Z̄[value rows] (rows k ≡ 0 mod 4).
//
// sine_forward / sine_backward: the per-(point, feature) epilogues of a sine layer whose rows
// come in groups of four (value, ∂/∂x, ∂/∂y, ∂/∂z).

struct Gemm {
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
    // How B is walked: 0 scalar loads; 1 contiguous along k (vec4 over k, dot products);
    // 2 contiguous along n (vec4 over n). A is loaded as vec4 when a_vec4 is 1.
    b_style: u32,
    a_vec4: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Elementwise {
    n_points: u32,
    width: u32,
    bias_off: u32,
    _pad0: u32,
    omega: f32,
    _pad1: f32,
    _pad2: f32,
    _pad3: f32,
}

const WG: u32 = 64u;
const KC: u32 = 256u;
const KC4: u32 = 64u;

@group(0) @binding(0) var<uniform> g: Gemm;
@group(0) @binding(1) var<storage, read> a_src: array<f32>;
@group(0) @binding(2) var<storage, read> b_src: array<f32>;
// Mode 1: the parameters (bias).
@group(0) @binding(3) var<storage, read> aux: array<f32>;
@group(0) @binding(4) var<storage, read_write> out0: array<f32>;
// The same buffers as a_src and b_src, seen as vec4 for aligned 16-byte loads.
@group(0) @binding(5) var<storage, read> a_src4: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> b_src4: array<vec4<f32>>;

@group(0) @binding(10) var<uniform> e: Elementwise;
@group(0) @binding(11) var<storage, read> params: array<f32>;
// sine_forward: pre-activations in (bias added in place) and activations out.
@group(0) @binding(12) var<storage, read_write> z: array<f32>;
@group(0) @binding(13) var<storage, read_write> act: array<f32>;
// sine_backward: Ā of the layer's outputs in, Z̄ of its pre-activations out (in place).
@group(0) @binding(14) var<storage, read_write> grad: array<f32>;
@group(0) @binding(15) var<storage, read> z_in: array<f32>;

fn b_at(k: u32, n: u32) -> f32 {
    if n < g.n {
        return b_src[g.b_off + k * g.b_rs + n * g.b_cs];
    }
    return 0.0;
}

@compute @workgroup_size(64)
fn gemm(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let m = (wid.y * nwg.x + wid.x) * WG + lid;
    if m >= g.m {
        return;
    }
    var k_begin = 0u;
    var k_end = g.k;
    var out_row = m * g.ldc;
    if g.mode == 2u {
        k_begin = wid.z * g.k_chunk;
        k_end = min(k_begin + g.k_chunk, g.k);
        out_row += wid.z * g.m * g.ldc;
    }
    // This row of A, KC values of k at a time; zero-padded to a multiple of 4.
    var arow: array<vec4<f32>, KC4>;
    var bsum = 0.0;
    let a_base = g.a_off + m * g.a_rs;
    for (var kc = k_begin; kc < k_end; kc += KC) {
        let kn = min(KC, k_end - kc);
        let kn4 = (kn + 3u) / 4u;
        if g.a_vec4 == 1u {
            let base4 = (a_base + kc) / 4u;
            for (var t = 0u; t < kn4; t++) {
                arow[t] = a_src4[base4 + t];
            }
        } else {
            for (var t = 0u; t < kn4; t++) {
                var v = vec4<f32>(0.0);
                for (var c = 0u; c < 4u; c++) {
                    if 4u * t + c < kn {
                        v[c] = a_src[a_base + (kc + 4u * t + c) * g.a_cs];
                    }
                }
                arow[t] = v;
            }
        }
        if g.mode == 2u {
            for (var t = 0u; t < kn4; t++) {
                bsum += arow[t].x;
            }
        }
        let first = kc == k_begin;
        let last = kc + KC >= k_end;
        for (var n = 0u; n < g.n; n += 4u) {
            var acc = vec4<f32>(0.0);
            if g.b_style == 1u {
                // B(k, n) = b[b_off + n * b_cs + k]: one dot product per column.
                for (var c = 0u; c < 4u; c++) {
                    if n + c < g.n {
                        var bb = (g.b_off + (n + c) * g.b_cs + kc) / 4u;
                        var d = vec4<f32>(0.0);
                        for (var t = 0u; t < kn4; t++) {
                            d = fma(arow[t], b_src4[bb + t], d);
                        }
                        acc[c] = d.x + d.y + d.z + d.w;
                    }
                }
            } else if g.b_style == 2u && n + 4u <= g.n {
                // B(k, n..n+3) = one vec4.
                var bb = (g.b_off + kc * g.b_rs + n) / 4u;
                let step = g.b_rs / 4u;
                for (var t = 0u; t < kn4; t++) {
                    let a = arow[t];
                    acc = fma(vec4<f32>(a.x), b_src4[bb], acc);
                    acc = fma(vec4<f32>(a.y), b_src4[bb + step], acc);
                    acc = fma(vec4<f32>(a.z), b_src4[bb + 2u * step], acc);
                    acc = fma(vec4<f32>(a.w), b_src4[bb + 3u * step], acc);
                    bb += 4u * step;
                }
            } else {
                for (var t = 0u; t < kn; t++) {
                    let k = kc + t;
                    let a = arow[t / 4u][t % 4u];
                    acc = fma(vec4<f32>(a), vec4<f32>(b_at(k, n), b_at(k, n + 1u), b_at(k, n + 2u), b_at(k, n + 3u)), acc);
                }
            }
            for (var c = 0u; c < 4u; c++) {
                let nc = n + c;
                if nc < g.n {
                    var x = acc[c];
                    if !first {
                        x += out0[out_row + nc];
                    }
                    if last && g.mode == 1u {
                        x = sin(g.omega * (x + aux[g.bias_off + nc]));
                    }
                    out0[out_row + nc] = x;
                }
            }
        }
    }
    if g.mode == 2u {
        out0[g.pbias_off + wid.z * g.m + m] = bsum;
    }
}

@compute @workgroup_size(256)
fn sine_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = (wid.y * nwg.x + wid.x) * 256u + lid;
    if t >= e.n_points * e.width {
        return;
    }
    let p = t / e.width;
    let o = t % e.width;
    let i0 = 4u * p * e.width + o;
    let i1 = i0 + e.width;
    let i2 = i1 + e.width;
    let i3 = i2 + e.width;
    let zv = z[i0] + params[e.bias_off + o];
    z[i0] = zv;
    let w0 = e.omega;
    let wc = w0 * cos(w0 * zv);
    act[i0] = sin(w0 * zv);
    act[i1] = wc * z[i1];
    act[i2] = wc * z[i2];
    act[i3] = wc * z[i3];
}

@compute @workgroup_size(256)
fn sine_backward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = (wid.y * nwg.x + wid.x) * 256u + lid;
    if t >= e.n_points * e.width {
        return;
    }
    let p = t / e.width;
    let o = t % e.width;
    let i0 = 4u * p * e.width + o;
    let i1 = i0 + e.width;
    let i2 = i1 + e.width;
    let i3 = i2 + e.width;
    // z̄_j = ω0 cos · t̄_j,  z̄_v = ω0 cos · h̄ − ω0² sin · Σ_j t̄_j z_j.
    let w0 = e.omega;
    let zv = z_in[i0];
    let s = sin(w0 * zv);
    let wc = w0 * cos(w0 * zv);
    let a = vec4<f32>(grad[i0], grad[i1], grad[i2], grad[i3]);
    let mix = a.y * z_in[i1] + a.z * z_in[i2] + a.w * z_in[i3];
    grad[i0] = wc * a.x - w0 * w0 * s * mix;
    grad[i1] = wc * a.y;
    grad[i2] = wc * a.z;
    grad[i3] = wc * a.w;
}
