//! Slow, simple reference implementations (brute force over all triangles, in f64) used to check the
//! fast paths. O(n) per query; for tests and spot checks only.

use glam::DVec3;

use crate::Mesh;

/// Closest point on triangle (a, b, c) to p in f64 (Ericson), with barycentric weights.
pub fn closest_on_triangle_f64(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (DVec3, DVec3) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, DVec3::X);
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, DVec3::Y);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, DVec3::new(1.0 - v, v, 0.0));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, DVec3::Z);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, DVec3::new(1.0 - w, 0.0, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, DVec3::new(0.0, 1.0 - w, w));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, DVec3::new(1.0 - v - w, v, w))
}

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
