//! [`SirenGpuOptions`]: the tuning knobs of a [`super::SirenGpu`] (which kernels run, their
//! blocking, the training step), kept apart from its parameters and buffers, and the measured
//! defaults they start from. None of them changes what a network computes beyond f32 rounding
//! (the cooperative-matrix kernels' f16 aside, see [`LayerKernels::CoopF16`]).

use super::SirenConfig;
use super::kernels::{LayerKernels, TiledBlock};
use super::step::TrainStep;
use crate::gpu::StepLayout;

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

/// The default of [`SirenGpuOptions::coop_min_points`] for a served network
/// ([`crate::NeuralSdf`]) of `config` on an adapter: [`COOP_AUTO_MIN_POINTS`] on GPUs for
/// networks at least [`COOP_AUTO_MIN_WIDTH`] wide, else none (networks that train keep none).
pub fn auto_coop_min_points(cpu_adapter: bool, config: &SirenConfig) -> Option<u32> {
    (!cpu_adapter && config.width >= COOP_AUTO_MIN_WIDTH).then_some(COOP_AUTO_MIN_POINTS)
}

/// Default of [`SirenGpuOptions::fused_max_points`] on CPU adapters: the latency-bound batches
/// (the 3000 points). GPUs run every inference batch on the fused kernel: on an H100
/// it took 15–17 % less time than the per-layer kernels at 50 000 points (`default` preset,
/// two alternating runs; docs/benchmarks "NVIDIA H100"), and at 3000 it is the only way to fill
/// the GPU.
pub const DEFAULT_FUSED_MAX_POINTS: u32 = 8192;

/// Default of [`SirenGpuOptions::max_points_per_launch`].
pub const DEFAULT_MAX_POINTS_PER_LAUNCH: u32 = 65536;

/// How a [`super::SirenGpu`] runs: set at [`super::SirenGpu::with_options`], changed on a live
/// network with [`super::SirenGpu::set_options`] (a [`super::SirenTrainer`]'s with
/// [`super::SirenTrainer::set_net_options`], which also rebuilds its passes). The
/// [`Default`] is what [`super::SirenGpu::new`] runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SirenGpuOptions {
    /// The kernels of the hidden layers (default [`LayerKernels::Auto`]).
    pub kernels: LayerKernels,
    /// The tiled GEMM's register blocks (default [`TiledBlock::Auto`]; they matter only where
    /// the tiled kernels run, see [`super::SirenGpu::runs_tiled`]). Results agree to f32
    /// rounding whichever block runs.
    pub tiled_block: TiledBlock,
    /// Inference launches of at most this many points run on the tiled family's fused
    /// all-layer kernel, larger ones on its per-layer kernels; `Some(0)` disables it. `None`
    /// (the default): by adapter, every batch on GPUs, [`DEFAULT_FUSED_MAX_POINTS`] on CPU
    /// adapters. Only where the tiled kernels run and the width fits the fused kernel (a
    /// multiple of 4, at most 1024).
    pub fused_max_points: Option<u32>,
    /// Register blocks of four rows per invocation of the fused kernel, 1 to 3 (default 1;
    /// other values are clamped): more load each weight once for more rows, and fill fewer
    /// workgroups. A full block takes 16 KiB of workgroup memory at widths of 64 and more;
    /// where the device has less, the blocks get fewer rows, and only where not even 4 rows
    /// fit are there fewer blocks ([`super::SirenGpu::fused_row_blocks`] says how many run).
    pub fused_row_blocks: u32,
    /// With [`LayerKernels::Auto`], batches of values of at least this many points run on the
    /// cooperative-matrix kernels where the device has them ([`LayerKernels::CoopF16`]'s, f16
    /// with f32 accumulators); smaller ones, normals and training on the f32 kernels. `None`
    /// (the default, and what a network that trains keeps) never uses them; a served network
    /// ([`crate::NeuralSdf`]) starts at [`auto_coop_min_points`].
    pub coop_min_points: Option<u32>,
    /// Caps the points per launch (default [`DEFAULT_MAX_POINTS_PER_LAUNCH`]; clamped to 64 ..=
    /// 2²²; the device limits may lower it further). Smaller launches use less memory; larger
    /// ones amortise launch overhead.
    pub max_points_per_launch: u32,
    /// How training steps (and [`super::SirenGpu::loss_and_gradient`]) differentiate the
    /// loss's ∇ₓΦ terms (default [`TrainStep::Auto`]).
    pub train_step: TrainStep,
    /// Lays out the reverse-over-reverse step's per-point and reduction kernels for a GPU
    /// ([`StepLayout::Gpu`]) or a CPU adapter ([`StepLayout::Cpu`]). The GPU layout gives the
    /// per-point kernel (`ror_head`) 4 invocations per point, so that a subgroup's loads read
    /// 4 consecutive floats of each point's rows (one float from each of 32 rows apart took
    /// 63 µs for 10⁴ points on an H100), and sums the split partials of the layers with few
    /// outputs (the output and first layers) with a workgroup per output. Lavapipe measured
    /// both slower (the head 24.6 against 18.4 ms for the `small` preset's 10⁴ points, the two
    /// reductions 6.2 against 0.4 ms). Results agree to f32 rounding. `None` (the default):
    /// [`crate::GpuOptions::step_layout`] (`HWSDF_STEP_LAYOUT=gpu` or `cpu`, to compare the two
    /// on one GPU, e.g. in a whole fit by `train`), else by adapter
    /// ([`super::SirenGpu::gpu_step_layout`] says which runs).
    pub step_layout: Option<StepLayout>,
}

impl Default for SirenGpuOptions {
    fn default() -> Self {
        SirenGpuOptions {
            kernels: LayerKernels::Auto,
            tiled_block: TiledBlock::Auto,
            fused_max_points: None,
            fused_row_blocks: 1,
            coop_min_points: None,
            max_points_per_launch: DEFAULT_MAX_POINTS_PER_LAUNCH,
            train_step: TrainStep::Auto,
            step_layout: None,
        }
    }
}

impl SirenGpuOptions {
    /// These options with the numbers brought into their ranges (as the network stores them).
    pub(crate) fn clamped(mut self) -> Self {
        self.fused_row_blocks = self.fused_row_blocks.clamp(1, 3);
        self.max_points_per_launch = self.max_points_per_launch.clamp(64, 1 << 22);
        self
    }
}
