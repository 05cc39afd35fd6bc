//! The network inside a served model, and its GPU side.

use crate::nglod::{Nglod, NglodGpu};
use crate::siren::{Siren, SirenGpu};

/// The network inside a [`NeuralSdf`](crate::NeuralSdf).
#[derive(Clone, Debug)]
pub enum Network {
    /// A SIREN.
    Siren(Siren),
    /// An NGLOD model.
    Nglod(Nglod),
}

/// The network's GPU side, created on first GPU use and kept with the device it lives on.
// Boxed: both hold several buffers and pipelines inline, of very different sizes.
pub(crate) enum GpuNetwork {
    Siren(Box<SirenGpu>),
    Nglod(Box<NglodGpu>),
}
