//! Scenes on the GPU (`GpuScene`) against the CPU reference: every primitive and operator,
//! placed models, gradients and deciding leaves, rays, closest points, levels, batches split
//! into parts, bad input, and eight threads querying one scene at once.

use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{Quat, Vec3};
use sdf_nn::GpuContext;
use sdf_nn::serve::query::QueryKernel;
use sdf_nn::serve::scene::{
    GpuScene, Primitive, ProjectOptions, Ray, Scene, SceneGpuError, SceneNode, SceneQueryError,
    SceneQueryKind, TRACE_OVER_RELAXATION, TraceOptions, Transform,
};
use sdf_nn::{NeuralSdf, Nglod, NglodConfig, Normalization};

use crate::models::{hashed_sphere_model, sphere_model};
use crate::sphere_at;
use crate::{hits_at_the_same_t, hits_in_the_cpus_steps, random_points, shared_hits};

fn gpu() -> &'static GpuContext {
    GpuContext::shared().expect("a GPU adapter (lavapipe in CI)")
}

/// Every primitive, each placed (moved, turned, scaled), under every operator.
fn analytic_scene() -> Scene {
    let at = |x: f32, y: f32, turn: f32, s: f32| {
        Transform::new(
            Vec3::new(x, y, 0.0),
            Quat::from_rotation_y(turn) * Quat::from_rotation_x(0.3 * turn),
            s,
        )
    };
    let prim = |p, t| SceneNode::primitive(p, t);
    let e = Vec3::new(0.5, 0.3, 0.4);
    let sphere = prim(Primitive::Sphere { radius: 0.6 }, at(-2.0, 0.0, 0.0, 1.0));
    let cube = prim(Primitive::Box { half_extents: e }, at(-1.6, 0.3, 0.4, 1.3));
    let round = prim(
        Primitive::RoundBox {
            half_extents: e,
            radius: 0.1,
        },
        at(0.0, 0.0, 0.9, 0.8),
    );
    let capsule = prim(
        Primitive::Capsule {
            a: -e,
            b: e,
            radius: 0.25,
        },
        at(0.2, 0.4, -0.5, 1.0),
    );
    let torus = prim(
        Primitive::Torus {
            major: 0.6,
            minor: 0.2,
        },
        at(2.0, 0.0, 1.1, 1.0),
    );
    let plane = prim(
        Primitive::Plane {
            normal: Vec3::new(0.1, 1.0, 0.2),
            offset: -1.0,
        },
        Transform::IDENTITY,
    );
    let cylinder = prim(
        Primitive::Cylinder {
            radius: 0.3,
            half_height: 0.7,
        },
        at(2.2, 0.3, 0.2, 1.2),
    );
    SceneNode::Union(vec![
        SceneNode::SmoothUnion {
            k: 0.3,
            children: vec![sphere.clone(), cube.clone()],
        },
        SceneNode::SmoothDifference {
            k: 0.2,
            children: vec![round.clone(), capsule.clone()],
        },
        SceneNode::SmoothIntersection {
            k: 0.25,
            children: vec![torus.clone(), cylinder.clone()],
        },
        SceneNode::Difference(vec![cylinder, torus]),
        SceneNode::Intersection(vec![capsule, round]),
        SceneNode::Shell {
            t: 0.05,
            child: Box::new(sphere),
        },
        SceneNode::Offset {
            r: 0.1,
            child: Box::new(plane),
        },
    ])
    .transformed(Transform::new(
        Vec3::new(0.3, -0.2, 0.1),
        Quat::from_rotation_z(0.4),
        1.5,
    ))
    .pipe(|root| Scene::new(root).unwrap())
}

trait Pipe: Sized {
    fn pipe<T>(self, f: impl FnOnce(Self) -> T) -> T {
        f(self)
    }
}
impl<T> Pipe for T {}

/// The GPU's distances and samples at `points` against the CPU's (f64 through the operators)
/// at `level`: every distance within `tolerance · (1 + |d|)`, and where both chose the same
/// leaf, the gradients within `gradient_tolerance · (1 + |∇d|)`. How many points both decided
/// by the same leaf.
fn samples_match_the_cpu(
    scene: &Scene,
    on_gpu: &GpuScene,
    points: &[Vec3],
    level: f32,
    (tolerance, gradient_tolerance): (f32, f32),
    what: &str,
) -> usize {
    let cpu = scene.distances_and_gradients(points, level);
    let gpu_d = on_gpu.distances(points, level).unwrap();
    let gpu_s = on_gpu.samples(points, level).unwrap();
    let mut same_leaf = 0;
    for (i, c) in cpu.iter().enumerate() {
        let tol = tolerance * (1.0 + c.distance.abs());
        assert!(
            (gpu_d[i] - c.distance).abs() <= tol && (gpu_s[i].distance - c.distance).abs() <= tol,
            "{what}, point {} at level {level}: {} and {} vs {}",
            points[i],
            gpu_d[i],
            gpu_s[i].distance,
            c.distance
        );
        if gpu_s[i].leaf == c.leaf {
            same_leaf += 1;
            assert!(
                gpu_s[i]
                    .gradient
                    .abs_diff_eq(c.gradient, gradient_tolerance * (1.0 + c.gradient.length())),
                "{what}, gradient at {}: {} vs {}",
                points[i],
                gpu_s[i].gradient,
                c.gradient
            );
        }
    }
    same_leaf
}

/// The GPU's distances, gradients and leaves against the CPU's (f64 through the operators) on
/// an analytic scene: distances within 1e-5 (scene units ≈ 1), gradients within 1e-4, the same
/// leaf except where two children are within rounding of each other.
#[test]
fn analytic_scene_matches_the_cpu() {
    let scene = analytic_scene();
    let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    let points = random_points(4000, 4.0, 3);
    for level in [0.0, 0.2] {
        // Gradients within 1e-4 where they are unit vectors.
        let same = samples_match_the_cpu(&scene, &on_gpu, &points, level, (1e-5, 5e-5), "analytic");
        let leaf_differs = points.len() - same;
        assert!(
            leaf_differs <= 4,
            "{leaf_differs} of 4000 points decided by another leaf"
        );
    }
}

/// Rays and closest points on the GPU stop where the CPU's do.
#[test]
fn analytic_rays_and_closest_points_match_the_cpu() {
    let scene = analytic_scene();
    let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    let origins = random_points(500, 5.0, 4);
    let targets = random_points(500, 1.5, 5);
    let rays: Vec<Ray> = origins
        .iter()
        .zip(&targets)
        .map(|(&o, &t)| Ray {
            origin: o * 2.0,
            direction: t - o * 2.0,
            max_distance: 40.0,
        })
        .collect();
    let options = TraceOptions {
        level: 0.05,
        ..TraceOptions::default()
    };
    let cpu = scene.trace_rays(&rays, &options).unwrap();
    let gpu_hits = on_gpu.trace_rays(&rays, &options).unwrap();
    let hits = shared_hits(&cpu, &gpu_hits, "CPU against GPU");
    for &(i, c, g) in &hits {
        assert!(
            (c.t - g.t).abs() < 2e-3 * (1.0 + c.t),
            "ray {i}: t {} vs {}",
            g.t,
            c.t
        );
        assert!(
            c.point.abs_diff_eq(g.point, 1e-2),
            "ray {i}: point {} vs {}",
            g.point,
            c.point
        );
        // The hit point's distance on the CPU is the level within the tolerance.
        let d = scene.distance(g.point, options.level);
        assert!(
            d.abs() < 2e-3,
            "ray {i}: GPU hit at distance {d} from the level set"
        );
        if c.leaf == g.leaf && (c.t - g.t).abs() < 1e-4 {
            assert!(
                c.normal.abs_diff_eq(g.normal, 2e-2),
                "ray {i}: normal {} vs {}",
                g.normal,
                c.normal
            );
        }
    }
    assert!(hits.len() > 100, "only {} of 500 rays hit", hits.len());

    let project = ProjectOptions {
        level: 0.05,
        ..ProjectOptions::default()
    };
    let points = random_points(500, 3.0, 6);
    let cpu = scene.closest_points(&points, &project).unwrap();
    let gpu_p = on_gpu.closest_points(&points, &project).unwrap();
    let mut converged = 0;
    for (i, (c, g)) in cpu.iter().zip(&gpu_p).enumerate() {
        if g.converged {
            converged += 1;
            assert!(g.residual < project.tolerance);
            let d = scene.distance(g.point, project.level);
            assert!(d.abs() < 1e-4, "point {i}: projected to distance {d}");
        }
        if c.converged && g.converged && c.leaf == g.leaf {
            assert!(
                c.point.abs_diff_eq(g.point, 1e-3),
                "point {i}: {} vs {}",
                g.point,
                c.point
            );
        }
    }
    assert!(
        converged > 450,
        "only {converged} of 500 projections converged"
    );
}

/// A baked model placed twice (one weight copy) with primitives, under a smooth union and a
/// difference: the GPU's distances, normals, rays and closest points agree with the CPU's.
#[test]
fn placed_models_match_the_cpu() {
    placed_models_match_the_cpu_on(QueryKernel::PerInvocation);
}

/// The same with one subgroup per point or ray (lavapipe has subgroups of 8 lanes;
/// `scripts/subgroup-widths.sh` runs it at 4 and 16).
#[test]
fn placed_models_match_the_cpu_one_subgroup_per_element() {
    placed_models_match_the_cpu_on(QueryKernel::PerSubgroup);
}

/// On the faces of a model's box the scene's gradient is the inside's, on the CPU and on both
/// GPU kernels (the snippet took the derivative across a face as the clamped outside's, 0): a
/// linear field, exact under trilinear interpolation, at points on faces, an edge and corners.
#[test]
fn gradients_on_a_models_box_faces_are_the_insides() {
    let g = Vec3::new(0.3, -0.5, 0.8);
    let model = Nglod::from_sdf(8, move |p| p.dot(g)).unwrap();
    let identity = Normalization {
        center: glam::DVec3::ZERO,
        scale: 1.0,
    };
    let sdf =
        NeuralSdf::from_model_file(model.to_model_file(identity, serde_json::Value::Null)).unwrap();
    let scene = Scene::new(SceneNode::model(Arc::new(sdf), Transform::IDENTITY)).unwrap();
    let pts = [
        Vec3::new(1.0, 0.3, -0.2),
        Vec3::new(-1.0, 0.5, 0.1),
        Vec3::new(0.2, 1.0, -1.0),
        Vec3::ONE,
        -Vec3::ONE,
    ];
    // A model's gradient in a scene is its unit normal.
    let want = g.normalize();
    let mut paths = vec![("cpu", scene.distances_and_gradients(&pts, 0.0))];
    for kernel in [QueryKernel::PerInvocation, QueryKernel::PerSubgroup] {
        let name = if kernel == QueryKernel::PerInvocation {
            "gpu, one point per invocation"
        } else {
            "gpu, one point per subgroup"
        };
        paths.push((name, scene_on(&scene, kernel).samples(&pts, 0.0).unwrap()));
    }
    for (path, got) in paths {
        for (p, s) in pts.iter().zip(got) {
            assert!(
                (s.gradient - want).length() < 1e-2,
                "{path} at {p}: {} vs {want}",
                s.gradient
            );
        }
    }
}

/// Rays fired from afar hit, on both kernels, as on the CPU: at 2000 units and beyond f32's
/// points along a ray are coarser than the tolerance, and the GPU's rays stalled short of the
/// surface and missed (a user's sphere of radius 1000 seen from 10 radii: every ray missed).
#[test]
fn rays_from_afar_hit_on_both_kernels() {
    let scene = Scene::new(SceneNode::Union(vec![
        sphere_at(Vec3::ZERO, 1.0),
        sphere_at(Vec3::new(0.0, 5.0, 0.0), 0.5),
    ]))
    .unwrap();
    let rays: Vec<Ray> = [10.0, 300.0, 2000.0, 4000.0, 8000.0, 1.0e5]
        .into_iter()
        // Off the sphere's axis, so that the last steps shrink towards the surface.
        .map(|x| Ray {
            origin: Vec3::new(x, 0.6, 0.0),
            direction: -Vec3::X,
            max_distance: f32::INFINITY,
        })
        .collect();
    let options = TraceOptions::default();
    let cpu = scene.trace_rays(&rays, &options).unwrap();
    for kernel in [QueryKernel::PerInvocation, QueryKernel::PerSubgroup] {
        let gpu = scene_on(&scene, kernel)
            .trace_rays(&rays, &options)
            .unwrap();
        for ((ray, c), g) in rays.iter().zip(&cpu).zip(&gpu) {
            let (c, g) = (
                c.expect("the CPU hits"),
                g.unwrap_or_else(|| panic!("{kernel:?}: the ray from {} missed", ray.origin)),
            );
            let want = ray.origin.x - 0.8;
            assert!((c.t - want).abs() <= 1e-4 * want, "cpu t {} vs {want}", c.t);
            assert!(
                (g.t - want).abs() <= 1e-6 * want + 1e-3,
                "{kernel:?}: t {} vs {want}",
                g.t
            );
            assert!(
                (g.point - Vec3::new(0.8, 0.6, 0.0)).length() < 1e-3,
                "{kernel:?}: {}",
                g.point
            );
        }
    }
}

/// `scene` on the GPU, its queries run by `kernel`.
fn scene_on(scene: &Scene, kernel: QueryKernel) -> GpuScene<'static> {
    let mut on_gpu = GpuScene::new(gpu(), scene).unwrap();
    on_gpu
        .set_kernel(Some(kernel))
        .expect("lavapipe and the GPUs we test on have subgroups");
    on_gpu
}

fn placed_models_match_the_cpu_on(kernel: QueryKernel) {
    let model = Arc::new(sphere_model(1.0));
    // A hash grid beside the NGLOD model: one scene, both encodings.
    let other = Arc::new(hashed_sphere_model(0.8));
    let scene = Scene::new(SceneNode::Difference(vec![
        SceneNode::SmoothUnion {
            k: 0.5,
            children: vec![
                SceneNode::model(
                    model.clone(),
                    Transform::new(Vec3::new(-3.0, 0.0, 0.0), Quat::from_rotation_y(0.5), 0.5),
                ),
                SceneNode::model(
                    model.clone(),
                    Transform::new(Vec3::new(2.0, 1.0, 0.0), Quat::from_rotation_x(1.0), 0.7),
                ),
                SceneNode::model(
                    other,
                    Transform::from_translation(Vec3::new(0.0, -2.0, 1.0)),
                ),
            ],
        },
        SceneNode::primitive(
            Primitive::Box {
                half_extents: Vec3::new(0.5, 3.0, 0.5),
            },
            Transform::from_translation(Vec3::new(-3.5, 0.0, 0.0)),
        ),
    ]))
    .unwrap();
    assert_eq!(scene.models().len(), 2);
    let on_gpu = scene_on(&scene, kernel);
    let points = random_points(2000, 5.0, 7);
    // Gradients within 1e-3 where they are unit vectors.
    samples_match_the_cpu(&scene, &on_gpu, &points, 0.0, (2e-5, 5e-4), "placed models");
    let rays: Vec<Ray> = random_points(200, 1.0, 8)
        .into_iter()
        .map(|t| Ray {
            origin: Vec3::new(0.0, 0.0, -12.0),
            direction: t * 3.0 - Vec3::new(0.0, 0.0, -12.0),
            max_distance: 30.0,
        })
        .collect();
    let options = TraceOptions::default();
    let (cpu, gpu_hits) = (
        scene.trace_rays(&rays, &options).unwrap(),
        on_gpu.trace_rays(&rays, &options).unwrap(),
    );
    let hits = hits_at_the_same_t(&cpu, &gpu_hits, "CPU against GPU");
    for &(i, c, g) in &hits {
        assert_eq!(c.leaf, g.leaf, "ray {i}");
    }
    assert!(hits.len() > 40, "only {} of 200 rays hit", hits.len());
    let points = random_points(300, 4.0, 9);
    let options = ProjectOptions::default();
    for (i, g) in on_gpu
        .closest_points(&points, &options)
        .unwrap()
        .iter()
        .enumerate()
    {
        if g.converged {
            let d = scene.distance(g.point, 0.0);
            assert!(d.abs() < 1e-4, "point {i}: projected to distance {d}");
        }
    }
}

/// A batch larger than one part is split into parts (one submission each) with the same answers.
#[test]
fn batches_are_split_into_parts() {
    let scene = analytic_scene();
    let mut on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    let points = random_points(1000, 3.0, 10);
    let whole = on_gpu.distances(&points, 0.0).unwrap();
    on_gpu.set_max_part(96);
    assert_eq!(on_gpu.max_elements(SceneQueryKind::Distance), 96);
    let parts = on_gpu.distances(&points, 0.0).unwrap();
    assert_eq!(whole, parts);
}

/// Bad rays and levels are refused with the CPU's typed errors, naming the element.
#[test]
fn bad_queries_are_refused() {
    let scene = analytic_scene();
    let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    let good = Ray {
        origin: Vec3::ZERO,
        direction: Vec3::X,
        max_distance: 1.0,
    };
    for (bad, want) in [
        (
            Ray {
                direction: Vec3::ZERO,
                ..good
            },
            "direction",
        ),
        (
            Ray {
                direction: Vec3::new(f32::NAN, 0.0, 0.0),
                ..good
            },
            "direction",
        ),
        (
            Ray {
                origin: Vec3::splat(f32::INFINITY),
                ..good
            },
            "not finite",
        ),
        (
            Ray {
                max_distance: -1.0,
                ..good
            },
            "maximum distance",
        ),
    ] {
        let err = on_gpu
            .trace_rays(&[good, bad], &TraceOptions::default())
            .unwrap_err();
        assert!(matches!(err, SceneGpuError::Query(_)), "{err}");
        let text = err.to_string();
        assert!(text.contains("1") && text.contains(want), "{text}");
    }
    assert!(matches!(
        on_gpu.distances(&[Vec3::ZERO], f32::NAN),
        Err(SceneGpuError::Query(SceneQueryError::Level(_)))
    ));
    // A point that is not finite is refused by every point query, not answered with the
    // largest float (where no bound lets a model run).
    let bad_points = [Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0)];
    assert!(matches!(
        on_gpu.distances(&bad_points, 0.0),
        Err(SceneGpuError::Query(SceneQueryError::Point {
            index: 1,
            ..
        }))
    ));
    assert!(matches!(
        on_gpu.samples(&bad_points, 0.0),
        Err(SceneGpuError::Query(SceneQueryError::Point {
            index: 1,
            ..
        }))
    ));
    assert!(matches!(
        on_gpu.closest_points(&bad_points, &ProjectOptions::default()),
        Err(SceneGpuError::Query(SceneQueryError::Point {
            index: 1,
            ..
        }))
    ));
    let bad_tolerance = ProjectOptions {
        tolerance: 0.0,
        ..ProjectOptions::default()
    };
    assert!(matches!(
        on_gpu.closest_points(&[Vec3::ZERO], &bad_tolerance),
        Err(SceneGpuError::Query(SceneQueryError::Tolerance(_)))
    ));
    let bad_relaxation = TraceOptions {
        over_relaxation: 2.0,
        ..TraceOptions::default()
    };
    assert!(matches!(
        on_gpu.trace_rays(&[good], &bad_relaxation),
        Err(SceneGpuError::Query(SceneQueryError::OverRelaxation(_)))
    ));
}

/// Eight threads query one scene at once for a bounded time (distances and rays, each thread
/// its own points): every answer matches the CPU's.
#[test]
fn eight_threads_query_one_scene() {
    let model = Arc::new(sphere_model(1.0));
    let scene = Scene::new(SceneNode::SmoothUnion {
        k: 0.4,
        children: vec![
            SceneNode::model(model, Transform::new(Vec3::X, Quat::IDENTITY, 0.5)),
            SceneNode::primitive(
                Primitive::Torus {
                    major: 1.0,
                    minor: 0.3,
                },
                Transform::IDENTITY,
            ),
        ],
    })
    .unwrap();
    let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    // Compile both kernels before the clock starts.
    on_gpu.distances(&[Vec3::ZERO], 0.0).unwrap();
    on_gpu
        .trace_rays(
            &[Ray {
                origin: Vec3::Z * 5.0,
                direction: -Vec3::Z,
                max_distance: 10.0,
            }],
            &TraceOptions::default(),
        )
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(4);
    let checked: usize = std::thread::scope(|s| {
        let handles: Vec<_> = (0..8u64)
            .map(|t| {
                let (scene, on_gpu) = (&scene, &on_gpu);
                s.spawn(move || {
                    let mut checked = 0;
                    let mut round = 0;
                    while Instant::now() < deadline || round == 0 {
                        let points = random_points(200 + 37 * t as usize, 3.0, 100 * t + round);
                        let want = scene.distances(&points, 0.0);
                        let got = on_gpu.distances(&points, 0.0).unwrap();
                        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                            assert!(
                                (g - w).abs() <= 2e-5 * (1.0 + w.abs()),
                                "thread {t} round {round} point {i}: {g} vs {w}"
                            );
                        }
                        let rays: Vec<Ray> = points[..50]
                            .iter()
                            .map(|&p| Ray {
                                origin: p * 3.0,
                                direction: -p,
                                max_distance: 20.0,
                            })
                            .collect();
                        let want = scene.trace_rays(&rays, &TraceOptions::default()).unwrap();
                        let got = on_gpu.trace_rays(&rays, &TraceOptions::default()).unwrap();
                        let what = format!("thread {t} round {round}, CPU against GPU");
                        hits_at_the_same_t(&want, &got, &what);
                        checked += got.len() + points.len();
                        round += 1;
                    }
                    checked
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).sum()
    });
    assert!(checked >= 8 * 250, "{checked}");
}

/// Unions of many placed models and primitives (the compiled chains that evaluate the nearest
/// model first and skip the others by their bounds), as a fresh union and continuing a smooth
/// union: distances and rays agree with the CPU's.
#[test]
fn unions_of_many_models_match_the_cpu() {
    let model = Arc::new(sphere_model(1.0));
    let placed = |i: usize| {
        SceneNode::model(
            model.clone(),
            Transform::new(
                Vec3::new(i as f32 * 2.2 - 4.4, (i % 2) as f32, 0.0),
                Quat::from_rotation_y(i as f32),
                0.4,
            ),
        )
    };
    let ball = SceneNode::primitive(
        Primitive::Sphere { radius: 0.5 },
        Transform::from_translation(Vec3::Y * 3.0),
    );
    let slab = SceneNode::primitive(
        Primitive::Box {
            half_extents: Vec3::new(6.0, 0.1, 2.0),
        },
        Transform::from_translation(Vec3::Y * -1.5),
    );
    let fresh: Vec<SceneNode> = (0..5)
        .map(placed)
        .chain([ball.clone(), slab.clone()])
        .collect();
    let mut continued = vec![SceneNode::SmoothUnion {
        k: 0.3,
        children: vec![ball, slab],
    }];
    continued.extend((0..5).map(placed));
    for children in [fresh, continued] {
        let scene = Scene::new(SceneNode::Union(children)).unwrap();
        // The chain is compiled as one union of leaves, not as five separate culled unions.
        let wgsl = scene
            .wgsl_with_prefix(0, "s", &gpu().device().limits())
            .unwrap();
        // Once in `s_distance`, once in `s_trace`.
        assert_eq!(wgsl.matches("nearest model bound first").count(), 2);
        let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
        let points = random_points(3000, 6.0, 11);
        let want = scene.distances(&points, 0.0);
        let got = on_gpu.distances(&points, 0.0).unwrap();
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!(
                (g - w).abs() <= 2e-5 * (1.0 + w.abs()),
                "point {i} {}: {g} vs {w}",
                points[i]
            );
        }
        let rays: Vec<Ray> = random_points(300, 5.0, 12)
            .into_iter()
            .map(|t| Ray {
                origin: Vec3::new(0.0, 8.0, 10.0),
                direction: t - Vec3::new(0.0, 8.0, 10.0),
                max_distance: 40.0,
            })
            .collect();
        let options = TraceOptions::default();
        let (cpu, hits) = (
            scene.trace_rays(&rays, &options).unwrap(),
            on_gpu.trace_rays(&rays, &options).unwrap(),
        );
        let shared = hits_at_the_same_t(&cpu, &hits, "CPU against GPU");
        assert!(shared.len() > 50, "{} of 300 rays hit", shared.len());
    }
}

/// Networks whose every width matters to the subgroup form, with random weights (not
/// distances, so only values and gradients are compared): NGLOD with 6 features (a partial
/// `vec4` of inputs), 40 hidden units (not a multiple of any subgroup's width) and a sparse
/// finest level; a hash grid of 5 levels (more levels than 8-lane groups on a 32-wide
/// subgroup), the finer ones hashed. Both kernels against the CPU, values and gradients.
#[test]
fn wide_networks_match_the_cpu_on_both_kernels() {
    let sparse = {
        let mut m = Nglod::new(NglodConfig {
            resolutions: vec![2, 4, 8, 16],
            feature_dim: 6,
            hidden: 40,
            seed: 3,
            sparse_levels: 1,
            ..NglodConfig::small()
        })
        .unwrap();
        m.place_bands(|p| (p.length() - 0.5).abs()).unwrap();
        m
    };
    let hashed = Nglod::new(NglodConfig::hashgrid(5, 4, 40, 2, 11, 24)).unwrap();
    let n = Normalization::identity();
    let models: Vec<Arc<NeuralSdf>> = [sparse, hashed]
        .into_iter()
        .map(|m| {
            Arc::new(
                NeuralSdf::from_model_file(m.to_model_file(n, serde_json::Value::Null)).unwrap(),
            )
        })
        .collect();
    let scene = Scene::new(SceneNode::Union(vec![
        SceneNode::model(models[0].clone(), Transform::IDENTITY),
        SceneNode::model(
            models[1].clone(),
            Transform::new(Vec3::new(0.7, 0.0, 0.2), Quat::from_rotation_z(0.4), 1.3),
        ),
    ]))
    .unwrap();
    let points = random_points(600, 1.6, 21);
    for kernel in [QueryKernel::PerInvocation, QueryKernel::PerSubgroup] {
        let on_gpu = scene_on(&scene, kernel);
        let what = format!("{kernel:?}");
        let compared = samples_match_the_cpu(&scene, &on_gpu, &points, 0.0, (1e-4, 1e-3), &what);
        assert!(compared > 500, "{kernel:?}: {compared} gradients compared");
    }
}

/// The tracer steps by each operand's own Lipschitz bound (`Scene::trace_rays`): far from a
/// steep model (slope 3), a ray straight down onto a plane crosses the plane's whole distance
/// in one step, where the scene-wide bound `|d| / L` would take about 25; the CPU and both GPU
/// kernels alike. And no step crosses the surface: under a difference at a level (its
/// subtracted operand traced against `−c`), beside the model, every hit is the first crossing
/// a fine march finds.
#[test]
fn steps_follow_each_operands_own_bound_on_both_kernels() {
    let steep = Arc::new(sphere_model(3.0));
    let placed = |x: f32| SceneNode::model(steep.clone(), Transform::from_translation(Vec3::X * x));
    let model = placed(-6.0);
    let plane = SceneNode::primitive(
        Primitive::Plane {
            normal: Vec3::Y,
            offset: 0.0,
        },
        Transform::IDENTITY,
    );
    let scene = Scene::new(SceneNode::Union(vec![placed(-30.0), plane])).unwrap();
    assert!(scene.lipschitz() > 2.5, "{}", scene.lipschitz());
    let down: Vec<Ray> = (0..8)
        .map(|i| Ray {
            origin: Vec3::new(6.0, 5.0, i as f32 - 4.0),
            direction: -Vec3::Y,
            max_distance: 20.0,
        })
        .collect();
    // Plain steps: one step and the hit. Over-relaxed: the first step overshoots the plane
    // (1.4 times its distance), the check sends the ray back to the plain step, then the hit.
    for (over_relaxation, most) in [(1.0, 2), (TRACE_OVER_RELAXATION, 3)] {
        let options = TraceOptions {
            over_relaxation,
            ..TraceOptions::default()
        };
        let cpu = scene.trace_rays(&down, &options).unwrap();
        let mut answers = vec![cpu];
        for kernel in [QueryKernel::PerInvocation, QueryKernel::PerSubgroup] {
            answers.push(
                scene_on(&scene, kernel)
                    .trace_rays(&down, &options)
                    .unwrap(),
            );
        }
        for hits in &answers {
            for (i, hit) in hits.iter().enumerate() {
                let hit = hit.expect("every ray hits the plane");
                assert!((hit.t - 5.0).abs() < 1e-3, "ray {i}: t {}", hit.t);
                assert!(hit.steps <= most, "ray {i}: {} steps", hit.steps);
            }
        }
    }

    let level = 0.05;
    let cutter = SceneNode::primitive(
        Primitive::Box {
            half_extents: Vec3::new(1.0, 3.0, 1.0),
        },
        Transform::from_translation(Vec3::new(-5.5, 0.0, 0.0)),
    );
    let ball = sphere_at(Vec3::new(-3.5, 0.0, 0.0), 1.0);
    let scene = Scene::new(SceneNode::Difference(vec![
        SceneNode::Union(vec![model, ball]),
        cutter,
    ]))
    .unwrap();
    let rays: Vec<Ray> = random_points(150, 1.0, 31)
        .into_iter()
        .map(|t| {
            let origin = Vec3::new(-4.5, 0.5, 8.0);
            Ray {
                origin,
                direction: Vec3::new(-4.5, 0.0, 0.0) + t * 2.0 - origin,
                max_distance: 20.0,
            }
        })
        .collect();
    let options = TraceOptions {
        level,
        ..TraceOptions::default()
    };
    let cpu = scene.trace_rays(&rays, &options).unwrap();
    let on_gpu = [QueryKernel::PerInvocation, QueryKernel::PerSubgroup].map(|kernel| {
        scene_on(&scene, kernel)
            .trace_rays(&rays, &options)
            .unwrap()
    });
    let mut hits = 0;
    for (i, (ray, c)) in rays.iter().zip(&cpu).enumerate() {
        let dir = ray.direction.normalize();
        // The first crossing of the level, marched in steps of 1e-3.
        let first = (0..20_000)
            .map(|k| k as f32 * 1e-3)
            .find(|&t| scene.distance(ray.origin + dir * t, level) <= 0.0);
        match (c, first) {
            (Some(c), Some(first)) => {
                hits += 1;
                assert!(
                    c.t <= first + 2e-3,
                    "ray {i}: hit at {} past the crossing at {first}",
                    c.t
                );
                assert!(
                    (c.t - first).abs() < 0.02,
                    "ray {i}: hit at {}, crossing at {first}",
                    c.t
                );
            }
            (None, None) => {}
            other => panic!("ray {i}: {other:?}"),
        }
        for g in &on_gpu {
            match (c, g[i]) {
                (Some(c), Some(g)) => assert!(
                    (c.t - g.t).abs() < 1e-3 * (1.0 + c.t),
                    "ray {i}: {} vs {}",
                    g.t,
                    c.t
                ),
                (None, None) => {}
                other => panic!("ray {i}: {other:?}"),
            }
        }
    }
    assert!(hits > 60, "{hits} of 150 rays hit");
}

/// Groups of models among leaves (a smooth-unioned pair, a model carved by a model and a box,
/// an offset union with a primitive, a shell, a model carved by a blended group), the groups
/// first in the tree: the compiled program takes the union's leaves first and keeps the tree's
/// leaf numbers, and the GPU code skips each group, and each model that is a union's or a
/// difference's right operand, by its floor where it cannot change its parent. Distances,
/// gradients and deciding leaves, and rays at two levels agree with the CPU's, which evaluates
/// everything.
#[test]
fn groups_of_models_skipped_by_their_floors_match_the_cpu() {
    let model = Arc::new(sphere_model(1.0));
    let spot =
        Arc::new(NeuralSdf::load(crate::support::example_model("spot.nglod.safetensors")).unwrap());
    let at = |m: &Arc<NeuralSdf>, x: f32, z: f32, scale: f32| {
        SceneNode::model(
            m.clone(),
            Transform::new(Vec3::new(x, 0.0, z), Quat::from_rotation_y(x + z), scale),
        )
    };
    let prim = |p, at: Vec3| SceneNode::primitive(p, Transform::from_translation(at));
    let ball = |at: Vec3| prim(Primitive::Sphere { radius: 0.3 }, at);
    let scene = Scene::new(SceneNode::Union(vec![
        SceneNode::SmoothUnion {
            k: 0.2,
            children: vec![at(&spot, -3.0, -1.0, 0.5), at(&model, -2.4, -1.0, 0.3)],
        },
        SceneNode::Difference(vec![
            at(&spot, 0.0, -1.2, 0.5),
            at(&model, 0.3, -1.0, 0.15),
            prim(
                Primitive::Box {
                    half_extents: Vec3::splat(0.25),
                },
                Vec3::new(-0.3, 0.3, -1.2),
            ),
        ]),
        SceneNode::Offset {
            r: 0.05,
            child: Box::new(SceneNode::Union(vec![
                at(&model, 2.5, -1.0, 0.3),
                ball(Vec3::new(3.2, 0.0, -1.0)),
            ])),
        },
        SceneNode::Shell {
            t: 0.04,
            child: Box::new(at(&spot, -1.5, 1.3, 0.5)),
        },
        SceneNode::Difference(vec![
            at(&spot, 1.5, 1.3, 0.5),
            SceneNode::SmoothUnion {
                k: 0.1,
                children: vec![at(&model, 1.8, 1.5, 0.15), ball(Vec3::new(1.2, 0.3, 1.3))],
            },
        ]),
        prim(
            Primitive::Box {
                half_extents: Vec3::new(4.5, 0.05, 3.0),
            },
            Vec3::new(0.0, -0.6, 0.0),
        ),
    ]))
    .unwrap();
    // The slab first, then the groups; leaf numbers in tree order.
    use sdf_nn::serve::scene::Instruction;
    assert_eq!(
        &scene.program()[..4],
        &[
            Instruction::Leaf(11),
            Instruction::Leaf(0),
            Instruction::Leaf(1),
            Instruction::SmoothUnion(0.2),
        ]
    );
    assert_eq!(scene.leaf_path(0), Some("root.children[0].children[0]"));
    let wgsl = scene
        .wgsl_with_prefix(0, "s", &gpu().device().limits())
        .unwrap();
    // In each of `s_distance`, `s_sample` and `s_trace`: the five groups, the blended group
    // carved from the last spot, and the two models right of a smooth union and a difference.
    assert_eq!(wgsl.matches("where their floor says").count(), 24);
    let on_gpu = GpuScene::new(gpu(), &scene).unwrap();
    // The scene's box, and inside and around the two carved spots.
    let mut points = random_points(3000, 4.0, 21);
    for (seed, centre) in [
        (23, Vec3::new(0.0, 0.0, -1.2)),
        (24, Vec3::new(1.5, 0.0, 1.3)),
    ] {
        points.extend(
            random_points(1000, 0.5, seed)
                .into_iter()
                .map(|p| p + centre),
        );
    }
    for level in [0.0, 0.05] {
        // Gradients within 1e-3 where they are unit vectors.
        let same_leaf =
            samples_match_the_cpu(&scene, &on_gpu, &points, level, (2e-5, 5e-4), "groups");
        assert!(
            same_leaf > 4980,
            "{same_leaf} of 5000 deciding leaves agree"
        );
        let rays: Vec<Ray> = random_points(300, 3.0, 22)
            .into_iter()
            .map(|t| Ray {
                origin: Vec3::new(0.0, 6.0, 8.0),
                direction: Vec3::new(t.x, -0.5, t.z * 0.5) - Vec3::new(0.0, 6.0, 8.0),
                max_distance: 30.0,
            })
            .collect();
        let options = TraceOptions {
            level,
            ..TraceOptions::default()
        };
        let cpu = scene.trace_rays(&rays, &options).unwrap();
        let hits = on_gpu.trace_rays(&rays, &options).unwrap();
        let shared = hits_in_the_cpus_steps(&cpu, &hits, "groups");
        assert!(shared > 150, "{shared} of 300 rays hit");
    }
}

/// SIREN leaves, with their activations in scratch (the default on CPU adapters) on both
/// kernels, and in private arrays (the default on GPUs), against the CPU: distances,
/// gradients, ray hits and closest points. A random SIREN under a union with a sphere, placed
/// twice, so that the two instances and the kernels' slots share one scratch.
#[test]
fn siren_leaves_match_the_cpu_in_both_activation_forms() {
    use sdf_nn::{GpuOptions, SirenActivations};
    let siren = sdf_nn::Siren::new(
        sdf_nn::SirenConfig {
            width: 8,
            hidden_layers: 2,
            omega0: 30.0,
        },
        5,
    )
    .unwrap();
    let model = Arc::new(
        NeuralSdf::from_model_file(
            siren.to_model_file(Normalization::identity(), serde_json::Value::Null),
        )
        .unwrap(),
    );
    let scene = Scene::new(SceneNode::Union(vec![
        SceneNode::model(model.clone(), Transform::from_translation(Vec3::X * -1.2)),
        SceneNode::model(
            model.clone(),
            Transform::new(Vec3::X * 1.2, Quat::from_rotation_y(0.7), 0.8),
        ),
        SceneNode::primitive(
            Primitive::Sphere { radius: 0.5 },
            Transform::from_translation(Vec3::Y * 1.5),
        ),
    ]))
    .unwrap();
    let private = GpuContext::with_options(&GpuOptions {
        siren_activations: Some(SirenActivations::Private),
        ..GpuOptions::from_env().unwrap()
    })
    .unwrap();
    let scratch = GpuContext::with_options(&GpuOptions {
        siren_activations: Some(SirenActivations::Scratch),
        ..GpuOptions::from_env().unwrap()
    })
    .unwrap();
    let points = random_points(500, 2.5, 31);
    let rays: Vec<Ray> = random_points(120, 1.5, 32)
        .into_iter()
        .map(|t| Ray {
            origin: Vec3::new(0.0, 0.5, -6.0),
            direction: t - Vec3::new(0.0, 0.5, -6.0),
            max_distance: 20.0,
        })
        .collect();
    // A random SIREN's slopes reach tens: small steps.
    // Its surface at the level of its median over its box, which it crosses there.
    let mut values = model.eval_cpu(&random_points(1001, 1.0, 30));
    values.sort_by(f32::total_cmp);
    let level = values[500];
    let trace = TraceOptions {
        max_steps: 4000,
        level,
        ..TraceOptions::default()
    };
    let cpu_hits = scene.trace_rays(&rays, &trace).unwrap();
    let on_sirens = cpu_hits.iter().flatten().filter(|h| h.leaf < 2).count();
    assert!(on_sirens > 40, "{on_sirens} of 120 rays hit the SIRENs");
    let forms = [
        (&private, QueryKernel::PerInvocation, "private"),
        (&scratch, QueryKernel::PerInvocation, "scratch"),
        (
            &scratch,
            QueryKernel::PerSubgroup,
            "scratch, one subgroup per element",
        ),
    ];
    for (gpu, kernel, what) in forms {
        let mut on_gpu = GpuScene::new(gpu, &scene).unwrap();
        on_gpu.set_kernel(Some(kernel)).unwrap();
        recorded_parts_match_the_plain_calls(gpu, &mut on_gpu, &points, level, what);
        // The SIREN's gradients reach ω0 = 30: compared relative to their length.
        let compared = samples_match_the_cpu(&scene, &on_gpu, &points, level, (2e-5, 1e-4), what);
        assert!(compared > 450, "{what}: {compared} gradients compared");
        let gpu_hits = on_gpu.trace_rays(&rays, &trace).unwrap();
        let hits = hits_at_the_same_t(&cpu_hits, &gpu_hits, what);
        assert!(
            hits.len() > 30,
            "{what}: only {} of 120 rays hit",
            hits.len()
        );
        for (i, g) in on_gpu
            .closest_points(
                &points[..100],
                &ProjectOptions {
                    level,
                    ..ProjectOptions::default()
                },
            )
            .unwrap()
            .iter()
            .enumerate()
        {
            if g.converged {
                let d = scene.distance(g.point, level);
                assert!(
                    d.abs() < 1e-4,
                    "{what}, point {i}: projected to distance {d}"
                );
            }
        }
    }
}

/// Caller-owned buffers recorded with more elements than one dispatch takes (the scratch's
/// slots, here a part of 64 elements): `record` splits them into dispatches, and the answers
/// are the plain call's.
fn recorded_parts_match_the_plain_calls(
    gpu: &GpuContext,
    on_gpu: &mut GpuScene,
    points: &[Vec3],
    level: f32,
    what: &str,
) {
    use sdf_nn::serve::scene::SceneQueryParams;
    let plain = on_gpu.distances(points, level).unwrap();
    on_gpu.set_max_part(64);
    let kind = SceneQueryKind::Distance;
    let buffers = on_gpu.create_buffers(kind, points.len() as u32).unwrap();
    let inputs: Vec<[f32; 4]> = points.iter().map(|p| p.extend(0.0).to_array()).collect();
    gpu.queue()
        .write_buffer(&buffers.inputs, 0, bytemuck::cast_slice(&inputs));
    let mut encoder = gpu.device().create_command_encoder(&Default::default());
    let params = SceneQueryParams::at_level(level);
    on_gpu
        .record(&mut encoder, &buffers, points.len() as u32, &params)
        .unwrap();
    gpu.queue().submit([encoder.finish()]);
    let recorded: Vec<f32> = gpu.read_back(&buffers.outputs).unwrap();
    assert_eq!(
        recorded[..points.len()],
        plain[..],
        "{what}: recorded in parts"
    );
    on_gpu.set_max_part(u32::MAX);
}
