//! Slow, simple reference implementations (brute force over all triangles, in f64) used to check the
//! fast paths. O(n) per query; for tests and spot checks only.

// The far path of the distance uses the same f64 routine: it lives there, and is shown here.
use crate::Mesh;
pub use crate::distance::closest_on_triangle_f64;

/// Unsigned distance and index of the nearest triangle, by scanning all triangles in f64.
/// Returns `(f64::INFINITY, u32::MAX)` for a mesh without valid triangles.
pub fn brute_force_distance(mesh: &Mesh, p: glam::Vec3) -> (f64, u32) {
    let p = p.as_dvec3();
    let mut best = (f64::INFINITY, u32::MAX);
    for (i, t) in mesh.triangles.iter().enumerate() {
        let Some([a, b, c]) = mesh.corners(t) else {
            continue;
        };
        let (q, _) = closest_on_triangle_f64(p, a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
        let d = q.distance(p);
        if d < best.0 {
            best = (d, i as u32);
        }
    }
    best
}

/// Exact generalised winding number: the sum of every triangle's signed solid angle / 4π, in f64.
pub fn brute_force_winding_number(mesh: &Mesh, p: glam::Vec3) -> f64 {
    let p = p.as_dvec3();
    let mut sum = 0.0;
    for t in &mesh.triangles {
        let Some([a, b, c]) = mesh.corners(t) else {
            continue;
        };
        let (a, b, c) = (a.as_dvec3() - p, b.as_dvec3() - p, c.as_dvec3() - p);
        let (la, lb, lc) = (a.length(), b.length(), c.length());
        let det = a.dot(b.cross(c));
        let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
        sum += 2.0 * det.atan2(den);
    }
    sum / (4.0 * std::f64::consts::PI)
}

/// Inside/outside by ray parity: counts crossings of a ray from `p` along `dir`. Returns `None` when
/// the ray passes within a small tolerance of an edge or vertex (where parity is unreliable), so the
/// caller can try another direction. Meaningful only for watertight meshes.
pub fn ray_parity_inside(mesh: &Mesh, p: glam::Vec3, dir: glam::Vec3) -> Option<bool> {
    let o = p.as_dvec3();
    let d = dir.as_dvec3().normalize();
    let mut crossings = 0usize;
    for t in &mesh.triangles {
        let Some([a, b, c]) = mesh.corners(t) else {
            continue;
        };
        let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
        // Möller–Trumbore with a margin on the barycentrics.
        let e1 = b - a;
        let e2 = c - a;
        let h = d.cross(e2);
        let det = e1.dot(h);
        if det.abs() < 1e-14 {
            continue;
        }
        let inv = 1.0 / det;
        let s = o - a;
        let u = s.dot(h) * inv;
        let q = s.cross(e1);
        let v = d.dot(q) * inv;
        let tt = e2.dot(q) * inv;
        let eps = 1e-9;
        if u < -eps || v < -eps || u + v > 1.0 + eps || tt < -eps {
            continue;
        }
        if u < eps || v < eps || u + v > 1.0 - eps || tt < eps {
            return None;
        }
        crossings += 1;
    }
    Some(crossings % 2 == 1)
}
