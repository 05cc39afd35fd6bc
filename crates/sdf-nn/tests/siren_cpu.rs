//! The SIREN's f64 CPU reference against finite differences, the f32 CPU evaluation against
//! the reference, initialisation, and model-file round trips. No GPU needed.

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::siren::{LossWeights, cpu};
use sdf_nn::{ModelFile, Normalization, Siren, SirenConfig};

fn tiny() -> SirenConfig {
    SirenConfig {
        width: 7,
        hidden_layers: 2,
        omega0: 30.0,
    }
}

fn random_batch(rng: &mut Pcg64, n: usize, n_surface: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let points: Vec<[f64; 3]> = (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
        .collect();
    let normals = (0..n_surface)
        .map(|_| {
            let v: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            [v[0] / l, v[1] / l, v[2] / l]
        })
        .collect();
    (points, normals)
}

fn params64(s: &Siren) -> Vec<f64> {
    s.params().iter().map(|&p| f64::from(p)).collect()
}

#[test]
fn input_gradient_matches_finite_differences() {
    let cfg = tiny();
    let net = Siren::new(cfg, 3).unwrap();
    let p64 = params64(&net);
    let mut rng = Pcg64::seed_from_u64(1);
    let h = 1e-6;
    for _ in 0..20 {
        let x: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        let (_, g) = cpu::forward_with_gradient(&cfg, &p64, x);
        for j in 0..3 {
            let mut xp = x;
            let mut xm = x;
            xp[j] += h;
            xm[j] -= h;
            let fd = (cpu::forward_with_gradient(&cfg, &p64, xp).0
                - cpu::forward_with_gradient(&cfg, &p64, xm).0)
                / (2.0 * h);
            assert!(
                (fd - g[j]).abs() <= 1e-6 * g[j].abs().max(1.0),
                "∂Φ/∂x{j}: analytic {} vs fd {fd}",
                g[j]
            );
        }
    }
}

#[test]
fn every_parameter_gradient_of_the_loss_matches_finite_differences() {
    let cfg = tiny();
    let net = Siren::new(cfg, 5).unwrap();
    let mut p64 = params64(&net);
    let mut rng = Pcg64::seed_from_u64(2);
    let (points, normals) = random_batch(&mut rng, 12, 6);
    // Mid-sized weights so every term contributes comparably to the check.
    let weights = LossWeights {
        surface: 3.0,
        off_surface: 2.0,
        normal: 1.5,
        eikonal: 0.7,
        alpha: 4.0,
        sign: 2.5,
    };
    // Off-surface sides: three on the wrong side of the initial Φ, two on the right one, one
    // unknown, so the sign term is active and also off.
    let sides: Vec<f64> = points[normals.len()..]
        .iter()
        .zip([-1.0, -1.0, 1.0, 0.0, -1.0, 1.0])
        .map(|(&x, flip)| flip * cpu::forward_with_gradient(&cfg, &p64, x).0.signum())
        .collect();
    let (terms, grad) = cpu::loss_and_gradient(&cfg, &p64, &points, &normals, &sides, &weights);
    let terms2 = cpu::loss(&cfg, &p64, &points, &normals, &sides, &weights);
    for t in 0..4 {
        assert!(terms[t] > 0.0, "term {t} is active");
        assert!((terms[t] - terms2[t]).abs() < 1e-12);
    }
    let unsigned = LossWeights {
        sign: 0.0,
        ..weights
    };
    let without = cpu::loss(&cfg, &p64, &points, &normals, &sides, &unsigned);
    assert!(terms[1] > without[1] + 1e-3, "the sign term is active");
    let total = |p: &[f64]| {
        cpu::loss(&cfg, p, &points, &normals, &sides, &weights)
            .iter()
            .sum::<f64>()
    };
    let scale = grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in 0..p64.len() {
        let orig = p64[i];
        p64[i] = orig + h;
        let lp = total(&p64);
        p64[i] = orig - h;
        let lm = total(&p64);
        p64[i] = orig;
        let fd = (lp - lm) / (2.0 * h);
        let err = (fd - grad[i]).abs() / scale;
        worst = worst.max(err);
        assert!(
            err < 1e-5,
            "param {i}: analytic {} vs fd {fd} (scale {scale})",
            grad[i]
        );
    }
    eprintln!("{} parameters, worst relative error {worst:e}", p64.len());
}

#[test]
fn f32_cpu_evaluation_matches_the_reference() {
    let cfg = SirenConfig {
        width: 32,
        hidden_layers: 3,
        omega0: 30.0,
    };
    let net = Siren::new(cfg, 9).unwrap();
    let p64 = params64(&net);
    let mut rng = Pcg64::seed_from_u64(3);
    let pts: Vec<glam::Vec3> = (0..50)
        .map(|_| {
            glam::Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect();
    let vals = net.eval_cpu(&pts);
    let grads = net.gradient_cpu(&pts);
    for ((p, v), g) in pts.iter().zip(&vals).zip(&grads) {
        let (rv, rg) = cpu::forward_with_gradient(&cfg, &p64, [p.x.into(), p.y.into(), p.z.into()]);
        assert!((f64::from(*v) - rv).abs() < 1e-4, "{v} vs {rv}");
        let gs = rg.iter().fold(1.0f64, |m, x| m.max(x.abs()));
        for j in 0..3 {
            assert!((f64::from(g[j]) - rg[j]).abs() < 1e-4 * gs, "{g} vs {rg:?}");
        }
    }
}

#[test]
fn initialisation_follows_the_design_document() {
    let cfg = SirenConfig::default();
    assert_eq!(
        cfg.param_count(),
        3 * 256 + 256 + 3 * (256 * 256 + 256) + 256 + 1
    );
    let a = Siren::new(cfg, 7).unwrap();
    assert_eq!(a, Siren::new(cfg, 7).unwrap(), "seeded and deterministic");
    assert_ne!(a, Siren::new(cfg, 8).unwrap());
    let layers = cfg.layers();
    let first = &a.params()[layers[0].weight..layers[0].bias];
    assert!(first.iter().all(|w| w.abs() <= 1.0 / 3.0));
    assert!(first.iter().any(|w| w.abs() > 0.3), "spans U(-1/3, 1/3)");
    let bound = (6.0f32 / 256.0).sqrt() / 30.0;
    for lay in &layers[1..] {
        let w = &a.params()[lay.weight..lay.bias];
        assert!(w.iter().all(|w| w.abs() <= bound));
        assert!(w.iter().any(|w| w.abs() > 0.9 * bound));
    }
    // The output bias starts "outside" everywhere (see OUTPUT_BIAS_INIT).
    assert_eq!(*a.params().last().unwrap(), sdf_nn::siren::OUTPUT_BIAS_INIT);
    let hidden_bias = &a.params()[layers[1].bias..layers[1].bias + 256];
    assert!(hidden_bias.iter().all(|b| b.abs() <= 1.0 / 16.0));
    assert!(Siren::new(SirenConfig { width: 0, ..cfg }, 0).is_err());
    for omega0 in [f32::NAN, 0.0, -30.0, 1e30, f32::INFINITY] {
        assert!(
            Siren::new(SirenConfig { omega0, ..cfg }, 0).is_err(),
            "{omega0}"
        );
    }
    assert!(Siren::new(SirenConfig { omega0: 1e4, ..cfg }, 0).is_ok());
}

#[test]
fn model_file_round_trips_bit_for_bit() {
    let net = Siren::new(SirenConfig::small(), 11).unwrap();
    let norm = Normalization {
        center: glam::Vec3::new(0.5, -1.0, 2.0).as_dvec3(),
        scale: 0.25,
    };
    let file = net.to_model_file(norm, serde_json::json!({"steps": 3}));
    let names: Vec<&str> = file.tensors.iter().map(|t| t.name.as_str()).collect();
    for want in ["net.0.weight", "net.0.bias", "net.3.weight", "net.3.bias"] {
        assert!(names.contains(&want), "{want} in {names:?}");
    }
    let w0 = file
        .tensors
        .iter()
        .find(|t| t.name == "net.0.weight")
        .unwrap();
    assert_eq!(w0.shape, vec![64, 3], "PyTorch nn.Linear layout [out, in]");
    let dir = std::env::temp_dir().join(format!("hwsdf-siren-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("model.safetensors");
    file.save(&path).unwrap();
    let loaded = ModelFile::load(&path).unwrap();
    let back = Siren::from_model_file(&loaded).unwrap();
    assert_eq!(back.config(), net.config());
    let bits = |s: &Siren| s.params().iter().map(|p| p.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back), bits(&net));
    assert_eq!(loaded.metadata.normalization, norm);
    assert_eq!(loaded.metadata.architecture, "siren");

    // A file whose config disagrees with its tensors is refused with a clear error.
    let mut bad = loaded.clone();
    bad.metadata.config = serde_json::json!({"width": 32, "hidden_layers": 3, "omega0": 30.0});
    let err = Siren::from_model_file(&bad).unwrap_err().to_string();
    assert!(err.contains("net.0.weight"), "{err}");
    let mut bad = loaded;
    bad.metadata.architecture = "nglod".into();
    assert!(Siren::from_model_file(&bad).is_err());
    std::fs::remove_dir_all(&dir).ok();
}
