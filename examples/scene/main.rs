//! A scene of two trained models, blended, hollowed and cut, queried and rendered on the GPU.
//!
//! ```sh
//! cargo run --release --example scene                 # writes scene.png here
//! cargo run --release --example scene -- out.png
//! cargo test --example scene                          # the checks below, on your GPU
//! ```
//!
//! `scene.toml` beside this file places `spot.nglod.safetensors` and
//! `teapot.nglod.safetensors` (NGLOD `small`, ~50 kB each), smooth-unions them, thickens the
//! union's offset surface into a shell and cuts a box away. The program loads it, compiles it
//! for the GPU once ([`GpuScene`]), asks for distances, a ray hit and a closest point (each
//! checked against the CPU reference), and renders the PNG that the README shows.

use std::path::Path;
use std::process::ExitCode;

use glam::Vec3;
use hwsdf::nn::serve::scene::{GpuScene, ProjectOptions, Ray, Scene, TraceOptions};
use hwsdf::nn::{GpuContext, RenderOptions, Renderer};

/// The scene file, beside this example.
fn scene_path() -> &'static Path {
    Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/examples/scene/scene.toml"
    ))
}

/// Queries the scene on the GPU and checks each answer against the CPU; returns a summary.
fn query(gpu: &GpuContext, scene: &Scene) -> Result<String, Box<dyn std::error::Error>> {
    let on_gpu = GpuScene::new(gpu, scene)?;
    let points = [
        Vec3::ZERO,
        Vec3::new(-0.6, 0.0, 0.0),
        Vec3::new(1.5, 0.5, 0.0),
    ];
    let d = on_gpu.distances(&points, 0.0)?;
    for (p, (gpu_d, cpu_d)) in points
        .iter()
        .zip(d.iter().zip(scene.distances(&points, 0.0)))
    {
        if (gpu_d - cpu_d).abs() > 1e-4 {
            return Err(format!("distance at {p}: GPU {gpu_d}, CPU {cpu_d}").into());
        }
    }
    // A ray from the front, through the cut, onto the inner wall of the shell.
    let ray = Ray {
        origin: Vec3::new(-0.5, 0.3, 3.0),
        direction: Vec3::new(0.0, -0.2, -1.0),
        max_distance: 10.0,
    };
    let hit = on_gpu.trace_rays(&[ray], &TraceOptions::default())?[0]
        .ok_or("the ray through the cut missed")?;
    let closest =
        on_gpu.closest_points(&[Vec3::new(0.0, 2.0, 0.0)], &ProjectOptions::default())?[0];
    if !closest.converged {
        return Err("the projection did not converge".into());
    }
    Ok(format!(
        "distances {d:?}; the ray hits leaf {} ({}) at t = {:.3}, normal {:.2}; the closest \
         surface point to (0, 2, 0) is {:.3} (residual {:.1e})",
        hit.leaf,
        scene.leaf_path(hit.leaf).unwrap_or("?"),
        hit.t,
        hit.normal,
        closest.point,
        closest.residual
    ))
}

fn run(out: &Path) -> Result<(), Box<dyn std::error::Error>> {
    let scene = Scene::load(scene_path())?;
    let gpu = GpuContext::new()?;
    println!("{}", query(&gpu, &scene)?);
    let options = RenderOptions {
        width: 640,
        height: 400,
        frame_radius: 0.95,
        yaw_degrees: 20.0,
        pitch_degrees: 25.0,
        ..RenderOptions::default()
    };
    Renderer::for_scene(&gpu, &scene)?
        .render(&gpu, &options)?
        .save_png(out)?;
    println!("rendered on {}: {}", gpu.describe(), out.display());
    Ok(())
}

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "scene.png".into());
    match run(Path::new(&out)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    /// The example's queries agree with the CPU, and the ray through the cut hits.
    #[test]
    fn the_example_scene_answers_on_the_gpu() {
        let scene = super::Scene::load(super::scene_path()).unwrap();
        let gpu = hwsdf::nn::GpuContext::shared().unwrap();
        let summary = super::query(gpu, &scene).unwrap();
        assert!(summary.contains("the ray hits leaf"), "{summary}");
    }
}
