//! Evaluates a saved model against its mesh: F1 in the box and near the surface, distance
//! errors, latency, storage, and (from an extracted mesh) Chamfer-L1 and normal consistency.
//!
//! ```sh
//! cargo run --release --bin eval -- spot.nglod.safetensors tests/data/spot.obj --json
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use hwsdf::cli::{GpuFlags, GroundTruthFlags, check_eval_points};
use hwsdf::eval::metrics::{DEFAULT_EVAL_POINTS, EVAL_SEED, SurfaceMetrics};
use hwsdf::eval::run::{self, Evaluation};
use hwsdf::geom::extract::ExtractOptions;
use hwsdf::nn::siren::LayerKernels;
use hwsdf::nn::{GpuContext, NeuralSdf};
use serde_json::json;

/// Score a trained neural SDF against the exact SDF of its mesh.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Model file written by `train`.
    model: PathBuf,
    /// The mesh it was trained on.
    mesh: PathBuf,
    /// Points in each evaluation set.
    #[arg(long, default_value_t = DEFAULT_EVAL_POINTS)]
    points: usize,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
    /// Resolution of the mesh extracted for Chamfer-L1 and normal consistency (0: skip).
    #[arg(long, default_value_t = 128)]
    surface_resolution: u32,
    /// NGLOD only: evaluate with the first k levels (a hash grid has no levels of detail short
    /// of all of them).
    #[arg(long)]
    lod: Option<usize>,
    /// SIREN only: the kernels to evaluate on. `coop` runs on f16 cooperative matrices (tensor
    /// cores) where the adapter has them (`gpu-info` says), trading some accuracy for speed.
    /// One of auto, row-blocked, gemm, tiled, coop.
    #[arg(long, default_value = "auto")]
    siren_kernels: LayerKernels,
    /// glTF: also follow buffer URIs outside the mesh's folder (absolute paths, `..`, symbolic links).
    #[arg(long)]
    allow_external_uris: bool,
    #[command(flatten)]
    gpu: GpuFlags,
    #[command(flatten)]
    ground_truth: GroundTruthFlags,
}

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    match eval(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn eval(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    check_eval_points("--points", args.points)?;
    // Checked before the evaluation it would otherwise follow.
    let max = hwsdf::geom::extract::MAX_RESOLUTION;
    if args.surface_resolution == 1 || args.surface_resolution > max {
        return Err(format!(
            "--surface-resolution {} is out of range: 0 (skip) or 2 to {max}",
            args.surface_resolution
        )
        .into());
    }
    let mut model = NeuralSdf::load(&args.model)?;
    model.set_lod(args.lod)?;
    if args.siren_kernels != LayerKernels::Auto {
        model.set_siren_kernels(args.siren_kernels)?;
    }
    let file_bytes = std::fs::metadata(&args.model)?.len();
    let uris = hwsdf::geom::LoadOptions::with_external_uris(args.allow_external_uris);
    let (mesh, normalization) = run::load_normalized_with(&args.mesh, &uris)?;
    if (normalization.center - model.normalization().center).length()
        > 1e-4 * f64::from(normalization.scale.recip())
        || (normalization.scale / model.normalization().scale - 1.0).abs() > 1e-4
    {
        eprintln!(
            "warning: {} was not trained on {} (its normalisation differs); scores compare it with this mesh anyway",
            args.model.display(),
            args.mesh.display()
        );
    }
    let gpu = args.gpu.open()?;
    let truth = run::GroundTruth::on(&gpu, mesh, &args.mesh, args.ground_truth.device())?;
    if let Some(why) = truth.labels.fallback() {
        eprintln!("warning: {}: {why}", args.mesh.display());
    }
    if args.siren_kernels == LayerKernels::CoopF16 && gpu.coop_f16_tile().is_none() {
        eprintln!(
            "warning: {} has no f16 cooperative matrices; --siren-kernels coop evaluates on the tiled f32 kernels",
            gpu.describe()
        );
    }
    let Evaluation {
        scores, latency, ..
    } = run::evaluate_scores(&gpu, &model, &truth, args.points)?;
    let (surface, surface_null_reason) = surface(&gpu, &model, &truth, args)?;
    let report = json!({
        "model": args.model.display().to_string(),
        "mesh": args.mesh.display().to_string(),
        "architecture": model.architecture(),
        "lod": model.lod(),
        "siren_kernels": args.siren_kernels.name(),
        "params": model.param_count(),
        "file_bytes": file_bytes,
        "eval_points": args.points,
        "f1_bbox": scores.f1_bbox,
        "f1_near_surface": scores.f1_near_surface,
        "f1_mean": scores.f1_mean,
        "sign_accuracy_bbox": scores.sign_accuracy_bbox,
        "sign_accuracy_near_surface": scores.sign_accuracy_near_surface,
        "sign_errors_bbox": scores.sign_errors_bbox,
        "sign_errors_near_surface": scores.sign_errors_near_surface,
        "f1_null_reason": scores.f1_null_reason,
        "ambiguous_bbox": scores.ambiguous_bbox,
        "ambiguous_near_surface": scores.ambiguous_near_surface,
        "inside_fraction_bbox": scores.inside_fraction_bbox,
        "bbox_mean_abs_error": scores.bbox_error.mean_abs,
        "near_surface_mean_abs_error": scores.near_surface_error.mean_abs,
        "near_surface_max_abs_error": scores.near_surface_error.max_abs,
        "per_point_ns": latency.per_point_ns,
        "batch3000_us": latency.batch3000_us,
        "gpu_per_point_ns": latency.gpu_per_point_ns,
        "gpu_batch3000_us": latency.gpu_batch3000_us,
        "latency_reps": latency.reps,
        "chamfer_l1": surface.map(|s| s.chamfer_l1),
        "normal_consistency": surface.map(|s| s.normal_consistency),
        "surface_null_reason": surface_null_reason,
        "surface_resolution": args.surface_resolution,
        "adapter": gpu.describe(),
        "ground_truth": truth.labels.path(),
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "model            {} ({}, {} params, {} bytes)",
            args.model.display(),
            model.architecture(),
            model.param_count(),
            file_bytes
        );
        println!("mesh             {}", args.mesh.display());
        let f4 = |x: Option<f64>| x.map_or_else(|| "n/a".to_owned(), |v| format!("{v:.4}"));
        println!(
            "F1 box / near    {} / {} (mean {})",
            f4(scores.f1_bbox),
            f4(scores.f1_near_surface),
            f4(scores.f1_mean)
        );
        if let Some(reason) = &scores.f1_null_reason {
            println!("                 n/a: {reason}");
        }
        println!(
            "inside/outside   {} (winding number between 0.2 and 0.8: open meshes)",
            hwsdf::eval::metrics::ambiguity_summary(
                scores.ambiguous_bbox,
                scores.ambiguous_near_surface
            )
        );
        println!(
            "sign accuracy    {} / {}",
            f4(scores.sign_accuracy_bbox),
            f4(scores.sign_accuracy_near_surface)
        );
        if let Some(e) = scores.sign_errors_bbox {
            println!("sign errors box  {e}");
        }
        if let Some(e) = scores.sign_errors_near_surface {
            println!("sign errors near {e}");
        }
        println!(
            "|Φ−SDF| near     mean {:.5}, max {:.5} (normalised units)",
            scores.near_surface_error.mean_abs, scores.near_surface_error.max_abs
        );
        println!(
            "wall time        {:.1} ns/point (50000 batch), {:.0} µs per 3000 (NeuralSdf::eval_normalized)",
            latency.per_point_ns, latency.batch3000_us
        );
        match (latency.gpu_per_point_ns, latency.gpu_batch3000_us) {
            (Some(ns), Some(us)) => println!(
                "kernel time      {ns:.1} ns/point (50000 batch), {us:.0} µs per 3000 (GPU timestamps, separate calls)"
            ),
            _ => println!("kernel time      not measured (no timestamp queries on this adapter)"),
        }
        if let Some(s) = surface {
            println!(
                "surface @{}³     Chamfer-L1 {:.5} (normalised units), normal consistency {:.4}",
                args.surface_resolution, s.chamfer_l1, s.normal_consistency
            );
        }
        if let Some(reason) = &surface_null_reason {
            println!("surface          n/a: {reason}");
        }
        println!("adapter          {}", gpu.describe());
        println!("ground truth     {}", truth.labels.path());
    }
    Ok(())
}

/// The surface figures (Chamfer-L1, normal consistency) of the mesh extracted from `model` at
/// `--surface-resolution`, or why there are none. A model that never changes sign in the box
/// (one trained for a few steps, say) has no surface to compare: its surface figures are null,
/// with the reason, and the rest stands.
fn surface(
    gpu: &GpuContext,
    model: &NeuralSdf,
    truth: &run::GroundTruth,
    args: &Args,
) -> Result<(Option<SurfaceMetrics>, Option<String>), Box<dyn std::error::Error>> {
    let mut surface_null_reason = None;
    let surface = if args.surface_resolution > 0 {
        // In the normalised frame, like every other figure here (extracted there: in mesh
        // coordinates a model far from the origin would collapse onto f32's grid).
        let options = ExtractOptions::new(args.surface_resolution);
        let (extracted, _) = run::extract_mesh_normalized(gpu, model, &options)?;
        if extracted.triangles.is_empty() {
            surface_null_reason = Some(if run::is_unsigned(model.model_file()) {
                format!(
                    "the unsigned field's level set Φ = {} has no triangles at {}³: it never \
                     comes that close to 0 in the box",
                    run::UNSIGNED_LEVEL,
                    args.surface_resolution
                )
            } else {
                format!(
                    "the model's level set has no triangles at {}³: it does not change sign in \
                     the box",
                    args.surface_resolution
                )
            });
            None
        } else {
            Some(SurfaceMetrics::between(
                &extracted,
                &truth.mesh,
                truth.sdf(),
                args.points.min(100_000),
                EVAL_SEED,
            )?)
        }
    } else {
        None
    };
    Ok((surface, surface_null_reason))
}
