// SIREN inference in one dispatch (`LayerKernels::Tiled`, batches bound by latency): a
// workgroup takes `group_rows` rows (points, or four rows per point with tangents) through
// the first layer, every hidden layer and the linear head, keeping their activations in
// workgroup memory (at most 16 KiB, every device has it); only Φ (and ∇Φ) reach global memory.
//
// Per layer, invocation i < (group_rows / 4) · (width / 4) owns a 4 × 4 register block: four
// rows (with tangents: one point's value and tangent rows, so the tangent epilogue
// a_j = ω0 cos(ω0 z_v) z_j runs in registers) by four output features. It reads its rows from
// workgroup memory (the same four rows for every invocation of a subgroup, a broadcast) and the
// weights transposed, from `wt4` (written by `fused_pack` whenever the parameters change): at
// input feature k, invocation i reads Wᵀ[k][4i..4i+3] as one vec4, so a subgroup's invocations
// read consecutive vec4s (one coalesced 512-byte load on a 32-wide subgroup) where the
// row-major weights had each invocation read a row of its own, a whole weight row apart. Every
// workgroup reads the same weights: they stay in cache. After a barrier it overwrites its block
// with the layer's activations in place.
//
// With `query` set, it answers a caller's points in one dispatch (crates/sdf-nn/src/query.rs):
// `points` holds vec4 points in mesh coordinates, mapped into the cube and clamped on load, and
// `values` receives the distances (and normals) of query_map.wgsl's rule instead of Φ (and ∇Φ).

struct Fused {
    // Rows in all: points, or 4 × points with tangents.
    rows: u32,
    // Rows per workgroup: a multiple of 4 with group_rows · width ≤ 4096 and ≤ 256.
    group_rows: u32,
    // A multiple of 4.
    width: u32,
    hidden_layers: u32,
    tangents: u32,
    // Floats from one point to the next in `points` (the point first): 3, or 12 with tangents
    // (the point, then e_x, e_y, e_z, which the kernel does not read); 4 with `query`.
    point_stride: u32,
    omega: f32,
    // 1: `points` are a caller's mesh-space points, `values` its results (see above).
    query: u32,
    // The query's map into the cube: xyz the mesh's centre, w its scale.
    map: vec4<f32>,
}

@group(0) @binding(0) var<uniform> f: Fused;
@group(0) @binding(1) var<storage, read> points: array<f32>;
@group(0) @binding(2) var<storage, read> params: array<f32>;
// The same buffer as vec4 (every weight row starts 16-byte aligned when width % 4 = 0).
@group(0) @binding(3) var<storage, read> params4: array<vec4<f32>>;
// Φ per row: Φ per point, or (Φ, ∇Φ) per point with tangents (with `query`: the distance, or
// the distance and the unit normal).
@group(0) @binding(4) var<storage, read_write> values: array<f32>;
// The hidden layers after the first, transposed: layer l's Wᵀ[k][o] at (l - 1)·w² + k·w + o.
@group(0) @binding(5) var<storage, read> wt4: array<vec4<f32>>;
// The same buffer, written by `fused_pack`.
@group(0) @binding(6) var<storage, read_write> wt_out: array<f32>;

// [row][feature / 4] of the current layer's activations.
var<workgroup> act: array<vec4<f32>, 1024>;

// Offset in `params` of layer l ≥ 1's weights (its bias follows them; l = hidden_layers is the
// head), as in siren_coop.wgsl.
fn hidden_offset(l: u32, w: u32) -> u32 {
    return 4u * w + (l - 1u) * (w * w + w);
}

// Point p as stored: normalised, or with `query` in mesh coordinates.
fn stored_point(p: u32) -> vec3<f32> {
    let b = p * f.point_stride;
    return vec3<f32>(points[b], points[b + 1u], points[b + 2u]);
}

// The network's input for point p.
fn point_at(p: u32) -> vec3<f32> {
    if f.query != 0u {
        return query_clamped(query_normalized(stored_point(p), f.map));
    }
    return stored_point(p);
}

// Row o of the first layer's W ([width, 3]).
fn w0_row(o: u32) -> vec3<f32> {
    return vec3<f32>(params[3u * o], params[3u * o + 1u], params[3u * o + 2u]);
}

@compute @workgroup_size(256)
fn fused_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let group = wid.y * nwg.x + wid.x;
    let first_row = group * f.group_rows;
    // Workgroup-uniform, so the barriers below stay in uniform control flow.
    if first_row >= f.rows {
        return;
    }
    let w = f.width;
    let w4 = w / 4u;
    let owns_block = lid < (f.group_rows / 4u) * w4;
    let r0 = 4u * (lid / w4);
    let cb = lid % w4;
    let o0 = 4u * cb;
    let om = f.omega;

    // First layer, straight from the points.
    if owns_block {
        var b = vec4<f32>(0.0);
        var wx = vec4<f32>(0.0);
        var wy = vec4<f32>(0.0);
        var wz = vec4<f32>(0.0);
        for (var c = 0u; c < 4u; c++) {
            let wr = w0_row(o0 + c);
            wx[c] = wr.x;
            wy[c] = wr.y;
            wz[c] = wr.z;
            b[c] = params[3u * w + o0 + c];
        }
        let last = f.rows - 1u;
        if f.tangents != 0u {
            let p = point_at(min(first_row + r0, last) / 4u);
            let zv = b + p.x * wx + p.y * wy + p.z * wz;
            let wc = om * cos(om * zv);
            act[r0 * w4 + cb] = sin(om * zv);
            act[(r0 + 1u) * w4 + cb] = wc * wx;
            act[(r0 + 2u) * w4 + cb] = wc * wy;
            act[(r0 + 3u) * w4 + cb] = wc * wz;
        } else {
            for (var i = 0u; i < 4u; i++) {
                let p = point_at(min(first_row + r0 + i, last));
                act[(r0 + i) * w4 + cb] = sin(om * (b + p.x * wx + p.y * wy + p.z * wz));
            }
        }
    }
    workgroupBarrier();

    // Hidden layers 1..L-1: W at 4w + (l - 1)(w² + w), then b.
    for (var l = 1u; l < f.hidden_layers; l++) {
        let woff = hidden_offset(l, w);
        // Wᵀ[k][o0..o0+3] of this layer at input feature k = 0.
        let wt = (l - 1u) * w * w4 + cb;
        var c0 = vec4<f32>(0.0);
        var c1 = vec4<f32>(0.0);
        var c2 = vec4<f32>(0.0);
        var c3 = vec4<f32>(0.0);
        if owns_block {
            for (var k4 = 0u; k4 < w4; k4++) {
                let a0 = act[r0 * w4 + k4];
                let a1 = act[(r0 + 1u) * w4 + k4];
                let a2 = act[(r0 + 2u) * w4 + k4];
                let a3 = act[(r0 + 3u) * w4 + k4];
                // Input features 4k4 .. 4k4 + 3, four outputs each.
                let q = wt + 4u * k4 * w4;
                let q0 = wt4[q];
                let q1 = wt4[q + w4];
                let q2 = wt4[q + 2u * w4];
                let q3 = wt4[q + 3u * w4];
                c0 = fma(vec4(a0.x), q0, c0);
                c0 = fma(vec4(a0.y), q1, c0);
                c0 = fma(vec4(a0.z), q2, c0);
                c0 = fma(vec4(a0.w), q3, c0);
                c1 = fma(vec4(a1.x), q0, c1);
                c1 = fma(vec4(a1.y), q1, c1);
                c1 = fma(vec4(a1.z), q2, c1);
                c1 = fma(vec4(a1.w), q3, c1);
                c2 = fma(vec4(a2.x), q0, c2);
                c2 = fma(vec4(a2.y), q1, c2);
                c2 = fma(vec4(a2.z), q2, c2);
                c2 = fma(vec4(a2.w), q3, c2);
                c3 = fma(vec4(a3.x), q0, c3);
                c3 = fma(vec4(a3.y), q1, c3);
                c3 = fma(vec4(a3.z), q2, c3);
                c3 = fma(vec4(a3.w), q3, c3);
            }
        }
        // Every block is read before any is overwritten.
        workgroupBarrier();
        if owns_block {
            let b = params4[(woff + w * w + o0) / 4u];
            if f.tangents != 0u {
                let zv = c0 + b;
                let wc = om * cos(om * zv);
                act[r0 * w4 + cb] = sin(om * zv);
                act[(r0 + 1u) * w4 + cb] = wc * c1;
                act[(r0 + 2u) * w4 + cb] = wc * c2;
                act[(r0 + 3u) * w4 + cb] = wc * c3;
            } else {
                act[r0 * w4 + cb] = sin(om * (c0 + b));
                act[(r0 + 1u) * w4 + cb] = sin(om * (c1 + b));
                act[(r0 + 2u) * w4 + cb] = sin(om * (c2 + b));
                act[(r0 + 3u) * w4 + cb] = sin(om * (c3 + b));
            }
        }
        workgroupBarrier();
    }

    // The linear head, one row per invocation; the bias only on value rows.
    let row = first_row + lid;
    let has_row = lid < f.group_rows && row < f.rows;
    var phi = 0.0;
    if has_row {
        let woff4 = hidden_offset(f.hidden_layers, w) / 4u;
        var s = vec4<f32>(0.0);
        for (var k4 = 0u; k4 < w4; k4++) {
            s = fma(act[lid * w4 + k4], params4[woff4 + k4], s);
        }
        phi = s.x + s.y + s.z + s.w;
        if f.tangents == 0u || lid % 4u == 0u {
            phi += params[4u * woff4 + w];
        }
    }
    if f.query == 0u {
        if has_row {
            values[row] = phi;
        }
        return;
    }
    if f.tangents == 0u {
        if has_row {
            values[row] = query_distance(phi, query_normalized(stored_point(row), f.map), f.map);
        }
        return;
    }
    // A point's four rows meet in workgroup memory (every row of `act` has been read).
    workgroupBarrier();
    if has_row {
        act[lid].x = phi;
    }
    workgroupBarrier();
    if has_row && lid % 4u == 0u {
        let x = query_normalized(stored_point(row / 4u), f.map);
        let n = query_normal(vec3<f32>(act[lid + 1u].x, act[lid + 2u].x, act[lid + 3u].x), x);
        values[row] = query_distance(phi, x, f.map);
        values[row + 1u] = n.x;
        values[row + 2u] = n.y;
        values[row + 3u] = n.z;
    }
}

// `wt4` from the parameters: one invocation per weight of the hidden layers after the first,
// in 256-wide groups folded into 2D. Reads are strided, writes coalesced; it runs once per
// change of the parameters, not per evaluation.
@compute @workgroup_size(256)
fn fused_pack(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let i = gid.y * nwg.x * 256u + gid.x;
    let w = f.width;
    if i >= (f.hidden_layers - 1u) * w * w {
        return;
    }
    let l = 1u + i / (w * w);
    let k = (i / w) % w;
    let o = i % w;
    wt_out[i] = params[hidden_offset(l, w) + o * w + k];
}
