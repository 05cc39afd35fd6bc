//! Closest point on one triangle: the scalar routine (generic over f32 and f64, so the search and
//! the f64 reference share one implementation) and the 4-wide packet version of the f32 one, which
//! must stay bit-identical to it (hence both in one file).

use std::ops::{Add, Div, Mul, Sub};

use glam::{DVec3, Vec3A, Vec4};

use super::simd::P4;

/// Four triangles in SoA form (one leaf's worth; a short leaf repeats its first triangle).
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(16))]
pub(super) struct TriPacket {
    pub(super) a: P4,
    pub(super) b: P4,
    pub(super) c: P4,
    /// Triangle slot of each lane (padding lanes repeat lane 0's).
    pub(super) slot: [u32; 4],
}

impl TriPacket {
    /// Squared distances from `p` to the four triangles: [`closest_on_triangle`] evaluated in all
    /// four lanes at once with every branch replaced by a select, operation for operation, so the
    /// results are bit-identical to the scalar function's `(q − p)²`.
    #[inline(always)]
    pub(super) fn dist2(&self, p: P4) -> Vec4 {
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

/// The arithmetic [`closest_on_triangle`] needs of a scalar: `f32` and `f64`.
pub(super) trait Real:
    Copy
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    fn is_finite(self) -> bool;
}

impl Real for f32 {
    const ZERO: f32 = 0.0;
    const ONE: f32 = 1.0;
    #[inline(always)]
    fn is_finite(self) -> bool {
        f32::is_finite(self)
    }
}

impl Real for f64 {
    const ZERO: f64 = 0.0;
    const ONE: f64 = 1.0;
    #[inline(always)]
    fn is_finite(self) -> bool {
        f64::is_finite(self)
    }
}

/// The arithmetic [`closest_on_triangle`] needs of a point: glam's `Vec3A` (the f32 search) and
/// `DVec3` (the far path and the f64 reference). Each method is the glam one, so the generic
/// routine compiles to the same operations, in the same order, as a routine written for the type.
pub(super) trait TriangleVector:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Self::Scalar, Output = Self>
{
    type Scalar: Real;
    const X: Self;
    const Y: Self;
    const Z: Self;
    /// Whether a face-region result whose weights are not finite (a triangle so small that its
    /// squared area underflows) becomes the first corner. The f32 search needs it (a BVH triangle
    /// can be that small in f32); the f64 routine never had it and keeps its results unchanged:
    /// such a triangle gives a non-finite point there, which no distance comparison picks.
    const UNDERFLOW_TO_CORNER: bool;
    fn new(x: Self::Scalar, y: Self::Scalar, z: Self::Scalar) -> Self;
    fn dot(self, o: Self) -> Self::Scalar;
}

impl TriangleVector for Vec3A {
    type Scalar = f32;
    const X: Vec3A = Vec3A::X;
    const Y: Vec3A = Vec3A::Y;
    const Z: Vec3A = Vec3A::Z;
    const UNDERFLOW_TO_CORNER: bool = true;
    #[inline(always)]
    fn new(x: f32, y: f32, z: f32) -> Vec3A {
        Vec3A::new(x, y, z)
    }
    #[inline(always)]
    fn dot(self, o: Vec3A) -> f32 {
        Vec3A::dot(self, o)
    }
}

impl TriangleVector for DVec3 {
    type Scalar = f64;
    const X: DVec3 = DVec3::X;
    const Y: DVec3 = DVec3::Y;
    const Z: DVec3 = DVec3::Z;
    const UNDERFLOW_TO_CORNER: bool = false;
    #[inline(always)]
    fn new(x: f64, y: f64, z: f64) -> DVec3 {
        DVec3::new(x, y, z)
    }
    #[inline(always)]
    fn dot(self, o: DVec3) -> f64 {
        DVec3::dot(self, o)
    }
}

/// Closest point on triangle (a, b, c) to p (Ericson, Real-Time Collision Detection 5.1.5), with the
/// barycentric weights of a, b, c. One routine for both precisions: f32 ([`Vec3A`], the search,
/// whose results [`TriPacket::dist2`] reproduces bit for bit) and f64 ([`DVec3`], the far path and
/// [`closest_on_triangle_f64`]).
#[inline(always)]
pub(super) fn closest_on_triangle<V: TriangleVector>(p: V, a: V, b: V, c: V) -> (V, V) {
    let zero = V::Scalar::ZERO;
    let one = V::Scalar::ONE;
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= zero && d2 <= zero {
        return (a, V::X);
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= zero && d4 <= d3 {
        return (b, V::Y);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= zero && d1 >= zero && d3 <= zero {
        let v = d1 / (d1 - d3);
        return (a + ab * v, V::new(one - v, v, zero));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= zero && d5 <= d6 {
        return (c, V::Z);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= zero && d2 >= zero && d6 <= zero {
        let w = d2 / (d2 - d6);
        return (a + ac * w, V::new(one - w, zero, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= zero && (d4 - d3) >= zero && (d5 - d6) >= zero {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, V::new(zero, one - w, w));
    }
    let denom = one / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    if V::UNDERFLOW_TO_CORNER && !(v.is_finite() && w.is_finite()) {
        // A triangle so small that its squared area underflows: treat it as its first corner.
        return (a, V::X);
    }
    (a + ab * v + ac * w, V::new(one - v - w, v, w))
}

/// Closest point on triangle (a, b, c) to p in f64 (Ericson), with barycentric weights: the far
/// path's exact distance, and the brute-force [`reference`](crate::reference)'s.
pub fn closest_on_triangle_f64(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (DVec3, DVec3) {
    closest_on_triangle(p, a, b, c)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distance::tests::lcg;

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
