//! SIREN kernels against the f64 CPU reference, and end-to-end training, on whatever adapter
//! the environment selects (lavapipe in CI). One test binary, so every pipeline is compiled
//! once.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::siren::{LossWeights, cpu};
use sdf_nn::{GpuContext, Siren, SirenConfig, SirenGpu};

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

fn random_points(rng: &mut Pcg64, n: usize) -> Vec<Vec3> {
    (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect()
}

fn to64(v: Vec3) -> [f64; 3] {
    [v.x.into(), v.y.into(), v.z.into()]
}

fn forward_matches(cfg: SirenConfig, n: usize, seed: u64) {
    let gpu = gpu();
    let net = Siren::new(cfg, seed).unwrap();
    let p64: Vec<f64> = net.params().iter().map(|&p| f64::from(p)).collect();
    let mut g = SirenGpu::new(gpu, &net).unwrap();
    let mut rng = Pcg64::seed_from_u64(seed);
    let pts = random_points(&mut rng, n);
    let vals = g.eval(gpu, &pts).unwrap();
    let with_grad = g.eval_with_gradient(gpu, &pts).unwrap();
    assert_eq!(vals.len(), n);
    assert_eq!(with_grad.len(), n);
    let (mut worst_v, mut worst_g) = (0.0f64, 0.0f64);
    for i in 0..n {
        let (rv, rg) = cpu::forward_with_gradient(&cfg, &p64, to64(pts[i]));
        // Φ is O(1); ∇Φ is O(ω0) before training.
        let gs = rg.iter().fold(1.0f64, |m, x| m.max(x.abs()));
        worst_v = worst_v.max((f64::from(vals[i]) - rv).abs());
        worst_v = worst_v.max((f64::from(with_grad[i].0) - rv).abs());
        for j in 0..3 {
            worst_g = worst_g.max((f64::from(with_grad[i].1[j]) - rg[j]).abs() / gs);
        }
    }
    eprintln!("{cfg:?} n={n}: |ΔΦ| ≤ {worst_v:e}, |Δ∇Φ|/scale ≤ {worst_g:e}");
    assert!(worst_v < 1e-6, "forward error {worst_v:e}");
    assert!(worst_g < 1e-5, "input-gradient error {worst_g:e}");
}

#[test]
fn forward_and_input_gradient_match_cpu_reference() {
    forward_matches(
        SirenConfig {
            width: 16,
            hidden_layers: 2,
            omega0: 30.0,
        },
        37,
        1,
    );
    forward_matches(
        SirenConfig {
            width: 32,
            hidden_layers: 3,
            omega0: 30.0,
        },
        300,
        2,
    );
}

fn gradients_match(cfg: SirenConfig, n: usize, n_surface: usize, seed: u64) {
    let gpu = gpu();
    let net = Siren::new(cfg, seed).unwrap();
    let p64: Vec<f64> = net.params().iter().map(|&p| f64::from(p)).collect();
    let mut g = SirenGpu::new(gpu, &net).unwrap();
    let mut rng = Pcg64::seed_from_u64(seed + 100);
    let pts = random_points(&mut rng, n);
    let normals: Vec<Vec3> = random_points(&mut rng, n_surface)
        .into_iter()
        .map(|v| v.normalize())
        .collect();
    let weights = LossWeights::default();
    let (terms, grads) = g.loss_and_gradient(gpu, &pts, &normals, &weights).unwrap();
    let p_64: Vec<[f64; 3]> = pts.iter().map(|&p| to64(p)).collect();
    let n_64: Vec<[f64; 3]> = normals.iter().map(|&p| to64(p)).collect();
    let (rterms, rgrad) = cpu::loss_and_gradient(&cfg, &p64, &p_64, &n_64, &weights);
    let got = [terms.surface, terms.off_surface, terms.normal, terms.eikonal];
    for t in 0..4 {
        let err = (f64::from(got[t]) - rterms[t]).abs() / rterms[t].abs().max(1e-3);
        assert!(err < 1e-4, "loss term {t}: {} vs {}", got[t], rterms[t]);
    }
    // Per-tensor scale: the largest reference gradient of the layer's W or b.
    let mut worst = 0.0f64;
    for lay in cfg.layers() {
        for range in [lay.weight..lay.bias, lay.bias..lay.bias + lay.fan_out] {
            let scale = rgrad[range.clone()].iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for i in range {
                let err = (f64::from(grads[i]) - rgrad[i]).abs() / scale.max(1e-12);
                worst = worst.max(err);
                assert!(err < 2e-4, "param {i}: gpu {} vs cpu {} (scale {scale:e})", grads[i], rgrad[i]);
            }
        }
    }
    eprintln!("{cfg:?} n={n}: loss {rterms:?}, worst gradient error {worst:e} (relative to tensor max)");
}

#[test]
fn loss_and_every_parameter_gradient_match_cpu_reference() {
    gradients_match(
        SirenConfig {
            width: 16,
            hidden_layers: 2,
            omega0: 30.0,
        },
        37,
        20,
        3,
    );
    gradients_match(
        SirenConfig {
            width: 32,
            hidden_layers: 3,
            omega0: 30.0,
        },
        300,
        150,
        4,
    );
}
