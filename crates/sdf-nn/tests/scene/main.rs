//! Scenes (`sdf_nn::serve::scene`) on the CPU: every operator against its closed form,
//! gradients against finite differences, rays against analytic intersections, closest points,
//! levels, trained models placed twice against the analytic sphere they hold, and every bad
//! scene (built in code or read from TOML) refused with its typed error. Analytic scenes here;
//! trained models in `models.rs`, bad trees and scene files in `files.rs`, the GPU's queries
//! against this CPU reference in `gpu.rs` (one shared device).

use std::f32::consts::FRAC_PI_2;

use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::serve::scene::{
    Primitive, ProjectOptions, Ray, RayHit, Scene, SceneNode, SceneQueryError, TraceOptions,
    Transform,
};

mod files;
mod gpu;
mod models;
mod steps;
#[path = "../support/mod.rs"]
mod support;

pub(crate) fn sphere_at(center: Vec3, radius: f32) -> SceneNode {
    SceneNode::primitive(
        Primitive::Sphere { radius },
        Transform::from_translation(center),
    )
}

/// The hits that two traces of the same rays share, as (ray, `want`'s hit, `got`'s hit);
/// panics, naming `what` and the ray, where one of them hits and the other does not.
pub(crate) fn shared_hits<'a>(
    want: &'a [Option<RayHit>],
    got: &'a [Option<RayHit>],
    what: &str,
) -> Vec<(usize, &'a RayHit, &'a RayHit)> {
    assert_eq!(want.len(), got.len(), "{what}: rays traced");
    want.iter()
        .zip(got)
        .enumerate()
        .filter_map(|(i, pair)| match pair {
            (Some(w), Some(g)) => Some((i, w, g)),
            (None, None) => None,
            (w, g) => panic!("{what}, ray {i}: {w:?} against {g:?}"),
        })
        .collect()
}

/// The hits that two traces share ([`shared_hits`]), each at `want`'s `t` within
/// `10⁻³ (1 + t)`.
pub(crate) fn hits_at_the_same_t<'a>(
    want: &'a [Option<RayHit>],
    got: &'a [Option<RayHit>],
    what: &str,
) -> Vec<(usize, &'a RayHit, &'a RayHit)> {
    let shared = shared_hits(want, got, what);
    for &(i, w, g) in &shared {
        assert!(
            (w.t - g.t).abs() < 1e-3 * (1.0 + w.t),
            "{what}, ray {i}: t {} against {}",
            g.t,
            w.t
        );
    }
    shared
}

/// The GPU's hits against the CPU's ([`hits_at_the_same_t`]), at least 49 in 50 after as many
/// steps (f32 and f64 may decide a rare ball check apart). How many hits they share.
pub(crate) fn hits_in_the_cpus_steps(
    cpu: &[Option<RayHit>],
    gpu: &[Option<RayHit>],
    what: &str,
) -> usize {
    let shared = hits_at_the_same_t(cpu, gpu, what);
    let same_steps = shared.iter().filter(|(_, c, g)| c.steps == g.steps).count();
    assert!(
        same_steps * 50 >= shared.len() * 49,
        "{what}: {same_steps} of {} hits in the CPU's steps",
        shared.len()
    );
    shared.len()
}

pub(crate) fn random_points(n: usize, half: f32, seed: u64) -> Vec<Vec3> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-half..half),
                rng.random_range(-half..half),
                rng.random_range(-half..half),
            )
        })
        .collect()
}

/// IQ's polynomial smooth minimum in its other, "mix" form: the scene code uses
/// `min − h²k/4`; the two are equal, so this checks the algebra too.
fn smin(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

pub(crate) fn assert_close(got: f32, want: f64, tol: f64, what: &str) {
    assert!(
        (got as f64 - want).abs() <= tol,
        "{what}: {got} vs {want} (tolerance {tol})"
    );
}

/// Placed primitives: a transform moves, turns and scales the shape and scales its distance.
#[test]
fn transforms_place_primitives() {
    let turn = Quat::from_rotation_z(FRAC_PI_2);
    // A box (1, 2, 3) turned a quarter about z is a box (2, 1, 3), then doubled: (4, 2, 6).
    let cube = SceneNode::primitive(
        Primitive::Box {
            half_extents: Vec3::new(1.0, 2.0, 3.0),
        },
        Transform::new(Vec3::new(10.0, 0.0, 0.0), turn, 2.0),
    );
    let scene = Scene::new(cube).unwrap();
    for (p, want) in [
        (Vec3::new(10.0 + 5.0, 0.0, 0.0), 1.0),
        (Vec3::new(10.0, 3.0, 0.0), 1.0),
        (Vec3::new(10.0, 0.0, -7.5), 1.5),
        (Vec3::new(10.0, 0.0, 0.0), -2.0),
        (Vec3::new(15.0, 3.0, 7.0), 3f64.sqrt()),
    ] {
        assert_close(scene.distance(p, 0.0), want, 1e-5, &format!("box at {p}"));
    }
    // Nested transform nodes compose: scale 2 then 3 about different centres.
    let nested = sphere_at(Vec3::X, 1.0)
        .transformed(Transform::new(Vec3::Y, Quat::IDENTITY, 2.0))
        .transformed(Transform::new(Vec3::Z, turn, 3.0));
    let scene = Scene::new(nested).unwrap();
    // Centre: z + R(3·(y + 2·x)) = (0,0,1) + 3·(R(0,1,0) + 2·R(1,0,0)) = (-3, 6, 1); radius 6.
    let centre = Vec3::new(-3.0, 6.0, 1.0);
    for p in random_points(200, 12.0, 1) {
        let want = (p - centre).length() as f64 - 6.0;
        assert_close(scene.distance(p, 0.0), want, 1e-5, "nested sphere");
    }
}

/// Every CSG and smooth operator on two or three spheres against its closed form.
#[test]
fn operators_match_closed_forms() {
    let (ca, cb, cc) = (
        Vec3::new(-0.5, 0.0, 0.0),
        Vec3::new(0.6, 0.2, 0.0),
        Vec3::new(0.0, 0.8, 0.3),
    );
    let (ra, rb, rc) = (1.0f32, 0.8, 0.5);
    let a = || sphere_at(ca, ra);
    let b = || sphere_at(cb, rb);
    let c = || sphere_at(cc, rc);
    let k = 0.4f32;
    type ClosedForm = Box<dyn Fn(f64, f64, f64) -> f64>;
    let cases: Vec<(&str, SceneNode, ClosedForm)> = vec![
        (
            "union",
            SceneNode::Union(vec![a(), b(), c()]),
            Box::new(|x, y, z| x.min(y).min(z)),
        ),
        (
            "intersection",
            SceneNode::Intersection(vec![a(), b()]),
            Box::new(|x, y, _| x.max(y)),
        ),
        (
            "difference",
            SceneNode::Difference(vec![a(), b(), c()]),
            Box::new(|x, y, z| x.max(-y).max(-z)),
        ),
        (
            "smooth_union",
            SceneNode::SmoothUnion {
                k,
                children: vec![a(), b(), c()],
            },
            Box::new(move |x, y, z| smin(smin(x, y, k as f64), z, k as f64)),
        ),
        (
            "smooth_intersection",
            SceneNode::SmoothIntersection {
                k,
                children: vec![a(), b()],
            },
            Box::new(move |x, y, _| -smin(-x, -y, k as f64)),
        ),
        (
            "smooth_difference",
            SceneNode::SmoothDifference {
                k,
                children: vec![a(), b()],
            },
            Box::new(move |x, y, _| -smin(-x, y, k as f64)),
        ),
        (
            "offset",
            SceneNode::Offset {
                r: 0.25,
                child: Box::new(a()),
            },
            Box::new(|x, _, _| x - 0.25),
        ),
        (
            "shell",
            SceneNode::Shell {
                t: 0.1,
                child: Box::new(b()),
            },
            Box::new(|_, y, _| y.abs() - 0.1),
        ),
        // Parameters under a transform scale with it: k, r, t in the subtree's units.
        (
            "scaled offset",
            SceneNode::Offset {
                r: 0.25,
                child: Box::new(a()),
            }
            .transformed(Transform::new(Vec3::ZERO, Quat::IDENTITY, 2.0)),
            Box::new(|_, _, _| f64::NAN),
        ),
    ];
    let points = random_points(400, 2.5, 2);
    for (name, node, want) in cases {
        let scene = Scene::new(node).unwrap();
        let got = scene.distances(&points, 0.0);
        for (p, d) in points.iter().zip(got) {
            let da = (*p - ca).length() as f64 - ra as f64;
            let db = (*p - cb).length() as f64 - rb as f64;
            let dc = (*p - cc).length() as f64 - rc as f64;
            let want = if name == "scaled offset" {
                // Sphere of radius 2 about 2·ca, grown by 0.5.
                (*p - 2.0 * ca).length() as f64 - 2.0 - 0.5
            } else {
                want(da, db, dc)
            };
            assert_close(d, want, 1e-5, &format!("{name} at {p}"));
        }
    }
}

/// A scene using every operator and primitive: the analytic gradient agrees with central
/// differences of the scene's own distance.
fn everything() -> SceneNode {
    let turn = Quat::from_axis_angle(Vec3::new(1.0, 1.0, 0.0).normalize(), 0.7);
    let at = |x: f32, y: f32, z: f32| Transform::new(Vec3::new(x, y, z), turn, 0.9);
    let prim = |p, t| SceneNode::primitive(p, t);
    SceneNode::SmoothUnion {
        k: 0.3,
        children: vec![
            SceneNode::Difference(vec![
                prim(
                    Primitive::RoundBox {
                        half_extents: Vec3::new(0.8, 0.5, 0.6),
                        radius: 0.1,
                    },
                    at(-1.0, 0.0, 0.0),
                ),
                prim(
                    Primitive::Cylinder {
                        radius: 0.2,
                        half_height: 1.0,
                    },
                    at(-1.0, 0.1, 0.0),
                ),
            ]),
            SceneNode::SmoothIntersection {
                k: 0.2,
                children: vec![
                    prim(
                        Primitive::Box {
                            half_extents: Vec3::splat(0.5),
                        },
                        at(1.0, 0.0, 0.0),
                    ),
                    prim(Primitive::Sphere { radius: 0.65 }, at(1.0, 0.1, 0.0)),
                ],
            },
            SceneNode::Shell {
                t: 0.05,
                child: Box::new(prim(
                    Primitive::Torus {
                        major: 0.7,
                        minor: 0.15,
                    },
                    at(0.0, 1.0, 0.0),
                )),
            },
            SceneNode::SmoothDifference {
                k: 0.1,
                children: vec![
                    prim(
                        Primitive::Capsule {
                            a: Vec3::new(-0.5, 0.0, 0.0),
                            b: Vec3::new(0.5, 0.0, 0.0),
                            radius: 0.2,
                        },
                        at(0.0, -1.0, 0.0),
                    ),
                    SceneNode::Offset {
                        r: 0.05,
                        child: Box::new(sphere_at(Vec3::new(0.3, -1.0, 0.0), 0.15)),
                    },
                ],
            },
            SceneNode::Intersection(vec![
                prim(
                    Primitive::Plane {
                        normal: Vec3::new(0.0, 1.0, 0.2),
                        offset: -1.5,
                    },
                    Transform::IDENTITY,
                ),
                sphere_at(Vec3::new(0.0, -1.5, 1.0), 0.6),
            ])
            .transformed(Transform::new(Vec3::new(0.1, 0.0, 0.0), turn, 1.3)),
        ],
    }
}

#[test]
fn gradients_match_finite_differences() {
    let scene = Scene::new(everything()).unwrap();
    let points = random_points(2000, 2.0, 3);
    let samples = scene.distances_and_gradients(&points, 0.0);
    let h = 1e-3f32;
    let mut checked = 0;
    for (p, s) in points.iter().zip(&samples) {
        let fd = |axis: Vec3| {
            let d = scene.distances(&[*p + axis * h, *p - axis * h], 0.0);
            (d[0] - d[1]) as f64 / (2.0 * h as f64)
        };
        let fd = glam::DVec3::new(fd(Vec3::X), fd(Vec3::Y), fd(Vec3::Z));
        let err = (fd - s.gradient.as_dvec3()).length();
        // A difference across a kink (a min switching children, a shell's sign) is not a
        // derivative; those few points are the only ones allowed to disagree.
        if err > 2e-3 {
            continue;
        }
        checked += 1;
        assert!(
            s.gradient.length() <= 1.0 + 1e-5,
            "1-Lipschitz: {}",
            s.gradient
        );
    }
    assert!(
        checked >= 1990,
        "only {checked} of 2000 gradients match their differences"
    );
    // The value with the gradient is the value without it.
    let plain = scene.distances(&points, 0.0);
    for (a, s) in plain.iter().zip(&samples) {
        assert_eq!(*a, s.distance);
    }
}

/// Rays against analytic sphere and plane intersections, from outside and inside, hits and
/// misses, at a level.
#[test]
fn rays_hit_spheres_and_planes_where_the_algebra_says() {
    let centre = Vec3::new(1.0, 2.0, -1.0);
    let radius = 1.5f32;
    let floor = SceneNode::primitive(
        Primitive::Plane {
            normal: Vec3::Y,
            offset: -3.0,
        },
        Transform::IDENTITY,
    );
    let scene = Scene::new(SceneNode::Union(vec![sphere_at(centre, radius), floor])).unwrap();
    let options = TraceOptions {
        tolerance: 1e-5,
        ..TraceOptions::default()
    };
    let mut rng = Pcg64::seed_from_u64(4);
    let mut rays = Vec::new();
    for _ in 0..200 {
        let origin = Vec3::new(
            rng.random_range(-6.0..6.0),
            rng.random_range(0.0..6.0),
            rng.random_range(-6.0..6.0),
        );
        // Unnormalised directions: `t` is still a distance.
        let random = Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..0.2),
            rng.random_range(-1.0..1.0),
        );
        // Half the rays aim near the sphere (some graze past it), half go anywhere.
        let direction = if rays.len() % 2 == 0 {
            (centre + random * radius * 1.2 - origin) * 3.0
        } else {
            random * 3.0
        };
        rays.push(Ray {
            origin,
            direction,
            max_distance: 50.0,
        });
    }
    let hits = scene.trace_rays(&rays, &options).unwrap();
    let mut sphere_hits = 0;
    for (ray, hit) in rays.iter().zip(hits) {
        let o = ray.origin.as_dvec3();
        let d = ray.direction.as_dvec3().normalize();
        // Sphere: |o + t d − c|² = r²; the nearest root ≥ 0 (the far one from inside).
        let oc = o - centre.as_dvec3();
        let (bq, cq) = (oc.dot(d), oc.length_squared() - (radius as f64).powi(2));
        let disc = bq * bq - cq;
        let t_sphere = (disc >= 0.0)
            .then(|| [-bq - disc.sqrt(), -bq + disc.sqrt()])
            .and_then(|r| r.into_iter().find(|&t| t >= 0.0));
        let t_plane = (d.y < 0.0)
            .then(|| (o.y + 3.0) / -d.y)
            .filter(|&t| t >= 0.0);
        let want = [t_sphere, t_plane]
            .into_iter()
            .flatten()
            .fold(f64::INFINITY, f64::min);
        // A ray that passes within 1e-3 of the sphere without touching it is a grazing ray:
        // sphere tracing crawls past it and may run out of steps, or stop within tolerance.
        let approach = (oc + d * (-oc.dot(d)).max(0.0)).length();
        if (approach - radius as f64).abs() < 1e-3 {
            continue;
        }
        let Some(hit) = hit else {
            assert!(want > 50.0, "ray {ray:?} missed, expected a hit at {want}");
            continue;
        };
        assert!(
            (hit.t as f64 - want).abs() < 1e-3,
            "ray {ray:?}: t {} vs {want}",
            hit.t
        );
        let normal_want = if t_sphere == Some(want) {
            sphere_hits += 1;
            assert_eq!(hit.leaf, 0);
            ((o + d * want) - centre.as_dvec3()).normalize()
        } else {
            assert_eq!(hit.leaf, 1);
            glam::DVec3::Y
        };
        assert!(
            (hit.normal.as_dvec3() - normal_want).length() < 1e-3,
            "{ray:?}"
        );
        assert!((hit.point.as_dvec3() - (o + d * hit.t as f64)).length() < 1e-4);
    }
    assert!(sphere_hits > 60, "only {sphere_hits} rays hit the sphere");

    // From inside the sphere the ray finds where it leaves; at level 0.5 the sphere is 0.5
    // larger; a ray stopped short misses.
    let inside = Ray {
        origin: centre,
        direction: Vec3::X,
        max_distance: 10.0,
    };
    let hit = scene.trace_ray(&inside, &options).unwrap().unwrap();
    assert_close(hit.t, radius as f64, 1e-4, "exit");
    let level = TraceOptions {
        level: 0.5,
        ..options
    };
    let from_left = Ray {
        origin: centre - Vec3::X * 10.0,
        direction: Vec3::X,
        max_distance: 20.0,
    };
    let hit = scene.trace_ray(&from_left, &level).unwrap().unwrap();
    assert_close(hit.t, 10.0 - 2.0, 1e-4, "level 0.5");
    let short = Ray {
        max_distance: 7.5,
        ..from_left
    };
    assert_eq!(scene.trace_ray(&short, &level).unwrap(), None);
    let away = Ray {
        origin: centre + Vec3::Y * 5.0,
        direction: Vec3::Y,
        max_distance: f32::INFINITY,
    };
    assert_eq!(scene.trace_ray(&away, &options).unwrap(), None);
}

#[test]
fn bad_rays_and_options_are_errors() {
    let scene = Scene::new(sphere_at(Vec3::ZERO, 1.0)).unwrap();
    let good = Ray {
        origin: Vec3::new(0.0, 0.0, -5.0),
        direction: Vec3::Z,
        max_distance: 10.0,
    };
    let o = TraceOptions::default();
    let bad_ray = |ray: Ray| scene.trace_rays(&[good, ray], &o).unwrap_err();
    assert!(matches!(
        bad_ray(Ray {
            direction: Vec3::ZERO,
            ..good
        }),
        SceneQueryError::Direction { index: 1, .. }
    ));
    assert!(matches!(
        bad_ray(Ray {
            direction: Vec3::new(f32::NAN, 0.0, 1.0),
            ..good
        }),
        SceneQueryError::Direction { index: 1, .. }
    ));
    assert!(matches!(
        bad_ray(Ray {
            direction: Vec3::new(f32::INFINITY, 0.0, 0.0),
            ..good
        }),
        SceneQueryError::Direction { index: 1, .. }
    ));
    assert!(matches!(
        bad_ray(Ray {
            origin: Vec3::splat(f32::NAN),
            ..good
        }),
        SceneQueryError::Point { index: 1, .. }
    ));
    assert!(matches!(
        bad_ray(Ray {
            max_distance: -1.0,
            ..good
        }),
        SceneQueryError::MaxDistance { index: 1, .. }
    ));
    assert!(matches!(
        scene.trace_ray(
            &good,
            &TraceOptions {
                level: f32::NAN,
                ..o
            }
        ),
        Err(SceneQueryError::Level(_))
    ));
    assert!(matches!(
        scene.trace_ray(
            &good,
            &TraceOptions {
                tolerance: 0.0,
                ..o
            }
        ),
        Err(SceneQueryError::Tolerance(_))
    ));
    for over_relaxation in [f32::NAN, 0.5, 2.0, f32::INFINITY] {
        assert!(matches!(
            scene.trace_ray(
                &good,
                &TraceOptions {
                    over_relaxation,
                    ..o
                }
            ),
            Err(SceneQueryError::OverRelaxation(_))
        ));
    }
    let p = ProjectOptions::default();
    assert!(matches!(
        scene.closest_points(&[Vec3::ONE, Vec3::new(0.0, f32::INFINITY, 0.0)], &p),
        Err(SceneQueryError::Point { index: 1, .. })
    ));
    assert!(matches!(
        scene.closest_point(
            Vec3::ONE,
            &ProjectOptions {
                level: f32::INFINITY,
                ..p
            }
        ),
        Err(SceneQueryError::Level(_))
    ));
    // Distances of a NaN point are NaN, not an error and not a number.
    assert!(scene.distance(Vec3::splat(f32::NAN), 0.0).is_nan());
}

/// `for_scene` options scale the default tolerances by the scene's half-side: the same
/// relative precision for a 2 mm part as for a unit one (the defaults stay absolute).
#[test]
fn tolerances_for_a_scene_are_in_proportion() {
    for radius in [1e-3_f32, 1.0, 1e4] {
        let scene = Scene::new(sphere_at(Vec3::new(radius, 0.0, 0.0), radius)).unwrap();
        let (trace, project) = (
            TraceOptions::for_scene(&scene),
            ProjectOptions::for_scene(&scene),
        );
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b;
        assert!(close(trace.tolerance, 1e-4 * radius), "{trace:?}");
        assert!(close(project.tolerance, 1e-5 * radius), "{project:?}");
        assert_eq!(
            (trace.max_steps, project.max_iterations),
            (
                TraceOptions::default().max_steps,
                ProjectOptions::default().max_iterations
            )
        );
    }
}

/// Closest points: on a sphere the exact closest point in one step; on a scene of every operator
/// a point on the surface (residual below the tolerance); at a level, on the level set.
#[test]
fn closest_points_land_on_the_surface() {
    let centre = Vec3::new(0.5, -1.0, 2.0);
    let scene = Scene::new(sphere_at(centre, 2.0)).unwrap();
    let options = ProjectOptions::default();
    let points = random_points(300, 6.0, 5);
    for (p, c) in points
        .iter()
        .zip(scene.closest_points(&points, &options).unwrap())
    {
        let want = centre + (*p - centre).normalize() * 2.0;
        assert!(c.converged && c.residual < options.tolerance, "{c:?}");
        assert!(c.iterations <= 2, "an exact distance needs one step: {c:?}");
        assert!(
            (c.point - want).length() < 1e-5,
            "{p}: {} vs {want}",
            c.point
        );
    }
    let level = ProjectOptions {
        level: 0.5,
        ..options
    };
    let c = scene.closest_point(centre + Vec3::Z * 7.0, &level).unwrap();
    assert!(
        (c.point - (centre + Vec3::Z * 2.5)).length() < 1e-5,
        "{c:?}"
    );

    let scene = Scene::new(everything()).unwrap();
    let points = random_points(300, 2.0, 6);
    let projected = scene.closest_points(&points, &options).unwrap();
    let converged: Vec<_> = projected.iter().filter(|c| c.converged).collect();
    assert!(
        converged.len() >= 290,
        "{} of 300 converged",
        converged.len()
    );
    for c in converged {
        assert!(c.residual < options.tolerance);
        // The residual is the scene's value there, measured independently.
        assert!(
            scene.distance(c.point, 0.0).abs() < options.tolerance + 1e-6,
            "{c:?}"
        );
    }
}

/// The level c shifts every query by c; the leaf reported is the one that decides the value.
#[test]
fn levels_and_leaves() {
    let centres = [
        Vec3::new(-3.0, 0.0, 0.0),
        Vec3::ZERO,
        Vec3::new(3.0, 0.0, 0.0),
    ];
    let union = SceneNode::Union(centres.iter().map(|&c| sphere_at(c, 1.0)).collect());
    let scene = Scene::new(union).unwrap();
    for (i, c) in centres.iter().enumerate() {
        let p = *c + Vec3::new(0.2, 1.5, 0.0);
        let s = scene.distance_and_gradient(p, 0.25);
        assert_eq!(s.leaf, i);
        assert_close(
            s.distance,
            (p - *c).length() as f64 - 1.0 - 0.25,
            1e-6,
            "level",
        );
        assert_close(
            scene.distance(p, -2.0),
            (p - *c).length() as f64 + 1.0,
            1e-6,
            "level",
        );
    }
    assert_eq!(scene.leaf_path(2), Some("root.children[2]"));
    // A difference's subtracted child decides inside the hole.
    let hole = SceneNode::Difference(vec![
        sphere_at(Vec3::ZERO, 2.0),
        sphere_at(Vec3::X * 2.0, 1.0),
    ]);
    let scene = Scene::new(hole).unwrap();
    assert_eq!(
        scene
            .distance_and_gradient(Vec3::new(1.5, 0.0, 0.0), 0.0)
            .leaf,
        1
    );
    assert_eq!(
        scene
            .distance_and_gradient(Vec3::new(-1.5, 0.0, 0.0), 0.0)
            .leaf,
        0
    );
}
