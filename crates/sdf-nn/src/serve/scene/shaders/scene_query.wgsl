// Batch queries of a scene, one invocation per point or ray: distances, distances with
// gradients, sphere-traced rays and closest points. Each query's work on element e is a
// function (`*_element`), which `scene_query_subgroup.wgsl` also calls with one element per
// subgroup; `lead` says whether this invocation writes the element's outputs. The host prepends the scene's snippet
// (`Scene::wgsl_with_prefix(1, "scene", ..)`), which defines `scene_distance`, `scene_sample`
// and the `scene_Sample` type and binds the weights at @group(1). The meaning of every query is
// the CPU reference's (`serve/scene/cpu.rs`), in f32.

struct SceneQuery {
    // Points or rays in this dispatch.
    count: u32,
    // Sphere-tracing steps per ray at most.
    max_steps: u32,
    // Projection steps per point at most.
    max_iterations: u32,
    // The first element of this dispatch in the buffers.
    first: u32,
    // The level c: every query answers for d - c.
    level: f32,
    // Hit or convergence tolerance on |d - c|.
    tolerance: f32,
    // Rays' over-relaxation factor in [1, 2) (1: plain steps).
    over_relaxation: f32,
    _pad0: f32,
}

@group(0) @binding(0) var<uniform> query: SceneQuery;
// Points: (x, y, z, unused). Rays: two per ray, (origin, max_distance), (direction, unused).
@group(0) @binding(1) var<storage, read> query_in: array<vec4<f32>>;
// Per element: distance (1 float), sample (5: d, gradient, leaf), hit (10: hit, t, point,
// normal, leaf, steps), closest point (7: point, residual, iterations, converged, leaf).
// Integers are stored bit for bit (bitcast).
@group(0) @binding(2) var<storage, read_write> query_out: array<f32>;

const QUERY_WG: u32 = 64u;

// This invocation's slot in the scratch of SIREN snippets in the scratch form (unused by the
// others): its index in the dispatch.
var<private> sdf_slot: u32;

fn query_index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.y * nwg.x + wid.x) * QUERY_WG + lid;
}

// Whether x is NaN or infinite (WGSL has no isnan; compilers may fold x != x away).
fn query_non_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) == 0x7f800000u;
}

// The query a pipeline runs (SceneQueryKind): 0 distance, 1 sample, 2 trace, 3 project.
override KIND: u32 = 0u;

// The query of this pipeline on element e; `lead`: this invocation writes the outputs.
fn query_element(e: u32, lead: bool) {
    switch KIND {
        case 0u: {
            distance_element(e, lead);
        }
        case 1u: {
            sample_element(e, lead);
        }
        case 2u: {
            trace_element(e, lead);
        }
        default: {
            project_element(e, lead);
        }
    }
}

@compute @workgroup_size(64)
fn query_per_invocation(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = query_index(wid, nwg, lid);
    sdf_slot = i;
    if i < query.count {
        query_element(query.first + i, true);
    }
}

fn distance_element(e: u32, lead: bool) {
    let d = scene_distance(query_in[e].xyz) - query.level;
    if lead {
        query_out[e] = d;
    }
}

fn sample_element(e: u32, lead: bool) {
    let s = scene_sample(query_in[e].xyz);
    if lead {
        let o = 5u * e;
        query_out[o] = s.d - query.level;
        query_out[o + 1u] = s.g.x;
        query_out[o + 2u] = s.g.y;
        query_out[o + 3u] = s.g.z;
        query_out[o + 4u] = bitcast<f32>(s.leaf);
    }
}

// How far a ray goes from the point it counts from before it starts again from where it is:
// at t = 2000 the points origin + dir * t are 2^-13 apart, coarser than the default tolerance
// (1e-4), and a ray fired from that far stalled short of the surface. Below it (every ray that
// starts near the scene) the arithmetic is origin + dir * t, as it was, step for step the CPU's.
const TRACE_REBASE: f32 = 256.0;

fn trace_element(e: u32, lead: bool) {
    var origin = query_in[2u * e].xyz;
    let max_distance = query_in[2u * e].w;
    let dir = normalize(query_in[2u * e + 1u].xyz);
    // t of `origin`: the ray's distance is t0 + t.
    var t0 = 0.0;
    var t = 0.0;
    var steps = 0u;
    var hit = false;
    // Over-relaxed steps, as the CPU's `March` takes them: omega times the room while the
    // free spheres of consecutive points overlap (by more than a thousandth of the step);
    // else back to the previous point, and plain steps from there on.
    var omega = query.over_relaxation;
    var prev_room = 0.0;
    var prev_step = 0.0;
    for (var step = 0u; step < query.max_steps; step++) {
        // (|t|: an over-relaxed step that failed its check goes back, far, from a new start.)
        if abs(t) > TRACE_REBASE {
            origin += dir * t;
            t0 += t;
            t = 0.0;
        }
        // x: d - c; y: the step bound (the radius of a ball free of the level set, with the
        // sign of x).
        let traced = scene_trace(origin + dir * t, query.level);
        let gap = traced.x;
        let room = abs(traced.y);
        steps = step + 1u;
        // A NaN room (a broken model) proves no overlap either.
        if omega > 1.0 && prev_step > 0.0 && !(room + prev_room >= prev_step * 1.001) {
            t += prev_room - prev_step;
            prev_step = prev_room;
            omega = 1.0;
            continue;
        }
        if abs(gap) <= query.tolerance {
            hit = true;
            break;
        }
        // NaN from a broken model ends the ray as a miss.
        if query_non_finite(gap) {
            break;
        }
        prev_room = room;
        prev_step = omega * room;
        t += prev_step;
        if !(t0 + t <= max_distance) && omega > 1.0 {
            // A long step went past the end: the plain one may not have.
            t += prev_room - prev_step;
            prev_step = prev_room;
            omega = 1.0;
        }
        if !(t0 + t <= max_distance) {
            break;
        }
    }
    var s = scene_Sample(0.0, vec3<f32>(0.0), 0u);
    let p = origin + dir * t;
    if hit {
        s = scene_sample(p);
    }
    if !lead {
        return;
    }
    let o = 10u * e;
    if hit {
        let len = length(s.g);
        var n = -dir;
        if len > 0.0 {
            n = s.g / len;
        }
        query_out[o] = 1.0;
        query_out[o + 1u] = t0 + t;
        query_out[o + 2u] = p.x;
        query_out[o + 3u] = p.y;
        query_out[o + 4u] = p.z;
        query_out[o + 5u] = n.x;
        query_out[o + 6u] = n.y;
        query_out[o + 7u] = n.z;
        query_out[o + 8u] = bitcast<f32>(s.leaf);
    } else {
        for (var k = 0u; k < 9u; k++) {
            query_out[o + k] = 0.0;
        }
    }
    query_out[o + 9u] = bitcast<f32>(steps);
}

fn project_element(e: u32, lead: bool) {
    var x = query_in[e].xyz;
    var iteration = 0u;
    loop {
        let s = scene_sample(x);
        let gap = s.d - query.level;
        let g2 = dot(s.g, s.g);
        let converged = abs(gap) < query.tolerance;
        // A vanished gradient or a NaN cannot be stepped from.
        if converged || iteration == query.max_iterations || g2 < 1e-24 || query_non_finite(gap) {
            if lead {
                let o = 7u * e;
                query_out[o] = x.x;
                query_out[o + 1u] = x.y;
                query_out[o + 2u] = x.z;
                query_out[o + 3u] = abs(gap);
                query_out[o + 4u] = bitcast<f32>(iteration);
                query_out[o + 5u] = select(0.0, 1.0, converged);
                query_out[o + 6u] = bitcast<f32>(s.leaf);
            }
            return;
        }
        x -= s.g * (gap / g2);
        iteration++;
    }
}
