// NGLOD's grid addressing, shared by nglod_forward.wgsl and nglod_train_{atomic,cas}.wgsl. Each of
// them declares `F` and the sparse levels' vertex table `table` (a u32 storage array).
//
// A level is (resolution r, offset of its features in params, offset of its table in `table`,
// 1 if sparse). A dense level stores every vertex; a sparse level stores only its band's
// vertices, and `table` maps each vertex of the level to its slot or to NO_SLOT.

const NO_SLOT: u32 = 0xffffffffu;

// Where vertex v of level lv keeps its first feature in params, or NO_SLOT for a sparse level's
// vertex outside its band (whose features are zero).
fn vertex_base(lv: vec4<u32>, v: vec3<u32>) -> u32 {
    let s = lv.x + 1u;
    let linear = (v.x * s + v.y) * s + v.z;
    var slot = linear;
    if lv.w != 0u {
        slot = table[lv.z + linear];
        if slot == NO_SLOT {
            return NO_SLOT;
        }
    }
    return lv.y + slot * F;
}
