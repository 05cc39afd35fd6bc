// SIREN training helpers: batch sampling on the GPU, the split-K weight-gradient reduction, and
// the final loss reduction into a history the host reads only every few steps.

struct Sample {
    n_points: u32,
    n_surface: u32,
    n_data: u32,
    seed: u32,
    // Box points with their known side, drawn from instead of the uniform box when not 0.
    n_pool: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Reduce {
    m: u32,
    n: u32,
    splits: u32,
    w_off: u32,
    b_off: u32,
    pbias_off: u32,
    _pad0: u32,
    _pad1: u32,
}

struct LossReduce {
    n_partials: u32,
    slot: u32,
    _pad0: u32,
    _pad1: u32,
}

const WG: u32 = 256u;

@group(0) @binding(0) var<uniform> smp: Sample;
@group(0) @binding(1) var<storage, read> data_points: array<f32>;
@group(0) @binding(2) var<storage, read> data_normals: array<f32>;
// Four rows of three per point: the point, then the unit tangents e_x, e_y, e_z.
@group(0) @binding(3) var<storage, read_write> x_streams: array<f32>;
// On the surface the normal; off it (the known side, 0, 0).
@group(0) @binding(4) var<storage, read_write> batch_normals: array<f32>;
// (x, y, z, side): +1 outside, −1 inside, 0 unknown.
@group(0) @binding(11) var<storage, read> box_pool: array<vec4<f32>>;

@group(0) @binding(5) var<uniform> red: Reduce;
@group(0) @binding(6) var<storage, read> partial: array<f32>;
@group(0) @binding(7) var<storage, read_write> grads: array<f32>;

@group(0) @binding(8) var<uniform> lr: LossReduce;
@group(0) @binding(9) var<storage, read> loss_partial: array<f32>;
@group(0) @binding(10) var<storage, read_write> history: array<f32>;

fn pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

fn unit(h: u32) -> f32 {
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

@compute @workgroup_size(256)
fn sample(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let p = (wid.y * nwg.x + wid.x) * WG + lid;
    if p >= smp.n_points {
        return;
    }
    let h0 = pcg(pcg(p) ^ smp.seed);
    var x: vec3<f32>;
    if p < smp.n_surface {
        // Uniform choice among the dataset's points (modulo bias is < n_data / 2^32).
        let i = h0 % smp.n_data;
        x = vec3<f32>(data_points[3u * i], data_points[3u * i + 1u], data_points[3u * i + 2u]);
        batch_normals[3u * p] = data_normals[3u * i];
        batch_normals[3u * p + 1u] = data_normals[3u * i + 1u];
        batch_normals[3u * p + 2u] = data_normals[3u * i + 2u];
    } else if smp.n_pool > 0u {
        let b = box_pool[h0 % smp.n_pool];
        x = b.xyz;
        batch_normals[3u * p] = b.w;
        batch_normals[3u * p + 1u] = 0.0;
        batch_normals[3u * p + 2u] = 0.0;
    } else {
        let h1 = pcg(h0);
        let h2 = pcg(h1);
        x = vec3<f32>(unit(h0), unit(h1), unit(h2)) * 2.0 - 1.0;
        batch_normals[3u * p] = 0.0;
        batch_normals[3u * p + 1u] = 0.0;
        batch_normals[3u * p + 2u] = 0.0;
    }
    let o = 12u * p;
    x_streams[o] = x.x;
    x_streams[o + 1u] = x.y;
    x_streams[o + 2u] = x.z;
    for (var j = 0u; j < 9u; j++) {
        x_streams[o + 3u + j] = select(0.0, 1.0, j % 4u == 0u);
    }
}

@compute @workgroup_size(256)
fn reduce_wgrad(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = (wid.y * nwg.x + wid.x) * WG + lid;
    let mn = red.m * red.n;
    if t < mn {
        var s = 0.0;
        for (var k = 0u; k < red.splits; k++) {
            s += partial[k * mn + t];
        }
        grads[red.w_off + t] += s;
    } else if t < mn + red.m {
        let m = t - mn;
        var s = 0.0;
        for (var k = 0u; k < red.splits; k++) {
            s += partial[red.pbias_off + k * red.m + m];
        }
        grads[red.b_off + m] += s;
    }
}

// reduce_wgrad's work for layers with few outputs and many splits (the reverse-over-reverse
// step's output and first layers: 257 and 1024 outputs of 1024 and 625 splits for the `default`
// preset's 10⁴ points): one workgroup per output, its invocations striding over the splits,
// summed in a tree. With one invocation per output summing every split in turn they took 19.7
// and 15.5 µs on an H100 at 256 and 157 splits (a hidden layer's 65 792 outputs: 9.4). The step's GPU layout only: lavapipe measured it
// slower (`SirenGpu::set_gpu_step_layout`).
@compute @workgroup_size(256)
fn reduce_wgrad_by_output(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let t = wid.y * nwg.x + wid.x;
    let mn = red.m * red.n;
    // Workgroup-uniform: the groups a folded 2D dispatch adds past the end do nothing.
    if t >= mn + red.m {
        return;
    }
    var s = 0.0;
    for (var k = lid; k < red.splits; k += WG) {
        if t < mn {
            s += partial[k * mn + t];
        } else {
            s += partial[red.pbias_off + k * red.m + (t - mn)];
        }
    }
    let sum = workgroup_sum(lid, vec4<f32>(s, 0.0, 0.0, 0.0)).x;
    if lid == 0u {
        if t < mn {
            grads[red.w_off + t] += sum;
        } else {
            grads[red.b_off + t - mn] += sum;
        }
    }
}

var<workgroup> acc: array<vec4<f32>, 256>;

// The tree sum of `v` over the workgroup's WG invocations (every one must call it, in uniform
// control flow); invocation 0 gets the sum.
fn workgroup_sum(lid: u32, v: vec4<f32>) -> vec4<f32> {
    acc[lid] = v;
    workgroupBarrier();
    for (var stride = WG / 2u; stride > 0u; stride /= 2u) {
        if lid < stride {
            acc[lid] += acc[lid + stride];
        }
        workgroupBarrier();
    }
    return acc[lid];
}

@compute @workgroup_size(256)
fn reduce_loss(@builtin(local_invocation_index) lid: u32) {
    var s = vec4<f32>(0.0);
    for (var i = lid; i < lr.n_partials; i += WG) {
        s += vec4<f32>(loss_partial[4u * i], loss_partial[4u * i + 1u], loss_partial[4u * i + 2u],
            loss_partial[4u * i + 3u]);
    }
    let r = workgroup_sum(lid, s);
    if lid == 0u {
        history[4u * lr.slot] = r.x;
        history[4u * lr.slot + 1u] = r.y;
        history[4u * lr.slot + 2u] = r.z;
        history[4u * lr.slot + 3u] = r.w;
    }
}
