// NGLOD's and the hash grid's addressing, shared by nglod_forward.wgsl, nglod_train.wgsl and the
// one-per-subgroup kernels. Each of them declares the sparse levels' vertex table `table` (a u32
// storage array).
//
// A level is (resolution r, offset of its features in params, z, kind):
//   kind 0, dense: every vertex, row-major (z unused);
//   kind 1, sparse: its band's vertices only, `table[z + vertex]` maps each vertex of the level to
//     its slot or to NO_SLOT;
//   kind 2, hashed: a table of z + 1 entries (a power of two), entry hash(vertex) & z, the
//     spatial hash of instant-ngp (nglod/mod.rs, hash_vertex).
// Each vertex keeps FL features. The MLP's input has F values: the levels' features summed
// (ZS = 0) or concatenated (ZS = FL, level l at l·FL).

const NO_SLOT: u32 = 0xffffffffu;

// Features per vertex of a level.
override FL: u32 = 8u;
// Where level l's features start in the MLP's input: l·ZS.
override ZS: u32 = 0u;

// Where vertex v of level lv keeps its first feature in params, or NO_SLOT for a sparse level's
// vertex outside its band (whose features are zero).
fn vertex_base(lv: vec4<u32>, v: vec3<u32>) -> u32 {
    if lv.w == 2u {
        return lv.y + ((v.x ^ (v.y * 2654435761u) ^ (v.z * 805459861u)) & lv.z) * FL;
    }
    let s = lv.x + 1u;
    let linear = (v.x * s + v.y) * s + v.z;
    var slot = linear;
    if lv.w != 0u {
        slot = table[lv.z + linear];
        if slot == NO_SLOT {
            return NO_SLOT;
        }
    }
    return lv.y + slot * FL;
}

// Where p (normalised) falls in a level of `res` cells per axis: the cell's first vertex, the
// position within the cell (0..1 per axis), and that position's derivative in p (r/2 inside
// the box, 0 along an axis where p is clamped to it).
struct GridCell {
    i0: vec3<u32>,
    t: vec3<f32>,
    du: vec3<f32>,
}

fn grid_cell(p: vec3<f32>, res: u32) -> GridCell {
    let r = f32(res);
    let u = (p + 1.0) * 0.5 * r;
    let uvw = clamp(u, vec3<f32>(0.0), vec3<f32>(r));
    // du/dx = r/2 in the box, faces included (the inside's derivative: a box-shaped mesh's faces
    // lie on them), 0 on an axis where the point is clamped.
    let du = select(vec3<f32>(0.0), vec3<f32>(0.5 * r), (u >= vec3<f32>(0.0)) & (u <= vec3<f32>(r)));
    // min() keeps the index in range even for NaN input (the shaders run without bounds checks).
    let i0 = min(vec3<u32>(floor(uvw)), vec3<u32>(res - 1u));
    return GridCell(i0, uvw - vec3<f32>(i0), du);
}

// Corner c (0..8) of a cell, as an offset from its first vertex.
fn corner_offset(c: u32) -> vec3<u32> {
    return vec3<u32>((c >> 2u) & 1u, (c >> 1u) & 1u, c & 1u);
}

// Corner c's trilinear weight (x) and the weight's gradient in p (yzw).
fn corner_weight(cell: GridCell, c: u32) -> vec4<f32> {
    let hi = corner_offset(c) == vec3<u32>(1u);
    let wv = select(1.0 - cell.t, cell.t, hi);
    let dw = select(vec3<f32>(-1.0), vec3<f32>(1.0), hi)
        * vec3<f32>(wv.y * wv.z, wv.x * wv.z, wv.x * wv.y) * cell.du;
    return vec4<f32>(wv.x * wv.y * wv.z, dw);
}

// How a subgroup of `lanes` lanes shares one point's corners (the one-point- and one-row-per-
// subgroup kernels): lanes 8g..8g+7 take the levels l with l % (lanes / 8) == g, one corner
// each, and a subgroup narrower than 8 loops over the corners. Level l's corners for `lane`
// run from x (8: none) in steps of y. Every (level, corner) falls to exactly one lane.
fn lane_corners(lane: u32, lanes: u32, l: u32) -> vec2<u32> {
    let first = select(8u, lane % 8u, lane / 8u == l % max(lanes / 8u, 1u));
    return vec2<u32>(first, min(lanes, 8u));
}
