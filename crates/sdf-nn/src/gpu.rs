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

use std::borrow::Cow;
use std::collections::HashMap;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use bytemuck::Pod;
use wgpu::util::DeviceExt;

use crate::shaders::Shader;

/// Errors from the GPU context and its helpers.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter at all was found.
    #[error(
        "no GPU adapter found (backends: {backends}). Install a Vulkan driver for your GPU, or the \
         CPU driver on machines without one: `apt-get install mesa-vulkan-drivers libvulkan1`"
    )]
    NoAdapter {
        /// The backends that were searched.
        backends: String,
    },
    /// [`GpuOptions::adapter`] (`--adapter`, `HWSDF_ADAPTER` or `WGPU_ADAPTER_NAME`) matched no
    /// adapter.
    #[error(
        "no adapter matches {requested:?} (from {from}: an index, a PCI bus id or part of a name); \
         available adapters: {available}. Unset {from} or set it to one of these"
    )]
    AdapterNotFound {
        /// The requested index, bus id or name fragment.
        requested: String,
        /// Where it came from.
        from: String,
        /// The adapters that exist, for the message.
        available: String,
    },
    /// The adapter lacks a limit the kernels need.
    #[error(
        "adapter {adapter:?} is unsupported: limit `{limit}` is {has}, HW SDF needs at least {need}"
    )]
    UnsupportedAdapter {
        /// Adapter name.
        adapter: String,
        /// Name of the wgpu limit.
        limit: &'static str,
        /// What the adapter offers.
        has: u64,
        /// What we need.
        need: u64,
    },
    /// The adapter refused to create a device.
    #[error("could not create a device on adapter {adapter:?}: {source}")]
    RequestDevice {
        /// Adapter name.
        adapter: String,
        /// The wgpu error.
        source: wgpu::RequestDeviceError,
    },
    /// A buffer would exceed the device's limits.
    #[error(
        "buffer `{label}` needs {requested} bytes, above the device limit {limit_name} = {limit} bytes"
    )]
    BufferTooLarge {
        /// Buffer label.
        label: String,
        /// Requested size in bytes.
        requested: u64,
        /// Name of the limit it exceeds.
        limit_name: &'static str,
        /// The limit.
        limit: u64,
    },
    /// A shader needs a device feature this device does not have.
    #[error(
        "shader `{shader}` needs device features {missing:?}, which adapter {adapter:?} does not offer"
    )]
    MissingFeatures {
        /// Shader name.
        shader: &'static str,
        /// The missing features.
        missing: wgpu::Features,
        /// Adapter name.
        adapter: String,
    },
    /// wgpu reported a validation or out-of-memory error.
    #[error("GPU error while {context}: {message}")]
    Wgpu {
        /// What we were doing.
        context: String,
        /// wgpu's message.
        message: String,
    },
    /// An environment variable of [`GpuOptions::from_env`] holds a value it does not know.
    #[error(
        "{variable}={value:?} is not a value it takes: use one of {allowed} (or leave it unset)"
    )]
    Environment {
        /// The variable.
        variable: &'static str,
        /// Its value.
        value: String,
        /// The values it takes.
        allowed: String,
    },
    /// Mapping a buffer for readback failed, or the device was lost while waiting.
    #[error("reading back `{label}` failed: {reason}")]
    Readback {
        /// Buffer label.
        label: String,
        /// What went wrong.
        reason: String,
    },
}

/// Which layout SIREN's reverse-over-reverse training step runs (`HWSDF_STEP_LAYOUT`): the
/// one for GPUs (many small splits, wide reductions) or the one for CPU adapters such as
/// lavapipe. By default the adapter decides.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StepLayout {
    /// The layout for real GPUs.
    Gpu,
    /// The layout for CPU adapters.
    Cpu,
}

/// How to choose the adapter and which of its capabilities to use: every library knob that can
/// come from the environment, read once by [`GpuOptions::from_env`].
#[derive(Clone, Debug)]
pub struct GpuOptions {
    /// Which adapter: its index in [`list_adapters`] (as `gpu-info` prints it), its PCI bus id
    /// (`wgpu::AdapterInfo::device_pci_bus_id`, e.g. `0000:65:00.0`), or part of its name
    /// (case-insensitive; the first match wins). `None`: the best adapter.
    pub adapter: Option<String>,
    /// Where [`GpuOptions::adapter`] came from, for error messages (e.g. `--adapter`).
    pub adapter_from: String,
    /// Restrict to these backends; `None` means wgpu's defaults (or `WGPU_BACKEND`).
    pub backends: Option<wgpu::Backends>,
    /// Ask for mappable storage buffers where the adapter has them (default `true`;
    /// `HWSDF_MAPPABLE_STORAGE=0` turns it off). See [`GpuContext::maps_storage`].
    pub mappable_storage: bool,
    /// Use f16 cooperative matrices (tensor cores) where the driver has them (default `true`;
    /// `HWSDF_NO_COOP=1` turns it off). See [`GpuContext::coop_f16_tile`].
    pub cooperative_matrices: bool,
    /// Force the layout of SIREN's training step (`HWSDF_STEP_LAYOUT=gpu|cpu`); `None`: by
    /// adapter.
    pub step_layout: Option<StepLayout>,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            adapter: None,
            adapter_from: String::new(),
            backends: None,
            mappable_storage: true,
            cooperative_matrices: true,
            step_layout: None,
        }
    }
}

/// The environment variables [`GpuOptions::from_env`] reads, in the order it reads them.
pub const ENV_VARIABLES: &[&str] = &[
    "HWSDF_ADAPTER",
    "WGPU_ADAPTER_NAME",
    "WGPU_BACKEND",
    "HWSDF_MAPPABLE_STORAGE",
    "HWSDF_NO_COOP",
    "HWSDF_STEP_LAYOUT",
];

impl GpuOptions {
    /// Options from the process's environment: `HWSDF_ADAPTER` (index, bus id or name), else
    /// `WGPU_ADAPTER_NAME` (name); `WGPU_BACKEND`; `HWSDF_MAPPABLE_STORAGE=0|1`;
    /// `HWSDF_NO_COOP=0|1`; `HWSDF_STEP_LAYOUT=gpu|cpu`. An empty variable counts as unset; any
    /// other value than those listed is an error naming the allowed ones.
    pub fn from_env() -> Result<Self, GpuError> {
        Self::from_vars(|name| std::env::var(name).ok())
    }

    /// [`GpuOptions::from_env`] over any source of variables (`var(name)` is the value of
    /// `name`, if set).
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<Self, GpuError> {
        let var = |name: &str| var(name).filter(|s| !s.trim().is_empty());
        let (adapter, adapter_from) = match (var("HWSDF_ADAPTER"), var("WGPU_ADAPTER_NAME")) {
            (Some(a), _) => (Some(a), "HWSDF_ADAPTER"),
            (None, Some(a)) => (Some(a), "WGPU_ADAPTER_NAME"),
            (None, None) => (None, ""),
        };
        let choice = |name: &'static str, allowed: &'static [&'static str]| {
            var(name)
                .map(|value| {
                    let v = value.trim().to_ascii_lowercase();
                    allowed
                        .iter()
                        .position(|a| *a == v)
                        .ok_or(GpuError::Environment {
                            variable: name,
                            value,
                            allowed: allowed.join(", "),
                        })
                })
                .transpose()
        };
        let backends = match var("WGPU_BACKEND") {
            None => None,
            Some(value) => {
                let backends = wgpu::Backends::from_comma_list(&value);
                if backends.is_empty() {
                    return Err(GpuError::Environment {
                        variable: "WGPU_BACKEND",
                        value,
                        allowed: "a comma-separated list of vulkan, metal, dx12, gl, webgpu".into(),
                    });
                }
                Some(backends)
            }
        };
        Ok(GpuOptions {
            adapter,
            adapter_from: adapter_from.into(),
            backends,
            mappable_storage: choice("HWSDF_MAPPABLE_STORAGE", &["0", "1"])?.is_none_or(|i| i == 1),
            cooperative_matrices: choice("HWSDF_NO_COOP", &["0", "1"])?.is_none_or(|i| i == 0),
            step_layout: choice("HWSDF_STEP_LAYOUT", &["gpu", "cpu"])?.map(|i| {
                if i == 0 {
                    StepLayout::Gpu
                } else {
                    StepLayout::Cpu
                }
            }),
        })
    }

    /// These options with the adapter chosen by a command-line flag instead (`None` keeps
    /// the environment's choice).
    pub fn with_adapter(mut self, adapter: Option<&str>, flag: &str) -> Self {
        if let Some(a) = adapter.filter(|a| !a.trim().is_empty()) {
            self.adapter = Some(a.to_owned());
            self.adapter_from = flag.to_owned();
        }
        self
    }
}

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
/// (BENCHMARKS "The query path"), which is most of a small query's wall time. Work that runs
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

/// Rank for the default choice: real GPUs first, then CPU rasterisers.
fn device_type_rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

/// Minimum limits every kernel of ours may rely on. All are within what lavapipe, NVIDIA, AMD,
/// Intel and Apple GPUs offer.
const NEEDED_STORAGE_BUFFERS: u32 = 8;
const NEEDED_WORKGROUP_STORAGE: u32 = 16 * 1024;
const NEEDED_INVOCATIONS: u32 = 256;

/// Features we use when present; none is required.
fn wanted_features() -> wgpu::Features {
    wgpu::Features::SHADER_FLOAT32_ATOMIC
        | wgpu::Features::TIMESTAMP_QUERY
        | wgpu::Features::SHADER_F16
        | wgpu::Features::SUBGROUP
        | wgpu::Features::MAPPABLE_PRIMARY_BUFFERS
}

/// Whether adapters of this type use the host's memory (CPU and integrated adapters).
fn shares_host_memory(device_type: wgpu::DeviceType) -> bool {
    matches!(
        device_type,
        wgpu::DeviceType::Cpu | wgpu::DeviceType::IntegratedGpu
    )
}

/// The features of the f16 cooperative-matrix kernels: f16 arithmetic, subgroups, and wgpu's
/// experimental cooperative matrices.
const COOP_F16_FEATURES: wgpu::Features = wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX
    .union(wgpu::Features::SHADER_F16)
    .union(wgpu::Features::SUBGROUP);

/// The side of the largest square tile (16 or 8) in which `adapter` multiplies f16 matrices
/// into f32 accumulators, if it also has the other features our cooperative-matrix kernels
/// need, among them one fixed subgroup size (they give each subgroup a tile).
fn coop_f16_tile(adapter: &wgpu::Adapter) -> Option<u32> {
    let info = adapter.get_info();
    if !adapter.features().contains(COOP_F16_FEATURES)
        || info.subgroup_min_size != info.subgroup_max_size
    {
        return None;
    }
    let props = adapter.cooperative_matrix_properties();
    [16, 8].into_iter().find(|&t| {
        props.iter().any(|p| {
            (p.m_size, p.n_size, p.k_size) == (t, t, t)
                && p.ab_type == wgpu::CooperativeScalarType::F16
                && p.cr_type == wgpu::CooperativeScalarType::F32
        })
    })
}

impl GpuContext {
    /// A context on the adapter chosen by the environment (see the module docs).
    pub fn new() -> Result<Self, GpuError> {
        Self::with_options(&GpuOptions::from_env()?)
    }

    /// A context on the adapter chosen by `options`.
    pub fn with_options(options: &GpuOptions) -> Result<Self, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        if let Some(b) = options.backends {
            desc.backends = b;
        }
        let backends = desc.backends;
        let instance = wgpu::Instance::new(desc);
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let adapter = choose_adapter(adapters, options, backends)?;
        Self::from_adapter(adapter, options)
    }

    /// One context per process, created from the environment on first use and shared after.
    ///
    /// Tests and binaries use this so that a device, and the pipelines compiled on it, are
    /// created once. A failure is returned to every caller until one succeeds.
    pub fn shared() -> Result<&'static GpuContext, GpuError> {
        static SHARED: OnceLock<GpuContext> = OnceLock::new();
        static INIT: Mutex<()> = Mutex::new(());
        if let Some(gpu) = SHARED.get() {
            return Ok(gpu);
        }
        let _guard = INIT.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(gpu) = SHARED.get() {
            return Ok(gpu);
        }
        let gpu = GpuContext::new()?;
        Ok(SHARED.get_or_init(|| gpu))
    }

    /// A context on an adapter the caller already chose, using its capabilities as `options`
    /// allow (their adapter choice is not used).
    pub fn from_adapter(adapter: wgpu::Adapter, options: &GpuOptions) -> Result<Self, GpuError> {
        let info = adapter.get_info();
        let have = adapter.limits();
        let check = |limit: &'static str, has: u32, need: u32| {
            if has < need {
                Err(GpuError::UnsupportedAdapter {
                    adapter: info.name.clone(),
                    limit,
                    has: has.into(),
                    need: need.into(),
                })
            } else {
                Ok(())
            }
        };
        check(
            "max_storage_buffers_per_shader_stage",
            have.max_storage_buffers_per_shader_stage,
            NEEDED_STORAGE_BUFFERS,
        )?;
        check(
            "max_compute_workgroup_storage_size",
            have.max_compute_workgroup_storage_size,
            NEEDED_WORKGROUP_STORAGE,
        )?;
        check(
            "max_compute_invocations_per_workgroup",
            have.max_compute_invocations_per_workgroup,
            NEEDED_INVOCATIONS,
        )?;

        // Ask for what the adapter has where bigger is better for us (buffer sizes, workgroup
        // memory, bindings), so large batches and grids are limited by the hardware, not by
        // wgpu's conservative defaults.
        let limits = wgpu::Limits {
            max_storage_buffers_per_shader_stage: have.max_storage_buffers_per_shader_stage,
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_compute_workgroup_storage_size: have.max_compute_workgroup_storage_size,
            max_compute_invocations_per_workgroup: have.max_compute_invocations_per_workgroup,
            max_compute_workgroup_size_x: have.max_compute_workgroup_size_x,
            max_compute_workgroup_size_y: have.max_compute_workgroup_size_y,
            max_compute_workgroup_size_z: have.max_compute_workgroup_size_z,
            max_compute_workgroups_per_dimension: have.max_compute_workgroups_per_dimension,
            ..wgpu::Limits::downlevel_defaults()
        };
        let mut features = adapter.features() & wanted_features();
        // Mappable storage: on a discrete GPU only the host-side queries' points and results
        // use it (`NeuralSdf::eval` and its kin: each crosses the bus once either way, and on
        // an H100 a query took 15–18 µs less than through staging copies). wgpu logs a
        // warning at device creation there. `HWSDF_MAPPABLE_STORAGE=0` leaves it off.
        if !options.mappable_storage {
            features.remove(wgpu::Features::MAPPABLE_PRIMARY_BUFFERS);
        }
        let request = |features: wgpu::Features, experimental: wgpu::ExperimentalFeatures| {
            pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
                label: Some("hwsdf"),
                required_features: features,
                required_limits: limits.clone(),
                experimental_features: experimental,
                ..Default::default()
            }))
        };
        // Cooperative matrices are experimental in wgpu: ask for them only where our kernels can
        // use them, and open the device without them if the driver refuses the request.
        // `HWSDF_NO_COOP=1` leaves them off.
        let coop_tile = coop_f16_tile(&adapter).filter(|_| options.cooperative_matrices);
        let with_coop = coop_tile.and_then(|_| {
            // SAFETY: wgpu's contract for experimental features. Only the kernels of
            // `siren::kernels::coop` use cooperative matrices, in the configuration
            // checked above, and their tests compare them against the f64 reference.
            let experimental = unsafe { wgpu::ExperimentalFeatures::enabled() };
            request(
                features | wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX,
                experimental,
            )
            .ok()
        });
        let coop_tile = coop_tile.filter(|_| with_coop.is_some());
        let (device, queue) = match with_coop {
            Some(dq) => dq,
            None => {
                request(features, wgpu::ExperimentalFeatures::disabled()).map_err(|source| {
                    GpuError::RequestDevice {
                        adapter: info.name.clone(),
                        source,
                    }
                })?
            }
        };
        let max_dispatch = device.limits().max_compute_workgroups_per_dimension;
        Ok(GpuContext {
            adapter_info: info,
            device,
            queue,
            pipelines: Mutex::new(HashMap::new()),
            max_dispatch,
            coop_tile,
            spin_wait_ns: AtomicU64::new(SPIN_WAIT.as_nanos() as u64),
            options: options.clone(),
        })
    }

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

    /// The limits the device was created with.
    pub fn limits(&self) -> wgpu::Limits {
        self.device.limits()
    }

    /// Checks a buffer size against the device limits for a buffer bound as storage.
    pub fn check_storage_size(&self, label: &str, bytes: u64) -> Result<(), GpuError> {
        let limits = self.device.limits();
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
    fn map_read<T: Pod>(&self, buffer: &wgpu::Buffer, label: &str) -> Result<Vec<T>, GpuError> {
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
        let view = slice.get_mapped_range().map_err(|e| error(e.to_string()))?;
        // The mapped bytes need not be aligned for T; copy through pod_collect.
        let out: Vec<T> = bytemuck::pod_collect_to_vec(&view);
        drop(view);
        buffer.unmap();
        Ok(out)
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
        // SAFETY: our shaders index only within the bounds they check themselves (every kernel
        // guards its global index against the element count); naga's inserted bounds checks
        // cost measurably on lavapipe. `shaders::tests` validates every shader with naga.
        let module = unsafe {
            self.device.create_shader_module_trusted(
                wgpu::ShaderModuleDescriptor {
                    label: Some(shader.name),
                    source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(shader.source)),
                },
                wgpu::ShaderRuntimeChecks::unchecked(),
            )
        };
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

    /// Workgroup counts `(x, y)` covering `workgroups` groups, folding into the second dimension
    /// when one dimension is not enough. Kernels recover the flat group index as
    /// `wid.y * num_workgroups.x + wid.x` and must bounds-check it.
    pub fn dispatch_size(&self, workgroups: u32) -> (u32, u32) {
        split_dispatch(workgroups, self.max_dispatch)
    }
}

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

fn describe_info(info: &wgpu::AdapterInfo) -> String {
    let driver = [info.driver.as_str(), info.driver_info.as_str()]
        .iter()
        .filter(|s| !s.is_empty())
        .copied()
        .collect::<Vec<_>>()
        .join(" ");
    format!(
        "{} ({:?}, {:?}{}{})",
        info.name,
        info.device_type,
        info.backend,
        if driver.is_empty() { "" } else { ", " },
        driver
    )
}

fn choose_adapter(
    adapters: Vec<wgpu::Adapter>,
    options: &GpuOptions,
    backends: wgpu::Backends,
) -> Result<wgpu::Adapter, GpuError> {
    if let Some(wanted) = &options.adapter {
        let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
        let available = infos
            .iter()
            .enumerate()
            .map(|(i, info)| describe_listed(i, info))
            .collect::<Vec<_>>();
        return select_adapter(&infos, wanted)
            .map(|i| {
                adapters
                    .into_iter()
                    .nth(i)
                    .expect("index from the same list")
            })
            .ok_or_else(|| GpuError::AdapterNotFound {
                requested: wanted.clone(),
                from: if options.adapter_from.is_empty() {
                    "GpuOptions::adapter".into()
                } else {
                    options.adapter_from.clone()
                },
                available: if available.is_empty() {
                    "none".into()
                } else {
                    available.join("; ")
                },
            });
    }
    adapters
        .into_iter()
        .min_by_key(|a| device_type_rank(a.get_info().device_type))
        .ok_or_else(|| GpuError::NoAdapter {
            backends: format!("{backends:?}"),
        })
}

/// Which of `infos` `wanted` names: an index into the list, else a PCI bus id (with or without
/// its `0000:` domain), else the first name that contains it (case-insensitive).
fn select_adapter(infos: &[wgpu::AdapterInfo], wanted: &str) -> Option<usize> {
    let wanted = wanted.trim();
    if let Ok(i) = wanted.parse::<usize>() {
        return (i < infos.len()).then_some(i);
    }
    let bus = |id: &str| {
        !id.is_empty()
            && (id.eq_ignore_ascii_case(wanted)
                || (wanted.contains(':')
                    && id
                        .to_ascii_lowercase()
                        .ends_with(&format!(":{}", wanted.to_ascii_lowercase()))))
    };
    if let Some(i) = infos.iter().position(|a| bus(&a.device_pci_bus_id)) {
        return Some(i);
    }
    let needle = wanted.to_lowercase();
    infos
        .iter()
        .position(|a| a.name.to_lowercase().contains(&needle))
}

/// `i: name (type, backend, driver) [PCI bus id]`, as `gpu-info` lists adapters.
fn describe_listed(i: usize, info: &wgpu::AdapterInfo) -> String {
    let bus = if info.device_pci_bus_id.is_empty() {
        "no PCI bus id".to_owned()
    } else {
        format!("PCI {}", info.device_pci_bus_id)
    };
    format!("{i}: {} [{bus}]", describe_info(info))
}

/// Every adapter wgpu can see, in the order `HWSDF_ADAPTER`/`--adapter` indices refer to, each
/// with its index, type, backend, driver and PCI bus id.
pub fn list_adapters() -> Vec<String> {
    let desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
    let backends = desc.backends;
    let instance = wgpu::Instance::new(desc);
    pollster::block_on(instance.enumerate_adapters(backends))
        .iter()
        .enumerate()
        .map(|(i, a)| describe_listed(i, &a.get_info()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::{select_adapter, split_dispatch};

    fn info(name: &str, bus: &str) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo {
            name: name.into(),
            device_pci_bus_id: bus.into(),
            ..wgpu::AdapterInfo::new(wgpu::DeviceType::DiscreteGpu, wgpu::Backend::Vulkan)
        }
    }

    #[test]
    fn adapters_are_chosen_by_index_bus_id_or_name() {
        // Eight identical GPUs share a name; the index and the bus id tell them apart.
        let infos: Vec<_> = (0..8)
            .map(|i| {
                info(
                    "NVIDIA H100 80GB HBM3",
                    &format!("0000:{:02x}:00.0", 0x18 + i),
                )
            })
            .chain([info("llvmpipe (LLVM 15.0.6, 256 bits)", "")])
            .collect();
        assert_eq!(select_adapter(&infos, "3"), Some(3));
        assert_eq!(select_adapter(&infos, " 8 "), Some(8));
        assert_eq!(select_adapter(&infos, "9"), None);
        assert_eq!(select_adapter(&infos, "0000:1c:00.0"), Some(4));
        assert_eq!(select_adapter(&infos, "0000:1C:00.0"), Some(4));
        assert_eq!(select_adapter(&infos, "1c:00.0"), Some(4));
        assert_eq!(select_adapter(&infos, "0000:99:00.0"), None);
        assert_eq!(select_adapter(&infos, "h100"), Some(0));
        assert_eq!(select_adapter(&infos, "LLVMPIPE"), Some(8));
        assert_eq!(select_adapter(&infos, "radeon"), None);
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
