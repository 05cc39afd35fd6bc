// SIREN inference in one dispatch (`LayerKernels::Tiled`): a workgroup takes `group_rows` rows
// (points, or four rows per point with tangents) through the first layer, every hidden layer
// and the linear head, keeping their activations in workgroup memory (16 KiB at RB = 1); only
// Φ (and ∇Φ) reach global memory.
//
// Per layer, invocation i < (group_rows / 4 / RB) · (width / 4) owns RB 4 × 4 register blocks
// of the same four output features: four rows each (with tangents: one point's value and
// tangent rows, so the tangent epilogue a_j = ω0 cos(ω0 z_v) z_j runs in registers), the
// blocks group_rows / RB rows apart. RB = 1 needs 16 KiB of workgroup memory (every device has
// it) and makes the most workgroups, for batches bound by latency; RB = 2 or 3 loads each
// weight once for 2 or 3 times the rows, for large batches, where every workgroup streaming
// all the weights from the cache is what bounds the kernel. It reads its rows from
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
    // Rows per workgroup: RB times a multiple of 4 with (group_rows / RB) · width ≤ 4096 and
    // group_rows / RB ≤ 256, and group_rows · width / 4 ≤ ACT4.
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

// Register blocks (of four rows) per invocation: 1, 2 or 3 (a pipeline constant).
override RB: u32 = 1u;
// vec4s of `act`: group_rows · width / 4, set by the host within the device's limit (16 KiB
// at RB = 1).
override ACT4: u32 = 1024u;

// [row][feature / 4] of the current layer's activations.
var<workgroup> act: array<vec4<f32>, ACT4>;

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
    return network_input(stored_point(p), f.query, f.map);
}

// Row o of the first layer's W ([width, 3]).
fn w0_row(o: u32) -> vec3<f32> {
    return vec3<f32>(params[3u * o], params[3u * o + 1u], params[3u * o + 2u]);
}

// The first layer's activations of the four rows from r0 at output features o0 .. o0 + 3
// (block column cb), straight from the points.
fn first_layer_block(first_row: u32, r0: u32, cb: u32, w4: u32) {
    let w = f.width;
    let o0 = 4u * cb;
    let om = f.omega;
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

// A register block: the sums of four rows at four output features.
struct RowBlock {
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    r3: vec4<f32>,
}

// `acc` plus the products of the block's rows from r0, at input features 4k4 .. 4k4 + 3, with
// those features' transposed weights q0 .. q3.
fn block_mac(acc: RowBlock, r0: u32, k4: u32, w4: u32, q0: vec4<f32>, q1: vec4<f32>, q2: vec4<f32>, q3: vec4<f32>) -> RowBlock {
    var out = acc;
    out.r0 = row_mac(out.r0, act[r0 * w4 + k4], q0, q1, q2, q3);
    out.r1 = row_mac(out.r1, act[(r0 + 1u) * w4 + k4], q0, q1, q2, q3);
    out.r2 = row_mac(out.r2, act[(r0 + 2u) * w4 + k4], q0, q1, q2, q3);
    out.r3 = row_mac(out.r3, act[(r0 + 3u) * w4 + k4], q0, q1, q2, q3);
    return out;
}

fn row_mac(acc: vec4<f32>, a: vec4<f32>, q0: vec4<f32>, q1: vec4<f32>, q2: vec4<f32>, q3: vec4<f32>) -> vec4<f32> {
    return fma(vec4(a.w), q3, fma(vec4(a.z), q2, fma(vec4(a.y), q1, fma(vec4(a.x), q0, acc))));
}

// A hidden layer's activations of the block at rows r0 .. r0 + 3, column cb, from its sums and
// the layer's bias b, in place.
fn store_block(r0: u32, cb: u32, w4: u32, b: vec4<f32>, c: RowBlock) {
    let om = f.omega;
    if f.tangents != 0u {
        let zv = c.r0 + b;
        let wc = om * cos(om * zv);
        act[r0 * w4 + cb] = sin(om * zv);
        act[(r0 + 1u) * w4 + cb] = wc * c.r1;
        act[(r0 + 2u) * w4 + cb] = wc * c.r2;
        act[(r0 + 3u) * w4 + cb] = wc * c.r3;
    } else {
        act[r0 * w4 + cb] = sin(om * (c.r0 + b));
        act[(r0 + 1u) * w4 + cb] = sin(om * (c.r1 + b));
        act[(r0 + 2u) * w4 + cb] = sin(om * (c.r2 + b));
        act[(r0 + 3u) * w4 + cb] = sin(om * (c.r3 + b));
    }
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
    // Rows between an invocation's blocks.
    let span = f.group_rows / RB;
    let owns_block = lid < (span / 4u) * w4;
    let r0 = 4u * (lid / w4);
    let r1 = r0 + span;
    let r2 = r1 + span;
    let cb = lid % w4;

    // First layer, straight from the points.
    if owns_block {
        first_layer_block(first_row, r0, cb, w4);
        if RB > 1u {
            first_layer_block(first_row, r1, cb, w4);
        }
        if RB > 2u {
            first_layer_block(first_row, r2, cb, w4);
        }
    }
    workgroupBarrier();

    // Hidden layers 1..L-1: W at 4w + (l - 1)(w² + w), then b.
    for (var l = 1u; l < f.hidden_layers; l++) {
        let woff = hidden_offset(l, w);
        // Wᵀ[k][o0..o0+3] of this layer at input feature k = 0.
        let wt = (l - 1u) * w * w4 + cb;
        // c: the block at r0; d: at r1 (RB > 1); e: at r2 (RB > 2). Blocks an RB leaves out
        // are constant branches once the pipeline is specialised, and vanish.
        var c = RowBlock();
        var d = RowBlock();
        var e = RowBlock();
        if owns_block {
            for (var k4 = 0u; k4 < w4; k4++) {
                // Input features 4k4 .. 4k4 + 3, four outputs each.
                let q = wt + 4u * k4 * w4;
                let q0 = wt4[q];
                let q1 = wt4[q + w4];
                let q2 = wt4[q + 2u * w4];
                let q3 = wt4[q + 3u * w4];
                c = block_mac(c, r0, k4, w4, q0, q1, q2, q3);
                if RB > 1u {
                    d = block_mac(d, r1, k4, w4, q0, q1, q2, q3);
                }
                if RB > 2u {
                    e = block_mac(e, r2, k4, w4, q0, q1, q2, q3);
                }
            }
        }
        // Every block is read before any is overwritten.
        workgroupBarrier();
        if owns_block {
            let b = params4[(woff + w * w) / 4u + cb];
            store_block(r0, cb, w4, b, c);
            if RB > 1u {
                store_block(r1, cb, w4, b, d);
            }
            if RB > 2u {
                store_block(r2, cb, w4, b, e);
            }
        }
        workgroupBarrier();
    }

    // The linear head, one row per invocation (RB rows, 256 apart).
    let woff4 = hidden_offset(f.hidden_layers, w) / 4u;
    let phi0 = head_row(first_row, lid, woff4);
    var phi1 = 0.0;
    var phi2 = 0.0;
    if RB > 1u {
        phi1 = head_row(first_row, lid + 256u, woff4);
    }
    if RB > 2u {
        phi2 = head_row(first_row, lid + 512u, woff4);
    }
    if f.query == 0u || f.tangents == 0u {
        write_row(first_row, lid, phi0);
        if RB > 1u {
            write_row(first_row, lid + 256u, phi1);
        }
        if RB > 2u {
            write_row(first_row, lid + 512u, phi2);
        }
        return;
    }
    // A query with normals: a point's four rows meet in workgroup memory (every row of `act`
    // has been read).
    workgroupBarrier();
    if has_row(first_row, lid) {
        act[lid].x = phi0;
    }
    if RB > 1u && has_row(first_row, lid + 256u) {
        act[lid + 256u].x = phi1;
    }
    if RB > 2u && has_row(first_row, lid + 512u) {
        act[lid + 512u].x = phi2;
    }
    workgroupBarrier();
    finish_point(first_row, lid, phi0);
    if RB > 1u {
        finish_point(first_row, lid + 256u, phi1);
    }
    if RB > 2u {
        finish_point(first_row, lid + 512u, phi2);
    }
}

// Whether the workgroup's row r (from first_row) is one of the batch's.
fn has_row(first_row: u32, r: u32) -> bool {
    return r < f.group_rows && first_row + r < f.rows;
}

// The head's Φ of the workgroup's row r (0 past the batch): the last activations times the
// output weights, the bias only on value rows.
fn head_row(first_row: u32, r: u32, woff4: u32) -> f32 {
    if !has_row(first_row, r) {
        return 0.0;
    }
    let w4 = f.width / 4u;
    var s = vec4<f32>(0.0);
    for (var k4 = 0u; k4 < w4; k4++) {
        s = fma(act[r * w4 + k4], params4[woff4 + k4], s);
    }
    var phi = s.x + s.y + s.z + s.w;
    if f.tangents == 0u || r % 4u == 0u {
        phi += params[4u * woff4 + f.width];
    }
    return phi;
}

// Writes row r's Φ (or ∇Φ's component), or with `query` and no tangents its distance.
fn write_row(first_row: u32, r: u32, phi: f32) {
    if !has_row(first_row, r) {
        return;
    }
    let row = first_row + r;
    if f.query == 0u {
        values[row] = phi;
    } else {
        values[row] = query_distance(phi, query_normalized(stored_point(row), f.map), f.map);
    }
}

// A query with normals: at a point's value row r, its distance and unit normal from its value
// `phi` and its tangent rows' Φ in `act`.
fn finish_point(first_row: u32, r: u32, phi: f32) {
    if !has_row(first_row, r) || r % 4u != 0u {
        return;
    }
    let row = first_row + r;
    let x = query_normalized(stored_point(row / 4u), f.map);
    let n = query_normal(vec3<f32>(act[r + 1u].x, act[r + 2u].x, act[r + 3u].x), x);
    values[row] = query_distance(phi, x, f.map);
    values[row + 1u] = n.x;
    values[row + 2u] = n.y;
    values[row + 3u] = n.z;
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
