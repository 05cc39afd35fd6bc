//! Extracts a mesh from a trained model: sparse surface nets, evaluated on the GPU in chunks,
//! written as OBJ in the original mesh's coordinates.
//!
//! ```sh
//! cargo run --release --bin extract -- spot.nglod.safetensors --resolution 256 --out spot.obj
//! ```

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use hwsdf::eval::run::extract_mesh;
use hwsdf::geom::extract::MAX_RESOLUTION;
use hwsdf::nn::{GpuContext, NeuralSdf};

/// Extract the zero level set of a trained neural SDF as an OBJ mesh.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Model file written by `train`.
    model: PathBuf,
    /// Cells per axis over the model's box (the surface is never sampled densely: memory grows
    /// with the surface area).
    #[arg(long, default_value_t = 256)]
    resolution: u32,
    /// Output OBJ.
    #[arg(long)]
    out: PathBuf,
    /// NGLOD only: use the first k levels.
    #[arg(long)]
    lod: Option<usize>,
}

fn main() -> ExitCode {
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
    let mut model = NeuralSdf::load(&args.model)?;
    model.set_lod(args.lod)?;
    let gpu = GpuContext::new()?;
    let start = Instant::now();
    let (mesh, stats) = extract_mesh(&gpu, &model, args.resolution)?;
    hwsdf::geom::io::write_obj(&mesh, &args.out)
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
