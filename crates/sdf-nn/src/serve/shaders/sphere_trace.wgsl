// Sphere tracing of a neural SDF, one invocation per pixel, Lambert-shaded, into an RGBA8 buffer.
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
}

@group(0) @binding(0) var<uniform> trace: TraceUniforms;
// One packed RGBA8 pixel (R in the low byte) per u32, rows top to bottom.
@group(0) @binding(1) var<storage, read_write> trace_image: array<u32>;

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
    // Pixel centre on the image plane at distance 1 in front of the camera.
    let ndc = vec2<f32>(
        (f32(gid.x) + 0.5) / f32(width) * 2.0 - 1.0,
        1.0 - (f32(y) + 0.5) / f32(height) * 2.0,
    );
    let tan_half = trace.eye.w;
    let dir = normalize(
        trace.forward.xyz
            + ndc.x * tan_half * trace.forward.w * trace.right.xyz
            + ndc.y * tan_half * trace.up.xyz,
    );
    let origin = trace.eye.xyz;

    var color = trace.background;
    let span = trace_box(origin, dir);
    if span.x <= span.y {
        // Outside the box the SDF is at least the distance to the box, so starting at the box
        // skips nothing; the first step is then a real network evaluation.
        var t = span.x;
        var hit = false;
        for (var i = 0u; i < trace.size.z; i++) {
            // x: the distance less the level; y: the step (with the sign of x).
            let traced = hwsdf_trace(origin + t * dir, trace.box_max.w);
            if traced.x < max(trace.right.w * t, trace.box_min.w) {
                hit = true;
                break;
            }
            t += traced.y * trace.up.w;
            if t > span.y {
                break;
            }
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
