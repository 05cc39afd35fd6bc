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
// `mlp_partial` sums one chunk of rows per workgroup row (y) into `partials`; `mlp_reduce` sums the
// chunks in a fixed order and adds the result to the gradient buffer, so the MLP gradients are
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
    levels: array<vec4<u32>, 8>,
}

const WG: u32 = 64u;

override F: u32 = 8u;
override H: u32 = 128u;

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> rows: array<f32>;
@group(0) @binding(3) var<storage, read_write> partials: array<f32>;

@compute @workgroup_size(WG)
fn mlp_partial(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let n_out = H * F + 2u * H + 2u;
    let m = wid.x * WG + lid;
    let chunk = wid.y;
    if m >= n_out || chunk >= u.n_chunks {
        return;
    }
    let stride = 2u + F + H;
    let start = chunk * u.chunk;
    let end = min(start + u.chunk, u.n_rows);
    let w1 = u.mlp_offset + H * F + H;
    var s = 0.0;
    if m < H * F {
        let j = m / F;
        let f = m % F;
        for (var i = start; i < end; i++) {
            let row = i * stride;
            if rows[row + 2u + F + j] > 0.0 {
                s += rows[row] * rows[row + 2u + f];
            }
        }
        s *= params[w1 + j];
    } else if m < H * F + H {
        let j = m - H * F;
        for (var i = start; i < end; i++) {
            let row = i * stride;
            if rows[row + 2u + F + j] > 0.0 {
                s += rows[row];
            }
        }
        s *= params[w1 + j];
    } else if m < H * F + 2u * H {
        let j = m - H * F - H;
        for (var i = start; i < end; i++) {
            let row = i * stride;
            s += rows[row] * rows[row + 2u + F + j];
        }
    } else if m == H * F + 2u * H {
        for (var i = start; i < end; i++) {
            s += rows[i * stride];
        }
    } else {
        for (var i = start; i < end; i++) {
            s += rows[i * stride + 1u];
        }
    }
    partials[chunk * n_out + m] = s;
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
