//! sdf-geom benchmarks: BVH build, cleaning, BVH and surface sampling of a 1.3 M-triangle mesh,
//! the NGLOD epoch mix (1e5 uniform + 2e5 near-surface + 2e5
//! surface points, all signed), and 1e5 Poisson-disk samples.
//!
//! `cargo bench -p hwsdf --bench geom`. Meshes come from `$HWSDF_MESHES`, else `../shared/meshes`
//! next to the repository; benchmarks whose mesh is missing are skipped.

use std::path::PathBuf;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use hwsdf::geom::{Mesh, SignedDistance, load_mesh, sample};

fn mesh_dir() -> PathBuf {
    std::env::var_os("HWSDF_MESHES")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/meshes"))
}

fn load(name: &str) -> Option<Mesh> {
    let path = mesh_dir().join(name);
    match load_mesh(&path) {
        Ok((m, _)) => Some(m.normalized().0),
        Err(e) => {
            eprintln!("skipping {name}: {e}");
            None
        }
    }
}

/// The NGLOD epoch mix in the normalised box, with the project's seeds.
pub fn epoch_points(mesh: &Mesh) -> Vec<Vec3> {
    let mut p = sample::uniform_box(100_000, 1);
    p.extend(sample::near_surface(
        mesh,
        200_000,
        sample::DEFAULT_SIGMA,
        2,
    ));
    p.extend(sample::surface(mesh, 200_000, 3).points);
    p
}

fn merged(a: &Mesh, b: &Mesh) -> Mesh {
    let off = a.vertices.len() as u32;
    Mesh {
        vertices: a.vertices.iter().chain(&b.vertices).copied().collect(),
        triangles: a
            .triangles
            .iter()
            .copied()
            .chain(b.triangles.iter().map(|t| t.map(|i| i + off)))
            .collect(),
    }
}

fn benches(c: &mut Criterion) {
    let bunny = load("stanford-bunny.obj");
    let armadillo = load("armadillo.obj");
    let fandisk = load("fandisk.obj");

    let mut g = c.benchmark_group("bvh_build");
    g.sample_size(20).measurement_time(Duration::from_secs(5));
    let mut build_cases: Vec<(String, &Mesh)> = Vec::new();
    if let Some(m) = &bunny {
        build_cases.push(("stanford-bunny 69k".into(), m));
    }
    if let Some(m) = &armadillo {
        build_cases.push(("armadillo 86k".into(), m));
    }
    let big = match (&armadillo, &fandisk) {
        (Some(a), Some(f)) => Some(merged(a, f)),
        _ => None,
    };
    if let Some(m) = &big {
        build_cases.push((
            format!("armadillo+fandisk {}k", m.triangles.len() / 1000),
            m,
        ));
    }
    for (name, m) in &build_cases {
        g.bench_function(BenchmarkId::from_parameter(name), |b| {
            b.iter(|| SignedDistance::new(m).expect("valid mesh"))
        });
    }
    g.finish();

    let mut g = c.benchmark_group("nglod_epoch_signed");
    g.sample_size(10).measurement_time(Duration::from_secs(15));
    g.throughput(Throughput::Elements(500_000));
    for (name, m) in [("stanford-bunny", &bunny), ("armadillo", &armadillo)] {
        let Some(m) = m else { continue };
        let sdf = SignedDistance::new(m).expect("valid mesh");
        let pts = epoch_points(m);
        g.bench_function(BenchmarkId::from_parameter(name), |b| {
            b.iter(|| sdf.signed_distance_batch(&pts))
        });
    }
    g.finish();

    // A scan-sized mesh, made here: the shared meshes stop at 86 k triangles, and users bring
    // millions. An icosphere's triangles are more regular than a scan's, so this tracks the
    // code's scaling rather than a particular scan.
    let sphere = Mesh::icosphere(1.0, 8);
    let mut g = c.benchmark_group(format!("large_mesh_{}k", sphere.triangles.len() / 1000));
    g.sample_size(10).measurement_time(Duration::from_secs(15));
    g.bench_function("clean", |b| {
        b.iter(|| Mesh::from_raw(sphere.vertices.clone(), sphere.triangles.clone()))
    });
    g.bench_function("bvh_build", |b| {
        b.iter(|| SignedDistance::new(&sphere).expect("valid mesh"))
    });
    g.bench_function("surface_samples_1e6", |b| {
        b.iter(|| sample::surface(&sphere, 1_000_000, 3))
    });
    g.finish();

    let mut g = c.benchmark_group("poisson_disk_1e5");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    if let Some(m) = &bunny {
        g.bench_function("stanford-bunny", |b| {
            b.iter(|| sample::poisson_disk(m, 100_000, 4))
        });
    }
    g.finish();
}

criterion_group!(geom, benches);
criterion_main!(geom);
