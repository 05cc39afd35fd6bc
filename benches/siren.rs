//! SIREN on the GPU (lavapipe on the development machine): inference per point at a batch of
//! 50 000, the latency of a batch of 3000, and one training step of 10^4 points, for the
//! `small` and `default` presets. Run: `cargo bench --bench siren`. Set `SIREN_BENCH_PRESETS`
//! to `small` or `default` to run one preset only. On a CPU adapter (lavapipe) the `default`
//! preset runs only the 3000-point latency (a batch of 50 000 or a training step takes tens of
//! seconds per iteration there); set `SIREN_BENCH_FULL=1` to run everything anyway.
//! `SIREN_BENCH_KERNELS` forces a layer-kernel family (`row-blocked`, `gemm`, `tiled` or
//! `coop`, inference on f16 cooperative matrices where the adapter has them; default:
//! `LayerKernels::Auto`), and `SIREN_BENCH_FUSED_MAX` the largest inference batch of
//! the tiled family's fused all-layer kernel (`SirenGpu::set_fused_max_points`; 0 disables it).
//! `SIREN_BENCH_TRAIN_STEP` forces the training step (`tangents` or `ror`, reverse over reverse;
//! default: `TrainStep::Auto`), and `SIREN_BENCH_TILED_BLOCK` the tiled GEMM's register blocks
//! (`4x4`, `8x4`, `4x8` or `8x8`; default: `TiledBlock::Auto`).

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use sdf_nn::siren::{LayerKernels, TiledBlock, TrainStep};
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

fn points(n: usize) -> Vec<Vec3> {
    sdf_geom::sample::uniform_box(n, 42)
}

fn bench(c: &mut Criterion) {
    let gpu = GpuContext::shared().expect("a GPU adapter");
    eprintln!("adapter: {}", gpu.describe());
    let (mesh, _) = sdf_geom::load_mesh("tests/data/spot.obj").expect("tests/data/spot.obj");
    for (name, cfg) in presets() {
        let siren = Siren::new(cfg, 1).unwrap();
        let mut net = SirenGpu::new(gpu, &siren).unwrap();
        net.set_layer_kernels(gpu, kernels()).unwrap();
        net.set_tiled_block(gpu, tiled_block()).unwrap();
        if let Ok(v) = std::env::var("SIREN_BENCH_FUSED_MAX") {
            net.set_fused_max_points(v.parse().expect("SIREN_BENCH_FUSED_MAX: a number"));
        }
        eprintln!(
            "{name}: kernels {:?} (tiled blocks {:?}), fused for 3000 points: {}, cooperative-matrix tiles: {:?}",
            net.layer_kernels(),
            net.tiled_block(),
            net.runs_fused(gpu, 3000),
            net.coop_tile()
        );
        let macs = cfg.forward_macs();

        let mut g = c.benchmark_group(format!("siren_{name}"));
        g.sample_size(10)
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(if name == "default" { 20 } else { 5 }));
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
        eprintln!(
            "{name}: {macs} MACs per point forward ({} flop per point)",
            2 * macs
        );
        if !full {
            g.finish();
            continue;
        }

        let train = SirenTrainConfig {
            surface_per_step: 5000,
            box_per_step: 5000,
            loss_every: 4096, // the loss is read back only every 4096 steps
            ..SirenTrainConfig::default()
        };
        let mut trainer = SirenTrainer::from_mesh(gpu, &siren, &mesh, train).unwrap();
        trainer.set_layer_kernels(gpu, kernels()).unwrap();
        trainer.set_tiled_block(gpu, tiled_block()).unwrap();
        trainer.set_train_step(gpu, train_step()).unwrap();
        eprintln!(
            "{name}: train step {:?}, reverse over reverse: {}",
            trainer.net().train_step(),
            trainer.net().runs_reverse_over_reverse()
        );
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

criterion_group!(benches, bench);
criterion_main!(benches);
