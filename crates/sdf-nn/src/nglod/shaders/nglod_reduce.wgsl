// NGLOD training step, part 2: MLP gradients from the rows written by nglod_train_*.wgsl.
//
// Row layout (stride 2 + F + H): [g, r², z (F), a (H)]. Outputs m, in the parameter order of the
// MLP block, plus one extra for the loss:
//   m <  H·F         W0[j, f] = W1[j] Σ g [a_j > 0] z_f      (j = m / F, f = m % F)
//   m <  H·F + H     b0[j]    = W1[j] Σ g [a_j > 0]
//   m <  H·F + 2H    W1[j]    = Σ g a_j
//   m == H·F + 2H    b1       = Σ g
//   m == H·F + 2H+1  loss     = Σ r²
//
// `mlp_partial` sums one chunk of rows per workgroup row (y) into `partials`: invocation j < H
// produces every output of hidden unit j (W0[j, :], b0[j], W1[j]), invocation H produces b1 and
// the loss. Each row's g and z are then the same for all invocations of a workgroup (uniform
// loads) and a_j is read once per row, rather than once per output. `mlp_reduce` sums the chunks
// in a fixed order and adds the result to the gradient buffer, so the MLP gradients are
// deterministic.

struct Uniforms {
    n_rows: u32,
    first: u32,
    n_prefix: u32,
    lod_base: u32,
    mlp_offset: u32,
    chunk: u32,
    n_chunks: u32,
    _pad: u32,
    levels: array<vec4<u32>, 16>,
}

const WG: u32 = 64u;

override F: u32 = 8u;
override H: u32 = 128u;

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> rows: array<f32>;
@group(0) @binding(3) var<storage, read_write> partials: array<f32>;

const MAX_F: u32 = 32u;

@compute @workgroup_size(WG)
fn mlp_partial(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let n_out = H * F + 2u * H + 2u;
    let j = wid.x * WG + lid;
    let chunk = wid.y;
    if j > H || chunk >= u.n_chunks {
        return;
    }
    let stride = 2u + F + H;
    let start = chunk * u.chunk;
    let end = min(start + u.chunk, u.n_rows);
    let out = chunk * n_out;
    if j == H {
        var sg = 0.0;
        var sl = 0.0;
        for (var i = start; i < end; i++) {
            sg += rows[i * stride];
            sl += rows[i * stride + 1u];
        }
        partials[out + H * F + 2u * H] = sg;
        partials[out + H * F + 2u * H + 1u] = sl;
        return;
    }
    var sw0: array<f32, MAX_F>;
    for (var f = 0u; f < F; f++) {
        sw0[f] = 0.0;
    }
    var sb0 = 0.0;
    var sw1 = 0.0;
    for (var i = start; i < end; i++) {
        let row = i * stride;
        let g = rows[row];
        let a = rows[row + 2u + F + j];
        sw1 += g * a;
        if a > 0.0 {
            sb0 += g;
            for (var f = 0u; f < F; f++) {
                sw0[f] += g * rows[row + 2u + f];
            }
        }
    }
    // dL/dh_j = g W1[j] [a_j > 0]: W1[j] is common to every row, so it is applied once here.
    let w1 = params[u.mlp_offset + H * F + H + j];
    for (var f = 0u; f < F; f++) {
        partials[out + j * F + f] = sw0[f] * w1;
    }
    partials[out + H * F + j] = sb0 * w1;
    partials[out + H * F + H + j] = sw1;
}

@group(0) @binding(4) var<storage, read_write> grads: array<f32>;
// stats[0] accumulates Σ r² over steps until the host reads and clears it.
@group(0) @binding(5) var<storage, read_write> stats: array<f32>;
@group(0) @binding(6) var<storage, read> partials_in: array<f32>;

@compute @workgroup_size(WG)
fn mlp_reduce(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let n_out = H * F + 2u * H + 2u;
    let m = wid.x * WG + lid;
    if m >= n_out {
        return;
    }
    var s = 0.0;
    for (var c = 0u; c < u.n_chunks; c++) {
        s += partials_in[c * n_out + m];
    }
    if m + 1u < n_out {
        grads[u.mlp_offset + m] += s;
    } else {
        stats[0] += s;
    }
}
