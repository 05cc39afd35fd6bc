//! A fit and its sign check, shared by the `siren_fit` example and the `siren_gpu` tests'
//! end-to-end runs (which include this file by path): train a SIREN on a mesh, then count the
//! uniform box points whose sign (Φ < 0 inside) disagrees with the mesh's exact sign, by their
//! true distance from the surface.

use std::time::Instant;

use sdf_nn::{GpuContext, Siren, SirenTrainConfig, SirenTrainer};

/// Trains `siren` on `mesh` with `train` (printing the loss every 100 steps under `name`),
/// writes the model file to `save` if given, and returns the fraction of 20 000 uniform box
/// points (drawn from `seed`) whose sign is right.
pub fn fit_and_check_signs(
    gpu: &GpuContext,
    name: &str,
    siren: &Siren,
    mesh: &sdf_geom::Mesh,
    train: &SirenTrainConfig,
    seed: u64,
    save: Option<&std::path::Path>,
) -> f64 {
    let t0 = Instant::now();
    let mut trainer = SirenTrainer::from_mesh(gpu, siren, mesh, train.clone()).unwrap();
    let t_setup = t0.elapsed();
    let summary = trainer
        .train(gpu, train.steps, |step, l| {
            if step % 100 == 0 {
                eprintln!("{name} step {step}: loss {:.3} {l:?}", l.total());
            }
        })
        .unwrap();
    let (normalized, _) = mesh.normalized();
    let truth = sdf_geom::SignedDistance::new(&normalized).unwrap();
    let pts = sdf_geom::sample::uniform_box(20_000, seed + 7);
    let vals = trainer.net().eval(gpu, &pts).unwrap();
    // Wrong signs by the true distance: near the surface (resolution) or far (spurious sheets).
    let truth_d = truth.signed_distance_batch(&pts);
    let mut wrong = [0usize; 6];
    for (&d, v) in truth_d.iter().zip(&vals) {
        if (*v < 0.0) != (d < 0.0) {
            let band = if d.abs() < 0.02 {
                0
            } else if d.abs() < 0.1 {
                1
            } else {
                2
            };
            wrong[band + if d < 0.0 { 3 } else { 0 }] += 1;
        }
    }
    eprintln!(
        "{name}: wrong signs outside / inside at |d| < 0.02, 0.02-0.1, > 0.1: {:?} / {:?}",
        &wrong[..3],
        &wrong[3..]
    );
    let acc = 1.0 - wrong.iter().sum::<usize>() as f64 / pts.len() as f64;
    if let Some(path) = save {
        // For `eval`'s F1 on the fit.
        trainer.model_file(gpu).unwrap().save(path).unwrap();
    }
    eprintln!(
        "{name}: {} steps in {:.1?} (setup {t_setup:.1?}), final loss {:?}, lr {:e}, sign accuracy {:.4}",
        summary.steps, summary.elapsed, summary.final_loss, summary.final_lr, acc
    );
    acc
}
