//! HW SDF: neural signed distance functions fitted to triangle meshes, trained on the GPU by
//! hand-written WGSL kernels.
//!
//! This facade re-exports the workspace crates:
//! - [`geom`]: meshes, exact BVH distance, winding-number sign, samplers;
//! - [`nn`]: the GPU context, kernels, models, trainers and model files;
//! - [`eval`]: metrics, timing and corpus runs;
//! - [`cli`]: the flags the binaries share (the GPU to run on, how to train).
//!
//! A model trained by `cargo run --release --bin train -- spot.obj` (which writes
//! `spot.nglod.safetensors`, or `spot.hashgrid.safetensors` on a CPU adapter), queried from Rust:
//!
//! ```no_run
//! use hwsdf::nn::{GpuContext, NeuralSdf};
//! use glam::Vec3;
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let gpu = GpuContext::new()?;
//! let sdf = NeuralSdf::load("spot.nglod.safetensors")?;
//! let points = [Vec3::ZERO, Vec3::new(0.5, 0.2, -0.1)];
//! // On the GPU, and the same answer from CPU threads.
//! let on_gpu = sdf.eval(&gpu, &points)?;
//! let on_cpu = sdf.eval_cpu(&points);
//! assert!((on_gpu[0] - on_cpu[0]).abs() < 1e-3);
//! // Distances with unit normals, for collisions or shading.
//! for (d, n) in sdf.eval_with_normals(&gpu, &points)? {
//!     println!("{d:+.4} {n}");
//! }
//! # Ok(())
//! # }
//! ```
#![warn(missing_docs)]

pub mod cli;

pub use sdf_eval as eval;
pub use sdf_geom as geom;
pub use sdf_nn as nn;
