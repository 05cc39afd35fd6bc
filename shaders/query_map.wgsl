// NeuralSdf's serving rule, shared by every kernel that answers a caller's points
// (`query.wgsl`, NGLOD's `query` entry points, the one-dispatch SIREN kernels). A point p in
// mesh coordinates maps to x = (p - centre) · scale in the network's cube [-1, 1]^3; the
// network is evaluated at clamp(x), and outside the cube the distance grows by |x - clamp(x)|:
// d = (Φ(clamp(x)) + |x - clamp(x)|) / scale, in mesh units. The normal points away from the
// cube outside it, and along the normalised gradient inside.
// `map`: xyz the mesh's centre, w its scale (the identity for queries in the normalised cube).

fn query_normalized(p: vec3<f32>, map: vec4<f32>) -> vec3<f32> {
    return (p - map.xyz) * map.w;
}

fn query_clamped(x: vec3<f32>) -> vec3<f32> {
    return clamp(x, vec3<f32>(-1.0), vec3<f32>(1.0));
}

// The distance in mesh units for the network's value `phi` at clamp(x).
fn query_distance(phi: f32, x: vec3<f32>, map: vec4<f32>) -> f32 {
    return (phi + length(x - query_clamped(x))) / map.w;
}

// The unit normal at x for the network's gradient at clamp(x) (zero where both vanish).
fn query_normal(gradient: vec3<f32>, x: vec3<f32>) -> vec3<f32> {
    let away = x - query_clamped(x);
    let outside = length(away);
    if outside > 0.0 {
        return away / outside;
    }
    let len = length(gradient);
    if len > 0.0 {
        return gradient / len;
    }
    return vec3<f32>(0.0);
}
