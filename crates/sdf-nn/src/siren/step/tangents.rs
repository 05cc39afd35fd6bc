//! The forward-mode training step: the SIREN loss and its parameter gradient with four rows per
//! point in every product (the point and its three unit tangents, so that ∇ₓΦ comes out of the
//! forward pass), then the backward pass over those rows. 12n row-products per hidden layer; the
//! reverse-over-reverse step of [`super::reverse_over_reverse`] does it in 6n and is the default
//! wherever it runs (see [`super::TrainStep`]).

use super::super::kernels::head::HeadUniforms;
use super::super::kernels::products::{GemmUniforms, gemm_backward, gemm_wgrad, splits_for};
use super::super::kernels::row_blocked::SPLITS;
use super::super::kernels::tiled::TiledEpilogue;
use super::super::kernels::{Launch, WG};
use super::super::loss::LossWeights;
use super::super::net::NetView;
use super::{StepLaunches, WgradReduce};
use crate::gpu::{GpuContext, GpuError, entry};

/// The step's intermediate buffers for a batch: per hidden layer the pre-activations and the
/// activations with their tangents (four rows per point), two ping-pong buffers of Z̄, the
/// values and the head's output gradients.
struct Buffers {
    z: Vec<wgpu::Buffer>,
    act: Vec<wgpu::Buffer>,
    zbar: [wgpu::Buffer; 2],
    values: wgpu::Buffer,
    dout: wgpu::Buffer,
}

impl Buffers {
    fn new(gpu: &GpuContext, net: &NetView<'_>, n: u32) -> Result<Self, GpuError> {
        let act_bytes = u64::from(4 * n) * net.config.width as u64 * 4;
        let mut z = Vec::new();
        let mut act = Vec::new();
        for _ in 0..net.config.hidden_layers {
            z.push(gpu.storage_zeroed("siren z", act_bytes)?);
            act.push(gpu.storage_zeroed("siren act", act_bytes)?);
        }
        Ok(Buffers {
            z,
            act,
            zbar: [
                gpu.storage_zeroed("siren zbar 0", act_bytes)?,
                gpu.storage_zeroed("siren zbar 1", act_bytes)?,
            ],
            values: gpu.storage_zeroed("siren values", u64::from(n) * 16)?,
            dout: gpu.storage_zeroed("siren dout", u64::from(n) * 16)?,
        })
    }
}

/// The launches of one step for `n` points (`n_surface` on the surface) reading the input
/// streams (twelve floats per point: the point and e_x, e_y, e_z) and the surface normals,
/// writing the loss partials (one per workgroup of `WG` points).
#[allow(clippy::too_many_arguments)]
pub(crate) fn build(
    gpu: &GpuContext,
    net: &NetView<'_>,
    n: u32,
    n_surface: u32,
    weights: &LossWeights,
    x_streams: &wgpu::Buffer,
    normals: &wgpu::Buffer,
    loss_partial: &wgpu::Buffer,
) -> Result<StepLaunches, GpuError> {
    let rows = 4 * n;
    let b = Buffers::new(gpu, net, n)?;
    let wgrads: Vec<GemmUniforms> = net.layers.iter().map(|l| gemm_wgrad(l, rows)).collect();
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
    let reduce = WgradReduce::new(gpu, "siren", &partial, net.grads, false)?;

    let mut launches = Vec::new();
    let mut keep = Vec::new();
    // Forward: Z_l = A_{l-1} W_lᵀ, then bias, sine and tangents.
    for l in 0..net.config.hidden_layers {
        let src = if l == 0 { x_streams } else { &b.act[l - 1] };
        launches.extend(net.hidden_forward(gpu, l, n, true, src, &b.z[l], &b.act[l])?);
    }
    let hu = record_head(
        gpu,
        net,
        &b,
        n,
        n_surface,
        weights,
        normals,
        loss_partial,
        &mut launches,
    );
    keep.push(hu);
    // Backward: each layer's weight gradient, then Z̄ of the layer below.
    let mut push_wgrad = |launches: &mut Vec<Launch>,
                          l: usize,
                          a: &wgpu::Buffer,
                          x: &wgpu::Buffer|
     -> Result<(), GpuError> {
        let val = wgrads[l];
        let (splits, pbias_off) = match net.dense_for(l) {
            Some(d) => {
                let (launch, pbias_off) = d.weight_gradient(gpu, l, n, a, x, &partial, false)?;
                launches.push(launch);
                (SPLITS, pbias_off)
            }
            None => {
                launches.push(match net.tiled {
                    Some(t) => t.gemm(gpu, &val, TiledEpilogue::WeightGradient, a, x, &partial),
                    None => net.gemm.launch(gpu, &val, a, x, net.params, &partial),
                });
                (splits_for(rows), val.pbias_off)
            }
        };
        reduce.push(
            gpu,
            launches,
            &mut keep,
            &net.layers[l],
            splits,
            pbias_off,
            false,
        );
        Ok(())
    };
    let l_hidden = net.config.hidden_layers;
    push_wgrad(&mut launches, l_hidden, &b.dout, &b.act[l_hidden - 1])?;
    for l in (0..l_hidden).rev() {
        let src = if l == 0 { x_streams } else { &b.act[l - 1] };
        push_wgrad(&mut launches, l, &b.zbar[l % 2], src)?;
        if l > 0 {
            launches.extend(hidden_backward(gpu, net, &b, l, n)?);
        }
    }
    let Buffers {
        z,
        act,
        zbar,
        values,
        dout,
    } = b;
    keep.extend(z);
    keep.extend(act);
    keep.extend(zbar);
    keep.push(dout);
    keep.push(values);
    keep.push(partial);
    Ok(StepLaunches {
        launches,
        keep,
        loss_groups: n.div_ceil(WG),
    })
}

/// Records the head (Φ, ∇ₓΦ and the loss) and its backward into Z̄ of the last hidden layer;
/// returns the head's uniforms, which the launches use.
#[allow(clippy::too_many_arguments)]
fn record_head(
    gpu: &GpuContext,
    net: &NetView<'_>,
    b: &Buffers,
    n: u32,
    n_surface: u32,
    weights: &LossWeights,
    normals: &wgpu::Buffer,
    loss_partial: &wgpu::Buffer,
    launches: &mut Vec<Launch>,
) -> wgpu::Buffer {
    let cfg = &net.config;
    let l_hidden = cfg.hidden_layers;
    let last = net.layers.last().expect("at least one layer");
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
        &net.head.forward,
        "siren head fwd",
        &[
            entry(0, &hu),
            entry(1, &b.act[l_hidden - 1]),
            entry(2, net.params),
            entry(3, normals),
            entry(4, &b.values),
            entry(5, &b.dout),
            entry(6, loss_partial),
        ],
        n,
    ));
    // Backward: the output layer gives Z̄ of the last sine layer.
    launches.push(Launch::flat(
        gpu,
        &net.head.backward,
        "siren head bwd",
        &[
            entry(0, &hu),
            entry(2, net.params),
            entry(7, &b.dout),
            entry(8, &b.z[l_hidden - 1]),
            entry(9, &b.zbar[(l_hidden - 1) % 2]),
        ],
        n * cfg.width as u32,
    ));
    hu
}

/// The launches of Z̄_{l-1} = D(Z_{l-1}) ⊙ Z̄_l W_l (layer `l > 0`) on whichever family runs
/// layer `l`.
fn hidden_backward(
    gpu: &GpuContext,
    net: &NetView<'_>,
    b: &Buffers,
    l: usize,
    n: u32,
) -> Result<Vec<Launch>, GpuError> {
    let rows = 4 * n;
    let omega = net.config.omega0;
    let (src, dst) = (&b.zbar[l % 2], &b.zbar[(l - 1) % 2]);
    if let Some(d) = net.dense_for(l) {
        let below = Some((omega, &b.z[l - 1]));
        return d.backward(gpu, l, rows, src, dst, below);
    }
    let u = gemm_backward(&net.layers[l], rows);
    Ok(match net.tiled {
        Some(t) => {
            let epilogue = TiledEpilogue::SineBelow {
                omega,
                z: &b.z[l - 1],
            };
            vec![t.gemm(gpu, &u, epilogue, src, net.params, dst)]
        }
        None => vec![
            net.gemm.launch(gpu, &u, src, net.params, net.params, dst),
            net.gemm
                .sine_backward(gpu, net.sine_layer(l - 1), n, dst, &b.z[l - 1]),
        ],
    })
}
