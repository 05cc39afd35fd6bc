//! The errors of the GPU context and its helpers.

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
    /// [`GpuOptions::adapter`](crate::GpuOptions::adapter) (`--adapter`, `HWSDF_ADAPTER` or `WGPU_ADAPTER_NAME`) matched no
    /// adapter.
    #[error(
        "no adapter matches {requested:?} (from {from}: an index, a PCI bus id or part of a name); \
         available adapters: {available}. Leave {from} out or give it one of these"
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
    /// An environment variable of [`GpuOptions::from_env`](crate::GpuOptions::from_env) holds a value it does not know.
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
