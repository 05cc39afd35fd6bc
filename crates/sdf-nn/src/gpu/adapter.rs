//! Choosing an adapter and opening a device on it with the limits and features our kernels use.

use std::collections::HashMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Mutex, OnceLock};

use super::{GpuContext, GpuError, GpuOptions, SPIN_WAIT};

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
pub(super) fn shares_host_memory(device_type: wgpu::DeviceType) -> bool {
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
}

pub(super) fn describe_info(info: &wgpu::AdapterInfo) -> String {
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
    use super::select_adapter;

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
}
