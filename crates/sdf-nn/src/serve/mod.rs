//! Serving a trained model: [`NeuralSdf`](neural::NeuralSdf) and its queries on the GPU and the
//! CPU, the WGSL that embeds a model in a renderer's own shaders, and the sphere-tracing renderer.
//!
//! The models (`crate::siren`, `crate::nglod`) know nothing of this module: serving builds on
//! their kernels, never the other way round.

pub mod neural;
pub mod query;
pub mod render;
pub mod wgsl;
