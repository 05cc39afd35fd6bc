// The fast generalised winding number (Barill et al. 2018) and the signed distance: the GPU twin
// of sdf-geom's `distance/winding.rs`. Compiled after closest.wgsl (its bindings, helpers and
// the nearest-triangle search).

const FOUR_PI: f32 = 12.566370614359172;

struct WNode4 {
    cx: vec4<f32>,
    cy: vec4<f32>,
    cz: vec4<f32>,
    radius2: vec4<f32>,
    nx: vec4<f32>,
    ny: vec4<f32>,
    nz: vec4<f32>,
    trace: vec4<f32>,
    // Diagonals of the moments' symmetric parts (× 3) and off-diagonals xy, xz, yz (× 6).
    s3x: vec4<f32>,
    s3y: vec4<f32>,
    s3z: vec4<f32>,
    o6xy: vec4<f32>,
    o6xz: vec4<f32>,
    o6yz: vec4<f32>,
    child: vec4<u32>,
    count: vec4<u32>,
}

@group(0) @binding(3) var<storage, read> wnodes: array<WNode4>;

const NONE: u32 = 0xffffffffu;

// Solid angles of four triangles (corners relative to the query) by van Oosterom and Strackee,
// as the CPU's `solid_angle4`; 0 where numerator and denominator both vanish (a query on a
// corner), where WGSL's atan2 is undefined.
fn solid_angle4(t: Packet, p: vec3<f32>) -> vec4<f32> {
    let ax = t.ax - p.x;
    let ay = t.ay - p.y;
    let az = t.az - p.z;
    let bx = t.bx - p.x;
    let by = t.by - p.y;
    let bz = t.bz - p.z;
    let cx = t.cx - p.x;
    let cy = t.cy - p.y;
    let cz = t.cz - p.z;
    let la = sqrt(ax * ax + ay * ay + az * az);
    let lb = sqrt(bx * bx + by * by + bz * bz);
    let lc = sqrt(cx * cx + cy * cy + cz * cz);
    let det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx);
    let den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
        + (cx * ax + cy * ay + cz * az) * lb;
    let zero = (det == vec4<f32>(0.0)) & (den == vec4<f32>(0.0));
    return select(2.0 * atan2(det, den), vec4<f32>(0.0), zero);
}

// The fast winding number at p (internal units) with accuracy parameter beta: a child whose
// sphere is farther than beta radii contributes its dipole and first-order terms, a near leaf
// its exact solid angles, a near inner child is opened (the same traversal as the CPU's).
fn winding_beta(p: vec3<f32>, beta: f32) -> f32 {
    var stack: array<u32, STACK>;
    var sp = 0u;
    let beta2 = beta * beta;
    var acc = vec4<f32>(0.0);
    var ni = 0u;
    loop {
        let w = wnodes[ni];
        let dx = w.cx - p.x;
        let dy = w.cy - p.y;
        let dz = w.cz - p.z;
        let d2 = dx * dx + dy * dy + dz * dz;
        let far = d2 > beta2 * w.radius2;
        if any(far) {
            let inv_d2 = 1.0 / d2;
            let inv3 = sqrt(inv_d2) * inv_d2;
            let rsr3 = w.s3x * dx * dx + w.s3y * dy * dy + w.s3z * dz * dz + w.o6xy * dx * dy
                + w.o6xz * dx * dz + w.o6yz * dy * dz;
            let t = (w.nx * dx + w.ny * dy + w.nz * dz + w.trace - rsr3 * inv_d2) * inv3;
            acc += select(vec4<f32>(0.0), t, far);
        }
        var next = NONE;
        for (var k = 0u; k < 4u; k++) {
            if far[k] {
                continue;
            }
            let c = w.child[k];
            let n = w.count[k];
            if n > 0u {
                for (var j = 0u; 4u * j < n; j++) {
                    // Spare lanes of a short last packet repeat lane 0: masked out.
                    let live = vec4<u32>(0u, 1u, 2u, 3u) < vec4<u32>(n - 4u * j);
                    acc += select(vec4<f32>(0.0), solid_angle4(packets[c + j], p), live);
                }
            } else if c != NONE {
                if next == NONE {
                    next = c;
                } else {
                    stack[sp] = c;
                    sp++;
                }
            }
        }
        if next != NONE {
            ni = next;
            continue;
        }
        if sp == 0u {
            break;
        }
        sp--;
        ni = stack[sp];
    }
    return (acc.x + acc.y + acc.z + acc.w) / FOUR_PI;
}

// The winding number as the sign uses it: recomputed at 4β near the threshold.
fn winding_refined(p: vec3<f32>) -> f32 {
    let w = winding_beta(p, params.beta);
    if abs(w - params.inside) < params.refine_band {
        return winding_beta(p, 4.0 * params.beta);
    }
    return w;
}

// The winding number per point (0 on the far path, as on the CPU).
@compute @workgroup_size(WG)
fn winding(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_index(wid, nwg, lid);
    if i == NO_POINT {
        return;
    }
    let q = load_point(i);
    var r = 0.0;
    if is_finite3(q) {
        let query = classify(q);
        if !query.far {
            r = winding_refined(query.p);
        }
    }
    out[i] = r;
}

// Signed distance per point (mesh units): negative inside, unsigned within the surface
// tolerance, positive on the far path.
@compute @workgroup_size(WG)
fn signed_distance(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_index(wid, nwg, lid);
    if i == NO_POINT {
        return;
    }
    let q = load_point(i);
    var r = 0.0;
    if is_finite3(q) {
        let query = classify(q);
        let nr = nearest(query.p);
        if query.far {
            r = far_closest(q, corners(nr.tri)).w;
        } else {
            let d = sqrt(nr.d2);
            r = d;
            if d > params.surface_eps && winding_refined(query.p) >= params.inside {
                r = -d;
            }
            r = scale1(r, -params.exponent);
        }
    }
    out[i] = r;
}
