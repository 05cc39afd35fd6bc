//! Epoch times of NGLOD training with its two sources of points: the CPU pool
//! (`SampleSource::CpuPool`) and draws labelled on the GPU (`SampleSource::Gpu`), same mesh,
//! model, mixture and seed; and the time of one epoch's draw and labels alone on each side.
//!
//! `cargo run -p sdf-nn --example nglod_sample_source -- tests/data/spot.obj --points 50000
//! --epochs 4 --preset small --batch 512 [--pool BLOCKS,EVERY] [--sources cpu-pool,gpu]`
//!
//! `--pool` sets both sources' pool (`NglodTrainConfig::pool_blocks`, `refresh_every`; the
//! trainer's default 4,4; 1,1 draws fresh points every epoch); `--sources` trains only those
//! named.
//!
//! Points per epoch are split 1 : 2 : 2 (uniform, near the surface with σ = 0.01, on it), as the
//! trainer's default. The first epoch includes the first pool block's wait (CPU pool) and each
//! pipeline's first compilation; the figures to compare are the later epochs'.

use std::error::Error;
use std::time::Instant;

use sdf_geom::{SignedDistance, load_mesh, sample};
use sdf_nn::ground_truth::{GpuGroundTruth, GpuSampler, LabelKind, SampleSpec, SampleTable};
use sdf_nn::nglod::SampleSource;
use sdf_nn::{GpuContext, Nglod, NglodConfig, NglodTrainConfig, NglodTrainer};

fn main() -> Result<(), Box<dyn Error>> {
    let mut mesh_path =
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/data/spot.obj").to_owned();
    let (mut points, mut epochs, mut batch) = (50_000usize, 4usize, 512u32);
    let mut preset = "small".to_owned();
    let defaults = NglodTrainConfig::default();
    let mut pool = (defaults.pool_blocks, defaults.refresh_every);
    let mut sources = vec![SampleSource::CpuPool, SampleSource::Gpu];
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--points" => points = value()?.parse()?,
            "--epochs" => epochs = value()?.parse()?,
            "--batch" => batch = value()?.parse()?,
            "--preset" => preset = value()?,
            "--pool" => {
                let v = value()?;
                let (b, e) = v.split_once(',').ok_or("--pool takes BLOCKS,EVERY")?;
                pool = (b.parse()?, e.parse()?);
            }
            "--sources" => {
                sources = value()?
                    .split(',')
                    .map(|s| match s {
                        "cpu-pool" => Ok(SampleSource::CpuPool),
                        "gpu" => Ok(SampleSource::Gpu),
                        other => Err(format!("unknown source {other}: cpu-pool or gpu")),
                    })
                    .collect::<Result<_, _>>()?;
            }
            _ => mesh_path = a.clone(),
        }
    }
    let gpu = GpuContext::new()?;
    println!(
        "adapter: {}; CPU threads: {}",
        gpu.describe(),
        rayon::current_num_threads()
    );
    let mesh = load_mesh(&mesh_path)?.0.normalized().0;
    let model_config = match preset.as_str() {
        "small" => NglodConfig::small(),
        "default" => NglodConfig::default_preset(),
        other => return Err(format!("unknown preset {other}: small or default").into()),
    };
    let (uniform, near) = (points / 5, 2 * points / 5);
    let surface = points - uniform - near;
    println!(
        "{mesh_path}: {} triangles; {preset} preset, {points} points per epoch \
         ({uniform} uniform, {near} near, {surface} on the surface), batch {batch}, pool {},{}",
        mesh.triangles.len(),
        pool.0,
        pool.1
    );

    // One epoch's draw and labels alone.
    let cpu = SignedDistance::new(&mesh)?;
    let t = Instant::now();
    let mut p = sample::uniform_box(uniform, 1);
    p.extend(sample::near_surface(&mesh, near, 0.01, 2));
    let labels = cpu.signed_distance_batch(&p);
    let on = sample::surface(&mesh, surface, 3).points;
    println!(
        "draw + label, CPU (sdf-geom samplers, SignedDistance on {} threads): {:.3} s for {} points",
        rayon::current_num_threads(),
        t.elapsed().as_secs_f64(),
        labels.len() + on.len()
    );
    let gt = GpuGroundTruth::new(&gpu, &cpu)?;
    let sampler = GpuSampler::new(&gpu, &SampleTable::new(&mesh)?)?;
    let spec = |seed| SampleSpec {
        uniform: uniform as u32,
        near: near as u32,
        surface: surface as u32,
        sigma: 0.01,
        seed,
        stream: 0,
        shuffle: true,
    };
    sampler.draw_and_label(&gpu, &gt, &spec(0), LabelKind::Signed)?; // compiles the pipelines
    sampler.draw(&gpu, &spec(0))?;
    let t = Instant::now();
    let p = sampler.draw(&gpu, &spec(1))?;
    println!(
        "draw alone, GPU (GpuSampler, read back): {:.3} s for {} points",
        t.elapsed().as_secs_f64(),
        p.len()
    );
    let t = Instant::now();
    let (p, _) = sampler.draw_and_label(&gpu, &gt, &spec(1), LabelKind::Signed)?;
    println!(
        "draw + label, GPU (GpuSampler + GpuGroundTruth, one submission, read back): {:.3} s for {} points",
        t.elapsed().as_secs_f64(),
        p.len()
    );

    // The labelling's share: the same uniform and near-surface points labelled by
    // GpuGroundTruth::signed_distance, which groups them by cell first.
    let unshuffled = sampler.draw(
        &gpu,
        &SampleSpec {
            shuffle: false,
            ..spec(1)
        },
    )?;
    let to_label = &unshuffled[..uniform + near];
    gt.signed_distance(&gpu, to_label)?;
    let t = Instant::now();
    gt.signed_distance(&gpu, to_label)?;
    println!(
        "labels alone, GPU, grouped by cell (GpuGroundTruth::signed_distance, uploaded and read \
         back): {:.3} s for {} points",
        t.elapsed().as_secs_f64(),
        to_label.len()
    );

    for source in sources {
        let config = NglodTrainConfig {
            epochs,
            uniform_points: uniform,
            near_points: near,
            surface_points: surface,
            batch_size: batch,
            seed: 3,
            sample_source: source,
            pool_blocks: pool.0,
            refresh_every: pool.1,
            ..Default::default()
        };
        let model = Nglod::new(model_config.clone())?;
        let mut trainer = NglodTrainer::new(&gpu, &model, &mesh, config)?;
        let mut last = Instant::now();
        let mut walls = Vec::new();
        let report = trainer.train_with(|e| {
            let wall = last.elapsed().as_secs_f64();
            last = Instant::now();
            walls.push(wall);
            println!(
                "  {} epoch {}: wall {wall:.2} s, GPU loop {:.2} s, stall {:.2} s, loss {:.3e}",
                source.name(),
                e.epoch,
                e.gpu_seconds,
                e.stall_seconds,
                e.loss
            );
        })?;
        let later = &walls[1.min(walls.len() - 1)..];
        println!(
            "{}: mean wall time per epoch after the first {:.3} s ({} steps in all, total {:.2} s)",
            source.name(),
            later.iter().sum::<f64>() / later.len() as f64,
            report.steps,
            report.total_seconds
        );
    }
    Ok(())
}
