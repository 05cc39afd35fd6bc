// SIREN's one matrix kernel: C[m, n] = Σ_k A[m, k] B[k, n] on 64×64 output tiles, 16-deep K
// tiles staged in workgroup memory, 4×4 register blocks per invocation, with a per-mode epilogue.
// Operands are read through (offset, row stride, column stride), so the same code does every
// product SIREN needs:
//
// mode 0, forward:  Z = A_prev · Wᵀ, then out1 = sin(ω0 (Z + b)) (and the tangents)
// mode 1, backward: Ā = Z̄ · W, then out0 = Z̄_prev from Ā and the previous pre-activations (aux)
// mode 2, weights:  W̄ partial[split] = Z̄ᵀ · A_prev over one K chunk (split-K, no atomics), plus
//                   the bias partial Σ Z̄[value rows] in the workgroups of column tile 0.
//
// With `tangents` set, activation rows come in groups of four per point: the value and its
// derivatives along x, y, z. An invocation's four rows are one such group, so every epilogue
// (which mixes the value and the tangents) stays in registers.

struct Gemm {
    mode: u32,
    m: u32,
    n: u32,
    k: u32,
    a_off: u32,
    a_rs: u32,
    a_cs: u32,
    // 1 when A is contiguous along k (then tile loads walk k fastest).
    a_kcontig: u32,
    b_off: u32,
    b_rs: u32,
    b_cs: u32,
    // 1 when B is contiguous along k.
    b_kcontig: u32,
    ldc: u32,
    bias_off: u32,
    tangents: u32,
    store_z: u32,
    k_chunk: u32,
    pbias_off: u32,
    omega: f32,
    _pad: u32,
}

const BM: u32 = 64u;
const BN: u32 = 64u;
const BK: u32 = 16u;

@group(0) @binding(0) var<uniform> g: Gemm;
@group(0) @binding(1) var<storage, read> a_src: array<f32>;
@group(0) @binding(2) var<storage, read> b_src: array<f32>;
// Mode 0: the parameters (bias). Mode 1: the previous layer's pre-activations.
@group(0) @binding(3) var<storage, read> aux: array<f32>;
// Mode 0: pre-activations Z. Mode 1: Z̄ of the previous layer. Mode 2: partials.
@group(0) @binding(4) var<storage, read_write> out0: array<f32>;
// Mode 0: activations.
@group(0) @binding(5) var<storage, read_write> out1: array<f32>;

// As[k][m] and Bs[k][permuted n]: an invocation reads its 4 rows and its 4 columns
// (n = tn + 16 c) as consecutive words.
var<workgroup> As: array<f32, 1024>;
var<workgroup> Bs: array<f32, 1024>;

@compute @workgroup_size(256)
fn gemm(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let tile_n = wid.x * BN;
    let tile_m = wid.y * BM;
    let tm = lid / 16u;
    let tn = lid % 16u;

    var k_begin = 0u;
    var k_end = g.k;
    if g.mode == 2u {
        k_begin = wid.z * g.k_chunk;
        k_end = min(k_begin + g.k_chunk, g.k);
    }

    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);

    for (var k0 = k_begin; k0 < k_end; k0 += BK) {
        for (var q = 0u; q < 4u; q++) {
            let idx = lid + 256u * q;
            var ml: u32;
            var kl: u32;
            if g.a_kcontig == 1u {
                ml = idx / BK;
                kl = idx % BK;
            } else {
                ml = idx % BM;
                kl = idx / BM;
            }
            let m = tile_m + ml;
            let k = k0 + kl;
            var v = 0.0;
            if m < g.m && k < k_end {
                v = a_src[g.a_off + m * g.a_rs + k * g.a_cs];
            }
            As[kl * BM + ml] = v;

            var nl: u32;
            var kb: u32;
            if g.b_kcontig == 1u {
                nl = idx / BK;
                kb = idx % BK;
            } else {
                nl = idx % BN;
                kb = idx / BN;
            }
            let n = tile_n + nl;
            let kk = k0 + kb;
            var w = 0.0;
            if n < g.n && kk < k_end {
                w = b_src[g.b_off + kk * g.b_rs + n * g.b_cs];
            }
            Bs[kb * BN + (nl % 16u) * 4u + nl / 16u] = w;
        }
        workgroupBarrier();
        for (var kl = 0u; kl < BK; kl++) {
            let ab = kl * BM + tm * 4u;
            let bb = kl * BN + tn * 4u;
            let b = vec4<f32>(Bs[bb], Bs[bb + 1u], Bs[bb + 2u], Bs[bb + 3u]);
            acc0 = fma(vec4<f32>(As[ab]), b, acc0);
            acc1 = fma(vec4<f32>(As[ab + 1u]), b, acc1);
            acc2 = fma(vec4<f32>(As[ab + 2u]), b, acc2);
            acc3 = fma(vec4<f32>(As[ab + 3u]), b, acc3);
        }
        workgroupBarrier();
    }

    let m0 = tile_m + tm * 4u;
    if g.mode == 2u {
        // Weight-gradient partial for this K chunk.
        let base = wid.z * g.m * g.n;
        for (var c = 0u; c < 4u; c++) {
            let n = tile_n + tn + 16u * c;
            if n < g.n {
                if m0 < g.m { out0[base + m0 * g.n + n] = acc0[c]; }
                if m0 + 1u < g.m { out0[base + (m0 + 1u) * g.n + n] = acc1[c]; }
                if m0 + 2u < g.m { out0[base + (m0 + 2u) * g.n + n] = acc2[c]; }
                if m0 + 3u < g.m { out0[base + (m0 + 3u) * g.n + n] = acc3[c]; }
            }
        }
        if wid.x == 0u {
            // Bias partial: Σ over this chunk's value rows (k ≡ 0 mod 4) of A[m, k], summed by
            // 4 invocations per m and combined through workgroup memory.
            let ml = lid % BM;
            let lane = lid / BM;
            let m = tile_m + ml;
            var s = 0.0;
            if m < g.m {
                for (var k = k_begin + 4u * lane; k < k_end; k += 16u) {
                    s += a_src[g.a_off + m * g.a_rs + k * g.a_cs];
                }
            }
            As[lid] = s;
            workgroupBarrier();
            if lane == 0u && m < g.m {
                out0[g.pbias_off + wid.z * g.m + m] = As[ml] + As[ml + 64u] + As[ml + 128u] + As[ml + 192u];
            }
        }
        return;
    }

    let w0 = g.omega;
    for (var c = 0u; c < 4u; c++) {
        let n = tile_n + tn + 16u * c;
        if n >= g.n {
            continue;
        }
        if g.tangents == 1u {
            if m0 >= g.m {
                continue;
            }
            let i0 = m0 * g.ldc + n;
            let i1 = i0 + g.ldc;
            let i2 = i1 + g.ldc;
            let i3 = i2 + g.ldc;
            if g.mode == 0u {
                let zv = acc0[c] + aux[g.bias_off + n];
                let s = sin(w0 * zv);
                let wc = w0 * cos(w0 * zv);
                if g.store_z == 1u {
                    out0[i0] = zv;
                    out0[i1] = acc1[c];
                    out0[i2] = acc2[c];
                    out0[i3] = acc3[c];
                }
                out1[i0] = s;
                out1[i1] = wc * acc1[c];
                out1[i2] = wc * acc2[c];
                out1[i3] = wc * acc3[c];
            } else {
                // Ā of the previous layer's outputs → Z̄ of its pre-activations:
                // z̄_j = ω0 cos · t̄_j,  z̄_v = ω0 cos · h̄ − ω0² sin · Σ_j t̄_j z_j.
                let zv = aux[i0];
                let s = sin(w0 * zv);
                let wc = w0 * cos(w0 * zv);
                let mix = acc1[c] * aux[i1] + acc2[c] * aux[i2] + acc3[c] * aux[i3];
                out0[i0] = wc * acc0[c] - w0 * w0 * s * mix;
                out0[i1] = wc * acc1[c];
                out0[i2] = wc * acc2[c];
                out0[i3] = wc * acc3[c];
            }
        } else {
            // Inference: four independent points, value only.
            let bias = aux[g.bias_off + n];
            if m0 < g.m { out1[m0 * g.ldc + n] = sin(w0 * (acc0[c] + bias)); }
            if m0 + 1u < g.m { out1[(m0 + 1u) * g.ldc + n] = sin(w0 * (acc1[c] + bias)); }
            if m0 + 2u < g.m { out1[(m0 + 2u) * g.ldc + n] = sin(w0 * (acc2[c] + bias)); }
            if m0 + 3u < g.m { out1[(m0 + 3u) * g.ldc + n] = sin(w0 * (acc3[c] + bias)); }
        }
    }
}
