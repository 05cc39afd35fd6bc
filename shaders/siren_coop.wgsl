// SIREN inference on cooperative matrices (`LayerKernels::CoopF16`: tensor cores from WGSL),
// in one dispatch. Appended to a tile file (`siren_coop_16x16.wgsl`, `siren_coop_8x8.wgsl`)
// that enables f16 and cooperative matrices and defines the tile types CA, CB, CC, their side
// T, the activation buffer size ACT and the number of scratch SLOTS.
//
// A workgroup takes `group_points` points through every layer:
// - the first layer (3 → width) in f32 from the points, stored as f16 activations;
// - each hidden layer as tiles of T points × T outputs: A = T points' activations (f16, row
//   major in workgroup memory), B = T rows of ω0·W (f16, packed by `coop_pack`), accumulated
//   in f32 over the width. The workgroup's SLOTS subgroups each take one tile at a time and
//   store it to f32 scratch, then the whole workgroup adds ω0·b, takes the sine and writes the
//   f16 activations of the next layer into the other half of `act`;
// - the linear head in f32, one point per invocation.
// ω0 is folded into the packed weights so that tiny trained weights stay normal f16 numbers.

struct Coop {
    points: u32,
    // A multiple of T with group_points · width ≤ ACT.
    group_points: u32,
    // A multiple of T.
    width: u32,
    hidden_layers: u32,
    omega: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Coop;
// Three floats per point.
@group(0) @binding(1) var<storage, read> points: array<f32>;
// The f32 parameters (layout in `siren/mod.rs`): the first layer, the biases and the head.
@group(0) @binding(2) var<storage, read> params: array<f32>;
// ω0 · W of hidden layers 1 .. L-1, each [width][width] row major (out, in).
@group(0) @binding(3) var<storage, read> packed: array<f16>;
@group(0) @binding(4) var<storage, read_write> values: array<f32>;
// `packed`, written by `coop_pack`.
@group(0) @binding(5) var<storage, read_write> packed_out: array<f16>;

// A layer's input activations and its output, [point][feature] each.
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
    let first = group * u.group_points;
    // Workgroup-uniform, so the barriers below stay in uniform control flow.
    if first >= u.points {
        return;
    }
    let w = u.width;
    let gp = u.group_points;
    let om = u.omega;
    let last = u.points - 1u;

    // First layer, from the points (the rows past the batch repeat its last point).
    for (var e = lid; e < gp * w; e += WG) {
        let o = e % w;
        let q = 3u * min(first + e / w, last);
        let z = params[3u * o] * points[q] + params[3u * o + 1u] * points[q + 1u]
            + params[3u * o + 2u] * points[q + 2u] + params[3u * w + o];
        act[e] = f16(sin(om * z));
    }
    workgroupBarrier();

    let tiles_o = w / T;
    let tiles = (gp / T) * tiles_o;
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
            let a0 = src + (t / tiles_o) * T * w;
            let b0 = woff + (t % tiles_o) * T * w;
            // Assigned, not declared, here: naga hoists a declaration's initialiser.
            acc = CC();
            for (var k = 0u; k < w; k += T) {
                // A(i, kk) = act[a0 + i·w + k + kk]; B(kk, j) = ω0·W[o0 + j][k + kk].
                let a = coopLoadT<CA>(&act[a0 + k], w);
                let b = coopLoad<CB>(&packed[b0 + k], w);
                acc = coopMultiplyAdd(a, b, acc);
            }
            coopStoreT(acc, &scratch[sg * T * T], T);
            workgroupBarrier();
            // The epilogue of every slot of this round, by the whole workgroup.
            for (var e = lid; e < SLOTS * T * T; e += WG) {
                let te = r * SLOTS + e / (T * T);
                if te < tiles {
                    let o = (te % tiles_o) * T + e % T;
                    let p = (te / tiles_o) * T + (e / T) % T;
                    act[dst + p * w + o] = f16(sin(scratch[e] + om * params[boff + o]));
                }
            }
            workgroupBarrier();
        }
    }

    // The linear head, in f32.
    let fin = ((u.hidden_layers - 1u) % 2u) * ACT;
    let hoff = hidden_offset(u.hidden_layers, w);
    for (var p = lid; p < gp && first + p < u.points; p += WG) {
        var s = 0.0;
        for (var k = 0u; k < w; k++) {
            s = fma(f32(act[fin + p * w + k]), params[hoff + k], s);
        }
        values[first + p] = s + params[hoff + w];
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
