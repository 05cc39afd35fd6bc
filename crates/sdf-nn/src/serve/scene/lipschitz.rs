//! A Lipschitz estimate of a [`NeuralSdf`], measured once per model, so that sphere tracing
//! can step by a bound on a function that is only approximately a distance.
//!
//! ```
//! use sdf_nn::{NeuralSdf, Nglod, Normalization};
//! use sdf_nn::serve::scene::lipschitz::{SAFETY, estimate};
//!
//! let sphere = Nglod::from_sdf(16, |p| p.length() - 0.5).unwrap();
//! let file = sphere.to_model_file(Normalization::identity(), serde_json::Value::Null);
//! let model = NeuralSdf::from_model_file(file).unwrap();
//! // An exact distance has |∇Φ| = 1; outside the box the rule Φ(clamp x) + |x − clamp x|
//! // adds the tangential gradient on the box's faces.
//! let l = estimate(&model);
//! assert!(l >= SAFETY && l < 2.0 * SAFETY);
//! ```
//!
//! **How.** On a grid of [`GRID`]³ cells over the model's normalised box `[-1, 1]³` (its vertices
//! and its cell centres, `(GRID+1)³ + GRID³` points) the network's raw gradient `∇Φ` (SIREN's
//! forward-mode gradient, NGLOD's analytic one, before any normalisation) is evaluated on CPU
//! threads. `L_in` is the largest `|∇Φ|`. Outside the box a model is served as
//! `f(x) = Φ(c(x)) + |x − c(x)|` with `c` the clamp to the box; there `∇f` is the part of `∇Φ`
//! along the box's free axes at `c(x)` plus a unit vector orthogonal to it, so
//! `|∇f|² = |∇_tan Φ|² + 1`. `T` is the largest tangential `|∇_tan Φ|` over the samples on the
//! box's faces (the clamped axes' components zeroed). The estimate is
//! `SAFETY · max(L_in, √(1 + T²))`, in the model's mesh units per mesh unit (the same number as
//! in normalised units: the normalisation scales distances and coordinates alike), and never
//! below `SAFETY`.
//!
//! **What it guarantees.** It is a measurement, not a proof: if the true Lipschitz constant of
//! the served function is at most [`SAFETY`] times the sampled maximum (its gradient does not
//! peak more than 25% above every sample, which holds when the network has no feature much finer
//! than the sample spacing `1/GRID` of the half box), then `|f(x) − f(y)| ≤ L |x − y|`, and a
//! sphere tracer stepping by `(f − c)/L` never steps over a crossing of the level `c`. A model
//! whose features are finer than that can be given a known bound instead
//! ([`crate::serve::scene::Scene::set_model_lipschitz`]).

use glam::Vec3;
use rayon::prelude::*;

use crate::NeuralSdf;
use crate::serve::network::Network;

/// Cells per axis of the sample grid.
pub const GRID: usize = 32;

/// The factor the sampled maximum is multiplied by.
pub const SAFETY: f32 = 1.25;

/// The Lipschitz estimate of `model` (see the module docs): at least [`SAFETY`].
pub fn estimate(model: &NeuralSdf) -> f32 {
    let points = sample_points();
    let gradients: Vec<Vec3> = match model.network() {
        Network::Siren(s) => s.gradient_cpu(&points),
        Network::Nglod(m) => m
            .gradient_cpu(&points, model.lod())
            .expect("the level of detail was validated by NeuralSdf::set_lod"),
    };
    let (inside, tangential) = points
        .par_iter()
        .zip(&gradients)
        .map(|(p, g)| {
            // Axes on which the point sits on a face are the clamped ones outside it.
            let on_face = p.abs().cmpge(Vec3::ONE);
            let tangential = Vec3::select(on_face, Vec3::ZERO, *g);
            let t = if on_face.any() {
                tangential.length()
            } else {
                0.0
            };
            (g.length(), t)
        })
        .reduce(|| (0.0f32, 0.0f32), |a, b| (a.0.max(b.0), a.1.max(b.1)));
    let outside = (1.0 + tangential * tangential).sqrt();
    SAFETY * inside.max(outside).max(1.0)
}

/// A floor of `model`'s network value Φ over its normalised cube: the smallest value on the
/// estimate's grid less `lipschitz` times the farthest any point of the cube is from the grid
/// (half a cell's side, `1/GRID`: the grid holds the cells' vertices and centres). A bound
/// wherever `lipschitz` bounds Φ's slope, which is what the ray tracer assumes of it; scenes
/// take the tighter of it and the weights' interval bound to skip models far from a point.
pub fn value_floor(model: &NeuralSdf, lipschitz: f32) -> f32 {
    let values = model.eval_cpu_normalized(&sample_points());
    let min = values
        .par_iter()
        .copied()
        .reduce(|| f32::INFINITY, f32::min);
    min - lipschitz / GRID as f32
}

/// The grid's vertices and cell centres in `[-1, 1]³`.
fn sample_points() -> Vec<Vec3> {
    let vertex = |i: usize| i as f32 * (2.0 / GRID as f32) - 1.0;
    let centre = |i: usize| (i as f32 + 0.5) * (2.0 / GRID as f32) - 1.0;
    let s = GRID + 1;
    let mut points = Vec::with_capacity(s * s * s + GRID * GRID * GRID);
    for x in 0..s {
        for y in 0..s {
            for z in 0..s {
                points.push(Vec3::new(vertex(x), vertex(y), vertex(z)));
            }
        }
    }
    for x in 0..GRID {
        for y in 0..GRID {
            for z in 0..GRID {
                points.push(Vec3::new(centre(x), centre(y), centre(z)));
            }
        }
    }
    points
}
