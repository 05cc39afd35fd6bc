// SIREN's per-point loss and its workgroup sum, shared by siren_head.wgsl (the tangent step) and
// siren_ror.wgsl (the reverse-over-reverse step): crates/sdf-nn/src/shaders.rs prepends this file
// to both. The formulas are the CPU reference's (siren::cpu::point_loss).

const NORM_EPS: f32 = 1e-12;
// Invocations per workgroup of the kernels that sum the loss (a pipeline constant; a power of
// two).
override LOSS_WG: u32 = 256u;

// The four weighted terms (surface |Φ|, off-surface exp(−α|Φ|) plus the sign term, normal
// 1 − cos, eikonal) and their derivatives with respect to Φ and ∇Φ.
struct PointLoss {
    terms: vec4<f32>,
    dphi: f32,
    dgrad: vec3<f32>,
}

// `weights`: (surface, off-surface, normal, eikonal). `n` is the normal on the surface; off
// it, `n.x` is the point's known side (+1 outside, −1 inside, 0 unknown), and a point on the
// wrong side adds `w_sign` |Φ| to the off-surface term.
fn point_loss(
    phi: f32,
    gr: vec3<f32>,
    on_surface: bool,
    n: vec3<f32>,
    weights: vec4<f32>,
    alpha: f32,
    w_sign: f32,
) -> PointLoss {
    var out: PointLoss;
    let gn = length(gr);
    out.terms.w = weights.w * abs(gn - 1.0);
    out.dgrad = weights.w * sign(gn - 1.0) / max(gn, NORM_EPS) * gr;
    if on_surface {
        out.terms.x = weights.x * abs(phi);
        out.dphi = weights.x * sign(phi);
        let denom = max(gn * length(n), NORM_EPS);
        let c = dot(gr, n) / denom;
        out.terms.z = weights.z * (1.0 - c);
        let gn2 = max(gn, NORM_EPS) * max(gn, NORM_EPS);
        out.dgrad -= weights.z * (n / denom - c * gr / gn2);
    } else {
        let e = exp(-alpha * abs(phi));
        out.terms.y = weights.y * e;
        out.dphi = -weights.y * alpha * sign(phi) * e;
        // w_sign relu(−s Φ): zero on the right side, w_sign |Φ| on the wrong one.
        if n.x * phi < 0.0 {
            out.terms.y += w_sign * abs(phi);
            out.dphi -= w_sign * n.x;
        }
    }
    return out;
}

var<workgroup> loss_red: array<vec4<f32>, LOSS_WG>;

// Tree sum of `terms` over a workgroup of LOSS_WG invocations; every invocation must call it
// (uniform control flow). Invocation 0 writes the sum at `loss_partial[4 group..]`.
fn store_loss_sum(lid: u32, terms: vec4<f32>, group: u32) {
    loss_red[lid] = terms;
    workgroupBarrier();
    for (var stride = LOSS_WG / 2u; stride > 0u; stride /= 2u) {
        if lid < stride {
            loss_red[lid] += loss_red[lid + stride];
        }
        workgroupBarrier();
    }
    if lid == 0u {
        let s = loss_red[0];
        loss_partial[4u * group] = s.x;
        loss_partial[4u * group + 1u] = s.y;
        loss_partial[4u * group + 2u] = s.z;
        loss_partial[4u * group + 3u] = s.w;
    }
}
