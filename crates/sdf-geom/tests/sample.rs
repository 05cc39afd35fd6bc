//! Samplers: determinism per seed, distributions, Poisson-disk spacing.

mod common;

use common::data;
use glam::Vec3;
use sdf_geom::sample::{self, min_pair_distance};
use sdf_geom::{Aabb, Mesh, SignedDistance, load_mesh};

fn unit(name: &str) -> Mesh {
    load_mesh(data(name)).unwrap().0.normalized().0
}

#[test]
fn samplers_are_deterministic_per_seed() {
    let mesh = unit("suzanne.obj");
    assert_eq!(sample::uniform_box(100, 1), sample::uniform_box(100, 1));
    assert_ne!(sample::uniform_box(100, 1), sample::uniform_box(100, 2));
    assert_eq!(
        sample::surface(&mesh, 100, 1),
        sample::surface(&mesh, 100, 1)
    );
    assert_ne!(
        sample::surface(&mesh, 100, 1).points,
        sample::surface(&mesh, 100, 2).points
    );
    assert_eq!(
        sample::near_surface(&mesh, 100, 0.01, 1),
        sample::near_surface(&mesh, 100, 0.01, 1)
    );
    assert_ne!(
        sample::near_surface(&mesh, 100, 0.01, 1),
        sample::near_surface(&mesh, 100, 0.01, 2)
    );
    let a = sample::poisson_disk(&mesh, 500, 3);
    let b = sample::poisson_disk(&mesh, 500, 3);
    assert_eq!(a, b);
    assert_ne!(
        a.samples.points,
        sample::poisson_disk(&mesh, 500, 4).samples.points
    );
    // Same result whatever the thread count.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let c = pool.install(|| sample::poisson_disk(&mesh, 500, 3));
    assert_eq!(a, c);
}

/// Seeds and samplers draw unrelated numbers: the pool's surface points of seed 0 were the
/// near-surface points (before their offsets) of seed 3, one generator seeded `seed ^ role`.
#[test]
fn nearby_seeds_and_samplers_share_no_stream() {
    let mesh = unit("suzanne.obj");
    let n = 64;
    let mut seen = std::collections::HashMap::new();
    for seed in 0..8u64 {
        let draws = [
            ("surface", sample::surface(&mesh, n, seed).points),
            // σ 0: the near-surface points' surface points themselves.
            ("near", sample::near_surface(&mesh, n, 0.0, seed)),
            (
                "poisson",
                sample::poisson_disk(&mesh, n, seed).samples.points,
            ),
        ];
        for (name, points) in draws {
            for p in points {
                let key = p.to_array().map(f32::to_bits);
                if let Some(first) = seen.insert(key, (name, seed)) {
                    assert_eq!(first, (name, seed), "{name} of seed {seed} drew {p}");
                }
            }
        }
    }
    // The sub-seeds of nearby seeds and streams are all distinct.
    let mut subs = std::collections::HashSet::new();
    for seed in 0..64 {
        for stream in 0..64 {
            assert!(
                subs.insert(sample::sub_seed(seed, stream)),
                "{seed} {stream}"
            );
        }
    }
}

#[test]
fn uniform_box_covers_the_box() {
    let p = sample::uniform_box(20_000, 5);
    assert_eq!(p.len(), 20_000);
    assert!(p.iter().all(|p| p.abs().max_element() <= 1.0));
    let mean = p.iter().copied().sum::<Vec3>() / p.len() as f32;
    assert!(mean.length() < 0.03, "{mean}");
    // Each octant gets about 1/8.
    let octant0 = p.iter().filter(|p| p.cmpgt(Vec3::ZERO).all()).count();
    assert!((octant0 as f32 / 20_000.0 - 0.125).abs() < 0.01);

    let b = Aabb {
        min: Vec3::new(2.0, 3.0, 4.0),
        max: Vec3::new(2.5, 3.1, 6.0),
    };
    let q = sample::uniform_in(&b, 1000, 1);
    assert!(
        q.iter()
            .all(|p| p.cmpge(b.min).all() && p.cmple(b.max).all())
    );
}

#[test]
fn surface_samples_lie_on_the_surface_with_face_normals() {
    let mesh = unit("teapot.obj");
    let sdf = SignedDistance::new(&mesh).unwrap();
    let s = sample::surface(&mesh, 5000, 8);
    assert_eq!(
        (s.points.len(), s.normals.len(), s.triangles.len()),
        (5000, 5000, 5000)
    );
    for ((p, n), t) in s.points.iter().zip(&s.normals).zip(&s.triangles) {
        assert!(sdf.unsigned_distance(*p) < 1e-5);
        assert!((n.length() - 1.0).abs() < 1e-5);
        let [a, b, c] = mesh.corners(&mesh.triangles[*t as usize]).unwrap();
        assert!((b - a).cross(c - a).normalize().dot(*n) > 0.9999);
    }
    // Area weighting: the share of samples on a set of triangles matches its share of area.
    let half = mesh.triangles.len() / 2;
    let area_first: f64 = Mesh {
        vertices: mesh.vertices.clone(),
        triangles: mesh.triangles[..half].to_vec(),
    }
    .area();
    let share = s.triangles.iter().filter(|&&t| (t as usize) < half).count() as f64 / 5000.0;
    assert!((share - area_first / mesh.area()).abs() < 0.03, "{share}");
    assert!(sample::surface(&Mesh::default(), 10, 1).is_empty());
}

#[test]
fn near_surface_offsets_have_sigma() {
    let mesh = unit("spot.obj");
    let sdf = SignedDistance::new(&mesh).unwrap();
    let sigma = 0.01;
    let p = sample::near_surface(&mesh, 4000, sigma, 2);
    assert_eq!(p.len(), 4000);
    // The offsets from the underlying surface points (the same draw with σ 0) are N(0, σ²) on
    // each axis, independently: each axis's std within 4 % (4.5 standard errors at 4000), its
    // kurtosis within 0.35 of a normal's 3 (uniform noise of the same σ has 1.8), and the axes'
    // correlations below 4/√n.
    let s = sample::near_surface(&mesh, 4000, 0.0, 2);
    let offsets: Vec<[f64; 3]> = p
        .iter()
        .zip(&s)
        .map(|(a, b)| (*a - *b).as_dvec3().to_array())
        .collect();
    let n = offsets.len() as f64;
    let moment = |f: &dyn Fn(&[f64; 3]) -> f64| offsets.iter().map(f).sum::<f64>() / n;
    for axis in 0..3 {
        let var = moment(&|o| o[axis] * o[axis]);
        let std = var.sqrt();
        assert!(
            (std / f64::from(sigma) - 1.0).abs() < 0.04,
            "axis {axis}: std {std}"
        );
        let kurtosis = moment(&|o| o[axis].powi(4)) / (var * var);
        assert!(
            (kurtosis - 3.0).abs() < 0.35,
            "axis {axis}: kurtosis {kurtosis}"
        );
        let other = (axis + 1) % 3;
        let correlation =
            moment(&|o| o[axis] * o[other]) / (var * moment(&|o| o[other] * o[other])).sqrt();
        assert!(
            correlation.abs() < 4.0 / n.sqrt(),
            "axes {axis}, {other}: {correlation}"
        );
    }
    // And the points are within a few σ of the surface.
    assert!(p.iter().all(|q| sdf.unsigned_distance(*q) < 6.0 * sigma));
}

#[test]
fn poisson_disk_keeps_its_minimum_distance() {
    for name in ["suzanne.obj", "spot.obj"] {
        let mesh = unit(name);
        let n = 2000;
        let pd = sample::poisson_disk(&mesh, n, 11);
        let pts = &pd.samples.points;
        assert_eq!(pts.len(), n);
        assert_eq!(pd.samples.normals.len(), n);
        // The reported minimum distance is the true one (brute force over all pairs)...
        let mut brute = f32::INFINITY;
        for i in 0..pts.len() {
            for j in i + 1..pts.len() {
                brute = brute.min(pts[i].distance(pts[j]));
            }
        }
        assert_eq!(pd.min_distance, brute.min(2.0 * pd.target_radius), "{name}");
        // ...and sample elimination keeps it a good fraction of the packing radius, far above what
        // independent uniform samples give.
        assert!(
            pd.min_distance > 0.4 * pd.target_radius,
            "{name}: min distance {} vs r_max {}",
            pd.min_distance,
            pd.target_radius
        );
        let uniform = sample::surface(&mesh, n, 11).points;
        assert!(min_pair_distance(&uniform, 2.0 * pd.target_radius) < 0.2 * pd.min_distance);
        // Points lie on the surface.
        let sdf = SignedDistance::new(&mesh).unwrap();
        assert!(pts.iter().all(|p| sdf.unsigned_distance(*p) < 1e-5));
    }
    // Yuksel's 5 candidates per sample keep at least as much spacing as the default 3.
    let mesh = unit("suzanne.obj");
    let k3 = sample::poisson_disk(&mesh, 1000, 5);
    let k5 = sample::poisson_disk_with(&mesh, 1000, 5, 5);
    assert_eq!(k5.samples.len(), 1000);
    assert!(
        k5.min_distance >= 0.9 * k3.min_distance,
        "{} vs {}",
        k5.min_distance,
        k3.min_distance
    );
    let empty = sample::poisson_disk(&Mesh::default(), 10, 1);
    assert!(empty.samples.is_empty());
}
