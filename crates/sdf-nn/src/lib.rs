//! GPU side of HW SDF: the wgpu context, the WGSL kernels' host code, the optimiser, the
//! SIREN, NGLOD and hash-grid models with their trainers and model files, the GPU ground truth,
//! and serving (queries, rendering, scenes).
//!
//! Every kernel sits beside the module that runs it (`src/**/shaders/*.wgsl`, embedded with
//! `include_str!`); each has a CPU reference that the tests compare it with.
//!
//! ```no_run
//! use sdf_nn::{Adam, AdamConfig, GpuContext};
//!
//! # fn main() -> Result<(), sdf_nn::GpuError> {
//! // Picks the adapter from HWSDF_ADAPTER (or WGPU_ADAPTER_NAME / WGPU_BACKEND), preferring a
//! // real GPU.
//! let gpu = GpuContext::new()?;
//! println!("running on {}", gpu.describe());
//!
//! let params = gpu.storage_from_slice("params", &[1.0f32, -2.0, 0.5])?;
//! let grads = gpu.storage_from_slice("grads", &[0.1f32, 0.2, -0.3])?;
//! let mut adam = Adam::new(&gpu, &params, &grads, 3, AdamConfig::default())?;
//! adam.step(&gpu, 1.0);
//! let updated: Vec<f32> = gpu.read_back(&params)?;
//! assert!(updated[0] < 1.0);
//! # Ok(())
//! # }
//! ```
#![warn(missing_docs)]

pub mod adam;
pub mod gpu;
pub mod ground_truth;
pub mod model_file;
pub mod nglod;
pub mod serve;
pub mod shaders;
pub mod siren;

pub use adam::{Adam, AdamConfig, AdamCpu, AdamState};
pub use gpu::{
    GpuContext, GpuError, GpuOptions, QueryKernel, SPIN_WAIT, SirenActivations, StepLayout,
};
pub use ground_truth::{
    GpuGroundTruth, GroundTruthDevice, GroundTruthError, GroundTruthPath, Labeller,
};
pub use model_file::{ModelFile, ModelFileError, Normalization};
pub use nglod::{
    DistanceMode, Nglod, NglodConfig, NglodError, NglodGpu, NglodTrainConfig, NglodTrainer,
};
pub use serve::error::{NeuralSdfError, QueryError};
pub use serve::neural::NeuralSdf;
pub use serve::query::{
    QueryBuffers, QueryBuffersDescriptor, QueryOutputs, QueryResults, QuerySpace, QueryTicket,
    QueryTransfer,
};
pub use serve::render::{RenderError, RenderOptions, Renderer, RgbaImage, render};
pub use serve::scene::{Scene, SceneError, SceneFileError, SceneNode};
pub use serve::wgsl::{EmbedError, SdfBindGroup};
pub use siren::{LossWeights, Siren, SirenConfig, SirenGpu, SirenTrainConfig, SirenTrainer};
