//! SIREN on the GPU (lavapipe on the development machine): inference per point at a batch of
//! 50 000, the latency of a batch of 3000, and one training step of 10^4 points, for the
//! `small` and `default` presets. Run: `cargo bench --bench siren`. Set `SIREN_BENCH_PRESETS`
//! to `small` or `default` to run one preset only. On a CPU adapter (lavapipe) the `default`
//! preset runs only the 3000-point latency (a batch of 50 000 or a training step takes tens of
//! seconds per iteration there); set `SIREN_BENCH_FULL=1` to run everything anyway.
//! `SIREN_BENCH_KERNELS` forces a layer-kernel family (`row-blocked`, `gemm`, `tiled` or
//! `coop`, inference on f16 cooperative matrices where the adapter has them; default:
//! `LayerKernels::Auto`), and `SIREN_BENCH_FUSED_MAX` the largest inference batch of
//! the tiled family's fused all-layer kernel (`SirenGpuOptions::fused_max_points`; 0 disables
//! it) and `SIREN_BENCH_FUSED_ROW_BLOCKS` its register blocks of rows per invocation (1 to 3,
//! `SirenGpuOptions::fused_row_blocks`; default 1).
//! `eval_resident` times the same network served (`NeuralSdf`, whose `Auto` runs batches of values
//! of at least `COOP_AUTO_MIN_POINTS` on cooperative matrices where the GPU has them) with the
//! points already on the GPU and the values left there: `record_query`, submit, wait, as
//! PyTorch's eval of a device tensor is timed.
//! `SIREN_BENCH_TRAIN_STEP` forces the training step (`tangents` or `ror`, reverse over reverse;
//! default: `TrainStep::Auto`), and `SIREN_BENCH_TILED_BLOCK` the tiled GEMM's register blocks
//! (`4x4`, `8x4`, `4x8` or `8x8`; default: `TiledBlock::Auto`).
//!
//! `SIREN_BENCH_PROFILE=N` runs no criterion bench: for each preset it profiles N training
//! steps (after a warm-up of about half a second), every launch in its own pass timed by GPU
//! timestamps (`SirenTrainer::profile_step`), and prints each launch's median GPU time, its
//! share, their sum, and the median wall time of a plain step beside it: where a step's time
//! goes, for the issue's ≤ 2 ms.

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group};
use glam::Vec3;
use sdf_nn::siren::{LayerKernels, SirenGpuOptions, TiledBlock, TrainStep};
use sdf_nn::{GpuContext, Siren, SirenConfig, SirenGpu, SirenTrainConfig, SirenTrainer};

fn presets() -> Vec<(&'static str, SirenConfig)> {
    let which = std::env::var("SIREN_BENCH_PRESETS").unwrap_or_default();
    [
        ("small", SirenConfig::small()),
        ("default", SirenConfig::default()),
    ]
    .into_iter()
    .filter(|(n, _)| which.is_empty() || which.split(',').any(|w| w == *n))
    .collect()
}

/// The value variable `var` names (its `auto` when unset or empty).
fn named<T: std::str::FromStr<Err = String> + Default>(var: &str) -> T {
    match std::env::var(var).as_deref() {
        Err(_) | Ok("") => T::default(),
        Ok(name) => name.parse().unwrap_or_else(|e| panic!("{var}: {e}")),
    }
}

/// The family `SIREN_BENCH_KERNELS` names.
fn kernels() -> LayerKernels {
    named("SIREN_BENCH_KERNELS")
}

/// The register blocks `SIREN_BENCH_TILED_BLOCK` names.
fn tiled_block() -> TiledBlock {
    named("SIREN_BENCH_TILED_BLOCK")
}

/// The training step `SIREN_BENCH_TRAIN_STEP` names.
fn train_step() -> TrainStep {
    match std::env::var("SIREN_BENCH_TRAIN_STEP").as_deref() {
        Err(_) | Ok("" | "auto") => TrainStep::Auto,
        Ok("tangents") => TrainStep::Tangents,
        Ok("ror") => TrainStep::ReverseOverReverse,
        Ok(other) => panic!("SIREN_BENCH_TRAIN_STEP={other}: expected auto, tangents or ror"),
    }
}

/// The options the knobs name: kernels, tiled blocks, fused kernel and training step.
fn options() -> SirenGpuOptions {
    let number = |var: &str| {
        std::env::var(var)
            .ok()
            .map(|v| v.parse().unwrap_or_else(|_| panic!("{var}: a number")))
    };
    let defaults = SirenGpuOptions::default();
    SirenGpuOptions {
        kernels: kernels(),
        tiled_block: tiled_block(),
        fused_max_points: number("SIREN_BENCH_FUSED_MAX"),
        fused_row_blocks: number("SIREN_BENCH_FUSED_ROW_BLOCKS")
            .unwrap_or(defaults.fused_row_blocks),
        train_step: train_step(),
        ..defaults
    }
}

fn points(n: usize) -> Vec<Vec3> {
    sdf_geom::sample::uniform_box(n, 42)
}

fn bench(c: &mut Criterion) {
    let gpu = GpuContext::shared().expect("a GPU adapter");
    eprintln!("adapter: {}", gpu.describe());
    let (mesh, _) = sdf_geom::load_mesh("tests/data/spot.obj").expect("tests/data/spot.obj");
    for (name, cfg) in presets() {
        let siren = Siren::new(cfg, 1).unwrap();
        let mut net = SirenGpu::with_options(gpu, &siren, &options()).unwrap();
        eprintln!(
            "{name}: kernels {:?} (tiled blocks {:?}), fused for 3000 points: {} (row blocks {:?}), cooperative-matrix tiles: {:?}",
            net.options().kernels,
            net.options().tiled_block,
            net.runs_fused(gpu, 3000),
            net.fused_row_blocks(gpu),
            net.coop_tile()
        );
        let macs = cfg.forward_macs();

        let mut g = c.benchmark_group(format!("siren_{name}"));
        // An iteration of `default` takes seconds on lavapipe; on a GPU it takes milliseconds,
        // and 3 s of samples are thousands of them (a lent GPU's minutes are few).
        let seconds = match (gpu.is_cpu(), name) {
            (true, "default") => 20,
            (true, _) => 5,
            (false, _) => 3,
        };
        g.sample_size(if gpu.is_cpu() { 10 } else { 30 })
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(seconds));
        let full =
            !gpu.is_cpu() || name == "small" || std::env::var_os("SIREN_BENCH_FULL").is_some();
        let sizes: &[usize] = if full { &[50_000, 3000] } else { &[3000] };
        for &n in sizes {
            let pts = points(n);
            net.eval(gpu, &pts).unwrap(); // compile and allocate outside the timing
            g.throughput(Throughput::Elements(n as u64));
            g.bench_with_input(BenchmarkId::new("eval", n), &pts, |b, pts| {
                b.iter(|| net.eval(gpu, pts).unwrap())
            });
        }
        // The same network served (`NeuralSdf`, whose `Auto` runs large batches of values on
        // cooperative matrices where the GPU has them), points and values left on the GPU:
        // a submission of `record_query` waited for, what PyTorch's eval of a device tensor
        // measures (scripts/siren_torch_bench.py).
        let mut served = sdf_nn::NeuralSdf::from_model_file(
            siren.to_model_file(sdf_nn::Normalization::identity(), serde_json::Value::Null),
        )
        .unwrap();
        served.set_siren_kernels(kernels()).unwrap();
        for &n in sizes {
            let mut buffers = served
                .create_query_buffers(
                    gpu,
                    &sdf_nn::QueryBuffersDescriptor {
                        capacity: n as u32,
                        space: sdf_nn::QuerySpace::Normalized,
                        ..Default::default()
                    },
                )
                .unwrap();
            buffers.upload(gpu, &points(n)).unwrap();
            let mut resident = || {
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                served
                    .record_query(gpu, &mut enc, &mut buffers, n as u32)
                    .unwrap();
                gpu.queue().submit([enc.finish()]);
                gpu.wait().unwrap();
            };
            resident(); // compile and allocate outside the timing
            g.throughput(Throughput::Elements(n as u64));
            g.bench_function(BenchmarkId::new("eval_resident", n), |b| {
                b.iter(&mut resident)
            });
        }
        eprintln!(
            "{name}: {macs} MACs per point forward ({} flop per point)",
            2 * macs
        );
        if !full {
            g.finish();
            continue;
        }

        let mut trainer = trainer(gpu, name, &siren, &mesh);
        trainer.step(gpu).unwrap();
        gpu.wait().unwrap();
        g.throughput(Throughput::Elements(10_000));
        g.bench_function(BenchmarkId::new("train_step", 10_000), |b| {
            b.iter(|| {
                trainer.step(gpu).unwrap();
                gpu.wait().unwrap();
            })
        });
        g.finish();
    }
}

/// The bench's trainer: 5000 + 5000 points per step on `mesh`, the knobs' kernels and step.
fn trainer(gpu: &GpuContext, name: &str, siren: &Siren, mesh: &sdf_geom::Mesh) -> SirenTrainer {
    let train = SirenTrainConfig {
        surface_per_step: 5000,
        box_per_step: 5000,
        loss_every: 4096, // the loss is read back only every 4096 steps
        ..SirenTrainConfig::default()
    };
    let mut trainer = SirenTrainer::from_mesh(gpu, siren, mesh, train).unwrap();
    trainer.set_net_options(gpu, &options()).unwrap();
    let net = trainer.net();
    eprintln!(
        "{name}: train step {:?}, reverse over reverse: {}",
        net.options().train_step,
        net.runs_reverse_over_reverse()
    );
    trainer
}

/// `SIREN_BENCH_PROFILE=steps`: the per-launch profile of a training step, per preset.
fn profile(steps: usize) {
    let gpu = GpuContext::shared().expect("a GPU adapter");
    println!("adapter: {}", gpu.describe());
    let Some(mut profiler) = sdf_nn::gpu::PassProfiler::new(gpu, 512) else {
        println!(
            "{} has no timestamp queries: nothing to profile",
            gpu.describe()
        );
        return;
    };
    let (mesh, _) = sdf_geom::load_mesh("tests/data/spot.obj").expect("tests/data/spot.obj");
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    for (name, cfg) in presets() {
        let siren = Siren::new(cfg, 1).unwrap();
        let mut trainer = trainer(gpu, name, &siren, &mesh);
        // Warm up: compile, allocate, and raise an idle GPU's clocks.
        let start = std::time::Instant::now();
        while start.elapsed() < Duration::from_millis(500) {
            trainer.step(gpu).unwrap();
            gpu.wait().unwrap();
        }
        let mut rows: Vec<(String, Vec<f64>)> = Vec::new();
        let mut wall = Vec::with_capacity(steps);
        for _ in 0..steps.max(1) {
            // A plain step's wall time, then a profiled one, in turn.
            let t = std::time::Instant::now();
            trainer.step(gpu).unwrap();
            gpu.wait().unwrap();
            wall.push(t.elapsed().as_secs_f64() * 1e6);
            let times = trainer.profile_step(gpu, &mut profiler).unwrap();
            if rows.is_empty() {
                rows = times
                    .iter()
                    .map(|t| (t.label.clone(), Vec::new()))
                    .collect();
            }
            for ((_, v), t) in rows.iter_mut().zip(&times) {
                v.push(t.ns as f64 / 1e3);
            }
        }
        let medians: Vec<(String, f64)> = rows
            .into_iter()
            .map(|(label, mut v)| (label, median(&mut v)))
            .collect();
        let total: f64 = medians.iter().map(|(_, m)| m).sum();
        println!(
            "siren_{name} training step of 10^4 points, {} launches, median of {steps} profiled steps:",
            medians.len()
        );
        println!("| # | launch | GPU µs | share |\n| --- | --- | --- | --- |");
        for (i, (label, m)) in medians.iter().enumerate() {
            println!("| {i} | {label} | {m:.1} | {:.1} % |", 100.0 * m / total);
        }
        println!(
            "| | sum of the launches (each in its own pass) | {total:.1} | |\n| | a plain step, wall (median of {steps}) | {:.1} | |",
            median(&mut wall)
        );
    }
}

criterion_group!(benches, bench);

fn main() {
    if let Ok(steps) = std::env::var("SIREN_BENCH_PROFILE") {
        profile(
            steps
                .parse()
                .expect("SIREN_BENCH_PROFILE: a number of steps"),
        );
        return;
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}
