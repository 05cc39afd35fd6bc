//! Labels per second of the exact ground truth, CPU against GPU, on the same points: signed
//! distances (`SignedDistance::signed_distance_batch`, rayon on every core, against
//! `GpuGroundTruth::signed_distance`) and closest points (`closest_point_batch` against
//! `closest_points`). Points: half uniform in the normalised box, half near the surface (σ = 0.01).
//!
//! `cargo run --release -p sdf-nn --example ground_truth_bench -- tests/data/spot.obj
//! ../shared/meshes/stanford-bunny.obj --points 100000 --reps 3`
//!
//! `--subdivide K` splits every triangle into 4 (at its edge midpoints) K times before the
//! trees are built: the shape stays, the triangle count grows 4^K-fold, so a 86 k-triangle
//! scan (armadillo) becomes the 1.4 M-triangle scan of issue 38's target with `--subdivide 2`.
//!
//! Each figure is the best of `--reps` runs, after one untimed GPU run (shader compilation).
//! Then `GpuGroundTruth::profile`: the GPU time of each launch (the grouping by cell, then the
//! closest-point, winding-number and signed-distance kernels) on the first part of the points,
//! which tells the kernels' time from the wall's and a search from a winding number.

use std::error::Error;
use std::time::{Duration, Instant};

use sdf_geom::{Mesh, SignedDistance, load_mesh, sample};
use sdf_nn::{GpuContext, GpuGroundTruth};

/// The best wall time of `reps` runs of `f`, and its last result.
fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> (Duration, T) {
    let mut best = Duration::MAX;
    let mut last = None;
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed());
        last = Some(r);
    }
    (best, last.expect("at least one run"))
}

fn rate(n: usize, t: Duration) -> String {
    format!(
        "{:>9.0} labels/s ({:.3} s)",
        n as f64 / t.as_secs_f64(),
        t.as_secs_f64()
    )
}

/// Every triangle split into four at its edge midpoints (shared edges share their midpoint).
fn split_in_four(mesh: &Mesh) -> Mesh {
    let mut vertices = mesh.vertices.clone();
    let mut midpoints = std::collections::HashMap::new();
    let mut mid = |a: u32, b: u32, vertices: &mut Vec<glam::Vec3>| -> u32 {
        *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
            vertices.push((vertices[a as usize] + vertices[b as usize]) * 0.5);
            vertices.len() as u32 - 1
        })
    };
    let mut triangles = Vec::with_capacity(mesh.triangles.len() * 4);
    for &[a, b, c] in &mesh.triangles {
        let (ab, bc, ca) = (
            mid(a, b, &mut vertices),
            mid(b, c, &mut vertices),
            mid(c, a, &mut vertices),
        );
        triangles.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
    }
    Mesh {
        vertices,
        triangles,
    }
}

fn main() -> Result<(), Box<dyn Error>> {
    let mut meshes = Vec::new();
    let (mut n, mut reps, mut subdivide) = (100_000usize, 3usize, 0usize);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--points" => n = args.next().ok_or("--points needs a value")?.parse()?,
            "--reps" => reps = args.next().ok_or("--reps needs a value")?.parse()?,
            "--subdivide" => subdivide = args.next().ok_or("--subdivide needs a value")?.parse()?,
            _ => meshes.push(a),
        }
    }
    if meshes.is_empty() {
        meshes.push(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/data/spot.obj").into());
    }
    let gpu = GpuContext::new()?;
    println!(
        "adapter: {}; CPU threads: {}",
        gpu.describe(),
        rayon::current_num_threads()
    );
    for path in &meshes {
        let mut unit = load_mesh(path)?.0.normalized().0;
        for _ in 0..subdivide {
            unit = split_in_four(&unit);
        }
        let t = Instant::now();
        let cpu = SignedDistance::new(&unit)?;
        let build = t.elapsed();
        let t = Instant::now();
        let gt = GpuGroundTruth::new(&gpu, &cpu)?;
        let upload = t.elapsed();
        let mut points = sample::uniform_box(n / 2, 1);
        points.extend(sample::near_surface(&unit, n - n / 2, 0.01, 2));
        gt.signed_distance(&gpu, &points[..points.len().min(4096)])?;
        gt.closest_points(&gpu, &points[..points.len().min(4096)])?;
        println!(
            "{path}: {} triangles, BVH build {:.3} s, upload {:.3} s, stack {}, {n} points",
            gt.triangle_count(),
            build.as_secs_f64(),
            upload.as_secs_f64(),
            gt.max_stack()
        );
        let (t_cpu, want) = best(reps, || cpu.signed_distance_batch(&points));
        let (t_gpu, got) = best(reps, || gt.signed_distance(&gpu, &points));
        let got = got?;
        let diag = unit.bounds().diagonal();
        let worst = want
            .iter()
            .zip(&got)
            .map(|(w, g)| (w.abs() - g.abs()).abs())
            .fold(0.0f32, f32::max);
        let flips = want
            .iter()
            .zip(&got)
            .filter(|(w, g)| w.abs() > 1e-5 * diag && w.signum() != g.signum())
            .count();
        println!("  signed  CPU {}", rate(n, t_cpu));
        println!(
            "  signed  GPU {}  (GPU/CPU {:.2}; max |Δd| {:.1e} of the diagonal, {flips} sign flips)",
            rate(n, t_gpu),
            t_cpu.as_secs_f64() / t_gpu.as_secs_f64(),
            worst / diag
        );
        // Where the GPU's time goes: each launch's own time on one part, against the wall.
        if let Some(profile) = gt.profile(&gpu, &points)? {
            let m = profile.points as f64;
            let mut per_kernel = 0u64;
            for t in &profile.launches {
                per_kernel += t.ns;
                // "kernel: launch": the kernel's own launch ends its group.
                let kernel_done = t.label.split_once(": ").is_some_and(|(k, l)| k == l);
                print!("  {:<30} {:>9.3} ms", t.label, t.ns as f64 * 1e-6);
                if kernel_done {
                    print!(
                        "   (with its grouping {:.0} labels/s of GPU time)",
                        m / (per_kernel as f64 * 1e-9)
                    );
                    per_kernel = 0;
                }
                println!();
            }
            println!("  (GPU times of one part of {} points)", profile.points);
        } else {
            println!("  (no timestamp queries: no GPU profile)");
        }
        let (t_cpu, _) = best(reps, || cpu.closest_point_batch(&points));
        let (t_gpu, got) = best(reps, || gt.closest_points(&gpu, &points));
        got?;
        println!("  closest CPU {}", rate(n, t_cpu));
        println!(
            "  closest GPU {}  (GPU/CPU {:.2})",
            rate(n, t_gpu),
            t_cpu.as_secs_f64() / t_gpu.as_secs_f64()
        );
    }
    Ok(())
}
