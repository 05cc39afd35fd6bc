// The analytic primitives of a scene, in f32, each returning (distance, gradient) in its own
// frame: the same formulas and medial-set rules as `primitive.rs` (which computes in f64).
// Every name starts with `hwsdf_`; the scene's prefix replaces it.

// `v / |v|`, or `fallback` where |v| is zero (glam's `normalize_or`).
fn hwsdf_normalize_or(v: vec3<f32>, fallback: vec3<f32>) -> vec3<f32> {
    let len = length(v);
    if len > 0.0 {
        return v / len;
    }
    return fallback;
}

fn hwsdf_sphere(p: vec3<f32>, radius: f32) -> vec4<f32> {
    return vec4<f32>(length(p) - radius, hwsdf_normalize_or(p, vec3<f32>(0.0, 1.0, 0.0)));
}

fn hwsdf_box(p: vec3<f32>, b: vec3<f32>) -> vec4<f32> {
    let s = select(vec3<f32>(1.0), vec3<f32>(-1.0), p < vec3<f32>(0.0));
    let q = abs(p) - b;
    let o = max(q, vec3<f32>(0.0));
    let len = length(o);
    if len > 0.0 {
        return vec4<f32>(len, o * s / len);
    }
    // Inside: the nearest face is that of the largest (least negative) component.
    if q.x >= q.y && q.x >= q.z {
        return vec4<f32>(q.x, s.x, 0.0, 0.0);
    }
    if q.y >= q.z {
        return vec4<f32>(q.y, 0.0, s.y, 0.0);
    }
    return vec4<f32>(q.z, 0.0, 0.0, s.z);
}

fn hwsdf_round_box(p: vec3<f32>, b: vec3<f32>, radius: f32) -> vec4<f32> {
    let v = hwsdf_box(p, b - vec3<f32>(radius));
    return vec4<f32>(v.x - radius, v.yzw);
}

fn hwsdf_capsule(p: vec3<f32>, a: vec3<f32>, b: vec3<f32>, radius: f32) -> vec4<f32> {
    let pa = p - a;
    let ba = b - a;
    let len2 = dot(ba, ba);
    var h = 0.0;
    if len2 > 0.0 {
        h = clamp(dot(pa, ba) / len2, 0.0, 1.0);
    }
    let v = pa - ba * h;
    return vec4<f32>(length(v) - radius, hwsdf_normalize_or(v, vec3<f32>(0.0, 1.0, 0.0)));
}

fn hwsdf_torus(p: vec3<f32>, major: f32, minor: f32) -> vec4<f32> {
    let xz = vec3<f32>(p.x, 0.0, p.z);
    let rho = length(xz);
    let radial = hwsdf_normalize_or(xz, vec3<f32>(1.0, 0.0, 0.0));
    let q = vec2<f32>(rho - major, p.y);
    let ql = length(q);
    var w = vec2<f32>(1.0, 0.0);
    if ql > 0.0 {
        w = q / ql;
    }
    return vec4<f32>(ql - minor, radial * w.x + vec3<f32>(0.0, w.y, 0.0));
}

// `n` is unit length (normalised by the host in f64).
fn hwsdf_plane(p: vec3<f32>, n: vec3<f32>, offset: f32) -> vec4<f32> {
    return vec4<f32>(dot(p, n) - offset, n);
}

fn hwsdf_cylinder(p: vec3<f32>, radius: f32, half_height: f32) -> vec4<f32> {
    let xz = vec3<f32>(p.x, 0.0, p.z);
    let rho = length(xz);
    let radial = hwsdf_normalize_or(xz, vec3<f32>(1.0, 0.0, 0.0));
    let axial = vec3<f32>(0.0, select(1.0, -1.0, p.y < 0.0), 0.0);
    let d = vec2<f32>(rho - radius, abs(p.y) - half_height);
    let o = max(d, vec2<f32>(0.0));
    let len = length(o);
    if len > 0.0 {
        return vec4<f32>(len, (radial * o.x + axial * o.y) / len);
    }
    if d.x > d.y {
        return vec4<f32>(d.x, radial);
    }
    return vec4<f32>(d.y, axial);
}

// A value of the scene with its gradient (scene frame) and the leaf that decides it.
struct hwsdf_Sample {
    d: f32,
    g: vec3<f32>,
    leaf: u32,
}

fn hwsdf_pick_min(a: hwsdf_Sample, b: hwsdf_Sample) -> hwsdf_Sample {
    if b.d < a.d {
        return b;
    }
    return a;
}

fn hwsdf_pick_max(a: hwsdf_Sample, b: hwsdf_Sample) -> hwsdf_Sample {
    if b.d > a.d {
        return b;
    }
    return a;
}

fn hwsdf_negate(a: hwsdf_Sample) -> hwsdf_Sample {
    return hwsdf_Sample(-a.d, -a.g, a.leaf);
}

// The polynomial smooth minimum min(a, b) - h^2 k / 4, h = max(k - |a - b|, 0) / k; the
// smaller child has weight 1 - h/2 in the gradient, the larger h/2.
fn hwsdf_smin(a: hwsdf_Sample, b: hwsdf_Sample, k: f32) -> hwsdf_Sample {
    var lo = a;
    var hi = b;
    if a.d > b.d {
        lo = b;
        hi = a;
    }
    let h = max(k - (hi.d - lo.d), 0.0) / k;
    return hwsdf_Sample(lo.d - h * h * k * 0.25, lo.g * (1.0 - 0.5 * h) + hi.g * (0.5 * h), lo.leaf);
}

fn hwsdf_smin_d(a: f32, b: f32, k: f32) -> f32 {
    let h = max(k - abs(a - b), 0.0) / k;
    return min(a, b) - h * h * k * 0.25;
}

fn hwsdf_shell(a: hwsdf_Sample, t: f32) -> hwsdf_Sample {
    return hwsdf_Sample(abs(a.d) - t, select(a.g, -a.g, a.d < 0.0), a.leaf);
}
