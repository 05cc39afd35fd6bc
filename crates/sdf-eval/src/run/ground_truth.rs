//! The ground truth of a run: the mesh loaded and normalised into `[-1, 1]³`, and its exact
//! signed distance, built once and shared by the checks, the trainers and the evaluation.

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance};
use sdf_nn::{DistanceMode, GpuContext, GroundTruthDevice, GroundTruthPath, Labeller};

use super::{ModelKind, RunError, TrainOptions};
use crate::metrics::EVAL_SEED;

/// Loads a mesh and normalises it into `[-1, 1]³`.
pub fn load_normalized(path: &Path) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    load_normalized_with(path, &sdf_geom::LoadOptions::default())
}

/// [`load_normalized`] with explicit [`sdf_geom::LoadOptions`] (the bins' `--allow-external-uris`).
/// The normalisation maps to the file's coordinates, also for a mesh loaded relative to its
/// [`sdf_geom::LoadReport::origin`] (far from the origin): its centre is then in f64. The
/// loader's warnings (recentred, indices or primitives skipped, a compressed copy ignored) go
/// to stderr as `warning: MESH: ...`, as `sdf` prints them.
pub fn load_normalized_with(
    path: &Path,
    options: &sdf_geom::LoadOptions,
) -> Result<(Mesh, sdf_geom::Normalization), RunError> {
    let (mesh, report) =
        sdf_geom::load_mesh_with(path, options).map_err(|source| RunError::Mesh {
            path: path.to_owned(),
            source,
        })?;
    for warning in &report.warnings {
        eprintln!("warning: {}: {warning}", path.display());
    }
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
    /// `auto` falls back to the CPU where the mesh does not fit the GPU or the GPU's labels of
    /// a probe disagree with the CPU's, and [`Labeller::fallback`] says why.
    ///
    /// # Errors
    /// The mesh's ([`RunError::Mesh`]); with `gpu`, a mesh that does not fit the device
    /// ([`RunError::GroundTruth`], naming the limit) or a probe that disagrees.
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

/// Points of the no-inside check ([`no_inside_check`]): 20 000 in the box, 20 000 near the
/// surface.
const NO_INSIDE_POINTS: usize = 40_000;

/// About how many exact queries a run of `options` makes (on a CPU adapter or not, with
/// `eval_points` per evaluation set): the no-inside check, the training samples' labels
/// (SIREN's box pool; NGLOD's and the hash grid's uniform and near-surface points of every pool
/// block drawn over the planned epochs, at least the time budget's minimum), and the
/// evaluation's signed distances and winding numbers. For the estimate of
/// [`labelling_estimate`].
pub fn planned_labels(options: &TrainOptions, cpu_adapter: bool, eval_points: usize) -> usize {
    let length = options.length(cpu_adapter);
    let units = length.asked.unwrap_or(length.default).max(1);
    let training = match options.model {
        ModelKind::Siren => {
            let c = sdf_nn::SirenTrainConfig::default();
            let sign = options.siren_weights.unwrap_or(c.weights).sign;
            if sign > 0.0 {
                c.box_pool.min(units.saturating_mul(c.box_per_step))
            } else {
                0
            }
        }
        ModelKind::Nglod | ModelKind::Hashgrid => {
            let c = options.model.grid_schedule().unwrap_or_default();
            let (blocks, refresh_every) = options.pool.unwrap_or((c.pool_blocks, c.refresh_every));
            let schedule = sdf_nn::nglod::PoolSchedule {
                blocks,
                refresh_every,
            };
            let drawn = schedule.blocks_at(units - 1).end;
            drawn.saturating_mul(c.uniform_points + c.near_points)
        }
    };
    let check = if options.distance == DistanceMode::Signed {
        NO_INSIDE_POINTS
    } else {
        0
    };
    // Each evaluation set: a signed distance and a winding number per point.
    check + training + 4 * eval_points
}

/// Points the labelling estimate is measured on, at most: box and near-surface points in turn.
const PROBE_POINTS: usize = 8192;

/// Says how long `labels` exact queries will take on `truth`'s path, measured on a probe
/// ([`Labeller::time_per_label`] over box and near-surface points in turn), when that passes
/// `threshold` seconds: `"labelling: about 1.2 M exact distances on the CPU, estimated 3 min
/// 20 s (167 µs each, measured on 1600 points)"`; `None` below it.
///
/// # Errors
/// The labels' ([`RunError::GroundTruth`]: the GPU failed).
pub fn labelling_estimate(
    truth: &GroundTruth,
    labels: usize,
    threshold: f64,
) -> Result<Option<String>, RunError> {
    let half = PROBE_POINTS / 2;
    let near = sdf_geom::sample::near_surface(
        &truth.mesh,
        half,
        crate::metrics::NEAR_SURFACE_SIGMA,
        EVAL_SEED ^ 3,
    );
    let probe: Vec<Vec3> = sdf_geom::sample::uniform_box(half, EVAL_SEED ^ 2)
        .into_iter()
        .zip(near)
        .flat_map(|(b, n)| [b, n])
        .collect();
    let (per_label, measured) = truth.labels.time_per_label(&probe)?;
    Ok(estimate_line(
        labels,
        per_label,
        measured,
        truth.labels.path(),
        threshold,
    ))
}

/// The line of [`labelling_estimate`] for `labels` queries at `per_label` seconds each
/// (measured on `measured` points on `path`), or `None` below `threshold` seconds.
pub fn estimate_line(
    labels: usize,
    per_label: f64,
    measured: usize,
    path: GroundTruthPath,
    threshold: f64,
) -> Option<String> {
    let seconds = labels as f64 * per_label;
    (seconds >= threshold).then(|| {
        format!(
            "labelling: about {} exact distances on the {}, estimated {} ({:.1} µs each, \
             measured on {measured} points)",
            count(labels),
            path.name().to_uppercase(),
            duration(seconds),
            per_label * 1e6,
        )
    })
}

/// `1234567` as `"1.2 M"`, `45000` as `"45 k"`, small counts as they are.
fn count(n: usize) -> String {
    match n {
        0..10_000 => n.to_string(),
        10_000..1_000_000 => format!("{:.0} k", n as f64 / 1e3),
        _ => format!("{:.1} M", n as f64 / 1e6),
    }
}

/// Seconds as `"12 s"`, `"3 min 20 s"` or `"2 h 05 min"`.
pub fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        0..60 => format!("{:.0} s", seconds.max(0.0)),
        60..3600 => format!("{} min {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, (s % 3600) / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn estimates_say_how_many_how_long_and_where() {
        let line = estimate_line(1_234_567, 167e-6, 1600, GroundTruthPath::Cpu, 2.0).unwrap();
        assert_eq!(
            line,
            "labelling: about 1.2 M exact distances on the CPU, estimated 3 min 26 s \
             (167.0 µs each, measured on 1600 points)"
        );
        assert_eq!(
            estimate_line(1000, 1e-6, 10, GroundTruthPath::Gpu, 2.0),
            None
        );
        assert!(
            estimate_line(45_000, 1e-4, 10, GroundTruthPath::Gpu, 2.0)
                .unwrap()
                .contains("about 45 k exact distances on the GPU, estimated 4 s")
        );
        assert_eq!(duration(7300.0), "2 h 01 min");
    }

    /// A longer run plans more labels: NGLOD's pool blocks over its epochs, SIREN's box pool
    /// up to its cap, the evaluation's sets.
    #[test]
    fn planned_labels_grow_with_the_run() {
        let nglod = |epochs| TrainOptions {
            epochs: Some(epochs),
            ..TrainOptions::new(ModelKind::Nglod, crate::run::Preset::Small)
        };
        let (one, ten) = (
            planned_labels(&nglod(1), true, 1000),
            planned_labels(&nglod(10), true, 1000),
        );
        // One block of 3·10^5 labelled points for the first epoch; 4 + 1 blocks by epoch 10.
        assert_eq!(one, 40_000 + 300_000 + 4000);
        assert_eq!(ten, 40_000 + 5 * 300_000 + 4000);
        // The hash grid samples as NGLOD does.
        let hashgrid = TrainOptions {
            model: ModelKind::Hashgrid,
            ..nglod(10)
        };
        assert_eq!(planned_labels(&hashgrid, true, 1000), ten);
        let siren = |steps| TrainOptions {
            steps: Some(steps),
            ..TrainOptions::new(ModelKind::Siren, crate::run::Preset::Small)
        };
        assert_eq!(planned_labels(&siren(2), true, 0), 40_000 + 10_000);
        assert_eq!(
            planned_labels(&siren(1_000_000), true, 0),
            40_000 + sdf_nn::SirenTrainConfig::default().box_pool
        );
    }
}
