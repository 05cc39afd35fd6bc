//! Host code of the SIREN kernels (`shaders/siren_gemm.wgsl`, `siren_dense.wgsl`,
//! `siren_head.wgsl`, `siren_train.wgsl`): inference, inference with the input gradient, and
//! the forward + double backward of a training step.
//!
//! Activations are row-major `[rows, width]` matrices. With tangents, a point owns four
//! consecutive rows: the value, then ∂/∂x, ∂/∂y, ∂/∂z. A hidden layer runs (see
//! [`LayerKernels`]) on the strided GEMM kernel followed by the elementwise sine kernels, on the
//! row-blocked kernels of `siren_dense.wgsl` with the sine fused in (CPU adapters), or on the
//! tiled kernels of `kernels::tiled` (GPUs; small inference batches in one fused dispatch);
//! weight gradients are split over the batch into partials that a second kernel sums into the
//! gradient buffer, so there are no atomics anywhere.
//!
//! A training step either carries the tangents ([`TrainStep::Tangents`], the four rows per
//! point above) or runs reverse over reverse ([`TrainStep::ReverseOverReverse`], one row per
//! point; the math and layout are in [`super::ror`]); [`SirenGpu::set_train_step`] chooses.

use glam::Vec3;

use super::kernels::coop::CoopKernels;
use super::kernels::products::{GemmUniforms, gemm_forward, splits_for};
use super::kernels::row_blocked::{Epilogue, RowBlockedPlan};
use super::kernels::tiled::{TiledEpilogue, TiledKernels};
use super::kernels::{Launch, LayerKernels, OneDispatch, TiledBlock, WG};
use super::ror::{self, TrainStep};
use super::tangents;
use super::{LayerLayout, Siren, SirenConfig, SirenConfigError};
use crate::gpu::{GpuContext, GpuError, GpuTimer, entry};
use crate::shaders;

/// Errors of the SIREN GPU code.
#[derive(Debug, thiserror::Error)]
pub enum SirenGpuError {
    /// The device failed or refused something.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The network configuration is unusable.
    #[error(transparent)]
    Config(#[from] SirenConfigError),
    /// The kernels asked for are known to give wrong results for this network on this adapter.
    #[error(
        "the {kernels} kernels cannot evaluate this network on a CPU adapter: {reason}; use the tiled kernels (or auto)"
    )]
    KernelsUnsupported {
        /// [`LayerKernels::name`] of the family asked for.
        kernels: &'static str,
        /// Why.
        reason: String,
    },
}

/// The widest hidden layer the GEMM (`siren_gemm.wgsl`) evaluates correctly on Debian 12's
/// lavapipe (Mesa 22.3, LLVM 15): from a fan-in of 500 on (vec4 loads; 497–499 take scalar loads
/// and pass) its results are wrong by 1e-2 and more there, with a threshold that moves with its K
/// chunk (KC = 128 moved it between 1500 and 2000, KC = 64 between 1024 and 1500). The same
/// shader is right at every width to 2048 on Mesa 26.1 (LLVM 19), so it is the older driver's
/// compiler; the tiled kernels are right on both. See [`gemm_trusted_wide`].
pub(crate) const GEMM_CPU_MAX_FAN_IN: usize = 496;

/// Whether the GEMM may run layers wider than [`GEMM_CPU_MAX_FAN_IN`] on `gpu`: on a GPU, and on
/// llvmpipe built with LLVM 19 or newer (measured right); not on llvmpipe with an older or
/// unknown LLVM (LLVM 15 measured wrong, 16–18 not measured).
fn gemm_trusted_wide(gpu: &GpuContext) -> bool {
    if !gpu.is_cpu() {
        return true;
    }
    let info = &gpu.adapter_info().driver_info;
    let llvm_major = info
        .split("LLVM ")
        .nth(1)
        .and_then(|v| v.split('.').next())
        .and_then(|m| m.parse::<u32>().ok());
    llvm_major.is_some_and(|m| m >= 19)
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ElementwiseUniforms {
    n_points: u32,
    width: u32,
    bias_off: u32,
    _pad0: u32,
    omega: f32,
    _pad1: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct HeadUniforms {
    pub(crate) mode: u32,
    pub(crate) n_points: u32,
    pub(crate) n_surface: u32,
    pub(crate) width: u32,
    pub(crate) w_off: u32,
    pub(crate) b_off: u32,
    pub(crate) _pad0: u32,
    pub(crate) _pad1: u32,
    pub(crate) w_surface: f32,
    pub(crate) w_off_surface: f32,
    pub(crate) w_normal: f32,
    pub(crate) w_eikonal: f32,
    pub(crate) alpha: f32,
    pub(crate) inv_n: f32,
    pub(crate) omega: f32,
    pub(crate) w_sign: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ReduceUniforms {
    pub(crate) m: u32,
    pub(crate) n: u32,
    pub(crate) splits: u32,
    pub(crate) w_off: u32,
    pub(crate) b_off: u32,
    pub(crate) pbias_off: u32,
    pub(crate) _pad0: u32,
    pub(crate) _pad1: u32,
}

/// Smallest batch of values that [`LayerKernels::Auto`] runs on f16 cooperative matrices in a
/// served network. On an H100 (SIREN `default`, points and values on the GPU, interleaved
/// rounds) the cooperative-matrix kernel took 78.5 µs against the f32 fused kernel's 75.4 µs at
/// 3000 points, and 77.7 against 167.4 µs at 8192 (440 against 680 µs at 50 000): its time is
/// flat up to 8192 points while the f32 kernel's grows, so they cross near 3200.
pub const COOP_AUTO_MIN_POINTS: u32 = 4096;

/// Narrowest hidden layers that [`LayerKernels::Auto`] runs on f16 cooperative matrices. On an
/// H100 the `small` preset (64 wide) took 424 µs on them at 50 000 points against 224 µs in f32
/// and the `default` (256 wide) 686 against 1016 µs; 128 is not measured, so it stays in f32.
pub const COOP_AUTO_MIN_WIDTH: usize = 256;

/// The default of [`SirenGpu::set_coop_min_points`] for a served network ([`crate::NeuralSdf`])
/// of `config` on an adapter: [`COOP_AUTO_MIN_POINTS`] on GPUs for networks at least
/// [`COOP_AUTO_MIN_WIDTH`] wide, else none (networks that train keep none).
pub fn auto_coop_min_points(cpu_adapter: bool, config: &SirenConfig) -> Option<u32> {
    (!cpu_adapter && config.width >= COOP_AUTO_MIN_WIDTH).then_some(COOP_AUTO_MIN_POINTS)
}

/// The kernel families a [`LayerKernels`] choice sets up: row-blocked, tiled, cooperative-matrix.
type Families = (
    Option<RowBlockedPlan>,
    Option<TiledKernels>,
    Option<CoopKernels>,
);

/// Default of [`SirenGpu::set_fused_max_points`] on CPU adapters: the latency-bound batches
/// (the 3000 points). GPUs run every inference batch on the fused kernel: on an H100
/// it took 15–17 % less time than the per-layer kernels at 50 000 points (`default` preset,
/// two alternating runs; BENCHMARKS "NVIDIA H100"), and at 3000 it is the only way to fill
/// the GPU.
pub const DEFAULT_FUSED_MAX_POINTS: u32 = 8192;

/// Whether [`TrainStep::Auto`] picks the reverse-over-reverse step on the row-blocked kernels:
/// on lavapipe it measured 529–565 ms per `small` step of 10⁴ points against 852–894 ms for
/// the tangents (BENCHMARKS.md, "The reverse-over-reverse training step").
const ROW_BLOCKED_AUTO_ROR: bool = true;

/// Rows per GEMM workgroup (see `siren_gemm.wgsl`).
const GEMM_ROWS: u32 = 64;

/// A network's one-dispatch kernel bound to a caller's query buffers
/// ([`SirenGpu::query_launch`]): a query of any count up to the buffers' capacity writes the
/// count into the uniforms (through the queue, when it changes) instead of building a new
/// launch.
#[derive(Debug)]
pub(crate) struct QueryLaunch {
    kernel: BoundDispatch,
    /// With [`LayerKernels::Auto`] and [`SirenGpu::set_coop_min_points`]: that many points,
    /// and the cooperative-matrix kernel that batches of values of at least as many run on.
    large: Option<(u32, BoundDispatch)>,
    /// Rows per point: 1, or 4 with normals.
    rows_per_point: u32,
}

/// A one-dispatch kernel and the row count its uniforms hold.
#[derive(Debug)]
struct BoundDispatch {
    kernel: OneDispatch,
    written: u32,
}

impl QueryLaunch {
    /// Records the query of `n` points into `pass`; a new count takes effect at the next
    /// submission, so record it at most once per submission.
    pub(crate) fn record(&mut self, gpu: &GpuContext, pass: &mut wgpu::ComputePass<'_>, n: u32) {
        let rows = n * self.rows_per_point;
        let bound = match self.large.as_mut() {
            Some((min, large)) if n >= *min => large,
            _ => &mut self.kernel,
        };
        if rows != bound.written {
            gpu.queue()
                .write_buffer(&bound.kernel.uniforms, 0, bytemuck::bytes_of(&rows));
            bound.written = rows;
        }
        let (x, y) = gpu.dispatch_size(rows.div_ceil(bound.kernel.group_rows).max(1));
        bound.kernel.launch.record_groups(pass, (x, y, 1));
    }
}

fn gemm_groups(gpu: &GpuContext, u: &GemmUniforms) -> (u32, u32, u32) {
    let z = if u.mode == 2 { splits_for(u.k) } else { 1 };
    let (x, y) = gpu.dispatch_size(u.m.div_ceil(GEMM_ROWS));
    (x, y, z)
}

/// The compiled pipelines SIREN uses.
#[derive(Debug, Clone)]
pub(crate) struct Pipelines {
    gemm: wgpu::ComputePipeline,
    sine_forward: wgpu::ComputePipeline,
    sine_backward: wgpu::ComputePipeline,
    pub(crate) head_forward: wgpu::ComputePipeline,
    /// `head_forward` without the loss reduction, for inference.
    head_eval: wgpu::ComputePipeline,
    pub(crate) head_backward: wgpu::ComputePipeline,
}

impl Pipelines {
    fn new(gpu: &GpuContext) -> Result<Self, GpuError> {
        Ok(Pipelines {
            gemm: gpu.pipeline(&shaders::SIREN_GEMM, "gemm", &[])?,
            sine_forward: gpu.pipeline(&shaders::SIREN_GEMM, "sine_forward", &[])?,
            sine_backward: gpu.pipeline(&shaders::SIREN_GEMM, "sine_backward", &[])?,
            head_forward: gpu.pipeline(&shaders::SIREN_HEAD, "head_forward", &[])?,
            head_eval: gpu.pipeline(&shaders::SIREN_HEAD, "head_eval", &[])?,
            head_backward: gpu.pipeline(&shaders::SIREN_HEAD, "head_backward", &[])?,
        })
    }
}

/// Buffers of the forward pass for a fixed capacity of points, and the launches for the
/// batch size they were last built for.
#[derive(Debug)]
struct EvalWorkspace {
    capacity: u32,
    tangents: bool,
    input: wgpu::Buffer,
    act: [wgpu::Buffer; 2],
    /// Pre-activations (tangent mode only).
    z: wgpu::Buffer,
    values: wgpu::Buffer,
    launches: Vec<Launch>,
    /// The launches were built for this many points.
    built_for: Option<u32>,
}

/// A SIREN's parameters (and gradients) on the GPU, with its kernels.
#[derive(Debug)]
pub struct SirenGpu {
    pub(crate) config: SirenConfig,
    pub(crate) layers: Vec<LayerLayout>,
    pub(crate) params: wgpu::Buffer,
    pub(crate) grads: wgpu::Buffer,
    pub(crate) pipelines: Pipelines,
    eval: Option<EvalWorkspace>,
    eval_grad: Option<EvalWorkspace>,
    max_chunk: u32,
    kernels: LayerKernels,
    /// The hidden layers on the row-blocked kernels, if any.
    dense: Option<RowBlockedPlan>,
    /// The tiled kernels, when they run every product.
    pub(crate) tiled: Option<TiledKernels>,
    /// The cooperative-matrix kernels, when they run inference of values.
    coop: Option<CoopKernels>,
    /// Largest inference batch (per launch) for the fused all-layer kernel of the tiled family.
    fused_max_points: u32,
    /// Register blocks per invocation the fused kernel may use ([`SirenGpu::set_fused_row_blocks`]).
    fused_row_blocks: u32,
    /// [`SirenGpu::set_gpu_step_layout`] (`None`: by adapter).
    gpu_step_layout: Option<bool>,
    /// The tiled GEMM's register blocks.
    tiled_block: TiledBlock,
    /// The parameters change only through [`SirenGpu::upload`] (a served model, see
    /// [`SirenGpu::new_frozen`]): the row-blocked kernels' packed weights are then copied when
    /// they change, not at the start of every evaluation.
    frozen: bool,
    /// [`SirenGpu::set_coop_min_points`].
    coop_min_points: Option<u32>,
    /// How training steps differentiate through ∇ₓΦ.
    train_step: TrainStep,
}

impl SirenGpu {
    /// Uploads `siren`'s parameters and compiles (or fetches from the context's cache) the
    /// kernels.
    pub fn new(gpu: &GpuContext, siren: &Siren) -> Result<Self, SirenGpuError> {
        Self::with_coop_min_points(gpu, siren, None)
    }

    /// [`SirenGpu::new`] with [`SirenGpu::set_coop_min_points`] set to `coop_min_points`.
    fn with_coop_min_points(
        gpu: &GpuContext,
        siren: &Siren,
        coop_min_points: Option<u32>,
    ) -> Result<Self, SirenGpuError> {
        let config = *siren.config();
        config.validate()?;
        // Padded to 16 bytes: the GEMM also reads it as vec4.
        let mut padded = siren.params().to_vec();
        padded.resize(padded.len().next_multiple_of(4), 0.0);
        let params = gpu.storage_from_slice("siren params", &padded)?;
        let grads = gpu.storage_zeroed("siren grads", padded.len() as u64 * 4)?;
        let layers = config.layers();
        let kernels = LayerKernels::default();
        let tiled_block = TiledBlock::default();
        let (dense, tiled, coop) = Self::families(
            gpu,
            kernels,
            tiled_block,
            &config,
            &layers,
            &params,
            coop_min_points.is_some(),
        )?;
        Ok(SirenGpu {
            config,
            layers,
            params,
            grads,
            pipelines: Pipelines::new(gpu)?,
            eval: None,
            eval_grad: None,
            max_chunk: 65536,
            kernels,
            dense,
            tiled,
            coop,
            fused_max_points: if gpu.is_cpu() {
                DEFAULT_FUSED_MAX_POINTS
            } else {
                u32::MAX
            },
            fused_row_blocks: 1,
            gpu_step_layout: None,
            tiled_block,
            frozen: false,
            coop_min_points,
            train_step: TrainStep::default(),
        })
    }

    /// [`SirenGpu::new`] for a network whose parameters nobody writes on the GPU (no trainer,
    /// no writes through [`SirenGpu::params_buffer`]): [`crate::NeuralSdf`]'s. Its evaluations
    /// skip [`SirenGpu::record_pack`]; [`SirenGpu::upload`] and
    /// [`SirenGpu::set_layer_kernels`] pack.
    pub(crate) fn new_frozen(gpu: &GpuContext, siren: &Siren) -> Result<Self, SirenGpuError> {
        // What `Auto` runs a served network's large batches on.
        let coop_min_points = auto_coop_min_points(gpu.is_cpu(), siren.config());
        let mut net = Self::with_coop_min_points(gpu, siren, coop_min_points)?;
        net.frozen = true;
        net.pack_now(gpu);
        Ok(net)
    }

    /// The row-blocked, tiled and cooperative-matrix kernels that `kernels` asks for on
    /// `gpu`, each where it applies.
    fn families(
        gpu: &GpuContext,
        kernels: LayerKernels,
        tiled_block: TiledBlock,
        config: &SirenConfig,
        layers: &[LayerLayout],
        params: &wgpu::Buffer,
        auto_coop: bool,
    ) -> Result<Families, SirenGpuError> {
        let mut dense = if kernels.row_blocked(gpu) {
            RowBlockedPlan::new(gpu, layers)?
        } else {
            None
        };
        let covers = |l: usize| dense.as_ref().is_some_and(|d| d.covers(l));
        // On a CPU, Auto keeps the row-blocked kernels only where they cover every hidden
        // layer; otherwise the tiled ones run every product, never the GEMM on a wide layer
        // (GEMM_CPU_MAX_FAN_IN).
        let auto_tiled =
            kernels == LayerKernels::Auto && gpu.is_cpu() && !(0..config.hidden_layers).all(covers);
        if auto_tiled {
            dense = None;
        }
        let tiled = if kernels.tiled(gpu) || auto_tiled {
            TiledKernels::new(gpu, config, params, tiled_block)?
        } else {
            None
        };
        let covers = |l: usize| dense.as_ref().is_some_and(|d| d.covers(l));
        if tiled.is_none()
            && config.width > GEMM_CPU_MAX_FAN_IN
            && (1..config.hidden_layers).any(|l| !covers(l))
            && !gemm_trusted_wide(gpu)
        {
            return Err(SirenGpuError::KernelsUnsupported {
                kernels: kernels.name(),
                reason: format!(
                    "its {}-wide hidden layers would run on the GEMM, which is wrong above a fan-in of {GEMM_CPU_MAX_FAN_IN} on llvmpipe before LLVM 19 ({})",
                    config.width,
                    gpu.adapter_info().driver_info
                ),
            });
        }
        let coop =
            if kernels == LayerKernels::CoopF16 || (kernels == LayerKernels::Auto && auto_coop) {
                CoopKernels::new(gpu, config, params)?
            } else {
                None
            };
        Ok((dense, tiled, coop))
    }

    /// Submits [`SirenGpu::record_pack`] on its own (a frozen network's weights changed).
    fn pack_now(&self, gpu: &GpuContext) {
        if self.dense.is_some() || self.coop.is_some() || self.tiled.is_some() {
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            self.record_eval_pack(&mut enc);
            gpu.queue().submit([enc.finish()]);
        }
    }

    /// [`SirenGpu::record_eval_pack`] unless the network is frozen (its packed weights are
    /// current).
    pub(crate) fn refresh_pack(&self, enc: &mut wgpu::CommandEncoder) {
        if !self.frozen {
            self.record_eval_pack(enc);
        }
    }

    /// [`SirenGpu::record_pack`], and the packings that only evaluations read (training steps
    /// skip them): the cooperative-matrix kernels' f16 weights, the fused kernel's transposed
    /// ones.
    fn record_eval_pack(&self, enc: &mut wgpu::CommandEncoder) {
        self.record_pack(enc);
        if let Some(c) = &self.coop {
            c.record_pack(enc);
        }
        if let Some(t) = &self.tiled {
            t.record_pack(enc);
        }
    }

    /// Chooses how training steps (and [`SirenGpu::loss_and_gradient`]) differentiate the
    /// loss's ∇ₓΦ terms (default [`TrainStep::Auto`]). A [`super::SirenTrainer`] must rebuild
    /// its passes: use [`super::SirenTrainer::set_train_step`].
    pub fn set_train_step(&mut self, step: TrainStep) {
        self.train_step = step;
    }

    /// The chosen training step (possibly [`TrainStep::Auto`]).
    pub fn train_step(&self) -> TrainStep {
        self.train_step
    }

    /// Whether training steps run reverse over reverse with the current kernels and
    /// [`TrainStep`] (otherwise they carry tangents).
    pub fn runs_reverse_over_reverse(&self) -> bool {
        let tiled = self.tiled.is_some();
        let dense = self.dense_ror_plan().is_some();
        match self.train_step {
            TrainStep::Tangents => false,
            TrainStep::ReverseOverReverse => tiled || dense,
            TrainStep::Auto => tiled || (ROW_BLOCKED_AUTO_ROR && dense),
        }
    }

    /// The tiled kernels, when they run every product.
    pub(crate) fn tiled_kernels(&self) -> Option<&TiledKernels> {
        self.tiled.as_ref()
    }

    /// The row-blocked kernels, when they cover every hidden layer (what the
    /// reverse-over-reverse step needs of them).
    pub(crate) fn dense_ror_plan(&self) -> Option<&RowBlockedPlan> {
        let covers_all = |d: &RowBlockedPlan| (0..self.config.hidden_layers).all(|l| d.covers(l));
        self.dense.as_ref().filter(|d| covers_all(d))
    }

    /// The layers' parameter layout.
    pub(crate) fn layer_layouts(&self) -> &[LayerLayout] {
        &self.layers
    }

    /// Chooses the kernels of the hidden layers (default [`LayerKernels::Auto`]).
    pub fn set_layer_kernels(
        &mut self,
        gpu: &GpuContext,
        kernels: LayerKernels,
    ) -> Result<(), SirenGpuError> {
        (self.dense, self.tiled, self.coop) = Self::families(
            gpu,
            kernels,
            self.tiled_block,
            &self.config,
            &self.layers,
            &self.params,
            self.coop_min_points.is_some(),
        )?;
        self.kernels = kernels;
        self.eval = None;
        self.eval_grad = None;
        if self.frozen {
            self.pack_now(gpu);
        }
        Ok(())
    }

    /// The kernels of the hidden layers.
    pub fn layer_kernels(&self) -> LayerKernels {
        self.kernels
    }

    /// How many hidden layers run on the row-blocked kernels (0 with the GEMM).
    pub fn row_blocked_layers(&self) -> usize {
        self.dense.as_ref().map_or(0, |d| {
            (0..self.layers.len()).filter(|&l| d.covers(l)).count()
        })
    }

    /// Chooses the tiled GEMM's register blocks (default [`TiledBlock::Auto`]; they matter
    /// only where the tiled kernels run, see [`SirenGpu::runs_tiled`]). Results agree to f32
    /// rounding whichever block runs.
    pub fn set_tiled_block(
        &mut self,
        gpu: &GpuContext,
        block: TiledBlock,
    ) -> Result<(), SirenGpuError> {
        self.tiled_block = block;
        self.set_layer_kernels(gpu, self.kernels)
    }

    /// The tiled GEMM's register blocks.
    pub fn tiled_block(&self) -> TiledBlock {
        self.tiled_block
    }

    /// Whether the tiled kernels run every product (they need 8 KiB of workgroup memory with
    /// 4 × 4 blocks, 16 KiB with 8 × 8, and
    /// 256 invocations per workgroup; without them the GEMM runs instead).
    pub fn runs_tiled(&self) -> bool {
        self.tiled.is_some()
    }

    /// Inference launches of at most `points` points run on the tiled family's fused
    /// all-layer kernel (default: every batch on GPUs, [`DEFAULT_FUSED_MAX_POINTS`] on CPU
    /// adapters; 0 disables it), larger ones on
    /// its per-layer kernels. Only with [`LayerKernels::Tiled`] and a width the fused kernel
    /// fits (a multiple of 4, at most 1024).
    pub fn set_fused_max_points(&mut self, points: u32) {
        self.fused_max_points = points;
        self.eval = None;
        self.eval_grad = None;
    }

    /// Lays out the reverse-over-reverse step's per-point and reduction kernels for a GPU
    /// (`Some(true)`), for a CPU adapter (`Some(false)`), or by the adapter (`None`, the
    /// default). The GPU layout gives the per-point kernel (`ror_head`) 4 invocations per point,
    /// so that a subgroup's loads read 4 consecutive floats of each point's rows (one float
    /// from each of 32 rows apart took 63 µs for 10⁴ points on an H100), and sums the split
    /// partials of the layers with few outputs (the output and first layers) with a workgroup
    /// per output. Lavapipe measured both slower (the head 24.6 against 18.4 ms for the
    /// `small` preset's 10⁴ points, the two reductions 6.2 against 0.4 ms). Results agree to
    /// f32 rounding. A [`super::SirenTrainer`] must rebuild its passes: use
    /// [`super::SirenTrainer::set_train_step`]. With `None`, [`crate::GpuOptions::step_layout`]
    /// (`HWSDF_STEP_LAYOUT=gpu` or `cpu`) overrides the adapter's choice (to compare the two on
    /// one GPU, e.g. in a whole fit by `train`).
    pub fn set_gpu_step_layout(&mut self, gpu_layout: Option<bool>) {
        self.gpu_step_layout = gpu_layout;
    }

    /// Whether the reverse-over-reverse step runs its GPU layout on `gpu`
    /// ([`SirenGpu::set_gpu_step_layout`]).
    pub fn gpu_step_layout(&self, gpu: &GpuContext) -> bool {
        self.gpu_step_layout
            .or_else(|| {
                gpu.options()
                    .step_layout
                    .map(|l| l == crate::gpu::StepLayout::Gpu)
            })
            .unwrap_or(!gpu.is_cpu())
    }

    /// Register blocks of four rows per invocation of the fused kernel, 1 to 3 (default 1):
    /// more load each weight once for more rows, and fill fewer workgroups. A full block takes
    /// 16 KiB of workgroup memory at widths of 64 and more; where the device has less, the
    /// blocks get fewer rows, and only where not even 4 rows fit are there fewer blocks
    /// ([`SirenGpu::fused_row_blocks`] says how many run).
    pub fn set_fused_row_blocks(&mut self, blocks: u32) {
        self.fused_row_blocks = blocks.clamp(1, 3);
        self.eval = None;
        self.eval_grad = None;
    }

    /// The register blocks per invocation the fused kernel runs with on `gpu` (`None` where the
    /// network does not fit it).
    pub fn fused_row_blocks(&self, gpu: &GpuContext) -> Option<u32> {
        TiledKernels::fused_layout(gpu, &self.config, self.fused_row_blocks).map(|l| l.row_blocks)
    }

    /// The side of the cooperative-matrix tiles that run inference of values, if they are set
    /// up: with [`LayerKernels::CoopF16`] where the device and the network allow them (every
    /// batch of values), and with [`LayerKernels::Auto`] where [`SirenGpu::set_coop_min_points`]
    /// set a batch size (a served network's default, [`auto_coop_min_points`]: batches of values
    /// of at least [`COOP_AUTO_MIN_POINTS`] on GPUs).
    pub fn coop_tile(&self) -> Option<u32> {
        self.coop.as_ref().map(CoopKernels::tile)
    }

    /// With [`LayerKernels::Auto`], batches of values of at least `points` points run on the
    /// cooperative-matrix kernels where the device has them ([`LayerKernels::CoopF16`]'s,
    /// f16 with f32 accumulators); smaller ones, normals and training on the f32 kernels.
    /// `None` (the default of a network that trains) never uses them; a served network
    /// ([`crate::NeuralSdf`]) starts at [`auto_coop_min_points`].
    pub fn set_coop_min_points(
        &mut self,
        gpu: &GpuContext,
        points: Option<u32>,
    ) -> Result<(), SirenGpuError> {
        self.coop_min_points = points;
        self.set_layer_kernels(gpu, self.kernels)
    }

    /// See [`SirenGpu::set_coop_min_points`].
    pub fn coop_min_points(&self) -> Option<u32> {
        self.coop_min_points
    }

    /// The smallest batch that `Auto` runs on the cooperative-matrix kernels (`u32::MAX`:
    /// none): values only.
    fn auto_coop_from(&self, tangents: bool) -> u32 {
        match self.coop_min_points {
            Some(m) if self.kernels == LayerKernels::Auto && !tangents => m,
            _ => u32::MAX,
        }
    }

    /// Whether an inference launch of `n` points runs on the fused all-layer kernel.
    pub fn runs_fused(&self, gpu: &GpuContext, n: u32) -> bool {
        self.tiled.is_some()
            && n <= self.fused_max_points
            && TiledKernels::fused_group_rows(gpu, &self.config).is_some()
    }

    /// Records the copy of the weights into the row-blocked kernels' uniform windows; every
    /// submission that runs this network's training launches must start with it (evaluations
    /// pack through [`SirenGpu::record_eval_pack`], which also packs the f16 weights).
    pub(crate) fn record_pack(&self, enc: &mut wgpu::CommandEncoder) {
        if let Some(d) = &self.dense {
            d.record_pack(enc, &self.params);
        }
    }

    pub(crate) fn dense_for(&self, l: usize) -> Option<&RowBlockedPlan> {
        self.dense.as_ref().filter(|d| d.covers(l))
    }

    /// The architecture.
    pub fn config(&self) -> &SirenConfig {
        &self.config
    }

    /// The flat parameter buffer (layout in [`super`]).
    pub fn params_buffer(&self) -> &wgpu::Buffer {
        &self.params
    }

    /// The flat gradient buffer, same layout; the backward pass accumulates into it.
    pub fn grads_buffer(&self) -> &wgpu::Buffer {
        &self.grads
    }

    /// Replaces the parameters on the GPU.
    pub fn upload(&self, gpu: &GpuContext, siren: &Siren) -> Result<(), SirenGpuError> {
        if *siren.config() != self.config {
            return Err(SirenConfigError::BadShape {
                width: siren.config().width,
                layers: siren.config().hidden_layers,
            }
            .into());
        }
        gpu.write(&self.params, siren.params())?;
        if self.frozen {
            self.pack_now(gpu);
        }
        Ok(())
    }

    /// The parameters as a host [`Siren`].
    pub fn download(&self, gpu: &GpuContext) -> Result<Siren, SirenGpuError> {
        let n = self.config.param_count() as u64;
        let p: Vec<f32> = gpu.read_back_range(&self.params, 0, n)?;
        Ok(Siren::from_params(self.config, p)?)
    }

    /// The gradient buffer's contents.
    pub fn read_grads(&self, gpu: &GpuContext) -> Result<Vec<f32>, SirenGpuError> {
        let n = self.config.param_count() as u64;
        Ok(gpu.read_back_range(&self.grads, 0, n)?)
    }

    /// Points per launch: bounded by the storage-binding limit on the largest activation
    /// buffer, and by 65536 to keep memory modest.
    fn chunk_capacity(&self, gpu: &GpuContext, tangents: bool) -> u32 {
        let limit = gpu.limits().max_storage_buffer_binding_size;
        let per_point = self.config.width as u64 * 4 * if tangents { 4 } else { 1 };
        let cap = (limit / per_point).clamp(64, u64::from(self.max_chunk));
        (cap as u32 / 64) * 64
    }

    /// Caps the points per launch (default 65536; at least 64; the device limits may lower it
    /// further). Smaller launches use less memory; larger ones amortise launch overhead.
    pub fn set_max_points_per_launch(&mut self, points: u32) {
        self.max_chunk = points.clamp(64, 1 << 22);
        self.eval = None;
        self.eval_grad = None;
    }

    /// Φ at each point (normalised coordinates), any number of points, split into launches that
    /// fit the device limits.
    pub fn eval(&mut self, gpu: &GpuContext, points: &[Vec3]) -> Result<Vec<f32>, SirenGpuError> {
        Ok(self.run_eval(gpu, points, false, None)?.0)
    }

    /// [`SirenGpu::eval`], also returning the GPU time of its dispatches (summed over the
    /// launches it splits into) from `timer`'s timestamp queries.
    pub fn eval_timed(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
        timer: &GpuTimer,
    ) -> Result<(Vec<f32>, u64), SirenGpuError> {
        let (values, ns) = self.run_eval(gpu, points, false, Some(timer))?;
        Ok((values, ns.unwrap_or(0)))
    }

    /// Φ and ∇Φ at each point.
    pub fn eval_with_gradient(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<(f32, Vec3)>, SirenGpuError> {
        let (vals, _) = self.run_eval(gpu, points, true, None)?;
        Ok(vals
            .chunks_exact(4)
            .map(|v| (v[0], Vec3::new(v[1], v[2], v[3])))
            .collect())
    }

    /// Records the evaluation of `n` points from `input` into `output`, into the caller's
    /// encoder: the serving path of [`crate::serve::query`] (issue 13). `input` holds the network's
    /// input rows (3 floats per normalised point, or with `gradients` the four rows of
    /// `stream_rows`: the point and the unit tangents); `output` receives 1 float per point, or
    /// with `gradients` 4 (value, then the gradient). Built on the launches of
    /// [`SirenGpu::eval`]: the rows are copied into its workspace and the values out of it, one
    /// chunk of its capacity at a time, all in `enc`.
    pub(crate) fn record_eval(
        &mut self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        n: u32,
        gradients: bool,
    ) -> Result<(), SirenGpuError> {
        if n == 0 {
            return Ok(());
        }
        let (in_per, out_per) = if gradients { (12u64, 4u64) } else { (3, 1) };
        let mut ws = match if gradients {
            self.eval_grad.take()
        } else {
            self.eval.take()
        } {
            Some(ws) => ws,
            None => self.alloc_eval(gpu, self.chunk_capacity(gpu, gradients), gradients)?,
        };
        let result = (|| {
            self.refresh_pack(enc);
            let mut first = 0u32;
            while first < n {
                let m = (n - first).min(ws.capacity);
                if ws.built_for != Some(m) {
                    ws.launches = self.eval_launches(gpu, &ws, m, &ws.input, &ws.values)?;
                    ws.built_for = Some(m);
                }
                let (i0, o0) = (u64::from(first) * 4, u64::from(first) * 4);
                enc.copy_buffer_to_buffer(
                    input,
                    i0 * in_per,
                    &ws.input,
                    0,
                    u64::from(m) * 4 * in_per,
                );
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("siren query"),
                        timestamp_writes: None,
                    });
                    for l in &ws.launches {
                        l.record(&mut pass);
                    }
                }
                enc.copy_buffer_to_buffer(
                    &ws.values,
                    0,
                    output,
                    o0 * out_per,
                    u64::from(m) * 4 * out_per,
                );
                first += m;
            }
            Ok::<(), GpuError>(())
        })();
        if gradients {
            self.eval_grad = Some(ws);
        } else {
            self.eval = Some(ws);
        }
        Ok(result?)
    }

    /// The launches of an evaluation of `n` points straight from `input` into `output` (the
    /// layouts of [`SirenGpu::record_eval`]), without its copies through the workspace; the
    /// workspace's activations are their scratch. `None` when `n` exceeds one launch's
    /// capacity: use `record_eval`, which splits. Record them with
    /// [`SirenGpu::record_launches`]. They stay valid while this network lives and its kernels
    /// are not changed.
    pub(crate) fn bound_eval(
        &mut self,
        gpu: &GpuContext,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        n: u32,
        gradients: bool,
    ) -> Result<Option<Vec<Launch>>, SirenGpuError> {
        let capacity = self.chunk_capacity(gpu, gradients);
        if n == 0 || n > capacity {
            return Ok(None);
        }
        let slot = if gradients {
            &mut self.eval_grad
        } else {
            &mut self.eval
        };
        let ws = match slot.take() {
            Some(ws) => ws,
            None => self.alloc_eval(gpu, capacity, gradients)?,
        };
        let launches = self.eval_launches(gpu, &ws, n, input, output);
        if gradients {
            self.eval_grad = Some(ws);
        } else {
            self.eval = Some(ws);
        }
        Ok(Some(launches?))
    }

    /// Whether an inference of `n` points (`tangents`: with gradients) runs on the
    /// cooperative-matrix kernels where they are set up: every one with
    /// [`LayerKernels::CoopF16`], batches of values from [`SirenGpu::set_coop_min_points`] on
    /// with `Auto`.
    fn runs_coop(&self, n: u32, tangents: bool) -> bool {
        self.kernels == LayerKernels::CoopF16 || self.auto_coop_from(tangents) <= n
    }

    /// The one-dispatch kernel over `n` points where this network runs one for them: the
    /// cooperative-matrix kernel if `coop` and it is set up, else the tiled fused kernel where
    /// [`SirenGpu::runs_fused`]. Its input and output are those of
    /// [`TiledKernels::fused_forward`] (`query`: the map into the cube of a caller's points).
    #[allow(clippy::too_many_arguments)]
    fn one_dispatch(
        &self,
        gpu: &GpuContext,
        n: u32,
        tangents: bool,
        query: Option<glam::Vec4>,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        coop: bool,
    ) -> Result<Option<OneDispatch>, GpuError> {
        let cfg = &self.config;
        let rows = if tangents { 4 * n } else { n };
        if let Some(c) = self.coop.as_ref().filter(|_| coop) {
            return Ok(Some(c.forward(
                gpu,
                cfg,
                rows,
                tangents,
                query,
                input,
                &self.params,
                output,
            )));
        }
        let layout = TiledKernels::fused_layout(gpu, cfg, self.fused_row_blocks);
        match (self.tiled.as_ref(), layout) {
            (Some(t), Some(layout)) if self.runs_fused(gpu, n) => Ok(Some(t.fused_forward(
                gpu,
                cfg,
                layout,
                rows,
                tangents,
                query,
                input,
                &self.params,
                output,
            )?)),
            _ => Ok(None),
        }
    }

    /// This network's query kernel in one dispatch, bound to a caller's `points` (vec4, mesh
    /// coordinates) and `results` (the distance per point, or with `normals` the distance and
    /// the unit normal) for up to `capacity` points mapped into the cube by `map` (the centre
    /// in xyz, the scale in w): NGLOD's serving path, for the kernel families that run an
    /// inference in one dispatch. `None` for the others, whose queries go through the two ends
    /// of `query.wgsl` around [`SirenGpu::bound_eval`]'s launches. Record it after
    /// [`SirenGpu::refresh_pack`].
    pub(crate) fn query_launch(
        &self,
        gpu: &GpuContext,
        points: &wgpu::Buffer,
        results: &wgpu::Buffer,
        capacity: u32,
        normals: bool,
        map: glam::Vec4,
    ) -> Result<Option<QueryLaunch>, SirenGpuError> {
        let rows_per_point = if normals { 4 } else { 1 };
        let written = capacity * rows_per_point;
        let always_coop = self.kernels == LayerKernels::CoopF16;
        let one =
            |coop| self.one_dispatch(gpu, capacity, normals, Some(map), points, results, coop);
        let Some(kernel) = one(always_coop)? else {
            return Ok(None);
        };
        // Auto's large batches: a second kernel bound to the same buffers, picked per query.
        let min = self.auto_coop_from(normals);
        let large = if !always_coop && self.coop.is_some() && min <= capacity {
            one(true)?.map(|kernel| (min, BoundDispatch { kernel, written }))
        } else {
            None
        };
        Ok(Some(QueryLaunch {
            kernel: BoundDispatch { kernel, written },
            large,
            rows_per_point,
        }))
    }

    /// Records `launches` (from [`SirenGpu::bound_eval`]) into `enc` in one compute pass, after
    /// the weight packing they need.
    pub(crate) fn record_launches(&self, enc: &mut wgpu::CommandEncoder, launches: &[Launch]) {
        self.refresh_pack(enc);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("siren query"),
            timestamp_writes: None,
        });
        for l in launches {
            l.record(&mut pass);
        }
    }

    fn run_eval(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
        tangents: bool,
        timer: Option<&GpuTimer>,
    ) -> Result<(Vec<f32>, Option<u64>), SirenGpuError> {
        let per = if tangents { 4 } else { 1 };
        let mut out = Vec::with_capacity(points.len() * per);
        let mut gpu_ns = timer.map(|_| 0u64);
        if points.is_empty() {
            return Ok((out, gpu_ns));
        }
        let mut ws = match if tangents {
            self.eval_grad.take()
        } else {
            self.eval.take()
        } {
            Some(ws) => ws,
            None => self.alloc_eval(gpu, self.chunk_capacity(gpu, tangents), tangents)?,
        };
        let result = (|| {
            for chunk in points.chunks(ws.capacity as usize) {
                let n = chunk.len() as u32;
                if ws.built_for != Some(n) {
                    ws.launches = self.eval_launches(gpu, &ws, n, &ws.input, &ws.values)?;
                    ws.built_for = Some(n);
                }
                let input: Vec<f32> = if tangents {
                    chunk.iter().flat_map(|p| stream_rows(*p)).collect()
                } else {
                    chunk.iter().flat_map(|p| p.to_array()).collect()
                };
                gpu.write(&ws.input, &input)?;
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                self.refresh_pack(&mut enc);
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("siren eval"),
                        timestamp_writes: timer.map(|t| t.writes(true, true)),
                    });
                    for l in &ws.launches {
                        l.record(&mut pass);
                    }
                }
                if let Some(t) = timer {
                    t.resolve(&mut enc);
                }
                gpu.queue().submit([enc.finish()]);
                if let (Some(t), Some(ns)) = (timer, gpu_ns.as_mut()) {
                    *ns += t.read_ns(gpu)?;
                }
                out.extend(gpu.read_back_range::<f32>(&ws.values, 0, u64::from(n) * per as u64)?);
            }
            Ok::<(), GpuError>(())
        })();
        if tangents {
            self.eval_grad = Some(ws);
        } else {
            self.eval = Some(ws);
        }
        result?;
        Ok((out, gpu_ns))
    }

    fn alloc_eval(
        &self,
        gpu: &GpuContext,
        capacity: u32,
        tangents: bool,
    ) -> Result<EvalWorkspace, SirenGpuError> {
        let per = if tangents { 4u64 } else { 1 };
        let rows = u64::from(capacity) * per;
        let width = self.config.width as u64;
        Ok(EvalWorkspace {
            capacity,
            tangents,
            input: gpu.storage_zeroed("siren eval input", rows * 3 * 4)?,
            act: [
                gpu.storage_zeroed("siren eval act 0", rows * width * 4)?,
                gpu.storage_zeroed("siren eval act 1", rows * width * 4)?,
            ],
            z: gpu.storage_zeroed("siren eval z", if tangents { rows * width * 4 } else { 4 })?,
            values: gpu.storage_zeroed("siren eval values", rows * 4)?,
            launches: Vec::new(),
            built_for: None,
        })
    }

    /// The launches of a forward pass over `n` points from `input` (three floats per point, or
    /// with tangents the twelve of [`stream_rows`]) into `values` (Φ per point, or Φ and ∇Φ),
    /// with `ws`'s activation buffers as scratch (sized for at least `n` points). Recorded after
    /// [`SirenGpu::record_pack`], in one compute pass, in order.
    fn eval_launches(
        &self,
        gpu: &GpuContext,
        ws: &EvalWorkspace,
        n: u32,
        input: &wgpu::Buffer,
        values: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let cfg = &self.config;
        let rows = if ws.tangents { 4 * n } else { n };
        let coop = self.runs_coop(n, ws.tangents);
        if let Some(one) = self.one_dispatch(gpu, n, ws.tangents, None, input, values, coop)? {
            return Ok(vec![one.launch]);
        }
        let p = &self.pipelines;
        let mut launches = Vec::new();
        for l in 0..cfg.hidden_layers {
            let src = if l == 0 { input } else { &ws.act[(l - 1) % 2] };
            let dst = &ws.act[l % 2];
            if let Some(d) = self.dense_for(l) {
                let omega = cfg.omega0;
                let (epilogue, out) = if ws.tangents {
                    (Epilogue::SineWithTangents { omega, act: dst }, &ws.z)
                } else {
                    (Epilogue::Sine { omega }, dst)
                };
                launches.extend(d.forward(gpu, l, rows, epilogue, src, &self.params, out)?);
            } else if let Some(t) = &self.tiled {
                let u = gemm_forward(&self.layers[l], rows, false, cfg.omega0);
                let omega = cfg.omega0;
                launches.push(if ws.tangents {
                    let epilogue = TiledEpilogue::SineWithTangents { omega, act: dst };
                    t.gemm(gpu, &u, epilogue, src, &self.params, &ws.z)
                } else {
                    t.gemm(
                        gpu,
                        &u,
                        TiledEpilogue::Sine { omega },
                        src,
                        &self.params,
                        dst,
                    )
                });
            } else if ws.tangents {
                let u = gemm_forward(&self.layers[l], rows, false, cfg.omega0);
                launches.push(self.gemm_launch(gpu, &u, src, &self.params, &ws.z));
                launches.push(self.sine_forward_launch(gpu, l, n, &ws.z, dst));
            } else {
                let u = gemm_forward(&self.layers[l], rows, true, cfg.omega0);
                launches.push(self.gemm_launch(gpu, &u, src, &self.params, dst));
            }
        }
        let last = self.layers.last().expect("at least one layer");
        let head = HeadUniforms {
            mode: ws.tangents as u32,
            n_points: n,
            width: cfg.width as u32,
            w_off: last.weight as u32,
            b_off: last.bias as u32,
            omega: cfg.omega0,
            ..Default::default()
        };
        let hu = gpu.uniform("siren head uniforms", &head);
        launches.push(Launch::flat(
            gpu,
            &p.head_eval,
            "siren eval head",
            &[
                entry(0, &hu),
                entry(1, &ws.act[(cfg.hidden_layers - 1) % 2]),
                entry(2, &self.params),
                entry(4, values),
            ],
            n,
        ));
        Ok(launches)
    }

    pub(crate) fn gemm_launch(
        &self,
        gpu: &GpuContext,
        u: &GemmUniforms,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Launch {
        let u = &u.with_load_styles();
        let ub = gpu.uniform("siren gemm uniforms", u);
        Launch::new(
            gpu,
            &self.pipelines.gemm,
            "siren gemm",
            &[
                entry(0, &ub),
                entry(1, a),
                entry(2, b),
                entry(3, &self.params),
                entry(4, out),
                entry(5, a),
                entry(6, b),
            ],
            gemm_groups(gpu, u),
        )
    }

    fn elementwise_uniforms(&self, gpu: &GpuContext, l: usize, n: u32) -> wgpu::Buffer {
        gpu.uniform(
            "siren elementwise uniforms",
            &ElementwiseUniforms {
                n_points: n,
                width: self.config.width as u32,
                bias_off: self.layers[l].bias as u32,
                omega: self.config.omega0,
                ..Default::default()
            },
        )
    }

    pub(crate) fn sine_forward_launch(
        &self,
        gpu: &GpuContext,
        l: usize,
        n: u32,
        z: &wgpu::Buffer,
        act: &wgpu::Buffer,
    ) -> Launch {
        let u = self.elementwise_uniforms(gpu, l, n);
        Launch::flat(
            gpu,
            &self.pipelines.sine_forward,
            "siren sine forward",
            &[
                entry(10, &u),
                entry(11, &self.params),
                entry(12, z),
                entry(13, act),
            ],
            n * self.config.width as u32,
        )
    }

    pub(crate) fn sine_backward_launch(
        &self,
        gpu: &GpuContext,
        l: usize,
        n: u32,
        grad: &wgpu::Buffer,
        z: &wgpu::Buffer,
    ) -> Launch {
        let u = self.elementwise_uniforms(gpu, l, n);
        Launch::flat(
            gpu,
            &self.pipelines.sine_backward,
            "siren sine backward",
            &[entry(10, &u), entry(14, grad), entry(15, z)],
            n * self.config.width as u32,
        )
    }

    /// The loss of one batch (the first `normals.len()` points on the surface with those
    /// normals, the rest off the surface, the first `sides.len()` of those on a known side:
    /// +1 outside, −1 inside, 0 unknown) and its gradient with respect to every parameter,
    /// computed by the training kernels without an optimiser step. For tests and diagnostics:
    /// it allocates the training buffers on each call.
    pub fn loss_and_gradient(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
        normals: &[Vec3],
        sides: &[f32],
        weights: &super::LossWeights,
    ) -> Result<(super::LossTerms, Vec<f32>), SirenGpuError> {
        let n = points.len().max(1) as u32;
        let n_surface = normals.len().min(points.len()) as u32;
        let passes = TrainPasses::new(gpu, self, n, n_surface, weights)?;
        let streams: Vec<f32> = points.iter().flat_map(|p| stream_rows(*p)).collect();
        gpu.write(&passes.x_streams, &streams)?;
        let off = points.len() - n_surface as usize;
        let flat_n: Vec<f32> = normals
            .iter()
            .take(n_surface as usize)
            .flat_map(|v| v.to_array())
            .chain(sides.iter().take(off).flat_map(|&s| [s, 0.0, 0.0]))
            .collect();
        gpu.write(&passes.normals, &flat_n)?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        self.record_pack(&mut enc);
        enc.clear_buffer(&self.grads, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("siren loss and gradient"),
                timestamp_writes: None,
            });
            passes.record(&mut pass);
        }
        gpu.queue().submit([enc.finish()]);
        if std::env::var_os("SIREN_PROFILE").is_some() {
            // Diagnostics: time every launch on its own.
            gpu.wait()?;
            for (i, l) in passes.launches.iter().enumerate() {
                let t = std::time::Instant::now();
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    l.record(&mut pass);
                }
                gpu.queue().submit([enc.finish()]);
                gpu.wait()?;
                eprintln!(
                    "launch {i} {} {:?}: {:?}",
                    l.label(),
                    l.groups(),
                    t.elapsed()
                );
            }
        }
        let partial: Vec<f32> =
            gpu.read_back_range(&passes.loss_partial, 0, u64::from(passes.loss_groups) * 4)?;
        let mut t = [0.0f32; 4];
        for row in partial.chunks_exact(4) {
            for k in 0..4 {
                t[k] += row[k];
            }
        }
        let terms = super::LossTerms {
            surface: t[0],
            off_surface: t[1],
            normal: t[2],
            eikonal: t[3],
        };
        Ok((terms, self.read_grads(gpu)?))
    }
}

/// A point's four input rows: the point, then the unit tangents e_x, e_y, e_z.
fn stream_rows(p: Vec3) -> [f32; 12] {
    [p.x, p.y, p.z, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
}

/// The launches of one training step's loss and gradient (from [`ror::build`] or
/// [`tangents::build`]), the buffers they use, and the loss partials' count.
pub(crate) struct StepLaunches {
    pub(crate) launches: Vec<Launch>,
    pub(crate) keep: Vec<wgpu::Buffer>,
    pub(crate) loss_groups: u32,
}

/// The buffers and recorded launches of one training step's forward and backward passes for a
/// batch of `n` points whose input streams the caller writes into [`TrainPasses::x_streams`].
#[derive(Debug)]
pub(crate) struct TrainPasses {
    pub(crate) n: u32,
    n_surface: u32,
    pub(crate) x_streams: wgpu::Buffer,
    pub(crate) normals: wgpu::Buffer,
    pub(crate) loss_partial: wgpu::Buffer,
    pub(crate) loss_groups: u32,
    launches: Vec<Launch>,
    _keep: Vec<wgpu::Buffer>,
}

impl TrainPasses {
    /// Everything for a batch of `n` points, `n_surface` of them on the surface.
    pub(crate) fn new(
        gpu: &GpuContext,
        net: &SirenGpu,
        n: u32,
        n_surface: u32,
        weights: &super::LossWeights,
    ) -> Result<Self, SirenGpuError> {
        let x_streams = gpu.storage_zeroed("siren x streams", u64::from(4 * n) * 3 * 4)?;
        // Every point's: the normal on the surface, (side, 0, 0) off it.
        let normals = gpu.storage_zeroed("siren batch normals", u64::from(n) * 3 * 4)?;
        // A sum per workgroup of the head, whichever step: the reverse-over-reverse head's
        // workgroups take the fewest points, in its GPU layout (passes rebuilt on these
        // buffers may have the other layout).
        let head_groups = n.div_ceil(WG.min(ror::HEAD_WG / ror::GPU_HEAD_LANES));
        let loss_partial = gpu.storage_zeroed("siren loss partial", u64::from(head_groups) * 16)?;
        Self::with_io(
            gpu,
            net,
            n,
            n_surface,
            weights,
            x_streams,
            normals,
            loss_partial,
        )
    }

    /// The passes rebuilt for `net`'s current kernels, on the same input and loss buffers (so
    /// launches bound to those stay valid).
    pub(crate) fn rebuilt(
        &self,
        gpu: &GpuContext,
        net: &SirenGpu,
        weights: &super::LossWeights,
    ) -> Result<Self, SirenGpuError> {
        Self::with_io(
            gpu,
            net,
            self.n,
            self.n_surface,
            weights,
            self.x_streams.clone(),
            self.normals.clone(),
            self.loss_partial.clone(),
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn with_io(
        gpu: &GpuContext,
        net: &SirenGpu,
        n: u32,
        n_surface: u32,
        weights: &super::LossWeights,
        x_streams: wgpu::Buffer,
        normals: wgpu::Buffer,
        loss_partial: wgpu::Buffer,
    ) -> Result<Self, SirenGpuError> {
        if net.runs_reverse_over_reverse() {
            let r = ror::build(
                gpu,
                net,
                n,
                n_surface,
                weights,
                &x_streams,
                &normals,
                &loss_partial,
            )?;
            return Ok(TrainPasses {
                n,
                n_surface,
                x_streams,
                normals,
                loss_partial,
                loss_groups: r.loss_groups,
                launches: r.launches,
                _keep: r.keep,
            });
        }
        let t = tangents::build(
            gpu,
            net,
            n,
            n_surface,
            weights,
            &x_streams,
            &normals,
            &loss_partial,
        )?;
        Ok(TrainPasses {
            n,
            n_surface,
            x_streams,
            normals,
            loss_partial,
            loss_groups: t.loss_groups,
            launches: t.launches,
            _keep: t.keep,
        })
    }

    /// Records forward, loss and backward (accumulating into the gradient buffer).
    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        for l in &self.launches {
            l.record(pass);
        }
    }

    /// The launches [`TrainPasses::record`] records, in order.
    pub(crate) fn launches(&self) -> &[Launch] {
        &self.launches
    }
}
