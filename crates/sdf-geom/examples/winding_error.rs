//! Measures the error of the fast winding number against the exact sum, for a few β.
//!
//! `cargo run --release -p sdf-geom --example winding_error -- MESH [N]`

use sdf_geom::{SignedDistance, SignedDistanceOptions, load_mesh, sample};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).ok_or("usage: winding_error MESH [N]")?;
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2000);
    let (mesh, _) = load_mesh(path)?;
    let (unit, _) = mesh.normalized();
    let mut points = sample::uniform_box(n, 11);
    points.extend(sample::near_surface(&unit, n, sample::DEFAULT_SIGMA, 12));
    let exact_sd = SignedDistance::new(&unit)?;
    let exact: Vec<f64> = points
        .iter()
        .map(|&p| exact_sd.winding_number_exact(p))
        .collect();
    for beta in [1.0f32, 1.5, 2.0, 3.0] {
        let sd = SignedDistance::with_options(
            &unit,
            SignedDistanceOptions {
                beta,
                refine_band: 0.0,
                ..Default::default()
            },
        )?;
        let fast = sd.winding_number_batch(&points);
        let (mut max_err, mut sum_err, mut flips) = (0.0f64, 0.0f64, 0);
        for (f, e) in fast.iter().zip(&exact) {
            let err = (*f as f64 - e).abs();
            max_err = max_err.max(err);
            sum_err += err;
            if (*f >= 0.5) != (*e >= 0.5) {
                flips += 1;
            }
        }
        let t = std::time::Instant::now();
        for _ in 0..3 {
            let _ = sd.winding_number_batch(&points);
        }
        println!(
            "beta {beta}: max |err| {max_err:.2e}, mean {:.2e}, sign flips {flips}/{}, {:.1} ms/3 runs",
            sum_err / points.len() as f64,
            points.len(),
            t.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(())
}
