// SIREN's per-layer products for GPUs (`LayerKernels::Tiled`): a tiled GEMM with the layer's
// epilogue fused in.
//
// C[m, n] = Σ_k A[m, k] B[k, n]. A workgroup of 256 invocations (a 16 × 16 grid) owns a
// (64·MB) × (64·NB) tile of C; K is swept in slices of 16 whose A ((64·MB) × 16) and B
// (16 × (64·NB)) parts are staged in workgroup memory (8 to 16 KiB in all), loaded as vec4 where
// the operand is contiguous and 16-byte aligned. Each invocation keeps MB × NB register blocks
// of 4 × 4 (four consecutive rows, four consecutive columns; blocks 64 rows or columns apart,
// so that the workgroup-memory reads of a slice stay conflict-free): per slice row, MB + NB
// vec4 reads for 16·MB·NB FMAs. 4 × 4 (MB = NB = 1) makes the most workgroups, for small
// products; 8 × 8 (MB = NB = 2) does twice the FMAs per workgroup-memory read, which large
// products on GPUs need to approach their FMA rate. Four rows aligned to 4 are one point with
// tangents (value, ∂x, ∂y, ∂z), so the tangent epilogues run in registers.
//
// Operands are read through (offset, row stride, column stride), as in siren_gemm.wgsl:
//   mode 0: C                                   (plain product)
//   mode 1: sin(ω0 (C + b))                     (inference; b read from `b_src` = params)
//   mode 2: four rows per point: out0 = z (bias added to the value row), out1 = activations
//           a_v = sin(ω0 z_v), a_j = ω0 cos(ω0 z_v) z_j
//   mode 3: four rows per point: C = Ā of the layer below's activations, turned into that
//           layer's Z̄ through its sine (pre-activations `z_in`):
//           z̄_j = ω0 cos · ā_j, z̄_v = ω0 cos · ā_v − ω0² sin · Σ_j ā_j z_j
//   mode 4: split-K weight gradient: partial[split] = Z̄ᵀ · A_prev over one chunk of batch rows
//           (k_chunk rows from wid.z · k_chunk, a multiple of 16); the workgroups of the first
//           column tile also sum the bias partial Σ Z̄[value rows] (k ≡ 0 mod 4) from the A
//           tiles they stage anyway, stored at pbias_off + split · M + m. The value rows are
//           every BIAS_STEP-th row (4 with tangents, 2 for the stacked rows of the
//           reverse-over-reverse step).
// Modes 5–8, the reverse-over-reverse training step (`siren::ror`): one row per point, every
// output and auxiliary matrix with row stride ldc, at its own element offset (out_off, out1_off,
// z_off, t_off); D(z) = ω0 cos(ω0 z), D'(z) = −ω0² sin(ω0 z):
//   mode 5: z = C + b → out0, sin(ω0 z) → out1                        (forward)
//   mode 6: C = G (Φ's gradient w.r.t. the layer below's activations) → out1,
//           H = D(z) ⊙ G → out0, z read from out1 at z_off            (input-gradient chain)
//   mode 7: C = H̄; D(z) ⊙ H̄ = Ḡ → out0; out1 holds G, replaced by
//           T = D'(z) ⊙ G ⊙ H̄; z read from out1 at z_off            (its adjoint)
//   mode 8: C = Ā; Z̄ = D(z) ⊙ Ā + T → out0, z and T read from z_in   (the forward's adjoint)

struct Tiled {
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
    // bit 0: A is contiguous along m (else along k); bit 1: A's vec4 loads are aligned;
    // bit 2: B is contiguous along n (else along k); bit 3: B's vec4 loads are aligned.
    flags: u32,
    // Modes 5–8: element offsets of out0, out1 and the auxiliary matrices (row stride ldc).
    out_off: u32,
    out1_off: u32,
    z_off: u32,
    t_off: u32,
}

// 1: the pipeline runs the reverse-over-reverse epilogues (modes 5–8); 0: they are compiled
// out, so that inference and the tangent step keep the code they had without them.
override ROR: u32 = 0u;
// Mode 4: the bias partial sums every BIAS_STEP-th row (4 with tangents, 2 with ROR).
override BIAS_STEP: u32 = 4u;
// 4-row blocks per invocation along m, and 4-column blocks along n: 1 or 2 each.
override MB: u32 = 1u;
override NB: u32 = 1u;

const BK: u32 = 16u;

@group(0) @binding(0) var<uniform> t: Tiled;
@group(0) @binding(1) var<storage, read> a_src: array<f32>;
@group(0) @binding(2) var<storage, read> b_src: array<f32>;
// The same buffers seen as vec4 for aligned loads.
@group(0) @binding(3) var<storage, read> a_src4: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> b_src4: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> out0: array<f32>;
// Mode 2: the activations.
@group(0) @binding(6) var<storage, read_write> out1: array<f32>;
// Mode 3: the pre-activations of the layer below ([M, ldc], like out0).
@group(0) @binding(7) var<storage, read> z_in: array<f32>;

// [k][m / 4] and [k][n / 4], rows of 16·MB and 16·NB vec4s: an invocation reads its four rows
// (columns) as one vec4, at `tile_at`. Sized for MB = NB = 2.
var<workgroup> tile_a: array<vec4<f32>, 256u * MB>;
var<workgroup> tile_b: array<vec4<f32>, 256u * NB>;

// Where the vec4 of columns 4·c4 .. 4·c4 + 3 at slice row k of a tile with rows of w4 vec4s
// (16 or 32) lives: the column is XORed with
// 2·((k / 4) mod 4), so the transposing loads below (invocations with the same column and k
// four apart: 64 floats apart without it, all in one of 32 four-byte banks) store to four
// different banks instead of one, a 4-way conflict gone on GPUs. A permutation within each row,
// so the reads of a row stay conflict-free, and the same for k and k + 1..3.
fn tile_at(k: u32, c4: u32, w4: u32) -> u32 {
    return k * w4 + (c4 ^ (2u * ((k >> 2u) & 3u)));
}

fn a_at(m: u32, k: u32, k_end: u32) -> f32 {
    if m < t.m && k < k_end {
        return a_src[t.a_off + m * t.a_rs + k * t.a_cs];
    }
    return 0.0;
}

fn b_at(k: u32, n: u32, k_end: u32) -> f32 {
    if k < k_end && n < t.n {
        return b_src[t.b_off + k * t.b_rs + n * t.b_cs];
    }
    return 0.0;
}

// Stages A's slice: (64·MB) × 16 floats, MB vec4 loads per invocation.
fn load_a(m0: u32, k0: u32, k_end: u32, lid: u32) {
    let aligned = (t.flags & 2u) != 0u;
    let w4 = 16u * MB;
    for (var r = 0u; r < MB; r++) {
        let e = lid + 256u * r;
        if (t.flags & 1u) != 0u {
            // Four consecutive m at one k.
            let ml = 4u * (e % w4);
            let kl = e / w4;
            let m = m0 + ml;
            let k = k0 + kl;
            var v: vec4<f32>;
            if aligned && m + 3u < t.m && k < k_end {
                v = a_src4[(t.a_off + m + k * t.a_cs) / 4u];
            } else {
                v = vec4<f32>(a_at(m, k, k_end), a_at(m + 1u, k, k_end), a_at(m + 2u, k, k_end),
                    a_at(m + 3u, k, k_end));
            }
            tile_a[tile_at(kl, ml / 4u, w4)] = v;
        } else {
            // Four consecutive k at one m.
            let ml = e / 4u;
            let kl = 4u * (e % 4u);
            let m = m0 + ml;
            let k = k0 + kl;
            var v: vec4<f32>;
            if aligned && m < t.m && k + 3u < k_end {
                v = a_src4[(t.a_off + m * t.a_rs + k) / 4u];
            } else {
                v = vec4<f32>(a_at(m, k, k_end), a_at(m, k + 1u, k_end), a_at(m, k + 2u, k_end),
                    a_at(m, k + 3u, k_end));
            }
            // kl is a multiple of 4: rows kl .. kl + 3 share the swizzle.
            let i = tile_at(kl, ml / 4u, w4);
            let c = ml % 4u;
            tile_a[i][c] = v.x;
            tile_a[i + w4][c] = v.y;
            tile_a[i + 2u * w4][c] = v.z;
            tile_a[i + 3u * w4][c] = v.w;
        }
    }
}

// Stages B's slice: 16 × (64·NB) floats, NB vec4 loads per invocation.
fn load_b(n0: u32, k0: u32, k_end: u32, lid: u32) {
    let aligned = (t.flags & 8u) != 0u;
    let w4 = 16u * NB;
    for (var r = 0u; r < NB; r++) {
        let e = lid + 256u * r;
        if (t.flags & 4u) != 0u {
            // Four consecutive n at one k.
            let nl = 4u * (e % w4);
            let kl = e / w4;
            let n = n0 + nl;
            let k = k0 + kl;
            var v: vec4<f32>;
            if aligned && n + 3u < t.n && k < k_end {
                v = b_src4[(t.b_off + k * t.b_rs + n) / 4u];
            } else {
                v = vec4<f32>(b_at(k, n, k_end), b_at(k, n + 1u, k_end), b_at(k, n + 2u, k_end),
                    b_at(k, n + 3u, k_end));
            }
            tile_b[tile_at(kl, nl / 4u, w4)] = v;
        } else {
            // Four consecutive k at one n.
            let nl = e / 4u;
            let kl = 4u * (e % 4u);
            let n = n0 + nl;
            let k = k0 + kl;
            var v: vec4<f32>;
            if aligned && n < t.n && k + 3u < k_end {
                v = b_src4[(t.b_off + n * t.b_cs + k) / 4u];
            } else {
                v = vec4<f32>(b_at(k, n, k_end), b_at(k + 1u, n, k_end), b_at(k + 2u, n, k_end),
                    b_at(k + 3u, n, k_end));
            }
            let i = tile_at(kl, nl / 4u, w4);
            let c = nl % 4u;
            tile_b[i][c] = v.x;
            tile_b[i + w4][c] = v.y;
            tile_b[i + 2u * w4][c] = v.z;
            tile_b[i + 3u * w4][c] = v.w;
        }
    }
}

// Row `m` of out0 at columns n..n+3 (those below N), from element offset `base`.
fn store0(base: u32, m: u32, n: u32, v: vec4<f32>) {
    if m >= t.m {
        return;
    }
    let o = base + m * t.ldc + n;
    for (var c = 0u; c < 4u; c++) {
        if n + c < t.n {
            out0[o + c] = v[c];
        }
    }
}

fn store1(m: u32, n: u32, v: vec4<f32>) {
    let o = m * t.ldc + n;
    for (var c = 0u; c < 4u; c++) {
        if n + c < t.n {
            out1[o + c] = v[c];
        }
    }
}

fn z_row(m: u32, n: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    let o = m * t.ldc + n;
    for (var c = 0u; c < 4u; c++) {
        if n + c < t.n {
            v[c] = z_in[o + c];
        }
    }
    return v;
}

// Row m (a point) of a reverse-over-reverse matrix at columns n..n+3 (those below N).
fn ror_store0(m: u32, n: u32, v: vec4<f32>) {
    if m < t.m {
        store0(t.out_off, m, n, v);
    }
}

fn ror_store1(m: u32, n: u32, v: vec4<f32>) {
    if m >= t.m {
        return;
    }
    let o = t.out1_off + m * t.ldc + n;
    for (var c = 0u; c < 4u; c++) {
        if n + c < t.n {
            out1[o + c] = v[c];
        }
    }
}

fn ror_load1(off: u32, m: u32, n: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    if m < t.m {
        let o = off + m * t.ldc + n;
        for (var c = 0u; c < 4u; c++) {
            if n + c < t.n {
                v[c] = out1[o + c];
            }
        }
    }
    return v;
}

fn ror_load_z(off: u32, m: u32, n: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    if m < t.m {
        let o = off + m * t.ldc + n;
        for (var c = 0u; c < 4u; c++) {
            if n + c < t.n {
                v[c] = z_in[o + c];
            }
        }
    }
    return v;
}

// The reverse-over-reverse epilogue of row m (modes 5–8).
fn ror_epilogue(m: u32, n: u32, c: vec4<f32>) {
    let w0 = t.omega;
    switch t.mode {
        case 5u: {
            let z = c + bias4(n);
            ror_store0(m, n, z);
            ror_store1(m, n, sin(w0 * z));
        }
        case 6u: {
            let z = ror_load1(t.z_off, m, n);
            ror_store1(m, n, c);
            ror_store0(m, n, w0 * cos(w0 * z) * c);
        }
        case 7u: {
            let z = ror_load1(t.z_off, m, n);
            let g = ror_load1(t.out1_off, m, n);
            ror_store0(m, n, w0 * cos(w0 * z) * c);
            ror_store1(m, n, -w0 * w0 * sin(w0 * z) * g * c);
        }
        default: {
            let z = ror_load_z(t.z_off, m, n);
            let tz = ror_load_z(t.t_off, m, n);
            ror_store0(m, n, w0 * cos(w0 * z) * c + tz);
        }
    }
}

fn bias4(n: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    for (var c = 0u; c < 4u; c++) {
        if n + c < t.n {
            v[c] = b_src[t.bias_off + n + c];
        }
    }
    return v;
}

// One 4 × 4 register block of C: rows m .. m + 3 (r0 .. r3), four columns each.
struct Block {
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    r3: vec4<f32>,
}

// c + a ⊗ b: one slice row's contribution to a block.
fn mac(c: Block, a: vec4<f32>, b: vec4<f32>) -> Block {
    return Block(fma(vec4<f32>(a.x), b, c.r0), fma(vec4<f32>(a.y), b, c.r1),
        fma(vec4<f32>(a.z), b, c.r2), fma(vec4<f32>(a.w), b, c.r3));
}

// Mode 4: the bias partial of rows m .. m + 3 (those below M), of split `split`.
fn store_bias(split: u32, m: u32, v: vec4<f32>) {
    let pb = t.pbias_off + split * t.m + m;
    for (var i = 0u; i < 4u; i++) {
        if m + i < t.m {
            out0[pb + i] = v[i];
        }
    }
}

// The epilogue of the block at rows m .. m + 3, columns n .. n + 3 (nothing where m or n lies
// beyond C; M is a multiple of 4 in the modes that treat four rows as a point).
fn epilogue(m: u32, n: u32, c: Block, split: u32) {
    if m >= t.m || n >= t.n {
        return;
    }
    if ROR != 0u && t.mode >= 5u {
        ror_epilogue(m, n, c.r0);
        ror_epilogue(m + 1u, n, c.r1);
        ror_epilogue(m + 2u, n, c.r2);
        ror_epilogue(m + 3u, n, c.r3);
        return;
    }
    switch t.mode {
        case 1u: {
            let b = bias4(n);
            store0(0u, m, n, sin(t.omega * (c.r0 + b)));
            store0(0u, m + 1u, n, sin(t.omega * (c.r1 + b)));
            store0(0u, m + 2u, n, sin(t.omega * (c.r2 + b)));
            store0(0u, m + 3u, n, sin(t.omega * (c.r3 + b)));
        }
        case 2u: {
            // The four rows are one point.
            let zv = c.r0 + bias4(n);
            store0(0u, m, n, zv);
            store0(0u, m + 1u, n, c.r1);
            store0(0u, m + 2u, n, c.r2);
            store0(0u, m + 3u, n, c.r3);
            let wc = t.omega * cos(t.omega * zv);
            store1(m, n, sin(t.omega * zv));
            store1(m + 1u, n, wc * c.r1);
            store1(m + 2u, n, wc * c.r2);
            store1(m + 3u, n, wc * c.r3);
        }
        case 3u: {
            let w0 = t.omega;
            let zv = z_row(m, n);
            let s = sin(w0 * zv);
            let wc = w0 * cos(w0 * zv);
            let mix = c.r1 * z_row(m + 1u, n) + c.r2 * z_row(m + 2u, n) + c.r3 * z_row(m + 3u, n);
            store0(0u, m, n, wc * c.r0 - w0 * w0 * s * mix);
            store0(0u, m + 1u, n, wc * c.r1);
            store0(0u, m + 2u, n, wc * c.r2);
            store0(0u, m + 3u, n, wc * c.r3);
        }
        case 4u: {
            let base = split * t.m * t.ldc;
            store0(base, m, n, c.r0);
            store0(base, m + 1u, n, c.r1);
            store0(base, m + 2u, n, c.r2);
            store0(base, m + 3u, n, c.r3);
        }
        default: {
            store0(0u, m, n, c.r0);
            store0(0u, m + 1u, n, c.r1);
            store0(0u, m + 2u, n, c.r2);
            store0(0u, m + 3u, n, c.r3);
        }
    }
}

@compute @workgroup_size(256)
fn tiled_gemm(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let bm = 64u * MB;
    let bn = 64u * NB;
    let wa = 16u * MB;
    let wb = 16u * NB;
    let n_tiles = (t.n + bn - 1u) / bn;
    let g = wid.y * nwg.x + wid.x;
    let m_tile = g / n_tiles;
    // Workgroup-uniform, so the barriers below stay in uniform control flow.
    if m_tile * bm >= t.m {
        return;
    }
    let m0 = m_tile * bm;
    let n0 = (g % n_tiles) * bn;
    var k_begin = 0u;
    var k_end = t.k;
    if t.mode == 4u {
        k_begin = wid.z * t.k_chunk;
        k_end = min(k_begin + t.k_chunk, t.k);
    }
    let tx = lid % 16u;
    let ty = lid / 16u;
    // Block (i, j) holds rows m0 + 4·ty + 64·i, columns n0 + 4·tx + 64·j. With MB or NB 1 the
    // branches on them are constant once the pipeline is specialised, and the unused blocks
    // vanish.
    var c00 = Block();
    var c01 = Block();
    var c10 = Block();
    var c11 = Block();
    // Mode 4, first column tile, tx = 0: the bias partials of the invocation's rows.
    let sum_bias = t.mode == 4u && n0 == 0u && tx == 0u;
    var bias0 = vec4<f32>(0.0);
    var bias1 = vec4<f32>(0.0);
    for (var k0 = k_begin; k0 < k_end; k0 += BK) {
        load_a(m0, k0, k_end, lid);
        load_b(n0, k0, k_end, lid);
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let a0 = tile_a[tile_at(kk, ty, wa)];
            let b0 = tile_b[tile_at(kk, tx, wb)];
            c00 = mac(c00, a0, b0);
            if NB > 1u {
                let b1 = tile_b[tile_at(kk, tx + 16u, wb)];
                c01 = mac(c01, a0, b1);
                if MB > 1u {
                    let a1 = tile_a[tile_at(kk, ty + 16u, wa)];
                    c10 = mac(c10, a1, b0);
                    c11 = mac(c11, a1, b1);
                }
            } else if MB > 1u {
                let a1 = tile_a[tile_at(kk, ty + 16u, wa)];
                c10 = mac(c10, a1, b0);
            }
        }
        if sum_bias {
            // k0 is a multiple of 4: value rows sit at kk ≡ 0 (mod BIAS_STEP).
            for (var kk = 0u; kk < BK; kk += BIAS_STEP) {
                bias0 += tile_a[tile_at(kk, ty, wa)];
                if MB > 1u {
                    bias1 += tile_a[tile_at(kk, ty + 16u, wa)];
                }
            }
        }
        workgroupBarrier();
    }
    let m = m0 + 4u * ty;
    let n = n0 + 4u * tx;
    if sum_bias {
        store_bias(wid.z, m, bias0);
        if MB > 1u {
            store_bias(wid.z, m + 64u, bias1);
        }
    }
    epilogue(m, n, c00, wid.z);
    if NB > 1u {
        epilogue(m, n + 64u, c01, wid.z);
    }
    if MB > 1u {
        epilogue(m + 64u, n, c10, wid.z);
        if NB > 1u {
            epilogue(m + 64u, n + 64u, c11, wid.z);
        }
    }
}
