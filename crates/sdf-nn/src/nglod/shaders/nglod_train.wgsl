// NGLOD training step, part 1: forward and backward for one (point, level prefix) pair per
// invocation.
//
// Each invocation ("row") evaluates the model with the first `lod` levels, then
//   - writes its row of the scratch buffer: [g, r², z (F), a (H)] with r = out - target,
//     g = dL/dout = 2r and a = relu(W0 z + b0); nglod_reduce.wgsl turns the rows into the MLP
//     gradients (a deterministic reduction, no atomics);
//   - scatters dL/dz times the trilinear weights into the grid gradients: many rows touch the same
//     grid vertex, so this is an atomic add.
//
// The host prepends nglod_grid.wgsl and one of the two scatters, which declare the gradient
// buffer `grads` and its add `grad_add`: nglod_scatter_atomic.wgsl (native float atomics) or
// nglod_scatter_cas.wgsl (a compare-exchange loop, any adapter).
//
// Gradients are sums over rows; Adam's grad_scale applies 1/batch.

struct Uniforms {
    // Rows in this step: batch points × prefixes per point.
    n_rows: u32,
    // First point of the batch in `points` / `targets`.
    first: u32,
    // Prefixes per point: 1 (only the full model) or K (NGLOD's sum over every prefix).
    n_prefix: u32,
    // Levels used by the first prefix; row i uses lod_base + i % n_prefix levels.
    lod_base: u32,
    mlp_offset: u32,
    // Rows per partial sum, and number of partial sums (used by nglod_reduce.wgsl).
    chunk: u32,
    n_chunks: u32,
    _pad: u32,
    // Per level: (resolution r, offset in params, z, kind): nglod_grid.wgsl.
    levels: array<vec4<u32>, 16>,
}

const WG: u32 = 64u;
const MAX_F: u32 = 32u;
const MAX_MLP_VEC4: u32 = 960u;

// The MLP's input width: FL summed levels, or K·FL concatenated ones (nglod_grid.wgsl).
override F: u32 = 8u;
override H: u32 = 128u;

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> points: array<f32>;
@group(0) @binding(3) var<storage, read> targets: array<f32>;
@group(0) @binding(4) var<storage, read_write> rows: array<f32>;
// Binding 5, the grid gradients `grads`, is the scatter's.
// The MLP block of params (W0, b0, W1, b1), copied here before each step (see nglod_forward.wgsl).
@group(0) @binding(6) var<uniform> mlp: array<vec4<f32>, MAX_MLP_VEC4>;

// The sparse levels' vertex tables (nglod_grid.wgsl); one unused entry when there are none.
@group(0) @binding(7) var<storage, read> table: array<u32>;

fn mlp_at(i: u32) -> f32 {
    return mlp[i / 4u][i % 4u];
}

@compute @workgroup_size(WG)
fn train_rows(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row_idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if row_idx >= u.n_rows {
        return;
    }
    let pi = u.first + row_idx / u.n_prefix;
    let lod = u.lod_base + row_idx % u.n_prefix;
    let p = vec3<f32>(points[3u * pi], points[3u * pi + 1u], points[3u * pi + 2u]);

    var z: array<f32, MAX_F>;
    for (var f = 0u; f < F; f++) {
        z[f] = 0.0;
    }
    for (var l = 0u; l < lod; l++) {
        let lv = u.levels[l];
        let cell = grid_cell(p, lv.x);
        for (var c = 0u; c < 8u; c++) {
            let w = corner_weight(cell, c).x;
            let base = vertex_base(lv, cell.i0 + corner_offset(c));
            if base == NO_SLOT {
                continue;
            }
            let zo = l * ZS;
            for (var f = 0u; f < FL; f++) {
                z[zo + f] += w * params[base + f];
            }
        }
    }

    let stride = 2u + F + H;
    let row = row_idx * stride;
    let b0 = H * F;
    let w1 = b0 + H;
    var o = mlp_at(w1 + H);
    // dL/dz = g Σ_j W1[j] [h_j > 0] W0[j, :] is linear in g = dL/dout: its sum v is taken in
    // the forward pass, before g is known, instead of a second pass over the hidden units.
    var v: array<f32, MAX_F>;
    for (var f = 0u; f < F; f++) {
        v[f] = 0.0;
    }
    for (var j = 0u; j < H; j++) {
        var h = mlp_at(b0 + j);
        for (var f = 0u; f < F; f++) {
            h += mlp_at(j * F + f) * z[f];
        }
        let a = max(h, 0.0);
        rows[row + 2u + F + j] = a;
        let c = mlp_at(w1 + j);
        o += c * a;
        if h > 0.0 {
            for (var f = 0u; f < F; f++) {
                v[f] += c * mlp_at(j * F + f);
            }
        }
    }
    // The served value: outside the box, the clamped point's plus the distance to the box
    // (the serving rule of query_map.wgsl), which a near-surface point beyond a face is
    // labelled against.
    let res = o + box_gap(p) - targets[pi];
    let g = 2.0 * res;
    rows[row] = g;
    rows[row + 1u] = res * res;
    for (var f = 0u; f < F; f++) {
        rows[row + 2u + f] = z[f];
    }

    for (var l = 0u; l < lod; l++) {
        let lv = u.levels[l];
        let cell = grid_cell(p, lv.x);
        for (var c = 0u; c < 8u; c++) {
            let w = corner_weight(cell, c).x;
            let base = vertex_base(lv, cell.i0 + corner_offset(c));
            if base == NO_SLOT {
                continue;
            }
            let zo = l * ZS;
            for (var f = 0u; f < FL; f++) {
                grad_add(base + f, w * g * v[zo + f]);
            }
        }
    }
}
