//! Serving a trained model: [`NeuralSdf`](neural::NeuralSdf) and its queries on the GPU and the
//! CPU, the WGSL that embeds a model in a renderer's own shaders, and the sphere-tracing renderer.
//!
//! The rooms depend on each other in one direction: [`network`] (the network and its GPU
//! side) and [`error`] are used by [`query`] (caller-owned buffers, recording, submission) and
//! [`wgsl`] (snippets for renderers); [`neural`] owns every method of `NeuralSdf` and drives
//! them; [`render`] draws a `NeuralSdf`; [`scene`] combines many models and primitives into
//! one scene. The models (`crate::siren`, `crate::nglod`) know
//! nothing of this module.

pub mod error;
pub mod network;
pub mod neural;
pub mod query;
pub mod render;
pub mod scene;
pub(crate) mod scratch;
pub mod wgsl;
