//! Triangulation of an OBJ polygon (a face of more than three corners): a fan where it is
//! convex, as every reader does, and ear clipping where it is not. A fan of a concave polygon
//! covers area outside it and covers some of its inside twice: an L-shaped face or the floor of
//! a machined pocket, exported as one n-gon, would grow a flap across its notch.

use glam::{DVec2, DVec3};

/// Polygons with more corners than this are fan-triangulated whatever their shape: ear
/// clipping as done here costs up to the cube of the corner count.
const MAX_EAR_CLIPPED_CORNERS: usize = 256;

/// The ear clipping one file may ask for, in squared corner counts (each concave polygon of `n`
/// corners costs `n²` of it): about a second's work. Past it, concave polygons are fanned with
/// a warning, so that a file of many large concave faces cannot stall the loader.
const EAR_CLIP_BUDGET: u64 = 50_000_000;

/// How a polygon was triangulated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Triangulation {
    /// Convex (or without area): a fan from its first corner.
    Fan,
    /// Concave: ear clipping in its plane.
    EarClipped,
    /// Concave, but not clipped cleanly: at some step no corner left was an ear (the outline
    /// crosses itself) and one was cut without the check, or the polygon has more than
    /// [`MAX_EAR_CLIPPED_CORNERS`] corners or the file's [`EAR_CLIP_BUDGET`] ran out and it
    /// was fanned.
    Fallback,
}

/// One file's polygons as they are triangulated: the buffers, the counts and the budget.
pub(super) struct Polygons {
    corners: Vec<DVec3>,
    triangles: Vec<[usize; 3]>,
    concave: usize,
    not_clipped: usize,
    budget: u64,
}

impl Default for Polygons {
    fn default() -> Self {
        Polygons {
            corners: Vec::new(),
            triangles: Vec::new(),
            concave: 0,
            not_clipped: 0,
            budget: EAR_CLIP_BUDGET,
        }
    }
}

impl Polygons {
    /// The triangles of the polygon with these corners, as indices into them.
    pub(super) fn triangulate(&mut self, corners: impl Iterator<Item = DVec3>) -> &[[usize; 3]] {
        self.corners.clear();
        self.corners.extend(corners);
        self.triangles.clear();
        match triangulate(&self.corners, &mut self.triangles, &mut self.budget) {
            Triangulation::Fan => {}
            Triangulation::EarClipped => self.concave += 1,
            Triangulation::Fallback => self.not_clipped += 1,
        }
        &self.triangles
    }

    /// Counts the concave polygons in `report`, with a warning for those not ear-clipped.
    pub(super) fn report(&self, report: &mut crate::mesh::LoadReport) {
        report.concave_polygons = self.concave + self.not_clipped;
        if self.not_clipped > 0 {
            report.warnings.push(format!(
                "{} concave polygons triangulated without the ear check (their outline crosses \
                 itself, they have more than {MAX_EAR_CLIPPED_CORNERS} corners, or the file's \
                 ear-clipping budget ran out): their triangles may cover area outside them",
                self.not_clipped
            ));
        }
    }
}

/// Appends the `n − 2` triangles of the polygon with corners `corners` (in order) to `out`, as
/// indices into `corners`, and says how. Ear clipping is paid for from `budget` (`n²` a
/// polygon; start from [`EAR_CLIP_BUDGET`]).
fn triangulate(corners: &[DVec3], out: &mut Vec<[usize; 3]>, budget: &mut u64) -> Triangulation {
    let n = corners.len();
    let fan =
        |out: &mut Vec<[usize; 3]>| out.extend((1..n.saturating_sub(1)).map(|k| [0, k, k + 1]));
    let Some(plane) = Plane::of(corners) else {
        fan(out);
        return Triangulation::Fan;
    };
    let flat: Vec<DVec2> = corners.iter().map(|&p| plane.project(p)).collect();
    // Turns against the polygon's orientation, beyond rounding of its size, make it concave.
    let tolerance = 1e-12 * plane.extent * plane.extent;
    let concave =
        (0..n).any(|i| turn(flat[(i + n - 1) % n], flat[i], flat[(i + 1) % n]) < -tolerance);
    if !concave {
        fan(out);
        return Triangulation::Fan;
    }
    let cost = (n as u64).pow(2);
    if n > MAX_EAR_CLIPPED_CORNERS || *budget < cost {
        fan(out);
        return Triangulation::Fallback;
    }
    *budget -= cost;
    ear_clip(&flat, tolerance, out)
}

/// The polygon's plane: its Newell normal and two axes in it, `u × v = normal`, so that the
/// polygon turns counter-clockwise in `(u, v)`.
struct Plane {
    origin: DVec3,
    u: DVec3,
    v: DVec3,
    /// The largest distance of a corner from the first one: the scale of the tolerances.
    extent: f64,
}

impl Plane {
    /// `None` when the polygon has no area (every corner on one line or one point).
    fn of(corners: &[DVec3]) -> Option<Plane> {
        let origin = corners[0];
        // Newell's normal, about the first corner (smaller terms than about the origin).
        let mut normal = DVec3::ZERO;
        for (i, &a) in corners.iter().enumerate() {
            let b = corners[(i + 1) % corners.len()];
            normal += (a - origin).cross(b - origin);
        }
        let extent = corners
            .iter()
            .map(|&p| (p - origin).length())
            .fold(0.0, f64::max);
        let length = normal.length();
        // NaN corners (an index past the positions) have no plane either.
        if length.is_nan() || length <= 1e-12 * extent * extent {
            return None;
        }
        let normal = normal / length;
        let u = normal.any_orthonormal_vector();
        Some(Plane {
            origin,
            u,
            v: normal.cross(u),
            extent,
        })
    }

    fn project(&self, p: DVec3) -> DVec2 {
        let d = p - self.origin;
        DVec2::new(d.dot(self.u), d.dot(self.v))
    }
}

/// Twice the signed area of the triangle `a b c`: positive when it turns counter-clockwise.
fn turn(a: DVec2, b: DVec2, c: DVec2) -> f64 {
    (b - a).perp_dot(c - a)
}

/// Ear clipping of a counter-clockwise polygon: cuts a corner in line with its neighbours (or
/// repeating one), as a triangle without area that the clean-up drops, or else a convex
/// corner whose triangle holds no other remaining corner, until a triangle is left. Corners in
/// line go first: a zero-width spike (an edge walked out and back) is cut away whole, where an
/// ear beside it would have put a two-sided fin outside the polygon. Where no corner is either
/// (the outline crosses itself), the second one is cut without the check.
fn ear_clip(flat: &[DVec2], tolerance: f64, out: &mut Vec<[usize; 3]>) -> Triangulation {
    let mut left: Vec<usize> = (0..flat.len()).collect();
    let mut how = Triangulation::EarClipped;
    // Where the last cut was: the next ear is usually beside it.
    let mut from = 0;
    while left.len() > 3 {
        let m = left.len();
        let corner = |i: usize| {
            let (a, b, c) = (left[(i + m - 1) % m], left[i], left[(i + 1) % m]);
            (a, b, c, turn(flat[a], flat[b], flat[c]))
        };
        let order = || (0..m).map(|k| (from + k) % m);
        let in_line = order().find(|&i| corner(i).3.abs() <= tolerance);
        let ear = || {
            order().find(|&i| {
                let (a, b, c, t) = corner(i);
                let (pa, pb, pc) = (flat[a], flat[b], flat[c]);
                t > tolerance
                    && left.iter().all(|&k| {
                        let p = flat[k];
                        // A corner at one of the ear's own positions (a polygon bridged to a hole
                        // repeats two) does not block it.
                        [a, b, c].contains(&k)
                            || p == pa
                            || p == pb
                            || p == pc
                            || !inside_or_on(p, pa, pb, pc, tolerance)
                    })
            })
        };
        let i = in_line.or_else(ear).unwrap_or_else(|| {
            how = Triangulation::Fallback;
            1
        });
        let (a, b, c) = (left[(i + m - 1) % m], left[i], left[(i + 1) % m]);
        out.push([a, b, c]);
        left.remove(i);
        from = i.saturating_sub(1);
    }
    out.push([left[0], left[1], left[2]]);
    how
}

/// Whether `p` lies in the counter-clockwise triangle `a b c` or on its edges.
fn inside_or_on(p: DVec2, a: DVec2, b: DVec2, c: DVec2, tolerance: f64) -> bool {
    turn(a, b, p) >= -tolerance && turn(b, c, p) >= -tolerance && turn(c, a, p) >= -tolerance
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The area the triangles cover, each counted with its sign in the polygon's plane.
    fn signed_area(corners: &[DVec3], tris: &[[usize; 3]]) -> f64 {
        let plane = Plane::of(corners).unwrap();
        let f: Vec<DVec2> = corners.iter().map(|&p| plane.project(p)).collect();
        tris.iter()
            .map(|t| 0.5 * turn(f[t[0]], f[t[1]], f[t[2]]))
            .sum()
    }

    fn polygon_area(corners: &[DVec3]) -> f64 {
        let plane = Plane::of(corners).unwrap();
        let f: Vec<DVec2> = corners.iter().map(|&p| plane.project(p)).collect();
        (0..f.len())
            .map(|i| 0.5 * f[i].perp_dot(f[(i + 1) % f.len()]))
            .sum()
    }

    /// An L listed from the corner beside its notch: the fan's second triangle lies in the
    /// notch.
    fn l_shape() -> Vec<DVec3> {
        xy(&[
            [2.0, 1.0],
            [1.0, 1.0],
            [1.0, 2.0],
            [0.0, 2.0],
            [0.0, 0.0],
            [2.0, 0.0],
        ])
    }

    fn xy(points: &[[f64; 2]]) -> Vec<DVec3> {
        points.iter().map(|p| DVec3::new(p[0], p[1], 0.0)).collect()
    }

    #[test]
    fn convex_polygons_are_fans() {
        let square = xy(&[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
        let mut tris = Vec::new();
        assert_eq!(
            triangulate(&square, &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::Fan
        );
        assert_eq!(tris, [[0, 1, 2], [0, 2, 3]]);
        // Collinear corners on an edge are not concave.
        let mut tris = Vec::new();
        let with_midpoint = xy(&[[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
        assert_eq!(
            triangulate(&with_midpoint, &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::Fan
        );
        // No area: a fan of degenerate triangles, which the clean-up drops.
        let mut tris = Vec::new();
        let line = xy(&[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]);
        assert_eq!(
            triangulate(&line, &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::Fan
        );
        assert_eq!(tris.len(), 2);
    }

    /// An L, a notched star and a comb, in either orientation and tilted in 3D: every
    /// triangle turns the polygon's way and together they cover its area once (a fan from
    /// the first corner covers more: it crosses the notch).
    #[test]
    fn concave_polygons_are_ear_clipped() {
        let l_shape = l_shape();
        let star: Vec<[f64; 2]> = (0..10)
            .map(|i| {
                let a = i as f64 * std::f64::consts::PI / 5.0;
                let r = if i % 2 == 0 { 1.0 } else { 0.4 };
                [r * a.cos(), r * a.sin()]
            })
            .collect();
        // A bar with four teeth.
        let comb = [
            [0.0, 0.0],
            [7.0, 0.0],
            [7.0, 3.0],
            [6.0, 3.0],
            [6.0, 1.0],
            [5.0, 1.0],
            [5.0, 3.0],
            [4.0, 3.0],
            [4.0, 1.0],
            [3.0, 1.0],
            [3.0, 3.0],
            [2.0, 3.0],
            [2.0, 1.0],
            [1.0, 1.0],
            [1.0, 3.0],
            [0.0, 3.0],
        ];
        let tilt = glam::DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 0.9);
        for shape in [l_shape, xy(&star), xy(&comb)] {
            for reversed in [false, true] {
                let mut corners: Vec<DVec3> =
                    shape.iter().map(|&p| tilt * p + DVec3::ONE).collect();
                // The other way round from the same first corner (whose fan crosses the notch).
                if reversed {
                    corners[1..].reverse();
                }
                let mut tris = Vec::new();
                assert_eq!(
                    triangulate(&corners, &mut tris, &mut EAR_CLIP_BUDGET.clone()),
                    Triangulation::EarClipped
                );
                assert_eq!(tris.len(), corners.len() - 2);
                let plane = Plane::of(&corners).unwrap();
                let f: Vec<DVec2> = corners.iter().map(|&p| plane.project(p)).collect();
                // None turns the other way (corners in line give triangles without area).
                for t in &tris {
                    assert!(
                        turn(f[t[0]], f[t[1]], f[t[2]]) > -1e-9,
                        "{t:?} of {corners:?}"
                    );
                }
                let want = polygon_area(&corners);
                assert!((signed_area(&corners, &tris) - want).abs() < 1e-9 * want);
                let fan: Vec<[usize; 3]> = (1..corners.len() - 1).map(|k| [0, k, k + 1]).collect();
                let fan_cover: f64 = fan
                    .iter()
                    .map(|t| 0.5 * turn(f[t[0]], f[t[1]], f[t[2]]).abs())
                    .sum();
                assert!(
                    fan_cover > want * 1.01,
                    "the fan was right already: {fan_cover} vs {want}"
                );
            }
        }
    }

    #[test]
    fn polygons_too_large_to_clip_fall_back_to_a_fan() {
        let star: Vec<[f64; 2]> = (0..MAX_EAR_CLIPPED_CORNERS + 2)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / (MAX_EAR_CLIPPED_CORNERS + 2) as f64;
                let r = if i % 2 == 0 { 1.0 } else { 0.9 };
                [r * a.cos(), r * a.sin()]
            })
            .collect();
        let mut tris = Vec::new();
        assert_eq!(
            triangulate(&xy(&star), &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::Fallback
        );
        assert_eq!(tris.len(), star.len() - 2);
        // One corner fewer is clipped.
        let mut tris = Vec::new();
        let smaller = &star[..MAX_EAR_CLIPPED_CORNERS];
        assert_eq!(
            triangulate(&xy(smaller), &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::EarClipped
        );
    }

    /// Repeated and in-line corners inside a concave polygon are cut without a fallback.
    #[test]
    fn repeated_corners_are_clipped_away() {
        let l_shape = xy(&[
            [0.0, 0.0],
            [1.0, 0.0],
            [2.0, 0.0],
            [2.0, 0.0],
            [2.0, 1.0],
            [1.0, 1.0],
            [1.0, 2.0],
            [0.0, 2.0],
        ]);
        let mut tris = Vec::new();
        assert_eq!(
            triangulate(&l_shape, &mut tris, &mut EAR_CLIP_BUDGET.clone()),
            Triangulation::EarClipped
        );
        assert!((signed_area(&l_shape, &tris) - 3.0).abs() < 1e-12);
    }

    /// A polygon whose outline crosses itself still gives `n − 2` triangles of its corners,
    /// whichever way it is cut (no outline is right for it).
    #[test]
    fn self_crossing_polygons_give_their_triangles() {
        let bow = xy(&[[0.0, 0.0], [2.0, 2.0], [2.0, 0.0], [1.0, 1.5], [0.0, 2.0]]);
        let mut tris = Vec::new();
        triangulate(&bow, &mut tris, &mut EAR_CLIP_BUDGET.clone());
        assert_eq!(tris.len(), 3);
        assert!(tris.iter().flatten().all(|&k| k < bow.len()));
    }

    /// A zero-width spike on an edge (walked out and back) is cut away whole: no two-sided fin
    /// outside the polygon (an ear beside the spike covered it once each way).
    #[test]
    fn spikes_are_cut_away_whole() {
        let spiked = xy(&[
            [0.0, 0.0],
            [4.0, 0.0],
            [4.0, 4.0],
            [2.0, 4.0],
            [2.0, 6.0],
            [2.0, 4.0],
            [0.0, 4.0],
        ]);
        let mut tris = Vec::new();
        triangulate(&spiked, &mut tris, &mut EAR_CLIP_BUDGET.clone());
        let f: Vec<DVec2> = spiked.iter().map(|p| p.truncate()).collect();
        // Every triangle with area lies in the square.
        for t in &tris {
            if turn(f[t[0]], f[t[1]], f[t[2]]).abs() > 1e-12 {
                assert!(t.iter().all(|&k| f[k].y <= 4.0), "{t:?}");
            }
        }
        assert!((signed_area(&spiked, &tris) - 16.0).abs() < 1e-9);
    }

    /// Past the file's budget, concave polygons are fanned (and said to be).
    #[test]
    fn the_budget_bounds_the_clipping() {
        let l_shape = l_shape();
        let mut budget = 36 + 35;
        let mut tris = Vec::new();
        assert_eq!(
            triangulate(&l_shape, &mut tris, &mut budget),
            Triangulation::EarClipped
        );
        assert_eq!(budget, 35);
        assert_eq!(
            triangulate(&l_shape, &mut tris, &mut budget),
            Triangulation::Fallback
        );
        assert_eq!((budget, tris.len()), (35, 8));
    }
}
