//! GPU time from timestamp queries ([`GpuTimer`]): a timed NGLOD or SIREN evaluation returns exactly the
//! values of the untimed one, and a GPU time above zero and within the wall time around the call,
//! also when the input is split over several dispatches and through [`NeuralSdf`]. Skips (prints
//! and passes) on adapters without timestamp queries. One test binary, one shared device. Also
//! how results are waited for: [`GpuContext::set_spin_wait`] changes when, never what.

use std::time::{Duration, Instant};

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::gpu::GpuTimer;
use sdf_nn::nglod::ScatterMode;
use sdf_nn::{
    GpuContext, NeuralSdf, Nglod, NglodConfig, NglodGpu, Normalization, Siren, SirenConfig,
    SirenGpu,
};

/// The shared context and a timer on it, or `None` (after saying so) without timestamps.
fn gpu_and_timer() -> Option<(&'static GpuContext, GpuTimer)> {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    match GpuTimer::new(gpu) {
        Some(timer) => Some((gpu, timer)),
        None => {
            assert!(!gpu.has_timestamps());
            eprintln!("skipped: {} has no timestamp queries", gpu.describe());
            None
        }
    }
}

/// NGLOD's small configuration with random grid features, so the grids decide the output.
fn model() -> Nglod {
    let mut m = Nglod::new(NglodConfig::small()).unwrap();
    let w0 = m.layout().w0;
    let mut rng = Pcg64::seed_from_u64(3);
    for p in &mut m.params_mut()[..w0] {
        *p = rng.random_range(-0.5..0.5);
    }
    m
}

fn points(n: usize, seed: u64) -> Vec<Vec3> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn timed_nglod_eval_matches_untimed_and_is_within_wall_time() {
    let Some((gpu, timer)) = gpu_and_timer() else {
        return;
    };
    let mut net = NglodGpu::new(gpu, &model(), ScatterMode::Auto).unwrap();
    let pts = points(5000, 1);
    // Warm-up: compiles the pipeline outside the timed calls.
    let untimed = net.eval(gpu, &pts, None).unwrap();

    let t = Instant::now();
    let (timed, ns) = net.eval_timed(gpu, &pts, None, &timer).unwrap();
    let wall = t.elapsed().as_nanos() as u64;
    assert_eq!(bits(&timed), bits(&untimed));
    assert!(ns > 0, "GPU time {ns} ns");
    assert!(ns <= wall, "GPU time {ns} ns above the wall time {wall} ns");
    eprintln!("one dispatch: {ns} ns on the GPU, {wall} ns wall");

    // Split into four dispatches: the times of all of them are summed, each within the wall.
    net.set_max_points_per_dispatch(1250);
    let t = Instant::now();
    let (split, split_ns) = net.eval_timed(gpu, &pts, None, &timer).unwrap();
    let wall = t.elapsed().as_nanos() as u64;
    assert_eq!(bits(&split), bits(&untimed));
    assert!(
        split_ns > 0 && split_ns <= wall,
        "{split_ns} ns vs {wall} ns"
    );
    eprintln!("four dispatches: {split_ns} ns on the GPU, {wall} ns wall");

    // Nothing to do: no dispatch, no time.
    assert_eq!(net.eval_timed(gpu, &[], None, &timer).unwrap(), (vec![], 0));
}

#[test]
fn neural_sdf_reports_gpu_time_for_nglod() {
    let Some((gpu, _)) = gpu_and_timer() else {
        return;
    };
    let file = model().to_model_file(
        Normalization {
            center: Vec3::ZERO.as_dvec3(),
            scale: 1.0,
        },
        serde_json::json!({}),
    );
    let sdf = NeuralSdf::from_model_file(file).unwrap();
    // Some points outside the box exercise the distance extension on both paths.
    let pts: Vec<Vec3> = points(3000, 2).into_iter().map(|p| p * 1.2).collect();
    let untimed = sdf.eval_normalized(gpu, &pts).unwrap();
    let t = Instant::now();
    let (timed, ns) = sdf.eval_normalized_timed(gpu, &pts).unwrap();
    let wall = t.elapsed().as_nanos() as u64;
    assert_eq!(bits(&timed), bits(&untimed));
    let ns = ns.expect("NGLOD on an adapter with timestamps reports a GPU time");
    assert!(ns > 0 && ns <= wall, "{ns} ns vs {wall} ns");
}

#[test]
fn timed_siren_eval_matches_untimed_and_is_within_wall_time() {
    let Some((gpu, timer)) = gpu_and_timer() else {
        return;
    };
    let cfg = SirenConfig {
        width: 16,
        hidden_layers: 2,
        omega0: 30.0,
    };
    let mut net = SirenGpu::new(gpu, &Siren::new(cfg, 4).unwrap()).unwrap();
    let pts = points(3000, 5);
    let untimed = net.eval(gpu, &pts).unwrap();
    // Also split into three launches of 1024 points (1024 + 1024 + 952), whose times add up.
    for max_per_launch in [None, Some(1024)] {
        if let Some(m) = max_per_launch {
            let options = sdf_nn::siren::SirenGpuOptions {
                max_points_per_launch: m,
                ..*net.options()
            };
            net.set_options(gpu, &options).unwrap();
        }
        let t = Instant::now();
        let (timed, ns) = net.eval_timed(gpu, &pts, &timer).unwrap();
        let wall = t.elapsed().as_nanos() as u64;
        assert_eq!(bits(&timed), bits(&untimed));
        assert!(ns > 0 && ns <= wall, "GPU time {ns} ns, wall {wall} ns");
        eprintln!("SIREN {max_per_launch:?}: {ns} ns on the GPU, {wall} ns wall");
    }
}

/// Blocking at once, or polling for as long as the work takes, gives the same values; the
/// setting reads back (a duration past u64 nanoseconds saturates).
#[test]
fn the_spin_wait_changes_when_results_arrive_not_what_they_are() {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    assert_eq!(gpu.spin_wait(), sdf_nn::SPIN_WAIT);
    let net = NglodGpu::new(gpu, &model(), ScatterMode::Auto).unwrap();
    let pts = points(3000, 11);
    let spun = net.eval(gpu, &pts, None).unwrap();
    gpu.set_spin_wait(Duration::ZERO);
    assert_eq!(gpu.spin_wait(), Duration::ZERO);
    let blocked = net.eval(gpu, &pts, None).unwrap();
    gpu.set_spin_wait(Duration::MAX);
    assert_eq!(gpu.spin_wait(), Duration::from_nanos(u64::MAX));
    let polled = net.eval(gpu, &pts, None).unwrap();
    gpu.set_spin_wait(sdf_nn::SPIN_WAIT);
    assert_eq!(bits(&spun), bits(&blocked));
    assert_eq!(bits(&spun), bits(&polled));
}
