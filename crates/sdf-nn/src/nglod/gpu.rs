//! Host side of the NGLOD kernels: `shaders/nglod_forward.wgsl` (inference),
//! `shaders/nglod_train.wgsl` (forward + backward per row, with the grid scatter of
//! `shaders/nglod_scatter_{atomic,cas}.wgsl`; one row per invocation, or per subgroup with
//! `shaders/nglod_train_subgroup.wgsl`) and
//! `shaders/nglod_reduce.wgsl` (MLP gradients and loss).

use std::sync::Mutex;

use glam::Vec3;

use super::{
    Band, LevelStorage, MAX_LEVELS, MAX_MLP_FLOATS, Nglod, NglodConfig, NglodError, Objective,
    ParamLayout,
};
use crate::gpu::{
    GpuContext, GpuError, GpuTimer, GridLaunch, Launch, PassProfiler, QueryKernel, UniformStager,
    entry, record_launches,
};
use crate::shaders;

/// Invocations per workgroup of every NGLOD kernel (the `WG` constant of the shaders).
const WG: u32 = 64;
/// Rows summed by one `mlp_partial` workgroup row: small enough that a 512-point batch still
/// spreads over several workgroups.
const CHUNK: u32 = 64;
/// Points per inference dispatch: bounds the staging buffers (12 MiB of points).
const EVAL_CHUNK: usize = 1 << 20;

/// How the backward kernel adds into the grid gradients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ScatterMode {
    /// Native float atomics when the device has `SHADER_FLOAT32_ATOMIC`, else compare-exchange.
    #[default]
    Auto,
    /// `atomicAdd` on `atomic<f32>`; an error on devices without float atomics.
    FloatAtomics,
    /// A compare-exchange loop on `atomic<u32>`: works on every adapter.
    CompareExchange,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct EvalUniforms {
    n_points: u32,
    lod: u32,
    mlp_offset: u32,
    _pad: u32,
    levels: [[u32; 4]; MAX_LEVELS],
    /// The serving entry points' map from mesh coordinates: centre (xyz) and scale (w).
    query: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct TrainUniforms {
    n_rows: u32,
    first: u32,
    n_prefix: u32,
    lod_base: u32,
    mlp_offset: u32,
    chunk: u32,
    n_chunks: u32,
    _pad: u32,
    levels: [[u32; 4]; MAX_LEVELS],
}

/// Bytes of a training step's uniforms, as [`crate::gpu::UniformStager`] stages them.
pub(crate) const TRAIN_UNIFORM_BYTES: u64 = std::mem::size_of::<TrainUniforms>() as u64;

/// Buffers of the inference path, grown on demand and reused between calls.
struct EvalScratch {
    capacity: usize,
    points: wgpu::Buffer,
    out: wgpu::Buffer,
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
}

/// The inference kernel bound to caller buffers (see [`NglodGpu::eval_binding`]).
pub(crate) struct NglodEvalBinding {
    pipeline: wgpu::ComputePipeline,
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    /// Centre (xyz) and scale (w) of the map from mesh coordinates.
    transform: [f32; 4],
    /// Points per workgroup: `WG`, or `WG / width` for the one-point-per-subgroup kernel.
    per_group: u32,
    /// The point count and level the uniforms hold.
    written: Option<(u32, usize)>,
}

/// An NGLOD model on the GPU: the flat parameter buffer, its gradient buffer (the layout of
/// [`Nglod::layout`], shared with [`crate::Adam`]), the sparse levels' vertex tables and the
/// pipelines.
pub struct NglodGpu {
    config: NglodConfig,
    bands: Vec<Band>,
    layout: ParamLayout,
    params: wgpu::Buffer,
    /// Every sparse level's vertex table, one after the other (`nglod_grid.wgsl`).
    table: wgpu::Buffer,
    grads: wgpu::Buffer,
    /// Uniform copy of the MLP block of `params`, refreshed before every dispatch that reads it
    /// (unless `frozen`).
    mlp: wgpu::Buffer,
    /// The parameters change only through [`NglodGpu::upload`], which also rewrites `mlp`: the
    /// inference paths then skip the refresh, one copy and one barrier fewer per query (a served
    /// model, see [`NglodGpu::new_frozen`]).
    frozen: bool,
    float_atomics: bool,
    /// F and H (every kernel), then FL and ZS (the grid lookups): nglod_grid.wgsl.
    constants: [(&'static str, f64); 4],
    eval: Mutex<Option<EvalScratch>>,
    eval_chunk: usize,
    /// The training rows' kernel if forced ([`NglodGpu::set_train_kernel`]).
    train_kernel: Option<QueryKernel>,
}

impl std::fmt::Debug for NglodGpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NglodGpu")
            .field("config", &self.config)
            .field("float_atomics", &self.float_atomics)
            .finish_non_exhaustive()
    }
}

/// The kernels' per-level uniform (nglod_grid.wgsl): resolution, offset in the parameters, and
/// the storage: `(0, 0)` dense, `(offset of the level's table in the concatenated vertex tables,
/// 1)` sparse, `(table size − 1, 2)` hashed.
fn level_table(config: &NglodConfig, layout: &ParamLayout) -> [[u32; 4]; MAX_LEVELS] {
    let mut t = [[0u32; 4]; MAX_LEVELS];
    for (l, &r) in config.resolutions.iter().enumerate() {
        // validate() bounds the parameter count and the tables well below u32::MAX.
        let (z, kind) = match config.storage(l) {
            LevelStorage::Dense => (0, 0),
            LevelStorage::Sparse => (config.table_offset(l).unwrap_or(0) as u32, 1),
            LevelStorage::Hashed(entries) => (entries - 1, 2),
        };
        t[l] = [r, layout.grid_offsets[l] as u32, z, kind];
    }
    t
}

impl NglodGpu {
    /// Uploads `model` to the GPU. `scatter` picks the grid-gradient kernel.
    pub fn new(gpu: &GpuContext, model: &Nglod, scatter: ScatterMode) -> Result<Self, NglodError> {
        let config = model.config().clone();
        config.validate()?;
        let float_atomics = match scatter {
            ScatterMode::Auto => gpu.has_float_atomics(),
            ScatterMode::FloatAtomics => {
                if !gpu.has_float_atomics() {
                    return Err(GpuError::MissingFeatures {
                        shader: shaders::NGLOD_TRAIN_ATOMIC.name,
                        missing: wgpu::Features::SHADER_FLOAT32_ATOMIC,
                        adapter: gpu.adapter_info().name.clone(),
                    }
                    .into());
                }
                true
            }
            ScatterMode::CompareExchange => false,
        };
        let layout = model.layout().clone();
        let params = gpu.storage_from_slice("nglod params", model.params())?;
        let mut tables = model.sparse_tables();
        // A binding cannot be empty.
        tables.resize(tables.len().max(1), super::NO_SLOT);
        let table = gpu.storage_from_slice("nglod vertex tables", &tables)?;
        let grads = gpu.storage_zeroed("nglod grads", layout.len as u64 * 4)?;
        let mlp = gpu.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("nglod mlp uniform"),
            size: u64::from(MAX_MLP_FLOATS) * 4,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let constants = [
            ("F", f64::from(config.input_dim())),
            ("H", f64::from(config.hidden)),
            ("FL", f64::from(config.feature_dim)),
            ("ZS", f64::from(config.input_offset(1) as u32)),
        ];
        Ok(NglodGpu {
            config,
            bands: model.bands().to_vec(),
            layout,
            params,
            table,
            grads,
            mlp,
            frozen: false,
            float_atomics,
            constants,
            eval: Mutex::new(None),
            eval_chunk: EVAL_CHUNK,
            train_kernel: None,
        })
    }

    /// [`NglodGpu::new`] for a model whose parameters nobody writes on the GPU (no trainer, no
    /// writes through [`NglodGpu::params_buffer`]): [`crate::NeuralSdf`]'s network. Its MLP
    /// uniform is written here and by [`NglodGpu::upload`] only, not before every dispatch.
    pub(crate) fn new_frozen(gpu: &GpuContext, model: &Nglod) -> Result<Self, NglodError> {
        let mut net = Self::new(gpu, model, ScatterMode::Auto)?;
        net.frozen = true;
        net.write_mlp(gpu, model)?;
        Ok(net)
    }

    /// Writes `model`'s MLP block into the uniform buffer through the queue.
    fn write_mlp(&self, gpu: &GpuContext, model: &Nglod) -> Result<(), NglodError> {
        gpu.write(&self.mlp, &model.params()[self.layout.w0..])?;
        Ok(())
    }

    /// The configuration.
    pub fn config(&self) -> &NglodConfig {
        &self.config
    }

    /// Whether the backward kernel uses native float atomics (else compare-exchange).
    pub fn uses_float_atomics(&self) -> bool {
        self.float_atomics
    }

    /// Forces the kernel of the training steps recorded from now on (`None`: by adapter and
    /// batch, [`GpuContext::train_kernel`]). [`QueryKernel::PerSubgroup`] needs subgroups that
    /// fit a workgroup of 64 ([`GpuContext::subgroups_within`]); elsewhere it is an error.
    pub fn set_train_kernel(
        &mut self,
        gpu: &GpuContext,
        kernel: Option<QueryKernel>,
    ) -> Result<(), NglodError> {
        if kernel == Some(QueryKernel::PerSubgroup) && gpu.subgroups_within(WG).is_none() {
            return Err(GpuError::MissingFeatures {
                shader: shaders::NGLOD_TRAIN_SUBGROUP_CAS.name,
                missing: wgpu::Features::SUBGROUP,
                adapter: gpu.adapter_info().name.clone(),
            }
            .into());
        }
        self.train_kernel = kernel;
        Ok(())
    }

    /// The kernel a training step of `rows` rows (points × level prefixes) runs: the forced
    /// one ([`NglodGpu::set_train_kernel`]), else [`GpuContext::train_kernel`]'s choice.
    pub fn train_kernel(&self, gpu: &GpuContext, rows: u64) -> QueryKernel {
        self.train_kernel.unwrap_or_else(|| gpu.train_kernel(rows))
    }

    /// The flat parameter buffer.
    pub fn params_buffer(&self) -> &wgpu::Buffer {
        &self.params
    }

    /// The flat gradient buffer (same layout as the parameters).
    pub fn grads_buffer(&self) -> &wgpu::Buffer {
        &self.grads
    }

    /// Caps the points per inference dispatch (default 2^20; at least 1). Larger inputs are split.
    pub fn set_max_points_per_dispatch(&mut self, n: usize) {
        self.eval_chunk = n.clamp(1, EVAL_CHUNK);
    }

    /// Number of parameters.
    pub fn param_count(&self) -> usize {
        self.layout.len
    }

    /// Replaces the parameters on the GPU with `model`'s (same configuration).
    pub fn upload(&self, gpu: &GpuContext, model: &Nglod) -> Result<(), NglodError> {
        if model.config() != &self.config || model.bands() != self.bands {
            return Err(NglodError::InvalidConfig(
                "upload: the model's configuration or sparse levels differ from the GPU model's"
                    .into(),
            ));
        }
        gpu.write(&self.params, model.params())?;
        if self.frozen {
            self.write_mlp(gpu, model)?;
        }
        Ok(())
    }

    /// Reads the parameters back into a host model.
    pub fn to_model(&self, gpu: &GpuContext) -> Result<Nglod, NglodError> {
        let params: Vec<f32> = gpu.read_back_range(&self.params, 0, self.layout.len as u64)?;
        Nglod::from_parts(self.config.clone(), self.bands.clone(), params)
    }

    /// Signed distances at `points` (normalised coordinates) with the first `lod` levels
    /// (`None`: all). Any number of points: large inputs are split into dispatches that fit the
    /// device's limits.
    pub fn eval(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        lod: Option<usize>,
    ) -> Result<Vec<f32>, NglodError> {
        Ok(self.eval_with_timer(gpu, points, lod, None)?.0)
    }

    /// [`NglodGpu::eval`], also returning the pure GPU time of its dispatches in nanoseconds,
    /// measured with `timer` (summed over the dispatches when a large input is split).
    pub fn eval_timed(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        lod: Option<usize>,
        timer: &GpuTimer,
    ) -> Result<(Vec<f32>, u64), NglodError> {
        let (values, ns) = self.eval_with_timer(gpu, points, lod, Some(timer))?;
        Ok((values, ns.unwrap_or(0)))
    }

    /// The one inference path, shared by [`NglodGpu::eval`] and [`NglodGpu::eval_timed`] (and
    /// called by [`crate::NeuralSdf`]): `timer`, when given, brackets every forward pass and the
    /// result's second field is the sum of their GPU nanoseconds (`None` without a timer).
    pub(crate) fn eval_with_timer(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        lod: Option<usize>,
        timer: Option<&GpuTimer>,
    ) -> Result<(Vec<f32>, Option<u64>), NglodError> {
        let k = self.config.lod(lod)?;
        if points.is_empty() {
            return Ok((Vec::new(), timer.map(|_| 0)));
        }
        let pipeline = gpu.pipeline(&shaders::NGLOD_FORWARD, "forward", &self.constants)?;
        let mut guard = self.eval.lock().unwrap_or_else(|e| e.into_inner());
        let want = points.len().min(self.eval_chunk);
        if guard.as_ref().is_none_or(|s| s.capacity < want) {
            // Grow to at least 4096 points so small calls do not reallocate each time.
            let capacity = want.max(4096).next_power_of_two().min(EVAL_CHUNK);
            let pts = gpu.storage_zeroed("nglod eval points", capacity as u64 * 12)?;
            let out = gpu.storage_zeroed("nglod eval out", capacity as u64 * 4)?;
            let uniforms = gpu.uniform("nglod eval uniforms", &self.eval_uniforms(0, k));
            let bind_group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("nglod eval"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    entry(0, &uniforms),
                    entry(1, &self.params),
                    entry(2, &pts),
                    entry(3, &out),
                    entry(4, &self.mlp),
                    entry(5, &self.table),
                ],
            });
            *guard = Some(EvalScratch {
                capacity,
                points: pts,
                out,
                uniforms,
                bind_group,
            });
        }
        let Some(s) = guard.as_ref() else {
            unreachable!("scratch was just created")
        };
        let mut result = Vec::with_capacity(points.len());
        let mut gpu_ns = 0u64;
        for chunk in points.chunks(s.capacity.min(self.eval_chunk)) {
            let n = chunk.len() as u32;
            gpu.write(&s.points, bytemuck::cast_slice::<Vec3, f32>(chunk))?;
            gpu.write(&s.uniforms, &[self.eval_uniforms(n, k)])?;
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            self.refresh_mlp(&mut enc);
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("nglod forward"),
                    // One pass per submission: it is both the first and the last timed pass.
                    timestamp_writes: timer.map(|t| t.writes(true, true)),
                });
                pass.set_pipeline(&pipeline);
                pass.set_bind_group(0, &s.bind_group, &[]);
                let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
                pass.dispatch_workgroups(x, y, 1);
            }
            if let Some(t) = timer {
                t.resolve(&mut enc);
            }
            gpu.queue().submit([enc.finish()]);
            result.extend(gpu.read_back_range::<f32>(&s.out, 0, u64::from(n))?);
            if let Some(t) = timer {
                gpu_ns += t.read_ns(gpu)?;
            }
        }
        Ok((result, timer.map(|_| gpu_ns)))
    }

    /// The serving kernel (`query`, or with `gradients` `query_grad`, in
    /// `shaders/nglod_forward.wgsl`) bound to a caller's `input` (`vec4` points in mesh
    /// coordinates, mapped to the model's cube by `center` and `scale`) and `output` (the
    /// distance in mesh units per point, or with `gradients` a `vec4`: distance and unit
    /// normal), for [`NglodGpu::record_eval`]. The whole query is this one dispatch. Holds its
    /// own small uniform buffer for the point count. With `subgroup_width` (the widest
    /// subgroup the adapter may run, which divides `WG`) the kernel is
    /// `shaders/nglod_query_subgroup.wgsl`'s, one point per subgroup.
    pub(crate) fn eval_binding(
        &self,
        gpu: &GpuContext,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        gradients: bool,
        (center, scale): (Vec3, f32),
        subgroup_width: Option<u32>,
    ) -> Result<NglodEvalBinding, NglodError> {
        let (shader, entry_point, per_group) = match (subgroup_width, gradients) {
            (None, false) => (&shaders::NGLOD_FORWARD, "query", WG),
            (None, true) => (&shaders::NGLOD_FORWARD, "query_grad", WG),
            (Some(w), _) => (&shaders::NGLOD_QUERY_SUBGROUP, "query_sg", WG / w),
        };
        let mut constants = self.constants.to_vec();
        if subgroup_width.is_some() {
            constants.push(("PER_GROUP", f64::from(per_group)));
            constants.push(("NORMALS", f64::from(u8::from(gradients))));
        }
        let pipeline = gpu.pipeline(shader, entry_point, &constants)?;
        let uniforms = gpu.uniform("nglod query uniforms", &self.eval_uniforms(0, 0));
        let bind_group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("nglod query"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                entry(0, &uniforms),
                entry(1, &self.params),
                entry(2, input),
                entry(3, output),
                entry(4, &self.mlp),
                entry(5, &self.table),
            ],
        });
        Ok(NglodEvalBinding {
            pipeline,
            uniforms,
            bind_group,
            transform: center.extend(scale).to_array(),
            per_group,
            written: None,
        })
    }

    /// Records the evaluation of the first `n` points of `binding`'s input into its output
    /// with the first `lod` levels, into `enc` (the serving path, [`crate::serve::query`]). The point
    /// count and level go through the queue when they change, so they take effect at the next
    /// submission: record one binding at most once per submission. `timer`, when given,
    /// brackets the dispatch (resolve it after).
    pub(crate) fn record_eval(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        binding: &mut NglodEvalBinding,
        n: u32,
        lod: Option<usize>,
        timer: Option<&GpuTimer>,
    ) -> Result<(), NglodError> {
        let k = self.config.lod(lod)?;
        if n == 0 {
            return Ok(());
        }
        if binding.written != Some((n, k)) {
            let u = EvalUniforms {
                query: binding.transform,
                ..self.eval_uniforms(n, k)
            };
            gpu.write(&binding.uniforms, &[u])?;
            binding.written = Some((n, k));
        }
        self.refresh_mlp(enc);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("nglod query"),
            timestamp_writes: timer.map(|t| t.writes(true, true)),
        });
        pass.set_pipeline(&binding.pipeline);
        pass.set_bind_group(0, &binding.bind_group, &[]);
        let (x, y) = gpu.dispatch_size(n.div_ceil(binding.per_group));
        pass.dispatch_workgroups(x, y, 1);
        Ok(())
    }

    /// Records [`NglodGpu::record_mlp_copy`] unless the network is frozen (its uniform is current).
    fn refresh_mlp(&self, enc: &mut wgpu::CommandEncoder) {
        if !self.frozen {
            self.record_mlp_copy(enc);
        }
    }

    /// Copies the MLP block of the parameters into the uniform buffer the kernels read it from.
    fn record_mlp_copy(&self, enc: &mut wgpu::CommandEncoder) {
        let (start, bytes) = self.mlp_range();
        enc.copy_buffer_to_buffer(&self.params, start, &self.mlp, 0, bytes);
    }

    /// Where the MLP block lies in the parameter buffer: byte offset and length.
    fn mlp_range(&self) -> (u64, u64) {
        let start = self.layout.w0 as u64 * 4;
        (start, self.layout.len as u64 * 4 - start)
    }

    fn eval_uniforms(&self, n: u32, lod: usize) -> EvalUniforms {
        EvalUniforms {
            n_points: n,
            lod: lod as u32,
            mlp_offset: self.layout.w0 as u32,
            _pad: 0,
            levels: level_table(&self.config, &self.layout),
            query: [0.0, 0.0, 0.0, 1.0],
        }
    }

    /// The loss and its gradient for one batch, computed by the training kernels, as
    /// [`super::cpu::loss_and_gradient`] defines them (`L = (1/N) Σ_i Σ_k (sdf_k - y)²`). Leaves
    /// the gradient buffer zeroed. For tests and diagnostics: training keeps everything on the GPU.
    pub fn loss_and_gradient(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        targets: &[f32],
        objective: Objective,
    ) -> Result<(f64, Vec<f32>), NglodError> {
        if points.len() != targets.len() {
            return Err(NglodError::LengthMismatch {
                what: "targets (one per point)",
                expected: points.len(),
                got: targets.len(),
            });
        }
        if points.is_empty() {
            return Ok((0.0, vec![0.0; self.layout.len]));
        }
        let pts =
            gpu.storage_from_slice("nglod points", bytemuck::cast_slice::<Vec3, f32>(points))?;
        let tgt = gpu.storage_from_slice("nglod targets", targets)?;
        let n = u32::try_from(points.len()).map_err(|_| NglodError::LengthMismatch {
            what: "points per gradient batch",
            expected: u32::MAX as usize,
            got: points.len(),
        })?;
        let kernels = TrainKernels::new(gpu, self, &pts, &tgt, n, objective)?;
        gpu.zero(&self.grads);
        gpu.zero(&kernels.stats);
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        kernels.record(gpu, &mut enc, (0, n), None)?;
        gpu.queue().submit([enc.finish()]);
        let mut grads: Vec<f32> = gpu.read_back_range(&self.grads, 0, self.layout.len as u64)?;
        let stats: Vec<f32> = gpu.read_back_range(&kernels.stats, 0, 1)?;
        gpu.zero(&self.grads);
        let inv = 1.0 / points.len() as f32;
        for g in &mut grads {
            *g *= inv;
        }
        Ok((f64::from(stats[0]) / points.len() as f64, grads))
    }
}

/// The training kernels bound to one set of point and target buffers.
pub(crate) struct TrainKernels {
    /// The model's parameter buffer and its MLP uniform copy (wgpu handles are shared).
    params: wgpu::Buffer,
    mlp: wgpu::Buffer,
    mlp_range: (u64, u64),
    uniforms: wgpu::Buffer,
    /// `stats[0]`: Σ r² accumulated over recorded steps until cleared.
    pub(crate) stats: wgpu::Buffer,
    _rows: wgpu::Buffer,
    _partials: wgpu::Buffer,
    /// The rows' forward and backward (`train_rows` or `train_rows_sg`), the MLP gradients'
    /// partial sums and their reduction; their workgroup grids change with each step's rows.
    train: Launch,
    partial: Launch,
    reduce: Launch,
    /// Which kernel `train` is, and the rows each of its workgroups takes.
    kernel: QueryKernel,
    rows_per_group: u32,
    base: TrainUniforms,
    max_points: u32,
    max_prefixes: u32,
    n_out: u32,
    hidden: u32,
}

impl TrainKernels {
    /// Kernels for batches of at most `max_points` points from `points` (3 f32 each) and
    /// `targets`.
    pub(crate) fn new(
        gpu: &GpuContext,
        model: &NglodGpu,
        points: &wgpu::Buffer,
        targets: &wgpu::Buffer,
        max_points: u32,
        objective: Objective,
    ) -> Result<Self, NglodError> {
        let c = &model.config;
        let (lod_base, n_prefix) = objective.prefixes(c.levels());
        let max_rows = u64::from(max_points) * n_prefix as u64;
        let max_chunks = max_rows.div_ceil(u64::from(CHUNK));
        if max_chunks > u64::from(gpu.limits().max_compute_workgroups_per_dimension) {
            return Err(NglodError::InvalidConfig(format!(
                "a batch of {max_points} points × {n_prefix} prefixes is too large for one step"
            )));
        }
        let stride = 2 + u64::from(c.input_dim()) + u64::from(c.hidden);
        let n_out = c.hidden * c.input_dim() + 2 * c.hidden + 2;
        let rows = gpu.storage_zeroed("nglod rows", max_rows * stride * 4)?;
        let partials = gpu.storage_zeroed("nglod partials", max_chunks * u64::from(n_out) * 4)?;
        let stats = gpu.storage_zeroed("nglod stats", 4)?;
        let base = TrainUniforms {
            n_rows: 0,
            first: 0,
            n_prefix: n_prefix as u32,
            lod_base: lod_base as u32,
            mlp_offset: model.layout.w0 as u32,
            chunk: CHUNK,
            n_chunks: 0,
            _pad: 0,
            levels: level_table(c, &model.layout),
        };
        let uniforms = gpu.uniform("nglod train uniforms", &base);
        let kernel = model.train_kernel(gpu, max_rows);
        let (train, kernel, rows_per_group) = match (kernel, gpu.subgroups_within(WG)) {
            (QueryKernel::PerSubgroup, Some(width)) => {
                let shader = if model.float_atomics {
                    &shaders::NGLOD_TRAIN_SUBGROUP_ATOMIC
                } else {
                    &shaders::NGLOD_TRAIN_SUBGROUP_CAS
                };
                // The rows of a workgroup: one per subgroup of the widest size it may run.
                let per_group = WG / width;
                let mut constants = model.constants.to_vec();
                constants.push(("PER_GROUP", f64::from(per_group)));
                let train = gpu.pipeline(shader, "train_rows_sg", &constants)?;
                (train, QueryKernel::PerSubgroup, per_group)
            }
            _ => {
                let shader = if model.float_atomics {
                    &shaders::NGLOD_TRAIN_ATOMIC
                } else {
                    &shaders::NGLOD_TRAIN_CAS
                };
                let train = gpu.pipeline(shader, "train_rows", &model.constants)?;
                (train, QueryKernel::PerInvocation, WG)
            }
        };
        // The reduction sees the MLP only: F and H.
        let mlp_constants = &model.constants[..2];
        let partial = gpu.pipeline(&shaders::NGLOD_REDUCE, "mlp_partial", mlp_constants)?;
        let reduce = gpu.pipeline(&shaders::NGLOD_REDUCE, "mlp_reduce", mlp_constants)?;
        let no_groups = (0, 0, 0);
        let train = Launch::new(
            gpu,
            &train,
            match kernel {
                QueryKernel::PerInvocation => "train_rows",
                QueryKernel::PerSubgroup => "train_rows_sg",
            },
            &[
                entry(0, &uniforms),
                entry(1, &model.params),
                entry(2, points),
                entry(3, targets),
                entry(4, &rows),
                entry(5, &model.grads),
                entry(6, &model.mlp),
                entry(7, &model.table),
            ],
            no_groups,
        );
        let partial = Launch::new(
            gpu,
            &partial,
            "mlp_partial",
            &[
                entry(0, &uniforms),
                entry(1, &model.params),
                entry(2, &rows),
                entry(3, &partials),
            ],
            no_groups,
        );
        let reduce = Launch::new(
            gpu,
            &reduce,
            "mlp_reduce",
            &[
                entry(0, &uniforms),
                entry(4, &model.grads),
                entry(5, &stats),
                entry(6, &partials),
            ],
            no_groups,
        );
        Ok(TrainKernels {
            params: model.params.clone(),
            mlp: model.mlp.clone(),
            mlp_range: model.mlp_range(),
            uniforms,
            stats,
            _rows: rows,
            _partials: partials,
            train,
            partial,
            reduce,
            kernel,
            rows_per_group,
            base,
            max_points,
            max_prefixes: n_prefix as u32,
            n_out,
            hidden: c.hidden,
        })
    }

    /// Trains only the first `lod` levels from now on (progressive training): the prefixes of
    /// `objective` capped at `lod`. `lod` is clamped to the levels the kernels were built for.
    pub(crate) fn set_lod(&mut self, objective: Objective, lod: usize) {
        let (base, count) = objective.prefixes(lod.max(1));
        let max = self.max_prefixes;
        self.base.lod_base = base as u32;
        self.base.n_prefix = (count as u32).min(max);
    }

    /// Records forward, backward and the MLP reduction for points `first..first + n` into
    /// `enc`, accumulating gradient sums into the model's gradient buffer; given a profiler,
    /// each launch in a pass of its own that it times. The uniforms go through the queue:
    /// submit before recording the next step.
    pub(crate) fn record(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        (first, n): (u32, u32),
        profiler: Option<&mut PassProfiler>,
    ) -> Result<(), NglodError> {
        let u = self.uniforms_for(first, n)?;
        gpu.write(&self.uniforms, &[u])?;
        self.record_passes(gpu, enc, &u, profiler);
        Ok(())
    }

    /// [`TrainKernels::record`] with the uniforms staged in `stager` (flush it before the
    /// submission), so that several steps can share one submission.
    pub(crate) fn record_staged(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        stager: &mut UniformStager,
        first: u32,
        n: u32,
    ) -> Result<(), NglodError> {
        let u = self.uniforms_for(first, n)?;
        stager.stage(enc, &self.uniforms, &u)?;
        self.record_passes(gpu, enc, &u, None);
        Ok(())
    }

    /// The uniforms of a step over points `first..first + n`.
    fn uniforms_for(&self, first: u32, n: u32) -> Result<TrainUniforms, NglodError> {
        if n > self.max_points {
            return Err(NglodError::LengthMismatch {
                what: "points in one step (at most the batch size)",
                expected: self.max_points as usize,
                got: n as usize,
            });
        }
        let n_rows = n * self.base.n_prefix;
        Ok(TrainUniforms {
            n_rows,
            first,
            n_chunks: n_rows.div_ceil(CHUNK),
            ..self.base
        })
    }

    /// Which kernel runs the rows of a step.
    pub(crate) fn kernel(&self) -> QueryKernel {
        self.kernel
    }

    /// The launches of a step whose uniforms are `u`, in order, with their workgroup grids.
    fn launches(&self, gpu: &GpuContext, u: &TrainUniforms) -> [GridLaunch<'_>; 3] {
        let (x, y) = gpu.dispatch_size(u.n_rows.div_ceil(self.rows_per_group));
        [
            (&self.train, (x, y, 1)),
            // One invocation per hidden unit plus one for b1 and the loss.
            (
                &self.partial,
                ((self.hidden + 1).div_ceil(WG), u.n_chunks, 1),
            ),
            (&self.reduce, (self.n_out.div_ceil(WG), 1, 1)),
        ]
    }

    /// The MLP copy and the passes of a step whose uniforms `u` are in place, each launch in a
    /// timed pass of its own given a profiler.
    fn record_passes(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        u: &TrainUniforms,
        profiler: Option<&mut PassProfiler>,
    ) {
        self.record_mlp_copy(enc);
        record_launches(enc, "nglod train step", &self.launches(gpu, u), profiler);
    }

    /// Copies the MLP block of the parameters into its uniform copy.
    fn record_mlp_copy(&self, enc: &mut wgpu::CommandEncoder) {
        let (start, bytes) = self.mlp_range;
        enc.copy_buffer_to_buffer(&self.params, start, &self.mlp, 0, bytes);
    }
}

#[cfg(test)]
mod tests {
    use crate::shaders;

    /// The uniforms have the layout every NGLOD kernel reads.
    #[test]
    fn uniforms_mirror_the_shaders() {
        shaders::assert_mirrors!(
            super::EvalUniforms,
            shaders::NGLOD_FORWARD,
            "Uniforms",
            [n_points, lod, mlp_offset, levels, query]
        );
        for shader in [shaders::NGLOD_TRAIN_CAS, shaders::NGLOD_REDUCE] {
            shaders::assert_mirrors!(
                super::TrainUniforms,
                shader,
                "Uniforms",
                [
                    n_rows, first, n_prefix, lod_base, mlp_offset, chunk, n_chunks, levels
                ]
            );
        }
    }
}
