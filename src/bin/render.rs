//! Sphere-traces a trained model or a scene on the GPU and writes a PNG.
//!
//! ```sh
//! cargo run --release --bin render -- model.safetensors --out image.png --size 512x512 --lod 2
//! cargo run --release --bin render -- --scene examples/scene/scene.toml --out scene.png
//! ```
//!
//! The camera orbits the model's normalised box (`--yaw`, `--pitch`), framed from the model's
//! normalisation so any model fills the image the same way; a scene's box is the one that holds
//! its surface (`Scene::frame`). An NGLOD or hash-grid model is traced as the scene of that one
//! leaf (steps by its Lipschitz bounds); a SIREN by the single-model tracer. `--level c` draws
//! the offset surface `d = c`. The image is written atomically.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use hwsdf::cli::{GpuFlags, Source, SourceFlags, check_level};
use hwsdf::nn::serve::network::Network;
use hwsdf::nn::{RenderOptions, Renderer};

/// Render a neural SDF model (SIREN, NGLOD or hash grid) or a scene to a PNG by sphere tracing on
/// the GPU.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    #[command(flatten)]
    source: SourceFlags,
    /// Output PNG.
    #[arg(long)]
    out: PathBuf,
    /// Image size, `WIDTHxHEIGHT` or one number for a square.
    #[arg(long, default_value = "512x512", value_parser = parse_size)]
    size: (u32, u32),
    /// Level of detail for NGLOD models: evaluate only the first K levels (default: all; a hash
    /// grid has no levels of detail short of all of them).
    #[arg(long, value_name = "K")]
    lod: Option<usize>,
    /// Camera azimuth in degrees around the vertical axis.
    #[arg(long, default_value_t = RenderOptions::default().yaw_degrees, allow_negative_numbers = true)]
    yaw: f32,
    /// Camera elevation in degrees.
    #[arg(long, default_value_t = RenderOptions::default().pitch_degrees, allow_negative_numbers = true)]
    pitch: f32,
    /// Radius (normalised units, the mesh's longest half-axis is 1) that fits the frame.
    #[arg(long, default_value_t = RenderOptions::default().frame_radius)]
    frame_radius: f32,
    /// Transparent background instead of a dark grey one.
    #[arg(long)]
    transparent: bool,
    /// The level c: draw the surface d = c (mesh or scene units; an offset surface).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    level: f32,
    #[command(flatten)]
    gpu: GpuFlags,
}

/// `512x512`, `640X480` or `256`.
fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("`{s}` is not a size: expected WIDTHxHEIGHT, e.g. 512x512"))
    };
    let (w, h) = match s.split_once(['x', 'X']) {
        Some((w, h)) => (parse(w)?, parse(h)?),
        None => {
            let n = parse(s)?;
            (n, n)
        }
    };
    let max = hwsdf::nn::serve::render::MAX_IMAGE_SIDE;
    if w == 0 || h == 0 || w > max || h > max {
        return Err(format!("size {w}x{h}: each side must be in 1..={max}"));
    }
    Ok((w, h))
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

fn run(args: &Args) -> Result<(), String> {
    // Fail before the slow GPU work if the image could not be written, or would replace the model
    // (or one of the scene's).
    args.source
        .check_outputs(&[], &[&args.out])
        .map_err(|e| e.to_string())?;
    hwsdf::cli::check_out_format("--out", &args.out, "png", "PNG")?;
    // A model far from the origin is drawn relative to its centre (the image is the same).
    let (mut source, centre) = args.source.load()?.recentred()?;
    match &mut source {
        Source::Model(sdf) => sdf.set_lod(args.lod).map_err(|e| e.to_string())?,
        Source::Scene(_) if args.lod.is_some() => {
            return Err("--lod applies to a model, not to a scene".into());
        }
        Source::Scene(_) => {}
    }
    let what = match source {
        Source::Model(_) => "the model's",
        Source::Scene(_) => "the scene's",
    };
    // In the model's own coordinates (a recentred model's frame moved back by its centre).
    check_level(args.level, source.frame().translated(centre), what)?;
    let mut options = RenderOptions {
        width: args.size.0,
        height: args.size.1,
        yaw_degrees: args.yaw,
        pitch_degrees: args.pitch,
        frame_radius: args.frame_radius,
        level: args.level,
        ..RenderOptions::default()
    };
    if args.transparent {
        options.background = glam::Vec4::ZERO;
    }
    // Check the options before the (slow) device and shader setup.
    options.validate().map_err(|e| e.to_string())?;

    let gpu = args.gpu.open().map_err(|e| e.to_string())?;
    let start = std::time::Instant::now();
    let described = match &source {
        Source::Model(sdf) => {
            // A model whose sums overflow (NaN or ∞ everywhere) would sphere-trace every pixel
            // to its step limit and save a blank image: refuse it, as `eval` does.
            let probe = probe_grid(PROBE_SIDE);
            let values = sdf
                .eval_normalized(&gpu, &probe)
                .map_err(|e| e.to_string())?;
            hwsdf::eval::run::finite_values(&probe, values).map_err(|e| e.to_string())?;
            format!(
                "{} model ({} parameters{})",
                sdf.architecture(),
                sdf.param_count(),
                match sdf.lod() {
                    Some(k) => format!(", LOD {k}"),
                    None => String::new(),
                }
            )
        }
        Source::Scene(scene) => format!(
            "scene ({} leaves, {} models)",
            scene.leaves().len(),
            scene.models().len()
        ),
    };
    // A grid model is traced as a scene of one leaf, as `query --rays` traces it: steps divided
    // by its Lipschitz bounds near each point (about 3 where a trained NGLOD is steepest), where
    // the single-model tracer's steps (0.9 times the distance) passed over thin parts. A
    // SIREN keeps the single-model tracer: its bounds take seconds to measure on the CPU (17 s
    // for `default` on 2 cores, against 46 ms for an NGLOD), and its eikonal term keeps its
    // slope near 1.
    let renderer = match source {
        Source::Model(sdf) if matches!(sdf.network(), Network::Siren(_)) => {
            Renderer::new(&gpu, &sdf)
        }
        source => Renderer::for_scene(&gpu, &source.into_scene()?),
    }
    .map_err(|e| e.to_string())?;
    let image = renderer.render(&gpu, &options).map_err(|e| e.to_string())?;
    image.save_png(&args.out).map_err(|e| e.to_string())?;
    eprintln!(
        "{described} rendered at {}x{} on {} in {:.2?}: {}",
        options.width,
        options.height,
        gpu.describe(),
        start.elapsed(),
        args.out.display()
    );
    Ok(())
}

/// Points per axis of the grid a model is checked on before rendering.
const PROBE_SIDE: usize = 8;

/// A `side`³ grid over the normalised box [-1, 1]³, corners included.
fn probe_grid(side: usize) -> Vec<glam::Vec3> {
    let at = |i: usize| -1.0 + 2.0 * i as f32 / (side - 1) as f32;
    (0..side * side * side)
        .map(|i| glam::Vec3::new(at(i % side), at(i / side % side), at(i / (side * side))))
        .collect()
}
