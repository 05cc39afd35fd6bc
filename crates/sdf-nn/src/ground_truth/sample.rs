//! Training points drawn on the GPU (`shaders/sample.wgsl`), and labelled there by
//! [`GpuGroundTruth`]'s signed-distance kernel without a trip through the host.
//!
//! ```no_run
//! use sdf_geom::{SignedDistance, load_mesh};
//! use sdf_nn::GpuContext;
//! use sdf_nn::ground_truth::{GpuGroundTruth, GpuSampler, LabelKind, SampleSpec, SampleTable};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let mesh = load_mesh("tests/data/spot.obj")?.0.normalized().0;
//! let gpu = GpuContext::shared()?;
//! let gt = GpuGroundTruth::new(gpu, &SignedDistance::new(&mesh)?)?;
//! let sampler = GpuSampler::new(gpu, &SampleTable::new(&mesh)?)?;
//! let spec = SampleSpec {
//!     uniform: 1000, near: 2000, surface: 2000, sigma: 0.01, seed: 7, stream: 0, shuffle: true,
//! };
//! let (points, distances) = sampler.draw_and_label(gpu, &gt, &spec, LabelKind::Signed)?;
//! # Ok(())
//! # }
//! ```
//!
//! # What it draws
//! The distributions of [`sdf_geom::sample`]'s `uniform_box`, `surface` and `near_surface`
//! (not their numbers): uniform in `[-1, 1]³`; a triangle with probability proportional to its
//! area, then `r₁ = √u₁`, `r₂ = u₂`, `p = a (1 − r₁) + b r₁ (1 − r₂) + c r₁ r₂`; a surface point
//! plus `σ · N(0, I)` by Box–Muller. The random words are Philox4x32-10's
//! ([`super::counter_rng`]), keyed by the seed and counted by the point's kind, rank and the
//! draw's stream, so a seed gives the same points on every run; [`SampleTable::draw_cpu`]
//! computes the same points on the CPU (the same integers; the floats to the rounding of
//! `sqrt`, `log`, `sin` and `cos`, which WGSL does not pin down).
//!
//! The triangle is found by a binary search over the cumulative areas, rounded to multiples of
//! 2⁻³² of the total (built on the CPU once per mesh, in f64): a triangle's probability is its
//! area fraction within 2⁻³².
//!
//! # Speed
//! On lavapipe (2 shared cores, November 2026, `examples/nglod_sample_source.rs`, spot) drawing
//! 5·10⁴ points takes 6–10 ms; labelling them (the 3·10⁴ off the surface) 0.35–0.55 s, where
//! the CPU samplers and `SignedDistance` draw and label the same in 0.04–0.08 s: as for
//! [`GpuGroundTruth`], the GPU path is for real GPUs.

use glam::Vec3;
use sdf_geom::Mesh;

use super::bin::CellOrder;
use super::counter_rng::{Kind, SampleSpec, Shuffle};
use super::{GpuGroundTruth, Kernel, Params};
use crate::gpu::{GpuContext, GpuError, Launch, PassProfiler, entry, record_launches};
use crate::shaders;

/// Invocations per workgroup (`WG` in `sample.wgsl`).
const WG: u32 = 64;

/// The sampler's uniform (`SampleParams` in `sample.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct SampleParams {
    n_points: u32,
    n_uniform: u32,
    n_near: u32,
    n_triangles: u32,
    key: [u32; 2],
    stream: u32,
    shuffle_half: u32,
    shuffle_keys: [u32; 4],
    sigma: f32,
    shuffle_n: u32,
    _pad1: u32,
    _pad2: u32,
}

/// Errors of the sampler.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// No triangle with a positive, finite area: nothing to sample on.
    #[error("the mesh has no triangle with a positive, finite area to sample points on")]
    NoArea,
    /// A draw's point count does not fit.
    #[error("a draw of {requested} points does not fit: at most {limit} here")]
    TooManyPoints {
        /// Points asked for.
        requested: u64,
        /// The most this call takes (its buffers' capacity, or `u32::MAX`).
        limit: u64,
    },
    /// σ must be finite and non-negative.
    #[error("the near-surface σ must be finite and non-negative, not {0}")]
    BadSigma(f32),
    /// The device failed, or a buffer would exceed its limits.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// What the sampler's labels are.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LabelKind {
    /// Signed distances (negative inside), as [`sdf_geom::SignedDistance::signed_distance`].
    #[default]
    Signed,
    /// Their absolute values.
    Unsigned,
}

/// A mesh's triangles of positive area and their cumulative areas: what the sampler searches,
/// built once per mesh on the CPU. Also the CPU reference of the GPU sampler
/// ([`SampleTable::draw_cpu`]).
#[derive(Clone, Debug)]
pub struct SampleTable {
    /// Corners of the triangles of positive area.
    corners: Vec<[Vec3; 3]>,
    /// The mesh's index of each.
    ids: Vec<u32>,
    /// `bounds[t]`: the cumulative area of triangles `0..=t` in units of 2⁻³² of the total,
    /// rounded (the last triangle's, 2³², left out).
    bounds: Vec<u32>,
}

impl SampleTable {
    /// The table of `mesh` (areas in f64, as [`sdf_geom::sample::surface`] computes them).
    ///
    /// # Errors
    /// [`SampleError::NoArea`] when no triangle has a positive, finite area.
    pub fn new(mesh: &Mesh) -> Result<Self, SampleError> {
        let mut corners = Vec::new();
        let mut ids = Vec::new();
        let mut cumulative = Vec::new();
        let mut total = 0.0f64;
        for (i, t) in mesh.triangles.iter().enumerate() {
            let Some([a, b, c]) = mesh.corners(t) else {
                continue;
            };
            let area = 0.5 * (b - a).as_dvec3().cross((c - a).as_dvec3()).length();
            if area.is_finite() && area > 0.0 && a.is_finite() && b.is_finite() && c.is_finite() {
                total += area;
                corners.push([a, b, c]);
                ids.push(i as u32);
                cumulative.push(total);
            }
        }
        if corners.is_empty() || !total.is_finite() {
            return Err(SampleError::NoArea);
        }
        let scale = 2f64.powi(32) / total;
        let bounds = cumulative[..cumulative.len() - 1]
            .iter()
            .map(|&c| (c * scale).round().min(f64::from(u32::MAX)) as u32)
            .collect();
        Ok(SampleTable {
            corners,
            ids,
            bounds,
        })
    }

    /// Triangles of positive area.
    pub fn len(&self) -> usize {
        self.corners.len()
    }

    /// Never true: a table has a triangle ([`SampleTable::new`]).
    pub fn is_empty(&self) -> bool {
        self.corners.is_empty()
    }

    /// The mesh's index of the table's triangle `t`.
    pub fn mesh_triangle(&self, t: u32) -> Option<u32> {
        self.ids.get(t as usize).copied()
    }

    /// The probability of the table's triangle `t` (its area fraction, to 2⁻³²).
    pub fn probability(&self, t: usize) -> f64 {
        let hi = self.bounds.get(t).map_or(2f64.powi(32), |&b| f64::from(b));
        let lo = t
            .checked_sub(1)
            .and_then(|s| self.bounds.get(s))
            .map_or(0.0, |&b| f64::from(b));
        (hi - lo) / 2f64.powi(32)
    }

    /// The table's triangle drawn for the word `w`.
    fn find(&self, w: u32) -> usize {
        self.bounds.partition_point(|&b| b <= w)
    }

    /// The CPU reference of the GPU sampler: the points of `spec` with, for each point on or
    /// near the surface, the mesh's index of its triangle.
    ///
    /// # Errors
    /// [`SampleError::TooManyPoints`] above `u32::MAX` points, [`SampleError::BadSigma`].
    pub fn draw_cpu(
        &self,
        spec: &SampleSpec,
    ) -> Result<(Vec<Vec3>, Vec<Option<u32>>), SampleError> {
        let n = check_spec(spec)?;
        let shuffle = spec.shuffle();
        Ok((0..n).map(|i| self.point(spec, &shuffle, i)).unzip())
    }

    /// Point `i` of `spec`, as `draw_point` in `sample.wgsl`.
    fn point(&self, spec: &SampleSpec, shuffle: &Shuffle, i: u32) -> (Vec3, Option<u32>) {
        let (kind, rank) = spec.source(shuffle, i);
        let w = spec.words(kind, rank, 0);
        if kind == Kind::Uniform {
            return (SampleSpec::uniform_point(w), None);
        }
        let t = self.find(w[0]);
        let [a, b, c] = self.corners[t];
        let r1 = super::counter_rng::unit_float(w[1]).sqrt();
        let r2 = super::counter_rng::unit_float(w[2]);
        let mut p = a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2);
        if kind == Kind::Near {
            p += SampleSpec::offset(w, spec.words(kind, rank, 1), spec.sigma);
        }
        (p, Some(self.ids[t]))
    }
}

/// Points in `spec`, or why it cannot be drawn.
fn check_spec(spec: &SampleSpec) -> Result<u32, SampleError> {
    if !(spec.sigma.is_finite() && spec.sigma >= 0.0) {
        return Err(SampleError::BadSigma(spec.sigma));
    }
    spec.len().ok_or(SampleError::TooManyPoints {
        requested: u64::from(spec.uniform) + u64::from(spec.near) + u64::from(spec.surface),
        limit: u64::from(u32::MAX),
    })
}

/// A mesh's [`SampleTable`] on the GPU, and the sampling kernels. See the
/// [module documentation](self).
#[derive(Debug)]
pub struct GpuSampler {
    corners: wgpu::Buffer,
    bounds: wgpu::Buffer,
    ids: Vec<u32>,
    triangles: u32,
}

impl GpuSampler {
    /// Uploads `table`.
    ///
    /// # Errors
    /// [`SampleError::Gpu`] where a buffer exceeds the device's limits.
    pub fn new(gpu: &GpuContext, table: &SampleTable) -> Result<Self, SampleError> {
        let flat: Vec<f32> = table
            .corners
            .iter()
            .flat_map(|t| t.iter().flat_map(|v| v.to_array()))
            .collect();
        Ok(GpuSampler {
            corners: gpu.storage_from_slice("sample corners", &flat)?,
            bounds: gpu.storage_from_slice("sample bounds", &table.bounds)?,
            ids: table.ids.clone(),
            triangles: table.len() as u32,
        })
    }

    /// The uniform of `spec` (checked by [`check_spec`]).
    fn params(&self, spec: &SampleSpec, n: u32) -> SampleParams {
        params(spec, n, self.triangles, spec.shuffle())
    }

    /// The points of `spec`, read back (for tests and diagnostics: training keeps them on the
    /// GPU, see [`LabelledDraw`]).
    ///
    /// # Errors
    /// [`SampleError::BadSigma`], [`SampleError::TooManyPoints`]; the GPU's.
    pub fn draw(&self, gpu: &GpuContext, spec: &SampleSpec) -> Result<Vec<Vec3>, SampleError> {
        Ok(self.draw_inner(gpu, spec, false)?.0)
    }

    /// [`GpuSampler::draw`] with the mesh's index of the triangle of each point on or near the
    /// surface (`None` for the uniform ones).
    ///
    /// # Errors
    /// As [`GpuSampler::draw`].
    pub fn draw_with_triangles(
        &self,
        gpu: &GpuContext,
        spec: &SampleSpec,
    ) -> Result<(Vec<Vec3>, Vec<Option<u32>>), SampleError> {
        self.draw_inner(gpu, spec, true)
    }

    fn draw_inner(
        &self,
        gpu: &GpuContext,
        spec: &SampleSpec,
        triangles: bool,
    ) -> Result<(Vec<Vec3>, Vec<Option<u32>>), SampleError> {
        let n = check_spec(spec)?;
        if n == 0 {
            return Ok((Vec::new(), Vec::new()));
        }
        let points = gpu.storage_zeroed("sample points", u64::from(n) * 12)?;
        let tri = gpu.storage_zeroed("sample triangles", u64::from(n) * 4)?;
        let uniform = gpu.uniform("sample params", &self.params(spec, n));
        let entry_point = if triangles {
            "draw_with_triangles"
        } else {
            "draw"
        };
        let pipeline = gpu.pipeline(&shaders::GROUND_TRUTH_SAMPLE, entry_point, &[])?;
        let mut entries = vec![
            entry(0, &uniform),
            entry(1, &self.corners),
            entry(2, &self.bounds),
            entry(3, &points),
        ];
        if triangles {
            entries.push(entry(4, &tri));
        }
        let bind_group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("sample"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        });
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
            pass.dispatch_workgroups(x, y, 1);
        }
        gpu.queue().submit([enc.finish()]);
        let flat: Vec<f32> = gpu.read_back_range(&points, 0, u64::from(n) * 3)?;
        let points = flat
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        let ids = if triangles {
            let t: Vec<u32> = gpu.read_back_range(&tri, 0, u64::from(n))?;
            t.into_iter()
                .map(|t| self.ids.get(t as usize).copied())
                .collect()
        } else {
            Vec::new()
        };
        Ok((points, ids))
    }

    /// The points of `spec` and their labels by `gt` (which must be the same mesh's), drawn
    /// and labelled in one submission ([`LabelledDraw`]), read back.
    ///
    /// # Errors
    /// As [`GpuSampler::draw`].
    pub fn draw_and_label(
        &self,
        gpu: &GpuContext,
        gt: &GpuGroundTruth,
        spec: &SampleSpec,
        labels: LabelKind,
    ) -> Result<(Vec<Vec3>, Vec<f32>), SampleError> {
        let n = check_spec(spec)?;
        let points = gpu.storage_zeroed("sample points", u64::from(n) * 12)?;
        let targets = gpu.storage_zeroed("sample labels", u64::from(n) * 4)?;
        let draw = LabelledDraw::new(gpu, self, gt, &points, &targets, labels)?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        draw.record(gpu, &mut enc, spec)?;
        gpu.queue().submit([enc.finish()]);
        let flat: Vec<f32> = gpu.read_back_range(&points, 0, u64::from(n) * 3)?;
        let labels = gpu.read_back_range(&targets, 0, u64::from(n))?;
        Ok((
            flat.chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect(),
            labels,
        ))
    }
}

/// The sampler and the ground truth bound to a caller's point and label buffers: records a
/// draw and its labelling into an encoder, so that the points never leave the GPU (the
/// training loop's source of points on the GPU).
///
/// The draw is made without its shuffle into scratch buffers, so that the points to label
/// (uniform and near-surface) lie together and the surface points (distance 0, as the CPU
/// pool labels them) cost nothing; the labelling runs over those, grouped by cell (a grid
/// over the box of about a cell per point, `bin.rs`), and a gather writes the shuffled draw and
/// its labels into the caller's buffers. The points are those of [`GpuSampler::draw`] for the
/// same [`SampleSpec`].
///
/// With a pool ([`LabelledDraw::with_pool`]) the labelled draws are kept, a block each, and an
/// epoch gathers its points from all the blocks kept ([`LabelledDraw::record_gather`]): the
/// CPU pool's scheme on the GPU, so that a block labelled once serves several epochs.
pub struct LabelledDraw {
    /// The draw without its shuffle, and the gather with it.
    draw_uniform: wgpu::Buffer,
    gather_uniform: wgpu::Buffer,
    label_uniform: wgpu::Buffer,
    draw: Launch,
    /// The labelled points grouped by cell, the order `label` takes them in.
    bins: CellOrder,
    label: Launch,
    gather: Launch,
    absolute: Option<Launch>,
    triangles: u32,
    label_params: Params,
    /// Points the buffers hold.
    capacity: u32,
    /// The scratch buffers the draw is labelled in: points, labels.
    scratch: (wgpu::Buffer, wgpu::Buffer),
    /// The pool's points and labels, and its blocks, where there is one.
    pool: Option<(wgpu::Buffer, wgpu::Buffer, u32)>,
}

impl std::fmt::Debug for LabelledDraw {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabelledDraw")
            .field("capacity", &self.capacity)
            .field("pool_blocks", &self.pool_blocks())
            .finish_non_exhaustive()
    }
}

impl LabelledDraw {
    /// Binds `sampler` and `gt` (the same mesh's) to `points` (3 f32 per point) and `targets`
    /// (1 f32 per point); draws hold at most as many points as both buffers do.
    ///
    /// # Errors
    /// The GPU's (pipeline compilation, scratch buffers beyond the device's limits).
    pub fn new(
        gpu: &GpuContext,
        sampler: &GpuSampler,
        gt: &GpuGroundTruth,
        points: &wgpu::Buffer,
        targets: &wgpu::Buffer,
        labels: LabelKind,
    ) -> Result<Self, SampleError> {
        Self::build(gpu, sampler, gt, (points, targets), labels, None)
    }

    /// [`LabelledDraw::new`] with a pool of `blocks` labelled draws, each as large as the
    /// caller's buffers ([`LabelledDraw::record_block`], [`LabelledDraw::record_gather`]).
    ///
    /// # Errors
    /// As [`LabelledDraw::new`]; [`SampleError::TooManyPoints`] for a pool of no block or of
    /// more than `u32::MAX` points; the pool's buffers beyond the device's limits (named).
    pub fn with_pool(
        gpu: &GpuContext,
        sampler: &GpuSampler,
        gt: &GpuGroundTruth,
        points: &wgpu::Buffer,
        targets: &wgpu::Buffer,
        labels: LabelKind,
        blocks: u32,
    ) -> Result<Self, SampleError> {
        Self::build(gpu, sampler, gt, (points, targets), labels, Some(blocks))
    }

    fn build(
        gpu: &GpuContext,
        sampler: &GpuSampler,
        gt: &GpuGroundTruth,
        (points, targets): (&wgpu::Buffer, &wgpu::Buffer),
        labels: LabelKind,
        pool_blocks: Option<u32>,
    ) -> Result<Self, SampleError> {
        let capacity =
            u32::try_from((points.size() / 12).min(targets.size() / 4)).unwrap_or(u32::MAX);
        let drawn = gpu.storage_zeroed("labelled draw: points", u64::from(capacity) * 12)?;
        // Beyond the labelled points each draw clears it: the surface points' labels are 0.
        let drawn_labels = gpu.storage_zeroed("labelled draw: labels", u64::from(capacity) * 4)?;
        let pool = match pool_blocks {
            None => None,
            Some(blocks) => {
                let pool_points = u64::from(capacity) * u64::from(blocks);
                // The kernels index the pool's coordinates (three a point) in u32.
                let limit = u64::from(u32::MAX / 3);
                if blocks == 0 || pool_points > limit {
                    return Err(SampleError::TooManyPoints {
                        requested: pool_points,
                        limit,
                    });
                }
                Some((
                    gpu.storage_zeroed("labelled draw: pool points", pool_points * 12)?,
                    gpu.storage_zeroed("labelled draw: pool labels", pool_points * 4)?,
                    blocks,
                ))
            }
        };
        let zero = sampler.params(&EMPTY, 0);
        let draw_uniform = gpu.uniform("labelled draw: draw params", &zero);
        let gather_uniform = gpu.uniform("labelled draw: gather params", &zero);
        let label_uniform = gpu.uniform("labelled draw: label params", &gt.params);
        // The workgroup grids depend on each draw's counts: set when recorded.
        let launch = |shader, name: &str, entries: &[wgpu::BindGroupEntry<'_>]| {
            let pipeline = gpu.pipeline(shader, name, &[])?;
            Ok::<_, GpuError>(Launch::new(gpu, &pipeline, name, entries, (0, 0, 0)))
        };
        let sample = &shaders::GROUND_TRUTH_SAMPLE;
        let draw = launch(
            sample,
            "draw",
            &[
                entry(0, &draw_uniform),
                entry(1, &sampler.corners),
                entry(2, &sampler.bounds),
                entry(3, &drawn),
            ],
        )?;
        let bins = CellOrder::new(gpu, &drawn, capacity)?;
        let label = gt.launch(
            gpu,
            Kernel::Signed,
            &label_uniform,
            &drawn,
            &drawn_labels,
            &bins,
        )?;
        // The gather reads the pool where there is one (the draw is copied into a block).
        let (from_points, from_labels) = match &pool {
            Some((p, l, _)) => (p, l),
            None => (&drawn, &drawn_labels),
        };
        let gather = launch(
            sample,
            "gather",
            &[
                entry(0, &gather_uniform),
                entry(3, points),
                entry(5, targets),
                entry(6, from_points),
                entry(7, from_labels),
            ],
        )?;
        let absolute = match labels {
            LabelKind::Signed => None,
            LabelKind::Unsigned => Some(launch(
                sample,
                "absolute",
                &[entry(0, &gather_uniform), entry(5, targets)],
            )?),
        };
        Ok(LabelledDraw {
            draw_uniform,
            gather_uniform,
            label_uniform,
            draw,
            bins,
            label,
            gather,
            absolute,
            triangles: sampler.triangles,
            label_params: gt.params,
            capacity,
            scratch: (drawn, drawn_labels),
            pool,
        })
    }

    /// The pool's blocks (1 without a pool: the last draw).
    pub fn pool_blocks(&self) -> u32 {
        self.pool.as_ref().map_or(1, |p| p.2)
    }

    /// Records the draw of `spec` into the first points of the buffers and their labelling
    /// into `enc` (with a pool, through its block 0). The uniforms go through the queue:
    /// submit before recording another draw.
    ///
    /// # Errors
    /// [`SampleError::TooManyPoints`] above the buffers' capacity, [`SampleError::BadSigma`].
    pub fn record(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        spec: &SampleSpec,
    ) -> Result<(), SampleError> {
        self.record_with(gpu, enc, spec, None)
    }

    /// [`LabelledDraw::record`], each launch in a timed pass of its own given a profiler.
    pub(crate) fn record_with(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        spec: &SampleSpec,
        profiler: Option<&mut PassProfiler>,
    ) -> Result<(), SampleError> {
        self.record_parts(gpu, enc, Some((spec, 0)), Some((spec, 1)), profiler)
    }

    /// Records the draw of `spec` (without its shuffle) and its labelling into block `block`
    /// of the pool, `block · len` points in (`len` = `spec`'s points). Every block of a pool
    /// and every gather from it must have the same `len`: blocks are laid out by it (a new
    /// length lays the pool out anew, every block to be drawn again). Without a pool, block 0
    /// is the draw the next gather reads. The uniforms go through the queue: one block per
    /// submission.
    ///
    /// # Errors
    /// As [`LabelledDraw::record`]; [`SampleError::TooManyPoints`] for a block beyond the
    /// pool.
    pub fn record_block(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        spec: &SampleSpec,
        block: u32,
    ) -> Result<(), SampleError> {
        self.record_parts(gpu, enc, Some((spec, block)), None, None)
    }

    /// Records the gather of `spec`'s points (`len` of them) from the first `blocks` blocks of
    /// the pool (`blocks · len` points) into the caller's buffers, in the order of `spec`'s
    /// shuffle over them ([`SampleSpec::shuffle_over`]): `len` distinct points of the pool, or
    /// the first `len` in their order without `shuffle`.
    ///
    /// # Errors
    /// [`SampleError::TooManyPoints`] for more blocks than the pool has or a draw above the
    /// buffers' capacity.
    pub fn record_gather(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        spec: &SampleSpec,
        blocks: u32,
    ) -> Result<(), SampleError> {
        self.record_parts(gpu, enc, None, Some((spec, blocks)), None)
    }

    /// The launches of a block's draw and labelling (copied into its place in the pool), then
    /// of a gather from the pool's first blocks.
    fn record_parts(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        block: Option<(&SampleSpec, u32)>,
        gather: Option<(&SampleSpec, u32)>,
        mut profiler: Option<&mut PassProfiler>,
    ) -> Result<(), SampleError> {
        if let Some((spec, b)) = block {
            let n = self.check_blocks(spec, b.saturating_add(1))?;
            if n > 0 {
                self.record_draw(gpu, enc, spec, n, profiler.as_deref_mut())?;
                if let Some((pool_points, pool_labels, _)) = &self.pool {
                    let (at, n) = (u64::from(b) * u64::from(n), u64::from(n));
                    enc.copy_buffer_to_buffer(&self.scratch.0, 0, pool_points, at * 12, n * 12);
                    enc.copy_buffer_to_buffer(&self.scratch.1, 0, pool_labels, at * 4, n * 4);
                }
            }
        }
        if let Some((spec, blocks)) = gather {
            let n = self.check_blocks(spec, blocks)?;
            if n > 0 {
                let params = params(spec, n, self.triangles, spec.shuffle_over(n * blocks));
                gpu.write(&self.gather_uniform, &[params])?;
                let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
                let mut launches = vec![(&self.gather, (x, y, 1))];
                if let Some(absolute) = &self.absolute {
                    launches.push((absolute, (x, y, 1)));
                }
                record_launches(enc, "gather", &launches, profiler);
            }
        }
        Ok(())
    }

    /// `spec`'s points, checked against the buffers and a pool of at least `blocks` blocks.
    fn check_blocks(&self, spec: &SampleSpec, blocks: u32) -> Result<u32, SampleError> {
        let n = check_spec(spec)?;
        if n > self.capacity {
            return Err(SampleError::TooManyPoints {
                requested: u64::from(n),
                limit: u64::from(self.capacity),
            });
        }
        let have = self.pool_blocks();
        if blocks == 0 || blocks > have {
            return Err(SampleError::TooManyPoints {
                requested: u64::from(n) * u64::from(blocks),
                limit: u64::from(self.capacity) * u64::from(have),
            });
        }
        Ok(n)
    }

    /// The draw of `spec`'s `n` points without its shuffle into the scratch buffers, and the
    /// labelling of its uniform and near-surface points.
    fn record_draw(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        spec: &SampleSpec,
        n: u32,
        profiler: Option<&mut PassProfiler>,
    ) -> Result<(), SampleError> {
        let unshuffled = SampleSpec {
            shuffle: false,
            ..*spec
        };
        let labelled = spec.uniform + spec.near;
        let draw = params(&unshuffled, n, self.triangles, unshuffled.shuffle());
        gpu.write(&self.draw_uniform, &[draw])?;
        gpu.write(
            &self.label_uniform,
            &[Params {
                n_points: labelled,
                ..self.label_params
            }],
        )?;
        // The surface points' labels are 0: a longer labelled part of an earlier draw may
        // have written there.
        if labelled < n {
            let tail = u64::from(n - labelled) * 4;
            enc.clear_buffer(&self.scratch.1, u64::from(labelled) * 4, Some(tail));
        }
        let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
        let mut launches = vec![(&self.draw, (x, y, 1))];
        if labelled > 0 {
            // Every drawn point lies in the box [-1, 1]³ but for near-surface offsets, which
            // the grouping clamps to the nearest cell.
            let grid = (Vec3::splat(-1.0), Vec3::splat(1.0));
            launches.extend(self.bins.prepare(gpu, enc, labelled, grid)?);
            let (lx, ly) = gpu.dispatch_size(labelled.div_ceil(super::WG));
            launches.push((&self.label, (lx, ly, 1)));
        }
        record_launches(enc, "draw and label", &launches, profiler);
        Ok(())
    }
}

/// A draw of no points.
const EMPTY: SampleSpec = SampleSpec {
    uniform: 0,
    near: 0,
    surface: 0,
    sigma: 0.0,
    seed: 0,
    stream: 0,
    shuffle: false,
};

/// The sampler's uniform for `n` points of `spec` (checked by [`check_spec`]) on a table of
/// `triangles` triangles, in the order of the shuffle `s` (`spec`'s over a draw or a pool).
fn params(spec: &SampleSpec, n: u32, triangles: u32, s: Shuffle) -> SampleParams {
    SampleParams {
        n_points: n,
        n_uniform: spec.uniform,
        n_near: spec.near,
        n_triangles: triangles,
        key: spec.key(),
        stream: spec.stream,
        shuffle_half: s.half,
        shuffle_keys: s.keys,
        sigma: spec.sigma,
        shuffle_n: s.n,
        _pad1: 0,
        _pad2: 0,
    }
}

#[cfg(test)]
mod tests {
    use crate::shaders;

    /// The uniform has the layout the kernels read, and the workgroup sizes are the shaders'.
    #[test]
    fn params_mirror_the_shader() {
        shaders::assert_mirrors!(
            super::SampleParams,
            shaders::GROUND_TRUTH_SAMPLE,
            "SampleParams",
            [
                n_points,
                n_uniform,
                n_near,
                n_triangles,
                key,
                stream,
                shuffle_half,
                shuffle_keys,
                sigma,
                shuffle_n
            ]
        );
        assert!(
            shaders::GROUND_TRUTH_SAMPLE
                .source
                .contains(&format!("const WG: u32 = {}u;", super::WG))
        );
        assert!(
            shaders::GROUND_TRUTH_CLOSEST
                .source
                .contains(&format!("const WG: u32 = {}u;", super::super::WG))
        );
    }
}
