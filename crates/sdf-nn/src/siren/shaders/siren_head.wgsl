// SIREN's linear output layer and the loss.
//
// head_forward: one invocation per point. Φ = w·h + b (and ∇Φ_j = w·t_j when the activations
// carry tangents). In training mode it also evaluates the point's four loss terms, writes the
// derivatives of the loss with respect to Φ and ∇Φ (the seed of the backward pass, already
// divided by N) and reduces the terms over the workgroup into one partial per workgroup.
//
// head_backward: one invocation per (point, feature). Turns those derivatives into Z̄ of the
// last sine layer: h̄ = w dΦ, t̄_j = w d∇Φ_j, then through sin/cos as in the GEMM's epilogue.

struct Head {
    // 0: value only (one activation row per point); 1: value and gradient; 2: training.
    mode: u32,
    n_points: u32,
    n_surface: u32,
    width: u32,
    w_off: u32,
    b_off: u32,
    _pad0: u32,
    _pad1: u32,
    w_surface: f32,
    w_off_surface: f32,
    w_normal: f32,
    w_eikonal: f32,
    alpha: f32,
    inv_n: f32,
    omega: f32,
    w_sign: f32,
}

const WG: u32 = 256u;

@group(0) @binding(0) var<uniform> h: Head;
@group(0) @binding(1) var<storage, read> act: array<f32>;
@group(0) @binding(2) var<storage, read> params: array<f32>;
@group(0) @binding(3) var<storage, read> normals: array<f32>;
// Mode 0: Φ per point. Modes 1, 2: (Φ, ∇Φ) per point.
@group(0) @binding(4) var<storage, read_write> values: array<f32>;
// Modes 2: (dL/dΦ, dL/d∇Φ) per point.
@group(0) @binding(5) var<storage, read_write> dout: array<f32>;
// Mode 2: four loss sums per workgroup.
@group(0) @binding(6) var<storage, read_write> loss_partial: array<f32>;

@group(0) @binding(7) var<storage, read> dout_in: array<f32>;
@group(0) @binding(8) var<storage, read> z_last: array<f32>;
@group(0) @binding(9) var<storage, read_write> zbar: array<f32>;


// Inference only (modes 0 and 1): head_forward without the loss reduction. Its workgroup
// barriers make lavapipe run every workgroup of head_forward as coroutines, which cost ~0.4 ms
// per launch there even for one point; this entry point has none.
@compute @workgroup_size(256)
fn head_eval(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let p = (wid.y * nwg.x + wid.x) * WG + lid;
    if p < h.n_points {
        head_point(p);
    }
}

// Φ (mode 0) or Φ and ∇Φ (modes 1, 2) of point p into `values`; returns them.
fn head_point(p: u32) -> vec4<f32> {
    let bias = params[h.b_off];
    if h.mode == 0u {
        var s = 0.0;
        let row = p * h.width;
        for (var i = 0u; i < h.width; i++) {
            s = fma(params[h.w_off + i], act[row + i], s);
        }
        values[p] = s + bias;
        return vec4<f32>(s + bias, 0.0, 0.0, 0.0);
    }
    var y = vec4<f32>(0.0);
    let r0 = 4u * p * h.width;
    for (var i = 0u; i < h.width; i++) {
        let w = params[h.w_off + i];
        let a = vec4<f32>(act[r0 + i], act[r0 + h.width + i], act[r0 + 2u * h.width + i],
            act[r0 + 3u * h.width + i]);
        y = fma(vec4<f32>(w), a, y);
    }
    y.x += bias;
    values[4u * p] = y.x;
    values[4u * p + 1u] = y.y;
    values[4u * p + 2u] = y.z;
    values[4u * p + 3u] = y.w;
    return y;
}

@compute @workgroup_size(256)
fn head_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let group = wid.y * nwg.x + wid.x;
    let p = group * WG + lid;
    var terms = vec4<f32>(0.0);
    if p < h.n_points {
        let y = head_point(p);
        if h.mode != 0u {
            let phi = y.x;
            let gr = y.yzw;
            if h.mode == 2u {
                let on_surface = p < h.n_surface;
                // On the surface the normal, off it the known side in `.x`.
                let n = vec3<f32>(normals[3u * p], normals[3u * p + 1u], normals[3u * p + 2u]);
                let weights = vec4<f32>(h.w_surface, h.w_off_surface, h.w_normal, h.w_eikonal);
                let l = point_loss(phi, gr, on_surface, n, weights, h.alpha, h.w_sign);
                terms = l.terms;
                dout[4u * p] = l.dphi * h.inv_n;
                dout[4u * p + 1u] = l.dgrad.x * h.inv_n;
                dout[4u * p + 2u] = l.dgrad.y * h.inv_n;
                dout[4u * p + 3u] = l.dgrad.z * h.inv_n;
            }
        }
    }
    if h.mode == 2u {
        store_loss_sum(lid, terms * h.inv_n, group);
    }
}

@compute @workgroup_size(256)
fn head_backward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = (wid.y * nwg.x + wid.x) * WG + lid;
    if t >= h.n_points * h.width {
        return;
    }
    let p = t / h.width;
    let i = t % h.width;
    let w = params[h.w_off + i];
    let d = vec4<f32>(dout_in[4u * p], dout_in[4u * p + 1u], dout_in[4u * p + 2u], dout_in[4u * p + 3u]);
    let ab = w * d;
    let i0 = 4u * p * h.width + i;
    let i1 = i0 + h.width;
    let i2 = i1 + h.width;
    let i3 = i2 + h.width;
    let w0 = h.omega;
    let zv = z_last[i0];
    let s = sin(w0 * zv);
    let wc = w0 * cos(w0 * zv);
    let mix = ab.y * z_last[i1] + ab.z * z_last[i2] + ab.w * z_last[i3];
    zbar[i0] = wc * ab.x - w0 * w0 * s * mix;
    zbar[i1] = wc * ab.y;
    zbar[i2] = wc * ab.z;
    zbar[i3] = wc * ab.w;
}
