//! f64 reference of the NGLOD forward pass, the MSE loss and its gradient with respect to every
//! parameter (grid features and MLP), for the level-of-detail prefixes of an [`Objective`].
//!
//! Straightforward loops, no shortcuts: the GPU kernels and the f32 CPU paths are tested
//! against this, and this is tested against finite differences.

use glam::Vec3;

use super::{Nglod, NglodError, Objective, cell};

/// Per-point trace of one forward pass, kept for the backward pass.
struct Trace {
    /// (param index of a corner's first feature, where its level's features start in the MLP's
    /// input, trilinear weight) for every level and corner.
    corners: Vec<(usize, usize, f64)>,
    z: Vec<f64>,
    h: Vec<f64>,
    out: f64,
}

/// How far `p` lies outside `[-1, 1]³` (0 inside): what serving adds to the network's value
/// at the clamped point, computed as the training kernels do (in f32).
fn box_gap(p: Vec3) -> f32 {
    p.distance(p.clamp(Vec3::NEG_ONE, Vec3::ONE))
}

fn forward_trace(model: &Nglod, params: &[f64], p: Vec3, lod: usize) -> Trace {
    let config = model.config();
    let layout = model.layout();
    let f = config.feature_dim as usize;
    let input = config.input_dim() as usize;
    let hd = config.hidden as usize;
    let pd = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
    let mut z = vec![0.0; input];
    let mut corners = Vec::with_capacity(8 * lod);
    for (l, &res) in config.resolutions[..lod].iter().enumerate() {
        let zo = config.input_offset(l);
        let (i0, t) = cell(pd, res);
        for c in 0..8 {
            let d = [(c >> 2) & 1, (c >> 1) & 1, c & 1];
            let mut w = 1.0;
            for a in 0..3 {
                w *= if d[a] == 1 { t[a] } else { 1.0 - t[a] };
            }
            let v = [i0[0] + d[0], i0[1] + d[1], i0[2] + d[2]];
            // A sparse level's vertex outside its band has zero features.
            let Some(base) = model.vertex_base(l, v) else {
                continue;
            };
            for (k, zk) in z[zo..zo + f].iter_mut().enumerate() {
                *zk += w * params[base + k];
            }
            corners.push((base, zo, w));
        }
    }
    let mut h = vec![0.0; hd];
    let mut out = params[layout.b1];
    for (j, hj) in h.iter_mut().enumerate() {
        let mut s = params[layout.b0 + j];
        for (k, zk) in z.iter().enumerate() {
            s += params[layout.w0 + j * input + k] * zk;
        }
        *hj = s;
        out += params[layout.w1 + j] * s.max(0.0);
    }
    Trace { corners, z, h, out }
}

/// The output at `p` with the first `lod` levels, in f64, of `model`'s architecture (its
/// configuration and sparse levels' bands) with the parameters `params`.
pub fn forward(model: &Nglod, params: &[f64], p: Vec3, lod: usize) -> Result<f64, NglodError> {
    check(model, params, lod)?;
    Ok(forward_trace(model, params, p, lod).out)
}

fn check(model: &Nglod, params: &[f64], lod: usize) -> Result<(), NglodError> {
    model.config().lod(Some(lod))?;
    if params.len() != model.param_count() {
        return Err(NglodError::LengthMismatch {
            what: "NGLOD parameters",
            expected: model.param_count(),
            got: params.len(),
        });
    }
    Ok(())
}

/// The loss `L = (1/N) Σ_i Σ_k (sdf_k(x_i) - y_i)²` over the prefixes `k` of `objective`, and
/// its gradient dL/dparams, for `model`'s architecture with the parameters `params`. `sdf_k` is
/// the value served ([`crate::NeuralSdf`]'s box rule): the network at the point clamped to
/// `[-1, 1]³` plus the point's distance to the box. Near-surface samples beyond a face, where a
/// mesh touches its box, are labelled with their true distance; fitting the clamped value
/// alone to it pulled the face's value up (about a quarter of the samples' σ) and the surface
/// in.
pub fn loss_and_gradient(
    model: &Nglod,
    params: &[f64],
    points: &[Vec3],
    targets: &[f32],
    objective: Objective,
) -> Result<(f64, Vec<f64>), NglodError> {
    let config = model.config();
    check(model, params, config.levels())?;
    if points.len() != targets.len() {
        return Err(NglodError::LengthMismatch {
            what: "targets (one per point)",
            expected: points.len(),
            got: targets.len(),
        });
    }
    let layout = model.layout();
    let f = config.feature_dim as usize;
    let input = config.input_dim() as usize;
    let (first, count) = objective.prefixes(config.levels());
    let n = points.len().max(1) as f64;
    let mut loss = 0.0;
    let mut grad = vec![0.0; params.len()];
    for (&p, &y) in points.iter().zip(targets) {
        for lod in first..first + count {
            let t = forward_trace(model, params, p, lod);
            let r = t.out + f64::from(box_gap(p)) - f64::from(y);
            loss += r * r / n;
            let g = 2.0 * r / n;
            grad[layout.b1] += g;
            let mut dz = vec![0.0; input];
            for (j, &hj) in t.h.iter().enumerate() {
                grad[layout.w1 + j] += g * hj.max(0.0);
                if hj > 0.0 {
                    let dh = g * params[layout.w1 + j];
                    grad[layout.b0 + j] += dh;
                    for k in 0..input {
                        grad[layout.w0 + j * input + k] += dh * t.z[k];
                        dz[k] += dh * params[layout.w0 + j * input + k];
                    }
                }
            }
            for &(base, zo, w) in &t.corners {
                for k in 0..f {
                    grad[base + k] += w * dz[zo + k];
                }
            }
        }
    }
    Ok((loss, grad))
}
