//! The ground truth of a run: the mesh loaded and normalised into `[-1, 1]³`, and its exact
//! signed distance, built once and shared by the checks, the trainers and the evaluation.

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance};
use sdf_nn::{GpuContext, GroundTruthDevice, Labeller};

use super::RunError;
use crate::metrics::EVAL_SEED;

/// Loads a mesh and normalises it into `[-1, 1]³`.
pub fn load_normalized(path: &Path) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    load_normalized_with(path, &sdf_geom::LoadOptions::default())
}

/// [`load_normalized`] with explicit [`sdf_geom::LoadOptions`] (the bins' `--allow-external-uris`).
/// The normalisation maps to the file's coordinates, also for a mesh loaded relative to its
/// [`sdf_geom::LoadReport::origin`] (far from the origin): its centre is then in f64.
pub fn load_normalized_with(
    path: &Path,
    options: &sdf_geom::LoadOptions,
) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    let (mesh, report) =
        sdf_geom::load_mesh_with(path, options).map_err(|source| RunError::Mesh {
            path: path.to_owned(),
            source,
        })?;
    let (unit, normalization) = mesh.normalized();
    Ok((unit, normalization.translated(report.origin)))
}

/// A normalised mesh with its exact signed distance, built once per run: the no-inside check,
/// the trainers' samplers and the evaluation all read the same BVH (1.3–1.6 s to build for a
/// 1.4 M-triangle scan on 2 cores, once instead of three times), and all label through the same
/// [`Labeller`], on the path the run chose (`--ground-truth`).
#[derive(Clone, Debug)]
pub struct GroundTruth<'g> {
    /// The mesh, in the normalised cube.
    pub mesh: Mesh,
    /// Its exact labels (signed distance, winding numbers) on the CPU or the GPU.
    pub labels: Labeller<'g>,
}

impl GroundTruth<'static> {
    /// Builds the signed distance of `mesh` (already normalised, as [`load_normalized`] gives it),
    /// loaded from `path` (for errors), labelling on the CPU.
    pub fn new(mesh: Mesh, path: &Path) -> Result<Self, RunError> {
        let sdf = build(&mesh, path)?;
        Ok(GroundTruth {
            mesh,
            labels: Labeller::cpu(sdf),
        })
    }
}

impl<'g> GroundTruth<'g> {
    /// [`GroundTruth::new`] labelling where `device` asks on `gpu` ([`Labeller::choose`]):
    /// `auto` falls back to the CPU where the mesh does not fit the GPU, and
    /// [`Labeller::fallback`] says why.
    ///
    /// # Errors
    /// The mesh's ([`RunError::Mesh`]); with `gpu`, a mesh that does not fit the device
    /// ([`RunError::GroundTruth`], naming the limit).
    pub fn on(
        gpu: &'g GpuContext,
        mesh: Mesh,
        path: &Path,
        device: GroundTruthDevice,
    ) -> Result<Self, RunError> {
        let sdf = build(&mesh, path)?;
        let labels = Labeller::choose(gpu, sdf, device)?;
        Ok(GroundTruth { mesh, labels })
    }

    /// The CPU signed distance of the mesh (the one the labels come from, or the GPU's trees
    /// were built from).
    pub fn sdf(&self) -> &SignedDistance {
        self.labels.sdf()
    }
}

/// The signed distance of `mesh`, loaded from `path`.
fn build(mesh: &Mesh, path: &Path) -> Result<Arc<SignedDistance>, RunError> {
    SignedDistance::new(mesh)
        .map(Arc::new)
        .map_err(|source| RunError::Mesh {
            path: path.to_owned(),
            source,
        })
}

/// Why F1 would be undefined for `truth`'s mesh: (almost) no inside among a quick sample
/// of box and near-surface points (same bounds as the evaluation,
/// [`crate::metrics::no_inside_reason`]). For a warning before training.
///
/// # Errors
/// The labels' ([`RunError::GroundTruth`]: the GPU failed).
pub fn no_inside_check(truth: &GroundTruth) -> Result<Option<String>, RunError> {
    let (mesh, labels) = (&truth.mesh, &truth.labels);
    let clear = |points: Vec<Vec3>| -> Result<f64, RunError> {
        let signed = labels.signed_distance_batch(&points)?;
        Ok(crate::metrics::clear_inside_fraction(
            labels, &points, &signed,
        )?)
    };
    let b = clear(sdf_geom::sample::uniform_box(20_000, EVAL_SEED))?;
    let n = clear(sdf_geom::sample::near_surface(
        mesh,
        20_000,
        crate::metrics::NEAR_SURFACE_SIGMA,
        EVAL_SEED ^ 1,
    ))?;
    Ok(crate::metrics::no_inside_reason(b, n))
}
