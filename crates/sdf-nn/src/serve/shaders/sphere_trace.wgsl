// Sphere tracing of a neural SDF, one invocation per pixel, Lambert-shaded, into an RGBA8 buffer.
//
// Two passes per band of rows. `cone_trace` marches one cone per tile of TILE × TILE pixels, the
// cone around the tile's centre ray that holds all its pixels' rays, as far as the field leaves
// room for the whole cone, and records that depth; `sphere_trace` then starts each pixel's ray
// there, so the steps through empty space are taken once a tile rather than once a pixel.
//
// This file is not complete on its own: the host prepends a model's snippet from
// `NeuralSdf::wgsl(1)`, which defines `hwsdf_trace` and `hwsdf_normal` (mesh coordinates) and
// binds the weights at @group(1) (for a scene, wrappers of the scene's `scene_trace` and
// `scene_normal`). Everything here is in the mesh's coordinates and units.

struct TraceUniforms {
    // xyz: camera position; w: tan(vertical field of view / 2).
    eye: vec4<f32>,
    // xyz: unit view direction; w: width / height.
    forward: vec4<f32>,
    // xyz: unit camera right; w: hit tolerance per unit distance travelled (a fraction of the
    // pixel footprint, so far surfaces are not traced finer than a pixel resolves).
    right: vec4<f32>,
    // xyz: unit camera up; w: step scale (< 1: neural SDFs are not exact distances).
    up: vec4<f32>,
    // xyz: unit direction towards the light; w: ambient term.
    light: vec4<f32>,
    // rgb: surface colour (linear); a unused.
    albedo: vec4<f32>,
    // rgba: colour of pixels whose ray misses (written as is).
    background: vec4<f32>,
    // The model's box in mesh coordinates; box_min.w: smallest hit tolerance (mesh units);
    // box_max.w: the level c drawn (the surface d = c).
    box_min: vec4<f32>,
    box_max: vec4<f32>,
    // x: width, y: height, z: maximum steps per ray, w: the first row of this dispatch (the
    // host splits large images into bands of rows, one submission each).
    size: vec4<u32>,
    // x: the pixels' over-relaxation factor (1: plain steps); y: the row after this dispatch's
    // band (its cones stop there); zw unused.
    march: vec4<f32>,
}

@group(0) @binding(0) var<uniform> trace: TraceUniforms;
// One packed RGBA8 pixel (R in the low byte) per u32, rows top to bottom.
@group(0) @binding(1) var<storage, read_write> trace_image: array<u32>;
// Per tile (rows of tiles, top to bottom): a depth along every ray of the tile before which no
// ray of it meets the surface (0 where no cone pass ran).
@group(0) @binding(2) var<storage, read_write> tile_start: array<f32>;

// This invocation's slot in the scratch of SIREN snippets in the scratch form (unused by the
// others): its index among the dispatch's pixels or cones.
var<private> sdf_slot: u32;

// Pixels per side of a workgroup of `sphere_trace` (bands of rows are made of them), and of
// the tile whose rays one cone of `cone_trace` holds.
const TILE: u32 = 8u;
const CONE_TILE: u32 = 8u;

// The unit direction of the ray through image point (x, y), in pixels from the top left corner
// (a pixel's centre is at +0.5).
fn ray_direction(x: f32, y: f32) -> vec3<f32> {
    let ndc = vec2<f32>(
        x / f32(trace.size.x) * 2.0 - 1.0,
        1.0 - y / f32(trace.size.y) * 2.0,
    );
    let tan_half = trace.eye.w;
    return normalize(
        trace.forward.xyz
            + ndc.x * tan_half * trace.forward.w * trace.right.xyz
            + ndc.y * tan_half * trace.up.xyz,
    );
}

// Entry and exit distances of the ray o + t·d through the box (exit < entry: a miss).
fn trace_box(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    // A huge reciprocal instead of 1/0 keeps the slab test finite on every driver.
    let big = vec3<f32>(1e30);
    let inv = select(1.0 / d, select(-big, big, d >= vec3<f32>(0.0)), abs(d) < vec3<f32>(1e-30));
    let t0 = (trace.box_min.xyz - o) * inv;
    let t1 = (trace.box_max.xyz - o) * inv;
    let lo = min(t0, t1);
    let hi = max(t0, t1);
    return vec2<f32>(max(max(lo.x, lo.y), max(lo.z, 0.0)), min(min(hi.x, hi.y), hi.z));
}

@compute @workgroup_size(8, 8)
fn sphere_trace(@builtin(global_invocation_id) gid: vec3<u32>) {
    let width = trace.size.x;
    let height = trace.size.y;
    let y = gid.y + trace.size.w;
    if gid.x >= width || y >= height {
        return;
    }
    sdf_slot = gid.y * width + gid.x;
    let dir = ray_direction(f32(gid.x) + 0.5, f32(y) + 0.5);
    let origin = trace.eye.xyz;

    var color = trace.background;
    let span = trace_box(origin, dir);
    if span.x <= span.y {
        // Outside the box the SDF is at least the distance to the box, so starting at the box
        // skips nothing; the first step is then a real network evaluation. Nor does starting
        // where the tile's cone stopped.
        let tiles_x = (width + CONE_TILE - 1u) / CONE_TILE;
        var t = max(span.x, tile_start[(y / CONE_TILE) * tiles_x + gid.x / CONE_TILE]);
        var hit = false;
        // Over-relaxed steps (Keinert et al. 2014): march.x times the room while the free
        // spheres of consecutive points overlap, so that the segment between them is free. Where
        // they do not, or where a long step left the box, the surface may lie in the gap: back
        // to the previous point, and plain steps from there on.
        // Spheres that only touch do not count: an unsigned field's sheet (room 0 on it) met
        // head-on lies exactly where they touch.
        var omega = trace.march.x;
        var prev_room = 0.0;
        var prev_step = 0.0;
        for (var i = 0u; i < trace.size.z; i++) {
            if t > span.y {
                if omega == 1.0 {
                    break;
                }
                // A long step left the box (or the cone's start lies past it): the plain one.
                t += prev_room - prev_step;
                prev_step = prev_room;
                omega = 1.0;
                if t > span.y {
                    break;
                }
            }
            // x: the distance less the level; y: the step (with the sign of x).
            let traced = hwsdf_trace(origin + t * dir, trace.box_max.w);
            let room = traced.y * trace.up.w;
            if omega > 1.0 && prev_step > 0.0 && room + prev_room < prev_step * 1.001 {
                t += prev_room - prev_step;
                prev_step = prev_room;
                omega = 1.0;
                continue;
            }
            if traced.x < max(trace.right.w * t, trace.box_min.w) {
                hit = true;
                break;
            }
            prev_room = room;
            prev_step = omega * room;
            t += prev_step;
        }
        if hit {
            let n = hwsdf_normal(origin + t * dir);
            let lambert = max(dot(n, trace.light.xyz), 0.0);
            let ambient = trace.light.w;
            let linear = trace.albedo.rgb * (ambient + (1.0 - ambient) * lambert);
            // Approximate sRGB encoding so the PNG looks right in viewers.
            color = vec4<f32>(pow(clamp(linear, vec3<f32>(0.0), vec3<f32>(1.0)), vec3<f32>(1.0 / 2.2)), 1.0);
        }
    }
    trace_image[y * width + gid.x] = pack4x8unorm(color);
}

// One cone per tile (invocation (i, j): the tile i of the band's tile row j). The cone's axis
// is the ray through the tile's centre; every ray of the tile leaves from the eye at an angle
// of at most α to it, so at depth t it lies within t·tan α of the axis point. Where the
// field's step s (the room around the axis point, scaled as the pixels' steps are) exceeds
// that radius, every ray of the tile can advance s − t·tan α. The march stops once the room
// falls below 1.5 radii (the pixels then separate; stopping at 3 radii left a CPU model of the
// example scene's rays 18 % more evaluations), inside the surface, or past the box.
@compute @workgroup_size(8, 8)
fn cone_trace(@builtin(global_invocation_id) gid: vec3<u32>) {
    let width = trace.size.x;
    let height = trace.size.y;
    let tiles_x = (width + CONE_TILE - 1u) / CONE_TILE;
    let row = gid.y + trace.size.w / CONE_TILE;
    if gid.x >= tiles_x || row * CONE_TILE >= min(height, u32(trace.march.y)) {
        return;
    }
    sdf_slot = gid.y * tiles_x + gid.x;
    let lo = vec2<f32>(f32(gid.x * CONE_TILE), f32(row * CONE_TILE));
    let hi = vec2<f32>(
        f32(min(gid.x * CONE_TILE + CONE_TILE, width)),
        f32(min(row * CONE_TILE + CONE_TILE, height)),
    );
    let axis = ray_direction(0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y));
    // tan α from the corners (the widest rays), through the cross product: 1 − cos α is below
    // f32's resolution for a tile a few pixels wide.
    var spread = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let corner = ray_direction(select(lo.x, hi.x, (k & 1u) != 0u), select(lo.y, hi.y, (k & 2u) != 0u));
        spread = max(spread, length(cross(axis, corner)) / dot(axis, corner));
    }
    // Rounding margin on the radius.
    spread = spread * 1.01 + 1e-6;
    let origin = trace.eye.xyz;
    // Past the box's farthest corner no ray of the tile is in the box.
    let far = length(max(abs(trace.box_min.xyz - origin), abs(trace.box_max.xyz - origin)));
    var t = 0.0;
    for (var i = 0u; i < trace.size.z; i++) {
        let traced = hwsdf_trace(origin + t * axis, trace.box_max.w);
        let room = traced.y * trace.up.w;
        let radius = t * spread;
        // Negated comparisons: a NaN (a broken model) stops the cone where it is.
        if !(traced.x > 0.0) || !(room >= 1.5 * radius + trace.box_min.w) {
            break;
        }
        t += room - radius;
        if !(t <= far) {
            break;
        }
    }
    tile_start[row * tiles_x + gid.x] = t;
}
