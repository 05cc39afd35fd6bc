//! [`GpuOptions`](crate::GpuOptions): the adapter choice and the capability switches, read from the environment
//! in one place.

use super::GpuError;

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

/// Where a SIREN's WGSL keeps one layer's activations while it computes the next, in the
/// kernels of ours that evaluate a whole network per invocation: the renderer and the scene
/// queries (`HWSDF_SIREN_ACTIVATIONS`). By default the adapter decides: [`Scratch`] on CPU
/// adapters where a SIREN is at least 32 units wide (narrower ones compile as fast from
/// private arrays), [`Private`] on GPUs. The answers are the same; the tests hold both to the
/// CPU reference and to each other.
///
/// [`Scratch`]: SirenActivations::Scratch
/// [`Private`]: SirenActivations::Private
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SirenActivations {
    /// Function-scope arrays, as the snippet of [`NeuralSdf::wgsl`](crate::NeuralSdf::wgsl)
    /// has them: a GPU keeps them in its local memory, interleaved across threads.
    Private,
    /// A read-write storage buffer of the kernel's, one slot per invocation. llvmpipe
    /// (lavapipe) compiles every compute shader as an LLVM coroutine, and LLVM 15 takes
    /// minutes to build the coroutine frame of a function with private arrays of a few hundred
    /// elements: a 64-wide SIREN's tracer took 15 s to compile, a 256-wide one did not finish
    /// in 10 minutes; from a storage buffer both compile in under a second.
    Scratch,
}

/// How a kernel shares its elements (a query's points, a scene's rays, a training step's rows)
/// among the GPU's invocations. The answers agree to f32 rounding; the tests hold both to the
/// CPU reference. Queries choose with [`GpuContext::query_kernel`](crate::GpuContext::query_kernel), NGLOD and hash-grid
/// training steps with [`GpuContext::train_kernel`](crate::GpuContext::train_kernel).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum QueryKernel {
    /// One invocation per point, which evaluates the network alone. The faster on CPU adapters
    /// (lavapipe runs a workgroup's invocations as the SIMD lanes of one thread), and the
    /// fallback without subgroup operations.
    PerInvocation,
    /// One subgroup per point: its lanes share the network's evaluation (the levels' corners
    /// split among them, the hidden units strided, the sums by `subgroupAdd`), so a point's
    /// latency shrinks by about the subgroup's width. Made for GPUs, where a few thousand
    /// points, one per invocation, leave most of the device idle while each invocation runs
    /// one long chain of dependent loads. Needs `wgpu::Features::SUBGROUP`, and applies to
    /// NGLOD models, hash grids and scenes (a SIREN model keeps its own kernels).
    PerSubgroup,
}

impl QueryKernel {
    /// The kernel's name, as `HWSDF_QUERY_KERNEL` and `HWSDF_TRAIN_KERNEL` spell it.
    pub const fn name(self) -> &'static str {
        match self {
            QueryKernel::PerInvocation => "invocation",
            QueryKernel::PerSubgroup => "subgroup",
        }
    }
}

/// How to choose the adapter and which of its capabilities to use: every library knob that can
/// come from the environment, read once by [`GpuOptions::from_env`](crate::GpuOptions::from_env).
#[derive(Clone, Debug)]
pub struct GpuOptions {
    /// Which adapter: its index in [`list_adapters`](crate::gpu::list_adapters) (as `gpu-info` prints it), its PCI bus id
    /// (`wgpu::AdapterInfo::device_pci_bus_id`, e.g. `0000:65:00.0`), or part of its name
    /// (case-insensitive; the first match wins). `None`: the best adapter.
    pub adapter: Option<String>,
    /// Where [`GpuOptions::adapter`](crate::GpuOptions::adapter) came from, for error messages (e.g. `--adapter`).
    pub adapter_from: String,
    /// Restrict to these backends; `None` means wgpu's defaults (or `WGPU_BACKEND`).
    pub backends: Option<wgpu::Backends>,
    /// Ask for mappable storage buffers where the adapter has them (default `true`;
    /// `HWSDF_MAPPABLE_STORAGE=0` turns it off). See [`GpuContext::maps_storage`](crate::GpuContext::maps_storage).
    pub mappable_storage: bool,
    /// Use f16 cooperative matrices (tensor cores) where the driver has them (default `true`;
    /// `HWSDF_NO_COOP=1` turns it off). See [`GpuContext::coop_f16_tile`](crate::GpuContext::coop_f16_tile).
    pub cooperative_matrices: bool,
    /// Force the layout of SIREN's training step (`HWSDF_STEP_LAYOUT=gpu|cpu`); `None`: by
    /// adapter.
    pub step_layout: Option<StepLayout>,
    /// Force the kernel of NGLOD, hash-grid and scene queries
    /// (`HWSDF_QUERY_KERNEL=invocation|subgroup`); `None`: by adapter
    /// ([`GpuContext::query_kernel`](crate::GpuContext::query_kernel)).
    pub query_kernel: Option<QueryKernel>,
    /// Force the kernel of NGLOD and hash-grid training steps
    /// (`HWSDF_TRAIN_KERNEL=invocation|subgroup`); `None`: by adapter
    /// ([`GpuContext::train_kernel`](crate::GpuContext::train_kernel)).
    pub train_kernel: Option<QueryKernel>,
    /// Force where SIREN activations live in the renderer and the scene queries
    /// (`HWSDF_SIREN_ACTIVATIONS=private|scratch`); `None`: by adapter
    /// ([`GpuContext::siren_activations`](crate::GpuContext::siren_activations)).
    pub siren_activations: Option<SirenActivations>,
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
            query_kernel: None,
            train_kernel: None,
            siren_activations: None,
        }
    }
}

/// The environment variables [`GpuOptions::from_env`](crate::GpuOptions::from_env) reads, in the order it reads them.
pub const ENV_VARIABLES: &[&str] = &[
    "HWSDF_ADAPTER",
    "WGPU_ADAPTER_NAME",
    "WGPU_BACKEND",
    "HWSDF_MAPPABLE_STORAGE",
    "HWSDF_NO_COOP",
    "HWSDF_STEP_LAYOUT",
    "HWSDF_QUERY_KERNEL",
    "HWSDF_TRAIN_KERNEL",
    "HWSDF_SIREN_ACTIVATIONS",
];

impl GpuOptions {
    /// Options from the process's environment: `HWSDF_ADAPTER` (index, bus id or name), else
    /// `WGPU_ADAPTER_NAME` (name); `WGPU_BACKEND`; `HWSDF_MAPPABLE_STORAGE=0|1`;
    /// `HWSDF_NO_COOP=0|1`; `HWSDF_STEP_LAYOUT=gpu|cpu`;
    /// `HWSDF_QUERY_KERNEL=invocation|subgroup`; `HWSDF_TRAIN_KERNEL=invocation|subgroup`;
    /// `HWSDF_SIREN_ACTIVATIONS=private|scratch`. An empty variable counts as unset; any
    /// other value than those listed is an error naming the allowed ones.
    pub fn from_env() -> Result<Self, GpuError> {
        Self::from_vars(|name| std::env::var(name).ok())
    }

    /// [`GpuOptions::from_env`](crate::GpuOptions::from_env) over any source of variables (`var(name)` is the value of
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
        const KERNELS: [QueryKernel; 2] = [QueryKernel::PerInvocation, QueryKernel::PerSubgroup];
        const KERNEL_NAMES: [&str; 2] = [KERNELS[0].name(), KERNELS[1].name()];
        let kernel =
            |name: &'static str| choice(name, &KERNEL_NAMES).map(|i| i.map(|i| KERNELS[i]));
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
            query_kernel: kernel("HWSDF_QUERY_KERNEL")?,
            train_kernel: kernel("HWSDF_TRAIN_KERNEL")?,
            siren_activations: choice("HWSDF_SIREN_ACTIVATIONS", &["private", "scratch"])?.map(
                |i| {
                    if i == 0 {
                        SirenActivations::Private
                    } else {
                        SirenActivations::Scratch
                    }
                },
            ),
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

/// Keeps Mesa's device-selection layer (`VK_LAYER_MESA_device_select`, installed with Mesa's
/// Vulkan drivers) out of a process that has no usable `XDG_RUNTIME_DIR`, such as a headless
/// server or CI: wgpu enables the window-system instance extensions wherever the driver has
/// them, the layer then asks Wayland for the default GPU, and libwayland prints
/// `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` two to four times. The
/// layer only orders adapters for programs that take the first one; we choose our own
/// ([`GpuOptions::adapter`](crate::GpuOptions::adapter)). Sets `NODEVICE_SELECT=1` (the layer's own switch) unless the
/// variable is set already or `XDG_RUNTIME_DIR` is a directory.
///
/// # Safety
/// It writes the process's environment, so no other thread may read or write the environment
/// while it runs: call it first thing in `main`, before any thread starts.
pub unsafe fn skip_device_select_layer_when_headless() {
    let runtime_dir =
        std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|dir| std::path::Path::new(&dir).is_dir());
    if !runtime_dir && std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: the caller guarantees no other thread touches the environment.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

#[cfg(test)]
mod tests {
    use super::{GpuOptions, QueryKernel, StepLayout};

    fn options(vars: &[(&str, &str)]) -> Result<GpuOptions, String> {
        GpuOptions::from_vars(|name| {
            vars.iter()
                .find(|(n, _)| *n == name)
                .map(|(_, v)| (*v).to_owned())
        })
        .map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_use_every_capability() {
        let o = options(&[]).unwrap();
        assert!(o.adapter.is_none() && o.backends.is_none());
        assert!(o.mappable_storage && o.cooperative_matrices);
        assert_eq!(o.step_layout, None);
        assert_eq!(o.query_kernel, None);
        assert_eq!(o.train_kernel, None);
        // An empty variable counts as unset.
        let o = options(&[("HWSDF_NO_COOP", " "), ("HWSDF_ADAPTER", "")]).unwrap();
        assert!(o.cooperative_matrices && o.adapter.is_none());
    }

    #[test]
    fn known_values_set_their_switch() {
        let o = options(&[
            ("HWSDF_MAPPABLE_STORAGE", "0"),
            ("HWSDF_NO_COOP", "1"),
            ("HWSDF_STEP_LAYOUT", "CPU"),
            ("HWSDF_QUERY_KERNEL", "Subgroup"),
            ("HWSDF_TRAIN_KERNEL", "invocation"),
            ("WGPU_BACKEND", "vulkan"),
            ("WGPU_ADAPTER_NAME", "llvmpipe"),
        ])
        .unwrap();
        assert!(!o.mappable_storage && !o.cooperative_matrices);
        assert_eq!(o.step_layout, Some(StepLayout::Cpu));
        assert_eq!(o.query_kernel, Some(QueryKernel::PerSubgroup));
        assert_eq!(o.train_kernel, Some(QueryKernel::PerInvocation));
        assert_eq!(o.backends, Some(wgpu::Backends::VULKAN));
        assert_eq!(o.adapter.as_deref(), Some("llvmpipe"));
        assert_eq!(o.adapter_from, "WGPU_ADAPTER_NAME");
        let o = options(&[("HWSDF_STEP_LAYOUT", "gpu"), ("HWSDF_NO_COOP", "0")]).unwrap();
        assert_eq!(o.step_layout, Some(StepLayout::Gpu));
        assert!(o.cooperative_matrices);
        // HWSDF_ADAPTER wins over wgpu's own variable.
        let o = options(&[("HWSDF_ADAPTER", "1"), ("WGPU_ADAPTER_NAME", "x")]).unwrap();
        assert_eq!(
            (o.adapter.as_deref(), o.adapter_from.as_str()),
            (Some("1"), "HWSDF_ADAPTER")
        );
    }

    #[test]
    fn unknown_values_are_errors_that_name_the_allowed_ones() {
        for (name, value, allowed) in [
            ("HWSDF_STEP_LAYOUT", "sideways", "gpu, cpu"),
            ("HWSDF_QUERY_KERNEL", "warp", "invocation, subgroup"),
            ("HWSDF_TRAIN_KERNEL", "lane", "invocation, subgroup"),
            ("HWSDF_NO_COOP", "yes", "0, 1"),
            ("HWSDF_MAPPABLE_STORAGE", "off", "0, 1"),
            ("WGPU_BACKEND", "vulcan", "vulkan"),
        ] {
            let err = options(&[(name, value)]).unwrap_err();
            assert!(
                err.contains(name) && err.contains(value) && err.contains(allowed),
                "{err}"
            );
        }
    }
}
