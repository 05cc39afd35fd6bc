//! The forward-mode training step: the SIREN loss and its parameter gradient with four rows per
//! point in every product (the point and its three unit tangents, so that ∇ₓΦ comes out of the
//! forward pass), then the backward pass over those rows. 12n row-products per hidden layer; the
//! reverse-over-reverse step of [`super::ror`] does it in 6n and is the default wherever it runs
//! (see [`super::ror::TrainStep`]).

use super::gpu::{HeadUniforms, ReduceUniforms, SirenGpu, SirenGpuError, StepLaunches};
use super::kernels::products::{GemmUniforms, gemm_backward, gemm_forward, gemm_wgrad, splits_for};
use super::kernels::row_blocked::{Epilogue, SPLITS};
use super::kernels::tiled::TiledEpilogue;
use super::kernels::{Launch, WG};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::shaders;

/// The launches of one step for `n` points (`n_surface` on the surface) reading the input
/// streams (twelve floats per point: the point and e_x, e_y, e_z) and the surface normals,
/// writing the loss partials (one per workgroup of `WG` points).
#[allow(clippy::too_many_arguments)]
pub(crate) fn build(
    gpu: &GpuContext,
    net: &SirenGpu,
    n: u32,
    n_surface: u32,
    weights: &super::LossWeights,
    x_streams: &wgpu::Buffer,
    normals: &wgpu::Buffer,
    loss_partial: &wgpu::Buffer,
) -> Result<StepLaunches, SirenGpuError> {
    let cfg = net.config;
    let layers = &net.layers;
    let p = &net.pipelines;
    let rows = 4 * n;
    let width = cfg.width as u64;
    let l_hidden = cfg.hidden_layers;
    let act_bytes = u64::from(rows) * width * 4;
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
    let wgrads: Vec<GemmUniforms> = layers.iter().map(|l| gemm_wgrad(l, rows)).collect();
    let partial_len = wgrads
        .iter()
        .enumerate()
        .map(|(l, u)| match net.dense_for(l) {
            Some(d) => d.partial_len(l),
            None => u64::from(u.pbias_off) + u64::from(splits_for(rows) * u.m),
        })
        .max()
        .unwrap_or(1);
    let partial = gpu.storage_zeroed("siren wgrad partial", partial_len * 4)?;
    let reduce = gpu.pipeline(&shaders::SIREN_TRAIN, "reduce_wgrad", &[])?;

    let mut launches = Vec::new();
    let mut keep = Vec::new();
    // Forward: Z_l = A_{l-1} W_lᵀ, then bias, sine and tangents.
    for l in 0..l_hidden {
        let src = if l == 0 { x_streams } else { &act[l - 1] };
        if let Some(d) = net.dense_for(l) {
            let epilogue = Epilogue::SineWithTangents {
                omega: cfg.omega0,
                act: &act[l],
            };
            launches.extend(d.forward(gpu, l, rows, epilogue, src, &net.params, &z[l])?);
        } else if let Some(t) = &net.tiled {
            let u = gemm_forward(&layers[l], rows, false, cfg.omega0);
            let epilogue = TiledEpilogue::SineWithTangents {
                omega: cfg.omega0,
                act: &act[l],
            };
            launches.push(t.gemm(gpu, &u, epilogue, src, &net.params, &z[l]));
        } else {
            let u = gemm_forward(&layers[l], rows, false, cfg.omega0);
            launches.push(net.gemm_launch(gpu, &u, src, &net.params, &z[l]));
            launches.push(net.sine_forward_launch(gpu, l, n, &z[l], &act[l]));
        }
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
        w_sign: weights.sign,
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
            entry(3, normals),
            entry(4, &values),
            entry(5, &dout),
            entry(6, loss_partial),
        ],
        n,
    ));
    // Backward: the output layer gives Z̄ of the last sine layer.
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
                      b: &wgpu::Buffer|
     -> Result<(), GpuError> {
        let val = wgrads[l];
        let (splits, pbias_off) = match net.dense_for(l) {
            Some(d) => {
                let (launch, pbias_off) = d.weight_gradient(gpu, l, n, a, b, &partial, false)?;
                launches.push(launch);
                (SPLITS, pbias_off)
            }
            None => {
                launches.push(match &net.tiled {
                    Some(t) => t.gemm(gpu, &val, TiledEpilogue::WeightGradient, a, b, &partial),
                    None => net.gemm_launch(gpu, &val, a, b, &partial),
                });
                (splits_for(rows), val.pbias_off)
            }
        };
        let ru = ReduceUniforms {
            m: val.m,
            n: val.n,
            splits,
            w_off: layers[l].weight as u32,
            b_off: layers[l].bias as u32,
            pbias_off,
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
        keep.push(rub);
        Ok(())
    };
    push_wgrad(
        &mut launches,
        &mut keep,
        l_hidden,
        &dout,
        &act[l_hidden - 1],
    )?;
    for l in (0..l_hidden).rev() {
        let src = if l == 0 { x_streams } else { &act[l - 1] };
        push_wgrad(&mut launches, &mut keep, l, &zbar[l % 2], src)?;
        if l > 0 {
            if let Some(d) = net.dense_for(l) {
                let below = Some((cfg.omega0, &z[l - 1]));
                let (src, dst) = (&zbar[l % 2], &zbar[(l - 1) % 2]);
                launches.extend(d.backward(gpu, l, rows, src, dst, below)?);
            } else if let Some(t) = &net.tiled {
                let u = gemm_backward(&layers[l], rows);
                let epilogue = TiledEpilogue::SineBelow {
                    omega: cfg.omega0,
                    z: &z[l - 1],
                };
                let (src, dst) = (&zbar[l % 2], &zbar[(l - 1) % 2]);
                launches.push(t.gemm(gpu, &u, epilogue, src, &net.params, dst));
            } else {
                let u = gemm_backward(&layers[l], rows);
                launches.push(net.gemm_launch(
                    gpu,
                    &u,
                    &zbar[l % 2],
                    &net.params,
                    &zbar[(l - 1) % 2],
                ));
                launches.push(net.sine_backward_launch(
                    gpu,
                    l - 1,
                    n,
                    &zbar[(l - 1) % 2],
                    &z[l - 1],
                ));
            }
        }
    }
    keep.push(hu);
    keep.extend(z);
    keep.extend(act);
    keep.extend(zbar);
    keep.push(dout);
    keep.push(values);
    keep.push(partial);
    Ok(StepLaunches {
        launches,
        keep,
        loss_groups,
    })
}
