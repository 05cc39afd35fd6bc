//! Sphere-tracing a trained model from your own wgpu compute shader: the whole embedding path.
//!
//! ```sh
//! cargo run --release --example sphere_trace -- MODEL.safetensors out.png
//! ```
//!
//! Steps, each marked below:
//! 1. load the model;
//! 2. get its WGSL snippet (`hwsdf_distance`, `hwsdf_normal`, in mesh coordinates) for a bind
//!    group index of your choice, and concatenate it with your shader;
//! 3. upload the weights with `NeuralSdf::bind_group` on your device and put its layout in your
//!    pipeline layout at that index;
//! 4. dispatch, read the pixels back, write a PNG.
//!
//! The library's own tracer (`hwsdf::nn::render`, the `render` binary) does the same with more
//! options; this file keeps only what a renderer author needs to see.

use std::borrow::Cow;
use std::process::ExitCode;

use hwsdf::nn::{GpuContext, NeuralSdf, RgbaImage};
use wgpu::util::DeviceExt;

/// Image side in pixels.
const SIZE: u32 = 512;
/// The bind group index we give the model; our own resources use group 0.
const MODEL_GROUP: u32 = 1;

/// The renderer's shader. It only calls `hwsdf_distance` and `hwsdf_normal`, which the model's
/// snippet defines; it knows nothing about the network inside.
const TRACER: &str = r#"
struct Camera {
    eye: vec4<f32>,      // xyz: position (mesh coordinates), w: tan(fov / 2)
    forward: vec4<f32>,  // xyz: view direction, w: image side in pixels
    right: vec4<f32>,    // xyz: right vector, w: far distance (stop tracing)
    up: vec4<f32>,       // xyz: up vector, w: unused
}
@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read_write> pixels: array<u32>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let side = u32(cam.forward.w);
    if id.x >= side || id.y >= side {
        return;
    }
    let uv = (vec2<f32>(id.xy) + 0.5) / f32(side) * 2.0 - 1.0;
    let dir = normalize(cam.forward.xyz + cam.eye.w * (uv.x * cam.right.xyz - uv.y * cam.up.xyz));

    // Sphere tracing: step by the distance bound. The snippet's distance is valid everywhere
    // (outside the model's box it adds the distance to the box), so we can start at the eye.
    var t = 0.0;
    var color = vec4<f32>(0.12, 0.13, 0.16, 1.0);
    for (var i = 0; i < 200; i++) {
        let p = cam.eye.xyz + t * dir;
        let d = hwsdf_distance(p);
        // Hit when within a fraction of a pixel's footprint at this distance.
        if d < 0.25 * t * cam.eye.w / f32(side) {
            // Lambert shading from the analytic normal, light from the upper left.
            let light = normalize(-0.5 * cam.right.xyz + 0.8 * cam.up.xyz - 0.6 * cam.forward.xyz);
            let lambert = max(dot(hwsdf_normal(p), light), 0.0);
            let shade = vec3<f32>(0.85, 0.72, 0.55) * (0.15 + 0.85 * lambert);
            color = vec4<f32>(pow(shade, vec3<f32>(1.0 / 2.2)), 1.0);
            break;
        }
        // 0.9: a trained network is only approximately a distance.
        t += 0.9 * d;
        if t > cam.right.w {
            break;
        }
    }
    pixels[id.y * side + id.x] = pack4x8unorm(color);
}
"#;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [model, out] = args.as_slice() else {
        eprintln!("usage: sphere_trace MODEL.safetensors OUT.png");
        return ExitCode::FAILURE;
    };
    match run(model, out) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(model: &str, out: &str) -> Result<(), Box<dyn std::error::Error>> {
    // 1. The model. Coordinates in and out of the snippet are the original mesh's.
    let sdf = NeuralSdf::load(model)?;

    // Any wgpu device works; we borrow HW SDF's adapter choice (WGPU_ADAPTER_NAME etc.) here.
    let gpu = GpuContext::new()?;
    let (device, queue) = (gpu.device(), gpu.queue());

    // 2. The snippet, bound at MODEL_GROUP, followed by our shader.
    let source = format!("{}\n{}", sdf.wgsl(MODEL_GROUP), TRACER);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("tracer + hwsdf"),
        source: wgpu::ShaderSource::Wgsl(Cow::Owned(source)),
    });

    // 3. The weights on our device, and the layout that goes at MODEL_GROUP.
    let model_group = sdf.bind_group(device)?;

    // Our own resources: the camera and the pixels.
    let camera = camera(&sdf);
    let camera_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("camera"),
        contents: &camera
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>(),
        usage: wgpu::BufferUsages::UNIFORM,
    });
    let pixel_bytes = u64::from(SIZE * SIZE * 4);
    let pixels = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("pixels"),
        size: pixel_bytes,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: pixel_bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    };
    let our_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("tracer"),
        entries: &[
            entry(0, wgpu::BufferBindingType::Uniform),
            entry(1, wgpu::BufferBindingType::Storage { read_only: false }),
        ],
    });
    let our_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("tracer"),
        layout: &our_layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: camera_buffer.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: pixels.as_entire_binding(),
            },
        ],
    });

    // An explicit pipeline layout: index 0 is ours, index MODEL_GROUP is the model's.
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("tracer"),
        bind_group_layouts: &[Some(&our_layout), Some(&model_group.layout)],
        immediate_size: 0,
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("tracer"),
        layout: Some(&pipeline_layout),
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });

    // 4. Dispatch one invocation per pixel, copy the pixels out, wait.
    let mut encoder = device.create_command_encoder(&Default::default());
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &our_group, &[]);
        pass.set_bind_group(MODEL_GROUP, &model_group.bind_group, &[]);
        pass.dispatch_workgroups(SIZE.div_ceil(8), SIZE.div_ceil(8), 1);
    }
    encoder.copy_buffer_to_buffer(&pixels, 0, &readback, 0, pixel_bytes);
    queue.submit([encoder.finish()]);
    readback.slice(..).map_async(wgpu::MapMode::Read, |result| {
        if let Err(e) = result {
            eprintln!("mapping the pixels failed: {e}");
        }
    });
    device.poll(wgpu::PollType::wait_indefinitely())?;
    let bytes = readback.slice(..).get_mapped_range()?.to_vec();

    // pack4x8unorm put R in the low byte, so the little-endian u32s are already RGBA bytes.
    let image = RgbaImage {
        width: SIZE,
        height: SIZE,
        pixels: bytes,
    };
    image.save_png(out)?; // written atomically
    println!("wrote {out}");
    Ok(())
}

/// An orbit camera looking at the centre of the model's box from the front-right and above,
/// far enough that the box's inscribed sphere (radius 1 in normalised units) fills the frame.
fn camera(sdf: &NeuralSdf) -> [f32; 16] {
    use glam::Vec3;
    let n = sdf.normalization();
    let radius = 1.05 / n.scale; // normalised units -> mesh units
    let tan_half = (35f32.to_radians() / 2.0).tan();
    let distance = radius * (1.0 + tan_half * tan_half).sqrt() / tan_half; // radius / sin(fov/2)
    let from_center = Vec3::new(0.55, 0.35, 0.75).normalize();
    let eye = n.center.as_vec3() + distance * from_center;
    let forward = -from_center;
    let right = forward.cross(Vec3::Y).normalize();
    let up = right.cross(forward);
    let far = distance + 2.0 * 3f32.sqrt() / n.scale;
    [
        eye.x,
        eye.y,
        eye.z,
        tan_half, //
        forward.x,
        forward.y,
        forward.z,
        SIZE as f32, //
        right.x,
        right.y,
        right.z,
        far, //
        up.x,
        up.y,
        up.z,
        0.0,
    ]
}
