// Exact closest point on a triangle mesh: the GPU twin of sdf-geom's `distance/closest.rs`.
// The trees are sdf-geom's `GpuTrees`, uploaded once per mesh; one invocation per query point,
// invocations taking the points in the order of `bin.wgsl` (grouped by cell), results written at
// each point's own index.
// `winding.wgsl` is compiled after this file (it needs the search for the signed distance).
//
// Coordinates: the trees are in internal units (the mesh's times 2^exponent); points come in mesh
// units, results go out in mesh units. Every rescaling is by a power of two (exact), so the near
// path computes what the CPU computes, operation for operation.

const WG: u32 = 64u;
// Entries of the traversal stacks: the host refuses trees whose `max_stack` is larger.
const STACK: u32 = 96u;
// The largest finite f32: the initial "best so far" (a literal infinity is not WGSL).
const BIG: f32 = 3.4028235e38;

struct Params {
    n_points: u32,
    exponent: i32,
    _pad0: u32,
    _pad1: u32,
    // Bounding-box centre in mesh units, halved; half the far radius in mesh units (may be +inf:
    // then no query is far). Halved so that `p / 2 - center_half` cannot overflow.
    center_half: vec3<f32>,
    far_half: f32,
    // Centre and far radius in internal units.
    center: vec3<f32>,
    far: f32,
    beta: f32,
    refine_band: f32,
    // Internal units.
    surface_eps: f32,
    inside: f32,
}

struct Node4 {
    min_x: vec4<f32>,
    min_y: vec4<f32>,
    min_z: vec4<f32>,
    max_x: vec4<f32>,
    max_y: vec4<f32>,
    max_z: vec4<f32>,
    child: vec4<u32>,
    count: vec4<u32>,
}

struct Packet {
    ax: vec4<f32>,
    ay: vec4<f32>,
    az: vec4<f32>,
    bx: vec4<f32>,
    by: vec4<f32>,
    bz: vec4<f32>,
    cx: vec4<f32>,
    cy: vec4<f32>,
    cz: vec4<f32>,
    slot: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> nodes: array<Node4>;
@group(0) @binding(2) var<storage, read> packets: array<Packet>;
// Binding 3 (the winding tree) is declared in winding.wgsl.
@group(0) @binding(4) var<storage, read> points: array<f32>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;
// The points' indices grouped by cell (`bin.wgsl`): invocation k queries point order[k].
@group(0) @binding(6) var<storage, read> order: array<u32>;

// The point invocation (wid, lid) queries, or NO_POINT past the batch's end.
const NO_POINT: u32 = 0xffffffffu;

fn point_index(wid: vec3<u32>, nwg: vec3<u32>, lid: vec3<u32>) -> u32 {
    let k = (wid.y * nwg.x + wid.x) * WG + lid.x;
    if k >= params.n_points {
        return NO_POINT;
    }
    return order[k];
}

fn load_point(i: u32) -> vec3<f32> {
    return vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
}

// No NaN or infinity in any component (WGSL has no isnan; the host writes NaN for such points).
fn is_finite3(p: vec3<f32>) -> bool {
    let e = vec3<u32>(0x7f800000u);
    return all((bitcast<vec3<u32>>(p) & e) != e);
}

// 2^e for −126 ≤ e ≤ 127, exactly (built from its bits).
fn pow2(e: i32) -> f32 {
    return bitcast<f32>(u32(e + 127) << 23u);
}

// v · 2^e as three multiplications by exact powers of two of the same sign: IEEE multiplication
// overflows to infinity and rounds once, where WGSL leaves `ldexp` indeterminate above 2^128
// (NVIDIA's gave 2^64 for an overflowing product) and lets it flush below 2^-126; the tamed
// meshes' exponents reach ±150.
fn scale3(v: vec3<f32>, e: i32) -> vec3<f32> {
    let a = clamp(e, -126, 127);
    let b = clamp(e - a, -126, 127);
    let c = clamp(e - a - b, -126, 127);
    return v * pow2(a) * pow2(b) * pow2(c);
}

fn scale1(x: f32, e: i32) -> f32 {
    return scale3(vec3<f32>(x, 0.0, 0.0), e).x;
}

fn max3(v: vec3<f32>) -> f32 {
    return max(v.x, max(v.y, v.z));
}

// Where a query goes. Near: `p` in internal units. Far: `p` is the proxy, the point at the far
// radius from the centre in the query's direction (internal units).
struct Query {
    p: vec3<f32>,
    far: bool,
}

fn classify(q: vec3<f32>) -> Query {
    // Halved, so the difference stays finite for any finite q; its length by the largest
    // component, so the square cannot overflow.
    let v = q * 0.5 - params.center_half;
    let m = max3(abs(v));
    var len = 0.0;
    var dir = vec3<f32>(0.0);
    if m > 0.0 {
        let u = v / m;
        let lu = length(u);
        len = m * lu;
        dir = u / lu;
    }
    if len > params.far_half {
        return Query(params.center + dir * params.far, true);
    }
    return Query(scale3(q, params.exponent), false);
}

// Squared distances from p to the four children's boxes.
fn box_dist2(n: Node4, p: vec3<f32>) -> vec4<f32> {
    let z = vec4<f32>(0.0);
    let dx = max(max(n.min_x - p.x, p.x - n.max_x), z);
    let dy = max(max(n.min_y - p.y, p.y - n.max_y), z);
    let dz = max(max(n.min_z - p.z, p.z - n.max_z), z);
    return dx * dx + dy * dy + dz * dz;
}

fn all_finite4(v: vec4<f32>) -> vec4<bool> {
    let e = vec4<u32>(0x7f800000u);
    return (bitcast<vec4<u32>>(v) & e) != e;
}

// Squared distances from p to a packet's four triangles: the CPU's `TriPacket::dist2`, Ericson's
// regions with every branch a select, face region first and the vertex regions last.
fn packet_dist2(t: Packet, p: vec3<f32>) -> vec4<f32> {
    let z = vec4<f32>(0.0);
    let abx = t.bx - t.ax;
    let aby = t.by - t.ay;
    let abz = t.bz - t.az;
    let acx = t.cx - t.ax;
    let acy = t.cy - t.ay;
    let acz = t.cz - t.az;
    let apx = p.x - t.ax;
    let apy = p.y - t.ay;
    let apz = p.z - t.az;
    let d1 = abx * apx + aby * apy + abz * apz;
    let d2 = acx * apx + acy * apy + acz * apz;
    let bpx = p.x - t.bx;
    let bpy = p.y - t.by;
    let bpz = p.z - t.bz;
    let d3 = abx * bpx + aby * bpy + abz * bpz;
    let d4 = acx * bpx + acy * bpy + acz * bpz;
    let vc = d1 * d4 - d3 * d2;
    let cpx = p.x - t.cx;
    let cpy = p.y - t.cy;
    let cpz = p.z - t.cz;
    let d5 = abx * cpx + aby * cpy + abz * cpz;
    let d6 = acx * cpx + acy * cpy + acz * cpz;
    let vb = d5 * d2 - d1 * d6;
    let va = d3 * d6 - d5 * d4;
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    let fin = all_finite4(v) & all_finite4(w);
    var qx = select(t.ax, t.ax + abx * v + acx * w, fin);
    var qy = select(t.ay, t.ay + aby * v + acy * w, fin);
    var qz = select(t.az, t.az + abz * v + acz * w, fin);
    let e43 = d4 - d3;
    let e56 = d5 - d6;
    let m6 = (va <= z) & (e43 >= z) & (e56 >= z);
    let w6 = e43 / (e43 + e56);
    qx = select(qx, t.bx + (t.cx - t.bx) * w6, m6);
    qy = select(qy, t.by + (t.cy - t.by) * w6, m6);
    qz = select(qz, t.bz + (t.cz - t.bz) * w6, m6);
    let m5 = (vb <= z) & (d2 >= z) & (d6 <= z);
    let w5 = d2 / (d2 - d6);
    qx = select(qx, t.ax + acx * w5, m5);
    qy = select(qy, t.ay + acy * w5, m5);
    qz = select(qz, t.az + acz * w5, m5);
    let m4 = (d6 >= z) & (d5 <= d6);
    qx = select(qx, t.cx, m4);
    qy = select(qy, t.cy, m4);
    qz = select(qz, t.cz, m4);
    let m3 = (vc <= z) & (d1 >= z) & (d3 <= z);
    let v3 = d1 / (d1 - d3);
    qx = select(qx, t.ax + abx * v3, m3);
    qy = select(qy, t.ay + aby * v3, m3);
    qz = select(qz, t.az + abz * v3, m3);
    let m2 = (d3 >= z) & (d4 <= d3);
    qx = select(qx, t.bx, m2);
    qy = select(qy, t.by, m2);
    qz = select(qz, t.bz, m2);
    let m1 = (d1 <= z) & (d2 <= z);
    qx = select(qx, t.ax, m1);
    qy = select(qy, t.ay, m1);
    qz = select(qz, t.az, m1);
    let ex = qx - p.x;
    let ey = qy - p.y;
    let ez = qz - p.z;
    return ex * ex + ey * ey + ez * ez;
}

// The closest point on triangle (a, b, c) to p: the CPU's `closest_on_triangle` (f32), branches
// and all, for the point of the triangle the search picked.
fn closest_on_triangle(p: vec3<f32>, a: vec3<f32>, b: vec3<f32>, c: vec3<f32>) -> vec3<f32> {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    if !is_finite3(vec3<f32>(v, w, 0.0)) {
        // A triangle whose squared area underflows: its first corner, as on the CPU.
        return a;
    }
    return a + ab * v + ac * w;
}

// Barycentric weights (of b and c) of the closest point of a triangle to a far point, in a frame
// where ap (the query relative to a) has components of order 1 and the triangle is tiny. Ericson's
// regions with every decision value rewritten to be linear in ap (vc = |ab|² d2 − (ab·ac) d1 and
// so on): his products of two ap-sized dot products cancel catastrophically in f32 this far away,
// which the CPU avoids by working in f64. Weights are clamped to the triangle, so a decision that
// rounding gets wrong still gives a point on it, off by about an ulp of the distance.
fn far_weights(ap: vec3<f32>, ab: vec3<f32>, ac: vec3<f32>) -> vec2<f32> {
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    let aa = dot(ab, ab);
    let cc = dot(ac, ac);
    let m = dot(ab, ac);
    if d1 <= 0.0 && d2 <= 0.0 {
        return vec2<f32>(0.0, 0.0);
    }
    let d3 = d1 - aa;
    let d4 = d2 - m;
    if d3 >= 0.0 && d4 <= d3 {
        return vec2<f32>(1.0, 0.0);
    }
    let vc = aa * d2 - m * d1;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return vec2<f32>(select(0.0, clamp(d1 / aa, 0.0, 1.0), aa > 0.0), 0.0);
    }
    let d5 = d1 - m;
    let d6 = d2 - cc;
    if d6 >= 0.0 && d5 <= d6 {
        return vec2<f32>(0.0, 1.0);
    }
    let vb = cc * d1 - m * d2;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return vec2<f32>(0.0, select(0.0, clamp(d2 / cc, 0.0, 1.0), cc > 0.0));
    }
    let area2 = aa * cc - m * m;
    let va = area2 - vb - vc;
    let e43 = d4 - d3;
    let e56 = d5 - d6;
    if va <= 0.0 && e43 >= 0.0 && e56 >= 0.0 {
        let s = e43 + e56;
        let w = select(0.0, clamp(e43 / s, 0.0, 1.0), s > 0.0);
        return vec2<f32>(1.0 - w, w);
    }
    if !(area2 > 0.0) {
        return vec2<f32>(0.0, 0.0);
    }
    let v = max(vb / area2, 0.0);
    let w = max(vc / area2, 0.0);
    let s = v + w;
    if s > 1.0 {
        return vec2<f32>(v / s, w / s);
    }
    return vec2<f32>(v, w);
}

// A triangle's corners from its packet lane (tri = packet * 4 + lane).
struct Corners {
    a: vec3<f32>,
    b: vec3<f32>,
    c: vec3<f32>,
}

fn corners(tri: u32) -> Corners {
    let t = packets[tri / 4u];
    let l = tri % 4u;
    return Corners(
        vec3<f32>(t.ax[l], t.ay[l], t.az[l]),
        vec3<f32>(t.bx[l], t.by[l], t.bz[l]),
        vec3<f32>(t.cx[l], t.cy[l], t.cz[l]),
    );
}

// The far path's distance and closest point (mesh units) from the query q (mesh units) to the
// triangle the proxy's search picked. Everything relative to corner a, halved and scaled by a
// power of two so that nothing overflows or underflows where it matters; the distance is +inf
// only if it exceeds the largest f32, as on the CPU.
fn far_closest(q: vec3<f32>, t: Corners) -> vec4<f32> {
    let e = params.exponent;
    let ap = q * 0.5 - scale3(t.a, -e - 1);
    let k = frexp(max3(abs(ap))).exp;
    let aps = scale3(ap, -k);
    let s = -e - 1 - k;
    let ab = t.b - t.a;
    let ac = t.c - t.a;
    let ab_s = scale3(ab, s);
    let ac_s = scale3(ac, s);
    let vw = far_weights(aps, ab_s, ac_s);
    let x = ab_s * vw.x + ac_s * vw.y;
    // The distance is length · 2^(k+1): +inf, as on the CPU, where that exceeds the largest f32.
    // Decided on the exponents rather than left to an overflowing product, which NVIDIA's
    // compiler turned into 2^64 (it seems to fold multiplications by powers of two into an
    // exponent add that does not saturate); every product below stays finite.
    let m = frexp(length(aps - x));
    var dist = bitcast<f32>(0x7f800000u);
    if m.exp + k + 1 <= 128 {
        dist = scale1(m.fract, m.exp + k + 1);
    }
    let point = scale3(t.a + ab * vw.x + ac * vw.y, -e);
    return vec4<f32>(point, dist);
}

// The nearest triangle: squared distance (internal units) and packet * 4 + lane.
struct Nearest {
    d2: f32,
    tri: u32,
}

// Best-first depth-first search of the 4-wide BVH, as the CPU's `nearest`: the children nearer
// than the best triangle so far are visited nearest first, the others pushed, and entries whose box
// is farther than the best triangle are dropped when popped. Lanes are tested in order with a
// strict `<`, so ties go to the same triangle as on the CPU.
fn nearest(p: vec3<f32>) -> Nearest {
    var st_d: array<f32, STACK>;
    var st_c: array<u32, STACK>;
    var st_n: array<u32, STACK>;
    var sp = 0u;
    var best = BIG;
    var best_tri = 0u;
    // Current entry: node, or first packet and packet count (0 for a node).
    var c = 0u;
    var count = 0u;
    loop {
        var descend = false;
        if count > 0u {
            for (var j = c; j < c + count; j++) {
                let d = packet_dist2(packets[j], p);
                for (var l = 0u; l < 4u; l++) {
                    if d[l] < best {
                        best = d[l];
                        best_tri = 4u * j + l;
                    }
                }
            }
        } else {
            let n = nodes[c];
            let d = box_dist2(n, p);
            // Candidates sorted by decreasing box distance (insertion sort of at most four).
            var cd: array<f32, 4>;
            var ci: array<u32, 4>;
            var m = 0u;
            for (var k = 0u; k < 4u; k++) {
                if d[k] < best {
                    var j = m;
                    while j > 0u && cd[j - 1u] < d[k] {
                        cd[j] = cd[j - 1u];
                        ci[j] = ci[j - 1u];
                        j--;
                    }
                    cd[j] = d[k];
                    ci[j] = k;
                    m++;
                }
            }
            if m > 0u {
                for (var j = 0u; j + 1u < m; j++) {
                    st_d[sp] = cd[j];
                    st_c[sp] = n.child[ci[j]];
                    st_n[sp] = n.count[ci[j]];
                    sp++;
                }
                let k = ci[m - 1u];
                c = n.child[k];
                count = n.count[k];
                descend = true;
            }
        }
        if descend {
            continue;
        }
        // Pop the next entry that can still hold something closer.
        var found = false;
        while sp > 0u {
            sp--;
            if st_d[sp] < best {
                c = st_c[sp];
                count = st_n[sp];
                found = true;
                break;
            }
        }
        if !found {
            break;
        }
    }
    return Nearest(best, best_tri);
}

// Closest point (xyz, mesh units) and unsigned distance (w) per point; 4 floats each.
@compute @workgroup_size(WG)
fn closest(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_index(wid, nwg, lid);
    if i == NO_POINT {
        return;
    }
    let q = load_point(i);
    var r = vec4<f32>(0.0);
    if is_finite3(q) {
        let query = classify(q);
        let nr = nearest(query.p);
        let t = corners(nr.tri);
        if query.far {
            r = far_closest(q, t);
        } else {
            let x = closest_on_triangle(query.p, t.a, t.b, t.c);
            let e = -params.exponent;
            r = vec4<f32>(scale3(x, e), scale1(sqrt(nr.d2), e));
        }
    }
    out[4u * i] = r.x;
    out[4u * i + 1u] = r.y;
    out[4u * i + 2u] = r.z;
    out[4u * i + 3u] = r.w;
}
