//! Evaluation of HW SDF models: the design document's inside/outside F1 on a box set and a
//! near-surface set, distance errors, latency per point and per batch, and storage.
//!
//! ```
//! use sdf_eval::metrics::Confusion;
//!
//! // Predicted against exact signed distances; the inside class (< 0) is positive.
//! let c = Confusion::from_distances(&[-0.2, 0.1, -0.3, 0.4], &[-0.1, -0.2, -0.3, 0.5]);
//! assert_eq!((c.true_pos, c.false_neg, c.false_pos, c.true_neg), (2, 1, 0, 1));
//! assert!((c.f1() - 0.8).abs() < 1e-12);
//! ```
#![warn(missing_docs)]

pub mod corpus;
pub mod metrics;
pub mod run;
pub mod timing;

pub use metrics::{
    Confusion, DepthBands, DistanceError, EvalSets, Scores, SignErrors, SurfaceMetrics,
};
pub use timing::Latency;
