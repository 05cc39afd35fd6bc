//! The JSON report of one run (`train`'s, and each `corpus` entry's).

use std::path::Path;

use sdf_nn::model_file::write_atomic;
use sdf_nn::{DistanceMode, GroundTruthPath};
use serde::{Deserialize, Serialize};

use super::{Evaluation, RunError, TrainOptions, Trained};

/// The JSON report of `train` (and of each `corpus` entry).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    /// Mesh file.
    pub mesh: String,
    /// `"siren"`, `"nglod"` or `"hashgrid"`.
    pub model: String,
    /// `"default"` or `"small"`.
    pub preset: String,
    /// The model's hyperparameters as its file records them (the preset's, or the
    /// [`NglodArchitecture`](super::NglodArchitecture) asked for over it).
    #[serde(default)]
    pub architecture: serde_json::Value,
    /// Parameter count.
    pub params: usize,
    /// Model file size in bytes.
    pub file_bytes: u64,
    /// F1 of the inside class, uniform box points (null when undefined: `f1_null_reason`).
    pub f1_bbox: Option<f64>,
    /// F1 of the inside class, near-surface points.
    pub f1_near_surface: Option<f64>,
    /// Mean of the two.
    pub f1_mean: Option<f64>,
    /// Why the F1 fields are null: a mesh without an inside, or an unsigned field.
    #[serde(default)]
    pub f1_null_reason: Option<String>,
    /// Fraction of the box points whose inside or outside is ambiguous: generalised winding
    /// number strictly between 0.2 and 0.8 (open meshes; see
    /// [`AMBIGUOUS_WINDING`](crate::metrics::AMBIGUOUS_WINDING)). A large one explains a low F1
    /// (null in reports written before it was recorded).
    #[serde(default)]
    pub ambiguous_bbox: Option<f64>,
    /// The same fraction of the near-surface points.
    #[serde(default)]
    pub ambiguous_near_surface: Option<f64>,
    /// `"signed"` or `"unsigned"`: what the model fits.
    #[serde(default)]
    pub distance: Option<DistanceMode>,
    /// Sign accuracy, box points (null for an unsigned field).
    pub sign_accuracy_bbox: Option<f64>,
    /// Sign accuracy, near-surface points.
    pub sign_accuracy_near_surface: Option<f64>,
    /// Where the box points' sign errors lie: which way each is wrong and how far from the
    /// surface (null for an unsigned field, and in reports written before it existed).
    #[serde(default)]
    pub sign_errors_bbox: Option<crate::SignErrors>,
    /// Where the near-surface points' sign errors lie.
    #[serde(default)]
    pub sign_errors_near_surface: Option<crate::SignErrors>,
    /// Exact fraction of the box points inside the mesh.
    #[serde(default)]
    pub inside_fraction_bbox: f64,
    /// Mean |Φ − SDF| on the box points, normalised units (|Φ − |SDF|| for an unsigned field).
    #[serde(default)]
    pub bbox_mean_abs_error: f64,
    /// Unsigned fields: symmetric Chamfer-L1 distance between the mesh and the extracted
    /// level set Φ = [`UNSIGNED_LEVEL`](super::UNSIGNED_LEVEL) (normalised units; an exact |d| scores about that level).
    #[serde(default)]
    pub chamfer_l1: Option<f64>,
    /// Mean |Φ − SDF| near the surface, normalised units.
    pub near_surface_mean_abs_error: f64,
    /// Max |Φ − SDF| near the surface, normalised units.
    pub near_surface_max_abs_error: f64,
    /// Median wall time per point of a 50000-point batch through `NeuralSdf::eval_normalized`
    /// (upload, kernels, readback, host work), ns.
    pub per_point_ns: f64,
    /// Median wall time of a 3000-point batch through `NeuralSdf::eval_normalized`, µs.
    pub batch3000_us: f64,
    /// Kernel time per point of the 50000 batch from GPU timestamps (separate, timed calls),
    /// where the adapter has them, ns.
    pub gpu_per_point_ns: Option<f64>,
    /// Kernel time of the 3000 batch from GPU timestamps (separate, timed calls), µs.
    #[serde(default)]
    pub gpu_batch3000_us: Option<f64>,
    /// Repetitions behind each latency median, at least (fewer for a batch that has taken 10 s:
    /// `timing::SLOW_AFTER`); null in reports written before it existed.
    #[serde(default)]
    pub latency_reps: Option<usize>,
    /// Training wall time, s.
    pub train_seconds: f64,
    /// Steps (SIREN) or epochs (NGLOD, the hash grid) run.
    pub trained: usize,
    /// Final training loss: null where the run read none (a SIREN run shorter than one loss
    /// window), which a report written as NaN could not be read back from.
    #[serde(default)]
    pub final_loss: Option<f32>,
    /// Learning rate at the end of training (null in reports written before it existed).
    #[serde(default)]
    pub final_lr: Option<f32>,
    /// Points per evaluation set.
    pub eval_points: usize,
    /// Adapter the run used.
    pub adapter: String,
    /// Where the labels (training samples, evaluation sets) were computed: `"gpu"` or `"cpu"`
    /// (null in reports written before it was recorded).
    #[serde(default)]
    pub ground_truth: Option<GroundTruthPath>,
    /// hwsdf version.
    pub hwsdf_version: String,
    /// Training details (e.g. NGLOD's GPU/sampling time split).
    pub training: serde_json::Value,
}

impl Report {
    /// The ambiguous fractions as summary lines print them: `"ambiguous box 0.0%, near 12.3%"`
    /// (`n/a` where not recorded).
    pub fn ambiguity_summary(&self) -> String {
        crate::metrics::ambiguity_summary(self.ambiguous_bbox, self.ambiguous_near_surface)
    }

    /// Assembles a report.
    pub fn new(
        mesh: &Path,
        options: &TrainOptions,
        trained: &Trained,
        file_bytes: u64,
        eval: &Evaluation,
        adapter: String,
        ground_truth: GroundTruthPath,
    ) -> Self {
        let s = &eval.scores;
        Report {
            mesh: mesh.display().to_string(),
            model: options.model.name().into(),
            preset: options.preset.name().into(),
            architecture: trained.file.metadata.config.clone(),
            params: trained.file.param_count(),
            file_bytes,
            f1_bbox: s.f1_bbox,
            f1_near_surface: s.f1_near_surface,
            f1_mean: s.f1_mean,
            f1_null_reason: s.f1_null_reason.clone(),
            ambiguous_bbox: s.ambiguous_bbox,
            ambiguous_near_surface: s.ambiguous_near_surface,
            distance: Some(options.distance),
            sign_accuracy_bbox: s.sign_accuracy_bbox,
            sign_accuracy_near_surface: s.sign_accuracy_near_surface,
            sign_errors_bbox: s.sign_errors_bbox,
            sign_errors_near_surface: s.sign_errors_near_surface,
            inside_fraction_bbox: s.inside_fraction_bbox,
            bbox_mean_abs_error: s.bbox_error.mean_abs,
            chamfer_l1: eval.chamfer.map(|c| c.chamfer_l1),
            near_surface_mean_abs_error: s.near_surface_error.mean_abs,
            near_surface_max_abs_error: s.near_surface_error.max_abs,
            per_point_ns: eval.latency.per_point_ns,
            batch3000_us: eval.latency.batch3000_us,
            gpu_per_point_ns: eval.latency.gpu_per_point_ns,
            gpu_batch3000_us: eval.latency.gpu_batch3000_us,
            latency_reps: Some(eval.latency.reps),
            train_seconds: trained.train_seconds,
            trained: trained.done,
            final_loss: Some(trained.final_loss).filter(|l| l.is_finite()),
            final_lr: Some(trained.lr),
            eval_points: eval.eval_points,
            adapter,
            ground_truth: Some(ground_truth),
            hwsdf_version: sdf_nn::model_file::HWSDF_VERSION.into(),
            training: trained.details.clone(),
        }
    }

    /// Writes the report as pretty JSON, atomically.
    pub fn write(&self, path: &Path) -> Result<(), RunError> {
        let json = serde_json::to_vec_pretty(self).expect("report serialises");
        write_atomic(path, &json).map_err(|source| RunError::Write {
            path: path.to_owned(),
            source,
        })
    }
}
