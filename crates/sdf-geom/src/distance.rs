//! Exact closest-point distance on an `obvhs` BVH, and the sign from the fast generalised winding number.

use std::f32::consts::PI;
use std::time::Duration;

use glam::{BVec4A, DMat3, DVec3, Vec3, Vec3A, Vec4};
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::triangle::Triangle;
use rayon::prelude::*;

use crate::reference::closest_on_triangle_f64;
use crate::{GeomError, Mesh};

/// Queries farther than this many bounding-sphere radii from the mesh's bounding-box centre take the
/// far path: the nearest triangle is found from the point at this radius in the query's direction,
/// and the distance to it is computed in f64 from the query itself. That triangle's distance is
/// within `radius / 8192` of the true minimum, below half an f32 ulp of distances this large, so the
/// result is correct to f32 rounding; and squared distances in the f32 search can no longer
/// overflow (they did from about 1.8e19). The sign there is "outside" (winding number 0: a closed
/// mesh's winding number is exactly 0 outside its bounding sphere, an open mesh's is below 1e-7).
/// A distance larger than `f32::MAX` (a query near `f32::MAX` on the far side) is `inf`: the only
/// non-finite result for a finite query.
pub const FAR_QUERY_RADII: f64 = 4096.0;

/// The winding number from which a point is inside: [`SignedDistance::is_inside`] and the sign
/// of [`SignedDistance::signed_distance`] (1 inside a closed mesh, 0 outside, fractional near an
/// open one).
const INSIDE_WINDING: f32 = 0.5;

/// Meshes whose largest coordinate magnitude lies outside `[2^-16, 2^16]` are rescaled internally
/// by a power of two (exact in floating point) so that the f32 search and winding sums neither
/// overflow (coordinates near 1e38) nor underflow; distances and points are scaled back on output.
/// Meshes inside that range are used as they are, bit for bit.
const TAME_EXPONENT: i32 = 16;

/// The result of a closest-point query.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ClosestPoint {
    /// Euclidean distance from the query to `point` (unsigned).
    pub distance: f32,
    /// The closest point on the mesh.
    pub point: Vec3,
    /// Index of the triangle in [`Mesh::triangles`] that holds `point`.
    pub triangle: u32,
    /// Barycentric coordinates of `point` with respect to that triangle's corners (sum to 1).
    pub barycentric: Vec3,
}

/// Tuning knobs for [`SignedDistance`]. The defaults are what the rest of the project uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SignedDistanceOptions {
    /// Accuracy parameter β of the fast winding number: a BVH node whose bounding sphere (radius r,
    /// around its area-weighted centroid) is farther than β·r from the query is replaced by its dipole
    /// and first-order terms. Larger is more accurate and slower. Default 1.5.
    pub beta: f32,
    /// If the fast winding number lands within this distance of 1/2, it is recomputed with β × 4
    /// before thresholding. Default 0.2, over twice the largest error measured at β = 1.5 (0.086,
    /// see the crate documentation), so a value on the wrong side of 1/2 is always re-evaluated.
    pub refine_band: f32,
    /// Points whose unsigned distance is at most `surface_tolerance × bounding-box diagonal` are *on*
    /// the surface: [`SignedDistance::signed_distance`] returns their distance unsigned (≥ 0) without
    /// computing a winding number, whose value there is 1/2 up to rounding anyway. Default 1e-6;
    /// 0 turns the shortcut off.
    pub surface_tolerance: f32,
    /// Maximum number of triangles per BVH leaf (1 to 255). Default 4.
    pub max_leaf_size: u32,
}

impl Default for SignedDistanceOptions {
    fn default() -> Self {
        SignedDistanceOptions {
            beta: 1.5,
            refine_band: 0.2,
            surface_tolerance: 1e-6,
            max_leaf_size: 4,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(16))]
struct Node {
    min: Vec3,
    /// Inner node: index of the first child (the second is `first + 1`). Leaf: first triangle slot.
    first: u32,
    max: Vec3,
    /// 0 for inner nodes, else number of triangles in the leaf.
    count: u32,
}

/// A node of the 4-wide BVH used by the closest-point search (collapsed from the binary one): the
/// boxes of up to four children in SoA form, so that one SIMD pass gives all four box distances.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node4 {
    /// Per-axis (x, y, z) lower corners of the four children's boxes; +∞ in unused slots.
    min: [Vec4; 3],
    /// Per-axis upper corners; −∞ in unused slots (so their box distance is +∞).
    max: [Vec4; 3],
    /// Inner child: index into `nodes4`. Leaf child: first index into `packets`.
    child: [u32; 4],
    /// 0 for an inner child (or an unused slot), else the number of triangle packets in the leaf.
    count: [u32; 4],
}

impl Node4 {
    const EMPTY: Node4 = Node4 {
        min: [Vec4::INFINITY; 3],
        max: [Vec4::NEG_INFINITY; 3],
        child: [0; 4],
        count: [0; 4],
    };

    /// Squared distances from `p` (splatted per axis) to the four children's boxes.
    #[inline(always)]
    fn box_dist2(&self, px: Vec4, py: Vec4, pz: Vec4) -> Vec4 {
        let dx = (self.min[0] - px).max(px - self.max[0]).max(Vec4::ZERO);
        let dy = (self.min[1] - py).max(py - self.max[1]).max(Vec4::ZERO);
        let dz = (self.min[2] - pz).max(pz - self.max[2]).max(Vec4::ZERO);
        dx * dx + dy * dy + dz * dz
    }
}

/// Three SoA vectors: the x, y and z coordinates of four points.
#[derive(Clone, Copy, Debug)]
struct P4 {
    x: Vec4,
    y: Vec4,
    z: Vec4,
}

impl P4 {
    #[inline(always)]
    fn sub(self, o: P4) -> P4 {
        P4 {
            x: self.x - o.x,
            y: self.y - o.y,
            z: self.z - o.z,
        }
    }
    #[inline(always)]
    fn add(self, o: P4) -> P4 {
        P4 {
            x: self.x + o.x,
            y: self.y + o.y,
            z: self.z + o.z,
        }
    }
    #[inline(always)]
    fn scale(self, s: Vec4) -> P4 {
        P4 {
            x: self.x * s,
            y: self.y * s,
            z: self.z * s,
        }
    }
    /// Same operation order as `Vec3A::dot`: (x·x + y·y) + z·z.
    #[inline(always)]
    fn dot(self, o: P4) -> Vec4 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    #[inline(always)]
    fn select(m: BVec4A, t: P4, f: P4) -> P4 {
        P4 {
            x: Vec4::select(m, t.x, f.x),
            y: Vec4::select(m, t.y, f.y),
            z: Vec4::select(m, t.z, f.z),
        }
    }
}

/// Four triangles in SoA form (one leaf's worth; a short leaf repeats its first triangle).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct TriPacket {
    a: P4,
    b: P4,
    c: P4,
    /// Triangle slot of each lane (padding lanes repeat lane 0's).
    slot: [u32; 4],
}

impl TriPacket {
    /// Squared distances from `p` to the four triangles: [`closest_on_triangle`] evaluated in all
    /// four lanes at once with every branch replaced by a select, operation for operation, so the
    /// results are bit-identical to the scalar function's `(q − p)²`.
    #[inline(always)]
    fn dist2(&self, p: P4) -> Vec4 {
        let (a, b, c) = (self.a, self.b, self.c);
        let z = Vec4::ZERO;
        let ab = b.sub(a);
        let ac = c.sub(a);
        let ap = p.sub(a);
        let d1 = ab.dot(ap);
        let d2 = ac.dot(ap);
        let bp = p.sub(b);
        let d3 = ab.dot(bp);
        let d4 = ac.dot(bp);
        let vc = d1 * d4 - d3 * d2;
        let cp = p.sub(c);
        let d5 = ab.dot(cp);
        let d6 = ac.dot(cp);
        let vb = d5 * d2 - d1 * d6;
        let va = d3 * d6 - d5 * d4;
        // Face region (lowest priority), then the other regions from the last test to the first.
        let denom = Vec4::ONE / (va + vb + vc);
        let v = vb * denom;
        let w = vc * denom;
        let finite = v.is_finite_mask() & w.is_finite_mask();
        let mut q = P4::select(finite, a.add(ab.scale(v)).add(ac.scale(w)), a);
        let e43 = d4 - d3;
        let e56 = d5 - d6;
        let m6 = va.cmple(z) & e43.cmpge(z) & e56.cmpge(z);
        q = P4::select(m6, b.add(c.sub(b).scale(e43 / (e43 + e56))), q);
        let m5 = vb.cmple(z) & d2.cmpge(z) & d6.cmple(z);
        q = P4::select(m5, a.add(ac.scale(d2 / (d2 - d6))), q);
        let m4 = d6.cmpge(z) & d5.cmple(d6);
        q = P4::select(m4, c, q);
        let m3 = vc.cmple(z) & d1.cmpge(z) & d3.cmple(z);
        q = P4::select(m3, a.add(ab.scale(d1 / (d1 - d3))), q);
        let m2 = d3.cmpge(z) & d4.cmple(d3);
        q = P4::select(m2, b, q);
        let m1 = d1.cmple(z) & d2.cmple(z);
        q = P4::select(m1, a, q);
        let e = q.sub(p);
        e.dot(e)
    }
}

/// Collapses the binary BVH below `root` into 4-wide nodes (appended to `out` in depth-first order,
/// leaves' triangles appended to `packets` in the same order): an inner node's slots are filled by
/// repeatedly opening the inner child with the largest box surface area. Returns the new node's
/// index.
fn collapse4(
    nodes: &[Node],
    wnodes: &[WindingNode],
    tris: &[[Vec3A; 3]],
    root: u32,
    out: &mut Vec<Node4>,
    wout: &mut Vec<WNode4>,
    packets: &mut Vec<TriPacket>,
) -> u32 {
    let half_area = |n: &Node| {
        let e = (n.max - n.min).max(Vec3::ZERO);
        e.x * e.y + e.y * e.z + e.z * e.x
    };
    let mut kids = [root; 4];
    let mut m = 1;
    while m < 4 {
        let open = (0..m)
            .filter(|&k| nodes[kids[k] as usize].count == 0)
            .max_by(|&a, &b| {
                half_area(&nodes[kids[a] as usize]).total_cmp(&half_area(&nodes[kids[b] as usize]))
            });
        let Some(k) = open else { break };
        let first = nodes[kids[k] as usize].first;
        kids[k] = first;
        kids[m] = first + 1;
        m += 1;
    }
    let idx = out.len();
    out.push(Node4::EMPTY);
    wout.push(WNode4::EMPTY);
    let mut node = Node4::EMPTY;
    let mut wnode = WNode4::EMPTY;
    for (k, &c) in kids[..m].iter().enumerate() {
        let n = &nodes[c as usize];
        for axis in 0..3 {
            node.min[axis][k] = n.min[axis];
            node.max[axis][k] = n.max[axis];
        }
        let w = &wnodes[c as usize];
        for axis in 0..3 {
            wnode.center[axis][k] = w.center[axis];
            wnode.area_normal[axis][k] = w.area_normal[axis];
            wnode.sym_diag3[axis][k] = 3.0 * w.sym_diag[axis];
            wnode.sym_off6[axis][k] = 6.0 * w.sym_off[axis];
        }
        wnode.radius2[k] = w.radius2;
        wnode.trace[k] = w.trace;
        if n.count > 0 {
            node.child[k] = packets.len() as u32;
            node.count[k] = n.count.div_ceil(4);
            wnode.child[k] = node.child[k];
            wnode.count[k] = n.count;
            for chunk in (n.first..n.first + n.count).collect::<Vec<u32>>().chunks(4) {
                let slot: [u32; 4] =
                    std::array::from_fn(|l| chunk[if l < chunk.len() { l } else { 0 }]);
                let corner = |j: usize| {
                    let v: [Vec3A; 4] = slot.map(|s| tris[s as usize][j]);
                    P4 {
                        x: Vec4::new(v[0].x, v[1].x, v[2].x, v[3].x),
                        y: Vec4::new(v[0].y, v[1].y, v[2].y, v[3].y),
                        z: Vec4::new(v[0].z, v[1].z, v[2].z, v[3].z),
                    }
                };
                packets.push(TriPacket {
                    a: corner(0),
                    b: corner(1),
                    c: corner(2),
                    slot,
                });
            }
        } else {
            node.child[k] = collapse4(nodes, wnodes, tris, c, out, wout, packets);
            wnode.child[k] = node.child[k];
        }
    }
    out[idx] = node;
    wout[idx] = wnode;
    idx as u32
}

/// Winding-number data of one binary BVH node (only used while building the 4-wide nodes).
#[derive(Clone, Copy, Debug, Default)]
struct WindingNode {
    /// Area-weighted centroid of the node's triangles.
    center: Vec3,
    /// Squared radius of a sphere around `center` containing all of the node's triangles.
    radius2: f32,
    /// Sum of the node's area vectors (area × unit normal).
    area_normal: Vec3,
    /// Trace of the first-order moment C = Σ a_t n_t (x̄_t − c)ᵀ.
    trace: f32,
    /// Diagonal of the symmetric part of C.
    sym_diag: Vec3,
    /// Off-diagonal (xy, xz, yz) of the symmetric part of C.
    sym_off: Vec3,
}

/// A node of the 4-wide winding tree: the [`WindingNode`] data of up to four children in SoA form,
/// so that the far-field test and expansion of all four run in one SIMD pass. It has the same shape
/// and indices as the [`Node4`] at the same position (inner child: index into `wnodes4`; leaf child:
/// first index into `packets`).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct WNode4 {
    /// Per-axis area-weighted centroids.
    center: [Vec4; 3],
    /// Squared bounding-sphere radii; +∞ in unused slots (never far, and never opened).
    radius2: Vec4,
    /// Per-axis summed area vectors.
    area_normal: [Vec4; 3],
    /// Traces of the first-order moments.
    trace: Vec4,
    /// Per-axis diagonals of the symmetric parts of the first-order moments, times 3.
    sym_diag3: [Vec4; 3],
    /// Off-diagonals (xy, xz, yz) of the symmetric parts, times 6 (3 × the two symmetric entries).
    sym_off6: [Vec4; 3],
    /// Inner child: index into `wnodes4`; leaf child: first packet; unused slot: `u32::MAX`.
    child: [u32; 4],
    /// Number of triangles of a leaf child (0 for an inner child or an unused slot).
    count: [u32; 4],
}

impl WNode4 {
    const EMPTY: WNode4 = WNode4 {
        center: [Vec4::ZERO; 3],
        radius2: Vec4::INFINITY,
        area_normal: [Vec4::ZERO; 3],
        trace: Vec4::ZERO,
        sym_diag3: [Vec4::ZERO; 3],
        sym_off6: [Vec4::ZERO; 3],
        child: [u32::MAX; 4],
        count: [0; 4],
    };
}

/// Lane-wise square root (one `sqrtps`; glam's `Vec4::sqrt` is four scalar calls).
#[inline(always)]
fn sqrt4(v: Vec4) -> Vec4 {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: SSE is part of the x86_64 baseline, so the instruction is always available.
        Vec4::from(unsafe { std::arch::x86_64::_mm_sqrt_ps(v.into()) })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        v.sqrt()
    }
}

/// Lane-wise `atan2(y, x)` in f32, with the quadrant and signed-zero conventions of `f32::atan2`
/// (±π for x < 0 or x = −0 and y = ±0; 0 for x = y = 0; ±π/4, ±3π/4 for infinite x and y; NaN in,
/// NaN out). The ratio of the smaller to the larger magnitude t ∈ [0, 1] goes through an odd
/// minimax polynomial for atan (SLEEF's `atan2f` coefficients), then the octant is restored;
/// measured against f64 to within a few ulp (see the tests).
#[inline(always)]
fn atan2_4(y: Vec4, x: Vec4) -> Vec4 {
    use std::f32::consts::FRAC_PI_2;
    let (ax, ay) = (x.abs(), y.abs());
    let swap = ay.cmpgt(ax);
    let (num, den) = (Vec4::select(swap, ax, ay), Vec4::select(swap, ay, ax));
    // num = den covers 0/0 (atan2(0, 0) = 0) and ∞/∞ (atan 1); a NaN takes the division.
    let t = Vec4::select(
        num.cmpeq(den),
        Vec4::select(den.cmpeq(Vec4::ZERO), Vec4::ZERO, Vec4::ONE),
        num / den,
    );
    let z = t * t;
    let mut u = Vec4::splat(0.002_823_639);
    u = u * z + Vec4::splat(-0.015_956_903);
    u = u * z + Vec4::splat(0.042_504_99);
    u = u * z + Vec4::splat(-0.074_890_09);
    u = u * z + Vec4::splat(0.106_347_93);
    u = u * z + Vec4::splat(-0.142_027_36);
    u = u * z + Vec4::splat(0.199_926_96);
    u = u * z + Vec4::splat(-0.333_331_02);
    let mut r = u * z * t + t;
    r = Vec4::select(swap, Vec4::splat(FRAC_PI_2) - r, r);
    // The sign bit of x, not x < 0: atan2(±0, −0) = ±π.
    r = Vec4::select(x.is_negative_mask(), Vec4::splat(PI) - r, r);
    r.copysign(y)
}

/// Exact unsigned distance plus a robust sign, for one mesh.
///
/// Owns a BVH (built with `obvhs` 0.4's PLOC builder, without spatial splits so each triangle sits in
/// exactly one leaf), a 4-wide copy of it for the distance and the winding number, and the triangles
/// in leaf order.
///
/// # Distance
/// The binary tree is collapsed into a 4-wide one (children's boxes in SoA form, one SIMD pass for
/// all four box distances; leaves' triangles in SoA packets of four, in depth-first order).
/// [`closest_point`](Self::closest_point) is a best-first depth-first traversal: the children
/// nearer than the best triangle so far are visited nearest first (by the distance from the query to
/// their box) and every entry whose box is farther than the best triangle is skipped. Point–triangle
/// distance is Ericson's Voronoi-region method, evaluated for four triangles at once with selects
/// (bit-identical to the scalar version). The result is exact up to f32 rounding (the same triangle
/// a brute-force scan would pick, up to ties). Batches run in Morton order of the points; in
/// [`signed_distance_batch`](Self::signed_distance_batch) each query first measures the previous
/// query's nearest triangle, which gives a tight starting bound (the distance, a minimum over all
/// triangles, is unchanged bit for bit).
///
/// # Sign
/// The sign comes from the generalised winding number w(p) = Σ Ω_t(p) / 4π (Jacobson et al. 2013),
/// thresholded at 1/2 (inside if w ≥ 1/2), which is well defined for open meshes, several components,
/// self-intersections and flipped or duplicated faces. It is evaluated with the fast hierarchical
/// method of Barill et al. 2018: a node farther than β·r from the query (r = radius of a sphere
/// around the node's area-weighted centroid c holding all its triangles) contributes the first two
/// terms of the Taylor expansion of its area integral, `[(N·d + tr C)/|d|³ − 3 dᵀ S d/|d|⁵] / 4π`
/// with d = c − p, N the summed area vectors, C = Σ a_t n_t (x̄_t − c)ᵀ and S its symmetric part;
/// every other node is opened, and leaves near the query use the exact van Oosterom–Strackee solid
/// angle. The traversal runs on the 4-wide tree (the same shape as the distance one): the far test
/// and the expansion of all four children of a node are one SIMD pass, and a near leaf's solid
/// angles are evaluated four triangles at a time with a polynomial f32 `atan2` (within 2·10⁻⁷
/// relative of f64). Each child keeps its own sphere, so the acceptance criterion is Barill's; a
/// node of the binary tree that lies between two levels of the 4-wide one is never tested, so its
/// children are expanded separately where it would have been expanded as a whole (more terms,
/// slightly smaller error). The neglected terms are O((r/|d|)²) relative to a node's solid angle, so the error does not
/// grow as the query approaches the surface; values within
/// [`SignedDistanceOptions::refine_band`] of 1/2 are recomputed with 4β. Measured errors are in the
/// crate documentation. On watertight, consistently oriented meshes w is 1 inside and 0 outside, so
/// the threshold agrees with ray parity away from the surface (tested).
#[derive(Clone, Debug)]
pub struct SignedDistance {
    /// 4-wide BVH for the closest-point search.
    nodes4: Vec<Node4>,
    /// The leaves' triangles in SoA packets of four, in the order the 4-wide BVH references them.
    packets: Vec<TriPacket>,
    /// 4-wide winding tree, index for index the same shape as `nodes4`.
    wnodes4: Vec<WNode4>,
    /// Triangle corners in leaf order.
    tris: Vec<[Vec3A; 3]>,
    /// Original triangle index for each slot of `tris`.
    tri_ids: Vec<u32>,
    options: SignedDistanceOptions,
    surface_eps: f32,
    stack_hint: usize,
    /// Internal coordinates are the mesh's times `to_internal` (a power of two, usually 1) ...
    to_internal: f64,
    /// ... and internal distances and points times `to_original` (its inverse) are the mesh's.
    to_original: f64,
    /// Bounding-box centre, internal coordinates.
    center: DVec3,
    /// Distance from `center` beyond which a query takes the far path (internal units).
    far: f64,
}

/// Where a query point goes: the ordinary f32 search, or the far path (internal coordinates).
enum Query {
    Near(Vec3A),
    Far(DVec3),
}

/// Per-thread traversal scratch space.
#[derive(Default)]
struct Scratch {
    /// Closest-point stack: (box distance², child, leaf triangle count or 0).
    pairs: Vec<(f32, u32, u32)>,
    nodes: Vec<u32>,
    /// Triangle slot nearest to the previous query of a batch (`u32::MAX`: none), a starting bound
    /// for the next one. Only used where the reported triangle does not matter (distances).
    last: u32,
}

/// Closest point on triangle (a, b, c) to p (Ericson, Real-Time Collision Detection 5.1.5), with the
/// barycentric weights of a, b, c.
#[inline(always)]
pub(crate) fn closest_on_triangle(p: Vec3A, a: Vec3A, b: Vec3A, c: Vec3A) -> (Vec3A, Vec3A) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, Vec3A::X);
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, Vec3A::Y);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, Vec3A::new(1.0 - v, v, 0.0));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, Vec3A::Z);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, Vec3A::new(1.0 - w, 0.0, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, Vec3A::new(0.0, 1.0 - w, w));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    if !(v.is_finite() && w.is_finite()) {
        // A triangle so small that its squared area underflows: treat it as its first corner.
        return (a, Vec3A::X);
    }
    (a + ab * v + ac * w, Vec3A::new(1.0 - v - w, v, w))
}

/// Signed solid angle of triangle (a, b, c) seen from the origin (van Oosterom & Strackee 1983);
/// positive when the triangle is counter-clockwise seen from the origin's side opposite its normal,
/// i.e. when the origin is behind the triangle.
#[inline(always)]
pub(crate) fn solid_angle(a: Vec3A, b: Vec3A, c: Vec3A) -> f32 {
    let la = a.length();
    let lb = b.length();
    let lc = c.length();
    let det = a.dot(b.cross(c));
    let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    2.0 * det.atan2(den)
}

/// [`solid_angle`] of four triangles at once (SoA corners relative to the query).
#[inline(always)]
fn solid_angle4(a: P4, b: P4, c: P4) -> Vec4 {
    let la = sqrt4(a.dot(a));
    let lb = sqrt4(b.dot(b));
    let lc = sqrt4(c.dot(c));
    let bc = P4 {
        x: b.y * c.z - b.z * c.y,
        y: b.z * c.x - b.x * c.z,
        z: b.x * c.y - b.y * c.x,
    };
    let det = a.dot(bc);
    let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    Vec4::splat(2.0) * atan2_4(det, den)
}

/// Triangles per obvhs build: larger meshes are first split top-down ([`sah_split`]) until each
/// part has at most this many. PLOC (obvhs's builder) merges only
/// mutual nearest neighbours in each pass, and on triangles whose spacing shrinks geometrically
/// that is one merge per pass: 60 000 such triangles took 13 s and a million would take about an
/// hour. Parts of this size bound that worst case to a fraction of a second each.
const PLOC_PART: usize = 1024;

/// The BVH over `prims`: nodes (inner nodes' children adjacent, the root first) and the order of
/// the triangles in its leaves. The parts are split off first, built by obvhs in parallel, and
/// placed in the order a depth-first build would place them, so the tree does not depend on the
/// thread count.
fn build_nodes(prims: &[Triangle], params: BvhBuildParams) -> (Vec<Node>, Vec<u32>) {
    let mut refs = prim_refs(prims);
    let plan = plan_parts(&mut refs, 0);
    let indices: Vec<u32> = refs.iter().map(|r| r.index).collect();
    drop(refs);
    let mut ranges = Vec::new();
    plan.leaves(&mut ranges);
    let bvhs: Vec<Bvh2> = ranges
        .par_iter()
        .map(|r| {
            let part: Vec<Triangle> = indices[r.clone()]
                .iter()
                .map(|&k| prims[k as usize])
                .collect();
            build_bvh2_from_tris(&part, params, &mut Duration::default())
        })
        .collect();
    let mut nodes = vec![Node::default()];
    let mut order = Vec::with_capacity(prims.len());
    let mut built = bvhs.iter();
    place(&plan, &indices, 0, &mut nodes, &mut order, &mut built);
    (depth_first(&nodes), order)
}

/// The same tree with its nodes renumbered in depth-first order (each inner node's two children
/// still adjacent, the left one's subtree next): obvhs numbers a part's nodes in the order PLOC
/// made them, so the bottom-up and top-down passes that follow jumped around memory, 3.4 s of
/// the build on 5.5 M triangles.
fn depth_first(nodes: &[Node]) -> Vec<Node> {
    let mut out = Vec::with_capacity(nodes.len());
    out.push(nodes[0]);
    // Inner nodes placed whose children are not yet: (old index, new index).
    let mut stack = vec![(0usize, 0usize)];
    while let Some((old, new)) = stack.pop() {
        let n = nodes[old];
        if n.count > 0 {
            continue;
        }
        let first = out.len();
        out.push(nodes[n.first as usize]);
        out.push(nodes[n.first as usize + 1]);
        out[new].first = first as u32;
        stack.push((n.first as usize + 1, first + 1));
        stack.push((n.first as usize, first));
    }
    out
}

/// What the top-down split reads of a triangle, kept beside its index so that each split streams
/// through one array instead of gathering corners from `prims` in an order that the splits above
/// it shuffled (on 1.4 M triangles the gathers made planning take 4 s of CPU).
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    /// The mean of the corners.
    centroid: Vec3,
    /// The triangle's bounds.
    lo: Vec3,
    hi: Vec3,
    /// The triangle in `prims`.
    index: u32,
}

/// Each triangle's [`PrimRef`], in the order of `prims`.
fn prim_refs(prims: &[Triangle]) -> Vec<PrimRef> {
    prims
        .par_iter()
        .enumerate()
        .map(|(k, t)| PrimRef {
            centroid: ((t.v0 + t.v1 + t.v2) / 3.0).into(),
            lo: t.v0.min(t.v1).min(t.v2).into(),
            hi: t.v0.max(t.v1).max(t.v2).into(),
            index: k as u32,
        })
        .collect()
}

/// How [`build_nodes`] splits the triangles: ranges of the reordered triangles, each of at most
/// [`PLOC_PART`], under a binary tree of [`sah_split`]s.
enum PartPlan {
    Part(std::ops::Range<usize>),
    Split(Box<PartPlan>, Box<PartPlan>),
}

impl PartPlan {
    /// The parts' ranges, depth first, left before right.
    fn leaves(&self, out: &mut Vec<std::ops::Range<usize>>) {
        match self {
            PartPlan::Part(r) => out.push(r.clone()),
            PartPlan::Split(l, r) => {
                l.leaves(out);
                r.leaves(out);
            }
        }
    }
}

/// Splits `refs` (which start at `offset` in the whole list) until every part has at most
/// [`PLOC_PART`] triangles; the two sides of a split are planned in parallel.
fn plan_parts(refs: &mut [PrimRef], offset: usize) -> PartPlan {
    if refs.len() <= PLOC_PART {
        return PartPlan::Part(offset..offset + refs.len());
    }
    let mid = sah_split(refs, SAH_CHUNK);
    let (left, right) = refs.split_at_mut(mid);
    let (l, r) = rayon::join(
        || plan_parts(left, offset),
        || plan_parts(right, offset + mid),
    );
    PartPlan::Split(Box::new(l), Box::new(r))
}

/// Fills `nodes[slot]` with the subtree of `plan`, taking the parts' BVHs from `built` in the
/// order of [`PartPlan::leaves`].
fn place(
    plan: &PartPlan,
    indices: &[u32],
    slot: usize,
    nodes: &mut Vec<Node>,
    order: &mut Vec<u32>,
    built: &mut std::slice::Iter<Bvh2>,
) {
    let range = match plan {
        PartPlan::Split(l, r) => {
            let first = nodes.len();
            nodes.extend([Node::default(), Node::default()]);
            place(l, indices, first, nodes, order, built);
            place(r, indices, first + 1, nodes, order, built);
            let (l, r) = (nodes[first], nodes[first + 1]);
            nodes[slot] = Node {
                min: l.min.min(r.min),
                first: first as u32,
                max: l.max.max(r.max),
                count: 0,
            };
            return;
        }
        PartPlan::Part(range) => range,
    };
    let bvh = built.next().expect("one BVH per part");
    let part = &indices[range.clone()];
    // obvhs's root goes to `slot`, its other nodes after the existing ones (in their order, so
    // siblings stay adjacent), its leaves' triangles after those already placed.
    let base = nodes.len() - 1;
    let at = |j: u32| if j == 0 { slot as u32 } else { base as u32 + j };
    let first_triangle = order.len() as u32;
    order.extend(bvh.primitive_indices.iter().map(|&k| part[k as usize]));
    for (j, n) in bvh.nodes.iter().enumerate() {
        let node = Node {
            min: n.aabb.min.into(),
            first: if n.prim_count == 0 {
                at(n.first_index)
            } else {
                first_triangle + n.first_index
            },
            max: n.aabb.max.into(),
            count: n.prim_count,
        };
        if j == 0 {
            nodes[slot] = node;
        } else {
            nodes.push(node);
        }
    }
}

/// Bins per axis of [`sah_split`].
const SAH_BINS: usize = 16;

/// Triangles per task of [`sah_split`]'s passes over a large split (the top levels, where
/// `rayon::join` has not yet spread the work).
const SAH_CHUNK: usize = 1 << 14;

/// Per-axis bins of a split: counts and bounds (what [`sah_split`] accumulates). Counts and
/// min/max are exact in any order, so the chunks' sums give the sequential pass's bins.
#[derive(Clone, Copy)]
struct SahBins {
    count: [[usize; SAH_BINS]; 3],
    lo: [[Vec3A; SAH_BINS]; 3],
    hi: [[Vec3A; SAH_BINS]; 3],
}

impl SahBins {
    fn new() -> Self {
        SahBins {
            count: [[0; SAH_BINS]; 3],
            lo: [[Vec3A::splat(f32::INFINITY); SAH_BINS]; 3],
            hi: [[Vec3A::splat(f32::NEG_INFINITY); SAH_BINS]; 3],
        }
    }

    fn merge(mut self, o: &SahBins) -> Self {
        for a in 0..3 {
            for b in 0..SAH_BINS {
                self.count[a][b] += o.count[a][b];
                self.lo[a][b] = self.lo[a][b].min(o.lo[a][b]);
                self.hi[a][b] = self.hi[a][b].max(o.hi[a][b]);
            }
        }
        self
    }
}

/// Reorders `refs` into two non-empty halves at the returned position: the split of the
/// triangles' centroids into [`SAH_BINS`] bins per axis with the least surface
/// area cost (the count of each side times the area of its box), so that the top levels of the
/// tree are as tight as PLOC's; the median of the longest axis where every centroid coincides.
/// Splits of more than `chunk` triangles bin in parallel chunks of that many.
fn sah_split(refs: &mut [PrimRef], chunk: usize) -> usize {
    let empty = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY));
    let union = |(a, b): (Vec3A, Vec3A), (c, d): (Vec3A, Vec3A)| (a.min(c), b.max(d));
    let centroid_bounds = |chunk: &[PrimRef]| {
        chunk.iter().fold(empty, |(lo, hi), r| {
            let c = Vec3A::from(r.centroid);
            (lo.min(c), hi.max(c))
        })
    };
    let (lo, hi) = if refs.len() > chunk {
        refs.par_chunks(chunk)
            .map(centroid_bounds)
            .reduce(|| empty, union)
    } else {
        centroid_bounds(refs)
    };
    let half_area = |(a, b): (Vec3A, Vec3A)| {
        let d = (b - a).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    };
    let extent = hi - lo;
    let bin_of = |r: &PrimRef, axis: usize| {
        let f = (r.centroid[axis] - lo[axis]) / extent[axis] * SAH_BINS as f32;
        (f as usize).min(SAH_BINS - 1)
    };
    let axes: Vec<usize> = (0..3)
        .filter(|&a| !extent[a].is_nan() && extent[a] > 0.0)
        .collect();
    let fill = |chunk: &[PrimRef]| {
        let mut bins = SahBins::new();
        for r in chunk {
            let (l, h) = (Vec3A::from(r.lo), Vec3A::from(r.hi));
            for &a in &axes {
                let b = bin_of(r, a);
                bins.count[a][b] += 1;
                bins.lo[a][b] = bins.lo[a][b].min(l);
                bins.hi[a][b] = bins.hi[a][b].max(h);
            }
        }
        bins
    };
    let bins = if refs.len() > chunk {
        refs.par_chunks(chunk)
            .map(fill)
            .reduce(SahBins::new, |a, b| a.merge(&b))
    } else {
        fill(refs)
    };
    let mut best: Option<(f32, usize, usize)> = None;
    for &axis in &axes {
        let count = &bins.count[axis];
        let boxes: [(Vec3A, Vec3A); SAH_BINS] =
            std::array::from_fn(|b| (bins.lo[axis][b], bins.hi[axis][b]));
        // Cost of splitting after bin i: left bins 0..=i, right the rest.
        let mut right = [(0.0f32, 0usize); SAH_BINS];
        let (mut acc, mut n) = (empty, 0);
        for i in (1..SAH_BINS).rev() {
            acc = union(acc, boxes[i]);
            n += count[i];
            right[i - 1] = (half_area(acc), n);
        }
        let (mut acc, mut n) = (empty, 0);
        for i in 0..SAH_BINS - 1 {
            acc = union(acc, boxes[i]);
            n += count[i];
            let (right_area, right_n) = right[i];
            if n == 0 || right_n == 0 {
                continue;
            }
            let cost = half_area(acc) * n as f32 + right_area * right_n as f32;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, i));
            }
        }
    }
    match best {
        Some((_, axis, bin)) => {
            let mut left = 0;
            for i in 0..refs.len() {
                if bin_of(&refs[i], axis) <= bin {
                    refs.swap(i, left);
                    left += 1;
                }
            }
            left
        }
        None => {
            let axis = extent.max_position();
            let mid = refs.len() / 2;
            refs.select_nth_unstable_by(mid, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
            mid
        }
    }
}

impl SignedDistance {
    /// Builds the BVH and the winding-number data with default options.
    ///
    /// # Errors
    /// [`GeomError::NonFiniteVertex`], [`GeomError::IndexOutOfRange`], or [`GeomError::NoTriangles`]
    /// if the mesh has no triangle of non-zero area. Zero-area triangles are skipped (they change
    /// neither distance nor winding number of a clean mesh).
    pub fn new(mesh: &Mesh) -> Result<Self, GeomError> {
        Self::with_options(mesh, SignedDistanceOptions::default())
    }

    /// Like [`SignedDistance::new`], with explicit options.
    pub fn with_options(mesh: &Mesh, options: SignedDistanceOptions) -> Result<Self, GeomError> {
        mesh.validate()?;
        let bounds = mesh.bounds();
        let max_abs = bounds.min.abs().max(bounds.max.abs()).max_element() as f64;
        let exponent = if max_abs > 0.0
            && (max_abs > 2f64.powi(TAME_EXPONENT) || max_abs < 2f64.powi(-TAME_EXPONENT))
        {
            // Largest magnitude into [0.5, 1).
            -(max_abs.log2().floor() as i32) - 1
        } else {
            0
        };
        let to_internal = 2f64.powi(exponent);
        let internal = |v: Vec3| -> Vec3 {
            if exponent == 0 {
                v
            } else {
                (v.as_dvec3() * to_internal).as_vec3()
            }
        };
        let mut prims = Vec::with_capacity(mesh.triangles.len());
        let mut ids = Vec::with_capacity(mesh.triangles.len());
        for (i, t) in mesh.triangles.iter().enumerate() {
            let [a, b, c] = t.map(|k| internal(mesh.vertices[k as usize]));
            if (b - a).as_dvec3().cross((c - a).as_dvec3()) == DVec3::ZERO {
                continue;
            }
            prims.push(Triangle {
                v0: a.into(),
                v1: b.into(),
                v2: c.into(),
            });
            ids.push(i as u32);
        }
        if prims.is_empty() {
            return Err(GeomError::NoTriangles {
                dropped: mesh.triangles.len(),
            });
        }
        let mut params = BvhBuildParams::fast_build();
        params.pre_split = false; // one leaf per triangle: no double counting in winding sums
        params.max_prims_per_leaf = options.max_leaf_size.clamp(1, 255);
        let (nodes, order) = build_nodes(&prims, params);

        let tris: Vec<[Vec3A; 3]> = order
            .iter()
            .map(|&k| {
                let t = &prims[k as usize];
                [t.v0, t.v1, t.v2]
            })
            .collect();
        let tri_ids: Vec<u32> = order.iter().map(|&k| ids[k as usize]).collect();

        // Winding data, bottom-up over the nodes reachable from the root.
        let mut order = Vec::with_capacity(nodes.len());
        let mut stack = vec![0u32];
        let mut max_stack = 1;
        while let Some(i) = stack.pop() {
            order.push(i);
            let n = &nodes[i as usize];
            if n.count == 0 {
                stack.push(n.first);
                stack.push(n.first + 1);
                max_stack = max_stack.max(stack.len());
            }
        }
        let mut wnodes = vec![WindingNode::default(); nodes.len()];
        // f64 moments: area, centroid, area vector, first-order moment C_ij = Σ a n_i (x̄ − c)_j.
        let mut moments = vec![(0.0f64, DVec3::ZERO, DVec3::ZERO, DMat3::ZERO); nodes.len()];
        let outer = |n: DVec3, d: DVec3| DMat3::from_cols(n * d.x, n * d.y, n * d.z);
        for &i in order.iter().rev() {
            let n = nodes[i as usize];
            let (area, center, area_normal, moment) = if n.count > 0 {
                let leaf = &tris[n.first as usize..(n.first + n.count) as usize];
                let parts: Vec<(f64, DVec3, DVec3)> = leaf
                    .iter()
                    .map(|t| {
                        let [a, b, c] = t.map(|v| Vec3::from(v).as_dvec3());
                        let cr = 0.5 * (b - a).cross(c - a);
                        (cr.length(), (a + b + c) / 3.0, cr)
                    })
                    .collect();
                let area: f64 = parts.iter().map(|x| x.0).sum();
                let an: DVec3 = parts.iter().map(|x| x.2).sum();
                let center = if area > 0.0 {
                    parts.iter().map(|x| x.0 * x.1).sum::<DVec3>() / area
                } else {
                    ((n.min + n.max) * 0.5).as_dvec3()
                };
                let moment = parts
                    .iter()
                    .fold(DMat3::ZERO, |m, x| m + outer(x.2, x.1 - center));
                (area, center, an, moment)
            } else {
                let (l, r) = (n.first as usize, n.first as usize + 1);
                let (ml, mr) = (moments[l], moments[r]);
                let area = ml.0 + mr.0;
                let center = if area > 0.0 {
                    (ml.0 * ml.1 + mr.0 * mr.1) / area
                } else {
                    ((n.min + n.max) * 0.5).as_dvec3()
                };
                let an = ml.2 + mr.2;
                let moment = ml.3 + mr.3 + outer(ml.2, ml.1 - center) + outer(mr.2, mr.1 - center);
                (area, center, an, moment)
            };
            moments[i as usize] = (area, center, area_normal, moment);
            let center = center.as_vec3();
            // Radius: farthest box corner (always valid), tightened by the children's spheres or the
            // leaf's vertices.
            let half = (n.max - n.min) * 0.5;
            let corner = (center - (n.min + n.max) * 0.5).abs() + half;
            let mut radius = corner.length();
            if n.count > 0 {
                let mut r = 0.0f32;
                for t in &tris[n.first as usize..(n.first + n.count) as usize] {
                    for v in t {
                        r = r.max(Vec3::from(*v).distance(center));
                    }
                }
                radius = radius.min(r);
            } else {
                let (l, r) = (n.first as usize, n.first as usize + 1);
                let rl = wnodes[l].center.distance(center) + wnodes[l].radius2.sqrt();
                let rr = wnodes[r].center.distance(center) + wnodes[r].radius2.sqrt();
                radius = radius.min(rl.max(rr));
            }
            // Guard against rounding: a tiny relative margin.
            radius *= 1.0 + 1e-5;
            let sym = (moment + moment.transpose()) * 0.5;
            wnodes[i as usize] = WindingNode {
                center,
                radius2: radius * radius,
                area_normal: area_normal.as_vec3(),
                trace: (sym.x_axis.x + sym.y_axis.y + sym.z_axis.z) as f32,
                sym_diag: DVec3::new(sym.x_axis.x, sym.y_axis.y, sym.z_axis.z).as_vec3(),
                sym_off: DVec3::new(sym.y_axis.x, sym.z_axis.x, sym.z_axis.y).as_vec3(),
            };
        }
        let mut nodes4 = Vec::with_capacity(nodes.len() / 2 + 1);
        let mut wnodes4 = Vec::with_capacity(nodes.len() / 2 + 1);
        let mut packets = Vec::with_capacity(tris.len() / 2 + 1);
        collapse4(
            &nodes,
            &wnodes,
            &tris,
            0,
            &mut nodes4,
            &mut wnodes4,
            &mut packets,
        );
        let ibounds = crate::Aabb {
            min: internal(bounds.min),
            max: internal(bounds.max),
        };
        let diag = ibounds.diagonal();
        let (lo, hi) = (ibounds.min.as_dvec3(), ibounds.max.as_dvec3());
        Ok(SignedDistance {
            to_internal,
            to_original: 2f64.powi(-exponent),
            center: (lo + hi) * 0.5,
            far: FAR_QUERY_RADII * ((hi - lo) * 0.5).length(),
            nodes4,
            packets,
            wnodes4,
            tris,
            tri_ids,
            options,
            surface_eps: options.surface_tolerance.max(0.0) * diag,
            stack_hint: max_stack + 8,
        })
    }

    /// Number of triangles in the BVH (zero-area triangles of the input are not included).
    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// The options this was built with.
    pub fn options(&self) -> SignedDistanceOptions {
        self.options
    }

    fn scratch(&self) -> Scratch {
        Scratch {
            pairs: Vec::with_capacity(2 * self.stack_hint),
            nodes: Vec::with_capacity(self.stack_hint),
            last: u32::MAX,
        }
    }

    /// Maps a (finite) query into internal coordinates and picks its path.
    #[inline]
    fn query(&self, p: Vec3) -> Query {
        let q = p.as_dvec3() * self.to_internal;
        if q.distance_squared(self.center) > self.far * self.far {
            Query::Far(q)
        } else if self.to_internal == 1.0 {
            Query::Near(p.into())
        } else {
            Query::Near(q.as_vec3().into())
        }
    }

    /// An internal distance in the mesh's units.
    #[inline]
    fn out(&self, d: f32) -> f32 {
        if self.to_original == 1.0 {
            d
        } else {
            (d as f64 * self.to_original) as f32
        }
    }

    /// The far path (see [`FAR_QUERY_RADII`]): distance, closest point, slot and barycentrics, all
    /// internal and in f64.
    fn far_closest(&self, q: DVec3, stack: &mut Vec<(f32, u32, u32)>) -> (f64, DVec3, u32, DVec3) {
        let dir = q - self.center;
        let proxy = self.center + dir * (self.far / dir.length());
        let (_, slot) = self.nearest(proxy.as_vec3().into(), stack, u32::MAX);
        let t = self.tris[slot as usize].map(|v| Vec3::from(v).as_dvec3());
        let (c, bary) = closest_on_triangle_f64(q, t[0], t[1], t[2]);
        (q.distance(c), c, slot, bary)
    }

    /// Squared distance from `p` to the triangle in `slot`.
    #[inline(always)]
    fn tri_dist2(&self, p: Vec3A, slot: usize) -> f32 {
        let t = &self.tris[slot];
        let (q, _) = closest_on_triangle(p, t[0], t[1], t[2]);
        (q - p).length_squared()
    }

    /// Best squared distance and slot of the nearest triangle. `seed` (a triangle slot, or
    /// `u32::MAX`) is tested first to start with a finite bound; the distance is the same either way
    /// (the minimum over all triangles), only the slot may differ between equally near triangles.
    #[inline]
    fn nearest(&self, p: Vec3A, stack: &mut Vec<(f32, u32, u32)>, seed: u32) -> (f32, u32) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { self.nearest_avx(p, stack, seed) };
        }
        self.nearest_impl(p, stack, seed)
    }

    /// [`nearest`](Self::nearest) compiled with AVX: the same SSE operations in VEX encoding (three
    /// operands, fewer register copies and spills), so the results are bit-identical. No FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    fn nearest_avx(&self, p: Vec3A, stack: &mut Vec<(f32, u32, u32)>, seed: u32) -> (f32, u32) {
        self.nearest_impl(p, stack, seed)
    }

    #[inline(always)]
    fn nearest_impl(&self, p: Vec3A, stack: &mut Vec<(f32, u32, u32)>, seed: u32) -> (f32, u32) {
        stack.clear();
        let (mut best, mut best_slot) = if (seed as usize) < self.tris.len() {
            (self.tri_dist2(p, seed as usize), seed)
        } else {
            (f32::INFINITY, 0)
        };
        let (px, py, pz) = (Vec4::splat(p.x), Vec4::splat(p.y), Vec4::splat(p.z));
        let p4 = P4 {
            x: px,
            y: py,
            z: pz,
        };
        // Current entry: (node or first packet, packet count; 0 for an inner node).
        let (mut c, mut count) = (0u32, 0u32);
        loop {
            if count > 0 {
                let start = c as usize;
                for t in &self.packets[start..start + count as usize] {
                    let d2 = t.dist2(p4);
                    if d2.cmplt(Vec4::splat(best)).any() {
                        // Lanes in slot order with a strict `<`: the same triangle as a scalar scan.
                        for (&d, &slot) in d2.to_array().iter().zip(&t.slot) {
                            if d < best {
                                best = d;
                                best_slot = slot;
                            }
                        }
                    }
                }
            } else {
                let n = &self.nodes4[c as usize];
                let d2 = n.box_dist2(px, py, pz);
                let mut mask = d2.cmplt(Vec4::splat(best)).bitmask();
                if mask != 0 {
                    if mask & (mask - 1) == 0 {
                        // One child left: go straight on.
                        let k = mask.trailing_zeros() as usize;
                        (c, count) = (n.child[k], n.count[k]);
                        continue;
                    }
                    // Several: sort by decreasing box distance, push all but the nearest, which is
                    // visited next.
                    let d = d2.to_array();
                    let mut cand = [(0.0f32, 0u32, 0u32); 4];
                    let mut m = 0;
                    while mask != 0 {
                        let k = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let e = (d[k], n.child[k], n.count[k]);
                        let mut j = m;
                        while j > 0 && cand[j - 1].0 < e.0 {
                            cand[j] = cand[j - 1];
                            j -= 1;
                        }
                        cand[j] = e;
                        m += 1;
                    }
                    for e in &cand[..m - 1] {
                        stack.push(*e);
                    }
                    (c, count) = (cand[m - 1].1, cand[m - 1].2);
                    continue;
                }
            }
            // Pop the next entry that can still hold something closer.
            loop {
                match stack.pop() {
                    Some((d, i, k)) if d < best => {
                        (c, count) = (i, k);
                        break;
                    }
                    Some(_) => {}
                    None => return (best, best_slot),
                }
            }
        }
    }

    /// The closest point on the mesh to `p`, with triangle id and barycentrics.
    ///
    /// A non-finite `p` gives a NaN distance and point, and triangle `u32::MAX`.
    pub fn closest_point(&self, p: Vec3) -> ClosestPoint {
        self.closest_point_with(p, &mut self.scratch())
    }

    fn closest_point_with(&self, p: Vec3, s: &mut Scratch) -> ClosestPoint {
        if !p.is_finite() {
            return ClosestPoint {
                distance: f32::NAN,
                point: Vec3::NAN,
                triangle: u32::MAX,
                barycentric: Vec3::NAN,
            };
        }
        let pa = match self.query(p) {
            Query::Near(pa) => pa,
            Query::Far(q) => {
                let (d, c, slot, bary) = self.far_closest(q, &mut s.pairs);
                return ClosestPoint {
                    distance: (d * self.to_original) as f32,
                    point: (c * self.to_original).as_vec3(),
                    triangle: self.tri_ids[slot as usize],
                    barycentric: bary.as_vec3(),
                };
            }
        };
        let (d2, slot) = self.nearest(pa, &mut s.pairs, u32::MAX);
        let t = &self.tris[slot as usize];
        let (q, bary) = closest_on_triangle(pa, t[0], t[1], t[2]);
        let point = if self.to_original == 1.0 {
            q.into()
        } else {
            (Vec3::from(q).as_dvec3() * self.to_original).as_vec3()
        };
        ClosestPoint {
            distance: self.out(d2.sqrt()),
            point,
            triangle: self.tri_ids[slot as usize],
            barycentric: bary.into(),
        }
    }

    /// Unsigned distance from `p` to the mesh (NaN for non-finite `p`).
    pub fn unsigned_distance(&self, p: Vec3) -> f32 {
        if !p.is_finite() {
            return f32::NAN;
        }
        let mut stack = Vec::with_capacity(self.stack_hint);
        match self.query(p) {
            Query::Near(pa) => self.out(self.nearest(pa, &mut stack, u32::MAX).0.sqrt()),
            Query::Far(q) => (self.far_closest(q, &mut stack).0 * self.to_original) as f32,
        }
    }

    #[inline]
    fn winding_beta(&self, p: Vec3A, beta: f32, stack: &mut Vec<u32>) -> f32 {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { self.winding_beta_avx(p, beta, stack) };
        }
        self.winding_beta_impl(p, beta, stack)
    }

    /// [`winding_beta`](Self::winding_beta) compiled with AVX (same operations, VEX encoding).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    fn winding_beta_avx(&self, p: Vec3A, beta: f32, stack: &mut Vec<u32>) -> f32 {
        self.winding_beta_impl(p, beta, stack)
    }

    #[inline(always)]
    fn winding_beta_impl(&self, p: Vec3A, beta: f32, stack: &mut Vec<u32>) -> f32 {
        let beta2 = Vec4::splat(beta * beta);
        let p4 = P4 {
            x: Vec4::splat(p.x),
            y: Vec4::splat(p.y),
            z: Vec4::splat(p.z),
        };
        let lane = Vec4::new(0.0, 1.0, 2.0, 3.0);
        stack.clear();
        // Solid angles (far-field terms and exact ones), summed per lane.
        let mut acc = Vec4::ZERO;
        let mut ni = 0u32;
        loop {
            let w = &self.wnodes4[ni as usize];
            let center = P4 {
                x: w.center[0],
                y: w.center[1],
                z: w.center[2],
            };
            let d = center.sub(p4);
            let d2 = d.dot(d);
            let far = d2.cmpgt(beta2 * w.radius2);
            let far_bits = far.bitmask();
            if far_bits != 0 {
                // Dipole plus first-order term of the Taylor expansion of the area integral
                // (Barill et al. 2018): (N·r + tr C) / |r|^3 - 3 rᵀ S r / |r|^5.
                // One division and one square root: 1/|r|² and 1/|r|.
                let inv_d2 = Vec4::ONE / d2;
                let inv3 = sqrt4(inv_d2) * inv_d2;
                let n = P4 {
                    x: w.area_normal[0],
                    y: w.area_normal[1],
                    z: w.area_normal[2],
                };
                // 3 rᵀ S r, with the factors 3 and 6 folded into the stored moments.
                let rsr3 = w.sym_diag3[0] * d.x * d.x
                    + w.sym_diag3[1] * d.y * d.y
                    + w.sym_diag3[2] * d.z * d.z
                    + w.sym_off6[0] * d.x * d.y
                    + w.sym_off6[1] * d.x * d.z
                    + w.sym_off6[2] * d.y * d.z;
                let t = (n.dot(d) + w.trace - rsr3 * inv_d2) * inv3;
                acc += Vec4::select(far, t, Vec4::ZERO);
            }
            let mut near = !far_bits & 0xf;
            let mut next = u32::MAX;
            while near != 0 {
                let k = near.trailing_zeros() as usize;
                near &= near - 1;
                let (c, n) = (w.child[k], w.count[k]);
                if n > 0 {
                    let start = c as usize;
                    let packets = &self.packets[start..start + n.div_ceil(4) as usize];
                    for (j, t) in packets.iter().enumerate() {
                        let a = t.a.sub(p4);
                        let b = t.b.sub(p4);
                        let cc = t.c.sub(p4);
                        // Padding lanes (a short last packet) repeat lane 0: masked out.
                        let live = lane.cmplt(Vec4::splat((n - 4 * j as u32) as f32));
                        acc += Vec4::select(live, solid_angle4(a, b, cc), Vec4::ZERO);
                    }
                } else if c != u32::MAX {
                    if next == u32::MAX {
                        next = c;
                    } else {
                        stack.push(c);
                    }
                }
            }
            if next != u32::MAX {
                ni = next;
                continue;
            }
            match stack.pop() {
                Some(i) => ni = i,
                None => break,
            }
        }
        acc.element_sum() / (4.0 * PI)
    }

    /// The winding number at an original-coordinate (finite) point; 0 on the far path.
    fn winding_at(&self, p: Vec3, s: &mut Scratch) -> f32 {
        match self.query(p) {
            Query::Near(pa) => self.winding_with(pa, s),
            Query::Far(_) => 0.0,
        }
    }

    fn winding_with(&self, p: Vec3A, s: &mut Scratch) -> f32 {
        let w = self.winding_beta(p, self.options.beta, &mut s.nodes);
        if (w - 0.5).abs() < self.options.refine_band {
            self.winding_beta(p, self.options.beta * 4.0, &mut s.nodes)
        } else {
            w
        }
    }

    /// The generalised winding number at `p` (1 inside a closed, outward-oriented surface, 0
    /// outside, 1/2 on it; fractional near holes of open meshes), by the fast hierarchical method.
    pub fn winding_number(&self, p: Vec3) -> f32 {
        if !p.is_finite() {
            return f32::NAN;
        }
        self.winding_at(p, &mut self.scratch())
    }

    /// The winding number with the exact solid angle of every triangle (O(n); for checks).
    pub fn winding_number_exact(&self, p: Vec3) -> f64 {
        let p = Vec3A::from((p.as_dvec3() * self.to_internal).as_vec3());
        let s: f64 = self
            .tris
            .iter()
            .map(|t| solid_angle(t[0] - p, t[1] - p, t[2] - p) as f64)
            .sum();
        s / (4.0 * std::f64::consts::PI)
    }

    /// Whether `p` is inside: winding number ≥ 1/2. False for non-finite `p`.
    pub fn is_inside(&self, p: Vec3) -> bool {
        self.winding_number(p) >= INSIDE_WINDING
    }

    /// [`is_inside`](Self::is_inside) for many points, in parallel with rayon.
    pub fn is_inside_batch(&self, points: &[Vec3]) -> Vec<bool> {
        self.batch(points, |sd, p, s| {
            p.is_finite() && sd.winding_at(p, s) >= INSIDE_WINDING
        })
    }

    /// Signed distance: negative inside (winding number ≥ 1/2), positive outside, NaN for a
    /// non-finite `p`. Points within the surface tolerance (see [`SignedDistanceOptions`]) get their
    /// distance unsigned.
    pub fn signed_distance(&self, p: Vec3) -> f32 {
        self.signed_distance_with(p, &mut self.scratch())
    }

    fn signed_distance_with(&self, p: Vec3, s: &mut Scratch) -> f32 {
        if !p.is_finite() {
            return f32::NAN;
        }
        let pa = match self.query(p) {
            Query::Near(pa) => pa,
            // Outside the bounding sphere by thousands of radii: outside.
            Query::Far(q) => {
                return (self.far_closest(q, &mut s.pairs).0 * self.to_original) as f32;
            }
        };
        let (d2, slot) = self.nearest(pa, &mut s.pairs, s.last);
        s.last = slot;
        let d = d2.sqrt();
        if d <= self.surface_eps {
            return self.out(d);
        }
        if self.winding_with(pa, s) >= INSIDE_WINDING {
            -self.out(d)
        } else {
            self.out(d)
        }
    }

    /// Runs `f` over all points in parallel. Large batches are processed in Morton (Z-curve) order
    /// of the points so that consecutive queries touch the same BVH nodes (much better cache use for
    /// random point sets); results are returned in input order.
    fn batch<T, F>(&self, points: &[Vec3], f: F) -> Vec<T>
    where
        T: Send + Copy + Default,
        F: Fn(&Self, Vec3, &mut Scratch) -> T + Sync,
    {
        if points.len() < 4096 {
            return points
                .par_iter()
                .with_min_len(256)
                .map_init(|| self.scratch(), |s, &p| f(self, p, s))
                .collect();
        }
        let mut b = crate::Aabb::EMPTY;
        for p in points.iter().filter(|p| p.is_finite()) {
            b.extend(*p);
        }
        let lo = b.min;
        let inv = 1023.0 / (b.max - b.min).max(Vec3::splat(1e-30));
        let mut keys: Vec<u64> = points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let code = if p.is_finite() {
                    let c = ((*p - lo) * inv).clamp(Vec3::ZERO, Vec3::splat(1023.0));
                    (spread10(c.x as u32) << 2) | (spread10(c.y as u32) << 1) | spread10(c.z as u32)
                } else {
                    u32::MAX
                };
                ((code as u64) << 32) | i as u64
            })
            .collect();
        keys.par_sort_unstable();
        // Gather the points in Morton order first: a tight loop whose cache misses overlap, rather
        // than one miss at the start of every query.
        let sorted_points: Vec<Vec3> = keys
            .par_iter()
            .with_min_len(4096)
            .map(|&k| points[k as u32 as usize])
            .collect();
        let sorted: Vec<T> = sorted_points
            .par_iter()
            .with_min_len(256)
            .map_init(|| self.scratch(), |s, &p| f(self, p, s))
            .collect();
        let mut out = vec![T::default(); points.len()];
        for (k, v) in keys.iter().zip(sorted) {
            out[*k as u32 as usize] = v;
        }
        out
    }

    /// [`signed_distance`](Self::signed_distance) for many points, in parallel with rayon.
    pub fn signed_distance_batch(&self, points: &[Vec3]) -> Vec<f32> {
        self.batch(points, |sd, p, s| sd.signed_distance_with(p, s))
    }

    /// [`closest_point`](Self::closest_point) for many points, in parallel with rayon.
    pub fn closest_point_batch(&self, points: &[Vec3]) -> Vec<ClosestPoint> {
        self.batch(points, |sd, p, s| sd.closest_point_with(p, s))
    }

    /// [`winding_number`](Self::winding_number) for many points, in parallel with rayon.
    pub fn winding_number_batch(&self, points: &[Vec3]) -> Vec<f32> {
        self.batch(points, |sd, p, s| {
            if p.is_finite() {
                sd.winding_at(p, s)
            } else {
                f32::NAN
            }
        })
    }
}

/// Spreads the low 10 bits of `v` so that there are two zero bits between each (for Morton codes).
fn spread10(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    x = (x | (x << 2)) & 0x0924_9249;
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The parts' plan bins the large splits in parallel chunks: the tree must still be the one a
    /// single thread builds (81 920 triangles: the first splits run over several chunks).
    #[test]
    fn parts_build_the_same_tree_at_any_thread_count() {
        let mesh = Mesh::icosphere(1.0, 6);
        let prims: Vec<Triangle> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|k| Vec3A::from(mesh.vertices[k as usize]));
                Triangle {
                    v0: a,
                    v1: b,
                    v2: c,
                }
            })
            .collect();
        assert!(prims.len() > 4 * SAH_CHUNK);
        let build = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| build_nodes(&prims, BvhBuildParams::fast_build()))
        };
        // Binned in chunks as the top splits are, and in one pass: the same split.
        let mut refs = prim_refs(&prims);
        let mut whole = refs.clone();
        let mid = sah_split(&mut refs, 1000);
        assert_eq!(mid, sah_split(&mut whole, usize::MAX));
        assert!(
            refs.iter()
                .map(|r| r.index)
                .eq(whole.iter().map(|r| r.index))
        );
        assert!(0 < mid && mid < prims.len());
        let (one_nodes, one_order) = build(1);
        let (nodes, order) = build(4);
        assert_eq!(order, one_order);
        assert!(nodes == one_nodes, "the trees differ");
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.iter().copied().eq(0..prims.len() as u32));
        // Depth-first numbering: children after their parent, every node reached once, every
        // triangle slot in one leaf.
        let (mut stack, mut seen, mut slots) = (vec![0usize], 0, vec![0u8; prims.len()]);
        while let Some(i) = stack.pop() {
            seen += 1;
            let n = nodes[i];
            if n.count > 0 {
                for s in n.first..n.first + n.count {
                    slots[s as usize] += 1;
                }
            } else {
                assert!(n.first as usize > i);
                stack.extend([n.first as usize + 1, n.first as usize]);
            }
        }
        assert_eq!(seen, nodes.len());
        assert!(slots.iter().all(|&c| c == 1));
    }

    /// A small deterministic generator (no dependency on the samplers).
    fn lcg(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    /// Relative error of `atan2_4` against f64 `atan2` (absolute below the smallest normal f32).
    fn atan2_error(y: f32, x: f32) -> f64 {
        let got = atan2_4(Vec4::splat(y), Vec4::splat(x)).x;
        let want = (y as f64).atan2(x as f64);
        if want.is_nan() {
            return if got.is_nan() { 0.0 } else { f64::INFINITY };
        }
        // Same sign, signed zeros included (atan2(±0, x) must keep the sign of the zero).
        if got.is_sign_negative() != want.is_sign_negative() {
            return f64::INFINITY;
        }
        (got as f64 - want).abs() / want.abs().max(f32::MIN_POSITIVE as f64)
    }

    #[test]
    fn vector_atan2_matches_f64() {
        let mut st = 11u64;
        let mut max_err = 0.0f64;
        // Random magnitudes over many decades, all four quadrants.
        for i in 0..400_000 {
            let e = |s: &mut u64| 2f32.powf(lcg(s) * if i % 2 == 0 { 8.0 } else { 60.0 });
            let y = lcg(&mut st).signum() * e(&mut st) * lcg(&mut st).abs();
            let x = lcg(&mut st).signum() * e(&mut st) * lcg(&mut st).abs();
            max_err = max_err.max(atan2_error(y, x));
        }
        // Near the octant boundaries |y| = |x| and the axes, where the reduction switches.
        for i in 0..20_000 {
            let x = 1.0 + i as f32 * 1e-4;
            for (y, x) in [
                (x, 1.0),
                (1.0, x),
                (-x, -1.0),
                (1.0, -x),
                (1e-4 * x, -1.0),
                (-1e-4 * x, 1.0),
                (1.0, 1e-4 * x),
                (-1.0, -1e-4 * x),
            ] {
                max_err = max_err.max(atan2_error(y, x));
            }
        }
        // Zeros of both signs, infinities, NaN, subnormals and exact diagonals.
        let special = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            1e-40,
            -1e-40,
            f32::MIN_POSITIVE,
            f32::MAX,
            -f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        for &y in &special {
            for &x in &special {
                let err = atan2_error(y, x);
                assert!(err < 1e-6, "atan2({y}, {x}): error {err}");
            }
        }
        eprintln!("vector atan2: max relative error {max_err:.2e}");
        assert!(max_err < 4e-7, "max relative error {max_err}");
    }

    #[test]
    fn vector_solid_angle_matches_scalar() {
        // Same f32 determinant and denominator, so only the atan2 differs: a few ulp.
        let mut st = 5u64;
        let v = |s: &mut u64| Vec3A::new(lcg(s), lcg(s), lcg(s));
        for _ in 0..20_000 {
            let t: [[Vec3A; 3]; 4] = std::array::from_fn(|_| [v(&mut st), v(&mut st), v(&mut st)]);
            let corner = |j: usize| P4 {
                x: Vec4::from_array(t.map(|t| t[j].x)),
                y: Vec4::from_array(t.map(|t| t[j].y)),
                z: Vec4::from_array(t.map(|t| t[j].z)),
            };
            let got = solid_angle4(corner(0), corner(1), corner(2)).to_array();
            for (l, t) in t.iter().enumerate() {
                let want = solid_angle(t[0], t[1], t[2]);
                assert!(
                    (got[l] - want).abs() <= 1e-6 * want.abs().max(1.0),
                    "{t:?}: {} vs {want}",
                    got[l]
                );
            }
        }
    }

    #[test]
    fn avx_paths_are_bit_identical() {
        // The AVX-compiled traversals run the same operations as the baseline ones.
        let mut st = 3u64;
        let vertices: Vec<Vec3> = (0..900)
            .map(|_| Vec3::new(lcg(&mut st), lcg(&mut st), lcg(&mut st)))
            .collect();
        let triangles: Vec<[u32; 3]> = (0..300).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        let (mesh, _) = Mesh::from_raw(vertices, triangles).unwrap();
        let sdf = SignedDistance::new(&mesh).unwrap();
        let (mut pairs, mut nodes) = (Vec::new(), Vec::new());
        for i in 0..2000 {
            let p = Vec3A::new(lcg(&mut st), lcg(&mut st), lcg(&mut st)) * 1.5;
            let seed = if i % 2 == 0 { u32::MAX } else { i % 300 };
            let want = sdf.nearest_impl(p, &mut pairs, seed);
            assert_eq!(sdf.nearest(p, &mut pairs, seed), want);
            let want = sdf.winding_beta_impl(p, 1.5, &mut nodes);
            assert_eq!(
                sdf.winding_beta(p, 1.5, &mut nodes).to_bits(),
                want.to_bits()
            );
        }
    }

    #[test]
    fn packet_distance_is_bit_identical_to_scalar() {
        let mut st = 7u64;
        let v = |s: &mut u64| Vec3A::new(lcg(s), lcg(s), lcg(s));
        let mut tris: Vec<[Vec3A; 3]> = (0..400)
            .map(|_| [v(&mut st), v(&mut st), v(&mut st)])
            .collect();
        // Degenerate and nearly degenerate triangles: collinear, repeated corner, tiny, huge.
        let a = v(&mut st);
        let b = v(&mut st);
        tris.push([a, b, a + (b - a) * 0.5]);
        tris.push([a, a, b]);
        tris.push([
            a,
            a + Vec3A::splat(1e-30),
            a + Vec3A::new(1e-30, 0.0, 2e-30),
        ]);
        tris.push([a * 1e6, b * 1e6, Vec3A::ZERO]);
        for chunk in tris.chunks(4) {
            let slot: [usize; 4] = std::array::from_fn(|l| if l < chunk.len() { l } else { 0 });
            let corner = |j: usize| P4 {
                x: Vec4::from_array(slot.map(|s| chunk[s][j].x)),
                y: Vec4::from_array(slot.map(|s| chunk[s][j].y)),
                z: Vec4::from_array(slot.map(|s| chunk[s][j].z)),
            };
            let packet = TriPacket {
                a: corner(0),
                b: corner(1),
                c: corner(2),
                slot: [0; 4],
            };
            for _ in 0..50 {
                // Points near and far, so that every Voronoi region is hit.
                let s = if lcg(&mut st) > 0.0 { 3.0 } else { 0.3 };
                let p = v(&mut st) * s;
                let p4 = P4 {
                    x: Vec4::splat(p.x),
                    y: Vec4::splat(p.y),
                    z: Vec4::splat(p.z),
                };
                let got = packet.dist2(p4).to_array();
                for (l, &k) in slot.iter().enumerate() {
                    let t = chunk[k];
                    let (q, _) = closest_on_triangle(p, t[0], t[1], t[2]);
                    let want = (q - p).length_squared();
                    assert_eq!(got[l].to_bits(), want.to_bits(), "{t:?} {p:?}");
                }
            }
        }
    }
}
