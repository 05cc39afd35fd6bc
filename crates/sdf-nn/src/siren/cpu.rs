//! f64 reference of the SIREN: forward with the input gradient (three tangents carried through
//! the layers), the four-term loss, and the gradient of that loss with respect to every
//! parameter (double backprop through Φ and ∇Φ). The GPU kernels are checked against it, and it
//! is checked against finite differences.
//!
//! The loss of a batch of `N` points, the first `n_surface` of which lie on the surface with
//! normals `n`, the others off it on a known side `s` (+1 outside, −1 inside, 0 unknown), is
//! the mean over all `N` points (as in the SIREN reference code, plus the sign term):
//!
//! ```text
//! L = 1/N Σ_surface [ w_s |Φ| + w_n (1 − cos(∇Φ, n)) ]
//!   + 1/N Σ_off     [ w_o exp(−α |Φ|) + w_sign max(0, −s Φ) ]
//!   + 1/N Σ_all     [ w_e | ‖∇Φ‖ − 1 | ]
//! ```

use super::SirenConfig;
use super::loss::LossWeights;

/// Guards norms in the cosine and eikonal terms against division by zero.
pub const NORM_EPS: f64 = 1e-12;

/// Activations of one point: per layer, the pre-activations `z` (value and three tangents) and
/// the outputs (value and three tangents), each `[fan_out][4]`.
struct Trace {
    z: Vec<Vec<[f64; 4]>>,
    out: Vec<Vec<[f64; 4]>>,
}

fn input_streams(p: [f64; 3]) -> Vec<[f64; 4]> {
    (0..3)
        .map(|i| {
            let mut t = [0.0; 4];
            t[0] = p[i];
            t[i + 1] = 1.0;
            t
        })
        .collect()
}

fn forward_trace(config: &SirenConfig, params: &[f64], p: [f64; 3]) -> (Trace, f64, [f64; 3]) {
    let w0 = f64::from(config.omega0);
    let layers = config.layers();
    let (last, hidden) = layers.split_last().expect("at least one layer");
    let mut trace = Trace {
        z: Vec::new(),
        out: Vec::new(),
    };
    let mut a = input_streams(p);
    for lay in hidden {
        let mut zs = Vec::with_capacity(lay.fan_out);
        let mut outs = Vec::with_capacity(lay.fan_out);
        for o in 0..lay.fan_out {
            let row = &params[lay.weight + o * lay.fan_in..][..lay.fan_in];
            let mut z = [0.0; 4];
            for (w, ai) in row.iter().zip(&a) {
                for s in 0..4 {
                    z[s] += w * ai[s];
                }
            }
            z[0] += params[lay.bias + o];
            let (s, c) = (w0 * z[0]).sin_cos();
            zs.push(z);
            outs.push([s, w0 * c * z[1], w0 * c * z[2], w0 * c * z[3]]);
        }
        trace.z.push(zs);
        a = outs.clone();
        trace.out.push(outs);
    }
    let mut y = [0.0; 4];
    for (w, ai) in params[last.weight..last.bias].iter().zip(&a) {
        for s in 0..4 {
            y[s] += w * ai[s];
        }
    }
    (trace, y[0] + params[last.bias], [y[1], y[2], y[3]])
}

/// Φ and ∇Φ at `p`.
pub fn forward_with_gradient(config: &SirenConfig, params: &[f64], p: [f64; 3]) -> (f64, [f64; 3]) {
    let (_, phi, g) = forward_trace(config, params, p);
    (phi, g)
}

/// One point's weighted loss terms `[surface, off_surface, normal, eikonal]` (not yet divided by
/// N) and the derivatives of their sum with respect to Φ and ∇Φ. `normal` is the normal of a
/// surface point; an off-surface point (`None`) is on side `side` (+1 outside, −1 inside, 0
/// unknown; no other value), which the sign term counts in `off_surface`.
pub fn point_loss(
    phi: f64,
    g: [f64; 3],
    normal: Option<[f64; 3]>,
    side: f64,
    w: &LossWeights,
) -> ([f64; 4], f64, [f64; 3]) {
    let (ws, wo, wn, we, alpha) = (
        f64::from(w.surface),
        f64::from(w.off_surface),
        f64::from(w.normal),
        f64::from(w.eikonal),
        f64::from(w.alpha),
    );
    let gn = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    let mut terms = [0.0; 4];
    let mut dphi;
    let mut dg = [0.0; 3];
    // Eikonal on every point: d|‖g‖ − 1|/dg = sign(‖g‖ − 1) g / ‖g‖.
    terms[3] = we * (gn - 1.0).abs();
    let es = we * sign(gn - 1.0) / gn.max(NORM_EPS);
    for j in 0..3 {
        dg[j] += es * g[j];
    }
    match normal {
        Some(n) => {
            terms[0] = ws * phi.abs();
            dphi = ws * sign(phi);
            let nn = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            let denom = (gn * nn).max(NORM_EPS);
            let gdotn = g[0] * n[0] + g[1] * n[1] + g[2] * n[2];
            let cos = gdotn / denom;
            terms[2] = wn * (1.0 - cos);
            // d cos/dg = n/(‖g‖‖n‖) − (g·n) g / (‖g‖³ ‖n‖).
            let gn2 = gn.max(NORM_EPS) * gn.max(NORM_EPS);
            for j in 0..3 {
                dg[j] -= wn * (n[j] / denom - cos * g[j] / gn2);
            }
        }
        None => {
            let e = (-alpha * phi.abs()).exp();
            terms[1] = wo * e;
            dphi = -wo * alpha * sign(phi) * e;
            if side * phi < 0.0 {
                let wsign = f64::from(w.sign);
                terms[1] += wsign * phi.abs();
                dphi -= wsign * side;
            }
        }
    }
    (terms, dphi, dg)
}

/// `sign` with sign(0) = 0, like WGSL's.
fn sign(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// The known side of point `i` of a batch whose first `n_surface` points are on the surface
/// and whose next `sides.len()` have `sides` (the rest: unknown).
fn side_of(i: usize, n_surface: usize, sides: &[f64]) -> f64 {
    i.checked_sub(n_surface)
        .and_then(|k| sides.get(k))
        .copied()
        .unwrap_or(0.0)
}

/// The batch loss terms `[surface, off_surface, normal, eikonal]` (each already weighted and
/// divided by the number of points). `normals` belong to the first `normals.len()` points,
/// `sides` to the off-surface points after them.
pub fn loss(
    config: &SirenConfig,
    params: &[f64],
    points: &[[f64; 3]],
    normals: &[[f64; 3]],
    sides: &[f64],
    weights: &LossWeights,
) -> [f64; 4] {
    let inv_n = 1.0 / points.len().max(1) as f64;
    let mut total = [0.0; 4];
    for (i, &p) in points.iter().enumerate() {
        let (phi, g) = forward_with_gradient(config, params, p);
        let side = side_of(i, normals.len(), sides);
        let (t, _, _) = point_loss(phi, g, normals.get(i).copied(), side, weights);
        for k in 0..4 {
            total[k] += t[k] * inv_n;
        }
    }
    total
}

/// The batch loss terms (as [`loss`]) and the gradient of their sum with respect to every
/// parameter, in the flat layout.
pub fn loss_and_gradient(
    config: &SirenConfig,
    params: &[f64],
    points: &[[f64; 3]],
    normals: &[[f64; 3]],
    sides: &[f64],
    weights: &LossWeights,
) -> ([f64; 4], Vec<f64>) {
    let w0 = f64::from(config.omega0);
    let layers = config.layers();
    let inv_n = 1.0 / points.len().max(1) as f64;
    let mut grad = vec![0.0; params.len()];
    let mut total = [0.0; 4];
    for (i, &p) in points.iter().enumerate() {
        let (trace, phi, g) = forward_trace(config, params, p);
        let side = side_of(i, normals.len(), sides);
        let (t, dphi, dg) = point_loss(phi, g, normals.get(i).copied(), side, weights);
        for k in 0..4 {
            total[k] += t[k] * inv_n;
        }
        // Adjoint of the output streams [Φ, g1, g2, g3].
        let dout = [dphi * inv_n, dg[0] * inv_n, dg[1] * inv_n, dg[2] * inv_n];
        let last = layers.last().expect("at least one layer");
        let l_hidden = layers.len() - 1;
        let h_last = &trace.out[l_hidden - 1];
        let mut abar: Vec<[f64; 4]> = vec![[0.0; 4]; last.fan_in];
        for k in 0..last.fan_in {
            let w = params[last.weight + k];
            for s in 0..4 {
                grad[last.weight + k] += dout[s] * h_last[k][s];
                abar[k][s] = w * dout[s];
            }
        }
        grad[last.bias] += dout[0];
        for l in (0..l_hidden).rev() {
            let lay = &layers[l];
            let inp = if l == 0 {
                input_streams(p)
            } else {
                trace.out[l - 1].clone()
            };
            let mut next_abar = vec![[0.0; 4]; lay.fan_in];
            for o in 0..lay.fan_out {
                let z = trace.z[l][o];
                let (s, c) = (w0 * z[0]).sin_cos();
                let ab = abar[o];
                let zb = [
                    w0 * c * ab[0] - w0 * w0 * s * (ab[1] * z[1] + ab[2] * z[2] + ab[3] * z[3]),
                    w0 * c * ab[1],
                    w0 * c * ab[2],
                    w0 * c * ab[3],
                ];
                grad[lay.bias + o] += zb[0];
                for k in 0..lay.fan_in {
                    let wi = lay.weight + o * lay.fan_in + k;
                    for st in 0..4 {
                        grad[wi] += zb[st] * inp[k][st];
                        next_abar[k][st] += params[wi] * zb[st];
                    }
                }
            }
            abar = next_abar;
        }
    }
    (total, grad)
}
