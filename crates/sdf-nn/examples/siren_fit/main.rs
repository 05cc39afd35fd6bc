//! Manual SIREN experiments that the `train` binary and the `siren` bench do not cover (they
//! were `#[ignore]`d tests driven by `SIREN_*` variables):
//!
//! - `fit` (the default): trains a SIREN on a mesh (default: a unit icosphere) and reports
//!   the sign of 20 000 uniform box points against the mesh's, by distance band, with knobs
//!   `train` lacks (ω0, the initial output bias, the batch and dataset sizes):
//!   `cargo run --release -p sdf-nn --example siren_fit -- fit --mesh tests/data/spot.obj
//!   --steps 1000 --batch 1000 --omega 10 --save /tmp/spot.safetensors`
//! - `time`: wall times of inference, inference with gradients and the loss with its gradient
//!   on a batch of the `small` preset, with a kernel family and training step:
//!   `cargo run --release -p sdf-nn --example siren_fit -- time --points 10000 --kernels tiled
//!   --train-step ror`
//!
//! Flags (each `--name value`): fit: `--mesh`, `--steps` (200), `--lr` (1e-4), `--batch`
//! (surface and box points per step, 5000), `--data` (dataset size, 20 000),
//! `--eikonal-weight` (5), `--sign-weight` (the default), `--seed` (1), `--preset`
//! (`small` or `default`; `small`), `--omega`, `--out-bias`, `--save`; time: `--points`
//! (10 000), `--kernels` (`auto`), `--train-step` (`auto`, `tangents` or `ror`).

mod fit;

use std::collections::HashMap;
use std::str::FromStr;

use glam::Vec3;
use sdf_nn::siren::{LayerKernels, LossWeights, SirenGpuOptions, TrainStep};
use sdf_nn::{GpuContext, Siren, SirenConfig, SirenGpu, SirenTrainConfig};

/// The command and its `--name value` flags.
struct Args {
    command: String,
    flags: HashMap<String, String>,
}

impl Args {
    fn parse() -> Result<Self, String> {
        let mut args = std::env::args().skip(1).peekable();
        let command = match args.peek() {
            Some(c) if !c.starts_with("--") => args.next().unwrap_or_default(),
            _ => "fit".to_owned(),
        };
        let mut flags = HashMap::new();
        while let Some(name) = args.next() {
            let key = name
                .strip_prefix("--")
                .ok_or_else(|| format!("expected a --flag, got {name:?}"))?;
            let value = args
                .next()
                .ok_or_else(|| format!("--{key} needs a value"))?;
            flags.insert(key.to_owned(), value);
        }
        Ok(Args { command, flags })
    }

    /// The value of `--name`, if given.
    fn opt<T: FromStr>(&mut self, name: &str) -> Result<Option<T>, String> {
        self.flags
            .remove(name)
            .map(|v| v.parse().map_err(|_| format!("--{name}: bad value {v:?}")))
            .transpose()
    }

    /// The value of `--name`, or `default`.
    fn get<T: FromStr>(&mut self, name: &str, default: T) -> Result<T, String> {
        Ok(self.opt(name)?.unwrap_or(default))
    }

    /// Errors on flags nobody asked for.
    fn finish(&self) -> Result<(), String> {
        match self.flags.keys().next() {
            Some(k) => Err(format!("unknown flag --{k} for {}", self.command)),
            None => Ok(()),
        }
    }
}

fn main() {
    let run = || -> Result<(), String> {
        let mut args = Args::parse()?;
        let gpu = GpuContext::shared().map_err(|e| e.to_string())?;
        eprintln!("adapter: {}", gpu.describe());
        match args.command.as_str() {
            "fit" => fit_command(gpu, &mut args),
            "time" => time_command(gpu, &mut args),
            other => Err(format!("unknown command {other:?}: fit or time")),
        }
    };
    if let Err(e) = run() {
        eprintln!("siren_fit: {e}");
        std::process::exit(2);
    }
}

fn fit_command(gpu: &GpuContext, args: &mut Args) -> Result<(), String> {
    let mesh_path: Option<String> = args.opt("mesh")?;
    let batch: usize = args.get("batch", 5000)?;
    let train = SirenTrainConfig {
        steps: args.get("steps", 200)?,
        lr: args.get("lr", 1e-4)?,
        surface_per_step: batch,
        box_per_step: batch,
        dataset_size: args.get("data", 20_000)?,
        weights: LossWeights {
            eikonal: args.get("eikonal-weight", 5.0)?,
            sign: args.get("sign-weight", LossWeights::default().sign)?,
            ..LossWeights::default()
        },
        ..SirenTrainConfig::default()
    };
    let seed: u64 = args.get("seed", 1)?;
    let preset = match args.get("preset", "small".to_owned())?.as_str() {
        "small" => SirenConfig::small(),
        "default" => SirenConfig::default(),
        other => return Err(format!("--preset {other}: small or default")),
    };
    let config = SirenConfig {
        omega0: args.get("omega", preset.omega0)?,
        ..preset
    };
    let out_bias: Option<f32> = args.opt("out-bias")?;
    let save: Option<std::path::PathBuf> = args.opt("save")?;
    args.finish()?;
    let mesh = match mesh_path {
        None => sdf_geom::Mesh::icosphere(1.0, 3),
        Some(path) => sdf_geom::load_mesh(&path).map_err(|e| e.to_string())?.0,
    };
    let mut siren = Siren::new(config, seed).map_err(|e| e.to_string())?;
    if let Some(b) = out_bias {
        *siren.params_mut().last_mut().expect("an output bias") = b;
    }
    fit::fit_and_check_signs(gpu, "fit", &siren, &mesh, &train, seed, save.as_deref());
    Ok(())
}

fn time_command(gpu: &GpuContext, args: &mut Args) -> Result<(), String> {
    let n: usize = args.get("points", 10_000)?;
    let kernels: LayerKernels = args.get("kernels", LayerKernels::Auto)?;
    let train_step = match args.get("train-step", "auto".to_owned())?.as_str() {
        "auto" => TrainStep::Auto,
        "tangents" => TrainStep::Tangents,
        "ror" => TrainStep::ReverseOverReverse,
        other => return Err(format!("--train-step {other}: auto, tangents or ror")),
    };
    args.finish()?;
    let cfg = SirenConfig::small();
    let options = SirenGpuOptions {
        kernels,
        train_step,
        ..SirenGpuOptions::default()
    };
    let net = Siren::new(cfg, 1).map_err(|e| e.to_string())?;
    let mut g = SirenGpu::with_options(gpu, &net, &options).map_err(|e| e.to_string())?;
    eprintln!(
        "kernels {:?}, reverse over reverse: {}",
        g.options().kernels,
        g.runs_reverse_over_reverse()
    );
    let pts = sdf_geom::sample::uniform_box(n, 3);
    let nrm: Vec<Vec3> = pts[..n / 2].iter().map(|p| p.normalize()).collect();
    let timed = |f: &mut dyn FnMut()| {
        let t = std::time::Instant::now();
        f();
        t.elapsed()
    };
    for rep in 0..3 {
        let a = timed(&mut || drop(g.eval(gpu, &pts).unwrap()));
        let b = timed(&mut || drop(g.eval_with_gradient(gpu, &pts).unwrap()));
        let weights = LossWeights::default();
        let c = timed(&mut || drop(g.loss_and_gradient(gpu, &pts, &nrm, &[], &weights).unwrap()));
        let flop = 2.0 * cfg.forward_macs() as f64 * n as f64;
        eprintln!(
            "rep {rep}: eval {a:.2?} ({:.2} GFLOP/s), eval+grad {b:.2?} ({:.2} GFLOP/s), loss+grad {c:.2?}",
            flop / a.as_secs_f64() / 1e9,
            4.0 * flop / b.as_secs_f64() / 1e9
        );
    }
    Ok(())
}
