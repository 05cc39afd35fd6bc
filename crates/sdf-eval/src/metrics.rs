//! Inside/outside F1 and distance errors, the way the design document scores a model.
//!
//! The positive class is *inside* (signed distance < 0). F1 is computed from the confusion
//! counts of predicted against exact signs; where neither the truth nor the prediction has any
//! inside point there is nothing to get wrong, and F1 is 1.

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance, sample};
use sdf_nn::{GroundTruthError, Labeller};
use serde::{Deserialize, Serialize};

/// Default number of points in each evaluation set (the design document's 10^5).
pub const DEFAULT_EVAL_POINTS: usize = 100_000;
/// Seed of the evaluation sets. Training seeds are small integers; this one never collides.
pub const EVAL_SEED: u64 = 0x5EED_E7A1_0000_0001;
/// σ of the near-surface perturbation, as in the design document.
pub const NEAR_SURFACE_SIGMA: f32 = 0.01;

/// A point counts as clearly inside where the generalised winding number is at least this.
/// Closed meshes have w ≈ 1 inside; an open sheet only bends the winding number a little past
/// the sign threshold of 1/2 on its concave side (an open wavy sheet puts 0.7% of the box and
/// 21% of the near-surface points "inside" by sign alone), and a two-sided soup has w = 0.
pub const CLEAR_INSIDE_WINDING: f32 = 0.75;
/// A mesh with fewer than this fraction of the box points clearly inside...
pub const NO_INSIDE_BOX_FRACTION: f64 = 1e-3;
/// ...and fewer than this fraction of the near-surface points clearly inside has no inside to
/// score: it is flat, an open sheet or a two-sided triangle soup. The second bound keeps thin
/// closed shapes (a slab 1% as thick as it is wide) from being flagged.
pub const NO_INSIDE_NEAR_FRACTION: f64 = 1e-2;

/// Fraction of `truth` that is inside (negative).
pub fn inside_fraction(truth: &[f32]) -> f64 {
    truth.iter().filter(|&&d| d < 0.0).count() as f64 / truth.len().max(1) as f64
}

/// Fraction of `points` (labelled `truth` by `labels`) that are clearly inside: negative, with
/// a winding number of at least [`CLEAR_INSIDE_WINDING`]. Only the negative points pay for a
/// winding number.
///
/// # Errors
/// The labels' (the GPU failed).
pub fn clear_inside_fraction(
    labels: &Labeller<'_>,
    points: &[Vec3],
    truth: &[f32],
) -> Result<f64, GroundTruthError> {
    let inside: Vec<Vec3> = points
        .iter()
        .zip(truth)
        .filter(|&(_, &d)| d < 0.0)
        .map(|(p, _)| *p)
        .collect();
    let clear = labels
        .winding_number_batch(&inside)?
        .iter()
        .filter(|&&w| w >= CLEAR_INSIDE_WINDING)
        .count();
    Ok(clear as f64 / points.len().max(1) as f64)
}

/// A point is ambiguous, neither clearly inside nor clearly outside, where the generalised
/// winding number lies strictly between these bounds: open meshes (holes, missing caps, sheets)
/// bend it part of the way there, and the sign the ground truth gives (w ≥ 1/2) is then a
/// convention a model cannot be expected to learn. A closed mesh has w ≈ 0 or 1 everywhere off
/// its surface.
pub const AMBIGUOUS_WINDING: (f32, f32) = (0.2, 0.8);

/// Fraction of `winding` (the generalised winding numbers of a point set) that is ambiguous
/// ([`AMBIGUOUS_WINDING`]). Non-finite values do not count.
pub fn ambiguous_fraction(winding: &[f32]) -> f64 {
    let (lo, hi) = AMBIGUOUS_WINDING;
    let n = winding.iter().filter(|&&w| w > lo && w < hi).count();
    n as f64 / winding.len().max(1) as f64
}

/// The ambiguous fractions of the box and near-surface sets as summary lines print them:
/// `"ambiguous box 0.0%, near 12.3%"` (`n/a` for a missing one).
pub fn ambiguity_summary(bbox: Option<f64>, near: Option<f64>) -> String {
    let pct = |x: Option<f64>| x.map_or_else(|| "n/a".to_owned(), |v| format!("{:.1}%", v * 100.0));
    format!("ambiguous box {}, near {}", pct(bbox), pct(near))
}

/// Fraction of `truth` that is negative with a winding number (`winding`, of the same points)
/// of at least [`CLEAR_INSIDE_WINDING`]: [`clear_inside_fraction`] with the winding numbers
/// already known.
fn clear_fraction(truth: &[f32], winding: &[f32]) -> f64 {
    let clear = truth
        .iter()
        .zip(winding)
        .filter(|&(&d, &w)| d < 0.0 && w >= CLEAR_INSIDE_WINDING)
        .count();
    clear as f64 / truth.len().max(1) as f64
}

/// Why the inside class cannot be scored on a mesh with these fractions of box and
/// near-surface points clearly inside ([`clear_inside_fraction`]), or `None` if it can.
pub fn no_inside_reason(box_clear: f64, near_clear: f64) -> Option<String> {
    (box_clear < NO_INSIDE_BOX_FRACTION && near_clear < NO_INSIDE_NEAR_FRACTION).then(|| {
        format!(
            "the mesh has (almost) no inside: {:.3}% of the box points and {:.3}% of the \
             near-surface points are clearly inside (it is flat, an open sheet or a two-sided \
             triangle soup), so the F1 of the inside class is undefined",
            box_clear * 100.0,
            near_clear * 100.0
        )
    })
}

/// Why F1 is not reported for an unsigned distance field.
pub const UNSIGNED_REASON: &str =
    "unsigned distance field: no inside to score; see the distance errors and Chamfer distance";

/// Confusion counts of the inside class.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Confusion {
    /// Inside, predicted inside.
    pub true_pos: u64,
    /// Outside, predicted inside.
    pub false_pos: u64,
    /// Inside, predicted outside.
    pub false_neg: u64,
    /// Outside, predicted outside.
    pub true_neg: u64,
}

/// `(truly inside, predicted inside, exact distance)` for each point of predicted and exact
/// signed distances (same length): negative is inside, and a NaN prediction counts as outside,
/// never as a correct inside. The one rule [`Confusion`] and [`SignErrors`] count by.
fn signs<'a>(
    predicted: &'a [f32],
    truth: &'a [f32],
) -> impl Iterator<Item = (bool, bool, f32)> + 'a {
    assert_eq!(predicted.len(), truth.len(), "one prediction per point");
    predicted
        .iter()
        .zip(truth)
        .map(|(&p, &t)| (t < 0.0, p < 0.0, t))
}

impl Confusion {
    /// Counts from predicted and exact signed distances (same length).
    pub fn from_distances(predicted: &[f32], truth: &[f32]) -> Self {
        let mut c = Confusion::default();
        for (inside, predicted_inside, _) in signs(predicted, truth) {
            match (inside, predicted_inside) {
                (true, true) => c.true_pos += 1,
                (false, true) => c.false_pos += 1,
                (true, false) => c.false_neg += 1,
                (false, false) => c.true_neg += 1,
            }
        }
        c
    }

    /// F1 of the inside class; 1 when there is no inside point in truth or prediction.
    pub fn f1(&self) -> f64 {
        let denom = 2 * self.true_pos + self.false_pos + self.false_neg;
        if denom == 0 {
            1.0
        } else {
            (2 * self.true_pos) as f64 / denom as f64
        }
    }

    /// Fraction of points whose sign is right.
    pub fn accuracy(&self) -> f64 {
        let n = self.true_pos + self.false_pos + self.false_neg + self.true_neg;
        if n == 0 {
            1.0
        } else {
            (self.true_pos + self.true_neg) as f64 / n as f64
        }
    }
}

/// Sign errors counted by the exact distance of their points to the surface (normalised
/// units), in bands whose upper bounds are [`SIGN_ERROR_BANDS`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DepthBands {
    /// |d| ≤ 0.01 (the near-surface set's σ): the surface a little off.
    pub within_0_01: u64,
    /// 0.01 < |d| ≤ 0.05.
    pub within_0_05: u64,
    /// 0.05 < |d| ≤ 0.2.
    pub within_0_2: u64,
    /// |d| > 0.2: far from any surface, a region with the wrong sign (a spurious surface, or
    /// an inside the fit never carved).
    pub beyond_0_2: u64,
}

/// The upper bounds of [`DepthBands`]' first three bands.
pub const SIGN_ERROR_BANDS: [f32; 3] = [0.01, 0.05, 0.2];

impl DepthBands {
    fn add(&mut self, depth: f32) {
        let [a, b, c] = SIGN_ERROR_BANDS;
        match depth {
            d if d <= a => self.within_0_01 += 1,
            d if d <= b => self.within_0_05 += 1,
            d if d <= c => self.within_0_2 += 1,
            _ => self.beyond_0_2 += 1,
        }
    }

    /// Errors in every band.
    pub fn total(&self) -> u64 {
        self.within_0_01 + self.within_0_05 + self.within_0_2 + self.beyond_0_2
    }

    /// Errors farther than 0.05 from the surface: wrong regions rather than a surface a little
    /// off.
    pub fn beyond_0_05(&self) -> u64 {
        self.within_0_2 + self.beyond_0_2
    }
}

/// Where a set's sign errors lie: which way each is wrong, and how far its point is from the
/// surface. F1 says how many signs are wrong; this says what kind of failure they are. Errors
/// within 0.01 are the surface slightly displaced; far *false inside* points are spurious
/// surfaces in empty space; far *false outside* points are an inside the fit did not carve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SignErrors {
    /// Predicted inside where the point is outside (false positives of the inside class).
    pub false_inside: DepthBands,
    /// Predicted outside (or NaN) where the point is inside (false negatives).
    pub false_outside: DepthBands,
}

impl SignErrors {
    /// The errors of `predicted` against exact signed distances `truth` (same length), with
    /// [`Confusion::from_distances`]' rule: negative is inside, NaN counts as outside.
    pub fn from_distances(predicted: &[f32], truth: &[f32]) -> Self {
        let mut e = SignErrors::default();
        for (inside, predicted_inside, t) in signs(predicted, truth) {
            match (inside, predicted_inside) {
                (false, true) => e.false_inside.add(t.abs()),
                (true, false) => e.false_outside.add(t.abs()),
                _ => {}
            }
        }
        e
    }

    /// Every wrong sign.
    pub fn total(&self) -> u64 {
        self.false_inside.total() + self.false_outside.total()
    }
}

impl std::fmt::Display for DepthBands {
    /// `N (a / b / c / d by |d| ≤ 0.01, ≤ 0.05, ≤ 0.2, > 0.2)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({} / {} / {} / {} at |d| ≤ 0.01, ≤ 0.05, ≤ 0.2, > 0.2)",
            self.total(),
            self.within_0_01,
            self.within_0_05,
            self.within_0_2,
            self.beyond_0_2
        )
    }
}

impl std::fmt::Display for SignErrors {
    /// One line: the false inside and false outside counts by band.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "false inside {}, false outside {}",
            self.false_inside, self.false_outside
        )
    }
}

/// Mean and max of |predicted − exact|.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DistanceError {
    /// Mean absolute error.
    pub mean_abs: f64,
    /// Largest absolute error.
    pub max_abs: f64,
}

impl DistanceError {
    /// Errors of `predicted` against `truth`. A non-finite prediction makes both infinite.
    pub fn between(predicted: &[f32], truth: &[f32]) -> Self {
        assert_eq!(predicted.len(), truth.len(), "one prediction per point");
        if predicted.is_empty() {
            return DistanceError::default();
        }
        let (mut sum, mut max) = (0.0f64, 0.0f64);
        for (&p, &t) in predicted.iter().zip(truth) {
            let e = if p.is_finite() {
                (f64::from(p) - f64::from(t)).abs()
            } else {
                f64::INFINITY
            };
            sum += e;
            max = max.max(e);
        }
        DistanceError {
            mean_abs: sum / predicted.len() as f64,
            max_abs: max,
        }
    }
}

/// Points with their exact signed distances.
#[derive(Clone, Debug)]
pub struct EvalSet {
    /// Points in the normalised cube.
    pub points: Vec<Vec3>,
    /// Exact signed distances at `points`.
    pub truth: Vec<f32>,
}

/// The two evaluation sets of the design document, on a normalised mesh.
#[derive(Clone, Debug)]
pub struct EvalSets {
    /// Uniform in the bounding box `[-1, 1]³`.
    pub bbox: EvalSet,
    /// Poisson-disk surface samples perturbed by N(0, σ²), σ = 0.01.
    pub near_surface: EvalSet,
    /// Fractions of the box and near-surface sets clearly inside ([`clear_inside_fraction`]).
    pub clear_inside: (f64, f64),
    /// Fractions of the box and near-surface sets whose inside or outside is ambiguous
    /// ([`ambiguous_fraction`]).
    pub ambiguous: (f64, f64),
}

impl EvalSets {
    /// `n` points in each set, drawn with `seed`, labelled by `labels` (built on the same
    /// normalised `mesh`; on the CPU or the GPU, as the run chose).
    ///
    /// # Errors
    /// The labels' (the GPU failed).
    pub fn new(
        mesh: &Mesh,
        labels: &Labeller<'_>,
        n: usize,
        seed: u64,
    ) -> Result<Self, GroundTruthError> {
        let bbox = sample::uniform_box(n, seed);
        let near = sample::perturb(
            &sample::poisson_disk(mesh, n, seed ^ 0x9E37_79B9)
                .samples
                .points,
            NEAR_SURFACE_SIGMA,
            seed ^ 0x7F4A_7C15,
        );
        let (tb, tn) = (
            labels.signed_distance_batch(&bbox)?,
            labels.signed_distance_batch(&near)?,
        );
        // Every point's winding number: the clear inside and the ambiguous fractions.
        let (wb, wn) = (
            labels.winding_number_batch(&bbox)?,
            labels.winding_number_batch(&near)?,
        );
        Ok(EvalSets {
            clear_inside: (clear_fraction(&tb, &wb), clear_fraction(&tn, &wn)),
            ambiguous: (ambiguous_fraction(&wb), ambiguous_fraction(&wn)),
            bbox: EvalSet {
                truth: tb,
                points: bbox,
            },
            near_surface: EvalSet {
                truth: tn,
                points: near,
            },
        })
    }

    /// Scores a model given as a batch prediction function (normalised coordinates in,
    /// normalised signed distances out).
    pub fn score<E>(
        &self,
        mut predict: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
    ) -> Result<Scores, E> {
        let pb = predict(&self.bbox.points)?;
        let pn = predict(&self.near_surface.points)?;
        let s = Scores::from_predictions(&pb, &self.bbox.truth, &pn, &self.near_surface.truth)
            .with_ambiguity(self.ambiguous);
        Ok(match self.no_inside_reason() {
            Some(reason) => s.without_f1(reason),
            None => s,
        })
    }

    /// [`EvalSets::score`] for a model of the unsigned distance ([`Scores::unsigned`]).
    pub fn score_unsigned<E>(
        &self,
        mut predict: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
    ) -> Result<Scores, E> {
        let pb = predict(&self.bbox.points)?;
        let pn = predict(&self.near_surface.points)?;
        Ok(
            Scores::unsigned(&pb, &self.bbox.truth, &pn, &self.near_surface.truth)
                .with_ambiguity(self.ambiguous),
        )
    }

    /// Why F1 is undefined on this mesh ([`no_inside_reason`]), or `None`.
    pub fn no_inside_reason(&self) -> Option<String> {
        no_inside_reason(self.clear_inside.0, self.clear_inside.1)
    }
}

/// What [`EvalSets::score`] reports.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// F1 of the inside class on the box set (`None` when undefined: see `f1_null_reason`).
    pub f1_bbox: Option<f64>,
    /// F1 of the inside class on the near-surface set.
    pub f1_near_surface: Option<f64>,
    /// Mean of the two, the design document's per-mesh figure.
    pub f1_mean: Option<f64>,
    /// Why the F1 fields are null: a mesh without an inside, or an unsigned field.
    pub f1_null_reason: Option<String>,
    /// Sign accuracy on the box set (`None` for an unsigned field).
    pub sign_accuracy_bbox: Option<f64>,
    /// Sign accuracy on the near-surface set.
    pub sign_accuracy_near_surface: Option<f64>,
    /// Where the box set's sign errors lie (`None` for an unsigned field).
    #[serde(default)]
    pub sign_errors_bbox: Option<SignErrors>,
    /// Where the near-surface set's sign errors lie.
    #[serde(default)]
    pub sign_errors_near_surface: Option<SignErrors>,
    /// Fraction of the box set inside the mesh (exact).
    pub inside_fraction_bbox: f64,
    /// Fraction of the near-surface set inside the mesh (exact).
    pub inside_fraction_near_surface: f64,
    /// |Φ − SDF| near the surface, in normalised units (|Φ − |SDF|| for an unsigned field).
    pub near_surface_error: DistanceError,
    /// |Φ − SDF| on the box set, in normalised units.
    pub bbox_error: DistanceError,
    /// Fraction of the box set whose inside or outside is ambiguous (winding number strictly
    /// between [`AMBIGUOUS_WINDING`]'s bounds: open meshes), which explains a low F1 (`None`
    /// where the scores were made without winding numbers).
    #[serde(default)]
    pub ambiguous_bbox: Option<f64>,
    /// The same fraction of the near-surface set.
    #[serde(default)]
    pub ambiguous_near_surface: Option<f64>,
}

impl Scores {
    /// Scores from predictions and truths of both sets.
    pub fn from_predictions(
        pred_bbox: &[f32],
        truth_bbox: &[f32],
        pred_near: &[f32],
        truth_near: &[f32],
    ) -> Self {
        let cb = Confusion::from_distances(pred_bbox, truth_bbox);
        let cn = Confusion::from_distances(pred_near, truth_near);
        Scores {
            f1_bbox: Some(cb.f1()),
            f1_near_surface: Some(cn.f1()),
            f1_mean: Some(0.5 * (cb.f1() + cn.f1())),
            f1_null_reason: None,
            sign_accuracy_bbox: Some(cb.accuracy()),
            sign_accuracy_near_surface: Some(cn.accuracy()),
            sign_errors_bbox: Some(SignErrors::from_distances(pred_bbox, truth_bbox)),
            sign_errors_near_surface: Some(SignErrors::from_distances(pred_near, truth_near)),
            inside_fraction_bbox: inside_fraction(truth_bbox),
            inside_fraction_near_surface: inside_fraction(truth_near),
            near_surface_error: DistanceError::between(pred_near, truth_near),
            bbox_error: DistanceError::between(pred_bbox, truth_bbox),
            ambiguous_bbox: None,
            ambiguous_near_surface: None,
        }
    }

    /// These scores with the ambiguous fractions of the box and near-surface sets
    /// ([`EvalSets::ambiguous`]).
    pub fn with_ambiguity(self, (bbox, near): (f64, f64)) -> Self {
        Scores {
            ambiguous_bbox: Some(bbox),
            ambiguous_near_surface: Some(near),
            ..self
        }
    }

    /// These scores with the F1 fields null, for `reason` (a mesh without an inside); sign
    /// accuracy and distance errors stay.
    pub fn without_f1(self, reason: String) -> Self {
        Scores {
            f1_bbox: None,
            f1_near_surface: None,
            f1_mean: None,
            f1_null_reason: Some(reason),
            ..self
        }
    }

    /// Scores of an unsigned field Φ ≈ |d| against the signed truths: distance errors against
    /// |d|; no F1, no sign accuracy.
    pub fn unsigned(
        pred_bbox: &[f32],
        truth_bbox: &[f32],
        pred_near: &[f32],
        truth_near: &[f32],
    ) -> Self {
        let abs = |t: &[f32]| t.iter().map(|d| d.abs()).collect::<Vec<f32>>();
        Scores {
            f1_bbox: None,
            f1_near_surface: None,
            f1_mean: None,
            f1_null_reason: Some(UNSIGNED_REASON.into()),
            sign_accuracy_bbox: None,
            sign_accuracy_near_surface: None,
            sign_errors_bbox: None,
            sign_errors_near_surface: None,
            inside_fraction_bbox: inside_fraction(truth_bbox),
            inside_fraction_near_surface: inside_fraction(truth_near),
            near_surface_error: DistanceError::between(pred_near, &abs(truth_near)),
            bbox_error: DistanceError::between(pred_bbox, &abs(truth_bbox)),
            ambiguous_bbox: None,
            ambiguous_near_surface: None,
        }
    }
}

/// How close an extracted mesh is to the original: symmetric Chamfer-L1 distance and normal
/// consistency, from area-uniform samples on each surface matched to the closest point of the
/// other (exact BVH queries, not nearest samples).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceMetrics {
    /// ½ (mean distance from extracted to original + mean distance from original to
    /// extracted), in the units of the meshes given.
    pub chamfer_l1: f64,
    /// Mean |n_a · n_b| over both directions, where n_b is the normal of the other mesh's
    /// triangle at the closest point; 1 for identical surfaces. Orientation-insensitive.
    pub normal_consistency: f64,
    /// Samples on each surface.
    pub samples: usize,
}

impl SurfaceMetrics {
    /// Compares `extracted` with `original` (whose signed distance `to_original` is) using
    /// `samples` points on each.
    pub fn between(
        extracted: &Mesh,
        original: &Mesh,
        to_original: &SignedDistance,
        samples: usize,
        seed: u64,
    ) -> Result<Self, sdf_geom::GeomError> {
        let to_extracted = SignedDistance::new(extracted)?;
        let (d_ab, n_ab) = one_way(extracted, original, to_original, samples, seed);
        let (d_ba, n_ba) = one_way(original, extracted, &to_extracted, samples, seed ^ 0xA5A5);
        Ok(SurfaceMetrics {
            chamfer_l1: 0.5 * (d_ab + d_ba),
            normal_consistency: 0.5 * (n_ab + n_ba),
            samples,
        })
    }
}

/// Mean distance and mean |normal dot| from samples on `from` to the closest points on `to`.
fn one_way(from: &Mesh, to: &Mesh, to_sdf: &SignedDistance, n: usize, seed: u64) -> (f64, f64) {
    use rayon::prelude::*;
    let s = sample::surface(from, n, seed);
    if s.points.is_empty() {
        return (f64::INFINITY, 0.0);
    }
    let (dist, dot): (f64, f64) = s
        .points
        .par_iter()
        .zip(&s.normals)
        .map(|(&p, &n)| {
            let c = to_sdf.closest_point(p);
            let tn = to
                .corners(&to.triangles[c.triangle as usize])
                .map(|[a, b, c]| (b - a).cross(c - a).normalize_or_zero())
                .unwrap_or(Vec3::ZERO);
            (f64::from(c.distance), f64::from(n.dot(tn).abs()))
        })
        .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    let k = s.points.len() as f64;
    (dist / k, dot / k)
}

#[cfg(test)]
mod tests {
    /// `sdf`'s labels on the CPU.
    fn cpu(sdf: &SignedDistance) -> sdf_nn::Labeller<'static> {
        sdf_nn::Labeller::cpu(std::sync::Arc::new(sdf.clone()))
    }

    use super::*;

    #[test]
    fn f1_on_hand_made_cases() {
        // truth: 3 inside, 3 outside. prediction: 2 of the insides right, 1 outside wrong.
        let truth = [-1.0, -0.5, -0.1, 0.2, 0.3, 1.0];
        let pred = [-0.9, -0.4, 0.05, -0.1, 0.3, 0.8];
        let c = Confusion::from_distances(&pred, &truth);
        assert_eq!(
            c,
            Confusion {
                true_pos: 2,
                false_pos: 1,
                false_neg: 1,
                true_neg: 2
            }
        );
        // precision 2/3, recall 2/3 -> F1 2/3
        assert!((c.f1() - 2.0 / 3.0).abs() < 1e-12);
        assert!((c.accuracy() - 4.0 / 6.0).abs() < 1e-12);

        let perfect = Confusion::from_distances(&truth, &truth);
        assert_eq!(perfect.f1(), 1.0);
        // Everything predicted outside: no true positives.
        assert_eq!(Confusion::from_distances(&[1.0; 6], &truth).f1(), 0.0);
        // Nothing inside anywhere: nothing to get wrong.
        assert_eq!(
            Confusion::from_distances(&[1.0, 2.0], &[0.5, 0.1]).f1(),
            1.0
        );
        // Zero is the surface: counted outside, as the "< 0 is inside" rule says.
        assert_eq!(Confusion::from_distances(&[0.0], &[-1.0]).false_neg, 1);
    }

    #[test]
    fn sign_errors_by_depth() {
        // Exact distances in each band on both sides; predictions wrong on some of them.
        let truth = [
            0.005, 0.03, 0.1, 0.5, // outside: one per band
            -0.01, -0.05, -0.2, -0.9, // inside: each at a band's upper bound, then beyond
            0.3, -0.3, // right
        ];
        // Three false inside (bands 0.01, 0.05 and beyond), four false outside (NaN and 0
        // among them), two right.
        let nan = f32::NAN;
        let pred = [-0.1, -0.1, 0.2, -0.4, 0.1, nan, 0.0, 0.1, 0.3, -0.3];
        let e = SignErrors::from_distances(&pred, &truth);
        assert_eq!(
            e.false_inside,
            DepthBands {
                within_0_01: 1,
                within_0_05: 1,
                within_0_2: 0,
                beyond_0_2: 1
            }
        );
        assert_eq!(
            e.false_outside,
            DepthBands {
                within_0_01: 1,
                within_0_05: 1,
                within_0_2: 1,
                beyond_0_2: 1
            }
        );
        assert_eq!(e.false_inside.beyond_0_05(), 1);
        // The same errors the confusion counts, and the accuracy they imply.
        let c = Confusion::from_distances(&pred, &truth);
        assert_eq!(e.false_inside.total(), c.false_pos);
        assert_eq!(e.false_outside.total(), c.false_neg);
        let s = Scores::from_predictions(&pred, &truth, &truth, &truth);
        assert_eq!(s.sign_errors_bbox, Some(e));
        assert_eq!(s.sign_errors_near_surface.unwrap().total(), 0);
        let n = truth.len() as f64;
        assert!((s.sign_accuracy_bbox.unwrap() - (n - e.total() as f64) / n).abs() < 1e-12);
        assert_eq!(
            Scores::unsigned(&pred, &truth, &pred, &truth).sign_errors_bbox,
            None
        );
        // NaN is never a correct inside.
        assert_eq!(Confusion::from_distances(&[f32::NAN], &[-1.0]).false_neg, 1);
    }

    #[test]
    fn f1_is_asymmetric_in_the_inside_class() {
        // Same sign accuracy, different F1: F1 only looks at the inside class.
        let truth = [-1.0, 1.0, 1.0, 1.0];
        let a = Confusion::from_distances(&[1.0, 1.0, 1.0, 1.0], &truth);
        let b = Confusion::from_distances(&[-1.0, -1.0, 1.0, 1.0], &truth);
        assert_eq!(a.accuracy(), 0.75);
        assert_eq!(b.accuracy(), 0.75);
        assert_eq!(a.f1(), 0.0);
        assert!((b.f1() - 2.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn distance_error() {
        let e = DistanceError::between(&[0.1, -0.2, 0.5], &[0.0, 0.0, 0.5]);
        assert!((e.mean_abs - 0.1).abs() < 1e-7 && (e.max_abs - 0.2).abs() < 1e-7);
        assert!(
            DistanceError::between(&[f32::NAN], &[0.0])
                .max_abs
                .is_infinite()
        );
    }

    fn unit_cube() -> Mesh {
        sdf_geom::Mesh::from_raw(
            (0..8)
                .map(|i| Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32))
                .collect(),
            vec![
                [0, 2, 1],
                [1, 2, 3],
                [4, 5, 6],
                [5, 7, 6],
                [0, 1, 4],
                [1, 5, 4],
                [2, 6, 3],
                [3, 6, 7],
                [0, 4, 2],
                [2, 4, 6],
                [1, 3, 5],
                [3, 7, 5],
            ],
        )
        .unwrap()
        .0
    }

    #[test]
    fn surface_metrics_of_identical_and_shifted_meshes() {
        let cube = unit_cube();
        let to_cube = SignedDistance::new(&cube).unwrap();
        let same = SurfaceMetrics::between(&cube, &cube, &to_cube, 2000, 1).unwrap();
        assert!(same.chamfer_l1 < 1e-6, "{same:?}");
        assert!((same.normal_consistency - 1.0).abs() < 1e-6, "{same:?}");
        // A copy shifted by 0.1 along x: the x faces are 0.1 apart; other faces mostly overlap.
        let shifted = sdf_geom::Mesh {
            vertices: cube.vertices.iter().map(|v| *v + Vec3::X * 0.1).collect(),
            triangles: cube.triangles.clone(),
        };
        let m = SurfaceMetrics::between(&shifted, &cube, &to_cube, 4000, 2).unwrap();
        // Each direction: the 2 x faces (1/3 of the area) are 0.1 away, the rest 0 (overlap)
        // except the 0.1-wide strip that sticks out: expected about 0.1/3 + small.
        assert!(m.chamfer_l1 > 0.03 && m.chamfer_l1 < 0.05, "{m:?}");
        // Near the edges of the inner x face the closest point is on a perpendicular face
        // (|n·n'| = 0): about 0.36 of that face, a sixth of the area, so roughly 0.9, not 1.
        assert!(
            m.normal_consistency > 0.8 && m.normal_consistency < 0.95,
            "{m:?}"
        );
    }

    #[test]
    fn eval_sets_on_a_cube_score_the_exact_sdf_perfectly() {
        let (unit, _) = unit_cube().normalized();
        let sdf = SignedDistance::new(&unit).unwrap();
        let sets = EvalSets::new(&unit, &cpu(&sdf), 2000, EVAL_SEED).unwrap();
        assert_eq!(sets.bbox.points.len(), 2000);
        // The normalised cube fills the box: almost every box point is inside.
        let inside = sets.bbox.truth.iter().filter(|&&d| d < 0.0).count();
        assert!(inside > 1900, "{inside}");
        // Near-surface points straddle the surface.
        let near_inside = sets.near_surface.truth.iter().filter(|&&d| d < 0.0).count();
        assert!((600..1400).contains(&near_inside), "{near_inside}");
        // The exact SDF scores 1; a constant "outside" model scores 0.
        let exact = sets
            .score(|p| Ok::<_, ()>(sdf.signed_distance_batch(p)))
            .unwrap();
        assert_eq!(exact.f1_mean, Some(1.0));
        assert_eq!(exact.f1_null_reason, None);
        assert_eq!(exact.near_surface_error.max_abs, 0.0);
        let outside = sets.score(|p| Ok::<_, ()>(vec![1.0; p.len()])).unwrap();
        assert_eq!(outside.f1_bbox, Some(0.0));
        // Deterministic for a seed, different for another.
        let again = EvalSets::new(&unit, &cpu(&sdf), 2000, EVAL_SEED).unwrap();
        assert_eq!(again.near_surface.points, sets.near_surface.points);
        let other = EvalSets::new(&unit, &cpu(&sdf), 2000, EVAL_SEED + 1).unwrap();
        assert_ne!(other.bbox.points, sets.bbox.points);
    }

    /// A grid of `n`×`n` quads over [-1, 1]² lifted by `z(x, y)`: an open sheet.
    fn sheet(n: u32, z: impl Fn(f32, f32) -> f32) -> Mesh {
        let mut v = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (
                    i as f32 / n as f32 * 2.0 - 1.0,
                    j as f32 / n as f32 * 2.0 - 1.0,
                );
                v.push(Vec3::new(x, y, z(x, y)));
            }
        }
        let mut t = Vec::new();
        let id = |i: u32, j: u32| j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                t.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
                t.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
            }
        }
        Mesh::from_raw(v, t).unwrap().0
    }

    /// Every face stored twice, once per orientation: the winding number is 0 everywhere.
    fn two_sided(m: &Mesh) -> Mesh {
        let mut t = m.triangles.clone();
        t.extend(m.triangles.iter().map(|&[a, b, c]| [a, c, b]));
        Mesh::from_raw(m.vertices.clone(), t).unwrap().0
    }

    fn reason(m: &Mesh) -> (Option<String>, f64, f64) {
        let (unit, _) = m.normalized();
        let sdf = SignedDistance::new(&unit).unwrap();
        let sets = EvalSets::new(&unit, &cpu(&sdf), 5000, EVAL_SEED).unwrap();
        (
            sets.no_inside_reason(),
            sets.clear_inside.0,
            sets.clear_inside.1,
        )
    }

    #[test]
    fn meshes_without_an_inside_are_detected() {
        let flat = sheet(8, |_, _| 0.0);
        let wavy = sheet(16, |x, y| 0.15 * (2.0 * x).sin() * (1.5 * y).cos());
        let soup = two_sided(&Mesh::icosphere(0.8, 2));
        for (name, m) in [("flat", &flat), ("open wavy", &wavy), ("two-sided", &soup)] {
            let (r, b, n) = reason(m);
            eprintln!("{name}: box {b:.5}, near {n:.5}");
            assert!(r.is_some(), "{name}: box {b}, near {n}");
        }
        // Closed shapes, thin ones included, have an inside.
        let slab = {
            let (cube, _) = unit_cube().normalized();
            Mesh {
                vertices: cube
                    .vertices
                    .iter()
                    .map(|v| Vec3::new(v.x, v.y, v.z * 0.01))
                    .collect(),
                triangles: cube.triangles.clone(),
            }
        };
        for (name, m) in [("sphere", &Mesh::icosphere(0.8, 2)), ("slab", &slab)] {
            let (r, b, n) = reason(m);
            eprintln!("{name}: box {b:.5}, near {n:.5}");
            assert!(r.is_none(), "{name}: {r:?}");
        }
        // Scores of a mesh without an inside: no F1, with the reason; sign accuracy and errors.
        let (unit, _) = flat.normalized();
        let sdf = SignedDistance::new(&unit).unwrap();
        let sets = EvalSets::new(&unit, &cpu(&sdf), 2000, EVAL_SEED).unwrap();
        let s = sets
            .score(|p| Ok::<_, ()>(sdf.signed_distance_batch(p)))
            .unwrap();
        assert_eq!(
            (s.f1_bbox, s.f1_near_surface, s.f1_mean),
            (None, None, None)
        );
        assert!(s.f1_null_reason.as_deref().unwrap().contains("no inside"));
        assert_eq!(s.sign_accuracy_bbox, Some(1.0));
        assert_eq!(s.near_surface_error.max_abs, 0.0);
        // An unsigned model is scored against |d|: the exact |d| has no error.
        let u = sets
            .score_unsigned(|p| {
                Ok::<_, ()>(
                    sdf.signed_distance_batch(p)
                        .iter()
                        .map(|d| d.abs())
                        .collect(),
                )
            })
            .unwrap();
        assert_eq!(u.f1_null_reason.as_deref(), Some(UNSIGNED_REASON));
        assert_eq!(u.sign_accuracy_bbox, None);
        assert_eq!(u.bbox_error.max_abs, 0.0);
    }

    /// The ambiguous fractions (winding number between 0.2 and 0.8) are 0 on a closed mesh
    /// (spot) and large on an open one (lilium's petals are open sheets), and the scores carry
    /// them.
    #[test]
    fn ambiguity_is_nil_on_a_closed_mesh_and_not_on_an_open_one() {
        for (name, closed) in [("spot.obj", true), ("lilium.obj", false)] {
            let path = format!("{}/../../tests/data/{name}", env!("CARGO_MANIFEST_DIR"));
            let unit = sdf_geom::load_mesh(&path).unwrap().0.normalized().0;
            let sdf = SignedDistance::new(&unit).unwrap();
            let sets = EvalSets::new(&unit, &cpu(&sdf), 4000, EVAL_SEED).unwrap();
            let (b, n) = sets.ambiguous;
            eprintln!("{name}: ambiguous box {b}, near surface {n}");
            if closed {
                assert!(b < 1e-3 && n < 1e-3, "{name}: {b} {n}");
            } else {
                // Measured (4000 points each): 30 % of the box, 49 % near the surface.
                assert!(b > 0.1 && n > 0.1, "{name}: {b} {n}");
            }
            let s = sets
                .score(|p| Ok::<_, ()>(sdf.signed_distance_batch(p)))
                .unwrap();
            assert_eq!(
                (s.ambiguous_bbox, s.ambiguous_near_surface),
                (Some(b), Some(n))
            );
        }
        assert_eq!(
            ambiguous_fraction(&[0.0, 0.2, 0.21, 0.5, 0.79, 0.8, 1.0]),
            3.0 / 7.0
        );
        assert_eq!(
            ambiguity_summary(Some(0.0), Some(0.1234)),
            "ambiguous box 0.0%, near 12.3%"
        );
    }
}
