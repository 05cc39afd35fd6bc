//! The 4-wide helpers of the SIMD traversals: points in SoA form ([`P4`]), and the lane-wise
//! square root and `atan2` that the solid angles need (glam gives neither as one SIMD pass).

use std::f32::consts::PI;

use glam::{BVec4A, Vec3A, Vec4};

/// Three SoA vectors: the x, y and z coordinates of four points (`repr(C)`: x, y, z in that
/// order, as [`GpuTriPacket`](super::GpuTriPacket) reads them).
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub(super) struct P4 {
    pub(super) x: Vec4,
    pub(super) y: Vec4,
    pub(super) z: Vec4,
}

impl P4 {
    /// The same point `p` in all four lanes.
    #[inline(always)]
    pub(super) fn splat(p: Vec3A) -> P4 {
        P4 {
            x: Vec4::splat(p.x),
            y: Vec4::splat(p.y),
            z: Vec4::splat(p.z),
        }
    }
    /// Four points, one per lane.
    #[inline(always)]
    pub(super) fn from_lanes(v: [Vec3A; 4]) -> P4 {
        P4 {
            x: Vec4::new(v[0].x, v[1].x, v[2].x, v[3].x),
            y: Vec4::new(v[0].y, v[1].y, v[2].y, v[3].y),
            z: Vec4::new(v[0].z, v[1].z, v[2].z, v[3].z),
        }
    }
    #[inline(always)]
    pub(super) fn sub(self, o: P4) -> P4 {
        P4 {
            x: self.x - o.x,
            y: self.y - o.y,
            z: self.z - o.z,
        }
    }
    #[inline(always)]
    pub(super) fn add(self, o: P4) -> P4 {
        P4 {
            x: self.x + o.x,
            y: self.y + o.y,
            z: self.z + o.z,
        }
    }
    #[inline(always)]
    pub(super) fn scale(self, s: Vec4) -> P4 {
        P4 {
            x: self.x * s,
            y: self.y * s,
            z: self.z * s,
        }
    }
    /// Same operation order as `Vec3A::dot`: (x·x + y·y) + z·z.
    #[inline(always)]
    pub(super) fn dot(self, o: P4) -> Vec4 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    #[inline(always)]
    pub(super) fn select(m: BVec4A, t: P4, f: P4) -> P4 {
        P4 {
            x: Vec4::select(m, t.x, f.x),
            y: Vec4::select(m, t.y, f.y),
            z: Vec4::select(m, t.z, f.z),
        }
    }
}

/// Lane-wise square root (one `sqrtps`; glam's `Vec4::sqrt` is four scalar calls).
#[inline(always)]
pub(super) fn sqrt4(v: Vec4) -> Vec4 {
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
pub(super) fn atan2_4(y: Vec4, x: Vec4) -> Vec4 {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distance::tests::lcg;

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
}
