//! Sphere-traced images of a [`NeuralSdf`]: the embedding of [`crate::serve::wgsl`] used for real.
//!
//! `shaders/sphere_trace.wgsl` is a compute shader with one invocation per pixel. It is compiled
//! concatenated after the model's snippet ([`NeuralSdf::wgsl`] at group 1), traces a ray from
//! an orbit camera through the model's box, shades hits by Lambert's law from `hwsdf_normal`
//! and writes packed RGBA8 pixels to a storage buffer, which is read back into an [`RgbaImage`].
//!
//! ```no_run
//! # fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use sdf_nn::{GpuContext, NeuralSdf, RenderOptions, render};
//! let gpu = GpuContext::new()?;
//! let sdf = NeuralSdf::load("model.safetensors")?;
//! let image = render(&gpu, &sdf, &RenderOptions::default())?;
//! image.save_png("model.png")?;
//! # Ok(()) }
//! ```

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use glam::{Vec3, Vec4};

use crate::gpu::{GpuContext, GpuError, storage_layout_entry};
use crate::model_file::{Normalization, write_atomic};
use crate::serve::neural::NeuralSdf;
use crate::serve::scene::{Scene, SceneBindGroup, SceneGpuError};
use crate::serve::scratch::{self, SCRATCH_GROUP};
use crate::serve::wgsl::{EmbedError, Lanes, SdfBindGroup};
use crate::shaders::SPHERE_TRACE;

/// Largest image side we accept (keeps the pixel buffer and the dispatch within every device's
/// limits).
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// The group index the sphere tracer gives the model's bind group (its own resources use 0).
const SDF_GROUP: u32 = 1;
/// Workgroup side of `sphere_trace` (8×8 invocations).
const TILE: u32 = 8;
/// The pixels' over-relaxation factor (`march.x` in the shader): a CPU model of the rays of the
/// example scene and of the scene benchmark found 1.4 near the fewest evaluations of both
/// (1.2–1.8 tried: 4.3 and 4.0 a pixel after cones stopping at 3 radii, against 6.0 and 5.6
/// plain).
const OVER_RELAX: f32 = 1.4;
/// Pixels per side of the tile one cone of the cone pass holds (`CONE_TILE` in the shader). 4
/// makes the pixels' part shorter (a CPU model of the example scene's rays: 5.5 evaluations a
/// pixel against 6.2) and the cones' longer; on lavapipe it rendered 2–5 % slower than 8.
const CONE_TILE: u32 = 8;

/// Errors of rendering and of writing images.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// Width or height is zero or above [`MAX_IMAGE_SIDE`].
    #[error(
        "image size {width}x{height} is out of range: each side must be in 1..={MAX_IMAGE_SIDE}"
    )]
    BadSize {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
    },
    /// A rendering option is out of range.
    #[error("invalid render option: {0}")]
    BadOption(String),
    /// The model's weights cannot be bound on this device.
    #[error(transparent)]
    Embed(#[from] EmbedError),
    /// The scene's weights cannot be bound on this device.
    #[error(transparent)]
    Scene(#[from] SceneGpuError),
    /// A GPU error (buffer limits, shader compilation, readback).
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// PNG encoding failed.
    #[error("encoding the PNG failed: {0}")]
    Png(String),
    /// Writing the image file failed.
    #[error("writing {path}: {source}")]
    Io {
        /// The output path.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// What to render and how. Angles are in degrees; the camera orbits the centre of the model's
/// normalised box (see [`Camera::orbit`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Camera azimuth around the vertical (+y) axis; 0 looks along −z.
    pub yaw_degrees: f32,
    /// Camera elevation above the horizontal plane.
    pub pitch_degrees: f32,
    /// Vertical field of view.
    pub fov_y_degrees: f32,
    /// Radius, in the model's normalised units, of the sphere around the box centre that just
    /// fits the frame. The mesh's longest axis spans `[-1, 1]`: 1.0 frames a round object
    /// tightly, the default 1.3 keeps the corners of elongated ones, √3 shows the whole box
    /// from any angle.
    pub frame_radius: f32,
    /// Steps per ray before giving up (a miss).
    pub max_steps: u32,
    /// Fraction of the distance bound taken per step: below 1 because a network is only
    /// approximately a distance.
    pub step_scale: f32,
    /// A ray hits when the distance falls below this fraction of one pixel's footprint.
    pub hit_tolerance_px: f32,
    /// Direction towards the light in the camera's frame (x right, y up, z towards the viewer).
    pub light: Vec3,
    /// Ambient fraction of the shading, in `[0, 1]`.
    pub ambient: f32,
    /// Surface colour (linear RGB).
    pub albedo: Vec3,
    /// Colour of pixels whose ray misses (RGBA, written as is; alpha 0 for a transparent PNG).
    pub background: Vec4,
    /// The level `c` (mesh or scene units): the surface drawn is the set `d = c`, an offset
    /// surface for `c ≠ 0`.
    pub level: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 512,
            height: 512,
            yaw_degrees: 35.0,
            pitch_degrees: 20.0,
            fov_y_degrees: 35.0,
            frame_radius: 1.3,
            max_steps: 160,
            step_scale: 0.9,
            hit_tolerance_px: 0.25,
            light: Vec3::new(-0.5, 0.8, 0.6),
            ambient: 0.15,
            albedo: Vec3::new(0.85, 0.72, 0.55),
            background: Vec4::new(0.12, 0.13, 0.16, 1.0),
            level: 0.0,
        }
    }
}

impl RenderOptions {
    /// Checks sizes and ranges.
    pub fn validate(&self) -> Result<(), RenderError> {
        let side = 1..=MAX_IMAGE_SIDE;
        if !side.contains(&self.width) || !side.contains(&self.height) {
            return Err(RenderError::BadSize {
                width: self.width,
                height: self.height,
            });
        }
        let bad = |m: String| Err(RenderError::BadOption(m));
        if !(self.fov_y_degrees > 0.0 && self.fov_y_degrees < 170.0) {
            return bad(format!(
                "fov_y_degrees {} is not in (0, 170)",
                self.fov_y_degrees
            ));
        }
        if !(self.frame_radius.is_finite() && self.frame_radius > 0.0) {
            return bad(format!(
                "frame_radius {} is not positive",
                self.frame_radius
            ));
        }
        if !self.level.is_finite() {
            return bad(format!("level {} is not finite", self.level));
        }
        if !(self.step_scale > 0.0 && self.step_scale <= 1.0) {
            return bad(format!("step_scale {} is not in (0, 1]", self.step_scale));
        }
        if !(self.hit_tolerance_px.is_finite() && self.hit_tolerance_px > 0.0) {
            return bad(format!(
                "hit_tolerance_px {} is not positive",
                self.hit_tolerance_px
            ));
        }
        if self.max_steps == 0 || self.max_steps > 100_000 {
            return bad(format!("max_steps {} is not in 1..=100000", self.max_steps));
        }
        if !self.pitch_degrees.is_finite() || self.pitch_degrees.abs() >= 89.9 {
            return bad(format!(
                "pitch_degrees {} is not in (-89.9, 89.9)",
                self.pitch_degrees
            ));
        }
        if !self.yaw_degrees.is_finite() {
            return bad("yaw_degrees is not finite".into());
        }
        if !self.light.is_finite() || self.light.length() == 0.0 {
            return bad("light must be a non-zero finite direction".into());
        }
        Ok(())
    }
}

/// A pinhole camera in the mesh's coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Camera position.
    pub eye: Vec3,
    /// Unit view direction.
    pub forward: Vec3,
    /// Unit right vector.
    pub right: Vec3,
    /// Unit up vector.
    pub up: Vec3,
    /// `tan(fov_y / 2)`.
    pub tan_half_fov_y: f32,
    /// Width / height.
    pub aspect: f32,
}

impl Camera {
    /// The orbit camera of `options` around the model's box: it looks at the box centre from
    /// the direction given by yaw and pitch, at the distance where a sphere of radius
    /// `frame_radius` (normalised units) is tangent to the narrower side of the frustum. Derived
    /// from the normalisation alone, so any model fills the frame the same way.
    pub fn orbit(normalization: Normalization, options: &RenderOptions) -> Camera {
        let target = normalization.center.as_vec3();
        let radius = options.frame_radius / normalization.scale;
        let aspect = options.width as f32 / options.height as f32;
        let tan_half_y = (options.fov_y_degrees.to_radians() * 0.5).tan();
        // The narrower half-angle bounds what fits.
        let tan_half = tan_half_y * aspect.min(1.0);
        let sin_half = tan_half / (1.0 + tan_half * tan_half).sqrt();
        let distance = radius / sin_half;
        let (yaw, pitch) = (
            options.yaw_degrees.to_radians(),
            options.pitch_degrees.to_radians(),
        );
        let from_target = Vec3::new(
            pitch.cos() * yaw.sin(),
            pitch.sin(),
            pitch.cos() * yaw.cos(),
        );
        let eye = target + distance * from_target;
        let forward = -from_target;
        let right = forward.cross(Vec3::Y).normalize();
        let up = right.cross(forward);
        Camera {
            eye,
            forward,
            right,
            up,
            tan_half_fov_y: tan_half_y,
            aspect,
        }
    }
}

/// The uniforms of `sphere_trace.wgsl` (its `TraceUniforms`, field for field).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct TraceUniforms {
    eye: [f32; 4],
    forward: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    light: [f32; 4],
    albedo: [f32; 4],
    background: [f32; 4],
    box_min: [f32; 4],
    box_max: [f32; 4],
    size: [u32; 4],
    march: [f32; 4],
}

/// An 8-bit RGBA image, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbaImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width · height · 4` bytes, R G B A per pixel.
    pub pixels: Vec<u8>,
}

impl RgbaImage {
    /// The pixel at column `x`, row `y` (0 is the top row).
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = ((y * self.width + x) * 4) as usize;
        [
            self.pixels[i],
            self.pixels[i + 1],
            self.pixels[i + 2],
            self.pixels[i + 3],
        ]
    }

    /// The image as PNG bytes.
    pub fn to_png(&self) -> Result<Vec<u8>, RenderError> {
        let png_err = |e: png::EncodingError| RenderError::Png(e.to_string());
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, self.width, self.height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        // Renders are mostly flat background: the best compression keeps committed images small.
        encoder.set_compression(png::Compression::High);
        let mut writer = encoder.write_header().map_err(png_err)?;
        writer.write_image_data(&self.pixels).map_err(png_err)?;
        writer.finish().map_err(png_err)?;
        Ok(out)
    }

    /// Writes the image as a PNG file, atomically (readers never see a partial file).
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<(), RenderError> {
        let path = path.as_ref();
        let bytes = self.to_png()?;
        write_atomic(path, &bytes).map_err(|source| RenderError::Io {
            path: path.to_owned(),
            source,
        })
    }
}

/// A model's or a scene's sphere-tracing pipeline and weights on one device, for rendering
/// many images.
#[derive(Debug)]
pub struct Renderer {
    pipeline: wgpu::ComputePipeline,
    /// The cone pre-pass (`cone_trace`): where each tile's rays may start.
    cones: wgpu::ComputePipeline,
    /// See [`Renderer::set_accelerated`].
    accelerated: bool,
    frame_layout: wgpu::BindGroupLayout,
    weights: Weights,
    /// The box traced and framed: a model's normalised cube, a scene's [`Scene::frame`].
    normalization: Normalization,
    /// Parameters of the model: the multiply-adds of one evaluation, at most.
    macs_per_eval: u64,
    /// See [`Renderer::set_max_submission_macs`].
    max_submission_macs: u64,
    /// Where the snippet's SIRENs keep their activations in scratch
    /// ([`crate::SirenActivations::Scratch`]).
    scratch: Option<PixelScratch>,
}

/// The tracer's scratch: a slot of `stride` floats per pixel of a band, in a buffer each image
/// allocates (at most `limit` bytes, the device's binding) bound with `layout` at
/// [`SCRATCH_GROUP`].
#[derive(Debug)]
struct PixelScratch {
    stride: u32,
    layout: wgpu::BindGroupLayout,
    limit: u64,
}

/// What the tracer's group 1 binds: a model's weights or a scene's.
#[derive(Debug)]
enum Weights {
    Model(SdfBindGroup),
    Scene(SceneBindGroup),
}

impl Weights {
    fn layout(&self) -> &wgpu::BindGroupLayout {
        match self {
            Weights::Model(w) => &w.layout,
            Weights::Scene(w) => &w.layout,
        }
    }

    fn bind_group(&self) -> &wgpu::BindGroup {
        match self {
            Weights::Model(w) => &w.bind_group,
            Weights::Scene(w) => &w.bind_group,
        }
    }
}

impl Renderer {
    /// Rows of one submission for `options` (a multiple of the 8-row tile, at least one tile).
    pub fn band_rows(&self, options: &RenderOptions) -> u32 {
        let per_row = u64::from(options.width)
            * u64::from(options.max_steps.max(1))
            * self.macs_per_eval.max(1);
        let mut rows = self.max_submission_macs / per_row.max(1);
        if let Some(scratch) = &self.scratch {
            // A band's pixels each hold a slot of the scratch, of at most MAX_SCRATCH_BYTES
            // where a band of one tile row fits that, else the binding (an image too wide for
            // one tile row of slots gets the binding's error).
            let per_row = 4 * u64::from(scratch.stride) * u64::from(options.width);
            let bytes = scratch::MAX_SCRATCH_BYTES.max(per_row * u64::from(TILE));
            rows = rows.min(bytes.min(scratch.limit) / per_row.max(1));
        }
        let rows = rows / u64::from(TILE) * u64::from(TILE);
        rows.clamp(
            u64::from(TILE),
            u64::from(options.height.next_multiple_of(TILE)),
        ) as u32
    }

    /// Bounds the worst-case multiply-adds of one submission (default 2^38; see
    /// [`Renderer::band_rows`]): lower it for a driver with a shorter watchdog. Images are
    /// traced in bands of rows, one submission each, with the same pixels whatever the bands.
    pub fn set_max_submission_macs(&mut self, macs: u64) {
        self.max_submission_macs = macs;
    }

    /// Whether rays are traced with the cone pre-pass and over-relaxed steps (default: yes).
    /// Without them every pixel's ray starts at the box and steps by its room alone, as before
    /// they existed: for comparisons. The images differ on a few silhouette pixels: rays that
    /// used to run out of steps (grazing rays), which now hit; grazing rays that passed within
    /// the hit tolerance of the surface without meeting it, which may now miss; and shades a few
    /// levels apart where a ray stops elsewhere within the tolerance.
    pub fn set_accelerated(&mut self, enabled: bool) {
        self.accelerated = enabled;
    }

    /// Compiles the sphere tracer for `sdf` (its current level of detail) and uploads its
    /// weights. Compilation is the slow part (seconds on lavapipe): keep the renderer.
    pub fn new(gpu: &GpuContext, sdf: &NeuralSdf) -> Result<Self, RenderError> {
        let weights = Weights::Model(sdf.bind_group(gpu.device())?);
        let stride = scratch::stride(gpu, [sdf.network()]);
        let source = format!(
            "{}{}\n{}",
            scratch::prelude(stride),
            sdf.wgsl_with_activations(SDF_GROUP, scratch::activations(stride)),
            SPHERE_TRACE.source
        );
        Self::compile(
            gpu,
            source,
            weights,
            (sdf.normalization(), sdf.param_count() as u64),
            stride,
        )
    }

    /// Compiles the sphere tracer for a whole scene ([`Scene::wgsl_with_prefix`]) and uploads
    /// its weights. The camera frames [`Scene::frame`] (at the options' level, when the image is
    /// rendered); rays step by the scene's trace field (`{prefix}_trace`: at least `|d − c|`
    /// over the scene's Lipschitz bound, see [`Scene::trace_rays`]).
    pub fn for_scene(gpu: &GpuContext, scene: &Scene) -> Result<Self, RenderError> {
        // The tracer binds two storage buffers besides the weights: its image and its tiles'
        // starts (group 0's bindings 1 and 2 in `compile`).
        let stride = scratch::stride(gpu, scene.models().iter().map(|m| m.network()));
        let (snippets, weights) = scene.compile(
            gpu.device(),
            SDF_GROUP,
            "scene",
            2 + u32::from(stride.is_some()),
            &[Lanes::One],
            scratch::activations(stride),
        )?;
        let weights = Weights::Scene(weights);
        let source = format!(
            "{}{}\n\
             fn hwsdf_trace(p: vec3<f32>, c: f32) -> vec2<f32> {{ return scene_trace(p, c); }}\n\
             fn hwsdf_normal(p: vec3<f32>) -> vec3<f32> {{ return scene_normal(p); }}\n{}",
            scratch::prelude(stride),
            snippets[0],
            SPHERE_TRACE.source
        );
        let params: u64 = scene
            .models()
            .iter()
            .map(|m| m.param_count() as u64)
            .sum::<u64>()
            + scene.leaves().len() as u64 * 64;
        Self::compile(gpu, source, weights, (scene.frame(0.0), params), stride)
    }

    /// The pipeline of `source` (a snippet defining `hwsdf_trace` and `hwsdf_normal`, then
    /// the tracer) with `weights` at group 1, for the box `framed.0` and evaluations of at most
    /// `framed.1` multiply-adds; with a scratch group of `stride` floats per pixel where the
    /// snippet's SIRENs keep their activations in scratch.
    fn compile(
        gpu: &GpuContext,
        source: String,
        weights: Weights,
        (normalization, macs_per_eval): (Normalization, u64),
        stride: Option<u32>,
    ) -> Result<Self, RenderError> {
        let device = gpu.device();
        let frame_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("sphere_trace frame"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage_layout_entry(1, false),
                storage_layout_entry(2, false),
            ],
        });
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = gpu.generated_module(SPHERE_TRACE.name, Cow::Owned(source));
        // An explicit layout: the weights' group is created from its own layout (by
        // `NeuralSdf::bind_group` or `Scene::upload`), which a derived layout would not accept.
        let scratch = stride.map(|stride| PixelScratch {
            stride,
            layout: scratch::layout(device),
            limit: crate::gpu::binding_limit(&gpu.limits()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("sphere_trace"),
            bind_group_layouts: &[
                Some(&frame_layout),
                Some(weights.layout()),
                scratch.as_ref().map(|s| &s.layout),
            ],
            immediate_size: 0,
        });
        let entry = |name: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(name),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let (pipeline, cones) = (entry("sphere_trace"), entry("cone_trace"));
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Wgpu {
                context: "compiling sphere_trace.wgsl with the model's snippet".into(),
                message: err.to_string(),
            }
            .into());
        }
        Ok(Renderer {
            pipeline,
            cones,
            accelerated: true,
            frame_layout,
            weights,
            normalization,
            macs_per_eval,
            max_submission_macs: MAX_SUBMISSION_MACS,
            scratch,
        })
    }

    /// Renders one image.
    pub fn render(
        &self,
        gpu: &GpuContext,
        options: &RenderOptions,
    ) -> Result<RgbaImage, RenderError> {
        Ok(self.render_with_tiles(gpu, options)?.0)
    }

    /// [`Renderer::render`], with the buffer of the tiles' start depths (`tile_start`).
    fn render_with_tiles(
        &self,
        gpu: &GpuContext,
        options: &RenderOptions,
    ) -> Result<(RgbaImage, wgpu::Buffer), RenderError> {
        options.validate()?;
        let (w, h) = (options.width, options.height);
        // A positive level grows the surface: grow the traced box with it.
        let n = Normalization {
            scale: 1.0 / (1.0 / self.normalization.scale + options.level.max(0.0)),
            ..self.normalization
        };
        let cam = Camera::orbit(n, options);
        // The light is given in the camera's frame so that it follows the orbit.
        let l = options.light.normalize();
        let light = (l.x * cam.right + l.y * cam.up - l.z * cam.forward).normalize();
        let half = 1.0 / n.scale;
        let pixel_angle = 2.0 * cam.tan_half_fov_y / h as f32;
        let uniforms = TraceUniforms {
            eye: cam.eye.extend(cam.tan_half_fov_y).to_array(),
            forward: cam.forward.extend(cam.aspect).to_array(),
            right: cam
                .right
                .extend(options.hit_tolerance_px * pixel_angle)
                .to_array(),
            // The step factor on `hwsdf_trace`'s step: a model's distance, or a scene's ball
            // radius, safe already (each operand divided by its own bound).
            up: cam.up.extend(options.step_scale).to_array(),
            light: light.extend(options.ambient.clamp(0.0, 1.0)).to_array(),
            albedo: options.albedo.extend(1.0).to_array(),
            background: options.background.to_array(),
            // A floor on the tolerance for rays that start at the camera's own position.
            box_min: (n.center.as_vec3() - Vec3::splat(half))
                .extend(1e-5 * half)
                .to_array(),
            box_max: (n.center.as_vec3() + Vec3::splat(half))
                .extend(options.level)
                .to_array(),
            size: [w, h, options.max_steps, 0],
            march: [
                if self.accelerated { OVER_RELAX } else { 1.0 },
                0.0,
                0.0,
                0.0,
            ],
        };
        let pixels_bytes = u64::from(w) * u64::from(h) * 4;
        let image = gpu.storage_zeroed("sphere_trace image", pixels_bytes)?;
        let (tiles_x, tiles_y) = (w.div_ceil(CONE_TILE), h.div_ceil(CONE_TILE));
        let tiles = gpu.storage_zeroed(
            "sphere_trace tile starts",
            u64::from(tiles_x) * u64::from(tiles_y) * 4,
        )?;
        let device = gpu.device();
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        // One submission per band of rows, so that no single submission runs long enough for a
        // driver's watchdog (a desktop GPU resets after about 2 s) however large the image or
        // the network.
        let rows = self.band_rows(options);
        let scratch = match &self.scratch {
            Some(s) => Some(scratch::bind_group(gpu, &s.layout, s.stride, w * rows)?),
            None => None,
        };
        for first in (0..h).step_by(rows as usize) {
            let band = TraceUniforms {
                size: [w, h, options.max_steps, first],
                march: [uniforms.march[0], (first + rows).min(h) as f32, 0.0, 0.0],
                ..uniforms
            };
            let uniform = gpu.uniform("sphere_trace uniforms", &band);
            let frame = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("sphere_trace frame"),
                layout: &self.frame_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: uniform.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: image.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: tiles.as_entire_binding(),
                    },
                ],
            });
            let mut enc = device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("sphere_trace"),
                    timestamp_writes: None,
                });
                pass.set_bind_group(0, &frame, &[]);
                pass.set_bind_group(SDF_GROUP, self.weights.bind_group(), &[]);
                if let Some(group) = &scratch {
                    pass.set_bind_group(SCRATCH_GROUP, group, &[]);
                }
                let band_rows = rows.min(h - first);
                if self.accelerated {
                    // One invocation per cone, 8 × 8 of them a workgroup.
                    let cones_y = band_rows.div_ceil(CONE_TILE);
                    pass.set_pipeline(&self.cones);
                    pass.dispatch_workgroups(tiles_x.div_ceil(8), cones_y.div_ceil(8), 1);
                }
                pass.set_pipeline(&self.pipeline);
                pass.dispatch_workgroups(w.div_ceil(TILE), band_rows.div_ceil(TILE), 1);
            }
            gpu.queue().submit([enc.finish()]);
        }
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Wgpu {
                context: "dispatching sphere_trace".into(),
                message: err.to_string(),
            }
            .into());
        }
        let pixels: Vec<u8> = gpu.read_back(&image)?;
        let image = RgbaImage {
            width: w,
            height: h,
            pixels,
        };
        Ok((image, tiles))
    }
}

/// Multiply-adds one submission of the sphere tracer may cost at most, counting every ray at
/// its step limit and one multiply-add per parameter per evaluation (a SIREN's cost; an
/// overestimate for NGLOD, which reads only a few of its grid features): 2^38, tens of
/// milliseconds on a desktop GPU in that worst case, far below the watchdogs that reset a GPU
/// after a long submission.
const MAX_SUBMISSION_MACS: u64 = 1 << 38;

/// The sphere tracer's full source for `sdf`: the model's snippet at group 1, then
/// `shaders/sphere_trace.wgsl` (the form for GPUs; see [`crate::SirenActivations`]).
pub fn sphere_trace_source(sdf: &NeuralSdf) -> String {
    format!("{}\n{}", sdf.wgsl(SDF_GROUP), SPHERE_TRACE.source)
}

/// Renders `sdf` with `options` on `gpu` (compiles a [`Renderer`] for this one image).
pub fn render(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
    options: &RenderOptions,
) -> Result<RgbaImage, RenderError> {
    options.validate()?;
    Renderer::new(gpu, sdf)?.render(gpu, options)
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::{CONE_TILE, Camera, RenderOptions, Renderer, TILE};
    use crate::{GpuContext, NeuralSdf, Nglod, Normalization};

    /// The tracer's uniforms have the layout `sphere_trace.wgsl` reads, with the same tile.
    #[test]
    fn trace_uniforms_mirror_the_shader() {
        crate::shaders::assert_mirrors!(
            super::TraceUniforms,
            super::SPHERE_TRACE,
            "TraceUniforms",
            [
                eye, forward, right, up, light, albedo, background, box_min, box_max, size, march
            ]
        );
        let source = super::SPHERE_TRACE.source;
        assert!(source.contains(&format!("const TILE: u32 = {TILE}u;")));
        assert!(source.contains(&format!("const CONE_TILE: u32 = {CONE_TILE}u;")));
        assert_eq!(TILE % CONE_TILE, 0, "a band of rows is made of whole cones");
        assert!(source.contains("@workgroup_size(8, 8)\nfn sphere_trace"));
    }

    /// The cone pass on a sphere of radius 0.6 (baked, no training), seen from two sides and
    /// in bands of one tile row: every tile's start lies before the first hit of each of its
    /// rays on the exact sphere (less the model's error), and the tiles on the sphere start past
    /// half the way from the box to it; the image is the one traced plainly (no cones, no
    /// over-relaxation) but for a few silhouette pixels.
    #[test]
    fn cones_start_rays_before_the_surface() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let n = Normalization {
            center: Vec3::new(1.0, -2.0, 0.5).as_dvec3(),
            scale: 0.25,
        };
        let model = Nglod::from_sdf(32, |p| p.length() - 0.6).unwrap();
        let sdf =
            NeuralSdf::from_model_file(model.to_model_file(n, serde_json::Value::Null)).unwrap();
        let (centre, radius, half) = (n.center.as_vec3(), 0.6 / n.scale, 1.0 / n.scale);
        let mut renderer = Renderer::new(gpu, &sdf).unwrap();
        renderer.set_max_submission_macs(1);
        for (width, height, yaw, pitch) in
            [(160u32, 120u32, 35.0f32, 20.0f32), (90, 132, -70.0, -45.0)]
        {
            let options = RenderOptions {
                width,
                height,
                yaw_degrees: yaw,
                pitch_degrees: pitch,
                ..RenderOptions::default()
            };
            renderer.set_accelerated(true);
            let (image, starts) = tile_starts(gpu, &renderer, &options);
            renderer.set_accelerated(false);
            let plain = renderer.render(gpu, &options).unwrap();
            // First crossing of the ray with the sphere.
            let sphere_hit = |o: Vec3, d: Vec3| {
                let o = o - centre;
                let b = o.dot(d);
                let disc = b * b - (o.length_squared() - radius * radius);
                (disc >= 0.0).then(|| -b - disc.sqrt())
            };
            // The baked sphere is within 4e-3 (normalised) of the exact one.
            let (advanced, covered) =
                check_tile_starts(n, &options, &starts, &sphere_hit, 4e-3 * half);
            assert!(covered >= 8, "{covered} tiles on the sphere");
            assert!(
                advanced * 10 >= covered * 9,
                "{advanced} of {covered} tiles on the sphere start past half the way to it"
            );
            // Where a ray stops within the hit tolerance moves (along grazing rays, by much),
            // and with it the normal: a shade some levels off, on a few pixels; hits and misses
            // agree, and no ray stops on a far side (a shade of ambient light only, ~100 levels
            // off).
            let (mut shaded, mut sides, mut worst) = (0, 0, 0);
            for (a, b) in image.pixels.chunks(4).zip(plain.pixels.chunks(4)) {
                sides += usize::from((a[3] > 0) != (b[3] > 0));
                let diff = a.iter().zip(b).map(|(u, v)| u.abs_diff(*v)).max().unwrap();
                shaded += usize::from(diff > 2);
                worst = worst.max(diff);
            }
            let pixels = (width * height) as usize;
            assert!(
                sides * 1000 <= pixels,
                "{sides} pixels hit on one side only"
            );
            assert!(shaded * 100 <= pixels, "{shaded} pixels shaded differently");
            assert!(worst <= 48, "a pixel differs by {worst} levels");
        }
    }

    /// Renders `options` and reads back the tiles' start depths.
    fn tile_starts(
        gpu: &GpuContext,
        renderer: &Renderer,
        options: &RenderOptions,
    ) -> (super::RgbaImage, Vec<f32>) {
        let (image, tiles) = renderer.render_with_tiles(gpu, options).unwrap();
        (image, gpu.read_back(&tiles).unwrap())
    }

    /// Asserts that each tile's start lies before `hit` (the first crossing of the ray from the
    /// eye in a unit direction with the exact surface) of every ray of the tile, less `slack`;
    /// returns how many of the tiles whose rays all hit start past half the way from the box to
    /// the nearest hit, and how many tiles' rays all hit.
    fn check_tile_starts(
        n: Normalization,
        options: &RenderOptions,
        starts: &[f32],
        hit: &dyn Fn(Vec3, Vec3) -> Option<f32>,
        slack: f32,
    ) -> (usize, usize) {
        let (width, height) = (options.width, options.height);
        let cam = Camera::orbit(n, options);
        let direction = |x: f32, y: f32| {
            let ndc = (x / width as f32 * 2.0 - 1.0, 1.0 - y / height as f32 * 2.0);
            let th = cam.tan_half_fov_y;
            (cam.forward + ndc.0 * th * cam.aspect * cam.right + ndc.1 * th * cam.up).normalize()
        };
        let (centre, half) = (n.center.as_vec3(), 1.0 / n.scale);
        let box_entry = |d: Vec3| {
            let t0 = (centre - half - cam.eye) / d;
            let t1 = (centre + half - cam.eye) / d;
            t0.min(t1).max_element()
        };
        let tiles_x = width.div_ceil(CONE_TILE);
        let (mut advanced, mut covered) = (0, 0);
        for (k, &start) in starts.iter().enumerate() {
            let (tx, ty) = (k as u32 % tiles_x, k as u32 / tiles_x);
            let mut first_hit = f32::INFINITY;
            let mut entry = f32::INFINITY;
            let mut all_hit = true;
            for y in ty * CONE_TILE..((ty + 1) * CONE_TILE).min(height) {
                for x in tx * CONE_TILE..((tx + 1) * CONE_TILE).min(width) {
                    let d = direction(x as f32 + 0.5, y as f32 + 0.5);
                    let h = hit(cam.eye, d);
                    all_hit &= h.is_some();
                    first_hit = first_hit.min(h.unwrap_or(f32::INFINITY));
                    entry = entry.min(box_entry(d));
                }
            }
            assert!(
                start <= first_hit + slack,
                "tile {tx},{ty}: starts at {start}, a ray hits at {first_hit}"
            );
            if all_hit {
                covered += 1;
                advanced += usize::from(start >= entry + 0.5 * (first_hit - entry));
            }
        }
        (advanced, covered)
    }

    /// The cones on a cuboid whose ends lie flat on the box's faces, seen obliquely: there the
    /// cone's axis passes outside the box, where the box rule's value exceeds the distance to
    /// the surface (by up to √2), and every tile's start still lies before the first hit of each
    /// of its rays on the exact cuboid.
    #[test]
    fn cones_stay_before_faces_on_the_box() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let half_extents = Vec3::new(1.0, 0.4, 0.4);
        let model = Nglod::from_sdf(32, |p| {
            let q = p.abs() - half_extents;
            q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
        })
        .unwrap();
        let n = Normalization::identity();
        let sdf =
            NeuralSdf::from_model_file(model.to_model_file(n, serde_json::Value::Null)).unwrap();
        let renderer = Renderer::new(gpu, &sdf).unwrap();
        let cuboid_hit = |o: Vec3, d: Vec3| {
            let t0 = (-half_extents - o) / d;
            let t1 = (half_extents - o) / d;
            let (near, far) = (t0.min(t1).max_element(), t0.max(t1).min_element());
            (near <= far && far >= 0.0).then_some(near.max(0.0))
        };
        for (yaw, pitch) in [(75.0f32, 10.0f32), (100.0, -30.0), (60.0, 40.0)] {
            let options = RenderOptions {
                width: 160,
                height: 120,
                yaw_degrees: yaw,
                pitch_degrees: pitch,
                ..RenderOptions::default()
            };
            let (_, starts) = tile_starts(gpu, &renderer, &options);
            // The baked cuboid is within a few thousandths of the exact one but at its edges.
            check_tile_starts(n, &options, &starts, &cuboid_hit, 0.01);
        }
    }

    /// Renders `options` accelerated, then plainly: the plain image's pixels off the background,
    /// and the pixels off it in one image only.
    fn hits_with_and_without_acceleration(
        gpu: &GpuContext,
        renderer: &mut Renderer,
        options: &RenderOptions,
    ) -> (usize, usize) {
        renderer.set_accelerated(true);
        let fast = renderer.render(gpu, options).unwrap();
        renderer.set_accelerated(false);
        let plain = renderer.render(gpu, options).unwrap();
        let background = options
            .background
            .to_array()
            .map(|c| (c * 255.0).round() as u8);
        let hit = |p: &[u8]| p != background;
        let plain_hits = plain.pixels.chunks(4).filter(|p| hit(p)).count();
        let sides = fast
            .pixels
            .chunks(4)
            .zip(plain.pixels.chunks(4))
            .filter(|(a, b)| hit(a) != hit(b))
            .count();
        (plain_hits, sides)
    }

    /// Over-relaxed steps do not jump over a sheet of zero thickness (the unsigned distance to
    /// a square in z = 0, met head-on, where the free spheres of the points before and after it
    /// only touch): the hits and misses of the plain trace, but for a few on its rim.
    #[test]
    fn over_relaxed_steps_keep_unsigned_sheets() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let model = Nglod::from_sdf(32, |p| {
            (p.truncate().abs() - 0.5)
                .max(glam::Vec2::ZERO)
                .extend(p.z)
                .length()
        })
        .unwrap();
        let sdf = NeuralSdf::from_model_file(
            model.to_model_file(Normalization::identity(), serde_json::Value::Null),
        )
        .unwrap();
        let mut renderer = Renderer::new(gpu, &sdf).unwrap();
        let options = RenderOptions {
            width: 64,
            height: 64,
            yaw_degrees: 0.0,
            pitch_degrees: 0.0,
            // Whole steps: a step below 1 would leave the spheres overlapping.
            step_scale: 1.0,
            ..RenderOptions::default()
        };
        let (on, sides) = hits_with_and_without_acceleration(gpu, &mut renderer, &options);
        assert!(on > 500, "{on} pixels on the sheet");
        assert!(sides * 50 <= on, "{sides} pixels hit on one side only");
    }

    /// Over-relaxed steps do not jump over thin walls: plates 0.01 thick facing the camera
    /// (where a step of 1.4 times the room crosses a plate from 0.07 away), on a slab, give the
    /// hits and misses of the plain trace.
    #[test]
    fn over_relaxed_steps_keep_thin_walls() {
        use crate::serve::scene::{Primitive, Scene, SceneNode, Transform};
        use glam::Quat;
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let plate = |x: f32, yaw: f32| {
            SceneNode::primitive(
                Primitive::Box {
                    half_extents: Vec3::new(0.5, 0.6, 0.005),
                },
                Transform::new(Vec3::new(x, 0.0, 0.0), Quat::from_rotation_y(yaw), 1.0),
            )
        };
        let scene = Scene::new(SceneNode::Union(vec![
            plate(-0.6, 35f32.to_radians()),
            plate(0.6, 0.0),
            SceneNode::primitive(
                Primitive::Box {
                    half_extents: Vec3::new(1.2, 0.05, 0.8),
                },
                Transform::from_translation(Vec3::new(0.0, -0.7, 0.0)),
            ),
        ]))
        .unwrap();
        let mut renderer = Renderer::for_scene(gpu, &scene).unwrap();
        let options = RenderOptions {
            width: 128,
            height: 96,
            pitch_degrees: 5.0,
            ..RenderOptions::default()
        };
        let (plain_hits, sides) = hits_with_and_without_acceleration(gpu, &mut renderer, &options);
        assert!(
            plain_hits > 1500,
            "{plain_hits} pixels on the plates and the slab"
        );
        assert!(sides <= 4, "{sides} pixels hit on one side only");
    }
}
