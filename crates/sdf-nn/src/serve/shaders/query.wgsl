// The serving path's two ends around a network's kernels (crates/sdf-nn/src/query.rs):
//   prepare: the caller's points (array<vec4<f32>>, xyz in mesh coordinates) -> the network's input:
//            normalised, clamped to [-1, 1]^3, as 3 floats per point, or (SIREN with gradients)
//            as four rows per point: the point and the unit tangents e_x, e_y, e_z;
//   finish:  the network's output -> the caller's results, in mesh units, with the rule of
//            query_map.wgsl (prepended) outside the box.
// One invocation per point. SIREN's one-dispatch kernels (tiled fused, cooperative matrices) apply
// the same rule themselves and need neither.

struct Query {
    n_points: u32,
    // 1: write SIREN's four input rows per point.
    streams: u32,
    // 1: the network gives (value, gradient) per point and the results are (distance, normal).
    normals: u32,
    scale: f32,
    center: vec4<f32>,
}

const WG: u32 = 64u;

@group(0) @binding(0) var<uniform> q: Query;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> net_in: array<f32>;
@group(0) @binding(3) var<storage, read> net_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> results: array<f32>;

fn normalized(idx: u32) -> vec3<f32> {
    return query_normalized(points[idx].xyz, vec4<f32>(q.center.xyz, q.scale));
}

@compute @workgroup_size(WG)
fn prepare(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if idx >= q.n_points {
        return;
    }
    let c = query_clamped(normalized(idx));
    if q.streams == 0u {
        net_in[3u * idx] = c.x;
        net_in[3u * idx + 1u] = c.y;
        net_in[3u * idx + 2u] = c.z;
    } else {
        let b = 12u * idx;
        net_in[b] = c.x;
        net_in[b + 1u] = c.y;
        net_in[b + 2u] = c.z;
        for (var k = 3u; k < 12u; k++) {
            // Rows 1..3 are the unit tangents: a 1 at offsets 3, 7 and 11.
            net_in[b + k] = select(0.0, 1.0, k % 4u == 3u);
        }
    }
}

@compute @workgroup_size(WG)
fn finish(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let idx = (wid.y * nwg.x + wid.x) * WG + lid;
    if idx >= q.n_points {
        return;
    }
    let x = normalized(idx);
    let map = vec4<f32>(q.center.xyz, q.scale);
    if q.normals == 0u {
        results[idx] = query_distance(net_out[idx], x, map);
        return;
    }
    let b = 4u * idx;
    let n = query_normal(vec3<f32>(net_out[b + 1u], net_out[b + 2u], net_out[b + 3u]), x);
    results[b] = query_distance(net_out[b], x, map);
    results[b + 1u] = n.x;
    results[b + 2u] = n.y;
    results[b + 3u] = n.z;
}
