// NGLOD and hash-grid serving with one point per subgroup (the host prepends nglod_grid.wgsl,
// query_map.wgsl and nglod_forward.wgsl, whose uniforms, bindings and serving rule these entry
// points share). One invocation per point (nglod_forward.wgsl's `query`) leaves a few thousand
// points to a few thousand threads, each running 8 gathers per level and the whole MLP alone: on
// a GPU that is one long chain of dependent loads per point, and the kernel takes as long as
// that chain. Here the subgroup's lanes split the work of one point:
// - lanes 8g..8g+7 gather the eight corners of the levels l with l % (width / 8) == g (a
//   subgroup narrower than 8 loops over the corners: nglod_grid.wgsl's lane_corners);
// - the features are summed over the subgroup (subgroupAdd, four inputs at a time);
// - each lane runs every width-th hidden unit, reading its row of W0 from `params` (lanes read
//   different rows, which a uniform buffer would serialise);
// - the output (and the gradient) are summed over the subgroup; lane 0 writes.
// Every lane takes the same point, so control flow is uniform in the subgroup.

// Per lane: its part of the MLP's input and of the input's gradient.
var<private> sg_z: array<f32, MAX_F>;
var<private> sg_dz: array<vec3<f32>, MAX_F>;

// The value (x) and, with `grad`, the gradient (yzw) at a normalised point, computed by the whole
// subgroup (every lane calls it with the same p and gets the same result).
fn value_grad_sg(p: vec3<f32>, lane: u32, lanes: u32, grad: bool) -> vec4<f32> {
    // Inputs up to the next multiple of 4 are summed in vec4s: zero them all.
    let f4 = (F + 3u) / 4u * 4u;
    for (var f = 0u; f < f4; f++) {
        sg_z[f] = 0.0;
        sg_dz[f] = vec3<f32>(0.0);
    }
    for (var l = 0u; l < u.lod; l++) {
        let corners = lane_corners(lane, lanes, l);
        if corners.x == 8u {
            continue;
        }
        let lv = u.levels[l];
        let cell = grid_cell(p, lv.x);
        for (var c = corners.x; c < 8u; c += corners.y) {
            let wd = corner_weight(cell, c);
            let w = wd.x;
            let dw = wd.yzw;
            let base = vertex_base(lv, cell.i0 + corner_offset(c));
            if base == NO_SLOT {
                continue;
            }
            let zo = l * ZS;
            for (var f = 0u; f < FL; f++) {
                let g = params[base + f];
                sg_z[zo + f] += w * g;
                if grad {
                    sg_dz[zo + f] += dw * g;
                }
            }
        }
    }
    for (var f = 0u; f < f4; f += 4u) {
        let s = subgroupAdd(vec4<f32>(sg_z[f], sg_z[f + 1u], sg_z[f + 2u], sg_z[f + 3u]));
        sg_z[f] = s.x;
        sg_z[f + 1u] = s.y;
        sg_z[f + 2u] = s.z;
        sg_z[f + 3u] = s.w;
        if grad {
            for (var k = 0u; k < 4u; k++) {
                sg_dz[f + k] = subgroupAdd(sg_dz[f + k]);
            }
        }
    }

    let w0 = u.mlp_offset;
    let b0 = w0 + H * F;
    let w1 = b0 + H;
    var o = 0.0;
    var g = vec3<f32>(0.0);
    for (var j = lane; j < H; j += lanes) {
        let row = w0 + j * F;
        var h = params[b0 + j];
        for (var f = 0u; f < F; f++) {
            h += params[row + f] * sg_z[f];
        }
        if h > 0.0 {
            let a = params[w1 + j];
            o += a * h;
            if grad {
                for (var f = 0u; f < F; f++) {
                    g += a * params[row + f] * sg_dz[f];
                }
            }
        }
    }
    // Broadcast: a reduction's rounding need not be the same on every lane.
    o = subgroupBroadcastFirst(subgroupAdd(o));
    if grad {
        g = subgroupBroadcastFirst(subgroupAdd(g));
    }
    // b1 from the uniform copy: every lane reads the same word.
    return vec4<f32>(o + mlp_at(w1 + H - w0), g);
}

// Points per workgroup: WG over the widest subgroup the adapter may run, as the host counts
// them. The workgroup's subgroups share out its slice whatever width the hardware runs (fewer
// subgroups take several points each, more leave some idle).
override PER_GROUP: u32 = 1u;

fn query_point(idx: u32) -> vec3<f32> {
    return query_normalized(vec3<f32>(points[4u * idx], points[4u * idx + 1u], points[4u * idx + 2u]), u.query);
}

// With normals (`query_grad`'s output: distance and unit normal per point) or without (`query`'s).
override NORMALS: bool = false;

// `query`, or with NORMALS `query_grad`, with one point per subgroup.
@compute @workgroup_size(WG)
fn query_sg(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(subgroup_id) sid: u32,
    @builtin(num_subgroups) subgroups: u32,
    @builtin(subgroup_invocation_id) lane: u32,
    @builtin(subgroup_size) lanes: u32,
) {
    let first = (wid.y * nwg.x + wid.x) * PER_GROUP;
    for (var k = sid; k < PER_GROUP && first + k < u.n_points; k += subgroups) {
        let idx = first + k;
        let x = query_point(idx);
        let vg = value_grad_sg(query_clamped(x), lane, lanes, NORMALS);
        // Lane 0 writes; every lane goes round the loop together (no `continue` that lets the
        // lanes part before the next point's subgroup sums: WGSL does not promise they meet).
        if lane == 0u {
            if NORMALS {
                let n = query_normal(vg.yzw, x);
                out[4u * idx] = query_distance(vg.x, x, u.query);
                out[4u * idx + 1u] = n.x;
                out[4u * idx + 2u] = n.y;
                out[4u * idx + 3u] = n.z;
            } else {
                out[idx] = query_distance(vg.x, x, u.query);
            }
        }
    }
}
