//! Scenes (`sdf_nn::serve::scene`) on the CPU: every operator against its closed form,
//! gradients against finite differences, rays against analytic intersections, closest points,
//! levels, trained models placed twice against the analytic sphere they hold, and every bad
//! scene (built in code or read from TOML) refused with its typed error. No GPU.

use std::f32::consts::FRAC_PI_2;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::serve::scene::{
    MAX_DEPTH, MAX_LEAVES, MAX_MODELS, Primitive, ProjectOptions, Ray, Scene, SceneError,
    SceneFileError, SceneNode, SceneQueryError, TraceOptions, Transform,
};
use sdf_nn::{NeuralSdf, Nglod, Normalization};

fn sphere_at(center: Vec3, radius: f32) -> SceneNode {
    SceneNode::primitive(
        Primitive::Sphere { radius },
        Transform::from_translation(center),
    )
}

fn random_points(n: usize, half: f32, seed: u64) -> Vec<Vec3> {
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

fn assert_close(got: f32, want: f64, tol: f64, what: &str) {
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

/// Sphere radius of the test models, in their normalised cube.
const MODEL_RADIUS: f32 = 0.6;

/// Mesh coordinates that are not the normalised ones: the model's sphere has its centre at
/// `center` and radius `MODEL_RADIUS / scale` = 2.4 mesh units.
fn normalization() -> Normalization {
    Normalization {
        center: Vec3::new(1.0, -2.0, 0.5),
        scale: 0.25,
    }
}

/// An NGLOD model holding (up to trilinear interpolation and f16 storage) a sphere's SDF times
/// `slope`: no training.
fn sphere_model(slope: f32) -> NeuralSdf {
    let model = Nglod::from_sdf(32, move |p| slope * (p.length() - MODEL_RADIUS)).unwrap();
    NeuralSdf::from_model_file(model.to_model_file(normalization(), serde_json::Value::Null))
        .unwrap()
}

/// A trained-model sphere placed twice (one weight copy), once under a transform node: the
/// scene's CPU distances, normals, rays and closest points match the two analytic spheres
/// within the model's fitting error.
#[test]
fn a_model_placed_twice_is_two_spheres() {
    let model = Arc::new(sphere_model(1.0));
    let n = normalization();
    let mesh_radius = MODEL_RADIUS / n.scale;
    let place_a = Transform::new(Vec3::new(-6.0, 0.0, 0.0), Quat::from_rotation_y(0.5), 0.5);
    let place_b = Transform::new(
        Vec3::new(5.0, 1.0, 0.0),
        Quat::from_rotation_x(FRAC_PI_2),
        1.5,
    );
    let scene = Scene::new(SceneNode::Union(vec![
        SceneNode::model(model.clone(), place_a),
        SceneNode::model(model.clone(), Transform::IDENTITY).transformed(place_b),
    ]))
    .unwrap();
    assert_eq!(scene.models().len(), 1, "one copy of the weights");
    assert_eq!(Arc::strong_count(&model), 2, "the test's and the scene's");
    // World spheres: centre t + R(s·c), radius s·2.4.
    let spheres = [place_a, place_b].map(|t| (t.apply(n.center), t.scale * mesh_radius));
    // The fitting error: trilinear interpolation and f16 features, ~4e-3 normalised units,
    // i.e. 0.016 mesh units, times each placement's scale.
    let tol = |leaf: usize| 0.02 * [place_a, place_b][leaf].scale as f64;
    let mut rng = Pcg64::seed_from_u64(8);
    let mut points = Vec::new();
    for (c, r) in spheres {
        for _ in 0..300 {
            let dir = Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            // Inside the model's box (half size 4 mesh units = 1.67 radii).
            points.push(c + dir * r * rng.random_range(0.3..1.5));
        }
    }
    let samples = scene.distances_and_gradients(&points, 0.0);
    for (p, s) in points.iter().zip(&samples) {
        let (d, leaf) = spheres
            .iter()
            .enumerate()
            .map(|(i, (c, r))| ((*p - *c).length() as f64 - *r as f64, i))
            .fold((f64::INFINITY, 0), |a, b| if b.0 < a.0 { b } else { a });
        assert_eq!(s.leaf, leaf, "{p}");
        assert_close(
            s.distance,
            d,
            tol(leaf),
            &format!("model sphere {leaf} at {p}"),
        );
        // Interpolating a cone tilts its gradient by up to ~h/ρ: check near the surface only.
        let from_centre = *p - spheres[leaf].0;
        if from_centre.length() > 0.8 * spheres[leaf].1 {
            let normal = from_centre.normalize();
            assert!(
                (s.gradient - normal).length() < 0.1,
                "{p}: {} vs {normal}",
                s.gradient
            );
        }
    }

    // Rays from far away at each sphere's centre hit at the analytic distance.
    let options = TraceOptions {
        tolerance: 1e-4,
        ..TraceOptions::default()
    };
    for (i, (c, r)) in spheres.iter().enumerate() {
        for dir in [Vec3::Z, Vec3::new(0.3, -1.0, 0.2).normalize()] {
            let ray = Ray {
                origin: *c - dir * 20.0,
                direction: dir,
                max_distance: 100.0,
            };
            let hit = scene.trace_ray(&ray, &options).unwrap().expect("a hit");
            assert_eq!(hit.leaf, i);
            assert_close(
                hit.t,
                20.0 - *r as f64,
                tol(i) * 2.0,
                &format!("ray at sphere {i}"),
            );
            assert!((hit.normal + dir).length() < 0.1, "{}", hit.normal);
        }
        // Closest points land on the sphere's surface.
        let from = *c + Vec3::new(0.4, 0.9, -0.2) * *r;
        let project = ProjectOptions {
            tolerance: 1e-4,
            ..ProjectOptions::default()
        };
        let cp = scene.closest_point(from, &project).unwrap();
        assert!(cp.converged && cp.residual < 1e-4, "{cp:?}");
        let want = *c + (from - *c).normalize() * *r;
        assert!(
            (cp.point - want).length() < 3.0 * tol(i) as f32,
            "{cp:?} vs {want}"
        );
    }
}

/// The Lipschitz estimate: about 1 (times the safety factor and the box rule's tangential
/// term) for a distance, three times that for a field three times as steep; rays through the
/// steep field stay exact because they step by it.
#[test]
fn lipschitz_estimates_follow_the_slope() {
    use sdf_nn::serve::scene::lipschitz::SAFETY;
    let flat = Arc::new(sphere_model(1.0));
    let steep = Arc::new(sphere_model(3.0));
    let mut scene = Scene::new(SceneNode::Union(vec![
        SceneNode::model(flat, Transform::IDENTITY),
        SceneNode::model(steep, Transform::from_translation(Vec3::X * 20.0)),
    ]))
    .unwrap();
    let (l_flat, l_steep) = (
        scene.model_lipschitz(0).unwrap(),
        scene.model_lipschitz(1).unwrap(),
    );
    // Trilinear interpolation of |x| has |∇| up to √3 in the cells at the centre.
    assert!((SAFETY..1.9 * SAFETY).contains(&l_flat), "{l_flat}");
    assert!(
        (2.9..3.1).contains(&(l_steep / l_flat)),
        "{l_steep} vs {l_flat}"
    );
    assert_eq!(scene.lipschitz(), l_steep);
    assert_eq!(scene.model_lipschitz(2), None);
    // The steep field's zero set is still the sphere: the ray stops on it, not past it.
    let n = normalization();
    let c = Vec3::X * 20.0 + n.center;
    let ray = Ray {
        origin: c - Vec3::Y * 10.0,
        direction: Vec3::Y,
        max_distance: 100.0,
    };
    let hit = scene
        .trace_ray(&ray, &TraceOptions::default())
        .unwrap()
        .unwrap();
    assert_close(
        hit.t,
        10.0 - (MODEL_RADIUS / n.scale) as f64,
        0.02,
        "steep ray",
    );
    scene.set_model_lipschitz(1, 4.0).unwrap();
    assert_eq!(scene.lipschitz(), 4.0);
    assert!(matches!(
        scene.set_model_lipschitz(1, 0.0),
        Err(SceneError::Lipschitz { .. })
    ));
    assert!(matches!(
        scene.set_model_lipschitz(5, 2.0),
        Err(SceneError::Lipschitz { .. })
    ));
}

/// Every bad tree built in code is refused with its typed error, naming the node.
#[test]
fn bad_trees_are_typed_errors() {
    let s = || sphere_at(Vec3::ZERO, 1.0);
    let err = |node: SceneNode| Scene::new(node).unwrap_err();
    let mut deep = s();
    for _ in 0..MAX_DEPTH {
        deep = SceneNode::Offset {
            r: 0.0,
            child: Box::new(deep),
        };
    }
    match err(deep) {
        SceneError::TooDeep { node, limit } => {
            assert_eq!(limit, MAX_DEPTH);
            assert_eq!(node.matches("children[0]").count(), MAX_DEPTH, "{node}");
        }
        e => panic!("{e:?}"),
    }
    let mut deepest = s();
    for _ in 1..MAX_DEPTH {
        deepest = SceneNode::Offset {
            r: 0.0,
            child: Box::new(deepest),
        };
    }
    assert_eq!(Scene::new(deepest).unwrap().depth(), MAX_DEPTH);
    assert!(matches!(
        err(SceneNode::Union((0..=MAX_LEAVES).map(|_| s()).collect())),
        SceneError::TooManyLeaves {
            limit: MAX_LEAVES,
            ..
        }
    ));
    let models: Vec<SceneNode> = (0..=MAX_MODELS)
        .map(|_| {
            let m = Nglod::from_sdf(2, |p| p.length() - 0.5).unwrap();
            let file = m.to_model_file(Normalization::identity(), serde_json::Value::Null);
            SceneNode::model(
                Arc::new(NeuralSdf::from_model_file(file).unwrap()),
                Transform::IDENTITY,
            )
        })
        .collect();
    match err(SceneNode::Union(models)) {
        SceneError::TooManyModels { node, limit } => {
            assert_eq!(limit, MAX_MODELS);
            assert_eq!(node, format!("root.children[{MAX_MODELS}]"));
        }
        e => panic!("{e:?}"),
    }
    let k_bad = |k| {
        err(SceneNode::SmoothUnion {
            k,
            children: vec![s(), s()],
        })
    };
    assert!(matches!(
        k_bad(0.0),
        SceneError::Parameter { field: "k", .. }
    ));
    assert!(matches!(
        k_bad(-1.0),
        SceneError::Parameter { field: "k", .. }
    ));
    assert!(matches!(
        k_bad(f32::NAN),
        SceneError::NonFinite { field: "k", .. }
    ));
    let placed = |t: Transform| err(SceneNode::Union(vec![s(), s().transformed(t)]));
    match placed(Transform {
        scale: 0.0,
        ..Transform::IDENTITY
    }) {
        SceneError::Scale { node, scale } => {
            assert_eq!((node.as_str(), scale), ("root.children[1]", 0.0))
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        placed(Transform {
            scale: -2.0,
            ..Transform::IDENTITY
        }),
        SceneError::Scale { .. }
    ));
    assert!(matches!(
        placed(Transform::from_translation(Vec3::new(
            0.0,
            f32::INFINITY,
            0.0
        ))),
        SceneError::NonFinite {
            field: "translation",
            ..
        }
    ));
    assert!(matches!(
        placed(Transform {
            rotation: Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
            ..Transform::IDENTITY
        }),
        SceneError::Rotation { .. }
    ));
    match err(SceneNode::Shell {
        t: 0.1,
        child: Box::new(sphere_at(Vec3::ZERO, -1.0)),
    }) {
        SceneError::Parameter {
            node, field, value, ..
        } => {
            assert_eq!(
                (node.as_str(), field, value),
                ("root.children[0]", "radius", -1.0)
            )
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        err(SceneNode::Shell {
            t: 0.0,
            child: Box::new(s())
        }),
        SceneError::Parameter { field: "t", .. }
    ));
    assert!(matches!(
        err(SceneNode::Union(vec![])),
        SceneError::Children {
            op: "union",
            found: 0,
            ..
        }
    ));
    // A rotation quaternion of any length is normalised.
    let long = Transform {
        rotation: Quat::from_rotation_z(FRAC_PI_2) * 3.0,
        ..Transform::IDENTITY
    };
    let scene = Scene::new(sphere_at(Vec3::X, 1.0).transformed(long)).unwrap();
    assert_close(
        scene.distance(Vec3::new(0.0, 1.0, 0.0), 0.0),
        -1.0,
        1e-6,
        "normalised",
    );
}

/// A fresh folder for one test's files.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hwsdf-scene-{name}-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("models")).unwrap();
    dir
}

/// Writes the sphere model to `dir/models/ball.safetensors`.
fn write_model(dir: &Path) {
    let model = Nglod::from_sdf(16, |p| p.length() - MODEL_RADIUS).unwrap();
    model
        .to_model_file(normalization(), serde_json::Value::Null)
        .save(&dir.join("models/ball.safetensors"))
        .unwrap();
}

/// A scene file with a model placed twice, primitives and operators, in both TOML styles
/// (dotted headers and inline tables), loads into the scene it describes.
#[test]
fn scene_files_load() {
    let dir = temp_dir("load");
    write_model(&dir);
    let text = r#"
# Two trained spheres and a box, the box drilled.
[models]
ball = "models/ball.safetensors"

[root]
type = "union"

[[root.children]]
type = "model"
model = "ball"
translation = [-10, 0, 0]
rotation = { axis = [0, 0, 2], degrees = 90 }
scale = 0.5

[[root.children]]
type = "transform"
translation = [10, 0, 0]
scale = [2, 2, 2]

[[root.children.children]]
type = "model"
model = "ball"

[[root.children]]
type = "difference"
children = [
    { type = "box", half_extents = [1, 1, 1], translation = [0, 0, 30] },
    { type = "cylinder", radius = 0.5, half_height = 2.0, translation = [0, 0, 30], rotation = { axis = [1, 0, 0], degrees = 90.0 } },
]
"#;
    std::fs::write(dir.join("scene.toml"), text).unwrap();
    let scene = Scene::load(dir.join("scene.toml")).unwrap();
    assert_eq!(
        (scene.models().len(), scene.leaves().len(), scene.depth()),
        (1, 4, 3)
    );
    let n = normalization();
    let turn = Quat::from_rotation_z(FRAC_PI_2);
    let a = Transform::new(Vec3::new(-10.0, 0.0, 0.0), turn, 0.5).apply(n.center);
    let b = Vec3::new(10.0, 0.0, 0.0) + 2.0 * n.center;
    let r = MODEL_RADIUS / n.scale;
    for (p, want, tol) in [
        // Inside the models' boxes (half size 4 mesh units: 1.67 radii).
        (a + Vec3::Y * 1.5 * r * 0.5, r as f64 * 0.25, 0.02),
        (b + Vec3::Z * 1.5 * r * 2.0, r as f64, 0.08),
        (Vec3::new(0.0, 0.0, 28.0), 1.0, 1e-5),
        // Drilled along z by the turned cylinder: the hole's wall is 0.5 from the axis.
        (Vec3::new(0.25, 0.0, 30.0), 0.25, 1e-5),
    ] {
        assert_close(scene.distance(p, 0.0), want, tol, &format!("{p}"));
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A tree of exactly the depth limit in dotted headers parses (nothing runs out of stack); one
/// level more is refused, and a very deep file is refused before it is parsed.
#[test]
fn deep_files_are_refused_not_crashed() {
    let headers = |depth: usize| {
        let mut text = String::from("[root]\ntype = \"union\"\n");
        let mut path = String::from("root");
        for level in 2..=depth {
            path.push_str(".children");
            let ty = if level == depth {
                "sphere\"\nradius = 1"
            } else {
                "union\""
            };
            text.push_str(&format!("[[{path}]]\ntype = \"{ty}\n"));
        }
        text
    };
    let inline = |depth: usize| {
        let mut text = String::from("root = ");
        for _ in 1..depth {
            text.push_str("{ type = \"offset\", r = 0.0, children = [");
        }
        text.push_str("{ type = \"sphere\", radius = 1 }");
        for _ in 1..depth {
            text.push_str("] }");
        }
        text
    };
    let scene = Scene::from_toml(&headers(MAX_DEPTH), Path::new(".")).unwrap();
    assert_eq!(scene.depth(), MAX_DEPTH);
    match Scene::from_toml(&headers(MAX_DEPTH + 1), Path::new(".")) {
        Err(SceneFileError::Scene(SceneError::TooDeep { node, limit })) => {
            assert_eq!(limit, MAX_DEPTH);
            assert_eq!(node.matches(".children[0]").count(), MAX_DEPTH);
        }
        other => panic!("{other:?}"),
    }
    // The TOML parser's own limit on nested inline tables and arrays comes first: a syntax
    // error with its place, not a crash.
    assert_eq!(
        Scene::from_toml(&inline(30), Path::new("."))
            .unwrap()
            .depth(),
        30
    );
    match Scene::from_toml(&inline(MAX_DEPTH), Path::new(".")) {
        Err(SceneFileError::Syntax {
            line: 1, message, ..
        }) => {
            assert!(message.contains("recurs"), "{message}")
        }
        other => panic!("{other:?}"),
    }
    for (style, make) in [
        ("headers", &headers as &dyn Fn(usize) -> String),
        ("inline", &inline),
    ] {
        match Scene::from_toml(&make(1000), Path::new(".")) {
            Err(SceneFileError::TooDeep { limit, .. }) => assert_eq!(limit, MAX_DEPTH),
            other => panic!("{style}: {other:?}"),
        }
    }
    // Brackets in strings and comments do not count.
    let text = format!(
        "# {}\n[root]\ntype = \"sphere\" # {}\nradius = 1\n",
        "[".repeat(500),
        "{".repeat(500)
    );
    Scene::from_toml(&text, Path::new(".")).unwrap();
}

/// Every bad scene file gives its typed error, saying what and where.
#[test]
fn bad_scene_files_are_typed_errors() {
    let dir = temp_dir("bad");
    write_model(&dir);
    std::fs::write(dir.join("models/garbage.safetensors"), b"not a model").unwrap();
    let parse = |text: &str| Scene::from_toml(text, &dir).unwrap_err();
    let ok_leaf = "[root]\ntype = \"sphere\"\nradius = 1\n";
    Scene::from_toml(ok_leaf, &dir).unwrap();

    match parse("[root]\ntype = \"sphere\"\nradius = = 1\n") {
        SceneFileError::Syntax { line, column, .. } => assert_eq!((line, column), (3, 10)),
        e => panic!("{e:?}"),
    }
    match parse("[root]\ntype = \"sphere\"\nradius = 1\nradiuss = 2\n") {
        SceneFileError::UnknownKey { key, line, .. } => {
            assert_eq!((key.as_str(), line), ("radiuss", 4))
        }
        e => panic!("{e:?}"),
    }
    // A key another node type takes is unknown to this one; in inline tables too.
    let text = "[root]\ntype = \"union\"\nchildren = [\n  { type = \"sphere\", radius = 1 },\n  \
                { type = \"box\", radius = 1, half_extents = [1, 1, 1] },\n]\n";
    match parse(text) {
        SceneFileError::UnknownKey {
            key,
            line,
            column,
            message,
        } => {
            assert_eq!((key.as_str(), line, column), ("radius", 5, 28), "{message}");
            assert!(message.contains("half_extents"), "{message}");
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse("[root]\ntype = \"union\"\nchildren = []\nscale = 2\n"),
        SceneFileError::UnknownKey { key, line: 4, .. } if key == "scale"
    ));
    assert!(matches!(
        parse("scene = 1\n[root]\ntype = \"sphere\"\nradius = 1\n"),
        SceneFileError::UnknownKey { key, line: 1, .. } if key == "scene"
    ));
    match parse("[root]\ntype = \"union\"\n[[root.children]]\ntype = \"unoin\"\n") {
        SceneFileError::UnknownOperator {
            name,
            line,
            column,
            message,
        } => {
            assert_eq!((name.as_str(), line, column), ("unoin", 4, 8));
            assert!(message.contains("smooth_union"), "{message}");
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse("[root]\ntype = \"union\"\n[[root.children]]\ntype = \"sphere\"\n"),
        SceneFileError::MissingKey {
            key: "radius",
            node_type: "sphere",
            line: 3,
            ..
        }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"smooth_union\"\nk = 1\n"),
        SceneFileError::MissingKey {
            key: "children",
            line: 1,
            ..
        }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"sphere\"\nradius = \"big\"\n"),
        SceneFileError::Schema { line: 3, .. }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"box\"\nhalf_extents = [1, 2]\n"),
        SceneFileError::Schema { line: 3, .. }
    ));
    assert!(
        matches!(parse("[models]\n"), SceneFileError::Schema { message, .. } if message.contains("root"))
    );
    let model =
        |file: &str| format!("[models]\nm = \"{file}\"\n[root]\ntype = \"model\"\nmodel = \"m\"\n");
    match parse(&model("models/missing.safetensors")) {
        SceneFileError::Model { name, path, .. } => {
            assert_eq!(name, "m");
            assert_eq!(path, dir.join("models/missing.safetensors"));
        }
        e => panic!("{e:?}"),
    }
    match parse(&model("models/garbage.safetensors")) {
        e @ SceneFileError::Model { .. } => assert!(e.to_string().contains("garbage.safetensors")),
        e => panic!("{e:?}"),
    }
    Scene::from_toml(&model("models/ball.safetensors"), &dir).unwrap();
    assert!(matches!(
        parse("[models]\nm = \"models/ball.safetensors\"\n[root]\ntype = \"model\"\nmodel = \"n\"\n"),
        SceneFileError::UnknownModel { node, name } if node == "root" && name == "n"
    ));
    let many: String = (0..=MAX_MODELS)
        .map(|i| format!("m{i} = \"models/ball.safetensors\"\n"))
        .collect();
    assert!(matches!(
        parse(&format!(
            "[models]\n{many}[root]\ntype = \"sphere\"\nradius = 1\n"
        )),
        SceneFileError::TooManyModels {
            limit: MAX_MODELS,
            ..
        }
    ));

    // Placements and parameters, on the second child so the path says which.
    let child = |keys: &str| {
        format!(
            "[root]\ntype = \"union\"\n[[root.children]]\ntype = \"sphere\"\nradius = 1\n\
             [[root.children]]\ntype = \"sphere\"\nradius = 1\n{keys}\n"
        )
    };
    assert!(matches!(
        parse(&child("scale = [1, 2]")),
        SceneFileError::Schema { line: 9, .. }
    ));
    match parse(&child("scale = [1, 2, 1]")) {
        SceneFileError::NonUniformScale { node, scale } => {
            assert_eq!(
                (node.as_str(), scale),
                ("root.children[1]", [1.0, 2.0, 1.0])
            )
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse(&child("scale = 0")),
        SceneFileError::Scene(SceneError::Scale { node, .. }) if node == "root.children[1]"
    ));
    assert!(matches!(
        parse(&child("scale = -1.0")),
        SceneFileError::Scene(SceneError::Scale { .. })
    ));
    for (keys, field) in [
        ("translation = [0, nan, 0]", "translation"),
        ("scale = inf", "scale"),
        (
            "rotation = { axis = [0, 1, 0], degrees = -inf }",
            "rotation.degrees",
        ),
    ] {
        match parse(&child(keys)) {
            SceneFileError::NonFinite { node, field: f, .. } => {
                assert_eq!((node.as_str(), f), ("root.children[1]", field), "{keys}")
            }
            e => panic!("{keys}: {e:?}"),
        }
    }
    assert!(matches!(
        parse("[root]\ntype = \"sphere\"\nradius = 1e39\n"),
        SceneFileError::NonFinite {
            field: "radius",
            ..
        }
    ));
    assert!(matches!(
        parse(&child("rotation = { axis = [0, 0, 0], degrees = 10 }")),
        SceneFileError::ZeroAxis { node } if node == "root.children[1]"
    ));
    assert!(matches!(
        parse(&child("rotation = { axis = [0, 0, 1], degree = 10 }")),
        SceneFileError::UnknownKey { key, .. } if key == "degree"
    ));
    let smooth = |k: &str| {
        format!(
            "[root]\ntype = \"smooth_union\"\nk = {k}\nchildren = [{{ type = \"sphere\", radius = 1 }}]\n"
        )
    };
    for k in ["0", "-0.5"] {
        assert!(matches!(
            parse(&smooth(k)),
            SceneFileError::Scene(SceneError::Parameter { field: "k", .. })
        ));
    }
    assert!(matches!(
        parse(&smooth("nan")),
        SceneFileError::NonFinite { field: "k", .. }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"offset\"\nr = 1\nchildren = []\n"),
        SceneFileError::Children {
            op: "offset",
            found: 0,
            ..
        }
    ));
    match Scene::load(dir.join("nowhere.toml")) {
        Err(SceneFileError::Io { path, .. }) => assert_eq!(path, dir.join("nowhere.toml")),
        other => panic!("{other:?}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}
