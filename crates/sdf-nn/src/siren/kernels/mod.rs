//! SIREN's kernel families, one module each with its own pipelines: [`row_blocked`] (CPU
//! adapters), [`tiled`] (GPUs), [`coop`] (f16 cooperative matrices) and the strided GEMM that
//! the first two fall back on, [`gemm`] (its shapes in [`products`]); every family ends in the
//! output layer's kernels of [`head`].
//! [`LayerKernels`] is the one policy that picks a family from the adapter. Every family records
//! its work as [`Launch`]es.

use crate::gpu::GpuContext;

pub(crate) mod coop;
pub(crate) mod gemm;
pub(crate) mod head;
pub(crate) mod products;
pub(crate) mod row_blocked;
pub(crate) mod tiled;

/// Which kernels run SIREN's hidden layers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LayerKernels {
    /// Row-blocked kernels on CPU adapters (lavapipe), where they measured ~20x faster than
    /// the GEMM; the tiled kernels on every other adapter (designed for GPUs: the row-blocked
    /// and GEMM layouts keep per-invocation arrays that live in slow local memory there).
    /// A served network ([`crate::NeuralSdf`]) at least
    /// [`COOP_AUTO_MIN_WIDTH`](crate::siren::COOP_AUTO_MIN_WIDTH) wide on a GPU with f16
    /// cooperative matrices runs batches of values of at least
    /// [`COOP_AUTO_MIN_POINTS`](crate::siren::COOP_AUTO_MIN_POINTS) on
    /// [`LayerKernels::CoopF16`]'s kernel (on an H100 0.65× the f32 kernel's time at 50 000
    /// points; its values within a few 1e-5 of f64 on random networks, 2e-4 on a trained one,
    /// see the `coop` tests); smaller batches, normals and training stay in f32.
    #[default]
    Auto,
    /// The row-blocked kernels of `siren_dense.wgsl` for every layer that qualifies.
    RowBlocked,
    /// The strided GEMM of `siren_gemm.wgsl` everywhere.
    Gemm,
    /// The tiled kernels of `siren_tiled_layer.wgsl` (workgroup-memory tiles, 4 × 4 register
    /// blocks, fused sine epilogues) for every product, and `siren_tiled_fused.wgsl` for
    /// inference batches that fit it.
    Tiled,
    /// Inference (values, and gradients as tangent rows) on f16 cooperative matrices with f32
    /// accumulators (tensor cores; `siren_coop.wgsl`, every layer in one dispatch), where the
    /// device has them and the network fits; training, and devices or networks they do not
    /// fit, on [`LayerKernels::Tiled`]. Every batch of values runs on it ([`LayerKernels::Auto`]
    /// only large ones, in served networks): its f16 rounding costs accuracy (see the tests).
    CoopF16,
}

impl LayerKernels {
    /// Every family, in the order of [`LayerKernels::name`]'s names.
    pub const ALL: [LayerKernels; 5] = [
        LayerKernels::Auto,
        LayerKernels::RowBlocked,
        LayerKernels::Gemm,
        LayerKernels::Tiled,
        LayerKernels::CoopF16,
    ];

    /// The name the command-line flags and bench variables use: `auto`, `row-blocked`,
    /// `gemm`, `tiled` or `coop`.
    pub fn name(self) -> &'static str {
        match self {
            LayerKernels::Auto => "auto",
            LayerKernels::RowBlocked => "row-blocked",
            LayerKernels::Gemm => "gemm",
            LayerKernels::Tiled => "tiled",
            LayerKernels::CoopF16 => "coop",
        }
    }

    /// Whether the row-blocked kernels are used on `gpu`.
    pub(crate) fn row_blocked(self, gpu: &GpuContext) -> bool {
        match self {
            LayerKernels::Auto => gpu.is_cpu(),
            LayerKernels::RowBlocked => true,
            LayerKernels::Gemm | LayerKernels::Tiled | LayerKernels::CoopF16 => false,
        }
    }

    /// Whether the tiled kernels are used on `gpu`.
    pub(crate) fn tiled(self, gpu: &GpuContext) -> bool {
        match self {
            LayerKernels::Auto => !gpu.is_cpu(),
            LayerKernels::Tiled | LayerKernels::CoopF16 => true,
            LayerKernels::RowBlocked | LayerKernels::Gemm => false,
        }
    }
}

impl std::str::FromStr for LayerKernels {
    type Err = String;

    /// A [`LayerKernels::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        by_name(s, &Self::ALL, Self::name, "kernels")
    }
}

/// The one of `all` whose `name` is `s`, or an error that lists the names (`what`: what they
/// name).
fn by_name<T: Copy>(
    s: &str,
    all: &[T],
    name: fn(T) -> &'static str,
    what: &str,
) -> Result<T, String> {
    all.iter().copied().find(|&k| name(k) == s).ok_or_else(|| {
        let names: Vec<&str> = all.iter().map(|&k| name(k)).collect();
        format!("unknown {what} {s:?}: expected {}", names.join(", "))
    })
}

/// The register block of each invocation of the tiled GEMM ([`LayerKernels::Tiled`], and
/// `Auto` where it picks the tiled kernels): rows × columns of C. A workgroup's tile of C is
/// 16 × 16 of these blocks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum TiledBlock {
    /// 4 × 4 on GPUs, 8 × 8 on CPU adapters: the block measured fastest for every product of
    /// the `default` preset on each (H100: 8 × 8 took 19 % more time for 50 000 points of
    /// inference and 36 % more per training step; lavapipe: 31 % and 12 % less).
    #[default]
    Auto,
    /// 4 × 4 (a 64 × 64 tile per workgroup; 8 KiB of workgroup memory).
    Block4x4,
    /// 8 × 4 (128 × 64).
    Block8x4,
    /// 4 × 8 (64 × 128).
    Block4x8,
    /// 8 × 8 (128 × 128; 16 KiB of workgroup memory): twice the FMAs per workgroup-memory
    /// read of 4 × 4.
    Block8x8,
}

impl TiledBlock {
    /// Every choice, in the order of [`TiledBlock::name`]'s names.
    pub const ALL: [TiledBlock; 5] = [
        TiledBlock::Auto,
        TiledBlock::Block4x4,
        TiledBlock::Block8x4,
        TiledBlock::Block4x8,
        TiledBlock::Block8x8,
    ];

    /// The name the bench variables use: `auto`, `4x4`, `8x4`, `4x8` or `8x8`.
    pub fn name(self) -> &'static str {
        match self {
            TiledBlock::Auto => "auto",
            TiledBlock::Block4x4 => "4x4",
            TiledBlock::Block8x4 => "8x4",
            TiledBlock::Block4x8 => "4x8",
            TiledBlock::Block8x8 => "8x8",
        }
    }

    /// 4-row and 4-column blocks per invocation (`MB`, `NB` in the shader); `None` for
    /// [`TiledBlock::Auto`].
    pub(crate) fn blocks(self) -> Option<(u32, u32)> {
        match self {
            TiledBlock::Auto => None,
            TiledBlock::Block4x4 => Some((1, 1)),
            TiledBlock::Block8x4 => Some((2, 1)),
            TiledBlock::Block4x8 => Some((1, 2)),
            TiledBlock::Block8x8 => Some((2, 2)),
        }
    }
}

impl std::str::FromStr for TiledBlock {
    type Err = String;

    /// A [`TiledBlock::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        by_name(s, &Self::ALL, Self::name, "tiled block")
    }
}

/// Invocations per workgroup of the 1D kernels ([`Launch::flat`]), and of SIREN's per-point
/// kernels.
pub(crate) const WG: u32 = 256;

pub(crate) use crate::gpu::Launch;

impl Launch {
    /// A 1D launch of `threads` invocations in 256-wide groups, folded into 2D if needed.
    pub(crate) fn flat(
        gpu: &GpuContext,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        entries: &[wgpu::BindGroupEntry<'_>],
        threads: u32,
    ) -> Self {
        let (x, y) = gpu.dispatch_size(threads.div_ceil(WG));
        Self::new(gpu, pipeline, label, entries, (x, y, 1))
    }
}

/// A launch of a one-dispatch inference kernel (tiled fused, cooperative matrices), with its
/// uniforms, whose first field is the row count.
#[derive(Debug)]
pub(crate) struct OneDispatch {
    pub(crate) launch: Launch,
    pub(crate) uniforms: wgpu::Buffer,
    /// Rows per workgroup.
    pub(crate) group_rows: u32,
}

/// Floats from one point to the next in a one-dispatch kernel's input: a caller's vec4 points
/// for a query, else the network's rows (the point, and with tangents the three unit axes).
pub(crate) fn point_stride(query: bool, tangents: bool) -> u32 {
    match (query, tangents) {
        (true, _) => 4,
        (false, true) => 12,
        (false, false) => 3,
    }
}
