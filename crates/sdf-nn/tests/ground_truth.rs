//! The GPU ground truth against the CPU's (`sdf_geom::SignedDistance`) on the shared test meshes
//! (closed, open, multi-component, non-manifold): distances, closest points, signs and winding
//! numbers; far queries and huge coordinates; meshes that do not fit. One test binary so every
//! test shares one device and its compiled pipelines (lavapipe JIT costs seconds per pipeline).

#[path = "support/mod.rs"]
mod support;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance, load_mesh, sample};
use sdf_nn::GpuContext;
use sdf_nn::ground_truth::{GpuGroundTruth, GroundTruthError, Labeller, MAX_STACK};
use support::test_data;

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

fn unit(name: &str) -> Mesh {
    load_mesh(test_data(name)).unwrap().0.normalized().0
}

/// Uniform in a box a little larger than the mesh's, near the surface at two scales, on it.
fn queries(mesh: &Mesh, n: usize, seed: u64) -> Vec<Vec3> {
    let mut p: Vec<Vec3> = sample::uniform_box(n, seed)
        .into_iter()
        .map(|p| p * 1.1)
        .collect();
    p.extend(sample::near_surface(mesh, n, 0.01, seed + 1));
    p.extend(sample::near_surface(mesh, n / 2, 0.001, seed + 2));
    p.extend(sample::surface(mesh, n / 4, seed + 3).points);
    p
}

/// Largest |GPU − CPU| winding number seen off the surface of the meshes below: 1e-3 (measured
/// maxima are in the report of each test).
const WINDING_TOLERANCE: f32 = 1e-3;

/// Distances within 1e-6 of the diagonal, closest points on the surface and at the CPU's (or as
/// near), signs equal farther than 1e-5 of the diagonal from the surface, winding numbers within
/// [`WINDING_TOLERANCE`] there; the labeller's own probe of the two paths agrees.
fn check_mesh(name: &str, n: usize) {
    let gpu = gpu();
    let mesh = unit(name);
    let cpu = SignedDistance::new(&mesh).unwrap();
    let probed = Labeller::on_gpu(gpu, std::sync::Arc::new(cpu.clone()));
    assert!(probed.is_ok(), "{name}: {:?}", probed.err());
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    let diag = mesh.bounds().diagonal();
    let (tol, band) = (1e-6 * diag, 1e-5 * diag);
    let pts = queries(&mesh, n, 11);

    let want = cpu.closest_point_batch(&pts);
    let dist: Vec<f32> = want.iter().map(|c| c.distance).collect();
    let got = gt.closest_points(gpu, &pts).unwrap();
    let mut worst = 0.0f32;
    // How far the GPU's and the CPU's closest points are off the mesh, measured exactly (f64,
    // every triangle): the f32 search's own distance at a point on a sliver is off by about as
    // much as the point itself, and would measure the search instead.
    let off_mesh = |q: Vec3| sdf_geom::reference::brute_force_distance(&mesh, q).0 as f32;
    let (mut off_gpu, mut off_cpu) = (0.0f32, 0.0f32);
    for ((p, w), &(point, d)) in pts.iter().zip(&want).zip(&got) {
        worst = worst.max((d - w.distance).abs());
        let (off, off_w) = (off_mesh(point), off_mesh(w.point));
        off_gpu = off_gpu.max(off);
        off_cpu = off_cpu.max(off_w);
        assert!((d - w.distance).abs() <= tol, "{name} {p}: {d} vs {w:?}");
        // The returned point is at the returned distance, on the mesh (as nearly as the CPU's
        // own point, which f32 rounding leaves up to a few 1e-6 off slivers), and the CPU's
        // point or one as near (equidistant triangles).
        assert!(
            (point.distance(*p) - d).abs() <= tol,
            "{name} {p}: {point} {d}"
        );
        assert!(
            off <= tol.max(2.0 * off_w),
            "{name} {p}: {point} off the mesh by {off}; {d} vs {w:?}"
        );
        assert!(
            point.distance(w.point) <= tol || (point.distance(*p) - w.distance).abs() <= tol,
            "{name} {p}: {point} vs {w:?}"
        );
    }

    let want = cpu.signed_distance_batch(&pts);
    let got = gt.signed_distance(gpu, &pts).unwrap();
    for ((p, w), g) in pts.iter().zip(&want).zip(&got) {
        assert!((g.abs() - w.abs()).abs() <= tol, "{name} {p}: {g} vs {w}");
        if w.abs() > band {
            assert_eq!(g.signum(), w.signum(), "{name} {p}: sign of {g} vs {w}");
        }
    }

    let want = cpu.winding_number_batch(&pts);
    let got = gt.winding_numbers(gpu, &pts).unwrap();
    let mut worst_w = 0.0f32;
    for (((p, w), g), d) in pts.iter().zip(&want).zip(&got).zip(&dist) {
        if *d > band {
            worst_w = worst_w.max((g - w).abs());
            assert!((g - w).abs() <= WINDING_TOLERANCE, "{name} {p}: {g} vs {w}");
        }
    }
    eprintln!(
        "{name}: {} points, {} triangles, stack {}: max |Δd| {:.2e} of the diagonal, closest \
         points off the mesh by {:.2e} (CPU {:.2e}) of it, max |Δw| {worst_w:.2e}",
        pts.len(),
        gt.triangle_count(),
        gt.max_stack(),
        worst / diag,
        off_gpu / diag,
        off_cpu / diag
    );
}

#[test]
fn spot_closed() {
    check_mesh("spot.obj", 1000);
}

#[test]
fn suzanne_open_multi_part() {
    check_mesh("suzanne.obj", 1000);
}

#[test]
fn pins_gltf() {
    check_mesh("pins.glb", 1000);
}

#[test]
fn boxframe() {
    check_mesh("boxframe.obj", 1000);
}

#[test]
fn cubegrid() {
    check_mesh("cubegrid.obj", 1000);
}

#[test]
fn teapot_open() {
    check_mesh("teapot.obj", 1000);
}

/// GPU and CPU signed distances agree to `rel` of the distance plus `abs`, with the same
/// infinities; every GPU value for a finite point is finite unless the CPU's is infinite. A
/// distance below f32's smallest normal may come back as 0 (WGSL lets a driver flush
/// subnormals; Mesa 26's lavapipe does).
fn agree(name: &str, cpu: &SignedDistance, gt: &GpuGroundTruth, pts: &[Vec3], rel: f32, abs: f32) {
    let close = |g: f32, w: f32| {
        (g - w).abs() <= rel * w.abs() + abs || (w.abs() < f32::MIN_POSITIVE && g == 0.0)
    };
    let gpu = gpu();
    let want = cpu.signed_distance_batch(pts);
    let got = gt.signed_distance(gpu, pts).unwrap();
    let closest = gt.closest_points(gpu, pts).unwrap();
    let want_c = cpu.closest_point_batch(pts);
    for (i, p) in pts.iter().enumerate() {
        let (w, g) = (want[i], got[i]);
        if w.is_infinite() {
            assert_eq!(g, w, "{name} {p}");
            continue;
        }
        assert!(g.is_finite(), "{name} {p}: {g} (CPU {w})");
        assert!(close(g, w), "{name} {p}: {g} vs {w}");
        let (point, d) = closest[i];
        assert!(
            point.is_finite() && d.is_finite(),
            "{name} {p}: {point} {d}"
        );
        let wd = want_c[i].distance;
        assert!(close(d, wd), "{name} {p}: {d} vs {wd}");
    }
}

/// Far queries (up to `f32::MAX`) take the far path without overflow; meshes far from the origin
/// or tiny take the power-of-two rescaling; nothing turns into NaN.
#[test]
fn far_queries_and_huge_coordinates_stay_finite() {
    let gpu = gpu();
    let mesh = unit("spot.obj");
    let far_points = |c: Vec3, s: f32| -> Vec<Vec3> {
        let mut p = vec![
            c + Vec3::new(1e6, 0.0, 0.0) * s,
            c + Vec3::new(-1e6, 2e5, 3.0) * s,
            c + Vec3::splat(1e12) * s,
            Vec3::new(3e38, -3e38, 1e38),
            Vec3::new(0.0, 0.0, 2e38),
            Vec3::new(-3e38, 1.0, 0.0),
        ];
        p.extend(
            sample::uniform_box(64, 5)
                .into_iter()
                .map(|q| c + q * 1.5 * s),
        );
        // Components below f32's smallest normal read as 0: WGSL lets a driver flush
        // subnormals (Mesa 26's lavapipe does, 22's does not), and the case at 1e-37 is about
        // the mesh's scaling, not about subnormal queries.
        let flush = |x: f32| if x.abs() < f32::MIN_POSITIVE { 0.0 } else { x };
        p.into_iter()
            .map(|q| Vec3::new(flush(q.x), flush(q.y), flush(q.z)))
            .collect()
    };
    let cpu = SignedDistance::new(&mesh).unwrap();
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    agree("spot", &cpu, &gt, &far_points(Vec3::ZERO, 1.0), 1e-6, 1e-6);

    // Translated by 1e7 (scaled by 1000 first, so that f32 still resolves its shape).
    let t = Vec3::splat(1e7);
    let moved = Mesh {
        vertices: mesh.vertices.iter().map(|v| *v * 1000.0 + t).collect(),
        triangles: mesh.triangles.clone(),
    };
    let cpu = SignedDistance::new(&moved).unwrap();
    assert!(cpu.gpu_trees().exponent < 0);
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    agree("spot + 1e7", &cpu, &gt, &far_points(t, 1000.0), 1e-5, 1e-2);

    // Tiny (scaled to 1e-30): the internal scale is 2^+100 or so, and a query of 1e38 must not
    // overflow on its way in.
    let tiny = Mesh {
        vertices: mesh.vertices.iter().map(|v| *v * 1e-30).collect(),
        triangles: mesh.triangles.clone(),
    };
    let cpu = SignedDistance::new(&tiny).unwrap();
    assert!(cpu.gpu_trees().exponent > 0);
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    agree(
        "spot × 1e-30",
        &cpu,
        &gt,
        &far_points(Vec3::ZERO, 1e-30),
        1e-5,
        1e-36,
    );

    // Near the smallest normal f32: an internal scale of 2^122, applied in two steps.
    let tinier = Mesh {
        vertices: mesh.vertices.iter().map(|v| *v * 1e-37).collect(),
        triangles: mesh.triangles.clone(),
    };
    let cpu = SignedDistance::new(&tinier).unwrap();
    assert!(cpu.gpu_trees().exponent > 120);
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    agree(
        "spot × 1e-37",
        &cpu,
        &gt,
        &far_points(Vec3::ZERO, 1e-37),
        1e-4,
        1e-43,
    );
}

#[test]
fn non_finite_points_give_nan_and_empty_input_nothing() {
    let gpu = gpu();
    let cpu = SignedDistance::new(&Mesh::icosphere(1.0, 2)).unwrap();
    let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
    let pts = [
        Vec3::new(f32::NAN, 0.0, 0.0),
        Vec3::ZERO,
        Vec3::new(0.0, f32::INFINITY, 0.0),
        Vec3::new(2.0, 0.0, 0.0),
    ];
    let d = gt.signed_distance(gpu, &pts).unwrap();
    assert!(d[0].is_nan() && d[2].is_nan());
    assert!(
        (d[1] + 1.0).abs() < 0.02 && (d[3] - 1.0).abs() < 0.02,
        "{d:?}"
    );
    let c = gt.closest_points(gpu, &pts).unwrap();
    assert!(c[0].1.is_nan() && c[0].0.is_nan() && c[2].1.is_nan());
    let w = gt.winding_numbers(gpu, &pts).unwrap();
    let cw = cpu.winding_number_batch(&pts);
    assert!(w[0].is_nan() && w[2].is_nan(), "{w:?}");
    // A coarse sphere: β = 1.5 leaves 1.06 at the centre, on both.
    assert!(
        (w[1] - cw[1]).abs() < 1e-4 && (w[3] - cw[3]).abs() < 1e-4,
        "{w:?} {cw:?}"
    );
    assert!(gt.signed_distance(gpu, &[]).unwrap().is_empty());
}

/// A tree larger than a storage binding, or deeper than the kernels' stack, is refused with the
/// limit's name. The device's own limits are far above the test meshes, so the check runs
/// against smaller limits (the same check `GpuGroundTruth::new` runs with the device's).
#[test]
fn trees_that_do_not_fit_are_refused() {
    let cpu = SignedDistance::new(&unit("spot.obj")).unwrap();
    let trees = cpu.gpu_trees();
    let limits = wgpu::Limits {
        max_storage_buffer_binding_size: 1 << 16,
        ..wgpu::Limits::downlevel_defaults()
    };
    let err = GpuGroundTruth::check_limits(&trees, &limits).unwrap_err();
    match &err {
        GroundTruthError::TreeTooLarge {
            what,
            bytes,
            limit_name,
            limit,
        } => {
            assert_eq!(*limit_name, "max_storage_buffer_binding_size");
            assert_eq!(*limit, 1 << 16);
            assert!(*bytes > *limit, "{what}: {bytes}");
        }
        other => panic!("{other:?}"),
    }
    assert!(err.to_string().contains("max_storage_buffer_binding_size"));
    GpuGroundTruth::check_limits(&trees, &wgpu::Limits::downlevel_defaults()).unwrap();

    let deep = sdf_geom::GpuTrees {
        max_stack: MAX_STACK + 1,
        ..trees
    };
    let err = GpuGroundTruth::check_limits(&deep, &wgpu::Limits::downlevel_defaults());
    assert!(
        matches!(err, Err(GroundTruthError::TreeTooDeep { needed, limit }) if needed == MAX_STACK + 1 && limit == MAX_STACK),
        "{err:?}"
    );
}

/// Triangles whose spacing shrinks geometrically (PLOC's worst case, the deepest trees the
/// builder makes): either the kernels' stack holds the tree and the answers are the CPU's, or
/// the mesh is refused with `TreeTooDeep` (never a stack overflow or a wrong answer).
#[test]
fn geometric_chains_are_answered_or_refused() {
    let n = 5000;
    let mut vertices = Vec::with_capacity(3 * n);
    let mut x = 1.0f32;
    for _ in 0..n {
        let s = x * 0.2;
        vertices.extend([
            Vec3::new(x, 0.0, 0.0),
            Vec3::new(x, s, 0.0),
            Vec3::new(x, 0.0, s),
        ]);
        x /= 1.002;
    }
    let triangles = (0..n as u32)
        .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
        .collect();
    let mesh = Mesh {
        vertices,
        triangles,
    };
    let cpu = SignedDistance::new(&mesh).unwrap();
    let needed = cpu.gpu_trees().max_stack;
    let gpu = gpu();
    match GpuGroundTruth::new(gpu, &cpu) {
        Ok(gt) => {
            assert!(needed <= MAX_STACK);
            let mut pts = sample::uniform_box(500, 5);
            pts.extend(sample::surface(&mesh, 500, 6).points);
            let want = cpu.signed_distance_batch(&pts);
            let got = gt.signed_distance(gpu, &pts).unwrap();
            for ((p, w), g) in pts.iter().zip(&want).zip(&got) {
                assert!((w.abs() - g.abs()).abs() <= 1e-6, "{p}: {g} vs {w}");
            }
            eprintln!("geometric chain: stack {needed}, answered");
        }
        Err(GroundTruthError::TreeTooDeep { needed: k, limit }) => {
            assert_eq!((k, limit), (needed, MAX_STACK));
            eprintln!("geometric chain: stack {needed}, refused");
        }
        Err(e) => panic!("{e}"),
    }
}

/// The labeller a run asks for: `gpu` labels on the kernels, as the CPU does (distances within
/// 1e-6 of the diagonal, sides equal away from the surface); `auto` takes the GPU exactly where
/// the adapter is not a CPU; `cpu` is the CPU's own answer.
#[test]
fn labellers_on_each_path_agree_with_the_cpu() {
    use sdf_nn::ground_truth::{GroundTruthDevice, GroundTruthPath};
    let gpu = gpu();
    let mesh = unit("spot.obj");
    let cpu = std::sync::Arc::new(SignedDistance::new(&mesh).unwrap());
    let pts = queries(&mesh, 1000, 5);
    let diag = mesh.bounds().diagonal();
    let on_gpu = Labeller::choose(gpu, cpu.clone(), GroundTruthDevice::Gpu).unwrap();
    assert_eq!(on_gpu.path(), GroundTruthPath::Gpu);
    assert!(on_gpu.fallback().is_none());
    let want = cpu.signed_distance_batch(&pts);
    let got = on_gpu.signed_distance_batch(&pts).unwrap();
    let unsigned = on_gpu.unsigned_distance_batch(&pts).unwrap();
    let inside = on_gpu.is_inside_batch(&pts).unwrap();
    let cpu_inside = cpu.is_inside_batch(&pts);
    for i in 0..pts.len() {
        assert!(
            (got[i] - want[i]).abs() <= 1e-6 * diag,
            "{}: {} {}",
            pts[i],
            got[i],
            want[i]
        );
        assert!((unsigned[i] - want[i].abs()).abs() <= 1e-6 * diag);
        if want[i].abs() > 1e-5 * diag {
            assert_eq!(inside[i], cpu_inside[i], "{}", pts[i]);
        }
    }
    let auto = Labeller::choose(gpu, cpu.clone(), GroundTruthDevice::Auto).unwrap();
    let expect = if gpu.is_cpu() {
        GroundTruthPath::Cpu
    } else {
        GroundTruthPath::Gpu
    };
    assert_eq!(auto.path(), expect);
    let on_cpu = Labeller::choose(gpu, cpu.clone(), GroundTruthDevice::Cpu).unwrap();
    assert_eq!(on_cpu.path(), GroundTruthPath::Cpu);
    assert_eq!(on_cpu.signed_distance_batch(&pts).unwrap(), want);
}
