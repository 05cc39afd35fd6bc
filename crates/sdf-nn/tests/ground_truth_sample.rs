//! The GPU sampler (`sdf_nn::ground_truth::GpuSampler`) against its CPU reference
//! (`SampleTable::draw_cpu`) and against the distributions it must draw: counts, determinism,
//! the near-surface σ, the surface points' area distribution (chi-square), points on their
//! triangles, and the labels of a draw against the CPU's `SignedDistance`. One test binary so
//! every test shares one device and its compiled pipelines.

#[path = "support/mod.rs"]
mod support;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance, load_mesh};
use sdf_nn::GpuContext;
use sdf_nn::ground_truth::{
    GpuGroundTruth, GpuSampler, LabelKind, LabelledDraw, SampleError, SampleSpec, SampleTable,
};
use support::test_data;

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

fn spot() -> Mesh {
    load_mesh(test_data("spot.obj")).unwrap().0.normalized().0
}

/// Spot, its exact signed distance on the CPU and on the GPU, and its GPU sampler.
fn spot_on_the_gpu(gpu: &GpuContext) -> (Mesh, SignedDistance, GpuGroundTruth, GpuSampler) {
    let mesh = spot();
    let cpu = SignedDistance::new(&mesh).unwrap();
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    let sampler = GpuSampler::new(gpu, &SampleTable::new(&mesh).unwrap()).unwrap();
    (mesh, cpu, gt, sampler)
}

fn spec(uniform: u32, near: u32, surface: u32, seed: u64) -> SampleSpec {
    SampleSpec {
        uniform,
        near,
        surface,
        sigma: 0.01,
        seed,
        stream: 0,
        shuffle: true,
    }
}

/// The square [-1, 1]² at z = 0, two triangles.
fn plane() -> Mesh {
    Mesh {
        vertices: vec![
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
    }
}

/// Twelve disjoint right triangles whose areas double from one to the next (1 : 2048), in a
/// shuffled order, and a zero-area one that must never be drawn.
fn ladder() -> (Mesh, Vec<f64>) {
    let mut mesh = Mesh::default();
    let mut areas = Vec::new();
    for (slot, k) in [5, 0, 11, 3, 8, 1, 10, 6, 2, 9, 4, 7]
        .into_iter()
        .enumerate()
    {
        let s = 0.02 * 2f32.powf(k as f32 / 2.0);
        let o = Vec3::new(slot as f32 - 6.0, 0.0, 0.0) * 0.2;
        let base = mesh.vertices.len() as u32;
        mesh.vertices
            .extend([o, o + Vec3::new(s, 0.0, 0.0), o + Vec3::new(0.0, s, 0.0)]);
        mesh.triangles.push([base, base + 1, base + 2]);
        areas.push(f64::from(s) * f64::from(s) / 2.0);
    }
    let base = mesh.vertices.len() as u32;
    mesh.vertices
        .extend([Vec3::ZERO, Vec3::X, Vec3::new(2.0, 0.0, 0.0)]);
    mesh.triangles.push([base, base + 1, base + 2]);
    areas.push(0.0);
    (mesh, areas)
}

/// Pearson's chi-square of `counts` against probabilities `p` (zero-probability bins must be
/// empty).
fn chi_square(counts: &[u64], p: &[f64]) -> f64 {
    let n: u64 = counts.iter().sum();
    counts
        .iter()
        .zip(p)
        .map(|(&c, &p)| {
            if p == 0.0 {
                assert_eq!(c, 0, "a bin of probability 0 was hit");
                0.0
            } else {
                let e = n as f64 * p;
                (c as f64 - e).powi(2) / e
            }
        })
        .sum()
}

/// The GPU draws the CPU reference's points: the same triangles and kinds (integers), the
/// uniform points bit for bit, the others to the rounding of sqrt, log, sin and cos.
#[test]
fn gpu_draw_matches_the_cpu_reference() {
    let gpu = gpu();
    let table = SampleTable::new(&spot()).unwrap();
    let sampler = GpuSampler::new(gpu, &table).unwrap();
    let s = SampleSpec {
        stream: 3,
        ..spec(2000, 3000, 3000, 42)
    };
    let (got, got_tri) = sampler.draw_with_triangles(gpu, &s).unwrap();
    let (want, want_tri) = table.draw_cpu(&s).unwrap();
    assert_eq!(got.len(), 8000);
    assert_eq!(got_tri, want_tri);
    let (mut worst_surface, mut worst_near) = (0.0f32, 0.0f32);
    let shuffle = s.shuffle();
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        let e = (*g - *w).abs().max_element();
        match s.source(&shuffle, i as u32).0 {
            sdf_nn::ground_truth::Kind::Uniform => assert_eq!(g, w, "uniform point {i}"),
            sdf_nn::ground_truth::Kind::Surface => worst_surface = worst_surface.max(e),
            sdf_nn::ground_truth::Kind::Near => worst_near = worst_near.max(e),
        }
    }
    eprintln!("largest |GPU - CPU|: surface {worst_surface:e}, near {worst_near:e}");
    assert!(worst_surface <= 1e-6, "{worst_surface}");
    assert!(worst_near <= 1e-6, "{worst_near}");
}

/// The counts of a draw; a seed gives the same points on every call, another seed or stream
/// other points; without the shuffle the kinds come in blocks.
#[test]
fn counts_and_determinism() {
    let gpu = gpu();
    let mesh = spot();
    let table = SampleTable::new(&mesh).unwrap();
    let sampler = GpuSampler::new(gpu, &table).unwrap();
    let s = spec(300, 500, 700, 9);
    let (a, tri) = sampler.draw_with_triangles(gpu, &s).unwrap();
    assert_eq!(a.len(), 1500);
    assert_eq!(tri.iter().filter(|t| t.is_none()).count(), 300);
    assert_eq!(sampler.draw(gpu, &s).unwrap(), a);
    assert_ne!(sampler.draw(gpu, &spec(300, 500, 700, 10)).unwrap(), a);
    let other_stream = SampleSpec { stream: 1, ..s };
    assert_ne!(sampler.draw(gpu, &other_stream).unwrap(), a);
    // The kinds are spread: every run of 100 points holds each kind.
    for run in tri.chunks(100) {
        assert!(run.iter().any(|t| t.is_none()) && run.iter().any(|t| t.is_some()));
    }
    let blocks = SampleSpec {
        shuffle: false,
        ..s
    };
    let (b, tri) = sampler.draw_with_triangles(gpu, &blocks).unwrap();
    assert!(tri[..300].iter().all(|t| t.is_none()));
    assert!(tri[300..].iter().all(|t| t.is_some()));
    assert!(b[..300].iter().all(|p| p.abs().max_element() <= 1.0));
    // The shuffle permutes the same points.
    let key = |p: &Vec3| p.to_array().map(f32::to_bits);
    let mut sorted_a: Vec<_> = a.iter().map(key).collect();
    let mut sorted_b: Vec<_> = b.iter().map(key).collect();
    sorted_a.sort_unstable();
    sorted_b.sort_unstable();
    assert_eq!(sorted_a, sorted_b);
    assert!(sampler.draw(gpu, &spec(0, 0, 0, 1)).unwrap().is_empty());
}

/// On the plane z = 0 a near-surface point's z is its Gaussian offset: its standard deviation
/// is σ within 3 % (20 000 draws: the estimate's own error is 0.5 %), its mean 0 and its
/// kurtosis 3 (Gaussian, not uniform or Laplace).
#[test]
fn near_surface_offsets_have_sigma() {
    let gpu = gpu();
    let sampler = GpuSampler::new(gpu, &SampleTable::new(&plane()).unwrap()).unwrap();
    let sigma = 0.05;
    let s = SampleSpec {
        sigma,
        ..spec(0, 20_000, 0, 5)
    };
    let z: Vec<f64> = sampler
        .draw(gpu, &s)
        .unwrap()
        .iter()
        .map(|p| f64::from(p.z))
        .collect();
    let n = z.len() as f64;
    let mean = z.iter().sum::<f64>() / n;
    let var = z.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / n;
    let kurt = z.iter().map(|z| (z - mean).powi(4)).sum::<f64>() / n / (var * var);
    eprintln!(
        "σ {sigma}: mean {mean:e}, std {}, kurtosis {kurt}",
        var.sqrt()
    );
    assert!((var.sqrt() / f64::from(sigma) - 1.0).abs() < 0.03);
    assert!(mean.abs() < 4.0 * f64::from(sigma) / n.sqrt());
    assert!((kurt - 3.0).abs() < 0.2, "{kurt}");
}

/// Surface points land on triangles in proportion to area: chi-square of the hit counts on
/// twelve triangles of areas 1 : 2 : … : 2048 (11 degrees of freedom, 40 000 draws, critical
/// value 31.3 at p = 0.001; drawing triangles uniformly gives about 10⁵), never on a triangle
/// without area; within the largest triangle the points are uniform (their mean is the
/// centroid, a quarter of them in each corner triangle of half the size).
#[test]
fn surface_points_follow_the_area() {
    let gpu = gpu();
    let (mesh, areas) = ladder();
    let sampler = GpuSampler::new(gpu, &SampleTable::new(&mesh).unwrap()).unwrap();
    let (points, tri) = sampler
        .draw_with_triangles(gpu, &spec(0, 0, 40_000, 21))
        .unwrap();
    let mut counts = vec![0u64; areas.len()];
    for t in &tri {
        counts[t.expect("a surface point") as usize] += 1;
    }
    let total: f64 = areas.iter().sum();
    let p: Vec<f64> = areas.iter().map(|a| a / total).collect();
    let chi = chi_square(&counts, &p);
    eprintln!("counts {counts:?}, chi-square {chi}");
    assert!(chi < 31.3, "chi-square {chi} over 11 degrees of freedom");

    let big = 2; // the slot of area 2048
    let [a, b, c] = mesh.corners(&mesh.triangles[big]).unwrap();
    let on_big: Vec<Vec3> = points
        .iter()
        .zip(&tri)
        .filter(|(_, t)| **t == Some(big as u32))
        .map(|(p, _)| *p)
        .collect();
    let n = on_big.len() as f32;
    let mean = on_big.iter().copied().sum::<Vec3>() / n;
    let centroid = (a + b + c) / 3.0;
    // A coordinate of a uniform point in this triangle has a standard deviation of s·0.236.
    let se = (b - a).length() * 0.236 / n.sqrt();
    assert!(
        (mean - centroid).abs().max_element() < 4.0 * se,
        "{mean} {centroid}"
    );
    for corner in [a, b, c] {
        // The corner triangle of half the size: points nearer to `corner` than the midpoints.
        let inside = on_big
            .iter()
            .filter(|p| {
                let w = barycentric(**p, a, b, c);
                let k = [a, b, c].iter().position(|v| *v == corner).unwrap();
                w[k] >= 0.5
            })
            .count() as f32
            / n;
        assert!(
            (inside - 0.25).abs() < 4.0 * (0.25f32 * 0.75 / n).sqrt(),
            "{inside}"
        );
    }

    // On spot: 16 groups of consecutive triangles of about equal area, 15 degrees of freedom
    // (critical value 37.7 at p = 0.001).
    let spot = spot();
    let sampler = GpuSampler::new(gpu, &SampleTable::new(&spot).unwrap()).unwrap();
    let (_, tri) = sampler
        .draw_with_triangles(gpu, &spec(0, 0, 20_000, 22))
        .unwrap();
    let area = |t: &[u32; 3]| {
        let [a, b, c] = spot.corners(t).unwrap();
        0.5 * (b - a).as_dvec3().cross((c - a).as_dvec3()).length()
    };
    let total = spot.area();
    let mut group = Vec::with_capacity(spot.triangles.len());
    let mut acc = 0.0;
    for t in &spot.triangles {
        group.push(((acc / total * 16.0) as usize).min(15));
        acc += area(t);
    }
    let mut p = vec![0.0; 16];
    for (t, &g) in spot.triangles.iter().zip(&group) {
        p[g] += area(t) / total;
    }
    let mut counts = vec![0u64; 16];
    for t in tri {
        counts[group[t.unwrap() as usize]] += 1;
    }
    let chi = chi_square(&counts, &p);
    eprintln!("spot: chi-square {chi} over 15 degrees of freedom");
    assert!(chi < 37.7, "{chi}");
}

fn barycentric(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> [f32; 3] {
    let (v0, v1, v2) = (b - a, c - a, p - a);
    let (d00, d01, d11) = (v0.dot(v0), v0.dot(v1), v1.dot(v1));
    let (d20, d21) = (v2.dot(v0), v2.dot(v1));
    let den = d00 * d11 - d01 * d01;
    let v = (d11 * d20 - d01 * d21) / den;
    let w = (d00 * d21 - d01 * d20) / den;
    [1.0 - v - w, v, w]
}

/// Surface points lie on the mesh (the CPU's distance to it is at f32 rounding), and
/// near-surface points are at about σ from it.
#[test]
fn surface_points_lie_on_the_mesh() {
    let gpu = gpu();
    let mesh = spot();
    let cpu = SignedDistance::new(&mesh).unwrap();
    let sampler = GpuSampler::new(gpu, &SampleTable::new(&mesh).unwrap()).unwrap();
    let s = SampleSpec {
        shuffle: false,
        ..spec(0, 2000, 2000, 3)
    };
    let points = sampler.draw(gpu, &s).unwrap();
    let worst = points[2000..]
        .iter()
        .map(|p| cpu.unsigned_distance(*p))
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-6, "{worst}");
    // |N(0, σ²)| along the normal has mean σ √(2/π); curvature and the tangential parts move
    // it a little.
    let mean = points[..2000]
        .iter()
        .map(|p| cpu.unsigned_distance(*p))
        .sum::<f32>()
        / 2000.0;
    let expect = 0.01 * (2.0 / std::f32::consts::PI).sqrt();
    assert!((mean / expect - 1.0).abs() < 0.1, "{mean} vs {expect}");
}

/// A draw labelled on the GPU in one submission: the points are the plain draw's, the labels
/// the CPU's signed distances of them (to 1e-6 of the diagonal; exactly 0 on the surface), and
/// their absolute values for unsigned labels.
#[test]
fn draw_and_label_matches_the_cpu() {
    let gpu = gpu();
    let (mesh, cpu, gt, sampler) = spot_on_the_gpu(gpu);
    let s = spec(1000, 1500, 500, 17);
    let (points, labels) = sampler
        .draw_and_label(gpu, &gt, &s, LabelKind::Signed)
        .unwrap();
    assert_eq!(points, sampler.draw(gpu, &s).unwrap());
    let tol = 1e-6 * mesh.bounds().diagonal();
    // The surface points are labelled 0 without a query, as the CPU pool labels them.
    assert_eq!(labels.iter().filter(|&&d| d == 0.0).count(), 500);
    let inside = labels.iter().filter(|&&d| d < 0.0).count();
    assert!(inside > 300, "{inside} points inside");
    for (p, d) in points.iter().zip(&labels) {
        let want = cpu.signed_distance(*p);
        assert!((d - want).abs() <= tol, "{p}: {d} vs {want}");
    }
    let (_, unsigned) = sampler
        .draw_and_label(gpu, &gt, &s, LabelKind::Unsigned)
        .unwrap();
    for (u, d) in unsigned.iter().zip(&labels) {
        assert_eq!(*u, d.abs());
    }
}

/// Bad input is an error, not a panic: a mesh without area, a bad σ, more points than the
/// buffers hold.
#[test]
fn bad_input_is_an_error() {
    let flat = Mesh {
        vertices: vec![Vec3::ZERO, Vec3::X, Vec3::new(2.0, 0.0, 0.0)],
        triangles: vec![[0, 1, 2], [0, 1, 7]],
    };
    assert!(matches!(SampleTable::new(&flat), Err(SampleError::NoArea)));
    let table = SampleTable::new(&plane()).unwrap();
    let nan = SampleSpec {
        sigma: f32::NAN,
        ..spec(1, 1, 1, 0)
    };
    assert!(matches!(
        table.draw_cpu(&nan),
        Err(SampleError::BadSigma(_))
    ));
    let huge = spec(u32::MAX, 1, 0, 0);
    assert!(matches!(
        table.draw_cpu(&huge),
        Err(SampleError::TooManyPoints { .. })
    ));
    let gpu = gpu();
    let sampler = GpuSampler::new(gpu, &table).unwrap();
    assert!(matches!(
        sampler.draw(gpu, &nan),
        Err(SampleError::BadSigma(_))
    ));
    let cpu = SignedDistance::new(&plane()).unwrap();
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    let points = gpu.storage_zeroed("points", 10 * 12).unwrap();
    let targets = gpu.storage_zeroed("targets", 10 * 4).unwrap();
    let draw = LabelledDraw::new(gpu, &sampler, &gt, &points, &targets, LabelKind::Signed).unwrap();
    let mut enc = gpu.device().create_command_encoder(&Default::default());
    assert!(matches!(
        draw.record(gpu, &mut enc, &spec(5, 5, 1, 0)),
        Err(SampleError::TooManyPoints {
            requested: 11,
            limit: 10
        })
    ));
    draw.record(gpu, &mut enc, &spec(5, 5, 0, 0)).unwrap();
}

/// A pool of three labelled draws kept on the GPU (`LabelledDraw::with_pool`), in buffers
/// larger than a draw: an epoch's gather takes distinct points of all three blocks, each with
/// its block's label, in the order of the epoch's shuffle over the whole pool; a plain `record`
/// through the pool is the plain draw; a block or a gather beyond the pool is an error; an
/// unsigned pool's labels are the distances' absolute values.
#[test]
fn a_pool_of_labelled_draws_gathers_distinct_points_of_every_block() {
    let gpu = gpu();
    let (mesh, cpu, gt, sampler) = spot_on_the_gpu(gpu);
    let n = 1500u32;
    // Room for 2000 points: the blocks lie `n` points apart, not the buffers' capacity.
    let points = gpu.storage_zeroed("points", 2000 * 12).unwrap();
    let targets = gpu.storage_zeroed("targets", 2000 * 4).unwrap();
    let draw = LabelledDraw::with_pool(gpu, &sampler, &gt, &points, &targets, LabelKind::Signed, 3)
        .unwrap();
    assert_eq!(draw.pool_blocks(), 3);
    let submit = |record: &dyn Fn(&mut wgpu::CommandEncoder) -> Result<(), SampleError>| {
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        record(&mut enc).unwrap();
        gpu.queue().submit([enc.finish()]);
    };
    let block = |k: u32| SampleSpec {
        stream: k,
        shuffle: false,
        ..spec(500, 700, 300, 23)
    };
    // The blocks in slots 2, 0, 1: a block's place is its slot, not its turn.
    let mut pool = vec![Vec3::ZERO; 3 * n as usize];
    for (k, slot) in [(7u32, 2u32), (8, 0), (9, 1)] {
        submit(&|enc| draw.record_block(gpu, enc, &block(k), slot));
        let at = (slot * n) as usize;
        pool[at..at + n as usize].copy_from_slice(&sampler.draw(gpu, &block(k)).unwrap());
    }
    let epoch = SampleSpec {
        stream: 4,
        ..spec(500, 700, 300, 23)
    };
    submit(&|enc| draw.record_gather(gpu, enc, &epoch, 3));
    let read_points = || -> Vec<Vec3> {
        let flat: Vec<f32> = gpu.read_back_range(&points, 0, u64::from(n) * 3).unwrap();
        flat.chunks(3).map(Vec3::from_slice).collect()
    };
    let read_labels = || -> Vec<f32> { gpu.read_back_range(&targets, 0, u64::from(n)).unwrap() };
    let got = read_points();
    let labels = read_labels();
    let shuffle = epoch.shuffle_over(3 * n);
    let tol = 1e-6 * mesh.bounds().diagonal();
    let mut per_block = [0u32; 3];
    let mut seen = std::collections::HashSet::new();
    for (i, (p, d)) in got.iter().zip(&labels).enumerate() {
        let j = shuffle.apply(i as u32);
        assert!(seen.insert(j), "pool point {j} twice");
        assert_eq!(*p, pool[j as usize], "point {i} (pool point {j})");
        per_block[(j / n) as usize] += 1;
        // The last 300 of each block are its surface points, labelled 0 without a query.
        let want = if j % n >= 1200 {
            0.0
        } else {
            cpu.signed_distance(*p)
        };
        assert!((d - want).abs() <= tol, "{p}: {d} vs {want}");
    }
    assert!(per_block.iter().all(|&c| c > n / 5), "{per_block:?}");
    // One block and its gather, as `LabelledDraw::new` records them: the shuffled draw.
    submit(&|enc| draw.record(gpu, enc, &epoch));
    assert_eq!(read_points(), sampler.draw(gpu, &epoch).unwrap());
    let mut enc = gpu.device().create_command_encoder(&Default::default());
    assert!(matches!(
        draw.record_block(gpu, &mut enc, &block(1), 3),
        Err(SampleError::TooManyPoints { .. })
    ));
    assert!(matches!(
        draw.record_gather(gpu, &mut enc, &epoch, 4),
        Err(SampleError::TooManyPoints { .. })
    ));
    drop(enc);
    let unsigned = LabelledDraw::with_pool(
        gpu,
        &sampler,
        &gt,
        &points,
        &targets,
        LabelKind::Unsigned,
        2,
    )
    .unwrap();
    for (k, slot) in [(7u32, 1u32), (8, 0)] {
        submit(&|enc| unsigned.record_block(gpu, enc, &block(k), slot));
    }
    submit(&|enc| unsigned.record_gather(gpu, enc, &epoch, 2));
    let shuffle = epoch.shuffle_over(2 * n);
    for (i, (p, d)) in read_points().iter().zip(read_labels()).enumerate() {
        let j = shuffle.apply(i as u32) % n;
        let want = if j >= 1200 {
            0.0
        } else {
            cpu.signed_distance(*p).abs()
        };
        assert!((d - want).abs() <= tol, "{p}: {d} vs {want}");
    }
}
