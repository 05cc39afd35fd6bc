// The grid gradients' scatter of nglod_train.wgsl with native float atomics
// (SHADER_FLOAT32_ATOMIC): many rows touch the same grid vertex.
@group(0) @binding(5) var<storage, read_write> grads: array<atomic<f32>>;

fn grad_add(i: u32, x: f32) {
    atomicAdd(&grads[i], x);
}
