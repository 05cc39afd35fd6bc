// NGLOD's and the hash grid's addressing, shared by nglod_forward.wgsl and
// nglod_train_{atomic,cas}.wgsl. Each of them declares the sparse levels' vertex table `table`
// (a u32 storage array).
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
