//! Extracts a mesh from a trained model or a scene: sparse surface nets, evaluated on the GPU in
//! chunks, written as OBJ in the original mesh's coordinates (a scene's frame).
//!
//! ```sh
//! cargo run --release --bin extract -- spot.nglod.safetensors --resolution 256 --out spot.obj
//! cargo run --release --bin extract -- --scene examples/scene/scene.toml --level 0.02 --out s.obj
//! ```

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use hwsdf::cli::{GpuFlags, Source, SourceFlags, check_level, check_out_format};
use hwsdf::eval::run::{extract_mesh_with, extract_scene_mesh};
use hwsdf::geom::extract::{EXTRACT_MEMORY_BUDGET, ExtractOptions, MAX_RESOLUTION};

/// Extract the zero level set (or the level set d = c) of a trained neural SDF or a scene as an
/// OBJ mesh.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    #[command(flatten)]
    source: SourceFlags,
    /// The level c: extract the surface d = c (mesh or scene units; an offset surface).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    level: f32,
    /// Cells per axis over the model's box (the surface is never sampled densely: memory grows
    /// with the surface area).
    #[arg(long, default_value_t = 256)]
    resolution: u32,
    /// Output OBJ.
    #[arg(long)]
    out: PathBuf,
    /// NGLOD only: use the first k levels (a hash grid has no levels of detail short of all of
    /// them).
    #[arg(long)]
    lod: Option<usize>,
    /// Memory budget in GiB: a resolution whose surface would need more is refused with the
    /// estimate, after the coarse levels (a few seconds) and before the fine ones.
    #[arg(long, default_value_t = EXTRACT_MEMORY_BUDGET as f64 / GIB)]
    max_memory_gib: f64,
    #[command(flatten)]
    gpu: GpuFlags,
}

const GIB: f64 = (1u64 << 30) as f64;

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    match extract(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn extract(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    if !(2..=MAX_RESOLUTION).contains(&args.resolution) {
        return Err(format!(
            "--resolution {} is out of range: use 2 to {MAX_RESOLUTION}",
            args.resolution
        )
        .into());
    }
    if !(args.max_memory_gib.is_finite() && args.max_memory_gib > 0.0) {
        return Err(format!("--max-memory-gib {} must be positive", args.max_memory_gib).into());
    }
    args.source.check_outputs(&[], &[&args.out])?;
    check_out_format("--out", &args.out, "obj", "OBJ")?;
    // A model far from the origin is extracted relative to its centre, added back in f64.
    let (mut source, centre) = args.source.load()?.recentred()?;
    let what = match &mut source {
        Source::Model(model) => {
            model.set_lod(args.lod)?;
            "the model's"
        }
        Source::Scene(_) if args.lod.is_some() => {
            return Err("--lod applies to a model, not to a scene".into());
        }
        Source::Scene(_) => "the scene's",
    };
    // In the model's own coordinates (a recentred model's frame moved back by its centre).
    check_level(args.level, source.frame().translated(centre), what)?;
    let gpu = args.gpu.open()?;
    let start = Instant::now();
    let options = ExtractOptions {
        max_bytes: (args.max_memory_gib * GIB).min(u64::MAX as f64) as u64,
        ..ExtractOptions::new(args.resolution)
    };
    let (mesh, stats) = match source {
        Source::Model(model) if args.level == 0.0 => extract_mesh_with(&gpu, &model, &options)?,
        // A model's offset surface is that of a scene of one leaf.
        source => extract_scene_mesh(&gpu, &source.into_scene()?, args.level, &options)?,
    };
    if mesh.triangles.is_empty() {
        // An empty OBJ would look like a result, and no loader takes it back.
        return Err(format!(
            "the model's surface does not cross the box at resolution {} ({} cells, {} distance \
             evaluations): nothing to write (an untrained or diverged model, or a surface finer \
             than the grid: try a higher --resolution)",
            args.resolution, stats.cells, stats.evaluations
        )
        .into());
    }
    hwsdf::geom::io::write_obj_offset(&mesh, centre, &args.out)
        .map_err(|e| format!("writing {}: {e}", args.out.display()))?;
    eprintln!(
        "{} vertices, {} triangles from {} cells ({} distance evaluations) in {:.2} s on {}; written to {}",
        mesh.vertices.len(),
        mesh.triangles.len(),
        stats.cells,
        stats.evaluations,
        start.elapsed().as_secs_f64(),
        gpu.describe(),
        args.out.display()
    );
    Ok(())
}
