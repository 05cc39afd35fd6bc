//! Scenes on the GPU (issue 37's targets): a scene of 8 NGLOD `default` models and 4 primitives
//! under unions and one smooth union, queried through `GpuScene`:
//! - `scene/distance/3000`: 3000 distances (wall: upload, one submission, readback);
//! - `scene/rays/3000`: 3000 sphere-traced rays of up to 128 steps;
//! - both again with the other kernel where the device has subgroups
//!   (`distance_per_invocation` on a GPU, `distance_per_subgroup` on lavapipe: see
//!   `QueryKernel`);
//! - `scene/rays_plain/3000`: the same rays traced as before local Lipschitz bounds and
//!   over-relaxation (plain steps by each model's whole-box estimate, kept by
//!   `Scene::set_model_lipschitz`);
//! - `scene/render/1920x1080`: a full-HD image from `Renderer::for_scene`, and
//!   `scene/render_plain/1920x1080` the same without its cone pass and over-relaxed steps
//!   (`Renderer::set_accelerated`), on the scene with whole-box estimates;
//! - `scene/eight_models/3000`: the 8 single-model queries (`NeuralSdf::eval`) one scene query
//!   replaces, for the lavapipe comparison.
//!
//! Run: `cargo bench --bench scene`. `SCENE_BENCH_MODEL=M.safetensors` places a trained NGLOD
//! model file (8 separate copies of its weights, so that the scene binds 8 models); without it
//! the models are untrained NGLOD `default` networks whose sparse level holds a band around a
//! sphere (their fields are not distances, so the ray figures are only indicative).
//! `SCENE_BENCH_SECONDS` sets criterion's measurement time (default 3).

use std::sync::Arc;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput};
use glam::{Quat, Vec3};
use sdf_nn::serve::query::QueryKernel;
use sdf_nn::serve::scene::{GpuScene, Primitive, Ray, Scene, SceneNode, TraceOptions, Transform};
use sdf_nn::{GpuContext, NeuralSdf, Nglod, NglodConfig, Normalization, RenderOptions, Renderer};

/// Eight models: the file of `SCENE_BENCH_MODEL` loaded 8 times, or 8 untrained `default`
/// networks.
fn models() -> Vec<Arc<NeuralSdf>> {
    (0..8u64)
        .map(|i| {
            // Empty counts as unset, as for the other benches' variables.
            let model = match std::env::var("SCENE_BENCH_MODEL") {
                Ok(path) if !path.is_empty() => {
                    NeuralSdf::load(&path).expect("SCENE_BENCH_MODEL loads")
                }
                _ => {
                    let mut m = Nglod::new(NglodConfig {
                        seed: i,
                        ..NglodConfig::default_preset()
                    })
                    .unwrap();
                    m.place_bands(|p| (p.length() - 0.6).abs()).unwrap();
                    NeuralSdf::from_model_file(
                        m.to_model_file(Normalization::identity(), serde_json::Value::Null),
                    )
                    .unwrap()
                }
            };
            Arc::new(model)
        })
        .collect()
}

/// The models on a 4×2 grid of spacing 2.5 (scale 1), four primitives, unions and one smooth
/// union.
fn scene() -> Scene {
    let mut placed: Vec<SceneNode> = models()
        .into_iter()
        .enumerate()
        .map(|(i, m)| {
            let at = Vec3::new(
                (i % 4) as f32 * 2.5 - 3.75,
                0.0,
                (i / 4) as f32 * 2.5 - 1.25,
            );
            SceneNode::model(m, Transform::new(at, Quat::from_rotation_y(i as f32), 1.0))
        })
        .collect();
    let blended = SceneNode::SmoothUnion {
        k: 0.3,
        children: placed.drain(..2).collect(),
    };
    let primitives = vec![
        SceneNode::primitive(
            Primitive::Box {
                half_extents: Vec3::new(6.0, 0.1, 3.0),
            },
            Transform::from_translation(Vec3::new(0.0, -1.1, 0.0)),
        ),
        SceneNode::primitive(
            Primitive::Sphere { radius: 0.5 },
            Transform::from_translation(Vec3::Y * 2.0),
        ),
        SceneNode::primitive(
            Primitive::Torus {
                major: 1.0,
                minor: 0.2,
            },
            Transform::from_translation(Vec3::new(0.0, 1.5, -3.0)),
        ),
        SceneNode::primitive(
            Primitive::Capsule {
                a: Vec3::new(-5.0, 1.0, 3.0),
                b: Vec3::new(5.0, 1.0, 3.0),
                radius: 0.2,
            },
            Transform::IDENTITY,
        ),
    ];
    let mut children = vec![blended];
    children.extend(placed);
    children.extend(primitives);
    Scene::new(SceneNode::Union(children)).unwrap()
}

fn points(n: usize) -> Vec<Vec3> {
    (0..n)
        .map(|i| {
            let f = |k: f32| ((i as f32 + 0.5) * k).fract() * 2.0 - 1.0;
            Vec3::new(
                f(0.618_034) * 6.0,
                f(0.754_877_7) * 2.0,
                f(0.569_840_3) * 3.5,
            )
        })
        .collect()
}

fn main() {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { sdf_nn::gpu::skip_device_select_layer_when_headless() };
    let gpu = GpuContext::shared().expect("a GPU adapter");
    eprintln!("adapter: {}", gpu.describe());
    let seconds: u64 = std::env::var("SCENE_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);
    let mut c = Criterion::default()
        .measurement_time(Duration::from_secs(seconds))
        .warm_up_time(Duration::from_secs(1))
        .sample_size(10)
        .configure_from_args();
    let scene = scene();
    let mut on_gpu = GpuScene::new(gpu, &scene).unwrap();
    let default_kernel = on_gpu.kernel(3000);
    eprintln!(
        "scene: {} leaves, {} models, Lipschitz bound {:.3}, default kernel {default_kernel:?}",
        scene.leaves().len(),
        scene.models().len(),
        on_gpu.lipschitz()
    );
    let n = 3000;
    let pts = points(n);
    let rays: Vec<Ray> = pts
        .iter()
        .map(|&p| Ray {
            origin: Vec3::new(p.x, 6.0, p.z + 8.0),
            direction: Vec3::new(p.x * 0.1, -6.0, -8.0),
            max_distance: 30.0,
        })
        .collect();
    let trace = TraceOptions {
        max_steps: 128,
        ..TraceOptions::default()
    };
    let hits = on_gpu.trace_rays(&rays, &trace).unwrap();
    eprintln!(
        "{} of {n} rays hit within 128 steps",
        hits.iter().filter(|h| h.is_some()).count()
    );
    let mut group = c.benchmark_group("scene");
    group.throughput(Throughput::Elements(n as u64));
    // Both kernels where the device has subgroups, the default one under the plain names.
    for kernel in [QueryKernel::PerSubgroup, QueryKernel::PerInvocation] {
        if on_gpu.set_kernel(Some(kernel)).is_err() {
            continue;
        }
        let suffix = match kernel {
            _ if kernel == default_kernel => "",
            QueryKernel::PerSubgroup => "_per_subgroup",
            QueryKernel::PerInvocation => "_per_invocation",
        };
        group.bench_function(BenchmarkId::new(format!("distance{suffix}"), n), |b| {
            b.iter(|| on_gpu.distances(&pts, 0.0).unwrap())
        });
        group.bench_function(BenchmarkId::new(format!("rays{suffix}"), n), |b| {
            b.iter(|| on_gpu.trace_rays(&rays, &trace).unwrap())
        });
    }
    on_gpu.set_kernel(None).unwrap();
    // The tracer before local bounds and over-relaxation: plain steps by each model's
    // whole-box estimate.
    let mut plain_scene = self::scene();
    for m in 0..plain_scene.models().len() {
        let estimate = plain_scene.model_lipschitz(m).unwrap();
        plain_scene.set_model_lipschitz(m, estimate).unwrap();
    }
    let plain_on_gpu = GpuScene::new(gpu, &plain_scene).unwrap();
    let plain_trace = TraceOptions {
        over_relaxation: 1.0,
        ..trace
    };
    group.bench_function(BenchmarkId::new("rays_plain", n), |b| {
        b.iter(|| plain_on_gpu.trace_rays(&rays, &plain_trace).unwrap())
    });
    let models = scene.models().to_vec();
    let local: Vec<Vec3> = pts.iter().map(|p| *p * 0.3).collect();
    for m in &models {
        m.eval(gpu, &local).unwrap();
    }
    group.bench_function(BenchmarkId::new("eight_models", n), |b| {
        b.iter(|| {
            for m in &models {
                m.eval(gpu, &local).unwrap();
            }
        })
    });
    let renderer = Renderer::for_scene(gpu, &scene).unwrap();
    let options = RenderOptions {
        width: 1920,
        height: 1080,
        frame_radius: 0.8,
        ..RenderOptions::default()
    };
    group.throughput(Throughput::Elements(1920 * 1080));
    group.bench_function(BenchmarkId::new("render", "1920x1080"), |b| {
        b.iter(|| renderer.render(gpu, &options).unwrap())
    });
    let mut renderer = Renderer::for_scene(gpu, &plain_scene).unwrap();
    renderer.set_accelerated(false);
    group.bench_function(BenchmarkId::new("render_plain", "1920x1080"), |b| {
        b.iter(|| renderer.render(gpu, &options).unwrap())
    });
    group.finish();
    c.final_summary();
}
