//! The Adam kernel against its f64 CPU reference, on whatever adapter the environment selects
//! (lavapipe in CI).

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::{Adam, AdamConfig, AdamCpu, GpuContext, GpuError, GpuOptions};

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

/// Largest relative error `|gpu - cpu| / max(|cpu|, scale)`. `scale` is the magnitude of the
/// terms that make up a value: where they cancel, f32 keeps an absolute error at their ulp, so
/// relative error is measured against them rather than against the small remainder.
fn max_rel_err(gpu: &[f32], cpu: &[f64], scale: f64) -> f64 {
    assert_eq!(gpu.len(), cpu.len());
    gpu.iter()
        .zip(cpu)
        .map(|(&g, &c)| (f64::from(g) - c).abs() / c.abs().max(scale))
        .fold(0.0, f64::max)
}

/// Runs `steps` Adam steps on GPU and CPU with the same random gradients and compares
/// parameters and both moments.
fn compare(len: usize, steps: usize, config: AdamConfig, grad_scale: f32, seed: u64) {
    compare_lazy(len, 0, steps, config, grad_scale, seed);
}

/// [`compare`] with the first `lazy` parameters lazy, and then a third of the gradients zero
/// (a grid's untouched entries), so that both kinds of parameter meet zero gradients.
fn compare_lazy(
    len: usize,
    lazy: usize,
    steps: usize,
    config: AdamConfig,
    grad_scale: f32,
    seed: u64,
) {
    let gpu = gpu();
    let mut rng = Pcg64::seed_from_u64(seed);
    let init: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
    let params = gpu.storage_from_slice("params", &init).unwrap();
    let grads = gpu.storage_zeroed("grads", len as u64 * 4).unwrap();
    let mut adam = Adam::new(gpu, &params, &grads, len as u32, config).unwrap();
    adam.set_lazy_prefix(lazy as u32);

    let mut cpu_params: Vec<f64> = init.iter().map(|&p| f64::from(p)).collect();
    let mut cpu = AdamCpu::new(len, config);
    cpu.lazy_len = lazy;
    for _ in 0..steps {
        let g: Vec<f32> = (0..len)
            .map(|_| {
                if lazy > 0 && rng.random_range(0..3) == 0 {
                    0.0
                } else {
                    rng.random_range(-2.0..2.0)
                }
            })
            .collect();
        gpu.write(&grads, &g).unwrap();
        adam.step(gpu, grad_scale);
        let g64: Vec<f64> = g.iter().map(|&x| f64::from(x)).collect();
        cpu.step(&mut cpu_params, &g64, f64::from(grad_scale));
    }
    assert_eq!(adam.step_count() as usize, steps);

    let p: Vec<f32> = gpu.read_back(&params).unwrap();
    let (m_buf, v_buf) = adam.moments();
    let m: Vec<f32> = gpu.read_back(m_buf).unwrap();
    let v: Vec<f32> = gpu.read_back(v_buf).unwrap();
    let g_left: Vec<f32> = gpu.read_back(&grads).unwrap();
    for (name, err) in [
        // Parameters are O(1): scale 1e-3 is a plain relative check on all but the rare
        // near-zero ones, which reach zero in steps of about lr from O(1) values whose f32
        // rounding they keep (hence at least lr). Moments are running sums of gradients of
        // either sign (|g| < 2).
        (
            "params",
            max_rel_err(&p, &cpu_params, f64::from(config.lr).max(1e-3)),
        ),
        ("m", max_rel_err(&m, &cpu.m, 0.1)),
        ("v", max_rel_err(&v, &cpu.v, 1e-3)),
    ] {
        assert!(
            err < 1e-6,
            "{name}: max relative error {err:e} over {len} elements"
        );
    }
    assert!(
        g_left.iter().all(|&g| g == 0.0),
        "the kernel zeroes consumed gradients"
    );
}

#[test]
fn adam_matches_cpu_reference_on_odd_length() {
    // 1037 is not a multiple of the 256-wide workgroup.
    compare(1037, 6, AdamConfig::default(), 1.0, 1);
}

#[test]
fn adam_matches_cpu_reference_with_other_hyperparameters() {
    let config = AdamConfig {
        lr: 1e-4,
        beta1: 0.8,
        beta2: 0.99,
        eps: 1e-6,
    };
    compare(1, 3, config, 0.25, 2);
    compare(255, 5, config, 0.25, 3);
    compare(257, 5, config, 0.25, 4);
    // The hash grid's: instant-ngp's β2 and ε, a large rate.
    compare(
        1037,
        6,
        sdf_nn::NglodTrainConfig::hashgrid().adam,
        1.0 / 4096.0,
        6,
    );
}

/// Lazy parameters skip zero gradients on the GPU as in the reference, and only they do: a
/// lazy entry never touched keeps its value and zero moments, an eager one moves.
#[test]
fn lazy_parameters_skip_zero_gradients_like_the_reference() {
    compare_lazy(
        1037,
        700,
        6,
        sdf_nn::NglodTrainConfig::hashgrid().adam,
        0.5,
        7,
    );
    let gpu = gpu();
    let init = [0.5f32; 4];
    let params = gpu.storage_from_slice("params", &init).unwrap();
    let grads = gpu.storage_zeroed("grads", 16).unwrap();
    let mut adam = Adam::new(gpu, &params, &grads, 4, AdamConfig::default()).unwrap();
    adam.set_lazy_prefix(2);
    for _ in 0..3 {
        // Entry 0 (lazy) and 2 (eager) get gradient on the first step only.
        gpu.write(&grads, &[1.0f32, 0.0, 1.0, 0.0]).unwrap();
        adam.step(gpu, 1.0);
        gpu.write(&grads, &[0.0f32; 4]).unwrap();
        adam.step(gpu, 1.0);
    }
    let p: Vec<f32> = gpu.read_back(&params).unwrap();
    let (m, _) = adam.moments();
    let m: Vec<f32> = gpu.read_back(m).unwrap();
    assert_eq!(
        (p[1], m[1]),
        (0.5, 0.0),
        "an untouched lazy entry stays as it was"
    );
    assert_eq!(
        p[3], 0.5,
        "an eager entry with no gradient ever does not move either"
    );
    // Lazy entry 0 moved on its three steps with gradient only; eager entry 2 on all six.
    assert!(p[0] < 0.5 && p[2] < p[0], "{p:?}");
}

#[test]
fn adam_covers_buffers_beyond_one_dispatch_dimension() {
    let gpu = gpu();
    // One element past what a single dispatch dimension of 256-wide workgroups can address.
    let max_groups = u64::from(gpu.limits().max_compute_workgroups_per_dimension);
    let len = max_groups * 256 + 1;
    if gpu.check_storage_size("adam large", len * 4).is_err() {
        panic!("adapter cannot bind {len} floats; the fold is covered by gpu::tests only");
    }
    compare(len as usize, 2, AdamConfig::default(), 1.0, 5);
}

#[test]
fn adam_state_round_trips_through_export_and_import() {
    let gpu = gpu();
    let len = 300;
    let g: Vec<f32> = (0..len).map(|i| (i as f32 * 0.37).sin()).collect();
    let run = |steps_before: usize, restore: Option<&sdf_nn::AdamState>| {
        let params = gpu.storage_from_slice("p", &vec![0.5f32; len]).unwrap();
        let grads = gpu.storage_zeroed("g", len as u64 * 4).unwrap();
        let mut adam = Adam::new(gpu, &params, &grads, len as u32, AdamConfig::default()).unwrap();
        if let Some(state) = restore {
            adam.import_state(gpu, state).unwrap();
        }
        for _ in 0..steps_before {
            gpu.write(&grads, &g).unwrap();
            adam.step(gpu, 1.0);
        }
        (adam.export_state(gpu).unwrap(), params)
    };
    // Two steps, export, import into a fresh optimiser, one more step: same as three steps
    // (parameters restored separately, as checkpoints do).
    let (three, _) = run(3, None);
    let (two, _) = run(2, None);
    assert_eq!(two.step, 2);
    let (resumed, _) = run(1, Some(&two));
    assert_eq!(resumed.step, 3);
    assert_eq!(resumed.m, three.m);
    assert_eq!(resumed.v, three.v);
    let mut bad = two.clone();
    bad.m.pop();
    let params = gpu.storage_zeroed("p", len as u64 * 4).unwrap();
    let grads = gpu.storage_zeroed("g", len as u64 * 4).unwrap();
    let mut adam = Adam::new(gpu, &params, &grads, len as u32, AdamConfig::default()).unwrap();
    assert!(adam.import_state(gpu, &bad).is_err());
}

#[test]
fn adam_rejects_short_buffers() {
    let gpu = gpu();
    let params = gpu.storage_zeroed("p", 16).unwrap();
    let grads = gpu.storage_zeroed("g", 16).unwrap();
    let err = Adam::new(gpu, &params, &grads, 5, AdamConfig::default()).unwrap_err();
    assert!(matches!(err, GpuError::BufferTooLarge { .. }), "{err}");
}

#[test]
fn buffers_round_trip_and_zero() {
    let gpu = gpu();
    let data: Vec<u32> = (0..1001).collect();
    let b = gpu.storage_from_slice("roundtrip", &data).unwrap();
    assert_eq!(gpu.read_back::<u32>(&b).unwrap(), data);
    assert_eq!(
        gpu.read_back_range::<u32>(&b, 10, 3).unwrap(),
        vec![10, 11, 12]
    );
    gpu.zero(&b);
    assert!(gpu.read_back::<u32>(&b).unwrap().iter().all(|&x| x == 0));
    assert!(gpu.read_back_range::<u32>(&b, 1000, 2).is_err());
    // Ranges whose byte offsets overflow u64 are typed errors, not overflow panics.
    assert!(gpu.read_back_range::<u32>(&b, u64::MAX / 2, 1).is_err());
    assert!(gpu.read_back_range::<u32>(&b, 0, u64::MAX / 2).is_err());
    assert!(
        gpu.read_back_range::<u32>(&b, u64::MAX / 8, u64::MAX / 8)
            .is_err()
    );
}

#[test]
fn oversized_buffer_is_a_typed_error() {
    let gpu = gpu();
    let too_big = gpu.limits().max_buffer_size + 4;
    let err = gpu.storage_zeroed("huge", too_big).unwrap_err();
    assert!(matches!(err, GpuError::BufferTooLarge { .. }), "{err}");
    assert!(err.to_string().contains("huge"));
}

#[test]
fn unknown_adapter_name_is_a_clear_error() {
    let options = GpuOptions {
        adapter: Some("no-such-adapter-hwsdf".into()),
        adapter_from: "WGPU_ADAPTER_NAME".into(),
        ..GpuOptions::default()
    };
    let err = GpuContext::with_options(&options).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, GpuError::AdapterNotFound { .. }), "{msg}");
    assert!(
        msg.contains("no-such-adapter-hwsdf") && msg.contains("WGPU_ADAPTER_NAME"),
        "{msg}"
    );
    // The message lists what does exist, so the user can correct the name.
    assert!(msg.contains(&gpu().adapter_info().name), "{msg}");
}

#[test]
fn no_adapter_error_says_how_to_fix_it() {
    let msg = GpuError::NoAdapter {
        backends: "VULKAN".into(),
    }
    .to_string();
    assert!(msg.contains("apt-get install mesa-vulkan-drivers"), "{msg}");
}
