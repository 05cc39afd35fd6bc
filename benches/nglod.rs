//! NGLOD on the GPU (lavapipe on the development machine): inference per point at a batch of
//! 50 000 and the latency of a batch of 3000 (criterion), for the `default` preset (its sparse
//! level holding the band around a sphere of radius 0.6, about the size of a real mesh's band),
//! the design document's dense model (`design`, what `scripts/nglod_torch_bench.py` runs as
//! `default`) and `small`; then two real training epochs of the design document's 5·10⁵ points on
//! the bunny with the `default` preset (or on
//! `tests/data/spot.obj` when `../shared/meshes` is absent), printing how each epoch's time splits
//! between the GPU loop and the CPU sampling that overlaps it.
//!
//! The hash grid's presets (`hashgrid_default`, `hashgrid_small`) are measured beside them, and
//! its `default` trains the same epochs with its own schedule.
//!
//! Run: `cargo bench --bench nglod`. `NGLOD_BENCH_EPOCHS=0` skips the training epochs;
//! `NGLOD_BENCH_MODELS=nglod` or `hashgrid` trains only one of the two, and `hashgrid_small`
//! (alone or in a list) the hash grid's `small`, the CPU adapters' default model.
//!
//! `NGLOD_BENCH_PROFILE=N` runs no criterion bench: for NGLOD `default` and the hash grid's
//! `default` (or those of `NGLOD_BENCH_MODELS`), with the points from the CPU pool and from
//! the GPU, and with one row per invocation and per subgroup (where the adapter has
//! subgroups), it trains two epochs, then times every launch of N steps on their own
//! (`NglodTrainer::profile_step`) and prints the medians, an epoch's worth of them, and the
//! second epoch's measured GPU loop beside it.

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput};
use sdf_nn::nglod::{SampleSource, ScatterMode};
use sdf_nn::{
    GpuContext, Nglod, NglodConfig, NglodGpu, NglodTrainConfig, NglodTrainer, QueryKernel,
};

/// The profile's launches of a block's draw and labelling on the GPU, which run once every
/// `refresh_every` epochs once the pool is full.
const BLOCK_LAUNCHES: [&str; 5] = [
    "draw",
    "bin_count",
    "bin_scan",
    "bin_scatter",
    "signed_distance",
];

fn inference(c: &mut Criterion, gpu: &GpuContext) {
    for (name, cfg) in [
        ("default", NglodConfig::default_preset()),
        ("design", NglodConfig::design_document()),
        ("small", NglodConfig::small()),
        ("hashgrid_default", NglodConfig::hashgrid_default()),
        ("hashgrid_small", NglodConfig::hashgrid_small()),
    ] {
        let mut model = Nglod::new(cfg).unwrap();
        if model.needs_bands() {
            model.place_bands(|p| (p.length() - 0.6).abs()).unwrap();
        }
        let net = NglodGpu::new(gpu, &model, ScatterMode::Auto).unwrap();
        let mut g = c.benchmark_group(format!("nglod_{name}"));
        g.sample_size(10)
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(5));
        for n in [50_000usize, 3000] {
            let pts = sdf_geom::sample::uniform_box(n, 42);
            net.eval(gpu, &pts, None).unwrap(); // compile and allocate outside the timing
            g.throughput(Throughput::Elements(n as u64));
            g.bench_with_input(BenchmarkId::new("eval", n), &pts, |b, pts| {
                b.iter(|| net.eval(gpu, pts, None).unwrap())
            });
        }
        g.finish();
    }
}

fn epoch_split(gpu: &GpuContext) {
    let epochs: usize = std::env::var("NGLOD_BENCH_EPOCHS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    if epochs == 0 {
        return;
    }
    let bunny = "../shared/meshes/stanford-bunny.obj";
    let path = if std::path::Path::new(bunny).exists() {
        bunny
    } else {
        "tests/data/spot.obj"
    };
    let (mesh, _) = sdf_geom::load_mesh(path).expect("bench mesh");
    let (unit, _) = mesh.normalized();
    for (name, model, schedule) in trained_models() {
        let config = NglodTrainConfig { epochs, ..schedule };
        split_one(gpu, name, path, &unit, Nglod::new(model).unwrap(), config);
    }
}

/// The models the training benches train, each with its schedule: NGLOD and the hash grid's
/// `default`, or those `NGLOD_BENCH_MODELS` names, by family (`nglod`, `hashgrid`: their
/// `default`) or by name (`hashgrid_small` too, the CPU adapters' default model).
fn trained_models() -> Vec<(&'static str, NglodConfig, NglodTrainConfig)> {
    let which = std::env::var("NGLOD_BENCH_MODELS").unwrap_or_default();
    [
        (
            "nglod_default",
            NglodConfig::default_preset(),
            NglodTrainConfig::default(),
        ),
        (
            "hashgrid_default",
            NglodConfig::hashgrid_default(),
            NglodTrainConfig::hashgrid(),
        ),
        (
            "hashgrid_small",
            NglodConfig::hashgrid_small(),
            NglodTrainConfig::hashgrid(),
        ),
    ]
    .into_iter()
    .filter(|(name, _, _)| {
        let family = name.split('_').next().unwrap_or(name);
        let by_family = name.ends_with("_default") && which.split(',').any(|w| w == family);
        let by_name = which.split(',').any(|w| w == *name);
        (which.is_empty() && name.ends_with("_default")) || by_family || by_name
    })
    .collect()
}

/// The training kernels this adapter runs.
fn train_kernels(gpu: &GpuContext) -> Vec<QueryKernel> {
    let mut kernels = vec![QueryKernel::PerInvocation];
    if gpu.subgroups_within(64).is_some() {
        kernels.push(QueryKernel::PerSubgroup);
    }
    kernels
}

/// `NGLOD_BENCH_PROFILE=steps`: the per-launch profile of a training step.
fn profile(gpu: &GpuContext, steps: usize) {
    let steps = steps.max(1);
    let Some(mut profiler) = sdf_nn::gpu::PassProfiler::new(gpu, 64) else {
        println!(
            "{} has no timestamp queries: nothing to profile",
            gpu.describe()
        );
        return;
    };
    let (mesh, _) = sdf_geom::load_mesh("tests/data/spot.obj").expect("tests/data/spot.obj");
    let (unit, _) = mesh.normalized();
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    for (name, model, schedule) in trained_models() {
        for source in [SampleSource::CpuPool, SampleSource::Gpu] {
            for kernel in train_kernels(gpu) {
                let config = NglodTrainConfig {
                    epochs: 2,
                    sample_source: source,
                    kernel: Some(kernel),
                    ..schedule.clone()
                };
                let model = Nglod::new(model.clone()).unwrap();
                let mut trainer = NglodTrainer::new(gpu, &model, &unit, config).unwrap();
                let report = trainer.train().unwrap();
                let epoch = report.epochs.last().expect("two epochs");
                let mut rows: Vec<(String, Vec<f64>)> = Vec::new();
                for _ in 0..steps {
                    let times = trainer
                        .profile_step(&mut profiler, source == SampleSource::Gpu)
                        .unwrap();
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
                let per_epoch = epoch.steps as f64;
                println!(
                    "{name}, points from {}, one row per {}: {} steps per epoch, medians of {steps} profiled steps",
                    source.name(),
                    kernel.name(),
                    epoch.steps
                );
                println!("| launch | GPU µs | per epoch, ms |\n| --- | --- | --- |");
                let mut epoch_ms = 0.0;
                for (label, mut v) in rows {
                    let m = median(&mut v);
                    // Once the pool is full a block is drawn once every `refresh_every`
                    // epochs (the measured second epoch, still filling it, draws one), the
                    // gather runs once an epoch, the rest once a step.
                    let times = if BLOCK_LAUNCHES.contains(&label.as_str()) {
                        1.0 / trainer.config().refresh_every as f64
                    } else if label == "gather" {
                        1.0
                    } else {
                        per_epoch
                    };
                    epoch_ms += m * times / 1e3;
                    println!("| {label} | {m:.1} | {:.2} |", m * times / 1e3);
                }
                println!(
                    "| sum once the pool is full, each launch in its own pass | | {epoch_ms:.2} |\n| the second epoch's step loop, measured (wall) | | {:.2} |",
                    epoch.gpu_seconds * 1e3
                );
            }
        }
    }
}

/// Trains `model` on `unit` and prints each epoch's split.
fn split_one(
    gpu: &GpuContext,
    name: &str,
    path: &str,
    unit: &sdf_geom::Mesh,
    model: Nglod,
    config: NglodTrainConfig,
) {
    let mut trainer = NglodTrainer::new(gpu, &model, unit, config).unwrap();
    println!(
        "{name} epoch split on {path} ({} faces), 5e5 points/epoch, batch {}:",
        unit.triangles.len(),
        trainer.config().batch_size
    );
    let report = trainer
        .train_with(|e| {
            println!(
                "  epoch {}: {} steps, GPU loop {:.2} s, sampling {:.2} s (overlapped), stall {:.2} s, loss {:.3e}",
                e.epoch, e.steps, e.gpu_seconds, e.sampling_seconds, e.stall_seconds, e.loss
            )
        })
        .unwrap();
    println!(
        "  total {:.2} s: GPU {:.2} s, sampling {:.2} s, stalls {:.2} s",
        report.total_seconds, report.gpu_seconds, report.sampling_seconds, report.stall_seconds
    );
}

fn main() {
    let gpu = GpuContext::shared().expect("a GPU adapter");
    eprintln!("adapter: {}", gpu.describe());
    if let Ok(steps) = std::env::var("NGLOD_BENCH_PROFILE") {
        profile(
            gpu,
            steps
                .parse()
                .expect("NGLOD_BENCH_PROFILE: a number of steps"),
        );
        return;
    }
    let mut c = Criterion::default().configure_from_args();
    inference(&mut c, gpu);
    epoch_split(gpu);
    c.final_summary();
}
