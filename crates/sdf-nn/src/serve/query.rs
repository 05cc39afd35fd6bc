//! Serving a [`NeuralSdf`] to code that queries it all the time (a planner checking collisions,
//! a renderer, a physics step), the way wgpu code is written: the caller owns the buffers, work
//! is recorded into the caller's encoder, a submission returns at once, and reading back is a
//! separate step that the caller may skip.
//!
//! - [`NeuralSdf::create_query_buffers`] makes a [`QueryBuffers`]: a points buffer
//!   ([`QueryBuffers::points`], `array<vec4<f32>>`, xyz used), a results buffer
//!   ([`QueryBuffers::results`]: `array<f32>` of distances, or with
//!   [`QueryOutputs::ValuesAndNormals`] `array<vec4<f32>>` of (distance, normal)), the network's
//!   scratch where it needs any, and a mappable staging buffer (or, on CPU and integrated adapters, mappable points
//!   and results buffers instead: [`QueryTransfer`]). Create it once, reuse it for every query.
//! - [`NeuralSdf::record_query`] records a query of the first `n` points into your encoder.
//!   The results stay on the GPU: bind [`QueryBuffers::results`] in your next pass. Your own
//!   pass may also have written [`QueryBuffers::points`] (it is a storage buffer).
//! - [`NeuralSdf::submit_query`] uploads points, records, copies the results to the staging
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
//! Distances and normals follow [`NeuralSdf`]'s rule outside the model's box, and are in mesh
//! units and coordinates (or, with [`QuerySpace::Normalized`], in the model's cube). Every
//! host-side method of [`NeuralSdf`] (`eval`, `eval_normalized`, `eval_with_normals`, the timed
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

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use glam::Vec3;

use crate::gpu::{GpuContext, GpuError, GpuTimer, entry};
use crate::nglod::gpu::NglodEvalBinding;
use crate::serve::neural::{GpuNetwork, NeuralSdf, NeuralSdfError};
use crate::shaders;
use crate::siren::eval::QueryLaunch;

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

/// Describes a [`QueryBuffers`] (see [`NeuralSdf::create_query_buffers`]).
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
    /// How [`NeuralSdf::submit_query`] moves points in and results out.
    pub transfer: QueryTransfer,
}

/// How [`NeuralSdf::submit_query`] and [`QueryBuffers::wait`] move points and results between
/// the host and the buffers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum QueryTransfer {
    /// [`QueryTransfer::Mapped`] where [`GpuContext::maps_storage_cheaply`] (CPU and integrated
    /// adapters), [`QueryTransfer::Staged`] elsewhere.
    #[default]
    Auto,
    /// Copies through an upload belt and a staging buffer, recorded in the query's submission:
    /// what a discrete GPU needs, whose mappable memory is slow for kernels.
    Staged,
    /// No copies: the points buffer is mapped and written, the results buffer mapped and read.
    /// On lavapipe a 10-point query costs two copy commands less. Needs the device feature
    /// `MAPPABLE_PRIMARY_BUFFERS` (asked for wherever the adapter has it: [`GpuContext::maps_storage`]). The results buffer
    /// is then mapped from [`NeuralSdf::submit_query`] until the [`QueryResults`] of its ticket
    /// is dropped: no submission may use [`QueryBuffers::results`] meanwhile
    /// ([`NeuralSdf::record_query`] refuses with [`QueryError::Busy`]).
    Mapped,
}

/// Errors of the serving API.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    /// More points than the buffers hold.
    #[error("{requested} points do not fit query buffers of capacity {capacity}")]
    Capacity {
        /// Points asked for.
        requested: usize,
        /// The buffers' capacity.
        capacity: u32,
    },
    /// The buffers were made for another model or another device.
    #[error("these query buffers belong to another model or another device")]
    Foreign,
    /// A submission is still in flight on these buffers (wait for it first).
    #[error("a query is already in flight on these buffers; wait for its ticket first")]
    Busy,
    /// The ticket is not the one in flight on these buffers.
    #[error("this ticket does not belong to the query in flight on these buffers")]
    StaleTicket,
    /// The capacity is zero or the buffers would exceed the device's limits.
    #[error("invalid query buffers: {0}")]
    Invalid(String),
    /// A query point from the host is NaN or infinite (kernels need not propagate NaN, so its
    /// result would be an arbitrary number rather than NaN).
    #[error("query point {index} is not finite: {point}")]
    NonFinitePoint {
        /// Its index in the batch.
        index: usize,
        /// The point.
        point: Vec3,
    },
}

/// The state of the staging buffer's mapping.
#[derive(Debug, Default)]
enum MapState {
    /// Not mapped, nothing in flight.
    #[default]
    Idle,
    /// `map_async` was called; its callback has not run yet.
    Pending,
    /// Mapped and readable.
    Mapped,
    /// The mapping failed.
    Failed(String),
}

/// The staging buffer's [`MapState`], and a condition variable its `map_async` callback
/// notifies: the callback may run on another thread's `poll` after ours has returned (devices
/// are shared), so a waiter waits for the callback itself, not only for the submission.
#[derive(Debug, Default)]
struct MapSlot {
    state: Mutex<MapState>,
    changed: Condvar,
}

impl MapSlot {
    fn lock(&self) -> MutexGuard<'_, MapState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn set(&self, state: MapState) {
        *self.lock() = state;
        self.changed.notify_all();
    }

    /// Whether the requested mapping's callback has not run yet.
    fn is_pending(&self) -> bool {
        matches!(*self.lock(), MapState::Pending)
    }

    /// Asks for `slice` to be mapped for `mode`, the callback settling this slot.
    fn request(self: &Arc<Self>, slice: wgpu::BufferSlice<'_>, mode: wgpu::MapMode) {
        self.set(MapState::Pending);
        let map = Arc::clone(self);
        slice.map_async(mode, move |r| {
            map.set(match r {
                Ok(()) => MapState::Mapped,
                Err(e) => MapState::Failed(e.to_string()),
            });
        });
    }

    /// Waits (up to 10 s, polling `device`) for the requested mapping: `Ok` once mapped, the
    /// reason otherwise. The slot is left idle.
    fn settle(&self, device: &wgpu::Device) -> Result<(), String> {
        match self.take_settled(device, Duration::from_secs(10)) {
            MapState::Mapped => Ok(()),
            MapState::Failed(reason) => Err(reason),
            MapState::Idle | MapState::Pending => Err("the mapping did not complete".into()),
        }
    }

    /// Takes the state once it is no longer [`MapState::Pending`], polling `device` between
    /// waits; [`MapState::Pending`] if that takes longer than `timeout`.
    fn take_settled(&self, device: &wgpu::Device, timeout: Duration) -> MapState {
        let deadline = Instant::now() + timeout;
        let mut state = self.lock();
        while matches!(*state, MapState::Pending) {
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            drop(state);
            let _ = device.poll(wgpu::PollType::Poll);
            state = self.lock();
            if matches!(*state, MapState::Pending) {
                let wait = (deadline - now).min(Duration::from_millis(1));
                state = self
                    .changed
                    .wait_timeout(state, wait)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
        std::mem::take(&mut *state)
    }
}

/// Reusable, caller-owned buffers for queries of up to `capacity` points of one
/// [`NeuralSdf`] on one device. See the [module docs](self).
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
    /// Mapped upload buffers that [`NeuralSdf::submit_query`] writes the points into and copies
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
    /// by [`NeuralSdf::submit_query`] right after it submits, for the same count and level of
    /// detail, while the GPU works and the host would only wait (one slot for plain queries,
    /// one for timed ones). On an H100 that takes the 3.4–3.7 µs of encoding out of the next
    /// query's wall time (BENCHMARKS.md, session 21).
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
    Nglod(NglodEvalBinding),
    /// SIREN on a kernel family that runs an inference in one dispatch (tiled fused,
    /// cooperative matrices): the same, straight from `points` to `results`.
    Siren(QueryLaunch),
    /// SIREN: `prepare` (points to the network's input rows), the network's launches bound to
    /// `net_in` and `net_out`, `finish` (its values and gradients to distances and normals).
    Staged(Box<Stages>),
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

    /// How many queries [`NeuralSdf::submit_query`] submitted from commands recorded ahead.
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
/// write-combined memory: 4.2 µs against 3.0 + 3.2 µs for 3000 points; BENCHMARKS.md).
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

impl NeuralSdf {
    /// Buffers for queries of this model on `gpu`'s device (see the [module docs](self)).
    pub fn create_query_buffers(
        &self,
        gpu: &GpuContext,
        desc: &QueryBuffersDescriptor<'_>,
    ) -> Result<QueryBuffers, NeuralSdfError> {
        if desc.capacity == 0 {
            return Err(QueryError::Invalid("capacity 0".into()).into());
        }
        let label = desc.label.unwrap_or("hwsdf query");
        let cap = u64::from(desc.capacity);
        let normals = desc.outputs == QueryOutputs::ValuesAndNormals;
        let out_floats = u64::from(desc.outputs.floats_per_point());
        let storage =
            |what: &str, bytes: u64| gpu.storage_zeroed(&format!("{label} {what}"), bytes);
        let mappable = gpu.maps_storage();
        let mapped = match desc.transfer {
            QueryTransfer::Auto => gpu.maps_storage_cheaply(),
            QueryTransfer::Staged => false,
            QueryTransfer::Mapped if mappable => true,
            QueryTransfer::Mapped => {
                return Err(QueryError::Invalid(format!(
                    "QueryTransfer::Mapped needs MAPPABLE_PRIMARY_BUFFERS, which {} lacks",
                    gpu.describe()
                ))
                .into());
            }
        };
        let (points, results, staging) = if mapped {
            let points = gpu.storage_zeroed_with(
                &format!("{label} points"),
                cap * 16,
                wgpu::BufferUsages::MAP_WRITE,
            )?;
            let results = gpu.storage_zeroed_with(
                &format!("{label} results"),
                cap * out_floats * 4,
                wgpu::BufferUsages::MAP_READ,
            )?;
            let staging = results.clone();
            (points, results, staging)
        } else {
            // The storage buffers first: their sizes are checked against the device's limits,
            // and the staging buffer is no larger than the results (wgpu panics on a buffer
            // above max_buffer_size).
            let points = storage("points", cap * 16)?;
            let results = storage("results", cap * out_floats * 4)?;
            let staging = gpu.device().create_buffer(&wgpu::BufferDescriptor {
                label: Some(&format!("{label} staging")),
                size: cap * out_floats * 4,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            (points, results, staging)
        };
        let transform = match desc.space {
            QuerySpace::Mesh => (self.normalization().center, self.normalization().scale),
            QuerySpace::Normalized => (Vec3::ZERO, 1.0),
        };
        let map = transform.0.extend(transform.1);
        let one_dispatch = self.with_gpu(gpu, |net, _| match net {
            GpuNetwork::Nglod(m) => Ok(Some(Kernels::Nglod(
                m.eval_binding(gpu, &points, &results, normals, transform)?,
            ))),
            GpuNetwork::Siren(s) => Ok(s
                .query_launch(gpu, &points, &results, desc.capacity, normals, map)?
                .map(Kernels::Siren)),
        })?;
        let kernels = match one_dispatch {
            Some(kernels) => kernels,
            None => {
                // SIREN takes its gradient as three tangent rows per point.
                let in_floats = if normals { 12 } else { 3 };
                let net_in = storage("network input", cap * in_floats * 4)?;
                let net_out = storage("network output", cap * out_floats * 4)?;
                let uniforms = gpu.uniform(
                    &format!("{label} uniforms"),
                    &QueryUniforms {
                        n_points: 0,
                        streams: normals.into(),
                        normals: normals.into(),
                        scale: transform.1,
                        center: transform.0.extend(0.0).to_array(),
                    },
                );
                let bind = |entry_point: &str, entries: &[(u32, &wgpu::Buffer)]| {
                    let pipeline = gpu.pipeline(&shaders::QUERY, entry_point, &[])?;
                    let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
                        .iter()
                        .map(|&(binding, b)| entry(binding, b))
                        .collect();
                    let group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some(entry_point),
                        layout: &pipeline.get_bind_group_layout(0),
                        entries: &entries,
                    });
                    Ok::<_, GpuError>((pipeline, group))
                };
                let prepare = bind("prepare", &[(0, &uniforms), (1, &points), (2, &net_in)])?;
                let finish = bind(
                    "finish",
                    &[(0, &uniforms), (1, &points), (3, &net_out), (4, &results)],
                )?;
                Kernels::Staged(Box::new(Stages {
                    net_in,
                    net_out,
                    uniforms,
                    written: None,
                    prepare,
                    finish,
                    bound: None,
                }))
            }
        };
        Ok(QueryBuffers {
            model: self.id(),
            device: gpu.device().clone(),
            capacity: desc.capacity,
            outputs: desc.outputs,
            space: desc.space,
            points,
            results,
            staging,
            mapped,
            upload_map: Arc::new(MapSlot::default()),
            kernels,
            belt: wgpu::util::StagingBelt::new(gpu.device().clone(), cap * 16),
            map: Arc::new(MapSlot::default()),
            generation: 0,
            in_flight: None,
            recorded: None,
            prepared: [None, None],
            prepared_used: 0,
        })
    }

    /// Records a query of the first `n` points of [`QueryBuffers::points`] into `enc`; the
    /// results land in [`QueryBuffers::results`] when `enc` has run, and stay on the GPU.
    ///
    /// The point count goes through the queue when it changes, taking effect at the next
    /// submission: record one [`QueryBuffers`] at most once per submission (use one per batch).
    pub fn record_query(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &mut QueryBuffers,
        n: u32,
    ) -> Result<(), NeuralSdfError> {
        self.record_query_timed(gpu, enc, buffers, n, false)
    }

    /// Uploads `points`, records their query, copies the results to the staging buffer and
    /// submits, without waiting: redeem the ticket with [`QueryBuffers::wait`].
    pub fn submit_query(
        &self,
        gpu: &GpuContext,
        buffers: &mut QueryBuffers,
        points: &[Vec3],
    ) -> Result<QueryTicket, NeuralSdfError> {
        self.submit_query_timed(gpu, buffers, points, false)
    }

    /// [`NeuralSdf::submit_query`], with the query's passes timed by this model's
    /// [`GpuTimer`] when `timed` (read it with [`NeuralSdf::read_query_ns`] after waiting).
    pub(crate) fn submit_query_timed(
        &self,
        gpu: &GpuContext,
        buffers: &mut QueryBuffers,
        points: &[Vec3],
        timed: bool,
    ) -> Result<QueryTicket, NeuralSdfError> {
        if buffers.in_flight.is_some() {
            return Err(QueryError::Busy.into());
        }
        self.check_buffers(gpu, buffers)?;
        let lod = self.lod();
        let (n, submission) = if buffers.mapped {
            let n = buffers.upload_mapped(gpu, points)?;
            // Commands recorded for this count and level of detail are current only while the
            // uniforms still hold them: no other recording came in between.
            let prepared = buffers.prepared[usize::from(timed)]
                .take()
                .filter(|p| p.n == n && p.lod == lod && buffers.recorded == Some((n, lod)));
            let commands = match prepared {
                Some(p) => {
                    buffers.prepared_used += 1;
                    p.commands
                }
                None => {
                    let mut enc = gpu.device().create_command_encoder(&Default::default());
                    self.record_query_timed(gpu, &mut enc, buffers, n, timed)?;
                    enc.finish()
                }
            };
            (n, gpu.queue().submit([commands]))
        } else {
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            let n = buffers.upload_in(&mut enc, points)?;
            buffers.belt.finish();
            self.record_query_timed(gpu, &mut enc, buffers, n, timed)?;
            let bytes = buffers.result_bytes(n);
            if bytes > 0 {
                enc.copy_buffer_to_buffer(&buffers.results, 0, &buffers.staging, 0, bytes);
            }
            let submission = gpu.queue().submit([enc.finish()]);
            buffers.belt.recall();
            (n, submission)
        };
        let bytes = buffers.result_bytes(n);
        // Unique across every QueryBuffers, so a ticket is only ever taken by its own buffers.
        buffers.generation = NEXT_GENERATION.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if bytes > 0 {
            buffers
                .map
                .request(buffers.staging.slice(..bytes), wgpu::MapMode::Read);
        }
        buffers.in_flight = Some((buffers.generation, n));
        if buffers.mapped && n > 0 && buffers.one_dispatch() {
            // The next query, likely of the same size, recorded while this one runs. Only
            // this method submits it, once this query has been waited for and its results
            // unmapped, so the busy check does not apply. On failure the next query records
            // its own.
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            if self
                .record_unchecked(gpu, &mut enc, buffers, n, timed)
                .is_ok()
            {
                buffers.prepared[usize::from(timed)] = Some(Prepared {
                    n,
                    lod,
                    commands: enc.finish(),
                });
            }
        }
        Ok(QueryTicket {
            generation: buffers.generation,
            submission,
            n,
        })
    }

    /// The GPU nanoseconds of the last timed query's passes (first to last), from this
    /// model's timer; `None` without timestamp queries. Call after its ticket was waited on.
    pub(crate) fn read_query_ns(&self, gpu: &GpuContext) -> Result<Option<u64>, NeuralSdfError> {
        self.with_gpu(gpu, |_, timer| match timer {
            Some(t) => Ok(Some(t.read_ns(gpu)?)),
            None => Ok(None),
        })
    }

    fn check_buffers(&self, gpu: &GpuContext, buffers: &QueryBuffers) -> Result<(), QueryError> {
        if buffers.model != self.id() || buffers.device != *gpu.device() {
            return Err(QueryError::Foreign);
        }
        Ok(())
    }

    /// [`NeuralSdf::record_query`], bracketing the passes with the model's timer when `timed`
    /// and the device has timestamp queries (resolved into `enc`).
    fn record_query_timed(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &mut QueryBuffers,
        n: u32,
        timed: bool,
    ) -> Result<(), NeuralSdfError> {
        self.check_buffers(gpu, buffers)?;
        // With mapped transfers the results buffer is mapped from `submit_query` until its
        // results are dropped: no other submission may use it meanwhile.
        if buffers.mapped && (buffers.in_flight.is_some() || buffers.map_busy()) {
            return Err(QueryError::Busy.into());
        }
        self.record_unchecked(gpu, enc, buffers, n, timed)
    }

    /// [`NeuralSdf::record_query_timed`] without its checks that `buffers` are this model's
    /// and, when mapped, free: both callers have made the first (`submit_query_timed` on
    /// entry), and the commands recorded ahead run only once the buffers are free.
    fn record_unchecked(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &mut QueryBuffers,
        n: u32,
        timed: bool,
    ) -> Result<(), NeuralSdfError> {
        buffers.check_count(n as usize)?;
        if n == 0 {
            return Ok(());
        }
        let lod = self.lod();
        buffers.recorded = Some((n, lod));
        let normals = buffers.outputs == QueryOutputs::ValuesAndNormals;
        self.with_gpu(gpu, |net, timer| {
            let timer: Option<&GpuTimer> = timer.filter(|_| timed);
            match (net, &mut buffers.kernels) {
                (GpuNetwork::Nglod(m), Kernels::Nglod(binding)) => {
                    m.record_eval(gpu, enc, binding, n, lod, timer)?
                }
                (GpuNetwork::Siren(s), Kernels::Siren(launch)) => {
                    s.refresh_pack(enc);
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("hwsdf query"),
                        timestamp_writes: timer.map(|t| t.writes(true, true)),
                    });
                    launch.record(gpu, &mut pass, n);
                }
                (GpuNetwork::Siren(s), Kernels::Staged(st)) => {
                    if st.written != Some(n) {
                        // n_points is the first field of the uniforms.
                        gpu.queue()
                            .write_buffer(&st.uniforms, 0, bytemuck::bytes_of(&n));
                        st.written = Some(n);
                    }
                    let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
                    {
                        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                            label: Some("hwsdf query prepare"),
                            timestamp_writes: timer.map(|t| t.writes(true, false)),
                        });
                        pass.set_pipeline(&st.prepare.0);
                        pass.set_bind_group(0, &st.prepare.1, &[]);
                        pass.dispatch_workgroups(x, y, 1);
                    }
                    if st.bound.as_ref().map(|b| b.0) != Some(n) {
                        let launches = s.bound_eval(gpu, &st.net_in, &st.net_out, n, normals)?;
                        st.bound = Some((n, launches));
                    }
                    match &st.bound {
                        Some((_, Some(launches))) => s.record_launches(enc, launches),
                        _ => s.record_eval(gpu, enc, &st.net_in, &st.net_out, n, normals)?,
                    }
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("hwsdf query finish"),
                        timestamp_writes: timer.map(|t| t.writes(false, true)),
                    });
                    pass.set_pipeline(&st.finish.0);
                    pass.set_bind_group(0, &st.finish.1, &[]);
                    pass.dispatch_workgroups(x, y, 1);
                }
                _ => return Err(QueryError::Foreign.into()),
            }
            if let Some(t) = timer {
                t.resolve(enc);
            }
            Ok(())
        })
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use crate::serve::neural::GpuNetwork;
    use crate::{GpuContext, NeuralSdf, Nglod, NglodConfig, Normalization, Siren, SirenConfig};

    fn gpu() -> &'static GpuContext {
        GpuContext::shared().expect("a GPU adapter (lavapipe in CI)")
    }

    fn sdf(file: crate::ModelFile) -> NeuralSdf {
        NeuralSdf::from_model_file(file).unwrap()
    }

    /// Points in and around the model's cube, with an odd count.
    fn points() -> Vec<Vec3> {
        (0..301)
            .map(|i| {
                let t = i as f32 * 0.37;
                Vec3::new(t.sin(), (1.3 * t).cos(), (0.7 * t).sin()) * 1.2
            })
            .collect()
    }

    /// `write_points` packs every point (a length that is not 16 bytes per point panics).
    #[test]
    fn write_points_packs_vec4() {
        for n in [0, 1, 2, 301] {
            let pts = &points()[..n];
            let mut bytes = vec![0xAAu8; n * 16];
            super::write_points(wgpu::WriteOnly::from_mut(bytes.as_mut_slice()), pts);
            let want: Vec<[f32; 4]> = pts.iter().map(|p| [p.x, p.y, p.z, 1.0]).collect();
            assert_eq!(bytes, bytemuck::cast_slice::<_, u8>(&want), "{n} points");
        }
        let short = std::panic::catch_unwind(|| {
            let mut bytes = vec![0u8; 16];
            super::write_points(
                wgpu::WriteOnly::from_mut(bytes.as_mut_slice()),
                &points()[..2],
            );
        });
        assert!(short.is_err(), "a view too short for the points must panic");
    }

    fn assert_close(got: &[f32], want: &[f32], what: &str) {
        assert_eq!(got.len(), want.len(), "{what}");
        for (i, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                "{what} {i}: {a} vs {b}"
            );
        }
    }

    /// Serves model file `a`, checks it, uploads `b`'s parameters into its GPU network with
    /// `upload`, and checks that the next query answers with `b`'s values.
    fn check_upload(
        what: &str,
        a: crate::ModelFile,
        b: crate::ModelFile,
        upload: impl FnOnce(&mut GpuNetwork) -> Result<(), crate::NeuralSdfError>,
    ) {
        let (gpu, pts) = (gpu(), points());
        let served = sdf(a);
        let want_b = sdf(b).eval_cpu(&pts);
        let got = served.eval(gpu, &pts).unwrap();
        assert_close(&got, &served.eval_cpu(&pts), what);
        served.with_gpu(gpu, |net, _| upload(net)).unwrap();
        let got = served.eval(gpu, &pts).unwrap();
        assert_close(&got, &want_b, &format!("{what} after upload"));
    }

    /// A served model's networks skip refreshing their derived weights (NGLOD's MLP uniform,
    /// SIREN's packed row-blocked weights) on every query; new parameters uploaded into them must
    /// still reach the next query.
    #[test]
    fn frozen_networks_follow_uploads() {
        let gpu = gpu();
        let id = Normalization::identity();
        let a = Nglod::new(NglodConfig::small()).unwrap();
        // Same configuration, other parameters (the MLP's included).
        let b = Nglod::from_params(
            a.config().clone(),
            a.params().iter().map(|&x| 0.25 - 0.5 * x).collect(),
        )
        .unwrap();
        let (fa, fb) = (
            a.to_model_file(id, serde_json::Value::Null),
            b.to_model_file(id, serde_json::Value::Null),
        );
        // What the file holds (its grids rounded to f16).
        let b = Nglod::from_model_file(&fb).unwrap();
        check_upload("nglod", fa, fb, |net| match net {
            GpuNetwork::Nglod(m) => Ok(m.upload(gpu, &b)?),
            GpuNetwork::Siren(_) => unreachable!(),
        });
        let a = Siren::new(SirenConfig::small(), 1).unwrap();
        let b = Siren::new(SirenConfig::small(), 2).unwrap();
        let (fa, fb) = (
            a.to_model_file(id, serde_json::Value::Null),
            b.to_model_file(id, serde_json::Value::Null),
        );
        check_upload("siren", fa, fb, |net| match net {
            GpuNetwork::Siren(s) => Ok(s.upload(gpu, &b)?),
            GpuNetwork::Nglod(_) => unreachable!(),
        });
    }

    /// The serving types cross threads (a renderer's or a planner's workers): no field, such
    /// as the commands recorded ahead, may take that away.
    #[test]
    fn serving_types_are_send_and_sync() {
        fn send_sync<T: Send + Sync>() {}
        send_sync::<crate::QueryBuffers>();
        send_sync::<crate::serve::query::QueryTicket>();
        send_sync::<NeuralSdf>();
    }

    /// `submit_query` records the next query while this one runs and submits those commands
    /// when the next query has the same size and level of detail. A query of another size,
    /// another level of detail, or after another recording into the buffers (which rewrites
    /// their uniforms) must not run them; plain and timed queries alternate, as the reports
    /// run them. NGLOD's query is one dispatch on every adapter.
    #[test]
    fn prepared_queries_answer_like_fresh_ones() {
        use crate::serve::query::{QueryBuffers, QueryBuffersDescriptor, QueryTransfer};
        let gpu = gpu();
        if !gpu.maps_storage() {
            eprintln!("skipped: {} does not map storage buffers", gpu.describe());
            return;
        }
        let mut model = Nglod::new(NglodConfig::small()).unwrap();
        if model.needs_bands() {
            model.place_bands(|p| (p.length() - 0.6).abs()).unwrap();
        }
        let mut served =
            sdf(model.to_model_file(Normalization::identity(), serde_json::Value::Null));
        let mut buffers = served
            .create_query_buffers(
                gpu,
                &QueryBuffersDescriptor {
                    capacity: 301,
                    transfer: QueryTransfer::Mapped,
                    ..Default::default()
                },
            )
            .unwrap();
        // Every query gets points of its own, so stale commands show as stale results.
        let sets: Vec<Vec<Vec3>> = (0..8)
            .map(|k| {
                points()
                    .iter()
                    .map(|p| *p * (1.0 - 0.07 * k as f32))
                    .collect()
            })
            .collect();
        let query = |served: &NeuralSdf, buffers: &mut QueryBuffers, pts: &[Vec3], timed: bool| {
            let ticket = served.submit_query_timed(gpu, buffers, pts, timed).unwrap();
            let mut got = Vec::new();
            buffers.wait(gpu, ticket).unwrap().extend_values(&mut got);
            if timed {
                served.read_query_ns(gpu).unwrap();
            }
            assert_close(
                &got,
                &served.eval_cpu(pts),
                &format!("{} points", pts.len()),
            );
        };
        for (i, pts) in sets[..4].iter().enumerate() {
            query(&served, &mut buffers, pts, i % 2 == 1);
        }
        // The third and fourth ran on commands recorded by the first and second.
        assert_eq!(buffers.prepared_used(), 2);
        // Another size.
        query(&served, &mut buffers, &sets[4][..100], false);
        assert_eq!(buffers.prepared_used(), 2);
        // A recording of 7 points in between rewrites the uniforms: the commands recorded for
        // 100 points would answer only 7 of them.
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        served.record_query(gpu, &mut enc, &mut buffers, 7).unwrap();
        gpu.queue().submit([enc.finish()]);
        gpu.wait().unwrap();
        query(&served, &mut buffers, &sets[5][..100], false);
        assert_eq!(buffers.prepared_used(), 2);
        query(&served, &mut buffers, &sets[6][..100], false);
        assert_eq!(buffers.prepared_used(), 3);
        // Another level of detail.
        served.set_lod(Some(1)).unwrap();
        query(&served, &mut buffers, &sets[7][..100], false);
        assert_eq!(buffers.prepared_used(), 3);
    }

    /// A SIREN query larger than one of the network's launches takes the path that splits it
    /// and copies through the network's workspace; it must agree with the bound one.
    #[test]
    fn siren_queries_beyond_one_launch_are_split() {
        let gpu = gpu();
        let siren = Siren::new(SirenConfig::small(), 3).unwrap();
        let served = sdf(siren.to_model_file(Normalization::identity(), serde_json::Value::Null));
        let pts = points();
        let want = served.eval_cpu(&pts);
        assert_close(&served.eval(gpu, &pts).unwrap(), &want, "one launch");
        served
            .with_gpu(gpu, |net, _| {
                if let GpuNetwork::Siren(s) = net {
                    let options = crate::siren::SirenGpuOptions {
                        max_points_per_launch: 64,
                        ..*s.options()
                    };
                    s.set_options(gpu, &options)?;
                }
                Ok(())
            })
            .unwrap();
        // Another count: the launches bound for 301 points would otherwise be reused.
        let pts = &pts[..300];
        let got = served.eval(gpu, pts).unwrap();
        assert_close(&got, &want[..300], "split into launches of 64");
        let normals = served.eval_with_normals(gpu, pts).unwrap();
        let want_n = served.eval_with_normals_cpu(pts);
        for (i, ((da, na), (db, nb))) in normals.iter().zip(&want_n).enumerate() {
            assert!(
                (da - db).abs() <= 1e-4 * db.abs().max(1.0),
                "{i}: {da} vs {db}"
            );
            assert!((*na - *nb).length() < 1e-3, "{i}: {na} vs {nb}");
        }
    }

    /// A SIREN whose kernels run an inference in one dispatch answers queries in that one
    /// dispatch, points to results (the tiled fused kernel here; the cooperative-matrix one is
    /// checked where the adapter has it, in `tests/siren_gpu.rs`); the row-blocked kernels, and
    /// a capacity beyond the fused kernel's batches, go through `query.wgsl`'s two ends. Both
    /// answer alike, in mesh coordinates, inside the box and beyond it.
    #[test]
    fn siren_queries_take_one_dispatch_where_the_kernels_allow() {
        let gpu = gpu();
        let norm = Normalization {
            center: Vec3::new(-2.0, 0.5, 1.0),
            scale: 0.25,
        };
        let siren = Siren::new(SirenConfig::small(), 5).unwrap();
        let pts: Vec<Vec3> = points().iter().map(|&p| norm.to_original(p)).collect();
        for (kernels, capacity, one_dispatch) in [
            (crate::siren::LayerKernels::Tiled, 400, true),
            (crate::siren::LayerKernels::RowBlocked, 400, false),
            // Past the fused kernel's batches on a CPU adapter; GPUs fuse every batch.
            (crate::siren::LayerKernels::Tiled, 10_000, !gpu.is_cpu()),
        ] {
            let mut served = sdf(siren.to_model_file(norm, serde_json::Value::Null));
            served.set_siren_kernels(kernels).unwrap();
            for outputs in [
                crate::QueryOutputs::Values,
                crate::QueryOutputs::ValuesAndNormals,
            ] {
                let desc = crate::QueryBuffersDescriptor {
                    capacity,
                    outputs,
                    ..Default::default()
                };
                let mut buffers = served.create_query_buffers(gpu, &desc).unwrap();
                assert_eq!(
                    matches!(buffers.kernels, super::Kernels::Siren(_)),
                    one_dispatch,
                    "{kernels:?} capacity {capacity}"
                );
                let what = format!("{kernels:?} {outputs:?} capacity {capacity}");
                let values = served.eval_cpu(&pts);
                let normals = served.eval_with_normals_cpu(&pts);
                // Counts that change between queries: the one dispatch rewrites its row count.
                for n in [301, 17, 300] {
                    let ticket = served.submit_query(gpu, &mut buffers, &pts[..n]).unwrap();
                    let got = buffers.wait(gpu, ticket).unwrap().floats();
                    let what = format!("{what} n={n}");
                    if outputs == crate::QueryOutputs::Values {
                        assert_close(&got, &values[..n], &what);
                        continue;
                    }
                    assert_eq!(got.len(), 4 * n, "{what}");
                    for (i, (g, (d, n))) in got.chunks_exact(4).zip(&normals).enumerate() {
                        assert!((g[0] - d).abs() <= 1e-4 * d.abs().max(1.0), "{what} {i}");
                        let gn = Vec3::new(g[1], g[2], g[3]);
                        assert!((gn - *n).length() < 1e-3, "{what} {i}: {gn} vs {n}");
                    }
                }
            }
        }
    }

    /// The fused kernel's query mode with several register blocks of rows per invocation: a
    /// narrow network's workgroup then holds more rows than invocations, and the head and the
    /// normals' finish handle two or three rows each.
    #[test]
    fn siren_one_dispatch_queries_with_row_blocks() {
        let gpu = gpu();
        let norm = Normalization {
            center: Vec3::new(0.5, 1.0, -1.5),
            scale: 2.0,
        };
        let cfg = SirenConfig {
            width: 20,
            hidden_layers: 2,
            omega0: 30.0,
        };
        let siren = Siren::new(cfg, 8).unwrap();
        let pts: Vec<Vec3> = points().iter().map(|&p| norm.to_original(p)).collect();
        for blocks in 1..=3 {
            let mut served = sdf(siren.to_model_file(norm, serde_json::Value::Null));
            served
                .set_siren_kernels(crate::siren::LayerKernels::Tiled)
                .unwrap();
            served
                .with_gpu(gpu, |net, _| {
                    if let GpuNetwork::Siren(s) = net {
                        let options = crate::siren::SirenGpuOptions {
                            fused_row_blocks: blocks,
                            ..*s.options()
                        };
                        s.set_options(gpu, &options)?;
                        assert_eq!(s.fused_row_blocks(gpu), Some(blocks));
                    }
                    Ok(())
                })
                .unwrap();
            let what = format!("{blocks} row blocks");
            assert_close(
                &served.eval(gpu, &pts).unwrap(),
                &served.eval_cpu(&pts),
                &what,
            );
            let got = served.eval_with_normals(gpu, &pts).unwrap();
            for (i, ((d, n), (wd, wn))) in got
                .iter()
                .zip(served.eval_with_normals_cpu(&pts))
                .enumerate()
            {
                assert!(
                    (d - wd).abs() <= 1e-4 * wd.abs().max(1.0),
                    "{what} {i}: {d} vs {wd}"
                );
                assert!((*n - wn).length() < 1e-3, "{what} {i}: {n} vs {wn}");
            }
        }
    }

    /// Changing a SIREN's kernels rebuilds its GPU side under a new identity: query buffers
    /// made before are refused, new ones answer on the new kernels. NGLOD has no kernels to
    /// choose.
    #[test]
    fn siren_kernels_change_refuses_old_buffers() {
        let gpu = gpu();
        let id = Normalization::identity();
        let siren = Siren::new(SirenConfig::small(), 4).unwrap();
        let mut served = sdf(siren.to_model_file(id, serde_json::Value::Null));
        let pts = points();
        let want = served.eval_cpu(&pts);
        let desc = crate::QueryBuffersDescriptor {
            capacity: pts.len() as u32,
            space: crate::QuerySpace::Normalized,
            ..Default::default()
        };
        let mut old = served.create_query_buffers(gpu, &desc).unwrap();
        served
            .set_siren_kernels(crate::siren::LayerKernels::Tiled)
            .unwrap();
        assert!(matches!(
            served.submit_query(gpu, &mut old, &pts),
            Err(crate::NeuralSdfError::Query(crate::QueryError::Foreign))
        ));
        let mut new = served.create_query_buffers(gpu, &desc).unwrap();
        let ticket = served.submit_query(gpu, &mut new, &pts).unwrap();
        let got = new.wait(gpu, ticket).unwrap().floats();
        assert_close(&got, &want, "tiled kernels");
        served
            .with_gpu(gpu, |net, _| match net {
                GpuNetwork::Siren(s) => {
                    assert!(s.runs_tiled());
                    Ok(())
                }
                GpuNetwork::Nglod(_) => unreachable!(),
            })
            .unwrap();
        let nglod = Nglod::new(NglodConfig::small()).unwrap();
        let mut served = sdf(nglod.to_model_file(id, serde_json::Value::Null));
        assert!(matches!(
            served.set_siren_kernels(crate::siren::LayerKernels::Tiled),
            Err(crate::NeuralSdfError::NoLayerKernels("nglod"))
        ));
    }
}
