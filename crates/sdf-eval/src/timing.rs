//! Latency as the design document measures it: per point from a 50000-point batch, and the
//! wall time of a 3000-point batch including upload, dispatch and readback.
//!
//! Two kinds of figure, from separate calls so that measuring one never slows the other:
//! - wall time through the public API (`NeuralSdf::eval_normalized`): what a user waits for;
//! - kernel time from GPU timestamps (`NeuralSdf::eval_normalized_timed`): what the GPU spends,
//!   without uploads, readbacks or the host. Resolving and reading the timestamps costs a second
//!   readback, so those calls are never the ones the wall clock times.

use std::time::{Duration, Instant};

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Batch size for the per-point figure.
pub const PER_POINT_BATCH: usize = 50_000;
/// Batch size for the latency figure.
pub const LATENCY_BATCH: usize = 3_000;
/// Minimum repetitions behind each median, unless they are slow ([`SLOW_AFTER`]).
pub const MIN_REPS: usize = 10;
/// Once the repetitions of one batch size have taken this long, [`FEW_REPS`] of them suffice:
/// on lavapipe a SIREN `default` batch of 50 000 points takes about 13 s, and ten repetitions
/// of it with their timed twins kept `train` measuring for five of its six minutes.
pub const SLOW_AFTER: Duration = Duration::from_secs(10);
/// The fewest repetitions behind a median once they are slow ([`SLOW_AFTER`]).
pub const FEW_REPS: usize = 3;

/// Whether `done` repetitions of a batch size, the first `elapsed` ago, suffice when `reps`
/// were asked for: all of them, or [`FEW_REPS`] once they have taken [`SLOW_AFTER`].
fn enough_reps(done: usize, reps: usize, elapsed: Duration) -> bool {
    done >= reps || (done >= FEW_REPS && elapsed >= SLOW_AFTER)
}
/// How long the reports keep the model busy before they time it. A GPU left idle lowers its
/// clocks and raises them only under sustained load, so the first calls after a pause run
/// several times slower than the rest (see docs/benchmarks "Latency after a warm-up"); steady
/// state is what a caller that queries all the time sees, and what criterion's warm-up
/// measures too.
pub const WARM_UP: Duration = Duration::from_millis(500);

/// Latency figures, medians over repetitions. The wall times and the GPU times come from
/// separate calls (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Latency {
    /// Median wall time of a 50000-point batch through the untimed call, divided by 50000, in
    /// nanoseconds (upload, kernels, readback and the host's work).
    pub per_point_ns: f64,
    /// Median wall time of a 3000-point batch through the untimed call, in microseconds.
    pub batch3000_us: f64,
    /// Median kernel time per point of the 50000 batch from timestamp queries, in nanoseconds,
    /// where the adapter has them (from the timed calls only).
    pub gpu_per_point_ns: Option<f64>,
    /// Median kernel time of the 3000 batch from timestamp queries, in microseconds, where the
    /// adapter has them (from the timed calls only).
    #[serde(default)]
    pub gpu_batch3000_us: Option<f64>,
    /// Repetitions behind each median, at least (the smaller batch gets more on a GPU).
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

/// Calls `f` until `duration` has passed, at least once (the call that pays for pipeline
/// compilation and buffer creation); returns the number of calls.
pub fn warm_up<E>(duration: Duration, mut f: impl FnMut() -> Result<(), E>) -> Result<usize, E> {
    let start = Instant::now();
    let mut calls = 0;
    while calls == 0 || start.elapsed() < duration {
        f()?;
        calls += 1;
    }
    Ok(calls)
}

/// How long the reports keep timing each batch size once they have [`MIN_REPS`] repetitions:
/// on a GPU a repetition takes well under a millisecond, and ten in a row of each call gave a
/// SIREN `default` fit's wall-over-kernel difference from 50 to 84 µs across six fits on H100s
/// (docs/benchmarks, session 20); on lavapipe ten repetitions mostly take longer than this.
pub const MEASURE_FOR: Duration = Duration::from_millis(250);
/// The most repetitions [`MEASURE_FOR`] adds up to per batch size.
pub const MAX_REPS: usize = 2000;

/// Measures `eval` (a batch evaluation returning one value per point) on the first
/// [`PER_POINT_BATCH`] and [`LATENCY_BATCH`] of `points`, after evaluating the large batch
/// for `warm` (the reports use [`WARM_UP`]): at least `reps` times each (and [`MIN_REPS`];
/// [`FEW_REPS`] once they have taken [`SLOW_AFTER`]), and on for `measure_for` (the reports
/// use [`MEASURE_FOR`]) up to [`MAX_REPS`]. `points` is cycled if shorter. Wall times only:
/// the GPU fields are `None` (see [`measure_latency_timed`]).
pub fn measure_latency<E>(
    points: &[Vec3],
    reps: usize,
    warm: Duration,
    measure_for: Duration,
    eval: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
) -> Result<Latency, E> {
    measure_latency_timed(points, reps, warm, measure_for, eval, |_| {
        Ok((Vec::new(), None))
    })
}

/// [`measure_latency`] with kernel times too: the wall figures time `eval` (the plain public
/// call), and `timed` (e.g. `NeuralSdf::eval_normalized_timed`, returning the batch's GPU time
/// in nanoseconds where it can) is called separately for the GPU figures. The two alternate,
/// one call each per repetition, so that both medians come from the same stretch of the
/// GPU's clocks and load and their difference is the cost of the round trip; the wall clock
/// never times a timed call. A GPU figure is `None` unless every timed repetition of its
/// batch reported a time.
pub fn measure_latency_timed<E>(
    points: &[Vec3],
    reps: usize,
    warm: Duration,
    measure_for: Duration,
    mut eval: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
    mut timed: impl FnMut(&[Vec3]) -> Result<(Vec<f32>, Option<u64>), E>,
) -> Result<Latency, E> {
    assert!(!points.is_empty(), "latency needs points");
    let batch = |n: usize| -> Vec<Vec3> { points.iter().copied().cycle().take(n).collect() };
    let big = batch(PER_POINT_BATCH);
    let small = batch(LATENCY_BATCH);
    let reps = reps.max(MIN_REPS);
    warm_up(warm, || eval(&big).map(|_| ()))?;
    let mut measure = |pts: &[Vec3]| -> Result<(f64, Option<f64>, usize), E> {
        // One call of each first, untimed: it pays for buffers of this size and the timer.
        eval(pts)?;
        timed(pts)?;
        let start = Instant::now();
        let (mut wall, mut ns) = (Vec::with_capacity(reps), Vec::with_capacity(reps));
        while !enough_reps(wall.len(), reps, start.elapsed())
            || (start.elapsed() < measure_for && wall.len() < MAX_REPS)
        {
            let t = Instant::now();
            eval(pts)?;
            wall.push(t.elapsed().as_secs_f64());
            ns.push(timed(pts)?.1.map(|t| t as f64));
        }
        let count = wall.len();
        let ns: Option<Vec<f64>> = ns.into_iter().collect();
        Ok((median(wall), ns.map(median), count))
    };
    let (per_batch, gpu_big, big_reps) = measure(&big)?;
    let (latency, gpu_small, small_reps) = measure(&small)?;
    Ok(Latency {
        per_point_ns: per_batch * 1e9 / PER_POINT_BATCH as f64,
        batch3000_us: latency * 1e6,
        gpu_per_point_ns: gpu_big.map(|ns| ns / PER_POINT_BATCH as f64),
        gpu_batch3000_us: gpu_small.map(|ns| ns / 1e3),
        reps: big_reps.min(small_reps),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slow repetitions stop at three; fast ones, or fewer than three however slow, go on to
    /// the count asked for.
    #[test]
    fn slow_repetitions_stop_at_a_few() {
        let slow = SLOW_AFTER + Duration::from_millis(1);
        assert!(!enough_reps(FEW_REPS - 1, MIN_REPS, slow));
        assert!(enough_reps(FEW_REPS, MIN_REPS, slow));
        assert!(!enough_reps(FEW_REPS, MIN_REPS, SLOW_AFTER / 2));
        assert!(!enough_reps(MIN_REPS - 1, MIN_REPS, Duration::ZERO));
        assert!(enough_reps(MIN_REPS, MIN_REPS, Duration::ZERO));
    }

    #[test]
    fn median_of_odd_and_even_samples() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 2.5);
    }

    #[test]
    fn latency_calls_eval_on_the_documented_batches() {
        let mut sizes = Vec::new();
        let lat = measure_latency(&[Vec3::ZERO; 7], 3, Duration::ZERO, Duration::ZERO, |p| {
            sizes.push(p.len());
            Ok::<_, ()>(vec![0.0; p.len()])
        })
        .unwrap();
        // The large batch: one warm-up call (Duration::ZERO still makes one), one untimed call,
        // then MIN_REPS timed ones; the small batch: one untimed call and MIN_REPS timed ones.
        assert_eq!(
            sizes.iter().filter(|&&n| n == PER_POINT_BATCH).count(),
            MIN_REPS + 2
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
        let lat = measure_latency(&[Vec3::ZERO], 1, Duration::ZERO, Duration::ZERO, |p| {
            Ok::<_, ()>(vec![0.0; p.len()])
        })
        .unwrap();
        assert_eq!(lat.gpu_per_point_ns, None);
        assert_eq!(lat.gpu_batch3000_us, None);
    }

    #[test]
    fn wall_and_gpu_times_come_from_separate_alternating_calls() {
        // The untimed call is the only one the wall clock sees, and the two alternate. The
        // timed call's untimed first call reports a huge time that must be ignored, its
        // repetitions 1, 2, ..., MIN_REPS ms (50000) and 7 µs (3000).
        let calls = std::cell::RefCell::new(Vec::new());
        let mut timed_big = 0u64;
        let lat = measure_latency_timed(
            &[Vec3::ONE; 3],
            1,
            Duration::ZERO,
            Duration::ZERO,
            |p| {
                calls.borrow_mut().push(('e', p.len()));
                Ok::<_, ()>(vec![0.0; p.len()])
            },
            |p| {
                calls.borrow_mut().push(('t', p.len()));
                let ns = if p.len() == PER_POINT_BATCH {
                    let ns = if timed_big == 0 {
                        u64::MAX / 2
                    } else {
                        timed_big * 1_000_000
                    };
                    timed_big += 1;
                    ns
                } else {
                    7_000
                };
                Ok::<_, ()>((vec![0.0; p.len()], Some(ns)))
            },
        )
        .unwrap();
        let calls = calls.into_inner();
        let plain = calls.iter().filter(|c| c.0 == 'e').count();
        assert_eq!(plain, 2 * (MIN_REPS + 1) + 1);
        assert_eq!(timed_big as usize, MIN_REPS + 1);
        // After the warm-up call, every batch alternates: eval, timed, eval, timed, ...
        for pair in calls[1..].chunks(2) {
            assert_eq!(pair[0].0, 'e', "{calls:?}");
            assert_eq!(pair[1], ('t', pair[0].1), "{calls:?}");
        }
        // Median of 1..=10 ms is 5.5 ms.
        let expected = 5.5e6 / PER_POINT_BATCH as f64;
        let got = lat.gpu_per_point_ns.expect("a GPU time");
        assert!((got - expected).abs() < 1e-9, "{got} vs {expected}");
        assert_eq!(lat.gpu_batch3000_us, Some(7.0));
    }

    #[test]
    fn measuring_goes_on_for_its_duration_up_to_max_reps() {
        // Calls that take no time reach MAX_REPS long before a minute has passed.
        let start = Instant::now();
        let lat = measure_latency(
            &[Vec3::ZERO],
            1,
            Duration::ZERO,
            Duration::from_secs(60),
            |p| Ok::<_, ()>(vec![0.0; p.len()]),
        )
        .unwrap();
        assert_eq!(lat.reps, MAX_REPS);
        assert!(start.elapsed() < Duration::from_secs(60));
        // Calls of ≥ 1 ms: the loop stops only once 30 ms have passed for each batch size.
        let start = Instant::now();
        let lat = measure_latency(
            &[Vec3::ZERO],
            1,
            Duration::ZERO,
            Duration::from_millis(30),
            |p| {
                std::thread::sleep(Duration::from_millis(1));
                Ok::<_, ()>(vec![0.0; p.len()])
            },
        )
        .unwrap();
        assert!(start.elapsed() >= Duration::from_millis(60));
        assert!((MIN_REPS..=30).contains(&lat.reps), "{} reps", lat.reps);
    }

    #[test]
    fn a_missing_gpu_time_gives_none() {
        let mut calls = 0;
        let lat = measure_latency_timed(
            &[Vec3::ZERO],
            1,
            Duration::ZERO,
            Duration::ZERO,
            |p| Ok::<_, ()>(vec![0.0; p.len()]),
            |p| {
                calls += 1;
                let ns = (calls != 3).then_some(100);
                Ok::<_, ()>((vec![0.0; p.len()], ns))
            },
        )
        .unwrap();
        assert_eq!(lat.gpu_per_point_ns, None);
        assert_eq!(lat.gpu_batch3000_us, Some(0.1));
    }

    #[test]
    fn warm_up_runs_for_its_duration_and_at_least_once() {
        let mut calls = 0;
        let count = || {
            calls += 1;
            Ok::<_, ()>(())
        };
        assert_eq!(warm_up(Duration::ZERO, count), Ok(1));
        assert_eq!(calls, 1);
        let start = Instant::now();
        let n = warm_up(Duration::from_millis(30), || {
            std::thread::sleep(Duration::from_millis(5));
            Ok::<_, ()>(())
        })
        .unwrap();
        assert!(start.elapsed() >= Duration::from_millis(30));
        // Six calls of ≥ 5 ms reach 30 ms; fewer only if the sleeps overshoot.
        assert!((1..=6).contains(&n), "{n} calls");
    }

    #[test]
    fn errors_propagate() {
        let r = measure_latency(&[Vec3::ZERO], 1, Duration::ZERO, Duration::ZERO, |_| {
            Err::<Vec<f32>, _>("boom")
        });
        assert_eq!(r.unwrap_err(), "boom");
    }
}
