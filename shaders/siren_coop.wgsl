// SIREN inference on cooperative matrices (`LayerKernels::CoopF16`: tensor cores from WGSL),
// in one dispatch. Appended to a tile file (`siren_coop_16x16.wgsl`, `siren_coop_8x8.wgsl`)
// that enables f16 and cooperative matrices and defines the tile types CA, CB, CC, their side
// T, the activation buffer size ACT and the number of scratch SLOTS.
//
// A workgroup takes `group_rows` rows through every layer. A row is a point, or, with
// tangents, one of a point's four rows: its value, then ∂/∂x, ∂/∂y, ∂/∂z (forward-mode input
// gradient, as in `siren_tiled_fused.wgsl`; T is a multiple of 4, so a tile holds whole points).
// - the first layer (3 → width) in f32 from the points, stored as f16 activations;
// - each hidden layer as tiles of T points × T outputs: A = T points' activations (f16, row
//   major in workgroup memory), B = T rows of ω0·W (f16, packed by `coop_pack`), accumulated
//   in f32 over the width. The workgroup's SLOTS subgroups each take one tile at a time and
//   store it to f32 scratch, then the whole workgroup adds ω0·b and takes the sine (value rows),
//   or multiplies by the cosine of the value row's argument (tangent rows), and writes the f16
//   activations of the next layer into the other half of `act`;
// - the linear head in f32, one row per invocation (the bias only on value rows).
// ω0 is folded into the packed weights so that tiny trained weights stay normal f16 numbers.

struct Coop {
    // Rows in all: points, or 4 × points with tangents.
    rows: u32,
    // A multiple of T with group_rows · act_stride ≤ ACT.
    group_rows: u32,
    // A multiple of T.
    width: u32,
    hidden_layers: u32,
    omega: f32,
    tangents: u32,
    // Floats per point in `points`: 3, or 12 with tangents (the point, then the unit axes).
    point_stride: u32,
    // f16s from one row of `act` to the next: the width plus a pad of 16 bytes, so that the
    // rows of a tile start in different memory banks; group_rows · act_stride ≤ ACT.
    act_stride: u32,
}

@group(0) @binding(0) var<uniform> u: Coop;
// `point_stride` floats per point, the point first.
@group(0) @binding(1) var<storage, read> points: array<f32>;
// The f32 parameters (layout in `siren/mod.rs`): the first layer, the biases and the head.
@group(0) @binding(2) var<storage, read> params: array<f32>;
// ω0 · W of hidden layers 1 .. L-1, each [width][width] row major (out, in).
@group(0) @binding(3) var<storage, read> packed: array<f16>;
// Φ per row: Φ per point, or (Φ, ∇Φ) per point with tangents.
@group(0) @binding(4) var<storage, read_write> values: array<f32>;
// `packed`, written by `coop_pack`.
@group(0) @binding(5) var<storage, read_write> packed_out: array<f16>;

// A layer's input activations and its output, [row][feature] each, rows `act_stride` apart.
var<workgroup> act: array<f16, 2u * ACT>;
// The f32 products of the tiles in flight, T × T row major each.
var<workgroup> scratch: array<f32, SLOTS * T * T>;

// Offset in `params` of hidden layer l ≥ 1's weights (its bias follows them).
fn hidden_offset(l: u32, w: u32) -> u32 {
    return 4u * w + (l - 1u) * (w * w + w);
}

// SLOTS subgroups: the host sets WG = SLOTS × the adapter's (fixed) subgroup size.
override WG: u32 = 256u;

@compute @workgroup_size(WG)
fn coop_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(subgroup_id) sg: u32,
) {
    let group = wid.y * nwg.x + wid.x;
    let first = group * u.group_rows;
    // Workgroup-uniform, so the barriers below stay in uniform control flow.
    if first >= u.rows {
        return;
    }
    let w = u.width;
    let ls = u.act_stride;
    let gr = u.group_rows;
    let om = u.omega;
    let last = u.rows - 1u;

    // First layer, from the points (rows past the batch repeat its last row): z = ω0 (W0 x + b0)
    // gives sin(z) on a value row and cos(z) ω0 W0[o][j] on the tangent row of axis j.
    for (var e = lid; e < gr * w; e += WG) {
        let o = e % w;
        let row = min(first + e / w, last);
        let j = select(0u, row % 4u, u.tangents != 0u);
        let q = u.point_stride * select(row, row / 4u, u.tangents != 0u);
        let z = om * (params[3u * o] * points[q] + params[3u * o + 1u] * points[q + 1u]
            + params[3u * o + 2u] * points[q + 2u] + params[3u * w + o]);
        // Both operands of `select` are evaluated: index a weight that exists on value rows.
        let wj = params[3u * o + max(j, 1u) - 1u];
        act[(e / w) * ls + o] = f16(select(cos(z) * om * wj, sin(z), j == 0u));
    }
    workgroupBarrier();

    let tiles_o = w / T;
    let tiles = (gr / T) * tiles_o;
    let rounds = (tiles + SLOTS - 1u) / SLOTS;
    var acc = CC();
    for (var l = 1u; l < u.hidden_layers; l++) {
        let src = ((l - 1u) % 2u) * ACT;
        let dst = (l % 2u) * ACT;
        let woff = (l - 1u) * w * w;
        let boff = hidden_offset(l, w) + w * w;
        for (var r = 0u; r < rounds; r++) {
            // Subgroup sg multiplies tile r·SLOTS + sg. naga wants cooperative operations in
            // workgroup-uniform control flow, so a subgroup past the last tile recomputes it
            // instead of skipping, and the epilogue ignores its slot.
            let t = min(r * SLOTS + sg, tiles - 1u);
            let a0 = src + (t / tiles_o) * T * ls;
            let b0 = woff + (t % tiles_o) * T * w;
            // Assigned, not declared, here: naga hoists a declaration's initialiser.
            acc = CC();
            for (var k = 0u; k < w; k += T) {
                // A(i, kk) = act[a0 + i·ls + k + kk]; B(kk, j) = ω0·W[o0 + j][k + kk].
                let a = coopLoadT<CA>(&act[a0 + k], ls);
                let b = coopLoad<CB>(&packed[b0 + k], w);
                acc = coopMultiplyAdd(a, b, acc);
            }
            coopStoreT(acc, &scratch[sg * T * T], T);
            workgroupBarrier();
            // The epilogue of every slot of this round, by the whole workgroup. A tangent row's
            // value row is in the same tile, i % 4 rows up.
            for (var e = lid; e < SLOTS * T * T; e += WG) {
                let te = r * SLOTS + e / (T * T);
                if te < tiles {
                    let i = (e / T) % T;
                    let o = (te % tiles_o) * T + e % T;
                    let row = (te / tiles_o) * T + i;
                    let j = select(0u, i % 4u, u.tangents != 0u);
                    let z = scratch[e - j * T] + om * params[boff + o];
                    act[dst + row * ls + o] = f16(select(cos(z) * scratch[e], sin(z), j == 0u));
                }
            }
            workgroupBarrier();
        }
    }

    // The linear head, in f32; the bias only on value rows.
    let fin = ((u.hidden_layers - 1u) % 2u) * ACT;
    let hoff = hidden_offset(u.hidden_layers, w);
    for (var r = lid; r < gr && first + r < u.rows; r += WG) {
        var s = 0.0;
        for (var k = 0u; k < w; k++) {
            s = fma(f32(act[fin + r * ls + k]), params[hoff + k], s);
        }
        let value_row = u.tangents == 0u || (first + r) % 4u == 0u;
        values[first + r] = s + select(0.0, params[hoff + w], value_row);
    }
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
