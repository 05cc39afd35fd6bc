//! The analytic primitives of a scene and their exact signed distances and gradients (Inigo
//! Quilez's catalogue), in f64, in the primitive's own frame.
//!
//! ```
//! use glam::{DVec3, Vec3};
//! use sdf_nn::serve::scene::Primitive;
//!
//! let cube = Primitive::Box { half_extents: Vec3::ONE };
//! let (d, g) = cube.distance_and_gradient(DVec3::new(3.0, 0.0, 0.0));
//! assert_eq!((d, g), (2.0, DVec3::X));
//! ```
//!
//! Every primitive's value is the exact signed distance to its surface, so its gradient has unit
//! length wherever it exists. On the medial set (the centre of a sphere, the planes of symmetry
//! inside a box) the gradient is one of the one-sided gradients, chosen by a fixed rule, so that
//! closest-point iterations never divide by zero.

use glam::{DVec2, DVec3, Vec3};

/// An analytic shape, centred at the origin of its frame (place it with a transform).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Primitive {
    /// A ball of radius `radius > 0`.
    Sphere {
        /// Radius.
        radius: f32,
    },
    /// An axis-aligned box with half extents `> 0`.
    Box {
        /// Half the edge lengths.
        half_extents: Vec3,
    },
    /// A box with half extents `half_extents` (the outer size) whose edges and corners are
    /// rounded with radius `0 ≤ radius ≤ min(half_extents)`.
    RoundBox {
        /// Half the outer edge lengths.
        half_extents: Vec3,
        /// Rounding radius.
        radius: f32,
    },
    /// All points within `radius > 0` of the segment `a`–`b` (`a = b` is a sphere).
    Capsule {
        /// One end of the axis.
        a: Vec3,
        /// The other end.
        b: Vec3,
        /// Radius.
        radius: f32,
    },
    /// A torus around the y axis: a tube of radius `minor > 0` around the circle of radius
    /// `major > 0` in the xz plane.
    Torus {
        /// Radius of the centre circle.
        major: f32,
        /// Radius of the tube.
        minor: f32,
    },
    /// The half space `n̂·p ≤ offset` below the plane `n̂·p = offset`, `n̂ = n/|n|`: `normal`
    /// need not be unit length (it is normalised) but must not be zero.
    Plane {
        /// Outward normal.
        normal: Vec3,
        /// Signed distance of the plane from the origin along the normal.
        offset: f32,
    },
    /// A capped cylinder around the y axis: radius `radius > 0`, `|y| ≤ half_height` (`> 0`).
    Cylinder {
        /// Radius.
        radius: f32,
        /// Half the height.
        half_height: f32,
    },
}

impl Primitive {
    /// The name used in scene files (`"sphere"`, `"box"`, `"round_box"`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            Primitive::Sphere { .. } => "sphere",
            Primitive::Box { .. } => "box",
            Primitive::RoundBox { .. } => "round_box",
            Primitive::Capsule { .. } => "capsule",
            Primitive::Torus { .. } => "torus",
            Primitive::Plane { .. } => "plane",
            Primitive::Cylinder { .. } => "cylinder",
        }
    }

    /// Checks the parameters: `Err((parameter, requirement))` names the first bad one.
    pub(crate) fn check(&self) -> Result<(), (&'static str, &'static str)> {
        let finite = |name, v: f32| v.is_finite().then_some(()).ok_or((name, "finite"));
        let positive = |name, v: f32| {
            finite(name, v)?;
            (v > 0.0).then_some(()).ok_or((name, "> 0"))
        };
        let positive3 = |name, v: Vec3| {
            (v.is_finite()).then_some(()).ok_or((name, "finite"))?;
            (v.min_element() > 0.0)
                .then_some(())
                .ok_or((name, "> 0 on every axis"))
        };
        match *self {
            Primitive::Sphere { radius } => positive("radius", radius),
            Primitive::Box { half_extents } => positive3("half_extents", half_extents),
            Primitive::RoundBox {
                half_extents,
                radius,
            } => {
                positive3("half_extents", half_extents)?;
                finite("radius", radius)?;
                if !(0.0..=half_extents.min_element()).contains(&radius) {
                    return Err(("radius", "between 0 and the smallest half extent"));
                }
                Ok(())
            }
            Primitive::Capsule { a, b, radius } => {
                a.is_finite().then_some(()).ok_or(("a", "finite"))?;
                b.is_finite().then_some(()).ok_or(("b", "finite"))?;
                positive("radius", radius)
            }
            Primitive::Torus { major, minor } => {
                positive("major", major)?;
                positive("minor", minor)
            }
            Primitive::Plane { normal, offset } => {
                normal
                    .is_finite()
                    .then_some(())
                    .ok_or(("normal", "finite"))?;
                // Normalising must not overflow or divide by zero.
                let len = normal.as_dvec3().length();
                (len > 1e-12).then_some(()).ok_or(("normal", "not zero"))?;
                finite("offset", offset)
            }
            Primitive::Cylinder {
                radius,
                half_height,
            } => {
                positive("radius", radius)?;
                positive("half_height", half_height)
            }
        }
    }

    /// The signed distance at `p` (the primitive's frame).
    pub fn distance(&self, p: DVec3) -> f64 {
        self.distance_and_gradient(p).0
    }

    /// The signed distance and its gradient at `p` (the primitive's frame).
    pub fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
        match *self {
            Primitive::Sphere { radius } => (p.length() - radius as f64, p.normalize_or(DVec3::Y)),
            Primitive::Box { half_extents } => box_sdf(p, half_extents.as_dvec3()),
            Primitive::RoundBox {
                half_extents,
                radius,
            } => {
                let r = radius as f64;
                let (d, g) = box_sdf(p, half_extents.as_dvec3() - DVec3::splat(r));
                (d - r, g)
            }
            Primitive::Capsule { a, b, radius } => {
                let (a, b) = (a.as_dvec3(), b.as_dvec3());
                let (pa, ba) = (p - a, b - a);
                let len2 = ba.length_squared();
                let h = if len2 > 0.0 {
                    (pa.dot(ba) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let v = pa - ba * h;
                (v.length() - radius as f64, v.normalize_or(DVec3::Y))
            }
            Primitive::Torus { major, minor } => {
                let (radial, rho) = radial(p);
                let q = DVec2::new(rho - major as f64, p.y);
                let w = q.normalize_or(DVec2::X);
                (q.length() - minor as f64, radial * w.x + DVec3::Y * w.y)
            }
            Primitive::Plane { normal, offset } => {
                let n = normal.as_dvec3().normalize();
                (p.dot(n) - offset as f64, n)
            }
            Primitive::Cylinder {
                radius,
                half_height,
            } => {
                let (radial, rho) = radial(p);
                let axial = DVec3::Y * if p.y < 0.0 { -1.0 } else { 1.0 };
                let d = DVec2::new(rho - radius as f64, p.y.abs() - half_height as f64);
                let out = d.max(DVec2::ZERO);
                if out != DVec2::ZERO {
                    let len = out.length();
                    (len, (radial * out.x + axial * out.y) / len)
                } else if d.x > d.y {
                    (d.x, radial)
                } else {
                    (d.y, axial)
                }
            }
        }
    }
}

/// The unit direction away from the y axis in the xz plane (x where `p` is on the axis) and the
/// distance from the axis.
fn radial(p: DVec3) -> (DVec3, f64) {
    let xz = DVec3::new(p.x, 0.0, p.z);
    (xz.normalize_or(DVec3::X), xz.length())
}

/// Exact distance and gradient of the box with half extents `b`.
fn box_sdf(p: DVec3, b: DVec3) -> (f64, DVec3) {
    let sign = DVec3::select(p.cmplt(DVec3::ZERO), -DVec3::ONE, DVec3::ONE);
    let q = p.abs() - b;
    let out = q.max(DVec3::ZERO);
    if out != DVec3::ZERO {
        let len = out.length();
        return (len, out * sign / len);
    }
    // Inside: the nearest face is that of the largest (least negative) component.
    let axis = if q.x >= q.y && q.x >= q.z {
        0
    } else if q.y >= q.z {
        1
    } else {
        2
    };
    let mut g = DVec3::ZERO;
    g[axis] = sign[axis];
    (q[axis], g)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn v(x: f64, y: f64, z: f64) -> DVec3 {
        DVec3::new(x, y, z)
    }

    /// Each primitive at points whose distance is known by hand (faces, edges, corners, inside).
    #[test]
    fn distances_match_closed_forms() {
        let sphere = Primitive::Sphere { radius: 2.0 };
        let cube = Primitive::Box {
            half_extents: Vec3::new(1.0, 2.0, 3.0),
        };
        let round = Primitive::RoundBox {
            half_extents: Vec3::new(1.0, 2.0, 3.0),
            radius: 0.5,
        };
        let capsule = Primitive::Capsule {
            a: Vec3::new(0.0, -1.0, 0.0),
            b: Vec3::new(0.0, 1.0, 0.0),
            radius: 0.5,
        };
        let torus = Primitive::Torus {
            major: 2.0,
            minor: 0.5,
        };
        let plane = Primitive::Plane {
            normal: Vec3::new(0.0, 2.0, 0.0),
            offset: 1.0,
        };
        let cylinder = Primitive::Cylinder {
            radius: 1.0,
            half_height: 2.0,
        };
        let cases = [
            (sphere, v(0.0, 3.0, 4.0), 3.0),
            (sphere, v(0.0, 0.0, 0.5), -1.5),
            (cube, v(4.0, 0.0, 0.0), 3.0),
            (cube, v(0.0, -2.5, 0.0), 0.5),
            (cube, v(2.0, 3.0, 4.0), 3f64.sqrt()),
            (cube, v(0.5, 0.0, 0.0), -0.5),
            (cube, v(0.0, 0.0, 0.0), -1.0),
            (round, v(4.0, 0.0, 0.0), 3.0),
            // The corner is rounded: from (0.5, 1.5, 2.5) plus the radius.
            (round, v(2.0, 3.0, 4.0), (3.0 * 1.5f64.powi(2)).sqrt() - 0.5),
            (round, v(0.0, 0.0, 0.0), -1.0),
            (capsule, v(2.0, 0.0, 0.0), 1.5),
            (capsule, v(0.0, 4.0, 0.0), 2.5),
            (capsule, v(3.0, -5.0, 0.0), 5.0 - 0.5),
            (torus, v(2.0, 0.0, 0.0), -0.5),
            (torus, v(0.0, 0.0, 5.0), 2.5),
            (torus, v(0.0, 1.0, 0.0), 5f64.sqrt() - 0.5),
            (plane, v(7.0, 3.0, -2.0), 2.0),
            (plane, v(0.0, -1.0, 0.0), -2.0),
            (cylinder, v(3.0, 0.0, 0.0), 2.0),
            (cylinder, v(0.0, 5.0, 0.0), 3.0),
            (cylinder, v(0.0, 0.0, 4.0), 3.0),
            (cylinder, v(4.0, 6.0, 0.0), 5.0),
            (cylinder, v(0.0, 0.0, 0.0), -1.0),
            (cylinder, v(0.0, 1.8, 0.5), -0.2),
        ];
        for (prim, p, want) in cases {
            let got = prim.distance(p);
            assert!(
                (got - want).abs() < 1e-12,
                "{prim:?} at {p}: {got} vs {want}"
            );
        }
    }

    /// Analytic gradients agree with central differences, away from the medial set.
    #[test]
    fn gradients_match_finite_differences() {
        let prims = [
            Primitive::Sphere { radius: 0.7 },
            Primitive::Box {
                half_extents: Vec3::new(0.5, 0.8, 0.3),
            },
            Primitive::RoundBox {
                half_extents: Vec3::new(0.5, 0.8, 0.3),
                radius: 0.2,
            },
            Primitive::Capsule {
                a: Vec3::new(-0.3, 0.1, 0.2),
                b: Vec3::new(0.4, -0.5, 0.0),
                radius: 0.25,
            },
            Primitive::Torus {
                major: 0.8,
                minor: 0.2,
            },
            Primitive::Plane {
                normal: Vec3::new(1.0, 2.0, -0.5),
                offset: 0.3,
            },
            Primitive::Cylinder {
                radius: 0.6,
                half_height: 0.4,
            },
        ];
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let h = 1e-6;
        for prim in prims {
            for _ in 0..500 {
                let p = v(
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-1.5..1.5),
                );
                let (_, g) = prim.distance_and_gradient(p);
                let fd = DVec3::new(
                    prim.distance(p + DVec3::X * h) - prim.distance(p - DVec3::X * h),
                    prim.distance(p + DVec3::Y * h) - prim.distance(p - DVec3::Y * h),
                    prim.distance(p + DVec3::Z * h) - prim.distance(p - DVec3::Z * h),
                ) / (2.0 * h);
                assert!((g - fd).length() < 1e-5, "{prim:?} at {p}: {g} vs {fd}");
                assert!(
                    (g.length() - 1.0).abs() < 1e-9,
                    "exact distances have |∇| = 1"
                );
            }
        }
    }

    #[test]
    fn parameters_are_checked() {
        let bad = [
            (Primitive::Sphere { radius: 0.0 }, "radius"),
            (Primitive::Sphere { radius: f32::NAN }, "radius"),
            (
                Primitive::Box {
                    half_extents: Vec3::new(1.0, -1.0, 1.0),
                },
                "half_extents",
            ),
            (
                Primitive::RoundBox {
                    half_extents: Vec3::ONE,
                    radius: 1.5,
                },
                "radius",
            ),
            (
                Primitive::Plane {
                    normal: Vec3::ZERO,
                    offset: 0.0,
                },
                "normal",
            ),
            (
                Primitive::Cylinder {
                    radius: 1.0,
                    half_height: f32::INFINITY,
                },
                "half_height",
            ),
        ];
        for (prim, field) in bad {
            assert_eq!(prim.check().unwrap_err().0, field, "{prim:?}");
        }
        assert!(
            Primitive::Capsule {
                a: Vec3::ONE,
                b: Vec3::ONE,
                radius: 1.0
            }
            .check()
            .is_ok()
        );
    }
}
