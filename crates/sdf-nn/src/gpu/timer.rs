//! GPU time from timestamp queries: one span ([`GpuTimer`]) or one per pass ([`PassProfiler`]).

use super::{GpuContext, GpuError};

/// Pure GPU time of a piece of work, from two timestamp queries: one written when the work's
/// first compute pass begins, one when its last pass ends.
///
/// Use it in four steps, one measurement at a time:
/// 1. pass [`GpuTimer::writes`] as the `timestamp_writes` of the compute passes
///    (`first` for the first pass, `last` for the last; both for a single pass);
/// 2. call [`GpuTimer::resolve`] on the encoder after the last pass;
/// 3. submit the encoder;
/// 4. call [`GpuTimer::read_ns`], which waits for the GPU and returns the nanoseconds between
///    the two timestamps.
///
/// Work split over several submissions is timed per submission and the results summed, so the
/// host-side gaps between submissions are not counted.
///
/// ```no_run
/// # fn main() -> Result<(), sdf_nn::GpuError> {
/// use sdf_nn::gpu::{GpuContext, GpuTimer};
/// let gpu = GpuContext::new()?;
/// let Some(timer) = GpuTimer::new(&gpu) else {
///     println!("no timestamp queries on {}", gpu.describe());
///     return Ok(());
/// };
/// let mut enc = gpu.device().create_command_encoder(&Default::default());
/// {
///     let _pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
///         label: Some("timed"),
///         timestamp_writes: Some(timer.writes(true, true)),
///     });
///     // set_pipeline, set_bind_group, dispatch_workgroups ...
/// }
/// timer.resolve(&mut enc);
/// gpu.queue().submit([enc.finish()]);
/// println!("{} ns on the GPU", timer.read_ns(&gpu)?);
/// # Ok(())
/// # }
/// ```
#[derive(Debug)]
pub struct GpuTimer {
    stamps: Timestamps,
}

/// Bytes of a pair of resolved `u64` timestamps.
const TIMER_BYTES: u64 = 2 * std::mem::size_of::<u64>() as u64;

/// A timestamp query set of `pairs` start/end pairs, where it is resolved to, and a host-mappable
/// copy: what [`GpuTimer`] and [`PassProfiler`] share.
#[derive(Debug)]
struct Timestamps {
    queries: wgpu::QuerySet,
    /// Where the raw timestamps are resolved to (`QUERY_RESOLVE | COPY_SRC`).
    resolved: wgpu::Buffer,
    /// Host-mappable copy of `resolved`.
    readback: wgpu::Buffer,
    /// Nanoseconds per timestamp tick.
    period_ns: f64,
}

impl Timestamps {
    /// `pairs` pairs, or `None` when the device lacks [`wgpu::Features::TIMESTAMP_QUERY`].
    fn new(gpu: &GpuContext, label: &str, pairs: u32) -> Option<Self> {
        if !gpu.has_timestamps() {
            return None;
        }
        let device = gpu.device();
        let queries = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some(label),
            ty: wgpu::QueryType::Timestamp,
            count: 2 * pairs,
        });
        // A resolve destination is written at offsets aligned to QUERY_RESOLVE_BUFFER_ALIGNMENT
        // (we resolve at 0).
        let buffer = |what: &str, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(&format!("{label} {what}")),
                size: u64::from(pairs) * TIMER_BYTES,
                usage,
                mapped_at_creation: false,
            })
        };
        Some(Timestamps {
            queries,
            resolved: buffer(
                "resolve",
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            ),
            readback: buffer(
                "readback",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            period_ns: f64::from(gpu.queue().get_timestamp_period()),
        })
    }

    /// The writes of pair `i`: its start when a pass begins (`first`), its end when a pass
    /// ends (`last`).
    fn writes(&self, i: u32, first: bool, last: bool) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.queries,
            beginning_of_pass_write_index: first.then_some(2 * i),
            end_of_pass_write_index: last.then_some(2 * i + 1),
        }
    }

    /// Records the resolution of the first `pairs` pairs into `enc`.
    fn resolve(&self, enc: &mut wgpu::CommandEncoder, pairs: u32) {
        enc.resolve_query_set(&self.queries, 0..2 * pairs, &self.resolved, 0);
        enc.copy_buffer_to_buffer(
            &self.resolved,
            0,
            &self.readback,
            0,
            u64::from(pairs) * TIMER_BYTES,
        );
    }

    /// Waits for the submitted work and returns every pair's GPU nanoseconds from start to end
    /// (0 if the driver reports the end before the start).
    fn read_ns(&self, gpu: &GpuContext, label: &str) -> Result<Vec<u64>, GpuError> {
        let ticks: Vec<u64> = gpu.map_read(&self.readback, label)?;
        Ok(ticks
            .chunks_exact(2)
            .map(|t| (t[1].saturating_sub(t[0]) as f64 * self.period_ns).round() as u64)
            .collect())
    }
}

impl GpuTimer {
    /// A timer on `gpu`'s device, or `None` when the device lacks
    /// [`wgpu::Features::TIMESTAMP_QUERY`] (see [`GpuContext::has_timestamps`]).
    pub fn new(gpu: &GpuContext) -> Option<Self> {
        Timestamps::new(gpu, "gpu timer", 1).map(|stamps| GpuTimer { stamps })
    }

    /// The `timestamp_writes` of a compute pass: `first` writes the start timestamp when the
    /// pass begins, `last` the end timestamp when it ends. A single pass takes `(true, true)`;
    /// passes in between take no writes (`None` in their descriptor).
    pub fn writes(&self, first: bool, last: bool) -> wgpu::ComputePassTimestampWrites<'_> {
        self.stamps.writes(0, first, last)
    }

    /// Records the resolution of both timestamps into `enc`, after the last timed pass. Submit
    /// `enc` before calling [`GpuTimer::read_ns`].
    pub fn resolve(&self, enc: &mut wgpu::CommandEncoder) {
        self.stamps.resolve(enc, 1);
    }

    /// Waits for the submitted work and returns the GPU nanoseconds between the start and the
    /// end timestamp (0 if the driver reports the end before the start).
    pub fn read_ns(&self, gpu: &GpuContext) -> Result<u64, GpuError> {
        Ok(self.stamps.read_ns(gpu, "gpu timer")?[0])
    }
}

/// The GPU time of every pass of a sequence of compute passes, each timed by its own pair of
/// timestamps: a profile of a training step or a query, to find where its time goes. Every pass
/// must be begun with [`PassProfiler::begin_pass`] (one per launch gives a profile per launch).
/// Timing every pass adds a little to each; measure totals without it.
pub struct PassProfiler {
    stamps: Timestamps,
    capacity: u32,
    labels: Vec<String>,
}

/// One timed pass of a [`PassProfiler`].
#[derive(Clone, Debug, PartialEq)]
pub struct PassTime {
    /// The pass's label.
    pub label: String,
    /// GPU nanoseconds from its start to its end.
    pub ns: u64,
}

impl PassProfiler {
    /// A profiler of up to `passes` passes (at most 2048: wgpu's limit is 4096 queries), or
    /// `None` where the device lacks [`wgpu::Features::TIMESTAMP_QUERY`].
    pub fn new(gpu: &GpuContext, passes: u32) -> Option<Self> {
        let capacity = passes.clamp(1, 2048);
        Timestamps::new(gpu, "pass profiler", capacity).map(|stamps| PassProfiler {
            stamps,
            capacity,
            labels: Vec::new(),
        })
    }

    /// Begins a compute pass named `label`, timed while the profiler has room (the passes
    /// beyond its capacity run untimed and are not reported).
    pub fn begin_pass<'e>(
        &mut self,
        enc: &'e mut wgpu::CommandEncoder,
        label: &str,
    ) -> wgpu::ComputePass<'e> {
        let i = self.labels.len() as u32;
        let timed = i < self.capacity;
        if timed {
            self.labels.push(label.to_owned());
        }
        enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: timed.then(|| self.stamps.writes(i, true, true)),
        })
    }

    /// Records the resolution of every timestamp so far into `enc`, after the last pass.
    /// Submit `enc` before calling [`PassProfiler::read`].
    pub fn resolve(&self, enc: &mut wgpu::CommandEncoder) {
        if !self.labels.is_empty() {
            self.stamps.resolve(enc, self.labels.len() as u32);
        }
    }

    /// Waits for the submitted work and returns each timed pass in order, then forgets them
    /// (the profiler can time another sequence).
    pub fn read(&mut self, gpu: &GpuContext) -> Result<Vec<PassTime>, GpuError> {
        let labels = std::mem::take(&mut self.labels);
        if labels.is_empty() {
            return Ok(Vec::new());
        }
        let ns = self.stamps.read_ns(gpu, "pass profiler")?;
        Ok(labels
            .into_iter()
            .zip(ns)
            .map(|(label, ns)| PassTime { label, ns })
            .collect())
    }
}
