//! The sign: the generalised winding number by Barill et al.'s fast hierarchical method on the
//! 4-wide winding tree (far nodes by their dipole and first-order terms, near leaves by exact
//! solid angles, four triangles at a time), and the per-node moments it is built from.

use std::f32::consts::PI;

use glam::{DMat3, DVec3, Vec3, Vec3A, Vec4};

use super::build::Node;
use super::simd::{P4, atan2_4, sqrt4};
use super::{Query, Scratch, SignedDistance};

/// Winding-number data of one binary BVH node (only used while building the 4-wide nodes).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct WindingNode {
    /// Area-weighted centroid of the node's triangles.
    pub(super) center: Vec3,
    /// Squared radius of a sphere around `center` containing all of the node's triangles.
    pub(super) radius2: f32,
    /// Sum of the node's area vectors (area × unit normal).
    pub(super) area_normal: Vec3,
    /// Trace of the first-order moment C = Σ a_t n_t (x̄_t − c)ᵀ.
    pub(super) trace: f32,
    /// Diagonal of the symmetric part of C.
    pub(super) sym_diag: Vec3,
    /// Off-diagonal (xy, xz, yz) of the symmetric part of C.
    pub(super) sym_off: Vec3,
}

/// A node of the 4-wide winding tree: the [`WindingNode`] data of up to four children in SoA form,
/// so that the far-field test and expansion of all four run in one SIMD pass. It has the same shape
/// and indices as the [`Node4`](super::closest::Node4) at the same position (inner child: index into `wnodes4`; leaf child:
/// first index into `packets`).
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(64))]
pub(super) struct WNode4 {
    /// Per-axis area-weighted centroids.
    pub(super) center: [Vec4; 3],
    /// Squared bounding-sphere radii; +∞ in unused slots (never far, and never opened).
    pub(super) radius2: Vec4,
    /// Per-axis summed area vectors.
    pub(super) area_normal: [Vec4; 3],
    /// Traces of the first-order moments.
    pub(super) trace: Vec4,
    /// Per-axis diagonals of the symmetric parts of the first-order moments, times 3.
    pub(super) sym_diag3: [Vec4; 3],
    /// Off-diagonals (xy, xz, yz) of the symmetric parts, times 6 (3 × the two symmetric entries).
    pub(super) sym_off6: [Vec4; 3],
    /// Inner child: index into `wnodes4`; leaf child: first packet; unused slot: `u32::MAX`.
    pub(super) child: [u32; 4],
    /// Number of triangles of a leaf child (0 for an inner child or an unused slot).
    pub(super) count: [u32; 4],
}

impl WNode4 {
    pub(super) const EMPTY: WNode4 = WNode4 {
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

/// Signed solid angle of triangle (a, b, c) seen from the origin (van Oosterom & Strackee 1983);
/// positive when the triangle is counter-clockwise seen from the origin's side opposite its normal,
/// i.e. when the origin is behind the triangle.
#[inline(always)]
pub(super) fn solid_angle(a: Vec3A, b: Vec3A, c: Vec3A) -> f32 {
    let la = a.length();
    let lb = b.length();
    let lc = c.length();
    let det = a.dot(b.cross(c));
    let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    2.0 * det.atan2(den)
}

/// [`solid_angle`] of four triangles at once (SoA corners relative to the query).
#[inline(always)]
pub(super) fn solid_angle4(a: P4, b: P4, c: P4) -> Vec4 {
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

impl SignedDistance {
    #[inline]
    pub(super) fn winding_beta(&self, p: Vec3A, beta: f32, stack: &mut Vec<u32>) -> f32 {
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
    pub(super) fn winding_beta_impl(&self, p: Vec3A, beta: f32, stack: &mut Vec<u32>) -> f32 {
        let beta2 = Vec4::splat(beta * beta);
        let p4 = P4::splat(p);
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
    pub(super) fn winding_at(&self, p: Vec3, s: &mut Scratch) -> f32 {
        match self.query(p) {
            Query::Near(pa) => self.winding_with(pa, s),
            Query::Far(_) => 0.0,
        }
    }

    pub(super) fn winding_with(&self, p: Vec3A, s: &mut Scratch) -> f32 {
        let w = self.winding_beta(p, self.options.beta, &mut s.nodes);
        if (w - 0.5).abs() < self.options.refine_band {
            self.winding_beta(p, self.options.beta * 4.0, &mut s.nodes)
        } else {
            w
        }
    }
}

/// The winding data of every node of the binary tree reachable from the root, computed bottom-up
/// (`order` lists parents before children): f64 moments of each leaf's triangles, merged upwards,
/// and a bounding sphere around each node's area-weighted centroid.
pub(super) fn winding_nodes(
    nodes: &[Node],
    tris: &[[Vec3A; 3]],
    order: &[u32],
) -> Vec<WindingNode> {
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
    wnodes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distance::tests::lcg;

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
}
