//! Serving a [`NeuralSdf`](crate::NeuralSdf) to code that queries it all the time (a planner checking collisions,
//! a renderer, a physics step), the way wgpu code is written: the caller owns the buffers, work
//! is recorded into the caller's encoder, a submission returns at once, and reading back is a
//! separate step that the caller may skip.
//!
//! - [`NeuralSdf::create_query_buffers`](crate::NeuralSdf::create_query_buffers) makes a [`QueryBuffers`]: a points buffer
//!   ([`QueryBuffers::points`], `array<vec4<f32>>`, xyz used), a results buffer
//!   ([`QueryBuffers::results`]: `array<f32>` of distances, or with
//!   [`QueryOutputs::ValuesAndNormals`] `array<vec4<f32>>` of (distance, normal)), the network's
//!   scratch where it needs any, and a mappable staging buffer (or, on CPU and integrated adapters, mappable points
//!   and results buffers instead: [`QueryTransfer`]). Create it once, reuse it for every query.
//! - [`NeuralSdf::record_query`](crate::NeuralSdf::record_query) records a query of the first `n` points into your encoder.
//!   The results stay on the GPU: bind [`QueryBuffers::results`] in your next pass. Your own
//!   pass may also have written [`QueryBuffers::points`] (it is a storage buffer).
//! - [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) uploads points, records, copies the results to the staging
//!   buffer and submits, returning a [`QueryTicket`] at once; [`QueryBuffers::wait`] (or
//!   [`QueryBuffers::is_ready`] then `wait`) maps the results and hands them out as a
//!   [`QueryResults`] guard that unmaps on drop. One submission per [`QueryBuffers`] is in
//!   flight at a time: keep two to overlap a query with the host's work on the last one.
//!   With mapped transfers it also records the next query of the same size while the GPU
//!   works, so a caller that repeats its batch size does not wait for the encoding.
//!
//! A query is one kernel launch from points to results for NGLOD, and for SIREN on the kernels
//! GPUs run (the tiled fused kernel and the cooperative-matrix one); SIREN on the row-blocked
//! and GEMM kernels adds a launch before and after the network's own.
//!
//! Distances and normals follow [`NeuralSdf`](crate::NeuralSdf)'s rule outside the model's box, and are in mesh
//! units and coordinates (or, with [`QuerySpace::Normalized`], in the model's cube). Every
//! host-side method of [`NeuralSdf`](crate::NeuralSdf) (`eval`, `eval_normalized`, `eval_with_normals`, the timed
//! variant the reports use) runs on this same path, with buffers it keeps per device.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use glam::Vec3;
//! use sdf_nn::serve::query::{QueryBuffersDescriptor, QueryOutputs};
//! use sdf_nn::{GpuContext, NeuralSdf};
//!
//! let gpu = GpuContext::new()?;
//! let sdf = NeuralSdf::load("model.safetensors")?;
//! // Once: buffers for up to 4096 points, distances and normals.
//! let mut buffers = sdf.create_query_buffers(
//!     &gpu,
//!     &QueryBuffersDescriptor {
//!         capacity: 4096,
//!         outputs: QueryOutputs::ValuesAndNormals,
//!         ..Default::default()
//!     },
//! )?;
//! let mut hits = Vec::new();
//! for _frame in 0..3 {
//!     let ticket = sdf.submit_query(&gpu, &mut buffers, &[Vec3::ZERO, Vec3::X])?;
//!     // ... the host's own work runs while the GPU answers ...
//!     hits.clear();
//!     buffers.wait(&gpu, ticket)?.extend_values_and_normals(&mut hits);
//! }
//! # Ok(())
//! # }
//! ```

mod mapping;
mod record;
#[cfg(test)]
mod tests;

use std::sync::Arc;
use std::time::Duration;

use glam::Vec3;

pub use crate::gpu::QueryKernel;
use crate::gpu::{GpuContext, GpuError};
use crate::nglod::gpu::NglodEvalBinding;
use crate::serve::error::{NeuralSdfError, QueryError};
use crate::siren::eval::QueryLaunch;
use mapping::{MapSlot, MapState};

/// Invocations per workgroup of `shaders/query.wgsl`.
const WG: u32 = 64;

/// What a query computes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum QueryOutputs {
    /// One signed distance per point (`array<f32>`).
    #[default]
    Values,
    /// Per point the signed distance and the unit normal, as one `vec4<f32>`: `(d, nx, ny, nz)`.
    ValuesAndNormals,
}

impl QueryOutputs {
    /// Floats per point in the results buffer.
    pub fn floats_per_point(self) -> u32 {
        match self {
            QueryOutputs::Values => 1,
            QueryOutputs::ValuesAndNormals => 4,
        }
    }
}

/// The coordinates of the points and the units of the distances.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum QuerySpace {
    /// The original mesh's coordinates and units.
    #[default]
    Mesh,
    /// The model's normalised cube `[-1, 1]³` and its units.
    Normalized,
}

/// Describes a [`QueryBuffers`] (see [`NeuralSdf::create_query_buffers`](crate::NeuralSdf::create_query_buffers)).
#[derive(Clone, Copy, Debug, Default)]
pub struct QueryBuffersDescriptor<'a> {
    /// Debug label of the buffers.
    pub label: Option<&'a str>,
    /// Most points one query takes (at least 1).
    pub capacity: u32,
    /// Distances only, or distances and normals.
    pub outputs: QueryOutputs,
    /// Mesh or normalised coordinates.
    pub space: QuerySpace,
    /// How [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) moves points in and results out.
    pub transfer: QueryTransfer,
    /// The kernel of an NGLOD model or hash grid; `None`: the device's for each query's
    /// count ([`GpuContext::query_kernel`]). [`QueryKernel::PerSubgroup`] on a device without usable subgroups is
    /// [`QueryError::NoSubgroups`].
    pub kernel: Option<QueryKernel>,
}

/// How [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) and [`QueryBuffers::wait`] move points and results between
/// the host and the buffers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum QueryTransfer {
    /// [`QueryTransfer::Mapped`] where [`GpuContext::maps_storage_cheaply`](crate::GpuContext::maps_storage_cheaply) (CPU and integrated
    /// adapters), [`QueryTransfer::Staged`] elsewhere.
    #[default]
    Auto,
    /// Copies through an upload belt and a staging buffer, recorded in the query's submission:
    /// what a discrete GPU needs, whose mappable memory is slow for kernels.
    Staged,
    /// No copies: the points buffer is mapped and written, the results buffer mapped and read.
    /// On lavapipe a 10-point query costs two copy commands less. Needs the device feature
    /// `MAPPABLE_PRIMARY_BUFFERS` (asked for wherever the adapter has it: [`GpuContext::maps_storage`](crate::GpuContext::maps_storage)). The results buffer
    /// is then mapped from [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) until the [`QueryResults`] of its ticket
    /// is dropped: no submission may use [`QueryBuffers::results`] meanwhile
    /// ([`NeuralSdf::record_query`](crate::NeuralSdf::record_query) refuses with [`QueryError::Busy`]).
    Mapped,
}

/// Reusable, caller-owned buffers for queries of up to `capacity` points of one
/// [`NeuralSdf`](crate::NeuralSdf) on one device. See the [module docs](self).
pub struct QueryBuffers {
    model: u64,
    device: wgpu::Device,
    capacity: u32,
    outputs: QueryOutputs,
    space: QuerySpace,
    points: wgpu::Buffer,
    results: wgpu::Buffer,
    /// Where results are read from: a staging copy of `results`, or `results` itself
    /// ([`QueryTransfer::Mapped`]).
    staging: wgpu::Buffer,
    /// [`QueryTransfer::Mapped`]: the points are written into the mapped points buffer and
    /// the results read from the mapped results buffer, with no copies.
    mapped: bool,
    /// The points buffer's write mapping ([`QueryTransfer::Mapped`]).
    upload_map: Arc<MapSlot>,
    kernels: Kernels,
    /// Mapped upload buffers that [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) writes the points into and copies
    /// from in its own encoder: unlike `Queue::write_buffer`, no staging buffer is created and
    /// no second command buffer submitted per query (≈ 8 µs of a 10-point query on lavapipe).
    belt: wgpu::util::StagingBelt,
    map: Arc<MapSlot>,
    /// Bumped on each submission; tickets carry it.
    generation: u64,
    in_flight: Option<(u64, u32)>,
    /// The point count and level of detail of the last query recorded into these buffers,
    /// which their uniforms hold from its submission on (a kernel's uniforms are written when
    /// they change).
    recorded: Option<(u32, Option<usize>)>,
    /// [`QueryTransfer::Mapped`] with one-dispatch kernels: the next query's commands, recorded
    /// by [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) right after it submits, for the same count and level of
    /// detail, while the GPU works and the host would only wait (one slot for plain queries,
    /// one for timed ones). On an H100 that takes the 3.4–3.7 µs of encoding out of the next
    /// query's wall time (docs/benchmarks, session 21).
    prepared: [Option<Prepared>; 2],
    /// How many queries were submitted from `prepared` (for tests).
    prepared_used: u64,
}

/// A query's commands, recorded ahead of its submission.
struct Prepared {
    n: u32,
    lod: Option<usize>,
    commands: wgpu::CommandBuffer,
}

impl std::fmt::Debug for QueryBuffers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QueryBuffers")
            .field("capacity", &self.capacity)
            .field("outputs", &self.outputs)
            .field("space", &self.space)
            .finish_non_exhaustive()
    }
}

/// How a query runs on the GPU.
enum Kernels {
    /// NGLOD: one dispatch of its serving kernel, straight from `points` to `results`.
    Nglod(NglodBindings),
    /// SIREN on a kernel family that runs an inference in one dispatch (tiled fused,
    /// cooperative matrices): the same, straight from `points` to `results`.
    Siren(QueryLaunch),
    /// SIREN: `prepare` (points to the network's input rows), the network's launches bound to
    /// `net_in` and `net_out`, `finish` (its values and gradients to distances and normals).
    Staged(Box<Stages>),
}

/// An NGLOD model's serving kernels bound to one set of buffers.
struct NglodBindings {
    /// One point per invocation (every device).
    per_invocation: NglodEvalBinding,
    /// One point per subgroup, where these buffers' queries may run it.
    per_subgroup: Option<NglodEvalBinding>,
    /// The caller's choice ([`QueryBuffersDescriptor::kernel`]); `None`: by each query's count
    /// ([`GpuContext::query_kernel`]).
    forced: Option<QueryKernel>,
}

impl NglodBindings {
    /// `model`'s kernels bound to `buffers` (points, results): one point per invocation, and
    /// one per subgroup where `kernel` asks for it or (`None`) the device may choose it.
    fn new(
        gpu: &GpuContext,
        model: &crate::nglod::NglodGpu,
        (points, results): (&wgpu::Buffer, &wgpu::Buffer),
        normals: bool,
        transform: (Vec3, f32),
        kernel: Option<QueryKernel>,
    ) -> Result<Self, NeuralSdfError> {
        // The subgroup kernel counts 64 / width points per workgroup.
        let width = gpu.subgroups_within(64);
        let subgroups = match kernel {
            Some(QueryKernel::PerInvocation) => None,
            Some(QueryKernel::PerSubgroup) => {
                Some(width.ok_or_else(|| QueryError::NoSubgroups {
                    adapter: gpu.describe(),
                })?)
            }
            None => width.filter(|_| gpu.may_use_subgroup_queries()),
        };
        let bind =
            |subgroups| model.eval_binding(gpu, points, results, normals, transform, subgroups);
        Ok(NglodBindings {
            per_invocation: bind(None)?,
            per_subgroup: subgroups.map(|w| bind(Some(w))).transpose()?,
            forced: kernel,
        })
    }

    /// The binding a query of `n` points runs.
    fn for_count(&mut self, gpu: &GpuContext, n: u32) -> &mut NglodEvalBinding {
        let kernel = self
            .forced
            .unwrap_or_else(|| gpu.query_kernel(u64::from(n)));
        match (kernel, &mut self.per_subgroup) {
            (QueryKernel::PerSubgroup, Some(binding)) => binding,
            _ => &mut self.per_invocation,
        }
    }
}

/// The two ends of `shaders/query.wgsl` around a network's own kernels.
struct Stages {
    net_in: wgpu::Buffer,
    net_out: wgpu::Buffer,
    uniforms: wgpu::Buffer,
    /// The point count the uniforms hold.
    written: Option<u32>,
    prepare: (wgpu::ComputePipeline, wgpu::BindGroup),
    finish: (wgpu::ComputePipeline, wgpu::BindGroup),
    /// The network's launches from `net_in` to `net_out` and the point count they were built
    /// for; `None` inside when the count exceeds one launch (the network then splits it and
    /// copies through its own workspace).
    bound: Option<(u32, Option<Vec<crate::siren::kernels::Launch>>)>,
}

/// A submitted query; redeem it with [`QueryBuffers::wait`] (a ticket dropped unredeemed keeps
/// its buffers busy until [`QueryBuffers::abandon`]).
#[derive(Debug)]
#[must_use = "a submitted query is read back with QueryBuffers::wait"]
pub struct QueryTicket {
    generation: u64,
    submission: wgpu::SubmissionIndex,
    n: u32,
}

impl QueryTicket {
    /// Points in the query.
    pub fn len(&self) -> usize {
        self.n as usize
    }

    /// Whether the query has no points.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The wgpu submission that carries the query.
    pub fn submission(&self) -> &wgpu::SubmissionIndex {
        &self.submission
    }
}

/// The mapped results of a query; unmaps the staging buffer when dropped.
pub struct QueryResults<'a> {
    view: Option<wgpu::BufferView>,
    staging: &'a wgpu::Buffer,
    map: &'a MapSlot,
    n: usize,
    outputs: QueryOutputs,
}

impl QueryResults<'_> {
    /// Points in the query.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether the query had no points.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The raw floats: one per point, or four (distance, normal) with normals.
    pub fn floats(&self) -> Vec<f32> {
        self.view
            .as_ref()
            .map(|v| bytemuck::pod_collect_to_vec(v))
            .unwrap_or_default()
    }

    /// Appends the distances to `out` (reuse `out` between queries to avoid allocating).
    pub fn extend_values(&self, out: &mut Vec<f32>) {
        let Some(v) = &self.view else { return };
        let per = self.outputs.floats_per_point() as usize * 4;
        out.extend(
            v.chunks_exact(per)
                .map(|c| f32::from_ne_bytes([c[0], c[1], c[2], c[3]])),
        );
    }

    /// Appends (distance, normal) pairs to `out`; normals are zero for a values-only query.
    pub fn extend_values_and_normals(&self, out: &mut Vec<(f32, Vec3)>) {
        let Some(v) = &self.view else { return };
        let f = |c: &[u8], i: usize| f32::from_ne_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
        match self.outputs {
            QueryOutputs::Values => out.extend(v.chunks_exact(4).map(|c| (f(c, 0), Vec3::ZERO))),
            QueryOutputs::ValuesAndNormals => out.extend(
                v.chunks_exact(16)
                    .map(|c| (f(c, 0), Vec3::new(f(c, 4), f(c, 8), f(c, 12)))),
            ),
        }
    }
}

impl Drop for QueryResults<'_> {
    fn drop(&mut self) {
        if self.view.take().is_some() {
            self.staging.unmap();
        }
        self.map.set(MapState::Idle);
    }
}

impl QueryBuffers {
    /// Most points one query takes.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// What the queries compute.
    pub fn outputs(&self) -> QueryOutputs {
        self.outputs
    }

    /// The coordinates the points are in.
    pub fn space(&self) -> QuerySpace {
        self.space
    }

    /// The points, `array<vec4<f32>>` (xyz used): `STORAGE | COPY_DST` (and `MAP_WRITE` with
    /// [`QueryTransfer::Mapped`]), so your own pass or copy may fill it as well as
    /// [`QueryBuffers::upload`].
    pub fn points(&self) -> &wgpu::Buffer {
        &self.points
    }

    /// The results, `STORAGE | COPY_SRC` (and `MAP_READ` with [`QueryTransfer::Mapped`]):
    /// `array<f32>` of distances, or `array<vec4<f32>>` of (distance, normal). Bind it in your
    /// next pass to use them without a readback.
    pub fn results(&self) -> &wgpu::Buffer {
        &self.results
    }

    /// Writes `points` into [`QueryBuffers::points`] through the queue (they take effect at
    /// the next submission) and returns their count.
    pub fn upload(&mut self, gpu: &GpuContext, points: &[Vec3]) -> Result<u32, QueryError> {
        let n = self.check_points(points)?;
        if let Some(size) = wgpu::BufferSize::new(u64::from(n) * 16) {
            // None: wgpu reported the error to the device's handler, as `write_buffer` would.
            if let Some(mut view) = gpu.queue().write_buffer_with(&self.points, 0, size) {
                write_points(view.slice(..), points);
            }
        }
        Ok(n)
    }

    /// Records the copy of `points` into [`QueryBuffers::points`] at the start of `enc`,
    /// through the upload belt; returns their count. Call [`StagingBelt::finish`] before
    /// submitting `enc` and [`StagingBelt::recall`] after.
    ///
    /// [`StagingBelt::finish`]: wgpu::util::StagingBelt::finish
    /// [`StagingBelt::recall`]: wgpu::util::StagingBelt::recall
    fn upload_in(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        points: &[Vec3],
    ) -> Result<u32, QueryError> {
        let n = self.check_points(points)?;
        let Some(size) = wgpu::BufferSize::new(u64::from(n) * 16) else {
            return Ok(0);
        };
        write_points(
            self.belt.write_buffer(enc, &self.points, 0, size).slice(..),
            points,
        );
        Ok(n)
    }

    /// [`QueryTransfer::Mapped`]: writes `points` into the mapped points buffer (mapping it
    /// first: no submission uses it, since the last query was waited for) and returns their
    /// count.
    fn upload_mapped(&mut self, gpu: &GpuContext, points: &[Vec3]) -> Result<u32, NeuralSdfError> {
        let n = self.check_points(points)?;
        let bytes = u64::from(n) * 16;
        if bytes == 0 {
            return Ok(0);
        }
        let error = |reason: String| GpuError::Readback {
            label: "query points".into(),
            reason,
        };
        let slice = self.points.slice(..bytes);
        self.upload_map.request(slice, wgpu::MapMode::Write);
        let written = self.upload_map.settle(gpu.device()).and_then(|()| {
            slice
                .get_mapped_range_mut()
                .map(|mut view| write_points(view.slice(..), points))
                .map_err(|e| e.to_string())
        });
        // Also on failure: unmapping cancels a mapping still pending, which would otherwise
        // land later and leave the buffer mapped for every later submission.
        self.points.unmap();
        written.map_err(error)?;
        Ok(n)
    }

    /// Whether the query of `ticket` can be read without blocking (polls the device once).
    pub fn is_ready(&self, gpu: &GpuContext, ticket: &QueryTicket) -> bool {
        let _ = gpu.device().poll(wgpu::PollType::Poll);
        self.in_flight.map(|(g, _)| g) == Some(ticket.generation)
            && !matches!(*self.map.lock(), MapState::Pending)
    }

    /// Blocks until the query of `ticket` has run and returns its mapped results.
    pub fn wait(
        &mut self,
        gpu: &GpuContext,
        ticket: QueryTicket,
    ) -> Result<QueryResults<'_>, NeuralSdfError> {
        match self.in_flight {
            Some((g, _)) if g == ticket.generation => {}
            _ => return Err(QueryError::StaleTicket.into()),
        }
        self.in_flight = None;
        let error = |reason: String| GpuError::Readback {
            label: "query results".into(),
            reason,
        };
        let bytes = self.result_bytes(ticket.n);
        let view = if bytes == 0 {
            None
        } else {
            // Polling until the mapping's callback has run answers small queries sooner than
            // a blocking wait wakes up ([`crate::SPIN_WAIT`]); longer work falls through to it.
            let mapped = gpu
                .spin_until(|_| !self.map.is_pending())
                .map_err(|e| error(e.to_string()))?;
            if !mapped {
                gpu.device()
                    .poll(wgpu::PollType::Wait {
                        submission_index: Some(ticket.submission),
                        timeout: None,
                    })
                    .map_err(|e| error(e.to_string()))?;
            }
            // The submission is done; its callback may still be running on another thread.
            self.map.settle(gpu.device()).map_err(error)?;
            self.map.set(MapState::Mapped);
            match self.staging.slice(..bytes).get_mapped_range() {
                Ok(view) => Some(view),
                Err(e) => {
                    // Nothing will hold the mapping: release it, or the next submission fails.
                    self.staging.unmap();
                    self.map.set(MapState::Idle);
                    return Err(error(e.to_string()).into());
                }
            }
        };
        Ok(QueryResults {
            view,
            staging: &self.staging,
            map: &self.map,
            n: ticket.n as usize,
            outputs: self.outputs,
        })
    }

    /// Forgets the query in flight, whose ticket was dropped unredeemed (until then every
    /// submission is refused with [`QueryError::Busy`]): waits for the device, releases the
    /// results' mapping, and leaves the buffers ready for the next query. Nothing happens when
    /// no query is in flight.
    pub fn abandon(&mut self, gpu: &GpuContext) -> Result<(), NeuralSdfError> {
        if self.in_flight.take().is_none() {
            return Ok(());
        }
        let error = |reason: String| GpuError::Readback {
            label: "abandoned query".into(),
            reason,
        };
        gpu.device()
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| error(e.to_string()))?;
        // A query of no points requested no mapping: the slot is idle and stays so.
        if matches!(
            self.map.take_settled(gpu.device(), Duration::from_secs(10)),
            MapState::Mapped
        ) {
            self.staging.unmap();
        }
        self.map.set(MapState::Idle);
        Ok(())
    }

    /// Bytes of the results of `n` points.
    fn result_bytes(&self, n: u32) -> u64 {
        u64::from(n) * u64::from(self.outputs.floats_per_point()) * 4
    }

    /// Whether a query is one dispatch from the points to the results (no network scratch).
    fn one_dispatch(&self) -> bool {
        matches!(self.kernels, Kernels::Nglod(_) | Kernels::Siren(_))
    }

    /// How many queries [`NeuralSdf::submit_query`](crate::NeuralSdf::submit_query) submitted from commands recorded ahead.
    #[cfg(test)]
    pub(crate) fn prepared_used(&self) -> u64 {
        self.prepared_used
    }

    /// Whether the staging (with mapped transfers: the results) buffer is mapped or being mapped.
    fn map_busy(&self) -> bool {
        !matches!(*self.map.lock(), MapState::Idle)
    }

    /// Whether these buffers live on `gpu`'s device.
    pub(crate) fn belongs_to(&self, gpu: &GpuContext) -> bool {
        self.device == *gpu.device()
    }

    /// Checks the count of `points` and that each is finite; returns the count.
    fn check_points(&self, points: &[Vec3]) -> Result<u32, QueryError> {
        let n = self.check_count(points.len())?;
        if let Some(index) = points.iter().position(|p| !p.is_finite()) {
            return Err(QueryError::NonFinitePoint {
                index,
                point: points[index],
            });
        }
        Ok(n)
    }

    fn check_count(&self, n: usize) -> Result<u32, QueryError> {
        if n > self.capacity as usize {
            return Err(QueryError::Capacity {
                requested: n,
                capacity: self.capacity,
            });
        }
        Ok(n as u32)
    }
}

/// Writes `points` as `vec4<f32>` (w = 1), the layout of [`QueryBuffers::points`], into `dst`,
/// which must hold exactly 16 bytes per point (panics otherwise): for your own writes into a
/// mapped points buffer or a staging view ([`wgpu::BufferViewMut::slice`],
/// [`wgpu::QueueWriteBufferView::slice`]).
///
/// One 16-byte store per point, straight from the caller's slice: one pass over the points
/// instead of packing a host vector and copying it (on an H100 host, into its mapped
/// write-combined memory: 4.2 µs against 3.0 + 3.2 µs for 3000 points; docs/benchmarks).
pub fn write_points(dst: wgpu::WriteOnly<'_, [u8]>, points: &[Vec3]) {
    dst.into_chunks::<16>().0.write_iter(
        points
            .iter()
            .map(|p| bytemuck::cast([p.x, p.y, p.z, 1.0f32])),
    );
}

/// The next query's generation: tickets carry it, and buffers take only their own in-flight one.
static NEXT_GENERATION: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// The uniforms of `shaders/query.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct QueryUniforms {
    n_points: u32,
    streams: u32,
    normals: u32,
    scale: f32,
    center: [f32; 4],
}
