//! Scoring a trained model against its ground truth (F1, distance errors, latency, and for an
//! unsigned field the Chamfer distance of its level set), and extracting its surface.

use glam::Vec3;
use sdf_geom::Mesh;
use sdf_geom::extract::{ExtractError, ExtractOptions, ExtractStats, extract_surface};
use sdf_nn::{DistanceMode, GpuContext, ModelFile, NeuralSdf};
use serde::{Deserialize, Serialize};

use super::{GroundTruth, RunError};
use crate::metrics::{EVAL_SEED, EvalSets, Scores};
use crate::timing::{Latency, MEASURE_FOR, WARM_UP, measure_latency_timed};

/// Memory an evaluation holds per point of `--points` / `--eval-points`, in bytes: the two sets'
/// points and truths, the Poisson-disk candidates of the near-surface set, predictions, and the
/// GPU's buffers (host memory on a CPU adapter). Measured with `eval --surface-resolution 0` on
/// lavapipe: peak RSS 295 MB at 2·10^5 points and 1168 MB at 10^6, 1.09 kB per point; rounded up.
pub const EVAL_BYTES_PER_POINT: u64 = 1200;

/// Memory budget of one evaluation, in bytes (4 GiB).
pub const EVAL_MEMORY_BUDGET: u64 = 4 << 30;

/// Refuses, before any work, an evaluation of empty sets, or of sets that would pass
/// [`EVAL_MEMORY_BUDGET`] (with the estimate).
pub fn check_eval_points(points: usize) -> Result<(), RunError> {
    if points == 0 {
        return Err(RunError::Options(
            "the evaluation sets need at least 1 point".into(),
        ));
    }
    let need = (points as u64).saturating_mul(EVAL_BYTES_PER_POINT);
    if need > EVAL_MEMORY_BUDGET {
        return Err(RunError::OverBudget {
            what: format!("evaluating on {points} points per set"),
            need,
            budget: EVAL_MEMORY_BUDGET,
            hint: format!(
                "use at most {} points",
                EVAL_MEMORY_BUDGET / EVAL_BYTES_PER_POINT
            ),
        });
    }
    Ok(())
}

/// Evaluation results of one model on one mesh.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Evaluation {
    /// F1 and distance errors.
    pub scores: Scores,
    /// Latency.
    pub latency: Latency,
    /// Points in each evaluation set.
    pub eval_points: usize,
    /// Unsigned fields: the mesh against the level set Φ = [`UNSIGNED_LEVEL`].
    pub chamfer: Option<crate::metrics::SurfaceMetrics>,
}

/// The level set of an unsigned field that stands for its surface (|d| has no zero crossing for
/// marching cubes to find): one cell of the [`UNSIGNED_EXTRACT_RESOLUTION`] grid, in normalised
/// units.
pub const UNSIGNED_LEVEL: f32 = 2.0 / UNSIGNED_EXTRACT_RESOLUTION as f32;
/// Cells per axis of the extraction behind an unsigned field's Chamfer distance.
pub const UNSIGNED_EXTRACT_RESOLUTION: u32 = 128;

/// Whether a model file holds an unsigned distance field (`training.distance`).
pub fn is_unsigned(file: &ModelFile) -> bool {
    file.metadata
        .training
        .get("distance")
        .and_then(|d| d.as_str())
        == Some(DistanceMode::Unsigned.name())
}

/// Scores and times `model` against `truth`, the exact SDF of the normalised mesh; an unsigned
/// field also gets the Chamfer distance of its level set at [`UNSIGNED_EXTRACT_RESOLUTION`].
pub fn evaluate(
    gpu: &GpuContext,
    model: &NeuralSdf,
    truth: &GroundTruth,
    points: usize,
) -> Result<Evaluation, RunError> {
    let mut evaluation = evaluate_scores(gpu, model, truth, points)?;
    if is_unsigned(model.model_file()) {
        let options = ExtractOptions::new(UNSIGNED_EXTRACT_RESOLUTION);
        let (level_set, _) = extract_mesh_normalized(gpu, model, &options)?;
        // An empty level set (the model never gets that close to 0) has no Chamfer distance.
        evaluation.chamfer = crate::metrics::SurfaceMetrics::between(
            &level_set,
            &truth.mesh,
            truth.sdf(),
            points.min(20_000),
            EVAL_SEED,
        )
        .ok();
    }
    Ok(evaluation)
}

/// [`evaluate`] without any surface: the scores and the latency only (`chamfer` is `None`), for
/// callers that extract the surface at a resolution of their own (`eval
/// --surface-resolution`), or none.
pub fn evaluate_scores(
    gpu: &GpuContext,
    model: &NeuralSdf,
    truth: &GroundTruth,
    points: usize,
) -> Result<Evaluation, RunError> {
    check_eval_points(points)?;
    let sets = EvalSets::new(&truth.mesh, &truth.labels, points, EVAL_SEED)?;
    let predict = |p: &[Vec3]| finite_values(p, model.eval_normalized(gpu, p)?);
    let scores = if is_unsigned(model.model_file()) {
        sets.score_unsigned(predict)?
    } else {
        sets.score(predict)?
    };
    // Wall time through the public call, and kernel time from timestamp queries (where the
    // adapter has them) in separate, alternating calls, so that the timestamps never slow the
    // wall figures and both see the same state of the GPU.
    let latency = measure_latency_timed(
        &sets.bbox.points,
        10,
        WARM_UP,
        MEASURE_FOR,
        |p| model.eval_normalized(gpu, p),
        |p| model.eval_normalized_timed(gpu, p),
    )?;
    Ok(Evaluation {
        scores,
        latency,
        eval_points: points,
        chamfer: None,
    })
}

/// `values` (of `points`), or [`RunError::NonFiniteModel`] at the first NaN or ∞: scores of
/// such a model would count its NaNs as outside and say nothing true.
pub fn finite_values(points: &[Vec3], values: Vec<f32>) -> Result<Vec<f32>, RunError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(RunError::NonFiniteModel {
            point: points[i],
            value: values[i],
        }),
        None => Ok(values),
    }
}

/// Extracts the model's surface at `resolution` cells per axis, evaluating on the GPU, and
/// returns it in the original mesh's coordinates. The surface is the zero level set, or for an
/// unsigned field ([`is_unsigned`]) the level set Φ = [`UNSIGNED_LEVEL`], since |d| has no zero
/// crossing to find.
pub fn extract_mesh(
    gpu: &GpuContext,
    model: &NeuralSdf,
    resolution: u32,
) -> Result<(Mesh, ExtractStats), RunError> {
    extract_mesh_with(gpu, model, &ExtractOptions::new(resolution))
}

/// [`extract_mesh`] with explicit options (memory budget, domain, bound factor).
pub fn extract_mesh_with(
    gpu: &GpuContext,
    model: &NeuralSdf,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), RunError> {
    let (mut mesh, stats) = extract_mesh_normalized(gpu, model, options)?;
    let n = model.normalization();
    for v in &mut mesh.vertices {
        *v = n.to_original(*v);
    }
    Ok((mesh, stats))
}

/// Extracts the level set `d = level` of a scene over its [`Scene::frame`] (grown by a
/// positive level), evaluating the whole scene on the GPU ([`GpuScene`]) batch by batch, and
/// returns it in the scene's frame. The pruning's distance bound is divided by the scene's
/// Lipschitz constant ([`Scene::lipschitz`]) besides `options.lipschitz`.
///
/// [`Scene::frame`]: sdf_nn::serve::scene::Scene::frame
/// [`Scene::lipschitz`]: sdf_nn::serve::scene::Scene::lipschitz
/// [`GpuScene`]: sdf_nn::serve::scene::GpuScene
pub fn extract_scene_mesh(
    gpu: &GpuContext,
    scene: &sdf_nn::serve::scene::Scene,
    level: f32,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), RunError> {
    let on_gpu = sdf_nn::serve::scene::GpuScene::new(gpu, scene)?;
    let frame = scene.frame(level);
    let half = 1.0 / frame.scale;
    let centre = frame.center.as_vec3();
    let options = ExtractOptions {
        lipschitz: options.lipschitz * on_gpu.lipschitz(),
        ..*options
    };
    let (mut mesh, stats) = extract_surface(
        |p: &[Vec3]| {
            let world: Vec<Vec3> = p.iter().map(|&q| centre + q * half).collect();
            let d = on_gpu.distances(&world, level)?;
            Ok::<_, sdf_nn::serve::scene::SceneGpuError>(
                d.into_iter().map(|x| x * frame.scale).collect::<Vec<_>>(),
            )
        },
        &options,
    )
    .map_err(|e| match e {
        ExtractError::Eval(e) => RunError::Scene(e),
        other => RunError::Options(other.to_string()),
    })?;
    for v in &mut mesh.vertices {
        *v = centre + *v * half;
    }
    Ok((mesh, stats))
}

/// The surface of [`extract_mesh_with`] in the model's normalised coordinates: what metrics
/// compare, exact whatever the mesh coordinates (a model far from the origin would round in
/// them).
pub fn extract_mesh_normalized(
    gpu: &GpuContext,
    model: &NeuralSdf,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), RunError> {
    let level = if is_unsigned(model.model_file()) {
        UNSIGNED_LEVEL
    } else {
        0.0
    };
    extract_surface(
        |p: &[Vec3]| {
            let d = model.eval_normalized(gpu, p)?;
            Ok::<_, sdf_nn::NeuralSdfError>(d.into_iter().map(|x| x - level).collect::<Vec<_>>())
        },
        options,
    )
    .map_err(|e| match e {
        ExtractError::Eval(e) => RunError::Model(e),
        other => RunError::Options(other.to_string()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Empty sets are refused before a run trains (the latency measurement asserted on them
    /// after it), as are sets past the memory budget.
    #[test]
    fn empty_or_oversized_sets_are_refused() {
        assert!(matches!(check_eval_points(0), Err(RunError::Options(_))));
        assert!(check_eval_points(1).is_ok());
        let too_many = (EVAL_MEMORY_BUDGET / EVAL_BYTES_PER_POINT + 1) as usize;
        assert!(matches!(
            check_eval_points(too_many),
            Err(RunError::OverBudget { .. })
        ));
    }
}
