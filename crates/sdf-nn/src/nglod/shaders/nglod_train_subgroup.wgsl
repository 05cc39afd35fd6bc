// NGLOD training step, part 1, with one row per subgroup (the host prepends nglod_grid.wgsl, a
// scatter and nglod_train.wgsl, whose uniforms, bindings, row layout and `grad_add` this
// entry point shares; nglod_reduce.wgsl reads the rows it writes as it reads `train_rows`').
//
// Why: a step of the default batch is 2048 rows (points × level prefixes). One row per
// invocation (`train_rows`) leaves a few rows per SM of a large GPU, each invocation running
// its gathers, the whole MLP forward and backward and its scatter alone: the step lasts one
// invocation's chain of dependent loads. Here a subgroup's lanes share a row:
// - the lanes share the levels' corners for the gather and, the same way, the scatter
//   (nglod_grid.wgsl's lane_corners);
// - the features are summed over the subgroup (subgroupAdd, four inputs at a time);
// - each lane runs every width-th hidden unit, reading its row of W0 from `params` (lanes read
//   different rows, which the uniform copy would serialise) and writing its a_j to the row;
// - dL/dz = g Σ_j W1[j] [h_j > 0] W0[j, :] is linear in g = dL/dout: as in `train_rows`, each
//   lane sums its units' W1[j] [h_j > 0] W0[j, :] in the forward pass, before g is known, and
//   one subgroupAdd of that sum finishes it.
// Every lane takes the same row, so control flow is uniform in the subgroup.

// Per lane: the row's MLP input (after the sums, on every lane), and Σ W1[j] [h_j > 0] W0[j, :]
// (this lane's units, then the subgroup's).
var<private> sgt_z: array<f32, MAX_F>;
var<private> sgt_v: array<f32, MAX_F>;

// Rows per workgroup: WG over the widest subgroup the adapter may run, as the host counts
// them; the workgroup's subgroups share out its slice whatever width the hardware runs.
override PER_GROUP: u32 = 1u;

// Replaces every lane's `a` by the subgroup's sum of it.
fn sgt_sum(a: ptr<private, array<f32, MAX_F>>) {
    let f4 = (F + 3u) / 4u * 4u;
    for (var f = 0u; f < f4; f += 4u) {
        let s = subgroupAdd(vec4<f32>((*a)[f], (*a)[f + 1u], (*a)[f + 2u], (*a)[f + 3u]));
        (*a)[f] = s.x;
        (*a)[f + 1u] = s.y;
        (*a)[f + 2u] = s.z;
        (*a)[f + 3u] = s.w;
    }
}

// This lane's part of the grid for a row at p with `lod` levels: it gathers features into
// sgt_z, or with `scatter` adds g · sgt_v times the trilinear weights to the grid gradients.
// Gather and scatter visit the same corners on the same lane.
fn sgt_grid(p: vec3<f32>, lod: u32, lane: u32, lanes: u32, scatter: bool, g: f32) {
    for (var l = 0u; l < lod; l++) {
        let corners = lane_corners(lane, lanes, l);
        if corners.x == 8u {
            continue;
        }
        let lv = u.levels[l];
        let cell = grid_cell(p, lv.x);
        for (var c = corners.x; c < 8u; c += corners.y) {
            let w = corner_weight(cell, c).x;
            let base = vertex_base(lv, cell.i0 + corner_offset(c));
            if base == NO_SLOT {
                continue;
            }
            let zo = l * ZS;
            for (var f = 0u; f < FL; f++) {
                if scatter {
                    grad_add(base + f, w * g * sgt_v[zo + f]);
                } else {
                    sgt_z[zo + f] += w * params[base + f];
                }
            }
        }
    }
}

fn train_row_sg(row_idx: u32, lane: u32, lanes: u32) {
    let pi = u.first + row_idx / u.n_prefix;
    let lod = u.lod_base + row_idx % u.n_prefix;
    let p = vec3<f32>(points[3u * pi], points[3u * pi + 1u], points[3u * pi + 2u]);
    // Inputs up to the next multiple of 4 are summed in vec4s: zero them all.
    let f4 = (F + 3u) / 4u * 4u;
    for (var f = 0u; f < f4; f++) {
        sgt_z[f] = 0.0;
        sgt_v[f] = 0.0;
    }
    sgt_grid(p, lod, lane, lanes, false, 0.0);
    sgt_sum(&sgt_z);

    let stride = 2u + F + H;
    let row = row_idx * stride;
    let w0 = u.mlp_offset;
    let b0 = w0 + H * F;
    let w1 = b0 + H;
    var o = 0.0;
    for (var j = lane; j < H; j += lanes) {
        let wrow = w0 + j * F;
        var h = params[b0 + j];
        for (var f = 0u; f < F; f++) {
            h += params[wrow + f] * sgt_z[f];
        }
        let a = max(h, 0.0);
        rows[row + 2u + F + j] = a;
        let c = params[w1 + j];
        o += c * a;
        if h > 0.0 {
            for (var f = 0u; f < F; f++) {
                sgt_v[f] += c * params[wrow + f];
            }
        }
    }
    // Broadcast: a reduction's rounding need not be the same on every lane, and g must be.
    // b1 from the uniform copy: every lane reads the same word.
    let out = subgroupBroadcastFirst(subgroupAdd(o)) + mlp_at(w1 + H - w0);
    // The served value, as in nglod_train.wgsl: outside the box plus the distance to it.
    let res = out + box_gap(p) - targets[pi];
    let g = 2.0 * res;
    if lane == 0u {
        rows[row] = g;
        rows[row + 1u] = res * res;
    }
    for (var f = lane; f < F; f += lanes) {
        rows[row + 2u + f] = sgt_z[f];
    }
    sgt_sum(&sgt_v);
    sgt_grid(p, lod, lane, lanes, true, g);
}

@compute @workgroup_size(WG)
fn train_rows_sg(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(subgroup_id) sid: u32,
    @builtin(num_subgroups) subgroups: u32,
    @builtin(subgroup_invocation_id) lane: u32,
    @builtin(subgroup_size) lanes: u32,
) {
    let first = (wid.y * nwg.x + wid.x) * PER_GROUP;
    for (var k = sid; k < PER_GROUP && first + k < u.n_rows; k += subgroups) {
        train_row_sg(first + k, lane, lanes);
    }
}
