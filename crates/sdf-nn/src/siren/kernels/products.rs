//! The GEMM shape of each of a SIREN layer's products (`C = A Wᵀ`, `C = A W`, the split-K
//! weight gradient), in the uniforms every GEMM kernel family reads.

use crate::siren::LayerLayout;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct GemmUniforms {
    pub(crate) mode: u32,
    pub(crate) m: u32,
    pub(crate) n: u32,
    pub(crate) k: u32,
    pub(crate) a_off: u32,
    pub(crate) a_rs: u32,
    pub(crate) a_cs: u32,
    pub(crate) b_off: u32,
    pub(crate) b_rs: u32,
    pub(crate) b_cs: u32,
    pub(crate) ldc: u32,
    pub(crate) bias_off: u32,
    pub(crate) k_chunk: u32,
    pub(crate) pbias_off: u32,
    pub(crate) omega: f32,
    pub(crate) b_style: u32,
    pub(crate) a_vec4: u32,
    pub(crate) _pad: [u32; 3],
}

impl GemmUniforms {
    /// Picks vec4 loads where the operands' layout allows them (16-byte aligned runs).
    pub(crate) fn with_load_styles(mut self) -> Self {
        let a4 = |x: u32| x.is_multiple_of(4);
        self.a_vec4 = (self.a_cs == 1
            && a4(self.a_off)
            && a4(self.a_rs)
            && a4(self.k)
            && a4(self.k_chunk.max(4))) as u32;
        self.b_style = if self.b_rs == 1 && a4(self.b_off) && a4(self.b_cs) && a4(self.k) {
            1
        } else if self.b_cs == 1 && a4(self.b_off) && a4(self.b_rs) && a4(self.k) {
            2
        } else {
            0
        };
        self
    }
}

/// Batch rows per split of a weight-gradient GEMM (a multiple of 4). 512: a `default` step's
/// 256 × 256 weight gradient over 2·10⁴ stacked rows makes 640 tiled workgroups, not 320, so
/// that they spread evenly over a GPU's SMs (on the H100 the step measured 36 % slower with
/// 8 × 8 register blocks' four times fewer workgroups). The partials it adds cost lavapipe
/// nothing measurable (420 ms per `small` weight gradient with 512 or 1024).
pub(crate) const K_CHUNK: u32 = 512;

/// Rows of a K chunk → number of splits.
pub(crate) fn splits_for(rows: u32) -> u32 {
    rows.div_ceil(K_CHUNK).max(1)
}

/// `C = A W_lᵀ` over `rows` rows of `A` (offset `a_off`, row stride `a_rs`), output row stride
/// `ldc`.
pub(crate) fn times_wt(
    lay: &LayerLayout,
    rows: u32,
    a_off: u32,
    a_rs: u32,
    ldc: u32,
) -> GemmUniforms {
    GemmUniforms {
        m: rows,
        n: lay.fan_out as u32,
        k: lay.fan_in as u32,
        a_off,
        a_rs,
        a_cs: 1,
        b_off: lay.weight as u32,
        b_rs: 1,
        b_cs: lay.fan_in as u32,
        ldc,
        bias_off: lay.bias as u32,
        ..Default::default()
    }
}

/// `C = A W_l`.
pub(crate) fn times_w(
    lay: &LayerLayout,
    rows: u32,
    a_off: u32,
    a_rs: u32,
    ldc: u32,
) -> GemmUniforms {
    GemmUniforms {
        m: rows,
        n: lay.fan_in as u32,
        k: lay.fan_out as u32,
        a_off,
        a_rs,
        a_cs: 1,
        b_off: lay.weight as u32,
        b_rs: lay.fan_in as u32,
        b_cs: 1,
        ldc,
        ..Default::default()
    }
}

/// Z = A_prev · Wᵀ (mode 0), or with `fused_sine` the inference activations sin(ω0 (Z + b)).
pub(crate) fn gemm_forward(
    lay: &LayerLayout,
    rows: u32,
    fused_sine: bool,
    omega: f32,
) -> GemmUniforms {
    let (fan_in, fan_out) = (lay.fan_in as u32, lay.fan_out as u32);
    GemmUniforms {
        mode: fused_sine as u32,
        omega,
        ..times_wt(lay, rows, 0, fan_in, fan_out)
    }
}

/// Ā_{l-1} = Z̄_l · W_l.
pub(crate) fn gemm_backward(lay: &LayerLayout, rows: u32) -> GemmUniforms {
    times_w(lay, rows, 0, lay.fan_out as u32, lay.fan_in as u32)
}

/// W̄_l partials = Z̄_lᵀ · A_{l-1}, split over the batch rows (also over the stacked rows
/// `[Z̄; H]ᵀ [A; Ḡ]` of the reverse-over-reverse step, whose tiled kernel ignores the mode).
pub(crate) fn gemm_wgrad(lay: &LayerLayout, rows: u32) -> GemmUniforms {
    let (m, n) = (lay.fan_out as u32, lay.fan_in as u32);
    let splits = splits_for(rows);
    GemmUniforms {
        mode: 2,
        m,
        n,
        k: rows,
        a_rs: 1,
        a_cs: m,
        b_rs: n,
        b_cs: 1,
        ldc: n,
        k_chunk: K_CHUNK,
        pbias_off: splits * m * n,
        ..Default::default()
    }
}

#[cfg(test)]
mod uniform_layout {
    /// GemmUniforms: the layout the shaders read.
    #[test]
    fn uniforms_mirror_the_shaders() {
        crate::shaders::assert_mirrors!(
            super::GemmUniforms,
            crate::shaders::SIREN_GEMM,
            "Gemm",
            [
                mode, m, n, k, a_off, a_rs, a_cs, b_off, b_rs, b_cs, ldc, bias_off, k_chunk,
                pbias_off, omega, b_style, a_vec4
            ]
        );
    }
}
