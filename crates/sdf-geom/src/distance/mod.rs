//! Exact closest-point distance on an `obvhs` BVH, and the sign from the fast generalised winding
//! number: the public [`SignedDistance`] (construction, queries, batches) and its options. The
//! rooms: `build` makes the trees, `closest` searches them for the nearest triangle, `winding`
//! sums the winding number, `triangle` holds the point–triangle routines (f32, f64 and 4-wide),
//! `simd` the 4-wide helpers, `gpu` lends the trees to GPU kernels.

mod build;
mod closest;
mod gpu;
mod simd;
mod triangle;
mod wide;
mod winding;

use glam::{DVec3, Vec3, Vec3A};
use obvhs::BvhBuildParams;
use rayon::prelude::*;

use crate::{GeomError, Mesh};
use build::{area_triangles, build_nodes, depth_first_order, tame_exponent};
use closest::Node4;
pub use gpu::{GpuBvhNode, GpuTrees, GpuTriPacket, GpuWindingNode};
pub use triangle::closest_on_triangle_f64;
use triangle::{TriPacket, closest_on_triangle};
use wide::collapse4;
use winding::{WNode4, solid_angle, winding_nodes};

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
        let exponent = tame_exponent(&bounds);
        let to_internal = 2f64.powi(exponent);
        let internal = |v: Vec3| -> Vec3 {
            if exponent == 0 {
                v
            } else {
                (v.as_dvec3() * to_internal).as_vec3()
            }
        };
        let (prims, ids) = area_triangles(mesh, internal)?;
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
        let (order, max_stack) = depth_first_order(&nodes);
        let wnodes = winding_nodes(&nodes, &tris, &order);
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
        // Gather the points in Morton order first: a tight loop whose cache misses overlap, rather
        // than one miss at the start of every query.
        let order = morton_order(points);
        let sorted_points: Vec<Vec3> = order
            .par_iter()
            .with_min_len(4096)
            .map(|&i| points[i as usize])
            .collect();
        let sorted: Vec<T> = sorted_points
            .par_iter()
            .with_min_len(256)
            .map_init(|| self.scratch(), |s, &p| f(self, p, s))
            .collect();
        let mut out = vec![T::default(); points.len()];
        for (&i, v) in order.iter().zip(sorted) {
            out[i as usize] = v;
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

/// The indices of `points` in Morton (Z-curve) order over the bounding box of the finite ones,
/// non-finite points last (ties by index): queries of neighbouring points, one after another
/// on a CPU thread or side by side in a GPU's SIMD group, then walk mostly the same nodes, and
/// those nodes stay in cache.
pub fn morton_order(points: &[Vec3]) -> Vec<u32> {
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
            (u64::from(code) << 32) | i as u64
        })
        .collect();
    keys.par_sort_unstable();
    keys.into_iter().map(|k| k as u32).collect()
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

    /// The Morton order is a permutation, with non-finite points last.
    #[test]
    fn morton_order_is_a_permutation() {
        let mut points = crate::sample::uniform_box(5000, 3);
        points[17] = glam::Vec3::NAN;
        let order = super::morton_order(&points);
        assert_eq!(*order.last().unwrap(), 17);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.into_iter().eq(0..5000));
    }

    /// A small deterministic generator (no dependency on the samplers).
    pub(super) fn lcg(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
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
}
