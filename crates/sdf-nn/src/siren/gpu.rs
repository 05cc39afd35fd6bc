//! Host code of the SIREN kernels: [`SirenGpu`], a network's parameters and gradients on the
//! GPU with the kernels that run it, for inference, inference with the input gradient, and the
//! loss and gradient of a training step.
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
//! point; the math and layout are in [`super::step::reverse_over_reverse`]);
//! [`SirenGpuOptions::train_step`] chooses. The launches are built by `siren/eval.rs` and
//! [`super::step`] from a borrowed view of this network (`siren/net.rs`); this module picks the
//! kernels.

use glam::Vec3;

use super::eval::{EvalSlots, EvalWorkspace, QueryLaunch, stream_rows};
use super::kernels::coop::CoopKernels;
use super::kernels::gemm::{GEMM_CPU_MAX_FAN_IN, GemmKernels, gemm_trusted_wide};
use super::kernels::head::HeadKernels;
use super::kernels::row_blocked::RowBlockedPlan;
use super::kernels::tiled::TiledKernels;
use super::kernels::{Launch, LayerKernels, OneDispatch};
use super::loss::{LossTerms, LossWeights};
use super::net::NetView;
use super::options::{DEFAULT_FUSED_MAX_POINTS, SirenGpuOptions, auto_coop_min_points};
use super::step::passes::TrainPasses;
use super::step::{StepNet, TrainStep};
use super::{LayerLayout, Siren, SirenConfig, SirenConfigError};
use crate::gpu::{GpuContext, GpuError, GpuTimer, StepLayout};

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

/// The kernel families a [`LayerKernels`] choice sets up: row-blocked, tiled, cooperative-matrix.
type Families = (
    Option<RowBlockedPlan>,
    Option<TiledKernels>,
    Option<CoopKernels>,
);

/// Whether [`TrainStep::Auto`] picks the reverse-over-reverse step on the row-blocked kernels:
/// on lavapipe it measured 529–565 ms per `small` step of 10⁴ points against 852–894 ms for
/// the tangents (docs/benchmarks, "The reverse-over-reverse training step").
const ROW_BLOCKED_AUTO_ROR: bool = true;

/// A SIREN's parameters (and gradients) on the GPU, with its kernels.
#[derive(Debug)]
pub struct SirenGpu {
    config: SirenConfig,
    layers: Vec<LayerLayout>,
    params: wgpu::Buffer,
    grads: wgpu::Buffer,
    /// The strided GEMM and sine kernels (every product the other families leave).
    gemm: GemmKernels,
    /// The output layer's kernels.
    head: HeadKernels,
    /// The inference workspaces, with the launches last built on them.
    evals: EvalSlots,
    /// The hidden layers on the row-blocked kernels, if any.
    dense: Option<RowBlockedPlan>,
    /// The tiled kernels, when they run every product.
    tiled: Option<TiledKernels>,
    /// The cooperative-matrix kernels, when they run inference of values.
    coop: Option<CoopKernels>,
    /// The parameters change only through [`SirenGpu::upload`] (a served model, see
    /// [`SirenGpu::new_frozen`]): the row-blocked kernels' packed weights are then copied when
    /// they change, not at the start of every evaluation.
    frozen: bool,
    /// The knobs, clamped ([`SirenGpuOptions::clamped`]).
    options: SirenGpuOptions,
}

impl SirenGpu {
    /// Uploads `siren`'s parameters and compiles (or fetches from the context's cache) the
    /// kernels, with the default [`SirenGpuOptions`].
    pub fn new(gpu: &GpuContext, siren: &Siren) -> Result<Self, SirenGpuError> {
        Self::with_options(gpu, siren, &SirenGpuOptions::default())
    }

    /// [`SirenGpu::new`] with `options`.
    pub fn with_options(
        gpu: &GpuContext,
        siren: &Siren,
        options: &SirenGpuOptions,
    ) -> Result<Self, SirenGpuError> {
        let options = options.clamped();
        let config = *siren.config();
        config.validate()?;
        // Padded to 16 bytes: the GEMM also reads it as vec4.
        let mut padded = siren.params().to_vec();
        padded.resize(padded.len().next_multiple_of(4), 0.0);
        let params = gpu.storage_from_slice("siren params", &padded)?;
        let grads = gpu.storage_zeroed("siren grads", padded.len() as u64 * 4)?;
        let layers = config.layers();
        let (dense, tiled, coop) = Self::families(gpu, &options, &config, &layers, &params)?;
        Ok(SirenGpu {
            config,
            layers,
            params,
            grads,
            gemm: GemmKernels::new(gpu)?,
            head: HeadKernels::new(gpu)?,
            evals: EvalSlots::default(),
            dense,
            tiled,
            coop,
            frozen: false,
            options,
        })
    }

    /// [`SirenGpu::with_options`] for a network whose parameters nobody writes on the GPU (no
    /// trainer, no writes through [`SirenGpu::params_buffer`]): [`crate::NeuralSdf`]'s. Its
    /// evaluations skip [`SirenGpu::record_pack`]; [`SirenGpu::upload`] and
    /// [`SirenGpu::set_options`] pack. `coop_min_points`: `None` takes a served network's
    /// default, [`auto_coop_min_points`], over `options`' own.
    pub(crate) fn new_frozen(
        gpu: &GpuContext,
        siren: &Siren,
        options: &SirenGpuOptions,
        coop_min_points: Option<Option<u32>>,
    ) -> Result<Self, SirenGpuError> {
        let options = SirenGpuOptions {
            // What `Auto` runs a served network's large batches on.
            coop_min_points: coop_min_points
                .unwrap_or_else(|| auto_coop_min_points(gpu.is_cpu(), siren.config())),
            ..*options
        };
        let mut net = Self::with_options(gpu, siren, &options)?;
        net.frozen = true;
        net.pack_now(gpu);
        Ok(net)
    }

    /// The row-blocked, tiled and cooperative-matrix kernels that `options.kernels` asks for on
    /// `gpu`, each where it applies.
    fn families(
        gpu: &GpuContext,
        options: &SirenGpuOptions,
        config: &SirenConfig,
        layers: &[LayerLayout],
        params: &wgpu::Buffer,
    ) -> Result<Families, SirenGpuError> {
        let kernels = options.kernels;
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
            TiledKernels::new(gpu, config, params, options.tiled_block)?
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
        let auto_coop = kernels == LayerKernels::Auto && options.coop_min_points.is_some();
        let coop = if kernels == LayerKernels::CoopF16 || auto_coop {
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

    /// The knobs this network runs with (clamped into their ranges).
    pub fn options(&self) -> &SirenGpuOptions {
        &self.options
    }

    /// Changes the knobs of this live network: the kernels are set up again where `options`
    /// changes which run, and inference rebuilds its launches. A [`super::SirenTrainer`] must
    /// rebuild its passes: use [`super::SirenTrainer::set_net_options`]. On an error the
    /// network keeps its options.
    pub fn set_options(
        &mut self,
        gpu: &GpuContext,
        options: &SirenGpuOptions,
    ) -> Result<(), SirenGpuError> {
        let options = options.clamped();
        let old = self.options;
        // The training step's knobs change neither the kernels nor inference.
        let eval_knobs = |o: &SirenGpuOptions| SirenGpuOptions {
            train_step: TrainStep::Auto,
            step_layout: None,
            ..*o
        };
        let families = (
            options.kernels,
            options.tiled_block,
            options.coop_min_points,
        ) != (old.kernels, old.tiled_block, old.coop_min_points);
        if families {
            (self.dense, self.tiled, self.coop) =
                Self::families(gpu, &options, &self.config, &self.layers, &self.params)?;
        }
        self.options = options;
        if eval_knobs(&options) != eval_knobs(&old) {
            self.evals.clear();
        }
        if families && self.frozen {
            self.pack_now(gpu);
        }
        Ok(())
    }

    /// Whether training steps run reverse over reverse with the current kernels and
    /// [`TrainStep`] (otherwise they carry tangents).
    pub fn runs_reverse_over_reverse(&self) -> bool {
        let tiled = self.tiled.is_some();
        let dense = self.view().dense_ror_plan().is_some();
        match self.options.train_step {
            TrainStep::Tangents => false,
            TrainStep::ReverseOverReverse => tiled || dense,
            TrainStep::Auto => tiled || (ROW_BLOCKED_AUTO_ROR && dense),
        }
    }

    /// Whether the reverse-over-reverse step runs its GPU layout on `gpu`
    /// ([`SirenGpuOptions::step_layout`]).
    pub fn gpu_step_layout(&self, gpu: &GpuContext) -> bool {
        self.options
            .step_layout
            .or(gpu.options().step_layout)
            .map_or(!gpu.is_cpu(), |l| l == StepLayout::Gpu)
    }

    /// The network as the launch builders see it.
    pub(crate) fn view(&self) -> NetView<'_> {
        NetView {
            config: self.config,
            layers: &self.layers,
            params: &self.params,
            grads: &self.grads,
            gemm: &self.gemm,
            head: &self.head,
            dense: self.dense.as_ref(),
            tiled: self.tiled.as_ref(),
        }
    }

    /// The network as the training step's builders see it on `gpu`.
    pub(crate) fn step_net(&self, gpu: &GpuContext) -> StepNet<'_> {
        StepNet {
            net: self.view(),
            reverse_over_reverse: self.runs_reverse_over_reverse(),
            gpu_layout: self.gpu_step_layout(gpu),
        }
    }

    /// How many hidden layers run on the row-blocked kernels (0 with the GEMM).
    pub fn row_blocked_layers(&self) -> usize {
        self.dense.as_ref().map_or(0, |d| {
            (0..self.layers.len()).filter(|&l| d.covers(l)).count()
        })
    }

    /// Whether the tiled kernels run every product (they need 8 KiB of workgroup memory with
    /// 4 × 4 blocks, 16 KiB with 8 × 8, and
    /// 256 invocations per workgroup; without them the GEMM runs instead).
    pub fn runs_tiled(&self) -> bool {
        self.tiled.is_some()
    }

    /// The register blocks per invocation the fused kernel runs with on `gpu` (`None` where the
    /// network does not fit it; see [`SirenGpuOptions::fused_row_blocks`]).
    pub fn fused_row_blocks(&self, gpu: &GpuContext) -> Option<u32> {
        TiledKernels::fused_layout(gpu, &self.config, self.options.fused_row_blocks)
            .map(|l| l.row_blocks)
    }

    /// The side of the cooperative-matrix tiles that run inference of values, if they are set
    /// up: with [`LayerKernels::CoopF16`] where the device and the network allow them (every
    /// batch of values), and with [`LayerKernels::Auto`] where
    /// [`SirenGpuOptions::coop_min_points`] sets a batch size (a served network's default,
    /// [`auto_coop_min_points`]: batches of values of at least
    /// [`super::COOP_AUTO_MIN_POINTS`] on GPUs).
    pub fn coop_tile(&self) -> Option<u32> {
        self.coop.as_ref().map(CoopKernels::tile)
    }

    /// The smallest batch that `Auto` runs on the cooperative-matrix kernels (`u32::MAX`:
    /// none): values only.
    fn auto_coop_from(&self, tangents: bool) -> u32 {
        match self.options.coop_min_points {
            Some(m) if self.options.kernels == LayerKernels::Auto && !tangents => m,
            _ => u32::MAX,
        }
    }

    /// Whether an inference launch of `n` points runs on the fused all-layer kernel.
    pub fn runs_fused(&self, gpu: &GpuContext, n: u32) -> bool {
        let max = self.options.fused_max_points.unwrap_or(if gpu.is_cpu() {
            DEFAULT_FUSED_MAX_POINTS
        } else {
            u32::MAX
        });
        self.tiled.is_some()
            && n <= max
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
    /// buffer, and by [`SirenGpuOptions::max_points_per_launch`] to keep memory modest.
    fn chunk_capacity(&self, gpu: &GpuContext, tangents: bool) -> u32 {
        let limit = gpu.limits().max_storage_buffer_binding_size;
        let per_point = self.config.width as u64 * 4 * if tangents { 4 } else { 1 };
        let max = u64::from(self.options.max_points_per_launch);
        let cap = (limit / per_point).clamp(64, max);
        (cap as u32 / 64) * 64
    }

    /// The inference workspace of `tangents`, taken out of its slot (put it back with
    /// [`EvalSlots::put`]), allocated for `capacity` points where there is none.
    fn take_workspace(
        &mut self,
        gpu: &GpuContext,
        capacity: u32,
        tangents: bool,
    ) -> Result<EvalWorkspace, GpuError> {
        match self.evals.take(tangents) {
            Some(ws) => Ok(ws),
            None => EvalWorkspace::new(gpu, self.config.width, capacity, tangents),
        }
    }

    /// The launches of a forward pass over `n` points from `input` into `values`, on `ws`'s
    /// activations: one dispatch where this network runs one for them, else layer by layer
    /// ([`EvalWorkspace::layer_launches`]). Recorded after [`SirenGpu::record_pack`], in one
    /// compute pass, in order.
    fn eval_launches(
        &self,
        gpu: &GpuContext,
        ws: &EvalWorkspace,
        n: u32,
        input: &wgpu::Buffer,
        values: &wgpu::Buffer,
    ) -> Result<Vec<Launch>, GpuError> {
        let coop = self.runs_coop(n, ws.tangents);
        if let Some(one) = self.one_dispatch(gpu, n, ws.tangents, None, input, values, coop)? {
            return Ok(vec![one.launch]);
        }
        ws.layer_launches(gpu, &self.view(), n, input, values)
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
        let capacity = self.chunk_capacity(gpu, gradients);
        let mut ws = self.take_workspace(gpu, capacity, gradients)?;
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
        self.evals.put(ws);
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
        let ws = self.take_workspace(gpu, capacity, gradients)?;
        let launches = self.eval_launches(gpu, &ws, n, input, output);
        self.evals.put(ws);
        Ok(Some(launches?))
    }

    /// Whether an inference of `n` points (`tangents`: with gradients) runs on the
    /// cooperative-matrix kernels where they are set up: every one with
    /// [`LayerKernels::CoopF16`], batches of values from [`SirenGpuOptions::coop_min_points`]
    /// on with `Auto`.
    fn runs_coop(&self, n: u32, tangents: bool) -> bool {
        self.options.kernels == LayerKernels::CoopF16 || self.auto_coop_from(tangents) <= n
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
        let layout = TiledKernels::fused_layout(gpu, cfg, self.options.fused_row_blocks);
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
        let always_coop = self.options.kernels == LayerKernels::CoopF16;
        let one =
            |coop| self.one_dispatch(gpu, capacity, normals, Some(map), points, results, coop);
        let Some(kernel) = one(always_coop)? else {
            return Ok(None);
        };
        // Auto's large batches: a second kernel bound to the same buffers, picked per query.
        let min = self.auto_coop_from(normals);
        let large = if !always_coop && self.coop.is_some() && min <= capacity {
            one(true)?.map(|kernel| (min, kernel))
        } else {
            None
        };
        Ok(Some(QueryLaunch::new(
            kernel,
            large,
            capacity,
            rows_per_point,
        )))
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
        let capacity = self.chunk_capacity(gpu, tangents);
        let mut ws = self.take_workspace(gpu, capacity, tangents)?;
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
        self.evals.put(ws);
        result?;
        Ok((out, gpu_ns))
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
        weights: &LossWeights,
    ) -> Result<(LossTerms, Vec<f32>), SirenGpuError> {
        let n = points.len().max(1) as u32;
        let n_surface = normals.len().min(points.len()) as u32;
        let passes = TrainPasses::new(gpu, &self.step_net(gpu), n, n_surface, weights)?;
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
        let partial: Vec<f32> =
            gpu.read_back_range(&passes.loss_partial, 0, u64::from(passes.loss_groups) * 4)?;
        let mut t = [0.0f32; 4];
        for row in partial.chunks_exact(4) {
            for k in 0..4 {
                t[k] += row[k];
            }
        }
        let terms = LossTerms {
            surface: t[0],
            off_surface: t[1],
            normal: t[2],
            eikonal: t[3],
        };
        Ok((terms, self.read_grads(gpu)?))
    }
}
