//! NGLOD (default preset) against SIREN's `small` preset on the Stanford bunny, each trained on
//! the GPU for the same wall-clock budget (after setup), scored on the sign of the distance (inside / outside)
//! at uniform box points and at near-surface points (σ = 0.01), as the design document scores.
//!
//! The mesh is `../shared/meshes/stanford-bunny.obj` relative to the repository root (2.4 MB, not
//! vendored); without it the test says so and passes. `HWSDF_BUNNY_SECONDS` overrides the
//! per-model budget (default 30 s).

use std::path::PathBuf;
use std::time::Instant;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance};
use sdf_nn::{
    GpuContext, Nglod, NglodConfig, NglodTrainConfig, NglodTrainer, Siren, SirenConfig,
    SirenTrainConfig, SirenTrainer,
};

fn bunny() -> Option<Mesh> {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/meshes/stanford-bunny.obj");
    if !path.exists() {
        eprintln!(
            "{} not found: skipping the bunny comparison",
            path.display()
        );
        return None;
    }
    Some(sdf_geom::load_mesh(&path).expect("the bunny loads").0)
}

/// Fraction of points where the predicted sign matches the exact one.
fn sign_accuracy(pred: &[f32], exact: &[f32]) -> f64 {
    let ok = pred
        .iter()
        .zip(exact)
        .filter(|&(&p, &e)| (p < 0.0) == (e < 0.0))
        .count();
    ok as f64 / exact.len() as f64
}

#[test]
fn nglod_is_at_least_as_good_as_siren_small_on_the_bunny() {
    let Some(mesh) = bunny() else { return };
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    let budget: f64 = std::env::var("HWSDF_BUNNY_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(30.0);
    let (unit, norm) = mesh.normalized();

    // Evaluation sets, labelled exactly.
    let sdf = SignedDistance::new(&unit).unwrap();
    let box_pts = sdf_geom::sample::uniform_box(20_000, 1001);
    let near_pts: Vec<Vec3> = sdf_geom::sample::near_surface(&unit, 20_000, 0.01, 1002);
    let box_exact = sdf.signed_distance_batch(&box_pts);
    let near_exact = sdf.signed_distance_batch(&near_pts);

    // One-off costs (building the distance BVH or the Poisson dataset, compiling pipelines) are
    // left out of both budgets; the time to sample NGLOD's first epoch is counted.

    // NGLOD: the design document's training, stopped at the budget.
    let t = Instant::now();
    let model = Nglod::new(NglodConfig::default_preset()).unwrap();
    let config = NglodTrainConfig {
        epochs: 1000,
        max_seconds: Some(budget),
        ..Default::default()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &unit, config).unwrap();
    let nglod_setup = t.elapsed().as_secs_f64();
    let report = trainer.train().unwrap();
    let nglod_secs = report.total_seconds;
    let g = trainer.gpu_model();
    let n_box = sign_accuracy(&g.eval(gpu, &box_pts, None).unwrap(), &box_exact);
    let n_near = sign_accuracy(&g.eval(gpu, &near_pts, None).unwrap(), &near_exact);
    eprintln!(
        "NGLOD default: setup {nglod_setup:.1} s, trained {nglod_secs:.1} s, {} epochs ({} steps), loss {:.2e}, GPU {:.1} s, \
         sampling {:.1} s (stall {:.1} s); sign accuracy box {n_box:.4}, near {n_near:.4}",
        report.epochs.len(),
        report.steps,
        report.final_loss,
        report.gpu_seconds,
        report.sampling_seconds,
        report.stall_seconds
    );

    // SIREN small: its own trainer and defaults, stepped until the same budget. The first step
    // (pipeline compilation) is setup.
    let t = Instant::now();
    let siren = Siren::new(SirenConfig::small(), 0).unwrap();
    let mut st = SirenTrainer::from_mesh(gpu, &siren, &mesh, SirenTrainConfig::default()).unwrap();
    st.step(gpu).unwrap();
    gpu.wait().unwrap();
    let siren_setup = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut steps = 1;
    while t.elapsed().as_secs_f64() < budget {
        st.step(gpu).unwrap();
        steps += 1;
    }
    let siren_secs = t.elapsed().as_secs_f64();
    let trained = st.siren(gpu).unwrap();
    assert_eq!(st.normalization(), norm);
    let s_box = sign_accuracy(&trained.eval_cpu(&box_pts), &box_exact);
    let s_near = sign_accuracy(&trained.eval_cpu(&near_pts), &near_exact);
    eprintln!(
        "SIREN small: setup {siren_setup:.1} s, trained {siren_secs:.1} s, {steps} steps; sign accuracy box {s_box:.4}, near {s_near:.4}"
    );

    assert!(
        n_box + n_near >= s_box + s_near,
        "NGLOD box {n_box:.4} near {n_near:.4} vs SIREN box {s_box:.4} near {s_near:.4}"
    );
}
