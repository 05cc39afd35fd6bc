// Points for training on the GPU: uniform in the box [-1, 1]^3, on the surface (triangle by area,
// uniform barycentric coordinates) and near it (plus an isotropic Gaussian offset), from
// Philox4x32-10 keyed by the seed. The twin of `ground_truth/counter_rng.rs` and of the CPU
// reference in `ground_truth/sample.rs`, integer for integer; one invocation per point.

const WG: u32 = 64u;

struct SampleParams {
    n_points: u32,
    n_uniform: u32,
    n_near: u32,
    // Triangles of positive area (the table's); the search runs over n_triangles - 1 bounds.
    n_triangles: u32,
    key: vec2<u32>,
    stream: u32,
    // Bits of each half of the Feistel shuffle; 0: no shuffle.
    shuffle_half: u32,
    shuffle_keys: vec4<u32>,
    sigma: f32,
    // The size of the shuffle's domain: n_points, or a pool's points for `gather`.
    shuffle_n: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> sp: SampleParams;
// Corners of the triangles of positive area, 9 floats each.
@group(0) @binding(1) var<storage, read> corners: array<f32>;
// Triangle t is drawn for a 32-bit word w with bounds[t - 1] <= w < bounds[t] (bounds[-1] = 0,
// bounds[n - 1] = 2^32): the cumulative areas in units of 2^-32 of the total.
@group(0) @binding(2) var<storage, read> bounds: array<u32>;
// 3 floats per point: the layout the ground-truth and training kernels read.
@group(0) @binding(3) var<storage, read_write> points: array<f32>;
// The table index of each surface or near-surface point's triangle (`draw_with_triangles`).
@group(0) @binding(4) var<storage, read_write> tri_out: array<u32>;
// Labels: gathered into (`gather`), made absolute in place (`absolute`).
@group(0) @binding(5) var<storage, read_write> targets: array<f32>;
// A draw without its shuffle and its labels (the surface points' left 0), for `gather`.
@group(0) @binding(6) var<storage, read> drawn: array<f32>;
@group(0) @binding(7) var<storage, read> drawn_labels: array<f32>;

// High and low words of a * b (WGSL has no 32 x 32 -> 64 product).
fn mulhilo(a: u32, b: u32) -> vec2<u32> {
    let al = a & 0xffffu;
    let ah = a >> 16u;
    let bl = b & 0xffffu;
    let bh = b >> 16u;
    let ll = al * bl;
    let lh = al * bh;
    let hl = ah * bl;
    let mid = (ll >> 16u) + (lh & 0xffffu) + (hl & 0xffffu);
    let hi = ah * bh + (lh >> 16u) + (hl >> 16u) + (mid >> 16u);
    return vec2<u32>(hi, a * b);
}

fn philox(counter: vec4<u32>, key: vec2<u32>) -> vec4<u32> {
    var c = counter;
    var k = key;
    for (var round = 0u; round < 10u; round++) {
        if round > 0u {
            k += vec2<u32>(0x9E3779B9u, 0xBB67AE85u);
        }
        let p0 = mulhilo(0xD2511F53u, c.x);
        let p1 = mulhilo(0xCD9E8D57u, c.z);
        c = vec4<u32>(p1.x ^ c.y ^ k.x, p1.y, p0.x ^ c.w ^ k.y, p0.y);
    }
    return c;
}

fn unit_float(x: u32) -> f32 {
    return f32(x >> 8u) * (1.0 / 16777216.0);
}

fn unit_float_open(x: u32) -> f32 {
    return f32((x >> 8u) + 1u) * (1.0 / 16777216.0);
}

fn gaussian_pair(a: u32, b: u32) -> vec2<f32> {
    // Clamped at 0: WGSL lets `log` err by 2^-21 near 1, so a driver may give a positive value
    // for u = 1 or just below, and the square root would be NaN (the CPU's ln(1) is 0).
    let r = sqrt(max(-2.0 * log(unit_float_open(a)), 0.0));
    let theta = 3.14159265358979 * (2.0 * unit_float(b) - 1.0);
    return r * vec2<f32>(cos(theta), sin(theta));
}

fn lowbias32(v: u32) -> u32 {
    var x = v;
    x ^= x >> 16u;
    x *= 0x7feb352du;
    x ^= x >> 15u;
    x *= 0x846ca68bu;
    x ^= x >> 16u;
    return x;
}

// The Feistel bijection of 0..shuffle_n (Shuffle::apply).
fn shuffle(i: u32) -> u32 {
    let h = sp.shuffle_half;
    if h == 0u {
        return i;
    }
    let mask = (1u << h) - 1u;
    var x = i;
    loop {
        var l = x >> h;
        var r = x & mask;
        for (var k = 0u; k < 4u; k++) {
            let t = l ^ (lowbias32(r ^ sp.shuffle_keys[k]) & mask);
            l = r;
            r = t;
        }
        x = (l << h) | r;
        if x < sp.shuffle_n {
            break;
        }
    }
    return x;
}

// The triangle of word w: the number of bounds at most w.
fn find_triangle(w: u32) -> u32 {
    var lo = 0u;
    var hi = sp.n_triangles - 1u;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if bounds[mid] <= w {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo;
}

fn corner(t: u32, k: u32) -> vec3<f32> {
    let o = 9u * t + 3u * k;
    return vec3<f32>(corners[o], corners[o + 1u], corners[o + 2u]);
}

struct Drawn {
    p: vec3<f32>,
    // Table index of the triangle; 0xffffffff for a uniform point.
    tri: u32,
}

fn draw_point(i: u32) -> Drawn {
    let j = shuffle(i);
    var kind = 0u;
    var rank = j;
    if j >= sp.n_uniform {
        rank = j - sp.n_uniform;
        kind = 1u;
        if rank >= sp.n_near {
            rank -= sp.n_near;
            kind = 2u;
        }
    }
    let w = philox(vec4<u32>(rank, kind, sp.stream, 0u), sp.key);
    if kind == 0u {
        let u = vec3<f32>(unit_float(w.x), unit_float(w.y), unit_float(w.z));
        return Drawn(u * 2.0 - 1.0, 0xffffffffu);
    }
    let t = find_triangle(w.x);
    let r1 = sqrt(unit_float(w.y));
    let r2 = unit_float(w.z);
    var p = corner(t, 0u) * (1.0 - r1) + corner(t, 1u) * (r1 * (1.0 - r2))
        + corner(t, 2u) * (r1 * r2);
    if kind == 1u {
        let w1 = philox(vec4<u32>(rank, kind, sp.stream, 1u), sp.key);
        let xy = gaussian_pair(w1.x, w1.y);
        let z = gaussian_pair(w.w, w1.z);
        p += vec3<f32>(xy, z.x) * sp.sigma;
    }
    return Drawn(p, t);
}

fn point_id(wid: vec3<u32>, nwg: vec3<u32>, lid: vec3<u32>) -> u32 {
    return (wid.y * nwg.x + wid.x) * WG + lid.x;
}

fn store(i: u32, p: vec3<f32>) {
    points[3u * i] = p.x;
    points[3u * i + 1u] = p.y;
    points[3u * i + 2u] = p.z;
}

// Point i of the draw into `points`.
@compute @workgroup_size(WG)
fn draw(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_id(wid, nwg, lid);
    if i >= sp.n_points {
        return;
    }
    store(i, draw_point(i).p);
}

// `draw`, also writing each point's triangle (for tests of the area distribution).
@compute @workgroup_size(WG)
fn draw_with_triangles(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_id(wid, nwg, lid);
    if i >= sp.n_points {
        return;
    }
    let d = draw_point(i);
    store(i, d.p);
    tri_out[i] = d.tri;
}

// |targets[i]|: unsigned distances from the signed-distance kernel's.
@compute @workgroup_size(WG)
fn absolute(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_id(wid, nwg, lid);
    if i >= sp.n_points {
        return;
    }
    targets[i] = abs(targets[i]);
}

// Point i of the shuffled draw and its label from the unshuffled draw `drawn`: the labels are
// computed over the uniform and near-surface points only (the first n_uniform + n_near of the
// unshuffled draw), which lie together there. From a pool of several draws, the first n_points
// of a shuffle of all of them (shuffle_n points): n_points distinct pool points.
@compute @workgroup_size(WG)
fn gather(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = point_id(wid, nwg, lid);
    if i >= sp.n_points {
        return;
    }
    let j = shuffle(i);
    store(i, vec3<f32>(drawn[3u * j], drawn[3u * j + 1u], drawn[3u * j + 2u]));
    targets[i] = drawn_labels[j];
}
