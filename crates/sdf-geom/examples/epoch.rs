//! Times one NGLOD epoch (1e5 uniform + 2e5 near-surface + 2e5 surface points, all signed) on a mesh,
//! plus the BVH build and 1e5 Poisson-disk samples; optionally exports the points as `.npy` (for the
//! Open3D comparison in `scripts/open3d_compare.py`).
//!
//! `cargo run --release -p sdf-geom --example epoch -- MESH [--export POINTS.npy] [--out SDF.npy] [--reps N]`

use std::time::Instant;

use sdf_geom::{SignedDistance, SignedDistanceOptions, load_mesh, npy, sample};

/// Process CPU time (user + system) in seconds, from /proc (Linux only; 0 elsewhere).
fn cpu_time() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    let Some(rest) = stat.rsplit(')').next() else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!(
            "usage: epoch MESH [--export POINTS.npy] [--out SDF.npy] [--reps N] [--no-surface-shortcut]"
        );
        std::process::exit(2);
    };
    let flag = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let reps: usize = flag("--reps").and_then(|s| s.parse().ok()).unwrap_or(3);
    let mut options = SignedDistanceOptions::default();
    if args.iter().any(|a| a == "--no-surface-shortcut") {
        options.surface_tolerance = 0.0;
    }

    let t = Instant::now();
    let (mesh, report) = load_mesh(path)?;
    println!(
        "load: {:.1} ms, {report:?}",
        t.elapsed().as_secs_f64() * 1e3
    );
    let (unit, _norm) = mesh.normalized();

    let mut best_build = f64::INFINITY;
    let mut sdf = None;
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        let s = SignedDistance::with_options(&unit, options)?;
        best_build = best_build.min(t.elapsed().as_secs_f64());
        sdf = Some(s);
    }
    let sdf = sdf.expect("built at least once");
    println!(
        "build ({} faces): {:.1} ms (best of {reps})",
        unit.triangles.len(),
        best_build * 1e3
    );

    let t = Instant::now();
    let mut points = sample::uniform_box(100_000, 1);
    points.extend(sample::near_surface(
        &unit,
        200_000,
        sample::DEFAULT_SIGMA,
        2,
    ));
    points.extend(sample::surface(&unit, 200_000, 3).points);
    println!("sampling 5e5: {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    if let Some(e) = flag("--export") {
        npy::write_points(&e, &points)?;
        println!("exported points (normalised coordinates) to {e}");
    }

    let parts = [
        ("uniform", 0..100_000),
        ("near", 100_000..300_000),
        ("surface", 300_000..500_000),
    ];
    // Per part: best of `reps` wall and CPU time (CPU time is less sensitive to a shared machine).
    let timed = |f: &dyn Fn() -> usize| {
        let (mut wall, mut cpu, mut v) = (f64::INFINITY, f64::INFINITY, 0);
        for _ in 0..reps.max(1) {
            let t = Instant::now();
            let c = cpu_time();
            v = f();
            wall = wall.min(t.elapsed().as_secs_f64() * 1e3);
            cpu = cpu.min((cpu_time() - c) * 1e3);
        }
        (wall, cpu, v)
    };
    for (name, r) in parts {
        let pts = &points[r];
        let (w, c, inside) = timed(&|| {
            sdf.signed_distance_batch(pts)
                .iter()
                .filter(|&&x| x < 0.0)
                .count()
        });
        println!(
            "  {name}: {w:.1} ms, CPU {c:.0} ms ({inside} inside of {})",
            pts.len()
        );
        let (wc, cc, _) = timed(&|| sdf.closest_point_batch(pts).len());
        let (ww, cw, _) = timed(&|| sdf.winding_number_batch(pts).len());
        println!(
            "    closest only {wc:.1} ms (CPU {cc:.0}), winding only {ww:.1} ms (CPU {cw:.0})"
        );
    }
    let mut best = f64::INFINITY;
    let mut best_cpu = f64::INFINITY;
    let mut d = Vec::new();
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        let c = cpu_time();
        d = sdf.signed_distance_batch(&points);
        best = best.min(t.elapsed().as_secs_f64());
        best_cpu = best_cpu.min(cpu_time() - c);
    }
    println!("epoch CPU time: {best_cpu:.2} s (all threads)");
    println!(
        "epoch 5e5 signed: {:.3} s (best of {reps}), {:.2} M points/s, threads {}",
        best,
        points.len() as f64 / best / 1e6,
        rayon::current_num_threads()
    );
    if let Some(o) = flag("--out") {
        npy::write_f32(&o, &d)?;
    }

    let t = Instant::now();
    let c = cpu_time();
    let pd = sample::poisson_disk(&unit, 100_000, 4);
    println!("poisson CPU time: {:.2} s (all threads)", cpu_time() - c);
    println!(
        "poisson 1e5: {:.1} ms, kept {}, min distance {:.5}, r_max {:.5}",
        t.elapsed().as_secs_f64() * 1e3,
        pd.samples.len(),
        pd.min_distance,
        pd.target_radius
    );
    Ok(())
}
