//! Serving a neural SDF to code that queries it every frame: a planner that checks a swept
//! robot (a chain of spheres) against an obstacle, with the serving API of `hwsdf::nn::serve::query`.
//!
//! ```sh
//! cargo run --release --example serve_queries               # an analytic sphere obstacle
//! cargo run --release --example serve_queries -- MODEL.safetensors
//! cargo test --example serve_queries                        # the checks below, on your GPU
//! ```
//!
//! It shows the three ways of using [`QueryBuffers`], each marked below:
//! 1. **submit, work, read back**: `submit_query` returns a ticket at once; the host does its
//!    own work; `wait` maps the distances and normals into a vector the caller reuses;
//! 2. **two buffers in flight**: the next frame's query is submitted before the last one is
//!    read, so the GPU and the host overlap;
//! 3. **GPU-resident**: `record_query` into our own encoder, then our own compute pass reads the
//!    results buffer and counts the colliding spheres; only that one counter comes back.

use std::process::ExitCode;

use glam::Vec3;
use hwsdf::nn::{
    GpuContext, NeuralSdf, Nglod, Normalization, QueryBuffers, QueryBuffersDescriptor, QueryOutputs,
};

/// Spheres on the robot's chain.
const SPHERES: usize = 256;
/// Planner frames.
const FRAMES: usize = 8;

/// Our own pass: counts the spheres whose centre distance is under their radius, reading the
/// query's results where they are (`array<vec4<f32>>`: distance, normal).
const COUNT: &str = r#"
struct Params { n: u32, radius: f32, _pad0: u32, _pad1: u32 }
@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> results: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> hits: atomic<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x < params.n && results[id.x].x < params.radius {
        atomicAdd(&hits, 1u);
    }
}
"#;

/// A sphere obstacle of radius 0.5 at the origin when no model is given.
fn obstacle() -> NeuralSdf {
    let model = Nglod::from_sdf(32, |p| p.length() - 0.5).expect("a valid grid");
    NeuralSdf::from_model_file(
        model.to_model_file(Normalization::identity(), serde_json::Value::Null),
    )
    .expect("a valid model")
}

/// The robot at frame `t`: a chain of spheres sweeping through the box.
fn robot(t: usize) -> Vec<Vec3> {
    let phase = t as f32 / FRAMES as f32;
    (0..SPHERES)
        .map(|i| {
            let s = i as f32 / (SPHERES - 1) as f32;
            Vec3::new(-1.2 + 2.4 * s, 0.6 - 1.2 * phase, 0.3 * (6.0 * s).sin())
        })
        .collect()
}

/// Sphere radius on the chain.
const RADIUS: f32 = 0.05;

/// Steps 1 and 2: every frame's distances and normals on the host, with two query buffers so
/// that frame `t + 1` is on the GPU while the host handles frame `t`. Returns per frame the
/// colliding spheres and the mean normal of the contacts.
fn plan(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
) -> Result<Vec<(usize, Vec3)>, Box<dyn std::error::Error>> {
    let desc = QueryBuffersDescriptor {
        label: Some("planner"),
        capacity: SPHERES as u32,
        outputs: QueryOutputs::ValuesAndNormals,
        ..Default::default()
    };
    let mut buffers: [QueryBuffers; 2] = [
        sdf.create_query_buffers(gpu, &desc)?,
        sdf.create_query_buffers(gpu, &desc)?,
    ];
    let mut hits = Vec::with_capacity(SPHERES); // reused every frame
    let mut frames = Vec::with_capacity(FRAMES);
    let [a, b] = &mut buffers;
    let mut pending = Some(sdf.submit_query(gpu, a, &robot(0))?);
    for t in 0..FRAMES {
        let (current, next) = if t % 2 == 0 {
            (&mut *a, &mut *b)
        } else {
            (&mut *b, &mut *a)
        };
        // Submit the next frame before reading this one: the GPU works while we do.
        let next_ticket = if t + 1 < FRAMES {
            Some(sdf.submit_query(gpu, next, &robot(t + 1))?)
        } else {
            None
        };
        let ticket = pending.take().expect("a query in flight");
        hits.clear();
        current
            .wait(gpu, ticket)?
            .extend_values_and_normals(&mut hits);
        let contacts: Vec<Vec3> = hits
            .iter()
            .filter(|(d, _)| *d < RADIUS)
            .map(|(_, n)| *n)
            .collect();
        let mean = contacts.iter().copied().sum::<Vec3>() / contacts.len().max(1) as f32;
        frames.push((contacts.len(), mean));
        pending = next_ticket;
    }
    Ok(frames)
}

/// Step 3: the query and our counting pass in one encoder; the distances never leave the GPU.
fn count_on_gpu(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
    points: &[Vec3],
) -> Result<u32, Box<dyn std::error::Error>> {
    let device = gpu.device();
    let mut buffers = sdf.create_query_buffers(
        gpu,
        &QueryBuffersDescriptor {
            label: Some("gpu-resident"),
            capacity: points.len() as u32,
            outputs: QueryOutputs::ValuesAndNormals,
            ..Default::default()
        },
    )?;
    let n = buffers.upload(gpu, points)?;
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("count"),
        source: wgpu::ShaderSource::Wgsl(COUNT.into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("count"),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    let params = gpu.uniform("count params", &[n, RADIUS.to_bits(), 0, 0]);
    let counter = gpu.storage_zeroed("hits", 4)?;
    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("count"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: params.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: buffers.results().as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: counter.as_entire_binding(),
            },
        ],
    });
    let mut enc = device.create_command_encoder(&Default::default());
    sdf.record_query(gpu, &mut enc, &mut buffers, n)?;
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(n.div_ceil(64), 1, 1);
    }
    gpu.queue().submit([enc.finish()]);
    Ok(gpu.read_back::<u32>(&counter)?[0])
}

fn main() -> ExitCode {
    let run = || -> Result<(), Box<dyn std::error::Error>> {
        let sdf = match std::env::args_os().nth(1) {
            Some(path) => NeuralSdf::load(path)?,
            None => obstacle(),
        };
        let gpu = GpuContext::new()?;
        println!("{} model on {}", sdf.architecture(), gpu.describe());
        for (t, (n, normal)) in plan(&gpu, &sdf)?.into_iter().enumerate() {
            println!(
                "frame {t}: {n:3} of {SPHERES} spheres collide, mean contact normal {normal:.2}"
            );
        }
        let last = robot(FRAMES / 2);
        println!(
            "frame {}: {} collisions counted on the GPU without reading the distances back",
            FRAMES / 2,
            count_on_gpu(&gpu, &sdf, &last)?
        );
        Ok(())
    };
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gpu() -> &'static GpuContext {
        GpuContext::shared().expect("a GPU adapter (lavapipe in CI)")
    }

    /// The overlapped planner sees, frame by frame, what the CPU evaluation sees: the same
    /// colliding spheres and the same contact normals.
    #[test]
    fn planner_matches_the_cpu() {
        let sdf = obstacle();
        let frames = plan(gpu(), &sdf).unwrap();
        assert_eq!(frames.len(), FRAMES);
        let mut any = 0;
        for (t, (n, normal)) in frames.iter().enumerate() {
            let cpu = sdf.eval_with_normals_cpu(&robot(t));
            let hits: Vec<Vec3> = cpu
                .iter()
                .filter(|(d, _)| *d < RADIUS)
                .map(|(_, n)| *n)
                .collect();
            assert_eq!(*n, hits.len(), "frame {t}");
            let mean = hits.iter().copied().sum::<Vec3>() / hits.len().max(1) as f32;
            assert!(
                (*normal - mean).length() < 1e-3,
                "frame {t}: {normal} vs {mean}"
            );
            any += n;
        }
        assert!(any > 0, "the sweep must hit the obstacle somewhere");
    }

    /// The GPU-resident count equals the count from the host's distances.
    #[test]
    fn gpu_resident_count_matches_the_cpu() {
        let sdf = obstacle();
        let pts = robot(FRAMES / 2);
        let cpu = sdf.eval_cpu(&pts).iter().filter(|d| **d < RADIUS).count();
        assert!(cpu > 0);
        assert_eq!(count_on_gpu(gpu(), &sdf, &pts).unwrap() as usize, cpu);
    }
}
