//! [`Launch`]: one compute dispatch with its pipeline and bind group, recorded into a shared
//! pass or, for a profile, into a timed pass of its own ([`record_launches`]).

use super::{GpuContext, PassProfiler};

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

    /// The label it was made with (a profile's row).
    pub(crate) fn label(&self) -> &str {
        &self.label
    }

    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        self.record_groups(pass, self.groups);
    }

    /// Records it with another workgroup grid.
    pub(crate) fn record_groups(&self, pass: &mut wgpu::ComputePass<'_>, groups: (u32, u32, u32)) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, groups.2);
    }
}

/// A launch to record and its workgroup grid (x, y, z), as [`record_launches`] takes them.
pub(crate) type GridLaunch<'a> = (&'a Launch, (u32, u32, u32));

/// Records `launches`, each with its workgroup grid, into one compute pass named `label`, or,
/// given a profiler, each into a timed pass of its own (named by the launch's label).
pub(crate) fn record_launches(
    enc: &mut wgpu::CommandEncoder,
    label: &str,
    launches: &[GridLaunch<'_>],
    profiler: Option<&mut PassProfiler>,
) {
    match profiler {
        None => {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(label),
                timestamp_writes: None,
            });
            for (launch, groups) in launches {
                launch.record_groups(&mut pass, *groups);
            }
        }
        Some(profiler) => {
            for (launch, groups) in launches {
                launch.record_groups(&mut profiler.begin_pass(enc, launch.label()), *groups);
            }
        }
    }
}
