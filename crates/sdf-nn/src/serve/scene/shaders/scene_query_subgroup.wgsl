// The queries of scene_query.wgsl with one element per subgroup: every lane of a subgroup takes
// the same point or ray through the scene's straight-line code (so its branches stay uniform),
// and each model it evaluates is shared among the lanes (the scene snippet's Lanes::Subgroup
// form: trilinear gathers and hidden units split, then summed). A few thousand points or rays
// then keep a GPU busy with short evaluations instead of one long one per invocation. Lane 0
// writes the outputs.
//
// Element of an invocation: its workgroup's first element plus its subgroup's index. The host
// dispatches enough workgroups for the widest subgroup the adapter may use.

@compute @workgroup_size(64)
fn query_per_subgroup(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(subgroup_id) sid: u32,
    @builtin(num_subgroups) subgroups: u32,
    @builtin(subgroup_invocation_id) lane: u32,
    @builtin(subgroup_size) lanes: u32,
) {
    let i = (wid.y * nwg.x + wid.x) * subgroups + sid;
    if i < query.count {
        scene_lane = lane;
        scene_lanes = lanes;
        query_element(query.first + i, lane == 0u);
    }
}
