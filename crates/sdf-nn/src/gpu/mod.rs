//! The GPU context: adapter choice, device creation with checked limits, buffer helpers and a
//! pipeline cache that lives as long as the device.
//!
//! Adapter choice honours the same environment variables as wgpu's own tools:
//! - `WGPU_BACKEND` (e.g. `vulkan`, `metal`, `dx12`) restricts the backends;
//! - `HWSDF_ADAPTER` picks one adapter by its index in [`list_adapters`] (what `gpu-info`
//!   prints), its PCI bus id (`0000:65:00.0`; eight identical GPUs share a name but not a bus), or
//!   part of its name; `WGPU_ADAPTER_NAME` picks the first adapter whose name contains the value
//!   (case-insensitive). Either is an error when nothing matches, rather than a silent fallback;
//! - otherwise a real GPU (discrete, then integrated, then virtual) is preferred over a CPU
//!   adapter such as lavapipe.
//!
//! Every variable is read once, by [`GpuOptions::from_env`]; `HWSDF_MAPPABLE_STORAGE=0` does not
//! ask for `MAPPABLE_PRIMARY_BUFFERS` (see [`GpuContext::maps_storage`]), `HWSDF_NO_COOP=1`
//! leaves cooperative matrices off, `HWSDF_STEP_LAYOUT=gpu|cpu` forces SIREN's step layout.

mod adapter;
mod error;
mod launch;
mod options;
mod pending;
mod staged;
mod timer;

use std::borrow::Cow;
use std::collections::HashMap;
use std::fmt;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytemuck::Pod;
use wgpu::util::DeviceExt;

use crate::shaders::Shader;

pub use adapter::list_adapters;
use adapter::{describe_info, shares_host_memory};
pub use error::GpuError;
pub(crate) use launch::{GridLaunch, Launch, record_launches};
pub use options::{
    ENV_VARIABLES, GpuOptions, QueryKernel, SirenActivations, StepLayout,
    skip_device_select_layer_when_headless,
};
pub(crate) use pending::PendingRead;
pub(crate) use staged::UniformStager;
pub use timer::{GpuTimer, PassProfiler, PassTime};

/// Cache key of a compiled compute pipeline: shader, entry point and override constants.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
struct PipelineKey {
    shader: &'static str,
    entry: String,
    constants: Vec<(String, u64)>,
}

/// How long a wait for the GPU polls without blocking before it blocks, by default (GPUs
/// only; [`GpuContext::set_spin_wait`] changes it). A blocking wait wakes up late: on an H100
/// through Vulkan an empty submit and readback took 62.7 µs blocking and 25.9 µs polling
/// (docs/benchmarks "The query path"), which is most of a small query's wall time. Work that runs
/// longer than this gets the blocking wait, so a long training step spins for at most this
/// long per wait.
pub const SPIN_WAIT: Duration = Duration::from_millis(2);

/// One device and queue, the adapter they came from, and every pipeline compiled on them.
///
/// Create one per process (tests share one per test binary): on lavapipe each pipeline's first
/// compilation costs seconds of LLVM time, and the cache makes that a one-off.
pub struct GpuContext {
    adapter_info: wgpu::AdapterInfo,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipelines: Mutex<HashMap<PipelineKey, wgpu::ComputePipeline>>,
    max_dispatch: u32,
    /// The side of the square f16 × f16 → f32 cooperative-matrix tiles the device runs (16 or
    /// 8; tensor cores), if any.
    coop_tile: Option<u32>,
    /// How long a wait polls before it blocks, in nanoseconds ([`GpuContext::set_spin_wait`]).
    spin_wait_ns: AtomicU64,
    /// The options the context was made with.
    options: GpuOptions,
}

impl fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.describe())
            .finish_non_exhaustive()
    }
}

/// [`GpuContext::query_kernel`]'s rule: the forced kernel where the device runs it, else one
/// point per subgroup on a GPU with usable subgroups for batches below
/// [`SUBGROUP_KERNEL_MAX_ELEMENTS`].
fn choose_query_kernel(
    forced: Option<QueryKernel>,
    subgroups: bool,
    cpu: bool,
    elements: u64,
) -> QueryKernel {
    match forced {
        Some(QueryKernel::PerSubgroup) if subgroups => QueryKernel::PerSubgroup,
        Some(_) => QueryKernel::PerInvocation,
        None if subgroups && !cpu && elements < SUBGROUP_KERNEL_MAX_ELEMENTS => {
            QueryKernel::PerSubgroup
        }
        None => QueryKernel::PerInvocation,
    }
}

/// From this many points or rays on, a query without a named kernel runs one per invocation
/// even on a GPU ([`GpuContext::query_kernel`]): a batch this large fills the GPU one per
/// invocation, where the subgroup kernel issues several times the instructions per point (each
/// lane repeats the point's index arithmetic, and the reductions are extra). A round number
/// between the sizes the two kernels are made for, not a measurement: gpu-compare's `kernels`
/// stage times both at 10 to 10⁶ points.
pub const SUBGROUP_KERNEL_MAX_ELEMENTS: u64 = 1 << 16;

/// Copies the whole of a mapped `buffer` out as `T`s and unmaps it. `label` names the data in
/// errors.
pub(crate) fn copy_out_mapped<T: Pod>(
    buffer: &wgpu::Buffer,
    label: &str,
) -> Result<Vec<T>, GpuError> {
    let view = buffer
        .slice(..)
        .get_mapped_range()
        .map_err(|e| GpuError::Readback {
            label: label.to_owned(),
            reason: e.to_string(),
        })?;
    // The mapped bytes need not be aligned for T; copy through pod_collect.
    let out: Vec<T> = bytemuck::pod_collect_to_vec(&view);
    drop(view);
    buffer.unmap();
    Ok(out)
}

impl GpuContext {
    /// The wgpu device.
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The wgpu queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// Adapter name, type, backend and driver, as wgpu reports them.
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.adapter_info
    }

    /// One line naming the adapter, for reports: `"llvmpipe (LLVM 15.0.6, 256 bits) (Cpu, Vulkan, llvmpipe Mesa 22.3.6)"`.
    pub fn describe(&self) -> String {
        describe_info(&self.adapter_info)
    }

    /// Whether this is a CPU adapter (lavapipe, WARP, SwiftShader).
    pub fn is_cpu(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::Cpu
    }

    /// Whether `atomicAdd` on `atomic<f32>` in storage buffers is available.
    pub fn has_float_atomics(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::SHADER_FLOAT32_ATOMIC)
    }

    /// Whether GPU timestamp queries are available.
    pub fn has_timestamps(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// The options this context was made with (its capabilities' switches and the SIREN step
    /// layout, as [`GpuOptions::from_env`] read them for [`GpuContext::new`]).
    pub fn options(&self) -> &GpuOptions {
        &self.options
    }

    /// The side (16 or 8) of the square tiles in which the device multiplies f16 cooperative
    /// matrices into f32 (tensor cores from WGSL), which
    /// [`crate::siren::LayerKernels::CoopF16`] needs; `None` without them.
    pub fn coop_f16_tile(&self) -> Option<u32> {
        self.coop_tile
    }

    /// Whether storage buffers can be mapped at all (`MAPPABLE_PRIMARY_BUFFERS`, asked for
    /// wherever the adapter has it unless `HWSDF_MAPPABLE_STORAGE=0`): the host-side queries
    /// of [`crate::NeuralSdf`] then read and write mapped points and results
    /// ([`crate::QueryTransfer::Mapped`]), on discrete GPUs too.
    pub fn maps_storage(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::MAPPABLE_PRIMARY_BUFFERS)
    }

    /// Whether storage buffers can be mapped directly and cheaply: the device allows it
    /// (`MAPPABLE_PRIMARY_BUFFERS`) and its memory is the host's (a CPU or integrated adapter),
    /// so kernels read and write mapped memory at full speed and copies through staging
    /// buffers are pure overhead. On a discrete GPU mappable memory is slow for kernels.
    pub fn maps_storage_cheaply(&self) -> bool {
        self.maps_storage() && shares_host_memory(self.adapter_info.device_type)
    }

    /// A zeroed storage buffer (as [`GpuContext::storage_zeroed`]) with extra `usage`, e.g.
    /// `MAP_READ` where [`GpuContext::maps_storage_cheaply`].
    pub fn storage_zeroed_with(
        &self,
        label: &str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, GpuError> {
        let bytes = bytes.max(4).next_multiple_of(4);
        self.check_storage_size(label, bytes)?;
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes,
            usage: storage_usage() | usage,
            mapped_at_creation: false,
        }))
    }

    /// The subgroup size of every compute dispatch, where the adapter has a single one.
    pub fn fixed_subgroup_size(&self) -> Option<u32> {
        let info = &self.adapter_info;
        (info.subgroup_min_size == info.subgroup_max_size).then_some(info.subgroup_min_size)
    }

    /// The widest subgroup the adapter may run, where the device has subgroup operations and a
    /// workgroup of `workgroup` invocations holds whole subgroups of every width the adapter
    /// may run (what the one-element-per-subgroup kernels need to count their elements).
    pub fn subgroups_within(&self, workgroup: u32) -> Option<u32> {
        let info = &self.adapter_info;
        let (min, max) = (info.subgroup_min_size, info.subgroup_max_size);
        let usable = self.device.features().contains(wgpu::Features::SUBGROUP)
            && min >= 1
            && max <= workgroup
            && workgroup.is_multiple_of(max)
            && workgroup.is_multiple_of(min);
        usable.then_some(max)
    }

    /// The kernel of an NGLOD, hash-grid or scene query of `elements` points or rays where the
    /// caller names none: `HWSDF_QUERY_KERNEL` ([`GpuOptions::query_kernel`]) if set, else
    /// [`QueryKernel::PerSubgroup`] on a GPU (not a CPU adapter) whose subgroups fit a
    /// workgroup of 64, for batches below [`SUBGROUP_KERNEL_MAX_ELEMENTS`], else
    /// [`QueryKernel::PerInvocation`]. A forced `subgroup` on a device without usable subgroups
    /// falls back to [`QueryKernel::PerInvocation`].
    pub fn query_kernel(&self, elements: u64) -> QueryKernel {
        choose_query_kernel(
            self.options.query_kernel,
            self.subgroups_within(64).is_some(),
            self.is_cpu(),
            elements,
        )
    }

    /// The kernel of an NGLOD or hash-grid training step of `rows` rows (points × level
    /// prefixes) where the caller names none: `HWSDF_TRAIN_KERNEL`
    /// ([`GpuOptions::train_kernel`]) if set, else the rule of [`GpuContext::query_kernel`]
    /// (one row per subgroup on a GPU with usable subgroups below
    /// [`SUBGROUP_KERNEL_MAX_ELEMENTS`] rows). A step of the default batch (2048 points) is
    /// 2048 rows, a few per SM of a large GPU when each invocation takes one: the same
    /// latency-bound shape as a query of 3000 points.
    pub fn train_kernel(&self, rows: u64) -> QueryKernel {
        choose_query_kernel(
            self.options.train_kernel,
            self.subgroups_within(64).is_some(),
            self.is_cpu(),
            rows,
        )
    }

    /// Whether [`GpuContext::query_kernel`] may choose [`QueryKernel::PerSubgroup`] for some
    /// batch size on this device.
    pub fn may_use_subgroup_queries(&self) -> bool {
        self.query_kernel(0) == QueryKernel::PerSubgroup
    }

    /// Where a SIREN's activations live in the renderer's and the scene queries' kernels:
    /// `HWSDF_SIREN_ACTIVATIONS` ([`GpuOptions::siren_activations`]) if set, else
    /// [`SirenActivations::Scratch`] on a CPU adapter (for SIRENs at least 32 units wide; a
    /// kernel of narrower ones keeps private arrays unless the variable asks for scratch) and
    /// [`SirenActivations::Private`] on a GPU.
    pub fn siren_activations(&self) -> SirenActivations {
        self.options.siren_activations.unwrap_or(if self.is_cpu() {
            SirenActivations::Scratch
        } else {
            SirenActivations::Private
        })
    }

    /// The limits the device was created with.
    pub fn limits(&self) -> wgpu::Limits {
        self.device.limits()
    }

    /// Checks a buffer size against the device limits for a buffer bound as storage.
    pub fn check_storage_size(&self, label: &str, bytes: u64) -> Result<(), GpuError> {
        Self::check_storage_size_in(&self.device.limits(), label, bytes)
    }

    /// [`GpuContext::check_storage_size`] against given `limits`: for checks before a device
    /// exists, or with limits smaller than the device's (tests of the error paths).
    pub fn check_storage_size_in(
        limits: &wgpu::Limits,
        label: &str,
        bytes: u64,
    ) -> Result<(), GpuError> {
        if bytes > limits.max_buffer_size {
            return Err(GpuError::BufferTooLarge {
                label: label.to_owned(),
                requested: bytes,
                limit_name: "max_buffer_size",
                limit: limits.max_buffer_size,
            });
        }
        if bytes > limits.max_storage_buffer_binding_size {
            return Err(GpuError::BufferTooLarge {
                label: label.to_owned(),
                requested: bytes,
                limit_name: "max_storage_buffer_binding_size",
                limit: limits.max_storage_buffer_binding_size,
            });
        }
        Ok(())
    }

    /// A storage buffer (also a copy source and destination) holding `data`.
    pub fn storage_from_slice<T: Pod>(
        &self,
        label: &str,
        data: &[T],
    ) -> Result<wgpu::Buffer, GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        // wgpu rejects zero-sized bindings; keep one element so empty inputs still bind.
        if bytes.is_empty() {
            return self.storage_zeroed(label, 4);
        }
        self.check_storage_size(label, bytes.len() as u64)?;
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: storage_usage(),
            }))
    }

    /// A zero-filled storage buffer of `bytes` bytes (rounded up to a multiple of 4).
    pub fn storage_zeroed(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        // wgpu zero-initialises new buffers, so no clear pass is needed.
        self.storage_zeroed_with(label, bytes, wgpu::BufferUsages::empty())
    }

    /// A uniform buffer holding `value`, writable later with [`GpuContext::write`].
    pub fn uniform<T: Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::bytes_of(value),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// Writes `data` at the start of `buffer`; it takes effect before the next submission.
    pub fn write<T: Pod>(&self, buffer: &wgpu::Buffer, data: &[T]) -> Result<(), GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.len() as u64 > buffer.size() {
            return Err(GpuError::BufferTooLarge {
                label: "write".into(),
                requested: bytes.len() as u64,
                limit_name: "destination buffer size",
                limit: buffer.size(),
            });
        }
        self.queue.write_buffer(buffer, 0, bytes);
        Ok(())
    }

    /// Fills `buffer` with zeros (submitted at once, not waited on).
    pub fn zero(&self, buffer: &wgpu::Buffer) {
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(buffer, 0, None);
        self.queue.submit([enc.finish()]);
    }

    /// Copies the whole of `buffer` back to the host and waits for it.
    pub fn read_back<T: Pod>(&self, buffer: &wgpu::Buffer) -> Result<Vec<T>, GpuError> {
        self.read_back_range(buffer, 0, buffer.size() / std::mem::size_of::<T>() as u64)
    }

    /// Copies `count` elements of type `T` starting at element `first` back to the host.
    pub fn read_back_range<T: Pod>(
        &self,
        buffer: &wgpu::Buffer,
        first: u64,
        count: u64,
    ) -> Result<Vec<T>, GpuError> {
        let size = std::mem::size_of::<T>() as u64;
        let label = format!("{:?}", buffer);
        let range = first
            .checked_mul(size)
            .zip(count.checked_mul(size))
            .and_then(|(offset, bytes)| Some((offset, bytes, offset.checked_add(bytes)?)));
        let Some((offset, bytes, _)) = range.filter(|&(offset, bytes, end)| {
            end <= buffer.size() && bytes.is_multiple_of(4) && offset.is_multiple_of(4)
        }) else {
            return Err(GpuError::Readback {
                label,
                reason: format!(
                    "elements {first}..+{count} of {size} bytes are outside the {}-byte buffer or not 4-byte aligned",
                    buffer.size()
                ),
            });
        };
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback staging"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(buffer, offset, &staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        self.map_read(&staging, &label)
    }

    /// Waits for the submitted work, then maps `buffer` (`MAP_READ`) and copies it out as `T`s.
    /// `label` names the data in errors.
    pub(crate) fn map_read<T: Pod>(
        &self,
        buffer: &wgpu::Buffer,
        label: &str,
    ) -> Result<Vec<T>, GpuError> {
        let error = |reason: String| GpuError::Readback {
            label: label.to_owned(),
            reason,
        };
        let slice = buffer.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|e| error(e.to_string()))?
            .map_err(|e| error(e.to_string()))?;
        copy_out_mapped(buffer, label)
    }

    /// How long a wait polls without blocking before it blocks (default [`SPIN_WAIT`]; CPU
    /// adapters never poll so).
    pub fn spin_wait(&self) -> Duration {
        Duration::from_nanos(self.spin_wait_ns.load(Ordering::Relaxed))
    }

    /// Sets [`GpuContext::spin_wait`] for every wait on this context from now on:
    /// [`Duration::ZERO`] blocks at once, for an application that would rather give the core
    /// to other work than have results a few tens of microseconds sooner.
    pub fn set_spin_wait(&self, spin: Duration) {
        let ns = u64::try_from(spin.as_nanos()).unwrap_or(u64::MAX);
        self.spin_wait_ns.store(ns, Ordering::Relaxed);
    }

    /// Blocks until all submitted work has finished: on GPUs it polls without blocking for up
    /// to [`GpuContext::spin_wait`] first (see [`SPIN_WAIT`]), then blocks.
    pub fn wait(&self) -> Result<(), GpuError> {
        let error = |e: wgpu::PollError| GpuError::Readback {
            label: "device".into(),
            reason: e.to_string(),
        };
        if self
            .spin_until(|status| status.is_queue_empty())
            .map_err(error)?
        {
            return Ok(());
        }
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(error)
    }

    /// Polls the device without blocking (which runs the callbacks of finished work) until
    /// `done` holds for a poll's status, for at most [`GpuContext::spin_wait`]; `Ok(false)`
    /// when time ran out, and at once on CPU adapters, whose driver needs the cores a spinning
    /// thread takes.
    pub(crate) fn spin_until(
        &self,
        mut done: impl FnMut(wgpu::PollStatus) -> bool,
    ) -> Result<bool, wgpu::PollError> {
        let spin = self.spin_wait();
        if self.is_cpu() || spin.is_zero() {
            return Ok(false);
        }
        let start = Instant::now();
        loop {
            if done(self.device.poll(wgpu::PollType::Poll)?) {
                return Ok(true);
            }
            if start.elapsed() >= spin {
                return Ok(false);
            }
            std::hint::spin_loop();
        }
    }

    /// The compute pipeline for `entry` in `shader` with the given override constants,
    /// compiled on first use and cached for the device's lifetime. Bind group layouts are
    /// derived from the shader (`pipeline.get_bind_group_layout(i)`).
    pub fn pipeline(
        &self,
        shader: &Shader,
        entry: &str,
        constants: &[(&str, f64)],
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        let missing = shader.required_features - self.device.features();
        if !missing.is_empty() {
            return Err(GpuError::MissingFeatures {
                shader: shader.name,
                missing,
                adapter: self.adapter_info.name.clone(),
            });
        }
        let key = PipelineKey {
            shader: shader.name,
            entry: entry.to_owned(),
            constants: constants
                .iter()
                .map(|(k, v)| ((*k).to_owned(), v.to_bits()))
                .collect(),
        };
        let mut cache = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = cache.get(&key) {
            return Ok(p.clone());
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self.trusted_module(shader.name, Cow::Borrowed(shader.source));
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(&format!("{}::{entry}", shader.name)),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants,
                    zero_initialize_workgroup_memory: false,
                },
                cache: None,
            });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Wgpu {
                context: format!("compiling {}::{entry}", shader.name),
                message: err.to_string(),
            });
        }
        cache.insert(key, pipeline.clone());
        Ok(pipeline)
    }

    /// A module of WGSL generated from validated models and scenes (large: every model's
    /// evaluation inlined): without naga's bounds checks on a GPU ([`GpuContext::trusted_module`]),
    /// with them on a CPU adapter, where lavapipe's LLVM took 286 s instead of seconds to compile
    /// an 8-model scene's unchecked distance kernel, which ran no faster.
    pub(crate) fn generated_module(&self, label: &str, source: Cow<'_, str>) -> wgpu::ShaderModule {
        if self.is_cpu() {
            return self
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(label),
                    source: wgpu::ShaderSource::Wgsl(source),
                });
        }
        self.trusted_module(label, source)
    }

    /// A shader module of our own WGSL (the crate's kernels, or code generated from validated
    /// models and scenes) without naga's inserted bounds checks.
    pub(crate) fn trusted_module(&self, label: &str, source: Cow<'_, str>) -> wgpu::ShaderModule {
        // SAFETY: our shaders index only within the bounds they check themselves (every kernel
        // guards its global index against the element count; generated snippets index weights
        // by offsets from the model's validated layout); naga's inserted bounds checks cost
        // measurably on lavapipe. `shaders::tests` validates every shader with naga.
        unsafe {
            self.device.create_shader_module_trusted(
                wgpu::ShaderModuleDescriptor {
                    label: Some(label),
                    source: wgpu::ShaderSource::Wgsl(source),
                },
                wgpu::ShaderRuntimeChecks::unchecked(),
            )
        }
    }

    /// Workgroup counts `(x, y)` covering `workgroups` groups, folding into the second dimension
    /// when one dimension is not enough. Kernels recover the flat group index as
    /// `wid.y * num_workgroups.x + wid.x` and must bounds-check it.
    pub fn dispatch_size(&self, workgroups: u32) -> (u32, u32) {
        split_dispatch(workgroups, self.max_dispatch)
    }
}

/// The largest buffer the device binds as storage, in bytes.
pub(crate) fn binding_limit(limits: &wgpu::Limits) -> u64 {
    limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size)
}

/// A bind-group layout entry: a storage buffer at `binding`, read-only or read-write, visible to
/// compute shaders.
pub(crate) fn storage_layout_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A bind-group entry that binds the whole of `buffer` at `binding`.
pub(crate) fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// See [`GpuContext::dispatch_size`]; `max` is the per-dimension limit.
pub fn split_dispatch(workgroups: u32, max: u32) -> (u32, u32) {
    let workgroups = workgroups.max(1);
    if workgroups <= max {
        (workgroups, 1)
    } else {
        let y = workgroups.div_ceil(max);
        (workgroups.div_ceil(y), y)
    }
}

fn storage_usage() -> wgpu::BufferUsages {
    wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST
}

#[cfg(test)]
mod tests {
    use super::split_dispatch;

    /// Small batches on a GPU take a subgroup per point, large ones and CPU adapters an
    /// invocation; a forced kernel wins where the device runs it.
    #[test]
    fn query_kernels_follow_the_rule() {
        use super::{QueryKernel as K, SUBGROUP_KERNEL_MAX_ELEMENTS as MAX, choose_query_kernel};
        let small = 3000;
        assert_eq!(
            choose_query_kernel(None, true, false, small),
            K::PerSubgroup
        );
        assert_eq!(
            choose_query_kernel(None, true, false, MAX - 1),
            K::PerSubgroup
        );
        assert_eq!(
            choose_query_kernel(None, true, false, MAX),
            K::PerInvocation
        );
        assert_eq!(
            choose_query_kernel(None, true, true, small),
            K::PerInvocation
        );
        assert_eq!(
            choose_query_kernel(None, false, false, small),
            K::PerInvocation
        );
        let sub = Some(K::PerSubgroup);
        assert_eq!(
            choose_query_kernel(sub, true, true, 1 << 30),
            K::PerSubgroup
        );
        assert_eq!(
            choose_query_kernel(sub, false, false, small),
            K::PerInvocation
        );
        let inv = Some(K::PerInvocation);
        assert_eq!(
            choose_query_kernel(inv, true, false, small),
            K::PerInvocation
        );
    }

    #[test]
    fn dispatch_folds_into_second_dimension() {
        assert_eq!(split_dispatch(0, 65535), (1, 1));
        assert_eq!(split_dispatch(10, 65535), (10, 1));
        assert_eq!(split_dispatch(65535, 65535), (65535, 1));
        let (x, y) = split_dispatch(65536, 65535);
        assert!(x <= 65535 && x * y >= 65536);
        for n in [1u32, 7, 8, 9, 100, 1000] {
            let (x, y) = split_dispatch(n, 7);
            assert!(x <= 7 && x * y >= n && x * (y - 1) < n, "{n} -> {x}x{y}");
        }
    }
}
