// The queries of scene_query.wgsl with one element per subgroup: every lane of a subgroup takes
// the same point or ray through the scene's straight-line code (so its branches stay uniform),
// and each model it evaluates is shared among the lanes (the scene snippet's Lanes::Subgroup
// form: trilinear gathers and hidden units split, then summed). A few thousand points or rays
// then keep a GPU busy with short evaluations instead of one long one per invocation. Lane 0
// writes the outputs.
//
// Elements per workgroup: 64 over the widest subgroup the adapter may run, as the host counts
// them. The workgroup's subgroups share out its slice whatever width the hardware runs (fewer
// subgroups take several elements each, more leave some idle).
override PER_GROUP: u32 = 1u;

@compute @workgroup_size(64)
fn query_per_subgroup(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(subgroup_id) sid: u32,
    @builtin(num_subgroups) subgroups: u32,
    @builtin(subgroup_invocation_id) lane: u32,
    @builtin(subgroup_size) lanes: u32,
    @builtin(local_invocation_index) lid: u32,
) {
    let first = (wid.y * nwg.x + wid.x) * PER_GROUP;
    // Every lane evaluates a SIREN whole (Lanes::Subgroup): each its own scratch slot.
    sdf_slot = query_index(wid, nwg, lid);
    scene_lane = lane;
    scene_lanes = lanes;
    for (var k = sid; k < PER_GROUP && first + k < query.count; k += subgroups) {
        query_element(query.first + first + k, lane == 0u);
    }
}
