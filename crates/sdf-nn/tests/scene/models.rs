//! Trained models in scenes: a model placed twice against its analytic spheres, Lipschitz
//! estimates.

use std::f32::consts::FRAC_PI_2;
use std::sync::Arc;

use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::nglod::{Encoding, LevelStorage};
use sdf_nn::serve::scene::{
    ProjectOptions, Ray, Scene, SceneError, SceneNode, TraceOptions, Transform,
};
use sdf_nn::{NeuralSdf, Nglod, NglodConfig, Normalization};

use crate::assert_close;

/// Sphere radius of the test models, in their normalised cube.
pub(crate) const MODEL_RADIUS: f32 = 0.6;

/// Mesh coordinates that are not the normalised ones: the model's sphere has its centre at
/// `center` and radius `MODEL_RADIUS / scale` = 2.4 mesh units.
pub(crate) fn normalization() -> Normalization {
    Normalization {
        center: Vec3::new(1.0, -2.0, 0.5).as_dvec3(),
        scale: 0.25,
    }
}

/// An NGLOD model holding (up to trilinear interpolation and f16 storage) a sphere's SDF times
/// `slope`: no training.
pub(crate) fn sphere_model(slope: f32) -> NeuralSdf {
    let model = Nglod::from_sdf(32, move |p| slope * (p.length() - MODEL_RADIUS)).unwrap();
    NeuralSdf::from_model_file(model.to_model_file(normalization(), serde_json::Value::Null))
        .unwrap()
}

/// A hash grid holding a sphere's SDF times `slope` plus small noise, no training: a level of
/// 32 cells that fits its table of 2¹⁶ entries holds the SDF at its vertices, a level of 64
/// cells hashed into the table holds noise of ±0.005, and the MLP passes their sum through
/// (`relu(z₀ + z₁ + 10) − 10`). Both of the hash grid's lookups, concatenated.
pub(crate) fn hashed_sphere_model(slope: f32) -> NeuralSdf {
    let config = NglodConfig {
        resolutions: vec![32, 64],
        feature_dim: 1,
        hidden: 1,
        seed: 0,
        sparse_levels: 0,
        band_cells: 0,
        encoding: Encoding::Hashed {
            log2_table_size: 16,
        },
    };
    assert_eq!(config.storage(1), LevelStorage::Hashed(1 << 16));
    let s = 33;
    let mut rng = Pcg64::seed_from_u64(4);
    let mut params: Vec<f32> = (0..s * s * s)
        .map(|i| {
            let v = Vec3::new((i / (s * s)) as f32, ((i / s) % s) as f32, (i % s) as f32);
            slope * ((v * (2.0 / 32.0) - 1.0).length() - MODEL_RADIUS)
        })
        .collect();
    params.extend((0..1 << 16).map(|_| rng.random_range(-0.005..0.005)));
    params.extend([1.0, 1.0, 10.0, 1.0, -10.0]);
    let model = Nglod::from_params(config, params).unwrap();
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
    let spheres = [place_a, place_b].map(|t| (t.apply(n.center.as_vec3()), t.scale * mesh_radius));
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
    let c = Vec3::X * 20.0 + n.center.as_vec3();
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
    // Outside its box the model's distance is steeper than its network: √(1 + 4²).
    assert_eq!(scene.lipschitz(), 17f32.sqrt());
    assert!(matches!(
        scene.set_model_lipschitz(1, 0.0),
        Err(SceneError::Lipschitz { .. })
    ));
    assert!(matches!(
        scene.set_model_lipschitz(5, 2.0),
        Err(SceneError::Lipschitz { .. })
    ));
}

/// A bound given by the caller is the network's in its box; outside it, where the served
/// distance continues by the distance to the box, slopes reach √(1 + b²): a ray from outside
/// towards a small sphere near the box's face stops on it, where a first step by b = 1 (1.69
/// from the ray's origin) jumped past it.
#[test]
fn a_given_bound_keeps_rays_from_outside_the_box_on_the_surface() {
    let centre = Vec3::new(0.9, 0.0, 0.0);
    let radius = 0.05;
    let model = Nglod::from_sdf(128, move |p| (p - centre).length() - radius).unwrap();
    let identity = Normalization {
        center: glam::DVec3::ZERO,
        scale: 1.0,
    };
    let sdf =
        NeuralSdf::from_model_file(model.to_model_file(identity, serde_json::Value::Null)).unwrap();
    let mut scene = Scene::new(SceneNode::model(Arc::new(sdf), Transform::IDENTITY)).unwrap();
    scene.set_model_lipschitz(0, 1.0).unwrap();
    assert_eq!(scene.model_lipschitz(0), Some(2f32.sqrt()));
    let origin = Vec3::new(1.5, 1.5, 0.0);
    let ray = Ray {
        origin,
        direction: (centre - origin).normalize(),
        max_distance: 10.0,
    };
    let hit = scene
        .trace_ray(&ray, &TraceOptions::default())
        .unwrap()
        .expect("the ray hits the sphere");
    assert_close(
        hit.t,
        f64::from((centre - origin).length() - radius),
        0.01,
        "ray from outside the box",
    );
}

/// The guarantee, observed: on untrained networks of both architectures (a random SIREN, whose
/// slopes are nothing like a distance's), no pair of points, inside the box or out, differs by
/// more than the estimate times their distance.
#[test]
fn lipschitz_estimates_bound_observed_slopes() {
    use sdf_nn::{Siren, SirenConfig};
    let n = normalization();
    let siren = Siren::new(SirenConfig::small(), 3).unwrap();
    let siren = NeuralSdf::from_model_file(siren.to_model_file(n, serde_json::Value::Null));
    let models = [Arc::new(siren.unwrap()), Arc::new(sphere_model(2.0))];
    let nodes = models
        .iter()
        .map(|m| SceneNode::model(m.clone(), Transform::IDENTITY))
        .collect();
    let scene = Scene::new(SceneNode::Union(nodes)).unwrap();
    let mut rng = Pcg64::seed_from_u64(11);
    for (i, model) in models.iter().enumerate() {
        let l = scene.model_lipschitz(i).unwrap() as f64;
        // Pairs a short step apart, over 1.5 times the box (mesh units: the box is ±4 about
        // the centre).
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..20_000 {
            let p = n.center.as_vec3()
                + Vec3::new(
                    rng.random_range(-6.0..6.0),
                    rng.random_range(-6.0..6.0),
                    rng.random_range(-6.0..6.0),
                );
            let step = Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ) * 0.05;
            a.push(p);
            b.push(p + step);
        }
        let (da, db) = (model.eval_cpu(&a), model.eval_cpu(&b));
        let steepest = a
            .iter()
            .zip(&b)
            .zip(da.iter().zip(&db))
            .map(|((p, q), (x, y))| (x - y).abs() as f64 / p.distance(*q) as f64)
            .fold(0.0, f64::max);
        assert!(
            steepest <= l,
            "model {i}: slope {steepest} over the estimate {l}"
        );
        // And the estimate is not absurdly loose: within the safety factor and the box term.
        assert!(
            steepest > 0.5 * l / SAFETY_FOR_TESTS,
            "model {i}: {steepest} vs {l}"
        );
    }
}

/// The per-cell floors the GPU's culling reads lie below the network at 2·10⁵ random points
/// of its cube and on its cells' faces, for an exact sphere and the example's trained spot, and
/// are tight: far from the surface they are within a few cells' slope of the value, where the
/// box's one floor is not; and a point is never farther from a cell's nine samples than
/// `COVER` (which half a cell's side was not).
#[test]
fn cell_floors_bound_the_network_tightly() {
    use sdf_nn::serve::scene::lipschitz::{COVER, GRID};
    let spot =
        Arc::new(NeuralSdf::load(crate::support::example_model("spot.nglod.safetensors")).unwrap());
    for (name, model) in [("sphere", Arc::new(sphere_model(1.0))), ("spot", spot)] {
        let scene = Scene::new(SceneNode::model(model.clone(), Transform::IDENTITY)).unwrap();
        let floors = scene.model_cell_floors(0).unwrap();
        let mut rng = Pcg64::seed_from_u64(41);
        let h = 2.0 / GRID as f32;
        let mut points: Vec<Vec3> = (0..200_000)
            .map(|_| Vec3::from(std::array::from_fn(|_| rng.random_range(-1.0f32..1.0))))
            .collect();
        // Points on the cells' faces and edges, where two cells meet.
        points.extend((0..20_000).map(|_| {
            let on = |x: f32| ((x + 1.0) / h).round() * h - 1.0;
            let p = Vec3::from(std::array::from_fn(|_| rng.random_range(-1.0f32..1.0)));
            Vec3::new(on(p.x), p.y, on(p.z))
        }));
        let values = model.eval_cpu_normalized(&points);
        let (mut below, mut far, mut far_gap) = (0, 0, 0.0f64);
        for (p, v) in points.iter().zip(&values) {
            let floor = floors.at(*p);
            below += usize::from(*v < floor);
            if *v > 0.3 {
                far += 1;
                far_gap += f64::from(v - floor);
            }
        }
        assert_eq!(below, 0, "{name}: {below} values below their cell's floor");
        let mean = far_gap / far as f64;
        // Two cells of slope at the estimate's worst, against the box's floor (≤ 0).
        assert!(
            mean < 0.15,
            "{name}: floors {mean} below the value far from the surface"
        );
        assert!(floors.min() <= values.iter().copied().fold(f32::INFINITY, f32::min));
    }
    // The covering radius: random points of a cell against its vertices and centre.
    let mut rng = Pcg64::seed_from_u64(42);
    let h = 2.0 / GRID as f32;
    let farthest = (0..100_000)
        .map(|_| {
            let p = Vec3::from(std::array::from_fn(|_| rng.random_range(0.0..h)));
            let centre = p.distance(Vec3::splat(h / 2.0));
            (0..8)
                .map(|c| {
                    let v = Vec3::new((c >> 2) as f32, (c >> 1 & 1) as f32, (c & 1) as f32);
                    p.distance(v * h)
                })
                .fold(centre, f32::min)
        })
        .fold(0.0f32, f32::max);
    assert!(farthest <= COVER, "{farthest} > {COVER}");
    assert!(
        farthest > h / 2.0 * 1.05,
        "{farthest}: half a side would do"
    );
}

/// [`sdf_nn::serve::scene::lipschitz::SAFETY`], as f64.
const SAFETY_FOR_TESTS: f64 = sdf_nn::serve::scene::lipschitz::SAFETY as f64;

/// The value floor the GPU's culling uses lies below every value of the network on a grid
/// finer than its own, and is tight (within a cell's worth of slope of the minimum); setting a
/// Lipschitz bound measures the cells' floors again (the smallest stays at the weights'
/// interval bound, which for a baked sphere is its smallest stored value).
#[test]
fn value_floors_bound_the_network_tightly() {
    let model = Arc::new(sphere_model(1.0));
    let mut scene = Scene::new(SceneNode::model(model.clone(), Transform::IDENTITY)).unwrap();
    let floor = scene.model_value_floor(0).unwrap();
    let side = 57;
    let grid: Vec<Vec3> = (0..side * side * side)
        .map(|i| {
            let at = |k: usize| -1.0 + 2.0 * k as f32 / (side - 1) as f32;
            Vec3::new(at(i % side), at(i / side % side), at(i / side / side))
        })
        .collect();
    let min = model
        .eval_cpu_normalized(&grid)
        .into_iter()
        .fold(f32::INFINITY, f32::min);
    assert!(floor <= min, "floor {floor} above the minimum {min}");
    assert!(
        floor > min - 0.2,
        "floor {floor} far below the minimum {min}"
    );
    assert!(scene.model_value_floor(1).is_none());
    assert!(scene.model_cell_floors(1).is_none());
    let before = scene.model_cell_floors(0).unwrap().clone();
    scene.set_model_lipschitz(0, 10.0).unwrap();
    let after = scene.model_cell_floors(0).unwrap();
    // A far cell: its nine samples less 10 instead of about 1.25 times the cover.
    let corner = Vec3::splat(0.98);
    let (was, is) = (before.at(corner), after.at(corner));
    assert!(is < was - 0.25, "{is} vs {was}");
    assert!(scene.model_value_floor(0).unwrap() >= floor - 1e-6);
}
