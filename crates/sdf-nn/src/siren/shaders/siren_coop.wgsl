// SIREN inference on cooperative matrices (`LayerKernels::CoopF16`: tensor cores from WGSL),
// in one dispatch. Appended to a tile file (`siren_coop_16x16.wgsl`, `siren_coop_8x8.wgsl`)
// that enables f16 and cooperative matrices and defines the tile types CA, CB, CC, their side
// T, the activation buffer size ACT and the most subgroups a workgroup may have, SLOTS.
//
// A workgroup takes GROUP_ROWS = 4 T rows through every layer. A row is a point, or, with
// tangents, one of a point's four rows: its value, then ∂/∂x, ∂/∂y, ∂/∂z (forward-mode input
// gradient, as in `siren_tiled_fused.wgsl`; T is a multiple of 4, so a tile holds whole points).
// - the first layer (3 → width) in f32 from the points, stored as f16 activations;
// - each hidden layer as products of A = the group's activations (f16, row major in workgroup
//   memory) and B = ω0·W (f16, packed by `coop_pack`), accumulated in f32 over the width.
//   Subgroup s owns the output tiles of columns 2s and 2s + 1 for all four row tiles: eight
//   accumulators in registers, so that each k step loads two B tiles from memory and four A
//   tiles from workgroup memory for eight products (the previous design loaded one of each per
//   product, and B once per tile of 16 points: it measured slower than f32 on the H100).
//   With every accumulator of the layer in registers, the next layer's activations overwrite
//   this layer's in place, so one activation buffer of 4 T rows fits beside the scratch.
//   Each accumulator then goes through the subgroup's f32 scratch slot, where the subgroup's
//   own lanes add ω0·b and take the sine (value rows), or multiply by the cosine of the value
//   row's argument (tangent rows), and write the f16 activations;
// - the linear head in f32, several invocations per row, summed through the scratch.
// ω0 is folded into the packed weights so that tiny trained weights stay normal f16 numbers.
// With `query` set, it answers a caller's points in one dispatch, as siren_tiled_fused.wgsl does
// (query_map.wgsl's rule, prepended after the tile file).

struct Coop {
    // Rows in all: points, or 4 × points with tangents.
    rows: u32,
    // A multiple of T, at most 2 T · SLOTS.
    width: u32,
    hidden_layers: u32,
    omega: f32,
    tangents: u32,
    // Floats from one point to the next in `points` (the point first): 3, or 12 with tangents
    // (the point, then the unit axes, which the kernel does not read); 4 with `query`.
    point_stride: u32,
    // f16s from one row of `act` to the next: the width plus a pad of 16 bytes, so that the
    // rows of a tile start in different memory banks; GROUP_ROWS · act_stride ≤ ACT.
    act_stride: u32,
    // 1: `points` are a caller's vec4 points in mesh coordinates, and `values` receives their
    // distances (and unit normals) instead of Φ (and ∇Φ).
    query: u32,
    // The query's map into the cube: xyz the mesh's centre, w its scale.
    map: vec4<f32>,
}

@group(0) @binding(0) var<uniform> u: Coop;
// `point_stride` floats per point, the point first.
@group(0) @binding(1) var<storage, read> points: array<f32>;
// The f32 parameters (layout in `siren/mod.rs`): the first layer, the biases and the head.
@group(0) @binding(2) var<storage, read> params: array<f32>;
// ω0 · W of hidden layers 1 .. L-1, each [width][width] row major (out, in).
@group(0) @binding(3) var<storage, read> packed: array<f16>;
// Φ per row: Φ per point, or (Φ, ∇Φ) per point with tangents (with `query`: the distance, or
// the distance and the unit normal).
@group(0) @binding(4) var<storage, read_write> values: array<f32>;
// `packed`, written by `coop_pack`.
@group(0) @binding(5) var<storage, read_write> packed_out: array<f16>;

// Rows per workgroup: four row tiles, one per pair of accumulators.
const GROUP_ROWS: u32 = 4u * T;

// The group's activations, [row][feature], rows `act_stride` apart: a layer's input, then,
// in place, its output.
var<workgroup> act: array<f16, ACT>;
// One T × T f32 tile per subgroup (row major), then the head's partial sums.
var<workgroup> scratch: array<f32, SLOTS * T * T>;

// Offset in `params` of hidden layer l ≥ 1's weights (its bias follows them).
fn hidden_offset(l: u32, w: u32) -> u32 {
    return 4u * w + (l - 1u) * (w * w + w);
}

// Point p as stored: normalised, or with `query` in mesh coordinates.
fn stored_point(p: u32) -> vec3<f32> {
    let b = p * u.point_stride;
    return vec3<f32>(points[b], points[b + 1u], points[b + 2u]);
}

// The network's input for point p.
fn point_at(p: u32) -> vec3<f32> {
    return network_input(stored_point(p), u.query, u.map);
}

// Subgroups of the workgroup: the host sets WG = ⌈tiles across the width / 2⌉ × the
// adapter's (fixed) subgroup size.
override WG: u32 = 256u;

// Turns the accumulator of row tile `rt`, column tile `ct` into the next layer's activations
// through subgroup `slot`'s scratch (`keep`: false for a subgroup's repeated last column tile,
// whose tile another accumulator already wrote). Called by every subgroup the same number of
// times, so the barriers stay in uniform control flow.
fn finish_tile(acc: CC, slot: u32, lane: u32, lanes: u32, rt: u32, ct: u32, keep: bool, boff: u32) {
    let s0 = slot * T * T;
    coopStoreT(acc, &scratch[s0], T);
    workgroupBarrier();
    if keep {
        for (var e = lane; e < T * T; e += lanes) {
            let i = e / T;
            let o = ct * T + e % T;
            // A tangent row's value row is in the same tile, i % 4 rows up.
            let j = select(0u, i % 4u, u.tangents != 0u);
            let z = scratch[s0 + e - j * T] + u.omega * params[boff + o];
            act[(rt * T + i) * u.act_stride + o] = f16(select(cos(z) * scratch[s0 + e], sin(z), j == 0u));
        }
    }
    workgroupBarrier();
}

@compute @workgroup_size(WG)
fn coop_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(subgroup_id) sg: u32,
    @builtin(subgroup_invocation_id) lane: u32,
    @builtin(subgroup_size) lanes: u32,
) {
    let group = wid.y * nwg.x + wid.x;
    let first = group * GROUP_ROWS;
    // Workgroup-uniform, so the barriers below stay in uniform control flow.
    if first >= u.rows {
        return;
    }
    let w = u.width;
    let ls = u.act_stride;
    let om = u.omega;
    let last = u.rows - 1u;

    // First layer, from the points (rows past the batch repeat its last row): z = ω0 (W0 x + b0)
    // gives sin(z) on a value row and cos(z) ω0 W0[o][j] on the tangent row of axis j.
    for (var e = lid; e < GROUP_ROWS * w; e += WG) {
        let o = e % w;
        let row = min(first + e / w, last);
        let j = select(0u, row % 4u, u.tangents != 0u);
        let x = point_at(select(row, row / 4u, u.tangents != 0u));
        let z = om * (params[3u * o] * x.x + params[3u * o + 1u] * x.y
            + params[3u * o + 2u] * x.z + params[3u * w + o]);
        // Both operands of `select` are evaluated: index a weight that exists on value rows.
        let wj = params[3u * o + max(j, 1u) - 1u];
        act[(e / w) * ls + o] = f16(select(cos(z) * om * wj, sin(z), j == 0u));
    }
    workgroupBarrier();

    let tiles_o = w / T;
    // This subgroup's two column tiles; past the width, the last one again (naga wants
    // cooperative operations in uniform control flow: recompute rather than skip).
    let c0 = min(2u * sg, tiles_o - 1u);
    let c1 = min(2u * sg + 1u, tiles_o - 1u);
    let keep0 = 2u * sg < tiles_o;
    let keep1 = 2u * sg + 1u < tiles_o;
    // Assigned, not declared, in the loop: naga hoists a declaration's initialiser.
    var acc00 = CC();
    var acc01 = CC();
    var acc10 = CC();
    var acc11 = CC();
    var acc20 = CC();
    var acc21 = CC();
    var acc30 = CC();
    var acc31 = CC();
    for (var l = 1u; l < u.hidden_layers; l++) {
        let woff = (l - 1u) * w * w;
        let boff = hidden_offset(l, w) + w * w;
        let b0off = woff + c0 * T * w;
        let b1off = woff + c1 * T * w;
        acc00 = CC();
        acc01 = CC();
        acc10 = CC();
        acc11 = CC();
        acc20 = CC();
        acc21 = CC();
        acc30 = CC();
        acc31 = CC();
        for (var k = 0u; k < w; k += T) {
            // A(i, kk) = act[(rt·T + i)·ls + k + kk]; B(kk, j) = ω0·W[c·T + j][k + kk].
            let b0 = coopLoad<CB>(&packed[b0off + k], w);
            let b1 = coopLoad<CB>(&packed[b1off + k], w);
            var a = coopLoadT<CA>(&act[k], ls);
            acc00 = coopMultiplyAdd(a, b0, acc00);
            acc01 = coopMultiplyAdd(a, b1, acc01);
            a = coopLoadT<CA>(&act[T * ls + k], ls);
            acc10 = coopMultiplyAdd(a, b0, acc10);
            acc11 = coopMultiplyAdd(a, b1, acc11);
            a = coopLoadT<CA>(&act[2u * T * ls + k], ls);
            acc20 = coopMultiplyAdd(a, b0, acc20);
            acc21 = coopMultiplyAdd(a, b1, acc21);
            a = coopLoadT<CA>(&act[3u * T * ls + k], ls);
            acc30 = coopMultiplyAdd(a, b0, acc30);
            acc31 = coopMultiplyAdd(a, b1, acc31);
        }
        // Every subgroup has read this layer's activations: they may be overwritten.
        workgroupBarrier();
        finish_tile(acc00, sg, lane, lanes, 0u, c0, keep0, boff);
        finish_tile(acc01, sg, lane, lanes, 0u, c1, keep1, boff);
        finish_tile(acc10, sg, lane, lanes, 1u, c0, keep0, boff);
        finish_tile(acc11, sg, lane, lanes, 1u, c1, keep1, boff);
        finish_tile(acc20, sg, lane, lanes, 2u, c0, keep0, boff);
        finish_tile(acc21, sg, lane, lanes, 2u, c1, keep1, boff);
        finish_tile(acc30, sg, lane, lanes, 3u, c0, keep0, boff);
        finish_tile(acc31, sg, lane, lanes, 3u, c1, keep1, boff);
    }

    // The linear head, in f32: `parts` invocations per row sum every parts-th feature into
    // the scratch, then one per row adds them up; the bias only on value rows.
    let hoff = hidden_offset(u.hidden_layers, w);
    let parts = max(WG / GROUP_ROWS, 1u);
    for (var e = lid; e < GROUP_ROWS * parts; e += WG) {
        let r = e / parts;
        var s = 0.0;
        for (var k = e % parts; k < w; k += parts) {
            s = fma(f32(act[r * ls + k]), params[hoff + k], s);
        }
        scratch[e] = s;
    }
    workgroupBarrier();
    let bias = params[hoff + w];
    if u.query == 0u {
        for (var r = lid; r < GROUP_ROWS && first + r < u.rows; r += WG) {
            let value_row = u.tangents == 0u || (first + r) % 4u == 0u;
            values[first + r] = head_sum(r, parts) + select(0.0, bias, value_row);
        }
    } else if u.tangents == 0u {
        for (var r = lid; r < GROUP_ROWS && first + r < u.rows; r += WG) {
            let x = query_normalized(stored_point(first + r), u.map);
            values[first + r] = query_distance(head_sum(r, parts) + bias, x, u.map);
        }
    } else {
        // One invocation per point: its value row and its three tangent rows.
        for (var r = 4u * lid; r < GROUP_ROWS && first + r < u.rows; r += 4u * WG) {
            let x = query_normalized(stored_point((first + r) / 4u), u.map);
            let g = vec3<f32>(head_sum(r + 1u, parts), head_sum(r + 2u, parts), head_sum(r + 3u, parts));
            let n = query_normal(g, x);
            values[first + r] = query_distance(head_sum(r, parts) + bias, x, u.map);
            values[first + r + 1u] = n.x;
            values[first + r + 2u] = n.y;
            values[first + r + 3u] = n.z;
        }
    }
}

// Row r's head sum from its `parts` partial sums in the scratch.
fn head_sum(r: u32, parts: u32) -> f32 {
    var s = 0.0;
    for (var p = 0u; p < parts; p++) {
        s += scratch[r * parts + p];
    }
    return s;
}

// ω0 · W of every hidden layer after the first into `packed_out`, one weight per invocation.
@compute @workgroup_size(256)
fn coop_pack(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let i = gid.y * nwg.x * 256u + gid.x;
    let w = u.width;
    if i >= (u.hidden_layers - 1u) * w * w {
        return;
    }
    let l = 1u + i / (w * w);
    packed_out[i] = f16(u.omega * params[hidden_offset(l, w) + i % (w * w)]);
}
