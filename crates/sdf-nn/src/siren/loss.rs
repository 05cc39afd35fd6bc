//! The SIREN loss's weights and terms: what the CPU reference ([`super::cpu`]), the GPU
//! training steps ([`super::step`]) and the trainer ([`super::train`]) share, so that none of
//! them imports another for it.

use serde::{Deserialize, Serialize};

/// Default of [`LossWeights::sign`].
pub const SIGN_WEIGHT: f32 = 1000.0;

/// Weights of the four loss terms, the off-surface sharpness α and the sign term.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LossWeights {
    /// On-surface |Φ| (3000).
    pub surface: f32,
    /// Off-surface exp(−α|Φ|) (100).
    pub off_surface: f32,
    /// On-surface 1 − cos(∇Φ, n) (100).
    pub normal: f32,
    /// Eikonal |‖∇Φ‖ − 1| on all points (5; the SIREN reference code uses 50).
    pub eikonal: f32,
    /// α of the off-surface term (100).
    pub alpha: f32,
    /// The sign term `w relu(−s Φ)` on off-surface points whose side `s` (+1 outside, −1
    /// inside) is known: zero where Φ has the right sign, `w |Φ|` where it has the wrong one.
    /// Counted in [`LossTerms::off_surface`]. The design document's loss has no such term (0),
    /// and model files written before it existed read as 0.
    #[serde(default)]
    pub sign: f32,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            surface: 3000.0,
            off_surface: 100.0,
            normal: 100.0,
            eikonal: 5.0,
            alpha: 100.0,
            sign: SIGN_WEIGHT,
        }
    }
}

/// The four weighted loss terms of a step (each a mean over the batch).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LossTerms {
    /// On-surface |Φ| term.
    pub surface: f32,
    /// Off-surface exp(−α|Φ|) term, with the sign term where sides are known.
    pub off_surface: f32,
    /// Normal-alignment term.
    pub normal: f32,
    /// Eikonal term.
    pub eikonal: f32,
}

impl LossTerms {
    /// Sum of the four terms.
    pub fn total(&self) -> f32 {
        self.surface + self.off_surface + self.normal + self.eikonal
    }

    /// The terms from the four floats the loss kernels write, in this order.
    pub(crate) fn from_slice(v: &[f32]) -> Self {
        LossTerms {
            surface: v[0],
            off_surface: v[1],
            normal: v[2],
            eikonal: v[3],
        }
    }
}
