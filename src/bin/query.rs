//! Queries a trained model or a scene on the GPU: distances (and normals) at points, ray hits,
//! closest points. Inputs and outputs are `.npy` files; outputs are written atomically.
//!
//! ```sh
//! query spot.nglod.safetensors --points P.npy --out D.npy --normals N.npy
//! query --scene examples/scene/scene.toml --rays R.npy --out H.npy
//! query --scene examples/scene/scene.toml --closest P.npy --out C.npy --level 0.05
//! ```
//!
//! - `--points P.npy` (N×3) → `--out D.npy`: N float32 values `d − c`; with `--normals N.npy`
//!   also N×3 unit normals.
//! - `--rays R.npy` (N×6: origin, direction) → `--out H.npy`: N×9 float32 rows `hit (0 or 1),
//!   t, point (3), normal (3), leaf`; a miss is `0, inf, NaN × 6, −1`. The leaf is the index
//!   of the scene's leaf hit (0 for a single model).
//! - `--closest P.npy` (N×3) → `--out C.npy`: N×6 rows `point (3), residual |d − c|,
//!   iterations, converged (0 or 1)`.
//!
//! Coordinates are the model's mesh coordinates, or the scene's frame. A model of a mesh far
//! from the origin for its size (its centre more than 16 half-extents away, as `train`
//! recentres such meshes: georeferenced, CAD) is queried relative to its centre: float64 inputs
//! keep their precision, and the rows of `--rays` and `--closest` come out as float64 (their
//! points would round in float32); the distances and normals of `--points` stay float32.
//! `--level c` queries the level set `d = c` (an offset surface) and must lie inside the
//! model's or scene's box.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use glam::{DVec3, Vec3};
use hwsdf::cli::{GpuFlags, Source, SourceFlags, check_level};
use hwsdf::geom::npy;
use hwsdf::nn::serve::scene::{GpuScene, ProjectOptions, Ray, TRACE_OVER_RELAXATION, TraceOptions};

/// Distances, normals, ray hits and closest points of a neural SDF model or a scene, on the GPU.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    #[command(flatten)]
    source: SourceFlags,
    /// Query points: an (N, 3) float32 or float64 .npy file; writes N distances to --out.
    #[arg(long, value_name = "P.npy", group = "query")]
    points: Option<PathBuf>,
    /// Rays: an (N, 6) .npy file (origin, direction); writes N×9 hits to --out.
    #[arg(long, value_name = "R.npy", group = "query")]
    rays: Option<PathBuf>,
    /// Points to project onto the surface: (N, 3); writes N×6 closest points to --out.
    #[arg(long, value_name = "P.npy", group = "query")]
    closest: Option<PathBuf>,
    /// The output .npy file.
    #[arg(long)]
    out: PathBuf,
    /// With --points: also write N×3 unit normals here.
    #[arg(long, value_name = "N.npy", requires = "points")]
    normals: Option<PathBuf>,
    /// The level c: query the level set d = c.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    level: f32,
    /// Rays: how far each looks.
    #[arg(long, default_value_t = f32::INFINITY)]
    max_distance: f32,
    /// Rays: sphere-tracing steps at most (default 1024); closest points: projection steps at
    /// most (default 32).
    #[arg(long)]
    max_steps: Option<u32>,
    /// Rays and closest points: the tolerance on |d − c| (default 1e-4 for rays, 1e-5 for
    /// closest points, times the half-side of the model's or scene's box: in proportion to it).
    #[arg(long)]
    tolerance: Option<f32>,
    /// Rays: over-relaxed steps, this factor times the safe step while consecutive free
    /// spheres overlap (1 traces plainly; at least 1, below 2).
    #[arg(long, default_value_t = TRACE_OVER_RELAXATION)]
    over_relaxation: f32,
    #[command(flatten)]
    gpu: GpuFlags,
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

/// A ray's direction read in f64, normalised before it becomes f32: components of 1e39 or
/// 1e-50 give a direction, where f32 would make them infinite or zero and the ray refused;
/// scaled by its largest component first, so that 1e200 or 1e-200 (whose squares overflow or
/// vanish in f64) do too. A zero or non-finite direction stays as it was read, for the refusal
/// to show.
fn unit_direction(d: DVec3) -> glam::Vec3 {
    let largest = d.abs().max_element();
    if d.is_finite() && largest > 0.0 {
        // A component of ±1 now: the length is between 1 and √3, never 0 or ∞.
        (d / largest).normalize().as_vec3()
    } else {
        d.as_vec3()
    }
}

fn run(args: &Args) -> Result<(), String> {
    let input = args
        .points
        .as_ref()
        .or(args.rays.as_ref())
        .or(args.closest.as_ref())
        .ok_or("give --points, --rays or --closest")?;
    let mut outputs = vec![args.out.as_path()];
    outputs.extend(args.normals.as_deref());
    args.source
        .check_outputs(&[input], &outputs)
        .map_err(|e| e.to_string())?;
    hwsdf::cli::check_out_format("--out", &args.out, "npy", ".npy")?;
    if let Some(normals) = &args.normals {
        hwsdf::cli::check_out_format("--normals", normals, "npy", ".npy")?;
    }
    // A model far from the origin is queried relative to its centre: inputs less the centre
    // (in f64), output points plus it, written as float64.
    let (source, centre) = args.source.load()?.recentred()?;
    let what = match source {
        Source::Model(_) => "the model's",
        Source::Scene(_) => "the scene's",
    };
    // In the model's own coordinates (a recentred model's frame moved back by its centre).
    check_level(args.level, source.frame().translated(centre), what)?;
    if args.max_distance.is_nan() || args.max_distance < 0.0 {
        return Err(format!("--max-distance {} must be >= 0", args.max_distance));
    }
    let gpu = args.gpu.open().map_err(|e| e.to_string())?;
    let start = Instant::now();
    let count = if let Some(path) = &args.points {
        let points = read_points(path, centre)?;
        query_points(args, &gpu, source, &points)?;
        points.len()
    } else if let Some(path) = &args.rays {
        let table = npy::read_table_f64(path, 6).map_err(|e| e.to_string())?;
        let rays: Vec<Ray> = table
            .chunks_exact(6)
            .map(|r| Ray {
                origin: (DVec3::new(r[0], r[1], r[2]) - centre).as_vec3(),
                direction: unit_direction(DVec3::new(r[3], r[4], r[5])),
                max_distance: args.max_distance,
            })
            .collect();
        let scene = source.into_scene()?;
        let on_gpu = GpuScene::new(&gpu, &scene).map_err(|e| e.to_string())?;
        let defaults = TraceOptions::for_scene(&scene);
        let options = TraceOptions {
            level: args.level,
            tolerance: args.tolerance.unwrap_or(defaults.tolerance),
            max_steps: args.max_steps.unwrap_or(defaults.max_steps),
            over_relaxation: args.over_relaxation,
        };
        let hits = on_gpu
            .trace_rays(&rays, &options)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let rows: Vec<f64> = hits
            .iter()
            .flat_map(|h| match h {
                Some(h) => {
                    let p = h.point.as_dvec3() + centre;
                    let n = h.normal.as_dvec3();
                    [1.0, h.t.into(), p.x, p.y, p.z, n.x, n.y, n.z, h.leaf as f64]
                }
                None => {
                    let nan = f64::NAN;
                    [0.0, f64::INFINITY, nan, nan, nan, nan, nan, nan, -1.0]
                }
            })
            .collect();
        write_rows(&args.out, &rows, 9, centre)?;
        rays.len()
    } else {
        let path = args.closest.as_ref().expect("one query flag");
        let points = read_points(path, centre)?;
        let scene = source.into_scene()?;
        let on_gpu = GpuScene::new(&gpu, &scene).map_err(|e| e.to_string())?;
        let defaults = ProjectOptions::for_scene(&scene);
        let options = ProjectOptions {
            level: args.level,
            tolerance: args.tolerance.unwrap_or(defaults.tolerance),
            max_iterations: args.max_steps.unwrap_or(defaults.max_iterations),
        };
        let closest = on_gpu
            .closest_points(&points, &options)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let rows: Vec<f64> = closest
            .iter()
            .flat_map(|c| {
                let p = c.point.as_dvec3() + centre;
                [
                    p.x,
                    p.y,
                    p.z,
                    c.residual.into(),
                    c.iterations.into(),
                    if c.converged { 1.0 } else { 0.0 },
                ]
            })
            .collect();
        write_rows(&args.out, &rows, 6, centre)?;
        points.len()
    };
    eprintln!(
        "{count} queries on {} in {:.2?}: {}",
        gpu.describe(),
        start.elapsed(),
        args.out.display()
    );
    Ok(())
}

/// Finite points from an (N, 3) .npy file, less `centre` (in f64: float64 points far from the
/// origin keep their precision).
fn read_points(path: &PathBuf, centre: DVec3) -> Result<Vec<Vec3>, String> {
    let points: Vec<Vec3> = npy::read_points_f64(path)
        .map_err(|e| e.to_string())?
        .into_iter()
        .map(|p| (p - centre).as_vec3())
        .collect();
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(format!(
            "{}: point {i} is not finite: {}",
            path.display(),
            points[i]
        ));
    }
    Ok(points)
}

/// Writes `N × columns` rows: float32, or float64 when the model was queried relative to a
/// centre far from the origin (its points would round in float32).
fn write_rows(path: &PathBuf, rows: &[f64], columns: usize, centre: DVec3) -> Result<(), String> {
    if centre == DVec3::ZERO {
        let rows: Vec<f32> = rows.iter().map(|&v| v as f32).collect();
        npy::write_table(path, &rows, columns)
    } else {
        npy::write_table_f64(path, rows, columns)
    }
    .map_err(|e| e.to_string())
}

/// Distances (and normals) at points: a model through its own query kernels, a scene through
/// its compiled program.
fn query_points(
    args: &Args,
    gpu: &hwsdf::nn::GpuContext,
    source: Source,
    points: &[Vec3],
) -> Result<(), String> {
    let c = args.level;
    let (distances, normals): (Vec<f32>, Option<Vec<Vec3>>) = match source {
        Source::Model(model) if args.normals.is_some() => {
            let v = model
                .eval_with_normals(gpu, points)
                .map_err(|e| e.to_string())?;
            (
                v.iter().map(|(d, _)| d - c).collect(),
                Some(v.iter().map(|(_, n)| *n).collect()),
            )
        }
        Source::Model(model) => (
            model
                .eval(gpu, points)
                .map_err(|e| e.to_string())?
                .into_iter()
                .map(|d| d - c)
                .collect(),
            None,
        ),
        Source::Scene(scene) => {
            let on_gpu = GpuScene::new(gpu, &scene).map_err(|e| e.to_string())?;
            if args.normals.is_some() {
                let s = on_gpu.samples(points, c).map_err(|e| e.to_string())?;
                (
                    s.iter().map(|s| s.distance).collect(),
                    Some(s.iter().map(|s| s.gradient.normalize_or_zero()).collect()),
                )
            } else {
                (
                    on_gpu.distances(points, c).map_err(|e| e.to_string())?,
                    None,
                )
            }
        }
    };
    if let (Some(path), Some(normals)) = (&args.normals, &normals) {
        npy::write_points(path, normals).map_err(|e| e.to_string())?;
    }
    npy::write_f32(&args.out, &distances).map_err(|e| e.to_string())
}
