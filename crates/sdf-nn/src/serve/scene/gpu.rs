//! Batch queries of a whole [`Scene`] on the GPU: the scene compiled to WGSL once
//! ([`super::embed`]), every model's weights in as few buffers as the device allows, and one
//! submission per batch (per buffer-sized part of a batch) whatever the number of models.
//!
//! ```no_run
//! use glam::Vec3;
//! use sdf_nn::GpuContext;
//! use sdf_nn::serve::scene::{GpuScene, Ray, Scene, TraceOptions};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let scene = Scene::load("examples/scene/scene.toml")?;
//! let gpu = GpuContext::shared()?;
//! let on_gpu = GpuScene::new(gpu, &scene)?; // compiles the scene, uploads the weights
//! let d = on_gpu.distances(&[Vec3::ZERO, Vec3::X], 0.0)?;
//! let ray = Ray { origin: Vec3::new(0.0, 0.0, -5.0), direction: Vec3::Z, max_distance: 10.0 };
//! let hits = on_gpu.trace_rays(&[ray], &TraceOptions::default())?;
//! # let _ = (d, hits); Ok(()) }
//! ```
//!
//! Every query means what the CPU reference ([`super::cpu`]) computes, in f32 instead of f64
//! through the operators: distances agree to f32 rounding (the tests hold primitives to 1e-5),
//! rays step by the same bound (`{prefix}_trace`, [`Scene::trace_rays`]) and stop by the same rules,
//! projections take the same steps.
//!
//! # Kernels
//! [`QueryKernel::PerSubgroup`] (the default on GPUs with subgroup operations, for batches
//! below [`crate::gpu::SUBGROUP_KERNEL_MAX_ELEMENTS`]) takes each point or ray with a whole
//! subgroup, which shares every model's evaluation; [`QueryKernel::PerInvocation`] (the default
//! for larger batches and on CPU adapters, where it is the faster) takes one per invocation.
//! [`GpuContext::query_kernel`] chooses per batch (`HWSDF_QUERY_KERNEL` forces one),
//! [`GpuScene::set_kernel`] forces one; the answers agree to f32 rounding.
//!
//! # Serving
//! The plain calls ([`GpuScene::distances`], [`GpuScene::samples`], [`GpuScene::trace_rays`],
//! [`GpuScene::closest_points`]) upload, dispatch and read back. For results that stay on the
//! GPU or a submission that overlaps the caller's work, [`GpuScene::record`] records a query
//! into the caller's encoder on the caller's buffers ([`SceneQueryBuffers`]); the caller
//! submits it and reads (or keeps) the results. A `GpuScene` is `Send + Sync`: threads may query
//! one scene at once, each call with its own buffers.
//!
//! Pipelines are compiled on first use of each query kind (seconds on lavapipe, whose shader
//! compiler is slow; milliseconds on a GPU driver).

use std::borrow::Cow;
use std::sync::{Mutex, OnceLock};

use glam::Vec3;

use crate::gpu::QueryKernel;
use crate::gpu::{GpuContext, GpuError, binding_limit, entry, storage_layout_entry};
use crate::serve::scene::cpu::{
    ClosestPoint, ProjectOptions, Ray, RayHit, SceneQueryError, SceneSample, TraceOptions,
    check_level_and_tolerance, check_points, check_ray, check_trace_options,
};
use crate::serve::scene::embed::{SceneBindGroup, SceneGpuError};
use crate::serve::scene::tree::Scene;
use crate::serve::scratch::{self, SCRATCH_GROUP};
use crate::serve::wgsl::Lanes;

/// The group of the scene's weights in the query kernels.
const SCENE_GROUP: u32 = 1;
/// Storage buffers the query kernels bind besides the scene's.
const QUERY_BUFFERS: u32 = 2;
/// Invocations per workgroup (`QUERY_WG`).
const WG: u32 = 64;

/// What a query computes: its kernel and the size of one element's input and output.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SceneQueryKind {
    /// `d − c` per point (1 float).
    Distance,
    /// `d − c`, its gradient and the deciding leaf per point (5 floats; the leaf bit for bit).
    Sample,
    /// A sphere-traced ray per element (input: two `vec4`s, origin and maximum distance, then
    /// direction; output: 10 floats, hit (0 or 1), t, point, normal, leaf and steps).
    Trace,
    /// A projection per point (7 floats: point, residual, iterations, converged (0 or 1),
    /// leaf).
    Project,
}

impl SceneQueryKind {
    const ALL: [SceneQueryKind; 4] = [
        SceneQueryKind::Distance,
        SceneQueryKind::Sample,
        SceneQueryKind::Trace,
        SceneQueryKind::Project,
    ];

    /// A label for errors and debugging.
    fn label(self) -> &'static str {
        match self {
            SceneQueryKind::Distance => "scene distance query",
            SceneQueryKind::Sample => "scene sample query",
            SceneQueryKind::Trace => "scene ray query",
            SceneQueryKind::Project => "scene projection query",
        }
    }

    /// `vec4<f32>` inputs per element.
    pub fn inputs_per_element(self) -> u32 {
        match self {
            SceneQueryKind::Trace => 2,
            _ => 1,
        }
    }

    /// `f32` outputs per element.
    pub fn outputs_per_element(self) -> u32 {
        match self {
            SceneQueryKind::Distance => 1,
            SceneQueryKind::Sample => 5,
            SceneQueryKind::Trace => 10,
            SceneQueryKind::Project => 7,
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// The kernels' uniform (`SceneQuery` in `shaders/scene_query.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct SceneQueryUniform {
    count: u32,
    max_steps: u32,
    max_iterations: u32,
    first: u32,
    level: f32,
    tolerance: f32,
    over_relaxation: f32,
    _pad: f32,
}

/// The parameters of one recorded query.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneQueryParams {
    /// The level `c`.
    pub level: f32,
    /// Hit tolerance (rays) or convergence tolerance (projections); unused otherwise.
    pub tolerance: f32,
    /// Sphere-tracing steps per ray at most.
    pub max_steps: u32,
    /// Projection steps per point at most.
    pub max_iterations: u32,
    /// Rays' over-relaxation factor ([`TraceOptions::over_relaxation`]; 1 traces plainly).
    pub over_relaxation: f32,
}

impl SceneQueryParams {
    /// Distances or samples at level `c`.
    pub fn at_level(level: f32) -> Self {
        SceneQueryParams {
            level,
            tolerance: 1.0,
            max_steps: 0,
            max_iterations: 0,
            over_relaxation: 1.0,
        }
    }
}

impl From<&TraceOptions> for SceneQueryParams {
    fn from(o: &TraceOptions) -> Self {
        SceneQueryParams {
            level: o.level,
            tolerance: o.tolerance,
            max_steps: o.max_steps,
            max_iterations: 0,
            over_relaxation: o.over_relaxation,
        }
    }
}

impl From<&ProjectOptions> for SceneQueryParams {
    fn from(o: &ProjectOptions) -> Self {
        SceneQueryParams {
            level: o.level,
            tolerance: o.tolerance,
            max_steps: 0,
            max_iterations: o.max_iterations,
            over_relaxation: 1.0,
        }
    }
}

/// Caller-owned buffers for up to `capacity` elements of one query kind: the inputs (storage,
/// written by the caller or by another kernel) and the outputs (storage, copyable), which may
/// stay on the GPU.
#[derive(Debug)]
pub struct SceneQueryBuffers {
    /// The query kind they are sized for.
    pub kind: SceneQueryKind,
    /// Elements they hold.
    pub capacity: u32,
    /// `vec4<f32>` inputs (see [`SceneQueryKind`]).
    pub inputs: wgpu::Buffer,
    /// `f32` outputs (see [`SceneQueryKind`]).
    pub outputs: wgpu::Buffer,
}

/// A scene compiled for one device: its query kernels and its weights.
#[derive(Debug)]
pub struct GpuScene<'g> {
    gpu: &'g GpuContext,
    /// Per kernel (`QueryKernel as usize`) where the device runs it.
    modules: Vec<wgpu::ShaderModule>,
    layout: wgpu::PipelineLayout,
    query_layout: wgpu::BindGroupLayout,
    weights: SceneBindGroup,
    /// Per kernel, per kind (`kernel as usize * 4 + kind`).
    pipelines: [OnceLock<wgpu::ComputePipeline>; 8],
    /// The caller's choice ([`GpuScene::set_kernel`]); `None`: by each batch's size.
    kernel: Option<QueryKernel>,
    /// Why the driver refused the subgroup kernels, where it did.
    refusal: Option<String>,
    /// The widest subgroup the adapter may run, where the module has the subgroup kernels.
    subgroup_width: Option<u32>,
    lipschitz: f32,
    leaves: usize,
    /// Most elements of one part of a batch, per kind (buffer and dispatch limits, and the
    /// scratch's slots).
    max_elements: [u32; 4],
    /// The scratch of SIRENs in the scratch form, bound at [`SCRATCH_GROUP`].
    scratch: Option<wgpu::BindGroup>,
    /// See [`GpuScene::set_max_part`].
    max_part: u32,
    /// Buffers and bind groups of earlier plain calls, per kind, for the next ones (a call
    /// takes one set, so threads never share a set).
    pools: [Mutex<Vec<Pooled>>; 4],
}

/// One plain call's GPU side, kept for reuse: its buffers, uniform, bind group and readback.
#[derive(Debug)]
struct Pooled {
    buffers: SceneQueryBuffers,
    uniform: wgpu::Buffer,
    group: wgpu::BindGroup,
    readback: wgpu::Buffer,
}

/// Sets kept per kind.
const POOL: usize = 8;

/// Batches of at least this many points are visited in Morton order on a GPU (see
/// `GpuScene::run_points`). On an H200, 3000 scattered points through a scene of 8 models took
/// 2.1 ms unsorted: each 32-wide warp evaluated the models near any of its points.
pub const MORTON_ON_GPU: usize = 1024;

impl<'g> GpuScene<'g> {
    /// Compiles `scene` for `gpu`'s device and uploads its weights. Measures the models'
    /// Lipschitz estimates (for rays) if the scene has not yet. The queries run the device's
    /// kernel for each batch's size ([`GpuContext::query_kernel`]; [`GpuScene::set_kernel`]
    /// forces one).
    pub fn new(gpu: &'g GpuContext, scene: &Scene) -> Result<GpuScene<'g>, SceneGpuError> {
        let device = gpu.device();
        let limits = gpu.limits();
        let subgroup_width = gpu.subgroups_within(WG);
        let forms: &[Lanes] = match subgroup_width {
            Some(_) => &[Lanes::One, Lanes::Subgroup],
            None => &[Lanes::One],
        };
        let stride = scratch::stride(gpu, scene.models().iter().map(|m| m.network()));
        let (snippets, weights) = scene.compile(
            device,
            SCENE_GROUP,
            "scene",
            QUERY_BUFFERS + u32::from(stride.is_some()),
            forms,
            scratch::activations(stride),
        )?;
        let prelude = scratch::prelude(stride);
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        // One module per kernel: the subgroup form's models sum over the subgroup, which the
        // per-invocation kernels (a point per lane) must not call.
        let query = crate::shaders::SCENE_QUERY.source;
        let mut modules = vec![gpu.generated_module(
            "scene_query.wgsl",
            Cow::Owned(format!("{prelude}{}\n{query}", snippets[0])),
        )];
        // (Its per-invocation entry point, which SCENE_QUERY brings along, is never used.)
        let mut subgroup_width = subgroup_width;
        let mut refusal = None;
        if let Some(snippet) = snippets.get(1) {
            let source = format!(
                "{prelude}{snippet}\n{query}\n{}",
                crate::shaders::SCENE_QUERY_SUBGROUP.source
            );
            // A driver that refuses the subgroup kernels leaves the scene its other kernel.
            let own = device.push_error_scope(wgpu::ErrorFilter::Validation);
            let module = gpu.generated_module("scene_query_subgroup.wgsl", Cow::Owned(source));
            match pollster::block_on(own.pop()) {
                None => modules.push(module),
                Some(err) => {
                    refusal = Some(err.to_string());
                    subgroup_width = None;
                }
            }
        }
        let query_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene query"),
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
                storage_layout_entry(1, true),
                storage_layout_entry(2, false),
            ],
        });
        // SIRENs in the scratch form: a slot per invocation of a dispatch, for the parts' sizes
        // to fit (a part is capped below).
        let scratch_layout = stride.map(|_| scratch::layout(device));
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene query"),
            bind_group_layouts: &[
                Some(&query_layout),
                Some(&weights.layout),
                scratch_layout.as_ref(),
            ],
            immediate_size: 0,
        });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Wgpu {
                context: "compiling the scene's WGSL".into(),
                message: err.to_string(),
            }
            .into());
        }
        let binding = binding_limit(&limits);
        let max_dispatch = u64::from(limits.max_compute_workgroups_per_dimension);
        let scratch = match (stride, &scratch_layout) {
            (Some(stride), Some(layout)) => {
                let slots = scratch::query_slots(gpu, stride);
                Some((slots, scratch::bind_group(gpu, layout, stride, slots)?))
            }
            _ => None,
        };
        let max_elements = SceneQueryKind::ALL.map(|kind| {
            let bytes_per_element = (16 * u64::from(kind.inputs_per_element()))
                .max(4 * u64::from(kind.outputs_per_element()));
            // The subgroup kernels cover the fewest elements per workgroup.
            let per_group = WG / subgroup_width.unwrap_or(1);
            // Each invocation that may evaluate holds a scratch slot, indexed by its place in
            // the dispatch: a subgroup kernel's whole workgroups of 64 do.
            let slots = scratch.as_ref().map_or(u64::MAX, |(slots, _)| {
                u64::from(*slots) / u64::from(WG) * u64::from(per_group)
            });
            (binding / bytes_per_element)
                .min(max_dispatch * max_dispatch * u64::from(per_group))
                .min(slots.max(1))
                .min(u64::from(u32::MAX / 16)) as u32
        });
        Ok(GpuScene {
            gpu,
            modules,
            layout,
            query_layout,
            weights,
            pipelines: Default::default(),
            kernel: None,
            subgroup_width,
            refusal,
            lipschitz: scene.lipschitz(),
            leaves: scene.leaves().len(),
            max_elements,
            scratch: scratch.map(|(_, group)| group),
            max_part: u32::MAX,
            pools: Default::default(),
        })
    }

    /// The scene's Lipschitz constant ([`Scene::lipschitz`]; the tracer's steps are at least
    /// `|d − c|` divided by it).
    pub fn lipschitz(&self) -> f32 {
        self.lipschitz
    }

    /// The scene's weights on the device (for binding them in the caller's own shader, whose
    /// snippet [`Scene::wgsl_with_prefix`] gives).
    pub fn weights(&self) -> &SceneBindGroup {
        &self.weights
    }

    /// Most elements of `kind` one set of buffers may hold on this device; larger plain calls
    /// are split into parts of this size.
    pub fn max_elements(&self, kind: SceneQueryKind) -> u32 {
        self.max_elements[kind.index()].min(self.max_part)
    }

    /// Splits the plain calls' batches into parts of at most `elements` (at least 1), one
    /// submission each: for a driver whose watchdog ends long submissions (rays of a large
    /// scene), or to bound the memory of one part. The answers do not change.
    pub fn set_max_part(&mut self, elements: u32) {
        self.max_part = elements.max(1);
    }

    /// The kernel a query of `elements` points or rays runs: the one
    /// [`GpuScene::set_kernel`] chose, else the device's for that size
    /// ([`GpuContext::query_kernel`]).
    pub fn kernel(&self, elements: u32) -> QueryKernel {
        match (self.kernel, self.subgroup_width) {
            (Some(kernel), _) => kernel,
            (None, Some(_)) => self.gpu.query_kernel(u64::from(elements)),
            (None, None) => QueryKernel::PerInvocation,
        }
    }

    /// Runs the next queries on `kernel` whatever their size (`None`: the device's choice
    /// per batch size). The answers agree to f32 rounding. [`QueryKernel::PerSubgroup`] needs a
    /// device with subgroup operations whose subgroups are at most 64 wide
    /// ([`SceneGpuError::NoSubgroups`] otherwise).
    pub fn set_kernel(&mut self, kernel: Option<QueryKernel>) -> Result<(), SceneGpuError> {
        if kernel == Some(QueryKernel::PerSubgroup) && self.subgroup_width.is_none() {
            let adapter = match &self.refusal {
                Some(why) => format!("{} (its driver refused them: {why})", self.gpu.describe()),
                None => self.gpu.describe(),
            };
            return Err(SceneGpuError::NoSubgroups { adapter });
        }
        self.kernel = kernel;
        Ok(())
    }

    /// The pipeline of `kind` on `kernel`, compiled on first use.
    fn pipeline(
        &self,
        kind: SceneQueryKind,
        kernel: QueryKernel,
    ) -> Result<&wgpu::ComputePipeline, GpuError> {
        let cell = &self.pipelines[kernel as usize * 4 + kind.index()];
        if let Some(p) = cell.get() {
            return Ok(p);
        }
        let device = self.gpu.device();
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut constants = vec![("KIND", kind.index() as f64)];
        if let (QueryKernel::PerSubgroup, Some(width)) = (kernel, self.subgroup_width) {
            constants.push(("PER_GROUP", f64::from(WG / width)));
        }
        let entry_point = match kernel {
            QueryKernel::PerInvocation => "query_per_invocation",
            QueryKernel::PerSubgroup => "query_per_subgroup",
        };
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(kind.label()),
            layout: Some(&self.layout),
            module: &self.modules[kernel as usize],
            entry_point: Some(entry_point),
            // The query kind (`KIND` in scene_query.wgsl) picks one branch at compile time.
            compilation_options: wgpu::PipelineCompilationOptions {
                constants: &constants,
                ..Default::default()
            },
            cache: None,
        });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Wgpu {
                context: format!("compiling the {} ({entry_point})", kind.label()),
                message: err.to_string(),
            });
        }
        // Two threads may both compile; the first stored wins and both are valid.
        Ok(cell.get_or_init(|| pipeline))
    }

    /// Buffers for up to `capacity` elements of `kind` (at most
    /// [`GpuScene::max_elements`]).
    pub fn create_buffers(
        &self,
        kind: SceneQueryKind,
        capacity: u32,
    ) -> Result<SceneQueryBuffers, GpuError> {
        let capacity = capacity.max(1);
        let in_bytes = 16 * u64::from(kind.inputs_per_element()) * u64::from(capacity);
        let out_bytes = 4 * u64::from(kind.outputs_per_element()) * u64::from(capacity);
        self.gpu
            .check_storage_size("scene query inputs", in_bytes)?;
        self.gpu
            .check_storage_size("scene query outputs", out_bytes)?;
        let device = self.gpu.device();
        let buffer = |label, size, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        use wgpu::BufferUsages as U;
        Ok(SceneQueryBuffers {
            kind,
            capacity,
            inputs: buffer("scene query inputs", in_bytes, U::STORAGE | U::COPY_DST),
            outputs: buffer("scene query outputs", out_bytes, U::STORAGE | U::COPY_SRC),
        })
    }

    /// Records a query of the first `count` elements of `buffers` into `encoder`, as one
    /// dispatch per [`GpuScene::max_elements`] of them. The inputs must be written before the
    /// encoder's submission runs; the outputs are ready when it has finished. `params` are not
    /// checked here (the plain calls check them).
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        buffers: &SceneQueryBuffers,
        count: u32,
        params: &SceneQueryParams,
    ) -> Result<(), GpuError> {
        let count = count.min(buffers.capacity);
        // In dispatches of at most `max_elements` (a SIREN's scratch holds no more slots).
        let part = self.max_elements(buffers.kind).max(1);
        let mut first = 0;
        while first < count {
            let n = part.min(count - first);
            let uniform = SceneQueryUniform {
                first,
                ..self.uniform(n, params)
            };
            let uniform = self.gpu.uniform("scene query", &uniform);
            let group = self.query_group(&uniform, buffers);
            self.encode(encoder, buffers.kind, &group, n)?;
            first += n;
        }
        Ok(())
    }

    fn uniform(&self, count: u32, params: &SceneQueryParams) -> SceneQueryUniform {
        SceneQueryUniform {
            count,
            max_steps: params.max_steps,
            max_iterations: params.max_iterations,
            first: 0,
            level: params.level,
            tolerance: params.tolerance,
            over_relaxation: params.over_relaxation,
            _pad: 0.0,
        }
    }

    fn query_group(&self, uniform: &wgpu::Buffer, buffers: &SceneQueryBuffers) -> wgpu::BindGroup {
        self.gpu
            .device()
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("scene query"),
                layout: &self.query_layout,
                entries: &[
                    entry(0, uniform),
                    entry(1, &buffers.inputs),
                    entry(2, &buffers.outputs),
                ],
            })
    }

    /// The dispatch of `kind` over `count` elements bound by `group`.
    fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        kind: SceneQueryKind,
        group: &wgpu::BindGroup,
        count: u32,
    ) -> Result<(), GpuError> {
        let kernel = self.kernel(count);
        let pipeline = self.pipeline(kind, kernel)?;
        let per_group = match (kernel, self.subgroup_width) {
            (QueryKernel::PerSubgroup, Some(width)) => WG / width,
            _ => WG,
        };
        let (x, y) = self.gpu.dispatch_size(count.div_ceil(per_group));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(kind.label()),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        pass.set_bind_group(SCENE_GROUP, &self.weights.bind_group, &[]);
        if let Some(group) = &self.scratch {
            pass.set_bind_group(SCRATCH_GROUP, group, &[]);
        }
        pass.dispatch_workgroups(x, y, 1);
        Ok(())
    }

    /// A pooled set for `count` elements of `kind`: one kept from an earlier call, or a new
    /// one (sized to a power of two, so that similar batches reuse it).
    fn take(&self, kind: SceneQueryKind, count: u32) -> Result<Pooled, GpuError> {
        let mut pool = self.pools[kind.index()]
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(i) = pool.iter().position(|p| p.buffers.capacity >= count) {
            return Ok(pool.swap_remove(i));
        }
        drop(pool);
        let capacity = count
            .checked_next_power_of_two()
            .unwrap_or(count)
            .clamp(count, self.max_elements(kind).max(count));
        let buffers = self.create_buffers(kind, capacity)?;
        let uniform = self.gpu.uniform(
            "scene query",
            &self.uniform(0, &SceneQueryParams::at_level(0.0)),
        );
        let group = self.query_group(&uniform, &buffers);
        let readback = self.gpu.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("scene query readback"),
            size: buffers.outputs.size(),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Pooled {
            buffers,
            uniform,
            group,
            readback,
        })
    }

    fn give(&self, kind: SceneQueryKind, pooled: Pooled) {
        let mut pool = self.pools[kind.index()]
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if pool.len() < POOL {
            pool.push(pooled);
        }
    }

    /// [`GpuScene::run`] on points visited in Morton order where that pays: neighbouring
    /// invocations then skip (or evaluate) the same models, instead of each SIMD group paying
    /// for the models near any of its points. From 256 points on a CPU adapter (lavapipe's
    /// 8-wide groups), from [`MORTON_ON_GPU`] on a GPU (the sort costs tens of µs of host time).
    fn run_points(
        &self,
        kind: SceneQueryKind,
        points: &[Vec3],
        params: &SceneQueryParams,
    ) -> Result<Vec<f32>, GpuError> {
        // A subgroup per point never diverges over models: nothing to gain from the order.
        let sort = self.kernel(points.len() as u32) == QueryKernel::PerInvocation
            && (points.len() >= MORTON_ON_GPU || (self.gpu.is_cpu() && points.len() >= 256));
        if !sort {
            let inputs: Vec<[f32; 4]> = points.iter().map(|p| p.extend(0.0).to_array()).collect();
            return self.run(kind, &inputs, params);
        }
        let order = sdf_geom::morton_order(points);
        let inputs: Vec<[f32; 4]> = order
            .iter()
            .map(|&i| points[i as usize].extend(0.0).to_array())
            .collect();
        let sorted = self.run(kind, &inputs, params)?;
        let per = kind.outputs_per_element() as usize;
        let mut out = vec![0.0; sorted.len()];
        for (k, &i) in order.iter().enumerate() {
            out[i as usize * per..(i as usize + 1) * per]
                .copy_from_slice(&sorted[k * per..(k + 1) * per]);
        }
        Ok(out)
    }

    /// Runs `kind` on `inputs` (`inputs_per_element` `vec4`s per element), in parts that fit
    /// the device, one submission each; returns the outputs of every element in order.
    fn run(
        &self,
        kind: SceneQueryKind,
        inputs: &[[f32; 4]],
        params: &SceneQueryParams,
    ) -> Result<Vec<f32>, GpuError> {
        let per_in = kind.inputs_per_element() as usize;
        let per_out = kind.outputs_per_element() as usize;
        let elements = inputs.len() / per_in;
        let mut out = Vec::with_capacity(elements * per_out);
        let part = self.max_elements(kind).max(1) as usize;
        for chunk in inputs.chunks(part * per_in) {
            let count = (chunk.len() / per_in) as u32;
            let pooled = self.take(kind, count)?;
            let (device, queue) = (self.gpu.device(), self.gpu.queue());
            let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
            queue.write_buffer(
                &pooled.uniform,
                0,
                bytemuck::bytes_of(&self.uniform(count, params)),
            );
            queue.write_buffer(&pooled.buffers.inputs, 0, bytemuck::cast_slice(chunk));
            let mut encoder = device.create_command_encoder(&Default::default());
            self.encode(&mut encoder, kind, &pooled.group, count)?;
            let bytes = u64::from(count) * per_out as u64 * 4;
            encoder.copy_buffer_to_buffer(&pooled.buffers.outputs, 0, &pooled.readback, 0, bytes);
            queue.submit([encoder.finish()]);
            if let Some(err) = pollster::block_on(scope.pop()) {
                return Err(GpuError::Wgpu {
                    context: format!("dispatching the {}", kind.label()),
                    message: err.to_string(),
                });
            }
            let values: Vec<f32> = self.gpu.map_read(&pooled.readback, kind.label())?;
            out.extend_from_slice(&values[..count as usize * per_out]);
            self.give(kind, pooled);
        }
        Ok(out)
    }

    /// `d − c` at each point (see [`Scene::distances`]); a NaN or infinite point is an error
    /// (where the CPU reference answers NaN).
    pub fn distances(&self, points: &[Vec3], level: f32) -> Result<Vec<f32>, SceneGpuError> {
        if !level.is_finite() {
            return Err(SceneQueryError::Level(level).into());
        }
        check_points(points)?;
        Ok(self.run_points(
            SceneQueryKind::Distance,
            points,
            &SceneQueryParams::at_level(level),
        )?)
    }

    /// `d − c`, its gradient and the deciding leaf at each point (see
    /// [`Scene::distances_and_gradients`]); a NaN or infinite point is an error.
    pub fn samples(&self, points: &[Vec3], level: f32) -> Result<Vec<SceneSample>, SceneGpuError> {
        if !level.is_finite() {
            return Err(SceneQueryError::Level(level).into());
        }
        check_points(points)?;
        let out = self.run_points(
            SceneQueryKind::Sample,
            points,
            &SceneQueryParams::at_level(level),
        )?;
        Ok(out
            .chunks_exact(5)
            .map(|v| SceneSample {
                distance: v[0],
                gradient: Vec3::new(v[1], v[2], v[3]),
                leaf: v[4].to_bits() as usize,
            })
            .collect())
    }

    /// Sphere-traces each ray (see [`Scene::trace_rays`]: the same steps, the same stops).
    pub fn trace_rays(
        &self,
        rays: &[Ray],
        options: &TraceOptions,
    ) -> Result<Vec<Option<RayHit>>, SceneGpuError> {
        check_trace_options(options)?;
        for (index, ray) in rays.iter().enumerate() {
            check_ray(index, ray)?;
        }
        let inputs: Vec<[f32; 4]> = rays
            .iter()
            .flat_map(|r| {
                // Normalised in f64, as the CPU does, so that huge directions stay finite.
                let d = r.direction.as_dvec3().normalize().as_vec3();
                [
                    r.origin.extend(r.max_distance).to_array(),
                    d.extend(0.0).to_array(),
                ]
            })
            .collect();
        let out = self.run(SceneQueryKind::Trace, &inputs, &options.into())?;
        Ok(out
            .chunks_exact(10)
            .map(|v| {
                (v[0] == 1.0).then(|| RayHit {
                    t: v[1],
                    point: Vec3::new(v[2], v[3], v[4]),
                    normal: Vec3::new(v[5], v[6], v[7]),
                    leaf: v[8].to_bits() as usize,
                    steps: v[9].to_bits(),
                })
            })
            .collect())
    }

    /// Projects each point onto the level set (see [`Scene::closest_points`]).
    pub fn closest_points(
        &self,
        points: &[Vec3],
        options: &ProjectOptions,
    ) -> Result<Vec<ClosestPoint>, SceneGpuError> {
        check_level_and_tolerance(options.level, options.tolerance)?;
        check_points(points)?;
        let out = self.run_points(SceneQueryKind::Project, points, &options.into())?;
        Ok(out
            .chunks_exact(7)
            .map(|v| ClosestPoint {
                point: Vec3::new(v[0], v[1], v[2]),
                residual: v[3],
                iterations: v[4].to_bits(),
                converged: v[5] == 1.0,
                leaf: v[6].to_bits() as usize,
            })
            .collect())
    }

    /// Leaves of the scene.
    pub fn leaf_count(&self) -> usize {
        self.leaves
    }
}

#[cfg(test)]
mod tests {
    /// The kernels' uniform has the layout `scene_query.wgsl` reads.
    #[test]
    fn query_uniform_mirrors_the_shader() {
        crate::shaders::assert_mirrors!(
            super::SceneQueryUniform,
            crate::shaders::SCENE_QUERY,
            "SceneQuery",
            [
                count,
                max_steps,
                max_iterations,
                first,
                level,
                tolerance,
                over_relaxation
            ]
        );
    }
}
