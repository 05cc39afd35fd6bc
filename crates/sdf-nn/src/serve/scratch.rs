//! The scratch buffer of SIREN snippets in the [`SirenActivations::Scratch`] form: what the
//! renderer and the scene queries bind at [`SCRATCH_GROUP`] where the adapter keeps a SIREN's
//! activations in storage rather than in private arrays (see [`SirenActivations`]).

use crate::gpu::{GpuContext, GpuError, SirenActivations};
use crate::serve::network::Network;
use crate::serve::wgsl;

/// The bind group index of the scratch buffer in our kernels (0: the kernel's own buffers, 1:
/// the weights).
pub(crate) const SCRATCH_GROUP: u32 = 2;

/// Most bytes of scratch a scene's queries keep, and a frame of the renderer takes where its
/// bands allow: 8192 slots of a 256-wide SIREN. Batches and frames are split to fit (a part of
/// 1024 rays, or a band of 16 rows of 512 pixels, still takes seconds on lavapipe).
pub(crate) const MAX_SCRATCH_BYTES: u64 = 64 << 20;

/// Narrowest SIREN for which a CPU adapter takes the scratch form by default. Below it LLVM
/// unrolls the layers' loops and keeps the arrays in registers: lavapipe compiled a 16-wide
/// SIREN's evaluation from private arrays in 0.9 s (twice, in a loop: 1.9 s) against 0.9 s
/// (2.9 s) from scratch, and the scene test's kernels of an 8-wide one in half the time; at 32
/// wide, 30 s against 1.3 s.
const SCRATCH_MIN_WIDTH: u32 = 32;

/// Floats per slot that `networks` need in the form `gpu` runs, or `None` where no scratch is
/// bound: a GPU (private arrays), no SIREN among them, or (unless `HWSDF_SIREN_ACTIVATIONS`
/// asks for scratch) none at least [`SCRATCH_MIN_WIDTH`] wide. Every SIREN of a kernel takes
/// the same form.
pub(crate) fn stride<'a>(
    gpu: &GpuContext,
    networks: impl IntoIterator<Item = &'a Network>,
) -> Option<u32> {
    if gpu.siren_activations() != SirenActivations::Scratch {
        return None;
    }
    let forced = gpu.options().siren_activations == Some(SirenActivations::Scratch);
    let strides: Vec<u32> = networks
        .into_iter()
        .filter_map(wgsl::scratch_stride)
        .collect();
    let wide = strides.iter().any(|&s| s >= 8 * SCRATCH_MIN_WIDTH);
    (forced || wide)
        .then(|| strides.into_iter().max())
        .flatten()
}

/// The form of the SIREN snippets for a kernel whose scratch stride is `stride`.
pub(crate) fn activations(stride: Option<u32>) -> SirenActivations {
    match stride {
        Some(_) => SirenActivations::Scratch,
        None => SirenActivations::Private,
    }
}

/// What a kernel's source starts with where SIRENs keep their activations in a scratch of
/// `stride` floats per slot (nothing where `stride` is `None`).
pub(crate) fn prelude(stride: Option<u32>) -> String {
    stride
        .map(|stride| wgsl::scratch_source(SCRATCH_GROUP, stride))
        .unwrap_or_default()
}

/// Slots of `stride` floats a scene's queries keep (see [`MAX_SCRATCH_BYTES`]).
pub(crate) fn query_slots(gpu: &GpuContext, stride: u32) -> u32 {
    let bytes = crate::gpu::binding_limit(&gpu.limits()).min(MAX_SCRATCH_BYTES);
    (bytes / (4 * u64::from(stride.max(1)))).clamp(1, u64::from(u32::MAX)) as u32
}

/// The scratch group's layout: one read-write storage buffer at binding 0.
pub(crate) fn layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("sdf_scratch"),
        entries: &[crate::gpu::storage_layout_entry(0, false)],
    })
}

/// A scratch buffer of `slots` slots of `stride` floats, bound with `layout`.
pub(crate) fn bind_group(
    gpu: &GpuContext,
    layout: &wgpu::BindGroupLayout,
    stride: u32,
    slots: u32,
) -> Result<wgpu::BindGroup, GpuError> {
    let floats = u64::from(stride) * u64::from(slots.max(1));
    // The shaders index it with u32s.
    if floats > u64::from(u32::MAX) {
        return Err(GpuError::BufferTooLarge {
            label: "SIREN scratch (HWSDF_SIREN_ACTIVATIONS)".into(),
            requested: 4 * floats,
            limit_name: "2^32 floats, what a u32 index reaches",
            limit: 4 * u64::from(u32::MAX),
        });
    }
    let buffer = gpu.storage_zeroed("SIREN scratch (HWSDF_SIREN_ACTIVATIONS)", 4 * floats)?;
    Ok(gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("sdf_scratch"),
        layout,
        entries: &[crate::gpu::entry(0, &buffer)],
    }))
}
