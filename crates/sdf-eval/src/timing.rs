//! Latency as the design document measures it: per point from a 50000-point batch, and the
//! wall time of a 3000-point batch including upload, dispatch and readback.

use std::time::Instant;

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Batch size for the per-point figure.
pub const PER_POINT_BATCH: usize = 50_000;
/// Batch size for the latency figure.
pub const LATENCY_BATCH: usize = 3_000;
/// Minimum repetitions behind each median.
pub const MIN_REPS: usize = 10;

/// Latency figures, medians over repetitions.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Latency {
    /// Median wall time of a 50000-point batch divided by 50000, in nanoseconds.
    pub per_point_ns: f64,
    /// Median wall time of a 3000-point batch, in microseconds.
    pub batch3000_us: f64,
    /// Median pure GPU time per point of the 50000 batch from timestamp queries, where the
    /// adapter has them.
    pub gpu_per_point_ns: Option<f64>,
    /// Repetitions behind each median.
    pub reps: usize,
}

/// Median of a non-empty sample (the mean of the middle two for an even count).
pub fn median(mut xs: Vec<f64>) -> f64 {
    assert!(!xs.is_empty(), "median of nothing");
    xs.sort_by(f64::total_cmp);
    let n = xs.len();
    if n % 2 == 1 {
        xs[n / 2]
    } else {
        0.5 * (xs[n / 2 - 1] + xs[n / 2])
    }
}

/// Median wall time in seconds of `reps` calls of `f`, after one untimed warm-up call (which
/// pays for pipeline compilation and buffer creation).
pub fn median_seconds<E>(reps: usize, mut f: impl FnMut() -> Result<(), E>) -> Result<f64, E> {
    f()?;
    let mut times = Vec::with_capacity(reps);
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(median(times))
}

/// Measures `eval` (a batch evaluation returning one value per point) on the first
/// [`PER_POINT_BATCH`] and [`LATENCY_BATCH`] of `points`, `reps` times each (at least
/// [`MIN_REPS`]). `points` is cycled if shorter. Wall times only: `gpu_per_point_ns` is `None`
/// (see [`measure_latency_timed`]).
pub fn measure_latency<E>(
    points: &[Vec3],
    reps: usize,
    mut eval: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
) -> Result<Latency, E> {
    measure_latency_timed(points, reps, |p| Ok((eval(p)?, None)))
}

/// [`measure_latency`] for an `eval` that also returns the pure GPU time of the batch in
/// nanoseconds where it can (e.g. `NeuralSdf::eval_normalized_timed`). `gpu_per_point_ns` is the
/// median GPU time of the timed [`PER_POINT_BATCH`] repetitions divided by the batch size, when
/// every one of them reported a GPU time, else `None`.
pub fn measure_latency_timed<E>(
    points: &[Vec3],
    reps: usize,
    mut eval: impl FnMut(&[Vec3]) -> Result<(Vec<f32>, Option<u64>), E>,
) -> Result<Latency, E> {
    assert!(!points.is_empty(), "latency needs points");
    let batch = |n: usize| -> Vec<Vec3> { points.iter().copied().cycle().take(n).collect() };
    let big = batch(PER_POINT_BATCH);
    let small = batch(LATENCY_BATCH);
    let reps = reps.max(MIN_REPS);
    // One entry per call, the untimed warm-up call first.
    let mut gpu_ns: Vec<Option<u64>> = Vec::with_capacity(reps + 1);
    let per_batch = median_seconds(reps, || {
        gpu_ns.push(eval(&big)?.1);
        Ok(())
    })?;
    let latency = median_seconds(reps, || eval(&small).map(|_| ()))?;
    let timed: Option<Vec<f64>> = gpu_ns.iter().skip(1).map(|t| t.map(|t| t as f64)).collect();
    Ok(Latency {
        per_point_ns: per_batch * 1e9 / PER_POINT_BATCH as f64,
        batch3000_us: latency * 1e6,
        gpu_per_point_ns: timed
            .filter(|t| !t.is_empty())
            .map(|t| median(t) / PER_POINT_BATCH as f64),
        reps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_samples() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 2.5);
    }

    #[test]
    fn latency_calls_eval_on_the_documented_batches() {
        let mut sizes = Vec::new();
        let lat = measure_latency(&[Vec3::ZERO; 7], 3, |p| {
            sizes.push(p.len());
            Ok::<_, ()>(vec![0.0; p.len()])
        })
        .unwrap();
        // One warm-up plus MIN_REPS timed calls of each size.
        assert_eq!(
            sizes.iter().filter(|&&n| n == PER_POINT_BATCH).count(),
            MIN_REPS + 1
        );
        assert_eq!(
            sizes.iter().filter(|&&n| n == LATENCY_BATCH).count(),
            MIN_REPS + 1
        );
        assert_eq!(lat.reps, MIN_REPS);
        assert!(lat.per_point_ns >= 0.0 && lat.batch3000_us >= 0.0);
    }

    #[test]
    fn untimed_latency_has_no_gpu_time() {
        let lat = measure_latency(&[Vec3::ZERO], 1, |p| Ok::<_, ()>(vec![0.0; p.len()])).unwrap();
        assert_eq!(lat.gpu_per_point_ns, None);
    }

    #[test]
    fn gpu_times_of_the_big_batch_flow_into_the_median() {
        // The warm-up call reports a huge time that must be ignored; the timed repetitions of
        // the 50000 batch report 1, 2, ..., MIN_REPS ms, the 3000 batch something else.
        let mut big_calls = 0u64;
        let lat = measure_latency_timed(&[Vec3::ONE; 3], 1, |p| {
            let ns = if p.len() == PER_POINT_BATCH {
                let ns = if big_calls == 0 {
                    u64::MAX / 2
                } else {
                    big_calls * 1_000_000
                };
                big_calls += 1;
                ns
            } else {
                7
            };
            Ok::<_, ()>((vec![0.0; p.len()], Some(ns)))
        })
        .unwrap();
        assert_eq!(big_calls as usize, MIN_REPS + 1);
        // Median of 1..=10 ms is 5.5 ms.
        let expected = 5.5e6 / PER_POINT_BATCH as f64;
        let got = lat.gpu_per_point_ns.expect("a GPU time");
        assert!((got - expected).abs() < 1e-9, "{got} vs {expected}");
    }

    #[test]
    fn a_missing_gpu_time_gives_none() {
        let mut calls = 0;
        let lat = measure_latency_timed(&[Vec3::ZERO], 1, |p| {
            calls += 1;
            let ns = (calls != 3).then_some(100);
            Ok::<_, ()>((vec![0.0; p.len()], ns))
        })
        .unwrap();
        assert_eq!(lat.gpu_per_point_ns, None);
    }

    #[test]
    fn errors_propagate() {
        let r = measure_latency(&[Vec3::ZERO], 1, |_| Err::<Vec<f32>, _>("boom"));
        assert_eq!(r.unwrap_err(), "boom");
    }
}
