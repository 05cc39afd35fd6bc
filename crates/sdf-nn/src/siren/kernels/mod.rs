//! SIREN kernel families beyond the original GEMM and row-blocked ones, one module each with
//! its own pipelines; [`super::LayerKernels`] picks the family. Every family records its work
//! as [`Launch`]es.

use crate::gpu::GpuContext;

pub(crate) mod coop;
pub(crate) mod products;
pub(crate) mod tiled;

/// Invocations per workgroup of the 1D kernels ([`Launch::flat`]), and of SIREN's per-point
/// kernels.
pub(crate) const WG: u32 = 256;

/// One recorded kernel launch: its pipeline, bind group and workgroup grid.
#[derive(Debug)]
pub(crate) struct Launch {
    label: String,
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    groups: (u32, u32, u32),
}

impl Launch {
    pub(crate) fn new(
        gpu: &GpuContext,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        entries: &[wgpu::BindGroupEntry<'_>],
        groups: (u32, u32, u32),
    ) -> Self {
        let bind_group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &pipeline.get_bind_group_layout(0),
            entries,
        });
        Launch {
            label: label.to_owned(),
            pipeline: pipeline.clone(),
            bind_group,
            groups,
        }
    }

    /// A 1D launch of `threads` invocations in 256-wide groups, folded into 2D if needed.
    pub(crate) fn flat(
        gpu: &GpuContext,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        entries: &[wgpu::BindGroupEntry<'_>],
        threads: u32,
    ) -> Self {
        let (x, y) = gpu.dispatch_size(threads.div_ceil(WG));
        Self::new(gpu, pipeline, label, entries, (x, y, 1))
    }

    /// The label it was made with (a profile's row).
    pub(crate) fn label(&self) -> &str {
        &self.label
    }

    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        self.record_groups(pass, self.groups);
    }

    /// Its workgroup grid.
    pub(crate) fn groups(&self) -> (u32, u32, u32) {
        self.groups
    }

    /// Records it with another workgroup grid.
    pub(crate) fn record_groups(&self, pass: &mut wgpu::ComputePass<'_>, groups: (u32, u32, u32)) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, groups.2);
    }
}

/// A launch of a one-dispatch inference kernel (tiled fused, cooperative matrices), with its
/// uniforms, whose first field is the row count.
#[derive(Debug)]
pub(crate) struct OneDispatch {
    pub(crate) launch: Launch,
    pub(crate) uniforms: wgpu::Buffer,
    /// Rows per workgroup.
    pub(crate) group_rows: u32,
}

/// Floats from one point to the next in a one-dispatch kernel's input: a caller's vec4 points
/// for a query, else the network's rows (the point, and with tangents the three unit axes).
pub(crate) fn point_stride(query: bool, tangents: bool) -> u32 {
    match (query, tangents) {
        (true, _) => 4,
        (false, true) => 12,
        (false, false) => 3,
    }
}
