// NGLOD inference: for each point, trilinearly interpolate the first `lod` levels' dense feature
// grids, sum them, and run the MLP  out = W1 · relu(W0 · z + b0) + b1.
//
// Parameter layout (one flat f32 buffer, shared with Adam):
//   grid l: (r_l+1)^3 vertices × F features, vertex (ix, iy, iz) at ((ix·(r+1) + iy)·(r+1) + iz)·F,
//   or for a sparse level its band's vertices only (nglod_grid.wgsl)
//   then W0 (H×F row-major), b0 (H), W1 (H), b1 (1) starting at `mlp_offset`.
//
// One invocation per point.

struct Uniforms {
    n_points: u32,
    lod: u32,
    mlp_offset: u32,
    _pad: u32,
    // Per level: (resolution r, offset in params, z, kind): nglod_grid.wgsl.
    levels: array<vec4<u32>, 16>,
    // The serving entry points (query, query_grad): xyz the mesh's centre, w its scale.
    query: vec4<f32>,
}

const WG: u32 = 64u;
const MAX_F: u32 = 32u;
// W0 + b0 + W1 + b1 must fit 3840 floats: 15 KiB, under the 16 KiB uniform binding every adapter
// offers.
const MAX_MLP_VEC4: u32 = 960u;

// The MLP's input width: FL summed levels, or K·FL concatenated ones (nglod_grid.wgsl).
override F: u32 = 8u;
override H: u32 = 128u;

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> points: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;
// The MLP block of params (W0, b0, W1, b1), copied here before each dispatch: every invocation
// reads the same weight at the same time, which is what uniform memory serves best (on lavapipe
// 3× faster than workgroup or storage memory, measured; a constant-cache broadcast on GPUs).
@group(0) @binding(4) var<uniform> mlp: array<vec4<f32>, MAX_MLP_VEC4>;

// The sparse levels' vertex tables (nglod_grid.wgsl); one unused entry when there are none.
@group(0) @binding(5) var<storage, read> table: array<u32>;

fn mlp_at(i: u32) -> f32 {
    return mlp[i / 4u][i % 4u];
}


@compute @workgroup_size(WG)
fn forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if idx >= u.n_points {
        return;
    }
    let p = vec3<f32>(points[3u * idx], points[3u * idx + 1u], points[3u * idx + 2u]);
    out[idx] = value_at(p);
}

// The network's value at a normalised point.
fn value_at(p: vec3<f32>) -> f32 {
    var z: array<f32, MAX_F>;
    for (var f = 0u; f < F; f++) {
        z[f] = 0.0;
    }
    for (var l = 0u; l < u.lod; l++) {
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

    let b0 = H * F;
    let w1 = b0 + H;
    var o = mlp_at(w1 + H);
    for (var j = 0u; j < H; j++) {
        var h = mlp_at(b0 + j);
        for (var f = 0u; f < F; f++) {
            h += mlp_at(j * F + f) * z[f];
        }
        o += mlp_at(w1 + j) * max(h, 0.0);
    }
    return o;
}

// The gradient differentiates the trilinear weights (zero along an axis where the point is
// clamped, as on the CPU and in the embedded WGSL) and the active ReLUs.
// The value (x) and the gradient (yzw) at a normalised point.
fn value_grad_at(p: vec3<f32>) -> vec4<f32> {
    var z: array<f32, MAX_F>;
    var dz: array<vec3<f32>, MAX_F>;
    for (var f = 0u; f < F; f++) {
        z[f] = 0.0;
        dz[f] = vec3<f32>(0.0);
    }
    for (var l = 0u; l < u.lod; l++) {
        let lv = u.levels[l];
        let cell = grid_cell(p, lv.x);
        for (var c = 0u; c < 8u; c++) {
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
                z[zo + f] += w * g;
                dz[zo + f] += dw * g;
            }
        }
    }

    let b0 = H * F;
    let w1 = b0 + H;
    var o = mlp_at(w1 + H);
    var grad = vec3<f32>(0.0);
    for (var j = 0u; j < H; j++) {
        var h = mlp_at(b0 + j);
        for (var f = 0u; f < F; f++) {
            h += mlp_at(j * F + f) * z[f];
        }
        if h > 0.0 {
            let a = mlp_at(w1 + j);
            o += a * h;
            for (var f = 0u; f < F; f++) {
                grad += a * mlp_at(j * F + f) * dz[f];
            }
        }
    }
    return vec4<f32>(o, grad);
}

// The serving path (crates/sdf-nn/src/query.rs) in one dispatch: `points` holds vec4 points in
// mesh coordinates (xyz), `out` receives the distance in mesh units (the rule of query_map.wgsl).
@compute @workgroup_size(WG)
fn query(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if idx >= u.n_points {
        return;
    }
    let x = query_normalized(vec3<f32>(points[4u * idx], points[4u * idx + 1u], points[4u * idx + 2u]), u.query);
    out[idx] = query_distance(value_at(query_clamped(x)), x, u.query);
}

// `query` with normals: out[4 idx..] = (distance, unit normal).
@compute @workgroup_size(WG)
fn query_grad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if idx >= u.n_points {
        return;
    }
    let x = query_normalized(vec3<f32>(points[4u * idx], points[4u * idx + 1u], points[4u * idx + 2u]), u.query);
    let vg = value_grad_at(query_clamped(x));
    let n = query_normal(vg.yzw, x);
    out[4u * idx] = query_distance(vg.x, x, u.query);
    out[4u * idx + 1u] = n.x;
    out[4u * idx + 2u] = n.y;
    out[4u * idx + 3u] = n.z;
}
