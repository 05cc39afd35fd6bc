// A batch's points grouped by cell on the GPU, for the ground-truth kernels: a counting sort by
// the Morton code of each point's cell in a grid over a box, of 2^bits cells per axis (the host
// picks about one cell per point, at most 64³ cells). Neighbouring invocations of the
// kernels then query neighbouring points, so a SIMD group walks mostly the same BVH and winding
// nodes (fewer divergent steps, nodes in cache) instead of 32 random corners of the box. The
// twin of `ground_truth/bin.rs`'s `cell_key`.
//
// Launches, over counts cleared by the host: `bin_count` (a histogram), `bin_scan` (one
// workgroup: the counts become each cell's first slot), `bin_scatter` (each point takes the next
// slot of its cell). The order within a cell follows the atomics' race; the kernels that read
// `order` write each result at the point's own index, so their output does not depend on it.

const WG: u32 = 64u;
const SCAN_WG: u32 = 256u;
// The most cells (64³): the count buffer's length.
const MAX_CELLS: u32 = 262144u;

struct BinParams {
    n_points: u32,
    // Bits per axis (at most 6) and cells in all (8^bits).
    bits: u32,
    n_cells: u32,
    _pad0: u32,
    // The grid's corner and cells per unit length (finite, positive).
    lo: vec3<f32>,
    _pad1: f32,
    scale: vec3<f32>,
    _pad2: f32,
}

@group(0) @binding(0) var<uniform> bp: BinParams;
// 3 floats per point.
@group(0) @binding(1) var<storage, read> bin_points: array<f32>;
@group(0) @binding(2) var<storage, read_write> cell_counts: array<atomic<u32>, MAX_CELLS>;
// Point indices, grouped by cell.
@group(0) @binding(3) var<storage, read_write> order: array<u32>;

var<workgroup> block_sums: array<u32, SCAN_WG>;

fn bin_index(wid: vec3<u32>, nwg: vec3<u32>, lid: vec3<u32>) -> u32 {
    return (wid.y * nwg.x + wid.x) * WG + lid.x;
}

// The low 10 bits of v, two zero bits between each.
fn spread10(v: u32) -> u32 {
    var x = v & 0x3ffu;
    x = (x | (x << 16u)) & 0x030000ffu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

// The Morton code of point i's cell; points outside the box go to the nearest cell, points with
// a non-finite coordinate to the last (the kernels skip them).
fn cell_key(i: u32) -> u32 {
    let p = vec3<f32>(bin_points[3u * i], bin_points[3u * i + 1u], bin_points[3u * i + 2u]);
    let e = vec3<u32>(0x7f800000u);
    if any((bitcast<vec3<u32>>(p) & e) == e) {
        return bp.n_cells - 1u;
    }
    // p - lo may overflow to ±inf, never NaN (scale is finite and positive): clamp takes it.
    let top = f32((1u << bp.bits) - 1u);
    let c = vec3<u32>(clamp((p - bp.lo) * bp.scale, vec3<f32>(0.0), vec3<f32>(top)));
    // The min keeps any key in the cleared counts should a conversion go wrong.
    return min((spread10(c.x) << 2u) | (spread10(c.y) << 1u) | spread10(c.z), bp.n_cells - 1u);
}

@compute @workgroup_size(WG)
fn bin_count(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = bin_index(wid, nwg, lid);
    if i < bp.n_points {
        atomicAdd(&cell_counts[cell_key(i)], 1u);
    }
}

// Exclusive prefix sum of the counts in place, by one workgroup: each invocation sums a run of
// cells, the runs' sums are scanned in workgroup memory, each run is rewritten.
@compute @workgroup_size(SCAN_WG)
fn bin_scan(@builtin(local_invocation_index) t: u32) {
    let run = (bp.n_cells + SCAN_WG - 1u) / SCAN_WG;
    let first = min(t * run, bp.n_cells);
    let end = min(first + run, bp.n_cells);
    var own = 0u;
    for (var j = first; j < end; j++) {
        own += atomicLoad(&cell_counts[j]);
    }
    block_sums[t] = own;
    workgroupBarrier();
    // Hillis–Steele: after the step of width `w`, entry t holds the sum of entries t-2w+1..t.
    for (var w = 1u; w < SCAN_WG; w <<= 1u) {
        var v = block_sums[t];
        if t >= w {
            v += block_sums[t - w];
        }
        workgroupBarrier();
        block_sums[t] = v;
        workgroupBarrier();
    }
    var next = block_sums[t] - own;
    for (var j = first; j < end; j++) {
        let c = atomicLoad(&cell_counts[j]);
        atomicStore(&cell_counts[j], next);
        next += c;
    }
}

@compute @workgroup_size(WG)
fn bin_scatter(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = bin_index(wid, nwg, lid);
    if i < bp.n_points {
        order[atomicAdd(&cell_counts[cell_key(i)], 1u)] = i;
    }
}
