//! Measures grid-model settings side by side on one mesh: each trains for the same time budget
//! (planned from its first epoch, as `train` plans a CPU run) and is scored on the design
//! document's two sets (F1 in the box and near the surface, 100 000 points each), as trained
//! (f32 on the GPU) and as saved (f16 grids, evaluated on the CPU). How the hash
//! grid's presets and schedule were chosen (docs/benchmarks).
//!
//! ```sh
//! cargo run --release -p sdf-eval --example grid_sweep -- MESH SECONDS SPEC [SPEC ...]
//! ```
//!
//! `SECONDS` may be `eN` instead: N epochs each, whatever they take (figures free of the
//! planner's estimate, for comparing settings on a busy machine). On a GPU the points are drawn
//! and labelled there (`--ground-truth auto`'s choice: `SampleSource::Gpu`), as `train` does.
//!
//! A SPEC is `nglod` (the default preset and schedule), `nglod-small`, `hashgrid` /
//! `hashgrid-small` (the presets with the hash grid's schedule), or
//! `hash:L,NMIN,NMAX,F,LOG2T,H` for a hash grid of L levels from NMIN to NMAX cells, F features,
//! tables of 2^LOG2T entries and H hidden units; any of them may end in `@LR,BATCH` to change
//! the learning rate and the batch size, and in `@LR,BATCH,lazy` to make Adam lazy on the grid
//! (`NglodTrainConfig::lazy_adam`).

use std::error::Error;
use std::sync::Arc;
use std::time::Instant;

use sdf_eval::metrics::{DEFAULT_EVAL_POINTS, EVAL_SEED, EvalSets};
use sdf_geom::SignedDistance;
use sdf_nn::ground_truth::{GroundTruthDevice, GroundTruthPath};
use sdf_nn::nglod::{SampleSource, TimeBudget};
use sdf_nn::{GpuContext, Labeller, Nglod, NglodConfig, NglodTrainConfig, NglodTrainer};

fn parse(spec: &str) -> Result<(NglodConfig, NglodTrainConfig), Box<dyn Error>> {
    let (model, schedule) = spec.split_once('@').unwrap_or((spec, ""));
    let (config, mut train) = match model {
        "nglod" => (NglodConfig::default_preset(), NglodTrainConfig::default()),
        "nglod-small" => (NglodConfig::small(), NglodTrainConfig::default()),
        "hashgrid" => (
            NglodConfig::hashgrid_default(),
            NglodTrainConfig::hashgrid(),
        ),
        "hashgrid-small" => (NglodConfig::hashgrid_small(), NglodTrainConfig::hashgrid()),
        other => {
            let numbers = other
                .strip_prefix("hash:")
                .ok_or_else(|| format!("unknown spec `{other}`"))?
                .split(',')
                .map(str::parse)
                .collect::<Result<Vec<u32>, _>>()?;
            let [l, nmin, nmax, f, t, h] = numbers[..] else {
                return Err(format!("`{other}`: hash:L,NMIN,NMAX,F,LOG2T,H").into());
            };
            (
                NglodConfig::hashgrid(l as usize, nmin, nmax, f, t, h),
                NglodTrainConfig::hashgrid(),
            )
        }
    };
    if !schedule.is_empty() {
        let parts: Vec<&str> = schedule.split(',').collect();
        train.adam.lr = parts[0].parse()?;
        if let Some(b) = parts.get(1) {
            train.batch_size = b.parse()?;
        }
        match parts.get(2) {
            None => {}
            Some(&"lazy") => train.lazy_adam = true,
            Some(other) => {
                return Err(format!("`{other}`: the third part is `lazy` or none").into());
            }
        }
    }
    config.validate()?;
    Ok((config, train))
}

fn main() -> Result<(), Box<dyn Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [path, seconds, specs @ ..] = &args[..] else {
        return Err("usage: grid_sweep MESH SECONDS SPEC [SPEC ...]".into());
    };
    let length = match seconds.strip_prefix('e') {
        Some(epochs) => Err(epochs.parse::<usize>()?),
        None => Ok(seconds.parse::<f64>()?),
    };
    let gpu = GpuContext::shared()?;
    eprintln!("adapter: {}", gpu.describe());
    let (mesh, _) = sdf_geom::load_mesh(path)?;
    let (unit, _) = mesh.normalized();
    let labels = Labeller::choose(
        gpu,
        Arc::new(SignedDistance::new(&unit)?),
        GroundTruthDevice::Auto,
    )?;
    let on_gpu = labels.path() == GroundTruthPath::Gpu;
    let sets = EvalSets::new(&unit, &labels, DEFAULT_EVAL_POINTS, EVAL_SEED)?;
    println!("spec\tparams\tbytes\tepochs\ttrain_s\tf1_box\tf1_near\tf16_box\tf16_near");
    for spec in specs {
        let (config, mut train) = parse(spec)?;
        match length {
            Ok(seconds) => {
                train.epochs = 1;
                train.time_budget = Some(TimeBudget {
                    seconds,
                    max_epochs: 1000,
                });
            }
            Err(epochs) => train.epochs = epochs,
        }
        if on_gpu {
            train.sample_source = SampleSource::Gpu;
        }
        let start = Instant::now();
        let mut trainer = NglodTrainer::new(gpu, &Nglod::new(config)?, &unit, train)?;
        let report = trainer.train()?;
        let setup = start.elapsed().as_secs_f64() - report.total_seconds;
        let g = trainer.gpu_model();
        let scores = sets.score(|p| g.eval(gpu, p, None))?;
        let model = trainer.model()?;
        // As saved: f16 grids, f32 MLP; scored again on the CPU to see what f16 costs.
        let w0 = model.layout().w0;
        let bytes = 2 * w0 + 4 * (model.param_count() - w0);
        let file = model.to_model_file(sdf_nn::Normalization::identity(), serde_json::Value::Null);
        let saved = Nglod::from_model_file(&file)?;
        let saved_scores = sets.score(|p| saved.eval_cpu(p, None))?;
        let f1 = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.4}"));
        println!(
            "{spec}\t{}\t{bytes}\t{}\t{:.1}\t{}\t{}\t{}\t{}",
            model.param_count(),
            report.epochs.len(),
            report.total_seconds,
            f1(scores.f1_bbox),
            f1(scores.f1_near_surface),
            f1(saved_scores.f1_bbox),
            f1(saved_scores.f1_near_surface),
        );
        eprintln!(
            "{spec}: setup {setup:.1} s, final loss {:.3e}",
            report.final_loss
        );
    }
    Ok(())
}
