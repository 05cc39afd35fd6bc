//! Exact signed distance on the GPU: the trees of an [`sdf_geom::SignedDistance`] (its 4-wide
//! BVH, triangle packets and winding tree, built on the CPU by `obvhs`) uploaded once, and WGSL
//! kernels that answer its queries: closest point and distance (`shaders/closest.wgsl`), fast
//! winding number and signed distance (`shaders/winding.wgsl`).
//!
//! ```no_run
//! use sdf_geom::{SignedDistance, load_mesh, sample};
//! use sdf_nn::GpuContext;
//! use sdf_nn::ground_truth::GpuGroundTruth;
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let (mesh, _) = load_mesh("tests/data/spot.obj")?;
//! let cpu = SignedDistance::new(&mesh.normalized().0)?;
//! let gpu = GpuContext::shared()?;
//! let gt = GpuGroundTruth::new(gpu, &cpu)?; // uploads the trees
//! let points = sample::uniform_box(10_000, 1);
//! let d = gt.signed_distance(gpu, &points)?;
//! assert!((d[0] - cpu.signed_distance(points[0])).abs() < 1e-5);
//! # Ok(())
//! # }
//! ```
//!
//! # What it computes
//! The same as the CPU, query for query (see [`sdf_geom::GpuTrees`]): the nearest triangle by a
//! best-first search (nearest box first, a fixed stack of [`MAX_STACK`] entries per invocation),
//! the closest point by Ericson's regions (the CPU's routine, operation for operation), the sign
//! by the fast winding number with the CPU's β (dipole and first-order terms for far nodes, van
//! Oosterom–Strackee solid angles at near leaves, re-evaluation at 4β near 1/2), unsigned within
//! the surface tolerance. Distances agree with the CPU's to f32 rounding (the kernels may fuse
//! multiply-adds, and WGSL's `atan2` is not the CPU's polynomial), so the sign can differ only
//! where the winding number is within rounding of 1/2.
//!
//! Huge coordinates and far queries get the CPU's care, in f32: the trees are in the CPU's
//! internal coordinates (a power-of-two rescaling, applied with `ldexp`); a query farther than
//! [`sdf_geom::FAR_QUERY_RADII`] bounding radii from the centre searches from a proxy at that
//! radius and measures its distance in a frame relative to the triangle, halved and rescaled by a
//! power of two, with Ericson's decisions rewritten so that nothing cancels catastrophically
//! (where the CPU uses f64). No finite query gives a NaN; a distance above `f32::MAX` is `inf`,
//! as on the CPU. Non-finite queries give NaN. Below f32's smallest normal (about 1.2·10⁻³⁸)
//! a coordinate or a distance follows the driver: WGSL lets it flush subnormals to zero (Mesa
//! 26's lavapipe does, 22's does not), which only a mesh near 10⁻³⁷ in size would notice.
//!
//! # Speed
//! Every batch is grouped by cell on the GPU before a kernel runs (`bin.rs`: a counting sort by
//! Morton code in a grid of about a cell per point, at most 64³), so that neighbouring
//! invocations query neighbouring points and walk mostly the same nodes (a host sort in Morton
//! order made lavapipe 1.6× faster; the GPU's grouping costs the host nothing and applies to
//! points that never leave the GPU, the training draws'). Large batches go in parts through two
//! sets of buffers, so that uploads and read-backs overlap the kernels. On lavapipe (2 cores,
//! November 2026, `examples/ground_truth_bench.rs`) the kernels label 5–17 % as fast as the CPU
//! path (spot, 100 000 points: about 0.11 M signed distances per second against 1.2 M), so there
//! the CPU path is the one to use; the kernels are for real GPUs.
//!
//! # Limits
//! Each tree must fit one storage binding, and the tree's [`sdf_geom::GpuTrees::max_stack`] the
//! kernels' stack: [`GpuGroundTruth::new`] checks both ([`GpuGroundTruth::check_limits`]) and
//! returns [`GroundTruthError`] naming the limit. Queries are split into dispatches that fit the
//! device's buffer and dispatch limits.

mod agreement;
mod bin;
mod labeller;

use glam::{DVec3, Vec3};
use sdf_geom::{GpuTrees, SignedDistance};

use bin::CellOrder;
pub use labeller::{
    GroundTruthDevice, GroundTruthPath, LabelProgress, Labeller, ProgressSink, UnknownDevice,
};

use crate::gpu::{
    GpuContext, GpuError, Launch, PassProfiler, PassTime, PendingRead, entry, record_launches,
};
use crate::shaders::{self, Shader};

pub mod counter_rng;
pub mod sample;

pub use counter_rng::{Kind, SampleSpec};
pub use sample::{GpuSampler, LabelKind, LabelledDraw, SampleError, SampleTable};

/// Invocations per workgroup (`WG` in `closest.wgsl`).
const WG: u32 = 64;
/// Entries of the kernels' traversal stacks (`STACK` in `closest.wgsl`): trees whose
/// [`sdf_geom::GpuTrees::max_stack`] is larger are refused.
pub const MAX_STACK: u32 = 96;
/// Points per part of a host query: parts that fill a large GPU several times over; on a CPU
/// adapter, parts of a few seconds, for the progress (smaller ones cost lavapipe locality: each
/// part is grouped on its own); fewer where the device's storage binding is small.
fn part_size(gpu: &GpuContext, kernel: Kernel) -> usize {
    let most = if gpu.is_cpu() { 1 << 18 } else { MAX_CHUNK };
    let binding = gpu.limits().max_storage_buffer_binding_size;
    usize::try_from(binding / (4 * kernel.width().max(3)) as u64)
        .unwrap_or(most)
        .clamp(1, most)
}

/// Points per dispatch at most: bounds the per-call buffers (two sets of them, about 60 MB
/// for closest points) and each dispatch's length. A million: an H100 holds 270 000
/// invocations at once, and a part should fill it several times over.
const MAX_CHUNK: usize = 1 << 20;

/// The kernels' uniform (`Params` in `closest.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    n_points: u32,
    exponent: i32,
    _pad0: u32,
    _pad1: u32,
    center_half: [f32; 3],
    far_half: f32,
    center: [f32; 3],
    far: f32,
    beta: f32,
    refine_band: f32,
    surface_eps: f32,
    inside: f32,
}

/// Errors of [`GpuGroundTruth`].
#[derive(Debug, thiserror::Error)]
pub enum GroundTruthError {
    /// One of the mesh's trees is larger than a storage binding of the device.
    #[error(
        "the mesh's {what} need {bytes} bytes, above the device limit {limit_name} = {limit} \
         bytes: compute this mesh's ground truth on the CPU"
    )]
    TreeTooLarge {
        /// Which tree: `"BVH nodes"`, `"triangle packets"` or `"winding nodes"`.
        what: &'static str,
        /// Its size.
        bytes: u64,
        /// The wgpu limit it exceeds.
        limit_name: &'static str,
        /// That limit's value on the device.
        limit: u64,
    },
    /// The BVH is deeper than the kernels' traversal stack allows.
    #[error(
        "the mesh's BVH needs a traversal stack of {needed} entries, above the GPU kernels' \
         {limit} (MAX_STACK): compute this mesh's ground truth on the CPU"
    )]
    TreeTooDeep {
        /// [`sdf_geom::GpuTrees::max_stack`] of the mesh.
        needed: u32,
        /// [`MAX_STACK`].
        limit: u32,
    },
    /// The GPU's labels of a few probe points disagree with the CPU's (checked when a
    /// [`Labeller`] is chosen): a fault of this device or its driver, found before any label
    /// of it is used.
    #[error(
        "the GPU's ground truth disagrees with the CPU's at {misses} of {points} probe points \
         (distances up to {worst:.1e} of the diagonal apart, {sign_misses} signs differ): a \
         fault of this device or its driver; compute the ground truth on the CPU"
    )]
    Disagrees {
        /// Probe points.
        points: usize,
        /// Points whose distances differ by more than 1e-5 of the diagonal, or whose signs
        /// differ where the CPU's is clear.
        misses: usize,
        /// Of those, the points whose signs differ.
        sign_misses: usize,
        /// The largest difference of the distances, in diagonals.
        worst: f32,
    },
    /// The device failed, or a per-call buffer would exceed its limits.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// A mesh's exact signed distance on the GPU: the trees of a [`SignedDistance`], uploaded once.
/// See the [module documentation](self).
#[derive(Debug)]
pub struct GpuGroundTruth {
    params: Params,
    /// The mesh's bounding sphere's cube doubled (mesh units): the grid points are grouped on
    /// (within their own bounds), so that a few far queries do not crowd the rest into a few
    /// cells.
    grid: (Vec3, Vec3),
    nodes: wgpu::Buffer,
    packets: wgpu::Buffer,
    winding: wgpu::Buffer,
    triangles: usize,
    max_stack: u32,
}

/// Where a query's GPU time goes ([`GpuGroundTruth::profile`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GroundTruthProfile {
    /// The points each kernel ran on (the batch's first part).
    pub points: usize,
    /// Each launch's label (`"kernel: launch"`) and GPU time, in the order they ran.
    pub launches: Vec<PassTime>,
}

/// Which kernel a query runs, and what it binds and returns.
#[derive(Clone, Copy)]
enum Kernel {
    Closest,
    Winding,
    Signed,
}

impl Kernel {
    fn shader(self) -> &'static Shader {
        match self {
            Kernel::Closest => &shaders::GROUND_TRUTH_CLOSEST,
            Kernel::Winding | Kernel::Signed => &shaders::GROUND_TRUTH_WINDING,
        }
    }

    fn entry_point(self) -> &'static str {
        match self {
            Kernel::Closest => "closest",
            Kernel::Winding => "winding",
            Kernel::Signed => "signed_distance",
        }
    }

    /// Floats written per point.
    fn width(self) -> usize {
        match self {
            Kernel::Closest => 4,
            Kernel::Winding | Kernel::Signed => 1,
        }
    }

    /// The trees the entry point reads (the layout derived from the shader binds only those):
    /// BVH nodes (binding 1), packets (2), winding nodes (3).
    fn trees(self) -> [bool; 3] {
        match self {
            Kernel::Closest => [true, true, false],
            Kernel::Winding => [false, true, true],
            Kernel::Signed => [true, true, true],
        }
    }
}

impl GpuGroundTruth {
    /// Uploads the trees of `sd` to the device of `gpu`.
    ///
    /// # Errors
    /// [`GroundTruthError::TreeTooLarge`] or [`GroundTruthError::TreeTooDeep`] where the mesh does
    /// not fit the device or the kernels ([`GpuGroundTruth::check_limits`]); the GPU's errors.
    pub fn new(gpu: &GpuContext, sd: &SignedDistance) -> Result<Self, GroundTruthError> {
        let trees = sd.gpu_trees();
        Self::check_limits(&trees, &gpu.limits())?;
        // Half the far radius and the centre in mesh units, for the far test without overflow;
        // computed in f64 (the far radius may exceed f32 in mesh units: then it is +inf, and no
        // query is far, which is right for a mesh that large).
        let to_mesh = 2f64.powi(-trees.exponent);
        let params = Params {
            n_points: 0,
            exponent: trees.exponent,
            _pad0: 0,
            _pad1: 0,
            center_half: (trees.center * to_mesh * 0.5).as_vec3().to_array(),
            far_half: (trees.far * to_mesh * 0.5) as f32,
            center: trees.center.as_vec3().to_array(),
            far: trees.far as f32,
            beta: trees.beta,
            refine_band: trees.refine_band,
            surface_eps: trees.surface_eps,
            inside: trees.inside,
        };
        let reach = DVec3::splat(2.0 * trees.far / sdf_geom::FAR_QUERY_RADII);
        let limit = DVec3::splat(f64::from(f32::MAX));
        let grid = [trees.center - reach, trees.center + reach]
            .map(|v| (v * to_mesh).clamp(-limit, limit).as_vec3());
        Ok(GpuGroundTruth {
            params,
            grid: (grid[0], grid[1]),
            nodes: gpu.storage_from_slice("ground truth BVH nodes", trees.nodes)?,
            packets: gpu.storage_from_slice("ground truth triangle packets", trees.packets)?,
            winding: gpu.storage_from_slice("ground truth winding nodes", trees.winding)?,
            triangles: trees.triangle_ids.len(),
            max_stack: trees.max_stack,
        })
    }

    /// Whether `trees` fit a device with `limits` and the kernels: each tree within one storage
    /// binding ([`GpuContext::check_storage_size_in`]), the stack bound within [`MAX_STACK`].
    /// [`GpuGroundTruth::new`] runs it with the device's limits.
    ///
    /// # Errors
    /// [`GroundTruthError::TreeTooLarge`] naming the tree and the limit, or
    /// [`GroundTruthError::TreeTooDeep`].
    pub fn check_limits(
        trees: &GpuTrees<'_>,
        limits: &wgpu::Limits,
    ) -> Result<(), GroundTruthError> {
        if trees.max_stack > MAX_STACK {
            return Err(GroundTruthError::TreeTooDeep {
                needed: trees.max_stack,
                limit: MAX_STACK,
            });
        }
        let sizes = [
            ("BVH nodes", size_of_val(trees.nodes)),
            ("triangle packets", size_of_val(trees.packets)),
            ("winding nodes", size_of_val(trees.winding)),
        ];
        for (what, bytes) in sizes {
            GpuContext::check_storage_size_in(limits, what, bytes as u64).map_err(|e| match e {
                GpuError::BufferTooLarge {
                    requested,
                    limit_name,
                    limit,
                    ..
                } => GroundTruthError::TreeTooLarge {
                    what,
                    bytes: requested,
                    limit_name,
                    limit,
                },
                other => other.into(),
            })?;
        }
        Ok(())
    }

    /// Number of triangles (those of non-zero area: the [`SignedDistance`]'s).
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// The traversal stack the mesh's trees need ([`sdf_geom::GpuTrees::max_stack`], at most
    /// [`MAX_STACK`]).
    pub fn max_stack(&self) -> u32 {
        self.max_stack
    }

    /// Signed distances at `points` (mesh units), as
    /// [`SignedDistance::signed_distance_batch`]: negative inside, NaN for non-finite points.
    pub fn signed_distance(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<f32>, GroundTruthError> {
        self.run(gpu, points, Kernel::Signed)
    }

    /// Closest points on the mesh and unsigned distances to them, as
    /// [`SignedDistance::closest_point_batch`]'s `point` and `distance` (NaN for non-finite
    /// points).
    pub fn closest_points(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<(Vec3, f32)>, GroundTruthError> {
        let flat = self.run(gpu, points, Kernel::Closest)?;
        Ok(flat
            .chunks_exact(4)
            .map(|r| (Vec3::new(r[0], r[1], r[2]), r[3]))
            .collect())
    }

    /// Fast winding numbers at `points`, as [`SignedDistance::winding_number_batch`] (0 on the
    /// far path, NaN for non-finite points). Near 1/2 (within the refinement band) the value is
    /// the one recomputed at 4β, as the sign uses it.
    pub fn winding_numbers(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<f32>, GroundTruthError> {
        self.run(gpu, points, Kernel::Winding)
    }

    /// The GPU time of each launch of a query of `points`, kernel by kernel: for the
    /// closest-point, winding-number and signed-distance kernels in turn, the three launches
    /// that group the points by cell and the kernel itself, labelled `"kernel: launch"` (e.g.
    /// `"signed_distance: bin_scatter"`), from timestamps written around each launch. Only the
    /// first part of the batch runs (as many points as one dispatch of the host queries takes:
    /// [`GroundTruthProfile::points`]). `None` where the device has no timestamp queries.
    ///
    /// What it is for: telling the kernels' own time from a query's wall time (uploads,
    /// readbacks, the host's work), and the traversals from one another (a signed distance is
    /// about a closest-point search and a winding number); `examples/ground_truth_bench` prints
    /// it. Timing each launch adds a little to each.
    ///
    /// # Errors
    /// The GPU's errors.
    pub fn profile(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Option<GroundTruthProfile>, GroundTruthError> {
        const KERNELS: [Kernel; 3] = [Kernel::Closest, Kernel::Winding, Kernel::Signed];
        const LAUNCHES: usize = 4;
        let Some(mut profiler) = PassProfiler::new(gpu, (KERNELS.len() * LAUNCHES) as u32) else {
            return Ok(None);
        };
        let n = KERNELS
            .iter()
            .map(|&k| part_size(gpu, k))
            .fold(points.len(), usize::min);
        if n == 0 {
            return Ok(Some(GroundTruthProfile {
                points: 0,
                launches: Vec::new(),
            }));
        }
        let part = &points[..n];
        let grid = self.grid_for(part);
        // Each kernel's buffers, all written before the one submission.
        let slots = KERNELS
            .iter()
            .map(|&k| QuerySlot::new(gpu, self, k, n as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        for slot in &slots {
            slot.record(gpu, self, part, grid, &mut enc, Some(&mut profiler))?;
        }
        profiler.resolve(&mut enc);
        gpu.queue().submit([enc.finish()]);
        let mut times = profiler.read(gpu)?;
        for (i, t) in times.iter_mut().enumerate() {
            t.label = format!("{}: {}", KERNELS[i / LAUNCHES].entry_point(), t.label);
        }
        Ok(Some(GroundTruthProfile {
            points: n,
            launches: times,
        }))
    }

    /// `kernel` bound to its uniform (a [`Params`]), the points it reads (3 f32 each), the
    /// buffer it writes (`kernel.width()` f32 per point, at each point's own index) and the
    /// grouping whose order it takes the points in, with the trees it reads.
    fn launch(
        &self,
        gpu: &GpuContext,
        kernel: Kernel,
        uniform: &wgpu::Buffer,
        points: &wgpu::Buffer,
        out: &wgpu::Buffer,
        bins: &CellOrder,
    ) -> Result<Launch, GpuError> {
        let pipeline = gpu.pipeline(kernel.shader(), kernel.entry_point(), &[])?;
        let mut entries = vec![entry(0, uniform)];
        for (k, (used, buffer)) in kernel
            .trees()
            .into_iter()
            .zip([&self.nodes, &self.packets, &self.winding])
            .enumerate()
        {
            if used {
                entries.push(entry(1 + k as u32, buffer));
            }
        }
        entries.extend([entry(4, points), entry(5, out), entry(6, bins.order())]);
        Ok(Launch::new(
            gpu,
            &pipeline,
            kernel.entry_point(),
            &entries,
            (0, 0, 0),
        ))
    }

    /// Runs `kernel` over `points`: `kernel.width()` floats per point, in input order, NaN for
    /// non-finite points (the kernels leave them 0: WGSL cannot write a NaN portably).
    ///
    /// The batch goes in parts of at most [`MAX_CHUNK`] points (fewer where the device's storage
    /// binding is small), each grouped by cell on the GPU ([`bin`]) before the kernel runs, and
    /// through two sets of buffers: the host uploads a part and reads the previous one back
    /// while the GPU works on the part between.
    fn run(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        kernel: Kernel,
    ) -> Result<Vec<f32>, GroundTruthError> {
        self.run_reporting(gpu, points, kernel, &mut |_| {})
    }

    /// [`GpuGroundTruth::run`], calling `done` with the number of points labelled so far as
    /// each part completes (a [`Labeller`]'s progress).
    fn run_reporting(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        kernel: Kernel,
        done: &mut dyn FnMut(usize),
    ) -> Result<Vec<f32>, GroundTruthError> {
        self.run_in_parts(gpu, points, kernel, part_size(gpu, kernel), done)
    }

    /// The box a batch's points are grouped by cell in: theirs, within the mesh's grid.
    fn grid_for(&self, points: &[Vec3]) -> (Vec3, Vec3) {
        let (lo, hi) = bin::finite_box(points);
        let (lo, hi) = (lo.max(self.grid.0), hi.min(self.grid.1));
        if lo.cmple(hi).all() {
            (lo, hi)
        } else {
            self.grid
        }
    }

    /// [`GpuGroundTruth::run_reporting`] in parts of at most `chunk` points.
    fn run_in_parts(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        kernel: Kernel,
        chunk: usize,
        done: &mut dyn FnMut(usize),
    ) -> Result<Vec<f32>, GroundTruthError> {
        let width = kernel.width();
        let mut result = Vec::with_capacity(points.len() * width);
        if points.is_empty() {
            return Ok(result);
        }
        let chunk = chunk.clamp(1, points.len());
        let grid = self.grid_for(points);
        let parts = points.len().div_ceil(chunk);
        let slots = (0..parts.min(2))
            .map(|_| QuerySlot::new(gpu, self, kernel, chunk as u32))
            .collect::<Result<Vec<_>, _>>()?;
        let mut pending: Option<PendingRead> = None;
        for (k, part) in points.chunks(chunk).enumerate() {
            let read = slots[k % slots.len()].submit(gpu, self, part, grid)?;
            if let Some(previous) = pending.replace(read) {
                result.extend(previous.wait::<f32>(gpu)?);
                done(result.len() / width);
            }
        }
        if let Some(last) = pending {
            result.extend(last.wait::<f32>(gpu)?);
            done(result.len() / width);
        }
        for (i, p) in points.iter().enumerate() {
            if !p.is_finite() {
                result[i * width..(i + 1) * width].fill(f32::NAN);
            }
        }
        Ok(result)
    }
}

/// One set of a query's buffers: a part's points, their grouping, the kernel's uniform and
/// results, bound to the kernel.
struct QuerySlot {
    points: wgpu::Buffer,
    out: wgpu::Buffer,
    uniform: wgpu::Buffer,
    bins: CellOrder,
    launch: Launch,
    kernel: Kernel,
}

impl QuerySlot {
    /// Buffers for parts of at most `capacity` points.
    fn new(
        gpu: &GpuContext,
        gt: &GpuGroundTruth,
        kernel: Kernel,
        capacity: u32,
    ) -> Result<Self, GroundTruthError> {
        let width = kernel.width();
        let points = gpu.storage_zeroed("ground truth points", u64::from(capacity) * 12)?;
        let out = gpu.storage_zeroed(
            "ground truth results",
            u64::from(capacity) * width as u64 * 4,
        )?;
        let uniform = gpu.uniform("ground truth params", &gt.params);
        let bins = CellOrder::new(gpu, &points, capacity)?;
        let launch = gt.launch(gpu, kernel, &uniform, &points, &out, &bins)?;
        Ok(QuerySlot {
            points,
            out,
            uniform,
            bins,
            launch,
            kernel,
        })
    }

    /// Uploads `part`, records its grouping over `grid`, the kernel and the copy of its
    /// results, and submits them.
    fn submit(
        &self,
        gpu: &GpuContext,
        gt: &GpuGroundTruth,
        part: &[Vec3],
        grid: (Vec3, Vec3),
    ) -> Result<PendingRead, GroundTruthError> {
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        self.record(gpu, gt, part, grid, &mut enc, None)?;
        let bytes = part.len() as u64 * self.kernel.width() as u64 * 4;
        let read = gpu.record_read(&mut enc, &self.out, 0, bytes);
        Ok(gpu.submit_with_read(enc, read))
    }

    /// Uploads `part` and records its grouping over `grid` and the kernel into `enc`, each
    /// launch in a pass of its own timed by `profiler` if given.
    fn record(
        &self,
        gpu: &GpuContext,
        gt: &GpuGroundTruth,
        part: &[Vec3],
        grid: (Vec3, Vec3),
        enc: &mut wgpu::CommandEncoder,
        profiler: Option<&mut PassProfiler>,
    ) -> Result<(), GroundTruthError> {
        let n = part.len() as u32;
        gpu.write(&self.points, bytemuck::cast_slice::<Vec3, f32>(part))?;
        gpu.write(
            &self.uniform,
            &[Params {
                n_points: n,
                ..gt.params
            }],
        )?;
        let [count, scan, scatter] = self.bins.prepare(gpu, enc, n, grid)?;
        let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
        record_launches(
            enc,
            "ground truth",
            &[count, scan, scatter, (&self.launch, (x, y, 1))],
            profiler,
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::shaders;

    /// The uniform has the layout the kernels read.
    #[test]
    fn params_mirror_the_shaders() {
        for shader in [shaders::GROUND_TRUTH_CLOSEST, shaders::GROUND_TRUTH_WINDING] {
            shaders::assert_mirrors!(
                super::Params,
                shader,
                "Params",
                [
                    n_points,
                    exponent,
                    center_half,
                    far_half,
                    center,
                    far,
                    beta,
                    refine_band,
                    surface_eps,
                    inside
                ]
            );
        }
    }

    /// The WGSL tree structs have the sizes of sdf-geom's (which are the CPU's nodes), and the
    /// constants the host relies on are the shaders'.
    #[test]
    fn tree_structs_and_constants_match() {
        let src = shaders::GROUND_TRUTH_WINDING.source;
        let module = naga::front::wgsl::parse_str(src).expect("valid WGSL");
        let mut layouter = naga::proc::Layouter::default();
        layouter.update(module.to_ctx()).expect("layout");
        let span = |name: &str| {
            module
                .types
                .iter()
                .find(|(_, t)| t.name.as_deref() == Some(name))
                .map(|(h, _)| layouter[h].size as usize)
                .unwrap_or_else(|| panic!("no struct {name}"))
        };
        assert_eq!(span("Node4"), size_of::<sdf_geom::GpuBvhNode>());
        assert_eq!(span("Packet"), size_of::<sdf_geom::GpuTriPacket>());
        assert_eq!(span("WNode4"), size_of::<sdf_geom::GpuWindingNode>());
        assert!(src.contains(&format!("const STACK: u32 = {}u;", super::MAX_STACK)));
        assert!(src.contains(&format!("const WG: u32 = {}u;", super::WG)));
    }

    /// The profile times the grouping's three launches and the kernel, for each of the three
    /// kernels, in that order, each by its own timestamps.
    #[test]
    fn the_profile_times_every_launch_of_each_kernel() {
        use super::GpuGroundTruth;
        let gpu = crate::GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let mesh = sdf_geom::Mesh::icosphere(0.8, 2);
        let cpu = sdf_geom::SignedDistance::new(&mesh).unwrap();
        let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
        let Some(profile) = gt
            .profile(gpu, &sdf_geom::sample::uniform_box(3000, 5))
            .unwrap()
        else {
            eprintln!("adapter has no timestamp queries: nothing to profile");
            return;
        };
        assert_eq!(profile.points, 3000);
        let times = &profile.launches;
        let labels: Vec<&str> = times.iter().map(|t| t.label.as_str()).collect();
        let mut want = Vec::new();
        for kernel in ["closest", "winding", "signed_distance"] {
            for launch in ["bin_count", "bin_scan", "bin_scatter", kernel] {
                want.push(format!("{kernel}: {launch}"));
            }
        }
        assert_eq!(labels, want);
        // Each kernel searches the trees for 3000 points: longer than no time at all.
        for t in times.iter().skip(3).step_by(4) {
            assert!(t.ns > 0, "{t:?}");
        }
        let empty = gt.profile(gpu, &[]).unwrap().expect("timestamps, as above");
        assert_eq!((empty.points, empty.launches.len()), (0, 0));
    }

    /// A batch in many parts (through the two alternating sets of buffers, each part grouped by
    /// cell) gives each point the value it gets in one part, and the CPU's: on the open teapot,
    /// every kernel, with points far away, on the mesh and non-finite ones spread over the
    /// parts.
    #[test]
    fn parts_through_alternating_buffers_agree_with_one_part() {
        use super::{GpuGroundTruth, Kernel};
        use glam::Vec3;
        let gpu = crate::GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let (mesh, _) = sdf_geom::load_mesh(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/data/teapot.obj"
        ))
        .unwrap();
        let mesh = mesh.normalized().0;
        let cpu = sdf_geom::SignedDistance::new(&mesh).unwrap();
        let gt = GpuGroundTruth::new(gpu, &cpu).unwrap();
        let mut points = sdf_geom::sample::near_surface(&mesh, 1500, 0.05, 3);
        points.extend(sdf_geom::sample::uniform_box(1500, 4));
        for (k, p) in [Vec3::NAN, Vec3::splat(1e30), mesh.vertices[0]]
            .into_iter()
            .enumerate()
        {
            points.insert(1000 * k + 17, p);
        }
        let signed = cpu.signed_distance_batch(&points);
        for kernel in [Kernel::Signed, Kernel::Closest, Kernel::Winding] {
            let whole = gt
                .run_in_parts(gpu, &points, kernel, points.len(), &mut |_| {})
                .unwrap();
            let mut reported = Vec::new();
            let parts = gt
                .run_in_parts(gpu, &points, kernel, 700, &mut |done| reported.push(done))
                .unwrap();
            assert_eq!(reported, [700, 1400, 2100, 2800, 3003]);
            assert_eq!(whole.len(), points.len() * kernel.width());
            for (i, (a, b)) in whole.iter().zip(&parts).enumerate() {
                assert!(
                    a.to_bits() == b.to_bits(),
                    "value {i}: {a} in one part, {b} in parts"
                );
            }
            if let Kernel::Signed = kernel {
                for (i, (g, c)) in whole.iter().zip(&signed).enumerate() {
                    assert!(
                        (g - c).abs() <= 1e-5 * c.abs().max(1.0) || (g.is_nan() && c.is_nan()),
                        "point {i}: GPU {g}, CPU {c}"
                    );
                }
            }
        }
    }
}
