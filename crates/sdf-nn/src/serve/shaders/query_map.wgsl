// NeuralSdf's serving rule, shared by every kernel that answers a caller's points
// (`query.wgsl`, NGLOD's `query` entry points, the one-dispatch SIREN kernels) and by the grid
// models' training kernels, which fit the value it serves. A point p in
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

// How far x lies outside the cube (0 inside): what the rule adds to the network's value.
fn box_gap(x: vec3<f32>) -> f32 {
    return length(x - query_clamped(x));
}

// A one-dispatch kernel's network input for a point as stored: with `query` (non-zero) a
// caller's point in mesh coordinates, mapped into the cube and clamped; else already normalised.
fn network_input(stored: vec3<f32>, query: u32, map: vec4<f32>) -> vec3<f32> {
    if query != 0u {
        return query_clamped(query_normalized(stored, map));
    }
    return stored;
}

// The distance in mesh units for the network's value `phi` at clamp(x).
fn query_distance(phi: f32, x: vec3<f32>, map: vec4<f32>) -> f32 {
    return (phi + box_gap(x)) / map.w;
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
