//! SIREN kernel families beyond the original GEMM and row-blocked ones, one module each with
//! its own pipelines; [`super::LayerKernels`] picks the family.

pub(crate) mod coop;
pub(crate) mod tiled;
