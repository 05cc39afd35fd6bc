//! `sdf`: exact signed distances from a mesh, for users who just want ground truth.
//!
//! ```text
//! sdf MESH --points IN.npy --out OUT.npy [--normalized] [--ground-truth gpu|cpu|auto]
//! ```
//!
//! Reads an `(N, 3)` float32 or float64 `.npy` of query points and writes `N` float32 signed
//! distances (negative inside) to `OUT.npy`, atomically. Points and distances are in the mesh's own
//! coordinates, or with `--normalized` in the normalised box (mesh centred on its bounding-box centre,
//! longest half-extent scaled to 1).
//!
//! `--ground-truth` chooses where the distances are computed: `auto` (the default) on the GPU
//! unless the adapter is a CPU (lavapipe), the mesh does not fit it or the GPU's labels of a
//! probe disagree with the CPU's, `gpu`, or `cpu` (which opens no GPU at all).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use glam::{DVec3, Vec3};
use hwsdf::cli::{GpuFlags, GroundTruthFlags, LabelFlags};
use hwsdf::geom::{GeomError, LoadOptions, SignedDistance, load_mesh_with, npy};
use hwsdf::nn::{GpuContext, GroundTruthDevice, Labeller};

/// Exact signed distance from a triangle mesh (OBJ, glTF, GLB) to query points in a .npy file.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// The mesh: .obj, .gltf or .glb.
    mesh: PathBuf,
    /// Query points: an (N, 3) float32 or float64 .npy file.
    #[arg(long)]
    points: PathBuf,
    /// Output: N float32 signed distances (negative inside), written atomically.
    #[arg(long)]
    out: PathBuf,
    /// Points (and the distances written) are in the normalised box [-1, 1]^3 instead of the
    /// mesh's own coordinates.
    #[arg(long)]
    normalized: bool,
    /// glTF: also follow buffer URIs outside the mesh's folder (absolute paths, `..`, symbolic links).
    #[arg(long)]
    allow_external_uris: bool,
    /// Print the load report and timings to stderr.
    #[arg(long, short)]
    verbose: bool,
    #[command(flatten)]
    ground_truth: GroundTruthFlags,
    #[command(flatten)]
    gpu: GpuFlags,
    #[command(flatten)]
    labelling: LabelFlags,
}

fn run(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    hwsdf::geom::io::check_outputs(&[&args.mesh, &args.points], &[&args.out])?;
    hwsdf::cli::check_out_format("--out", &args.out, "npy", ".npy")?;
    let t = Instant::now();
    let uris = LoadOptions::with_external_uris(args.allow_external_uris);
    // Name the mesh, as `train` and `eval` do: "the mesh has no triangles" alone says not which.
    let in_mesh = |e: GeomError| {
        let (mesh, e) = (args.mesh.display().to_string(), e.to_string());
        if e.contains(&mesh) {
            e
        } else {
            format!("mesh {mesh}: {e}")
        }
    };
    let (mesh, report) = load_mesh_with(&args.mesh, &uris).map_err(in_mesh)?;
    for w in &report.warnings {
        eprintln!("warning: {}: {w}", args.mesh.display());
    }
    if args.verbose {
        eprintln!("{report:#?}");
    }
    let mesh = if args.normalized {
        mesh.normalized().0
    } else {
        mesh
    };
    // Read in f64: a mesh far from the origin is loaded relative to its centre
    // (`report.origin`), and its points move with it before they become f32.
    let read = npy::read_points_f64(&args.points)?;
    let origin = if args.normalized {
        DVec3::ZERO
    } else {
        report.origin
    };
    let points: Vec<Vec3> = read.iter().map(|&p| (p - origin).as_vec3()).collect();
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        // Named as read: 1e39 is a number in the file, infinite only in float32.
        let p = read[i];
        let why = if p.is_finite() {
            "too far from the mesh for float32"
        } else {
            "not finite"
        };
        return Err(GeomError::Npy {
            path: args.points.clone(),
            message: format!("point {i} is {why}: [{}, {}, {}]", p.x, p.y, p.z),
        }
        .into());
    }
    // Only the f32 points are labelled: the f64 ones (24 bytes each) go before the labelling.
    drop(read);
    let sdf = std::sync::Arc::new(SignedDistance::new(&mesh).map_err(in_mesh)?);
    let device = args.ground_truth.device();
    // `cpu` opens no GPU; `auto` without a usable one labels on the CPU.
    let gpu = match device {
        GroundTruthDevice::Cpu => None,
        GroundTruthDevice::Gpu => Some(args.gpu.open()?),
        GroundTruthDevice::Auto => match args.gpu.open() {
            Ok(gpu) => Some(gpu),
            Err(e) => {
                eprintln!("warning: no GPU ({e}); distances on the CPU");
                None
            }
        },
    };
    let labels = labeller(gpu.as_ref(), sdf, device)?;
    if let Some(why) = labels.fallback() {
        eprintln!("warning: {}: {why}", args.mesh.display());
    }
    let t_build = t.elapsed();
    // No minutes of silence: the estimate (measured on a spread of the points) first, then
    // progress lines.
    let stride = (points.len() / PROBE_POINTS).max(1);
    let probe: Vec<Vec3> = points.iter().step_by(stride).copied().collect();
    let (per_label, measured) = labels.time_per_label(&probe)?;
    if let Some(line) = hwsdf::eval::run::estimate_line(
        points.len(),
        per_label,
        measured,
        labels.path(),
        args.labelling.label_estimate_after,
    ) {
        eprintln!("{line}");
    }
    let labels = labels.with_progress(args.labelling.progress());
    let d = labels.signed_distance_batch(&points)?;
    if args.verbose {
        eprintln!(
            "load + build {:.1} ms, {} points in {:.1} ms on the {}",
            t_build.as_secs_f64() * 1e3,
            points.len(),
            (t.elapsed() - t_build).as_secs_f64() * 1e3,
            labels.path().name().to_uppercase()
        );
    }
    Ok(npy::write_f32(&args.out, &d)?)
}

/// Points the labelling estimate is measured on, at most (a spread of the query points).
const PROBE_POINTS: usize = 4096;

/// The labels of `sdf` on `device`, on `gpu` where one is open.
fn labeller(
    gpu: Option<&GpuContext>,
    sdf: std::sync::Arc<SignedDistance>,
    device: GroundTruthDevice,
) -> Result<Labeller<'_>, hwsdf::nn::GroundTruthError> {
    match gpu {
        Some(gpu) => Labeller::choose(gpu, sdf, device),
        None => Ok(Labeller::cpu(sdf)),
    }
}

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
