//! Making a model's query buffers and recording and submitting its queries: the serving path
//! for a network's GPU side, which [`NeuralSdf`](crate::NeuralSdf) drives.

use std::sync::Arc;

use glam::Vec3;

use super::{
    Kernels, MapSlot, NEXT_GENERATION, NglodBindings, Prepared, QueryBuffers,
    QueryBuffersDescriptor, QueryOutputs, QuerySpace, QueryTicket, QueryTransfer, QueryUniforms,
    Stages, WG,
};
use crate::gpu::{GpuContext, GpuError, GpuTimer, entry};
use crate::model_file::Normalization;
use crate::serve::error::{NeuralSdfError, QueryError};
use crate::serve::network::GpuNetwork;
use crate::shaders;

impl QueryBuffers {
    /// Buffers for queries of `network`, the GPU side of model `model` (its identity) with
    /// `normalization`, on `gpu`'s device: see [`NeuralSdf::create_query_buffers`].
    ///
    /// [`NeuralSdf::create_query_buffers`]: crate::NeuralSdf::create_query_buffers
    pub(crate) fn new(
        gpu: &GpuContext,
        network: &mut GpuNetwork,
        model: u64,
        normalization: Normalization,
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
            QuerySpace::Mesh => (normalization.center.as_vec3(), normalization.scale),
            QuerySpace::Normalized => (Vec3::ZERO, 1.0),
        };
        let map = transform.0.extend(transform.1);
        let one_dispatch = match network {
            GpuNetwork::Nglod(m) => Some(Kernels::Nglod(NglodBindings::new(
                gpu,
                m,
                (&points, &results),
                normals,
                transform,
                desc.kernel,
            )?)),
            GpuNetwork::Siren(s) => s
                .query_launch(gpu, &points, &results, desc.capacity, normals, map)?
                .map(Kernels::Siren),
        };
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
            model,
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

    /// Refuses buffers made for another model (identity `model`) or another device.
    pub(crate) fn check_owner(&self, model: u64, gpu: &GpuContext) -> Result<(), QueryError> {
        if self.model != model || self.device != *gpu.device() {
            return Err(QueryError::Foreign);
        }
        Ok(())
    }

    /// Refuses a recording while the results buffer is in use: with mapped transfers it is
    /// mapped from a submission until its results are dropped, and no other submission may use
    /// it meanwhile.
    pub(crate) fn check_free(&self) -> Result<(), QueryError> {
        if self.mapped && (self.in_flight.is_some() || self.map_busy()) {
            return Err(QueryError::Busy);
        }
        Ok(())
    }

    /// Uploads `points`, records their query with `record` (which records `n` points' query
    /// into the encoder, as [`QueryBuffers::record`] does), copies the results to the staging
    /// buffer and submits, without waiting: see [`NeuralSdf::submit_query`]. `lod` is the
    /// model's level of detail and `timed` picks the slot of commands recorded ahead.
    ///
    /// [`NeuralSdf::submit_query`]: crate::NeuralSdf::submit_query
    pub(crate) fn submit(
        &mut self,
        gpu: &GpuContext,
        model: u64,
        points: &[Vec3],
        lod: Option<usize>,
        timed: bool,
        mut record: impl FnMut(&mut Self, &mut wgpu::CommandEncoder, u32) -> Result<(), NeuralSdfError>,
    ) -> Result<QueryTicket, NeuralSdfError> {
        if self.in_flight.is_some() {
            return Err(QueryError::Busy.into());
        }
        self.check_owner(model, gpu)?;
        let (n, submission) = if self.mapped {
            let n = self.upload_mapped(gpu, points)?;
            // Commands recorded for this count and level of detail are current only while the
            // uniforms still hold them: no other recording came in between.
            let prepared = self.prepared[usize::from(timed)]
                .take()
                .filter(|p| p.n == n && p.lod == lod && self.recorded == Some((n, lod)));
            let commands = match prepared {
                Some(p) => {
                    self.prepared_used += 1;
                    p.commands
                }
                None => {
                    self.check_free()?;
                    let mut enc = gpu.device().create_command_encoder(&Default::default());
                    record(self, &mut enc, n)?;
                    enc.finish()
                }
            };
            (n, gpu.queue().submit([commands]))
        } else {
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            let n = self.upload_in(&mut enc, points)?;
            self.belt.finish();
            record(self, &mut enc, n)?;
            let bytes = self.result_bytes(n);
            if bytes > 0 {
                enc.copy_buffer_to_buffer(&self.results, 0, &self.staging, 0, bytes);
            }
            let submission = gpu.queue().submit([enc.finish()]);
            self.belt.recall();
            (n, submission)
        };
        let bytes = self.result_bytes(n);
        // Unique across every QueryBuffers, so a ticket is only ever taken by its own self.
        self.generation = NEXT_GENERATION.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if bytes > 0 {
            self.map
                .request(self.staging.slice(..bytes), wgpu::MapMode::Read);
        }
        self.in_flight = Some((self.generation, n));
        if self.mapped && n > 0 && self.one_dispatch() {
            // The next query, likely of the same size, recorded while this one runs. Only
            // this method submits it, once this query has been waited for and its results
            // unmapped, so the busy check does not apply. On failure the next query records
            // its own.
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            if record(self, &mut enc, n).is_ok() {
                self.prepared[usize::from(timed)] = Some(Prepared {
                    n,
                    lod,
                    commands: enc.finish(),
                });
            }
        }
        Ok(QueryTicket {
            generation: self.generation,
            submission,
            n,
        })
    }

    /// Records a query of the first `n` points with `network` at level of detail `lod` into
    /// `enc`, bracketed by `timer` where given, without checking that the buffers are the
    /// model's or free (callers do).
    pub(crate) fn record(
        &mut self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        network: &mut GpuNetwork,
        lod: Option<usize>,
        n: u32,
        timer: Option<&GpuTimer>,
    ) -> Result<(), NeuralSdfError> {
        self.check_count(n as usize)?;
        if n == 0 {
            return Ok(());
        }
        self.recorded = Some((n, lod));
        let normals = self.outputs == QueryOutputs::ValuesAndNormals;
        {
            match (network, &mut self.kernels) {
                (GpuNetwork::Nglod(m), Kernels::Nglod(bindings)) => {
                    m.record_eval(gpu, enc, bindings.for_count(gpu, n), n, lod, timer)?
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
        }
    }
}
