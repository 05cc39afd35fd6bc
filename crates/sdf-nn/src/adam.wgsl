// Adam update (Kingma & Ba), in PyTorch's formulation, fused with zeroing the gradient so the
// next step's backward kernels can accumulate into it without a separate clear pass.
//
//   m = b1 m + (1 - b1) g
//   v = b2 v + (1 - b2) g^2
//   p = p - step_size * m / (sqrt(v) * inv_sqrt_bc2 + eps)
//
// step_size = lr / (1 - b1^t) and inv_sqrt_bc2 = 1 / sqrt(1 - b2^t) are computed on the host in
// f64 from the step counter t, so the kernel needs no pow.
//
// The first `lazy_len` parameters (a model's grid or hash-table entries) are lazy: one whose
// gradient is exactly zero (no point of the batch touched it) is left alone, moments included,
// as instant-ngp's optimiser leaves its hash tables; a step then reads one word for each of
// them instead of reading four and writing four.

struct AdamUniforms {
    step_size: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    inv_sqrt_bc2: f32,
    // Scale applied to the incoming gradient (e.g. 1/batch when kernels accumulate sums).
    grad_scale: f32,
    len: u32,
    lazy_len: u32,
}

const WG: u32 = 256u;

@group(0) @binding(0) var<uniform> u: AdamUniforms;
@group(0) @binding(1) var<storage, read_write> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> grads: array<f32>;
@group(0) @binding(3) var<storage, read_write> m: array<f32>;
@group(0) @binding(4) var<storage, read_write> v: array<f32>;

@compute @workgroup_size(WG)
fn adam_step(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    // Large buffers are dispatched as a 2D grid of workgroups; flatten it back.
    let i = (wid.y * nwg.x + wid.x) * WG + lid;
    if i >= u.len {
        return;
    }
    let raw = grads[i];
    if i < u.lazy_len && raw == 0.0 {
        return;
    }
    let g = raw * u.grad_scale;
    grads[i] = 0.0;
    let mi = u.beta1 * m[i] + (1.0 - u.beta1) * g;
    let vi = u.beta2 * v[i] + (1.0 - u.beta2) * g * g;
    m[i] = mi;
    v[i] = vi;
    params[i] = params[i] - u.step_size * mi / (sqrt(vi) * u.inv_sqrt_bc2 + u.eps);
}
