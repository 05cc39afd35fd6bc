//! The GPU's labels checked against the CPU's before a run uses them. The kernels are proven
//! against the CPU by the tests on lavapipe, but a run may meet a device or driver they never
//! ran on; a wrong label there would silently spoil every fit. So [`Labeller::choose`] labels a
//! few probe points on both paths first: `auto` falls back to the CPU if they disagree, and an
//! explicit `gpu` fails with [`GroundTruthError::Disagrees`].
//!
//! [`Labeller::choose`]: super::Labeller::choose

use glam::{DVec3, Vec3};
use sdf_geom::GpuTrees;

use super::GroundTruthError;

/// Probe points beside the surface (twice this many: each of as many triangles, on both
/// sides)...
const NEAR_PROBES: usize = 64;
/// ...and in the box.
const BOX_PROBES: usize = 64;
/// How far beside the surface the near probes lie, in diagonals.
const NEAR_OFFSET: f64 = 0.02;
/// Distances may differ by this many diagonals (the tests' bar is 1e-6; the H200 measured
/// 3.9e-8)...
const DISTANCE_TOLERANCE: f32 = 1e-5;
/// ...or by this many of the largest coordinate's magnitude: a closest point is computed at
/// the coordinates' scale, where a compiler's fused multiply-adds may round otherwise than the
/// CPU's arithmetic (an `sdf` call in mesh units on a mesh a few diagonals from the origin).
const COORDINATE_TOLERANCE: f32 = 64.0 * f32::EPSILON;
/// Signs are compared farther than this many diagonals from the surface...
const SIGN_BAND: f32 = 1e-4;
/// ...where the CPU's winding number is at least this far from 1/2 (the two fast winding
/// numbers differ by up to 1e-3 in the tests).
const WINDING_MARGIN: f32 = 0.01;

/// Points to compare the two paths on, in the units of the mesh the trees were built from:
/// the centroids of [`NEAR_PROBES`] triangles spread through the leaves (fewer for a mesh of
/// fewer), moved off the surface along the face normal by [`NEAR_OFFSET`] of the diagonal on
/// each side, and [`BOX_PROBES`] points of a Halton sequence in the bounding box grown by a
/// tenth.
pub(super) fn probe(trees: &GpuTrees<'_>) -> Probe {
    let to_mesh = 2f64.powi(-trees.exponent);
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    let root = &trees.nodes[0];
    for k in 0..4 {
        // Unused slots have an empty box (min +∞, max −∞).
        if root.min[0][k] <= root.max[0][k] {
            let corner = |c: &[[f32; 4]; 3]| {
                DVec3::new(c[0][k].into(), c[1][k].into(), c[2][k].into()) * to_mesh
            };
            lo = lo.min(corner(&root.min));
            hi = hi.max(corner(&root.max));
        }
    }
    let diagonal = (hi - lo).length();
    let magnitude = lo.abs().max(hi.abs()).max_element();
    let tolerance =
        (f64::from(DISTANCE_TOLERANCE) * diagonal).max(f64::from(COORDINATE_TOLERANCE) * magnitude);
    let mut points = Vec::with_capacity(2 * NEAR_PROBES + BOX_PROBES);
    let lanes = trees.packets.len() * 4;
    for i in 0..NEAR_PROBES.min(lanes) {
        let slot = i * lanes / NEAR_PROBES.min(lanes);
        let (packet, lane) = (&trees.packets[slot / 4], slot % 4);
        let corner = |c: &[[f32; 4]; 3]| {
            DVec3::new(c[0][lane].into(), c[1][lane].into(), c[2][lane].into()) * to_mesh
        };
        let (a, b, c) = (corner(&packet.a), corner(&packet.b), corner(&packet.c));
        let centroid = (a + b + c) / 3.0;
        let offset = (b - a).cross(c - a).normalize_or_zero() * (NEAR_OFFSET * diagonal);
        points.push((centroid + offset).as_vec3());
        points.push((centroid - offset).as_vec3());
    }
    let grown = (hi - lo) * 0.05;
    for i in 1..=BOX_PROBES {
        let t = DVec3::new(halton(i, 2), halton(i, 3), halton(i, 5));
        points.push((lo - grown + t * (hi - lo + 2.0 * grown)).as_vec3());
    }
    Probe {
        points,
        diagonal: diagonal as f32,
        tolerance: tolerance as f32,
    }
}

/// Where [`probe`] compares the two paths, and how closely.
pub(super) struct Probe {
    /// The points.
    pub points: Vec<Vec3>,
    /// The mesh's bounding-box diagonal.
    pub diagonal: f32,
    /// How far the paths' distances may differ: [`DISTANCE_TOLERANCE`] of the diagonal, or
    /// [`COORDINATE_TOLERANCE`] of the largest coordinate's magnitude if more.
    pub tolerance: f32,
}

/// Element `i` of the Halton sequence of `base`, in [0, 1).
fn halton(mut i: usize, base: usize) -> f64 {
    let (mut x, mut f) = (0.0, 1.0);
    while i > 0 {
        f /= base as f64;
        x += f * (i % base) as f64;
        i /= base;
    }
    x
}

/// How the GPU's signed distances at the probe points compare with the CPU's.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Agreement {
    /// Probe points.
    pub points: usize,
    /// Points whose distances differ by more than the probe's tolerance (or are not finite
    /// on the GPU), or whose signs differ where the CPU's is clear.
    pub misses: usize,
    /// Of those, the points whose signs differ.
    pub sign_misses: usize,
    /// The largest difference of the distances, in diagonals (∞ for a NaN).
    pub worst: f32,
}

impl Agreement {
    /// Compares the GPU's signed distances `gpu` at the points of `probe` with the CPU's
    /// `cpu`, whose winding numbers are `winding`.
    pub(super) fn of(probe: &Probe, cpu: &[f32], winding: &[f32], gpu: &[f32]) -> Self {
        let diagonal = probe.diagonal;
        let mut a = Agreement {
            points: cpu.len(),
            misses: 0,
            sign_misses: 0,
            worst: 0.0,
        };
        for ((&c, &w), &g) in cpu.iter().zip(winding).zip(gpu) {
            let apart = (g.abs() - c.abs()).abs();
            let apart = if apart.is_nan() { f32::INFINITY } else { apart };
            a.worst = a.worst.max(apart / diagonal);
            let clear = c.abs() > SIGN_BAND * diagonal && (w - 0.5).abs() > WINDING_MARGIN;
            // A NaN is a distance miss, not a sign.
            let flipped = clear && !g.is_nan() && (g < 0.0) != (c < 0.0);
            a.sign_misses += usize::from(flipped);
            a.misses += usize::from(flipped || apart > probe.tolerance);
        }
        a
    }

    /// `Ok` where the paths agree, else [`GroundTruthError::Disagrees`].
    pub(super) fn check(self) -> Result<(), GroundTruthError> {
        if self.misses == 0 {
            return Ok(());
        }
        Err(GroundTruthError::Disagrees {
            points: self.points,
            misses: self.misses,
            sign_misses: self.sign_misses,
            worst: self.worst,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paths agree within the tolerances; a distance apart, a clear sign flipped or a NaN
    /// is a disagreement; a flip beside the surface or where the winding number is nearly 1/2
    /// is not (the two fast winding numbers may round either way there).
    #[test]
    fn disagreements_are_counted_and_ambiguous_signs_forgiven() {
        let cpu = [0.5, -0.25, 1e-6, 0.3, -0.2];
        let winding = [0.0, 1.0, 0.5, 0.495, 0.9];
        let probe = Probe {
            points: vec![Vec3::ZERO; 5],
            diagonal: 2.0,
            tolerance: 2e-5,
        };
        let same = Agreement::of(&probe, &cpu, &winding, &cpu);
        assert_eq!((same.misses, same.sign_misses, same.worst), (0, 0, 0.0));
        assert!(same.check().is_ok());
        // Within 1e-5 of the diagonal; the flips beside the surface and at w ≈ 1/2 forgiven.
        let close = [0.500_01, -0.25, -1e-6, -0.3, -0.2];
        assert!(
            Agreement::of(&probe, &cpu, &winding, &close)
                .check()
                .is_ok()
        );
        let far = [0.6, -0.25, 1e-6, 0.3, -0.2];
        let a = Agreement::of(&probe, &cpu, &winding, &far);
        assert_eq!((a.misses, a.sign_misses), (1, 0));
        assert!((a.worst - 0.05).abs() < 1e-6, "{a:?}");
        let flipped = [0.5, 0.25, 1e-6, 0.3, -0.2];
        let a = Agreement::of(&probe, &cpu, &winding, &flipped);
        assert_eq!((a.misses, a.sign_misses), (1, 1));
        let nan = [0.5, -0.25, 1e-6, 0.3, f32::NAN];
        let a = Agreement::of(&probe, &cpu, &winding, &nan);
        assert_eq!((a.misses, a.sign_misses, a.worst), (1, 0, f32::INFINITY));
        let e = a.check().unwrap_err().to_string();
        assert!(e.contains("1 of 5 probe points"), "{e}");
    }

    /// The probe lies beside a sphere on both sides and in its box grown by a tenth.
    #[test]
    fn probes_lie_on_both_sides_and_in_the_box() {
        let mesh = sdf_geom::Mesh::icosphere(0.5, 2);
        let sdf = sdf_geom::SignedDistance::new(&mesh).unwrap();
        let Probe {
            points,
            diagonal,
            tolerance,
        } = probe(&sdf.gpu_trees());
        // Centred on the origin, the sphere's coordinates are within its diagonal.
        assert_eq!(tolerance, DISTANCE_TOLERANCE * diagonal);
        assert_eq!(points.len(), 2 * NEAR_PROBES + BOX_PROBES);
        assert!(
            (diagonal - mesh.bounds().diagonal()).abs() < 1e-5,
            "{diagonal}"
        );
        let d = sdf.signed_distance_batch(&points);
        let (near, boxed) = d.split_at(2 * NEAR_PROBES);
        let offset = NEAR_OFFSET as f32 * diagonal;
        // A face's centroid lies inside the sphere, a little: the distances are about the
        // offset, less or more.
        for pair in near.chunks(2) {
            assert!(pair[0] > 0.5 * offset && pair[0] < 1.5 * offset, "{pair:?}");
            assert!(
                pair[1] < -0.5 * offset && pair[1] > -1.5 * offset,
                "{pair:?}"
            );
        }
        assert!(boxed.iter().any(|&d| d < 0.0) && boxed.iter().any(|&d| d > 0.0));
        for p in &points[2 * NEAR_PROBES..] {
            assert!(p.abs().max_element() <= 0.5 * 1.1 + 1e-6, "{p}");
        }
    }
}
