//! HW SDF: neural signed distance functions fitted to triangle meshes, trained on the GPU by
//! hand-written WGSL kernels.
//!
//! This facade re-exports the workspace crates:
//! - [`geom`]: meshes, exact BVH distance, winding-number sign, samplers;
//! - [`nn`]: the GPU context, kernels, models, trainers and model files;
//! - [`eval`]: metrics, timing and corpus runs;
//! - [`cli`]: the flags the binaries share (the GPU to run on, how to train).
#![warn(missing_docs)]

pub mod cli;

pub use sdf_eval as eval;
pub use sdf_geom as geom;
pub use sdf_nn as nn;
