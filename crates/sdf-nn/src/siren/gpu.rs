//! Host code of the SIREN kernels (`shaders/siren_gemm.wgsl`, `siren_head.wgsl`,
//! `siren_train.wgsl`): inference, inference with the input gradient, and the forward + double
//! backward of a training step.
//!
//! Activations are row-major `[rows, width]` matrices. With tangents, a point owns four
//! consecutive rows: the value, then ∂/∂x, ∂/∂y, ∂/∂z. Every dense layer is one launch of the
//! tiled GEMM kernel, whose epilogue applies the sine (forward) or its derivative (backward);
//! weight gradients are split-K GEMMs over the batch whose partials a second kernel sums into
//! the gradient buffer, so there are no atomics anywhere.

use glam::Vec3;

use super::{LayerLayout, Siren, SirenConfig, SirenConfigError};
use crate::gpu::{GpuContext, GpuError};
use crate::shaders;

/// Errors of the SIREN GPU code.
#[derive(Debug, thiserror::Error)]
pub enum SirenGpuError {
    /// The device failed or refused something.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The network configuration is unusable.
    #[error(transparent)]
    Config(#[from] SirenConfigError),
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct GemmUniforms {
    mode: u32,
    m: u32,
    n: u32,
    k: u32,
    a_off: u32,
    a_rs: u32,
    a_cs: u32,
    a_kcontig: u32,
    b_off: u32,
    b_rs: u32,
    b_cs: u32,
    b_kcontig: u32,
    ldc: u32,
    bias_off: u32,
    tangents: u32,
    store_z: u32,
    k_chunk: u32,
    pbias_off: u32,
    omega: f32,
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct HeadUniforms {
    pub(crate) mode: u32,
    pub(crate) n_points: u32,
    pub(crate) n_surface: u32,
    pub(crate) width: u32,
    pub(crate) w_off: u32,
    pub(crate) b_off: u32,
    pub(crate) _pad0: u32,
    pub(crate) _pad1: u32,
    pub(crate) w_surface: f32,
    pub(crate) w_off_surface: f32,
    pub(crate) w_normal: f32,
    pub(crate) w_eikonal: f32,
    pub(crate) alpha: f32,
    pub(crate) inv_n: f32,
    pub(crate) omega: f32,
    pub(crate) _pad2: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ReduceUniforms {
    m: u32,
    n: u32,
    splits: u32,
    w_off: u32,
    b_off: u32,
    pbias_off: u32,
    _pad0: u32,
    _pad1: u32,
}

const TILE: u32 = 64;
const WG: u32 = 256;
/// Rows of the batch per split of a weight-gradient GEMM (a multiple of 16 and of 4).
const K_CHUNK: u32 = 1024;

/// Rows of a K chunk → number of splits.
fn splits_for(rows: u32) -> u32 {
    rows.div_ceil(K_CHUNK).max(1)
}

fn gemm_forward(
    lay: &LayerLayout,
    rows: u32,
    tangents: bool,
    store_z: bool,
    omega: f32,
) -> GemmUniforms {
    GemmUniforms {
        mode: 0,
        m: rows,
        n: lay.fan_out as u32,
        k: lay.fan_in as u32,
        a_rs: lay.fan_in as u32,
        a_cs: 1,
        a_kcontig: 1,
        b_off: lay.weight as u32,
        // B(k = i, n = o) = W[o, i].
        b_rs: 1,
        b_cs: lay.fan_in as u32,
        b_kcontig: 1,
        ldc: lay.fan_out as u32,
        bias_off: lay.bias as u32,
        tangents: tangents as u32,
        store_z: store_z as u32,
        omega,
        ..Default::default()
    }
}

/// Ā_{l-1} = Z̄_l · W_l, epilogue to Z̄_{l-1}.
fn gemm_backward(lay: &LayerLayout, rows: u32, omega: f32) -> GemmUniforms {
    GemmUniforms {
        mode: 1,
        m: rows,
        n: lay.fan_in as u32,
        k: lay.fan_out as u32,
        a_rs: lay.fan_out as u32,
        a_cs: 1,
        a_kcontig: 1,
        b_off: lay.weight as u32,
        b_rs: lay.fan_in as u32,
        b_cs: 1,
        b_kcontig: 0,
        ldc: lay.fan_in as u32,
        tangents: 1,
        omega,
        ..Default::default()
    }
}

/// W̄_l partials = Z̄_lᵀ · A_{l-1}, split over the batch rows.
fn gemm_wgrad(lay: &LayerLayout, rows: u32) -> GemmUniforms {
    let (m, n) = (lay.fan_out as u32, lay.fan_in as u32);
    let splits = splits_for(rows);
    GemmUniforms {
        mode: 2,
        m,
        n,
        k: rows,
        a_rs: 1,
        a_cs: m,
        a_kcontig: (m == 1) as u32,
        b_rs: n,
        b_cs: 1,
        b_kcontig: (n == 1) as u32,
        ldc: n,
        tangents: 1,
        k_chunk: K_CHUNK,
        pbias_off: splits * m * n,
        ..Default::default()
    }
}

fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// One recorded kernel launch: its pipeline, bind group and workgroup grid.
#[derive(Debug)]
pub(crate) struct Launch {
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

    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(self.groups.0, self.groups.1, self.groups.2);
    }
}

fn gemm_groups(u: &GemmUniforms) -> (u32, u32, u32) {
    let z = if u.mode == 2 { splits_for(u.k) } else { 1 };
    (u.n.div_ceil(TILE), u.m.div_ceil(TILE), z)
}

/// The compiled pipelines SIREN uses.
#[derive(Debug, Clone)]
pub(crate) struct Pipelines {
    pub(crate) gemm: wgpu::ComputePipeline,
    pub(crate) head_forward: wgpu::ComputePipeline,
    pub(crate) head_backward: wgpu::ComputePipeline,
}

impl Pipelines {
    fn new(gpu: &GpuContext) -> Result<Self, GpuError> {
        Ok(Pipelines {
            gemm: gpu.pipeline(&shaders::SIREN_GEMM, "gemm", &[])?,
            head_forward: gpu.pipeline(&shaders::SIREN_HEAD, "head_forward", &[])?,
            head_backward: gpu.pipeline(&shaders::SIREN_HEAD, "head_backward", &[])?,
        })
    }
}

/// Buffers and launches of the forward pass for a fixed capacity of points.
#[derive(Debug)]
struct EvalWorkspace {
    capacity: u32,
    tangents: bool,
    input: wgpu::Buffer,
    values: wgpu::Buffer,
    uniforms: Vec<wgpu::Buffer>,
    head_uniforms: wgpu::Buffer,
    launches: Vec<Launch>,
    /// The uniforms were last written for this many points.
    written_for: Option<u32>,
}

/// A SIREN's parameters (and gradients) on the GPU, with its kernels.
#[derive(Debug)]
pub struct SirenGpu {
    config: SirenConfig,
    layers: Vec<LayerLayout>,
    params: wgpu::Buffer,
    grads: wgpu::Buffer,
    pipelines: Pipelines,
    eval: Option<EvalWorkspace>,
    eval_grad: Option<EvalWorkspace>,
    dummy: wgpu::Buffer,
}

impl SirenGpu {
    /// Uploads `siren`'s parameters and compiles (or fetches from the context's cache) the
    /// kernels.
    pub fn new(gpu: &GpuContext, siren: &Siren) -> Result<Self, SirenGpuError> {
        let config = *siren.config();
        config.validate()?;
        let params = gpu.storage_from_slice("siren params", siren.params())?;
        let grads = gpu.storage_zeroed("siren grads", siren.params().len() as u64 * 4)?;
        Ok(SirenGpu {
            config,
            layers: config.layers(),
            params,
            grads,
            pipelines: Pipelines::new(gpu)?,
            eval: None,
            eval_grad: None,
            dummy: gpu.storage_zeroed("siren dummy", 4)?,
        })
    }

    /// The architecture.
    pub fn config(&self) -> &SirenConfig {
        &self.config
    }

    /// The flat parameter buffer (layout in [`super`]).
    pub fn params_buffer(&self) -> &wgpu::Buffer {
        &self.params
    }

    /// The flat gradient buffer, same layout; the backward pass accumulates into it.
    pub fn grads_buffer(&self) -> &wgpu::Buffer {
        &self.grads
    }

    /// Replaces the parameters on the GPU.
    pub fn upload(&self, gpu: &GpuContext, siren: &Siren) -> Result<(), SirenGpuError> {
        if *siren.config() != self.config {
            return Err(SirenConfigError::BadShape {
                width: siren.config().width,
                layers: siren.config().hidden_layers,
            }
            .into());
        }
        gpu.write(&self.params, siren.params())?;
        Ok(())
    }

    /// The parameters as a host [`Siren`].
    pub fn download(&self, gpu: &GpuContext) -> Result<Siren, SirenGpuError> {
        let n = self.config.param_count() as u64;
        let p: Vec<f32> = gpu.read_back_range(&self.params, 0, n)?;
        Ok(Siren::from_params(self.config, p)?)
    }

    /// The gradient buffer's contents.
    pub fn read_grads(&self, gpu: &GpuContext) -> Result<Vec<f32>, SirenGpuError> {
        let n = self.config.param_count() as u64;
        Ok(gpu.read_back_range(&self.grads, 0, n)?)
    }

    /// Points per launch: bounded by the storage-binding limit on the largest activation
    /// buffer, and by 65536 to keep memory modest.
    fn chunk_capacity(&self, gpu: &GpuContext, tangents: bool) -> u32 {
        let limit = gpu.limits().max_storage_buffer_binding_size;
        let per_point = self.config.width as u64 * 4 * if tangents { 4 } else { 1 };
        let cap = (limit / per_point).clamp(64, 65536);
        (cap as u32 / 64) * 64
    }

    /// Φ at each point (normalised coordinates), any number of points, split into launches that
    /// fit the device limits.
    pub fn eval(&mut self, gpu: &GpuContext, points: &[Vec3]) -> Result<Vec<f32>, SirenGpuError> {
        let vals = self.run_eval(gpu, points, false)?;
        Ok(vals)
    }

    /// Φ and ∇Φ at each point.
    pub fn eval_with_gradient(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<(f32, Vec3)>, SirenGpuError> {
        let vals = self.run_eval(gpu, points, true)?;
        Ok(vals
            .chunks_exact(4)
            .map(|v| (v[0], Vec3::new(v[1], v[2], v[3])))
            .collect())
    }

    fn run_eval(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
        tangents: bool,
    ) -> Result<Vec<f32>, SirenGpuError> {
        let per = if tangents { 4 } else { 1 };
        let mut out = Vec::with_capacity(points.len() * per);
        if points.is_empty() {
            return Ok(out);
        }
        let slot_missing = if tangents {
            self.eval_grad.is_none()
        } else {
            self.eval.is_none()
        };
        if slot_missing {
            let cap = self.chunk_capacity(gpu, tangents);
            let ws = self.build_eval(gpu, cap, tangents)?;
            if tangents {
                self.eval_grad = Some(ws);
            } else {
                self.eval = Some(ws);
            }
        }
        let ws = if tangents {
            self.eval_grad.as_mut()
        } else {
            self.eval.as_mut()
        }
        .expect("built above");
        for chunk in points.chunks(ws.capacity as usize) {
            let n = chunk.len() as u32;
            write_eval_uniforms(gpu, &self.config, &self.layers, ws, n)?;
            let input: Vec<f32> = if tangents {
                chunk
                    .iter()
                    .flat_map(|p| [p.x, p.y, p.z, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
                    .collect()
            } else {
                chunk.iter().flat_map(|p| p.to_array()).collect()
            };
            gpu.write(&ws.input, &input)?;
            let mut enc = gpu.device().create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("siren eval"),
                    timestamp_writes: None,
                });
                for l in &ws.launches {
                    l.record(&mut pass);
                }
            }
            gpu.queue().submit([enc.finish()]);
            out.extend(gpu.read_back_range::<f32>(&ws.values, 0, u64::from(n) * per as u64)?);
        }
        Ok(out)
    }

    fn build_eval(
        &self,
        gpu: &GpuContext,
        capacity: u32,
        tangents: bool,
    ) -> Result<EvalWorkspace, SirenGpuError> {
        let per = if tangents { 4u64 } else { 1 };
        let rows = u64::from(capacity) * per;
        let width = self.config.width as u64;
        let input = gpu.storage_zeroed("siren eval input", rows * 3 * 4)?;
        let act = [
            gpu.storage_zeroed("siren eval act 0", rows * width * 4)?,
            gpu.storage_zeroed("siren eval act 1", rows * width * 4)?,
        ];
        let values = gpu.storage_zeroed("siren eval values", u64::from(capacity) * per * 4)?;
        let n_hidden = self.config.hidden_layers;
        let mut uniforms = Vec::new();
        let mut launches = Vec::new();
        for l in 0..n_hidden {
            let u = gpu.uniform("siren gemm uniforms", &GemmUniforms::default());
            let src = if l == 0 { &input } else { &act[(l - 1) % 2] };
            let u_val = gemm_forward(
                &self.layers[l],
                rows as u32,
                tangents,
                false,
                self.config.omega0,
            );
            launches.push(Launch::new(
                gpu,
                &self.pipelines.gemm,
                "siren eval gemm",
                &[
                    entry(0, &u),
                    entry(1, src),
                    entry(2, &self.params),
                    entry(3, &self.params),
                    entry(4, &self.dummy),
                    entry(5, &act[l % 2]),
                ],
                gemm_groups(&u_val),
            ));
            uniforms.push(u);
        }
        let head_uniforms = gpu.uniform("siren head uniforms", &HeadUniforms::default());
        launches.push(Launch::flat(
            gpu,
            &self.pipelines.head_forward,
            "siren eval head",
            &[
                entry(0, &head_uniforms),
                entry(1, &act[(n_hidden - 1) % 2]),
                entry(2, &self.params),
                entry(3, &self.dummy),
                entry(4, &values),
                entry(5, &self.grads_dummy(gpu)?),
                entry(6, &self.grads_dummy(gpu)?),
            ],
            capacity,
        ));
        Ok(EvalWorkspace {
            capacity,
            tangents,
            input,
            values,
            uniforms,
            head_uniforms,
            launches,
            written_for: None,
        })
    }

    fn grads_dummy(&self, gpu: &GpuContext) -> Result<wgpu::Buffer, GpuError> {
        gpu.storage_zeroed("siren dummy rw", 4)
    }

    /// The loss of one batch (the first `normals.len()` points on the surface with those
    /// normals, the rest off the surface) and its gradient with respect to every parameter,
    /// computed by the training kernels without an optimiser step. For tests and diagnostics:
    /// it allocates the training buffers on each call.
    pub fn loss_and_gradient(
        &mut self,
        gpu: &GpuContext,
        points: &[Vec3],
        normals: &[Vec3],
        weights: &super::LossWeights,
    ) -> Result<(super::LossTerms, Vec<f32>), SirenGpuError> {
        let n = points.len().max(1) as u32;
        let n_surface = normals.len().min(points.len()) as u32;
        let passes = TrainPasses::new(gpu, self, n, n_surface, weights)?;
        let streams: Vec<f32> = points
            .iter()
            .flat_map(|p| [p.x, p.y, p.z, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
            .collect();
        gpu.write(&passes.x_streams, &streams)?;
        let flat_n: Vec<f32> = normals.iter().flat_map(|v| v.to_array()).collect();
        gpu.write(&passes.normals, &flat_n)?;
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        enc.clear_buffer(&self.grads, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("siren loss and gradient"),
                timestamp_writes: None,
            });
            passes.record(&mut pass);
        }
        gpu.queue().submit([enc.finish()]);
        let partial: Vec<f32> =
            gpu.read_back_range(&passes.loss_partial, 0, u64::from(passes.loss_groups) * 4)?;
        let mut t = [0.0f32; 4];
        for row in partial.chunks_exact(4) {
            for k in 0..4 {
                t[k] += row[k];
            }
        }
        let terms = super::LossTerms {
            surface: t[0],
            off_surface: t[1],
            normal: t[2],
            eikonal: t[3],
        };
        Ok((terms, self.read_grads(gpu)?))
    }
}

fn write_eval_uniforms(
    gpu: &GpuContext,
    config: &SirenConfig,
    layers: &[LayerLayout],
    ws: &mut EvalWorkspace,
    n: u32,
) -> Result<(), GpuError> {
    if ws.written_for == Some(n) {
        return Ok(());
    }
    let rows = if ws.tangents { 4 * n } else { n };
    for (l, u) in ws.uniforms.iter().enumerate() {
        let val = gemm_forward(&layers[l], rows, ws.tangents, false, config.omega0);
        gpu.write(u, &[val])?;
    }
    let last = layers.last().expect("at least one layer");
    let head = HeadUniforms {
        mode: ws.tangents as u32,
        n_points: n,
        width: config.width as u32,
        w_off: last.weight as u32,
        b_off: last.bias as u32,
        omega: config.omega0,
        ..Default::default()
    };
    gpu.write(&ws.head_uniforms, &[head])?;
    ws.written_for = Some(n);
    Ok(())
}

/// The buffers and recorded launches of one training step's forward and backward passes for a
/// batch of `n` points whose input streams the caller writes into [`TrainPasses::x_streams`].
#[derive(Debug)]
pub(crate) struct TrainPasses {
    pub(crate) n: u32,
    pub(crate) x_streams: wgpu::Buffer,
    pub(crate) normals: wgpu::Buffer,
    pub(crate) loss_partial: wgpu::Buffer,
    pub(crate) loss_groups: u32,
    launches: Vec<Launch>,
    _keep: Vec<wgpu::Buffer>,
}

impl TrainPasses {
    /// Everything for a batch of `n` points, `n_surface` of them on the surface.
    pub(crate) fn new(
        gpu: &GpuContext,
        net: &SirenGpu,
        n: u32,
        n_surface: u32,
        weights: &super::LossWeights,
    ) -> Result<Self, SirenGpuError> {
        let cfg = net.config;
        let layers = net.layers.clone();
        let p = net.pipelines.clone();
        let rows = 4 * n;
        let width = cfg.width as u64;
        let l_hidden = cfg.hidden_layers;
        let act_bytes = u64::from(rows) * width * 4;
        let x_streams = gpu.storage_zeroed("siren x streams", u64::from(rows) * 3 * 4)?;
        let normals =
            gpu.storage_zeroed("siren batch normals", u64::from(n_surface.max(1)) * 3 * 4)?;
        let mut z = Vec::new();
        let mut act = Vec::new();
        for _ in 0..l_hidden {
            z.push(gpu.storage_zeroed("siren z", act_bytes)?);
            act.push(gpu.storage_zeroed("siren act", act_bytes)?);
        }
        let zbar = [
            gpu.storage_zeroed("siren zbar 0", act_bytes)?,
            gpu.storage_zeroed("siren zbar 1", act_bytes)?,
        ];
        let values = gpu.storage_zeroed("siren values", u64::from(n) * 16)?;
        let dout = gpu.storage_zeroed("siren dout", u64::from(n) * 16)?;
        let loss_groups = n.div_ceil(WG);
        let loss_partial = gpu.storage_zeroed("siren loss partial", u64::from(loss_groups) * 16)?;
        let wgrads: Vec<GemmUniforms> = layers.iter().map(|l| gemm_wgrad(l, rows)).collect();
        let partial_len = wgrads
            .iter()
            .map(|u| u64::from(u.pbias_off) + u64::from(splits_for(rows) * u.m))
            .max()
            .unwrap_or(1);
        let partial = gpu.storage_zeroed("siren wgrad partial", partial_len * 4)?;
        let dummy_rw = gpu.storage_zeroed("siren dummy rw", 4)?;
        let reduce = gpu.pipeline(&shaders::SIREN_TRAIN, "reduce_wgrad", &[])?;

        let mut launches = Vec::new();
        let mut keep = Vec::new();
        // Forward.
        for l in 0..l_hidden {
            let val = gemm_forward(&layers[l], rows, true, true, cfg.omega0);
            let u = gpu.uniform("siren gemm fwd", &val);
            let src = if l == 0 { &x_streams } else { &act[l - 1] };
            launches.push(Launch::new(
                gpu,
                &p.gemm,
                "siren fwd",
                &[
                    entry(0, &u),
                    entry(1, src),
                    entry(2, &net.params),
                    entry(3, &net.params),
                    entry(4, &z[l]),
                    entry(5, &act[l]),
                ],
                gemm_groups(&val),
            ));
            keep.push(u);
        }
        let last = layers.last().expect("at least one layer");
        let head = HeadUniforms {
            mode: 2,
            n_points: n,
            n_surface,
            width: cfg.width as u32,
            w_off: last.weight as u32,
            b_off: last.bias as u32,
            w_surface: weights.surface,
            w_off_surface: weights.off_surface,
            w_normal: weights.normal,
            w_eikonal: weights.eikonal,
            alpha: weights.alpha,
            inv_n: 1.0 / n as f32,
            omega: cfg.omega0,
            ..Default::default()
        };
        let hu = gpu.uniform("siren head train", &head);
        launches.push(Launch::flat(
            gpu,
            &p.head_forward,
            "siren head fwd",
            &[
                entry(0, &hu),
                entry(1, &act[l_hidden - 1]),
                entry(2, &net.params),
                entry(3, &normals),
                entry(4, &values),
                entry(5, &dout),
                entry(6, &loss_partial),
            ],
            n,
        ));
        // Backward: output layer.
        launches.push(Launch::flat(
            gpu,
            &p.head_backward,
            "siren head bwd",
            &[
                entry(0, &hu),
                entry(2, &net.params),
                entry(7, &dout),
                entry(8, &z[l_hidden - 1]),
                entry(9, &zbar[(l_hidden - 1) % 2]),
            ],
            n * cfg.width as u32,
        ));
        let push_wgrad = |launches: &mut Vec<Launch>,
                          keep: &mut Vec<wgpu::Buffer>,
                          l: usize,
                          a: &wgpu::Buffer,
                          b: &wgpu::Buffer| {
            let val = wgrads[l];
            let u = gpu.uniform("siren gemm wgrad", &val);
            launches.push(Launch::new(
                gpu,
                &p.gemm,
                "siren wgrad",
                &[
                    entry(0, &u),
                    entry(1, a),
                    entry(2, b),
                    entry(3, &net.params),
                    entry(4, &partial),
                    entry(5, &dummy_rw),
                ],
                gemm_groups(&val),
            ));
            let ru = ReduceUniforms {
                m: val.m,
                n: val.n,
                splits: splits_for(rows),
                w_off: layers[l].weight as u32,
                b_off: layers[l].bias as u32,
                pbias_off: val.pbias_off,
                ..Default::default()
            };
            let rub = gpu.uniform("siren reduce", &ru);
            launches.push(Launch::flat(
                gpu,
                &reduce,
                "siren reduce wgrad",
                &[entry(5, &rub), entry(6, &partial), entry(7, &net.grads)],
                val.m * val.n + val.m,
            ));
            keep.push(u);
            keep.push(rub);
        };
        push_wgrad(
            &mut launches,
            &mut keep,
            l_hidden,
            &dout,
            &act[l_hidden - 1],
        );
        for l in (0..l_hidden).rev() {
            let src = if l == 0 { &x_streams } else { &act[l - 1] };
            push_wgrad(&mut launches, &mut keep, l, &zbar[l % 2], src);
            if l > 0 {
                let val = gemm_backward(&layers[l], rows, cfg.omega0);
                let u = gpu.uniform("siren gemm bwd", &val);
                launches.push(Launch::new(
                    gpu,
                    &p.gemm,
                    "siren bwd",
                    &[
                        entry(0, &u),
                        entry(1, &zbar[l % 2]),
                        entry(2, &net.params),
                        entry(3, &z[l - 1]),
                        entry(4, &zbar[(l - 1) % 2]),
                        entry(5, &dummy_rw),
                    ],
                    gemm_groups(&val),
                ));
                keep.push(u);
            }
        }
        keep.push(hu);
        keep.extend(z);
        keep.extend(act);
        keep.extend(zbar);
        keep.push(dout);
        keep.push(values);
        keep.push(partial);
        keep.push(dummy_rw);
        Ok(TrainPasses {
            n,
            x_streams,
            normals,
            loss_partial,
            loss_groups,
            launches,
            _keep: keep,
        })
    }

    /// Records forward, loss and backward (accumulating into the gradient buffer).
    pub(crate) fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        for l in &self.launches {
            l.record(pass);
        }
    }
}
