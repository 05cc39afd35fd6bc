//! The errors of serving: [`NeuralSdfError`] for everything a [`crate::NeuralSdf`] does, and
//! [`QueryError`] for misuse of the serving API's buffers.

use std::path::PathBuf;

use glam::Vec3;

use crate::gpu::GpuError;
use crate::model_file::ModelFileError;
use crate::nglod::NglodError;
use crate::siren::SirenGpuError;

/// Errors of [`NeuralSdf`](crate::NeuralSdf).
#[derive(Debug, thiserror::Error)]
pub enum NeuralSdfError {
    /// The model file could not be read or is not a valid model.
    #[error(transparent)]
    ModelFile(#[from] ModelFileError),
    /// [`NeuralSdf::load`](crate::NeuralSdf::load) read a model file that holds no valid model (another architecture,
    /// a configuration that does not validate, tensors that do not match it): `source` says
    /// what, as [`NeuralSdf::from_model_file`](crate::NeuralSdf::from_model_file) would, and the message names the file.
    #[error("{path}: {reason}")]
    InvalidModel {
        /// The model file.
        path: PathBuf,
        /// What is wrong with the model in it (in the message, so not also its `source()`).
        reason: Box<NeuralSdfError>,
    },
    /// The file's architecture is not one we know.
    #[error("unknown architecture `{0}` in the model file (expected `siren` or `nglod`)")]
    UnknownArchitecture(String),
    /// The file holds an NGLOD model that does not validate.
    #[error(transparent)]
    Nglod(#[from] NglodError),
    /// A SIREN GPU error.
    #[error(transparent)]
    Siren(#[from] SirenGpuError),
    /// A GPU error.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The serving API was misused (see [`crate::serve::query`]).
    #[error(transparent)]
    Query(#[from] QueryError),
    /// A level of detail was asked of a model without levels.
    #[error(
        "levels of detail exist only for NGLOD models (a hash grid's MLP reads all its levels at \
         once); this is a {0} model"
    )]
    NoLevels(&'static str),
    /// Layer kernels were chosen for a model that is not a SIREN.
    #[error("layer kernels are chosen only for SIREN models; this is a {0} model")]
    NoLayerKernels(&'static str),
}

/// Errors of the serving API.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    /// More points than the buffers hold.
    #[error("{requested} points do not fit query buffers of capacity {capacity}")]
    Capacity {
        /// Points asked for.
        requested: usize,
        /// The buffers' capacity.
        capacity: u32,
    },
    /// The buffers were made for another model or another device.
    #[error("these query buffers belong to another model or another device")]
    Foreign,
    /// A submission is still in flight on these buffers (wait for it first).
    #[error("a query is already in flight on these buffers; wait for its ticket first")]
    Busy,
    /// [`QueryKernel::PerSubgroup`](crate::serve::query::QueryKernel::PerSubgroup) was asked
    /// of a device without usable subgroups.
    #[error(
        "{adapter} has no subgroup operations usable by the one-point-per-subgroup query \
         kernel: use QueryKernel::PerInvocation"
    )]
    NoSubgroups {
        /// The adapter.
        adapter: String,
    },
    /// The ticket is not the one in flight on these buffers.
    #[error("this ticket does not belong to the query in flight on these buffers")]
    StaleTicket,
    /// The capacity is zero or the buffers would exceed the device's limits.
    #[error("invalid query buffers: {0}")]
    Invalid(String),
    /// A query point from the host is NaN or infinite (kernels need not propagate NaN, so its
    /// result would be an arbitrary number rather than NaN).
    #[error("query point {index} is not finite: {point}")]
    NonFinitePoint {
        /// Its index in the batch.
        index: usize,
        /// The point.
        point: Vec3,
    },
}
