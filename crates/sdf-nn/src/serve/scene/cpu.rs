//! The CPU reference of a [`Scene`]: distances, gradients, rays and closest points, in f64
//! through the operators (trained models answer in f32), on rayon threads.
//!
//! ```
//! use glam::Vec3;
//! use sdf_nn::serve::scene::{Primitive, Ray, Scene, SceneNode, TraceOptions, Transform};
//!
//! let ball = SceneNode::primitive(Primitive::Sphere { radius: 1.0 }, Transform::IDENTITY);
//! let scene = Scene::new(ball)?;
//! assert_eq!(scene.distance(Vec3::new(3.0, 0.0, 0.0), 0.0), 2.0);
//! // The level c: the distance to the level set is d − c.
//! assert_eq!(scene.distance(Vec3::new(3.0, 0.0, 0.0), 0.5), 1.5);
//! let ray = Ray { origin: Vec3::new(-5.0, 0.0, 0.0), direction: Vec3::X, max_distance: 100.0 };
//! let hit = scene.trace_ray(&ray, &TraceOptions::default())?.expect("a hit");
//! assert!((hit.t - 4.0).abs() < 1e-3 && hit.normal.abs_diff_eq(-Vec3::X, 1e-3));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! Every query evaluates a batch of points: each trained model is asked once per batch and
//! placement ([`NeuralSdf::eval_cpu`](crate::NeuralSdf::eval_cpu) or
//! [`NeuralSdf::eval_with_normals_cpu`](crate::NeuralSdf::eval_with_normals_cpu) on the points
//! mapped into its mesh frame), then each point runs the scene's program. Every leaf is
//! evaluated at every point: this is a reference, not an accelerated evaluator.
//!
//! Gradients are analytic through every operator (the smooth minimum's weights, the sign of a
//! shell, the negation of a difference); a primitive's is its exact gradient, a model's is its
//! unit normal rotated into the scene's frame. A NaN or infinite query point (or level) gives
//! NaN distances, as [`NeuralSdf::eval_cpu`](crate::NeuralSdf::eval_cpu) does; rays and
//! closest points refuse bad input with a [`SceneQueryError`].

use glam::{DQuat, DVec3, Vec3};
use rayon::prelude::*;

use crate::serve::scene::tree::{Instruction, LeafKind, MAX_DEPTH, Scene, TraceStep, Transform};

/// Errors of the ray and closest-point queries; `index` is the element of the batch.
#[derive(Debug, thiserror::Error)]
pub enum SceneQueryError {
    /// A ray's direction is zero, NaN or infinite.
    #[error("ray {index}: direction {direction} is zero or not finite")]
    Direction {
        /// The ray.
        index: usize,
        /// Its direction.
        direction: Vec3,
    },
    /// A ray's origin or a query point is NaN or infinite.
    #[error("point {index}: {point} is not finite")]
    Point {
        /// The ray or point.
        index: usize,
        /// The origin or point.
        point: Vec3,
    },
    /// A ray's maximum distance is NaN or negative (`+∞` is allowed).
    #[error("ray {index}: maximum distance {value} is NaN or negative")]
    MaxDistance {
        /// The ray.
        index: usize,
        /// The value.
        value: f32,
    },
    /// The level `c` is NaN or infinite.
    #[error("level {0} is not finite")]
    Level(f32),
    /// The tolerance is not finite and `> 0`.
    #[error("tolerance {0} must be finite and > 0")]
    Tolerance(f32),
    /// The over-relaxation factor is not in `[1, 2)`.
    #[error("over-relaxation {0} must lie in [1, 2)")]
    OverRelaxation(f32),
}

/// The scene's value at a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneSample {
    /// `d − c`: the scene's signed distance minus the level.
    pub distance: f32,
    /// Its gradient (analytic; not normalised: smooth blends shorten it).
    pub gradient: Vec3,
    /// The leaf ([`Scene::leaves`]) that decides the value: the one the minima and maxima
    /// chose, and in a smooth blend the one with the larger weight.
    pub leaf: usize,
}

/// A ray: `origin + t · direction` for `0 ≤ t ≤ max_distance` (`direction` is normalised, so
/// `t` is a distance).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Where it starts.
    pub origin: Vec3,
    /// Where it goes (any length but zero).
    pub direction: Vec3,
    /// How far it looks (`+∞` allowed: then the step count bounds it).
    pub max_distance: f32,
}

/// How rays are traced.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceOptions {
    /// The level `c`: rays hit the set `d = c`.
    pub level: f32,
    /// A hit is a point with `|d − c| ≤ tolerance` (scene units).
    pub tolerance: f32,
    /// Steps before a ray gives up (a miss).
    pub max_steps: u32,
    /// Over-relaxed steps (Keinert et al. 2014): this factor times the safe step while the free
    /// spheres of consecutive points overlap, back to the previous point and plain steps where
    /// they do not ([`Scene::trace_rays`]). In `[1, 2)`; 1 traces plainly. Default
    /// [`TRACE_OVER_RELAXATION`].
    pub over_relaxation: f32,
}

/// The default over-relaxation of ray queries ([`TraceOptions::over_relaxation`]), the
/// renderer's factor. On the scene bench's layout (8 copies of the example's spot model, 4
/// primitives), 3000 rays of the CPU reference took 31 % fewer steps on average (35.6 → 24.4)
/// for the same 2083 hits; 1.2 and 1.6 saved 20 % and 32 % (docs/benchmarks, session 28).
pub const TRACE_OVER_RELAXATION: f32 = 1.4;

/// The defaults' tolerances are absolute, chosen for a scene of half-side about 1 (a model of
/// a mesh in `[-1, 1]³`). A scene of a 2 mm part in metres, or of a building in
/// millimetres, wants them in proportion: `for_scene` scales them by the scene's half-side.
impl Default for TraceOptions {
    fn default() -> Self {
        TraceOptions {
            level: 0.0,
            tolerance: 1e-4,
            max_steps: 1024,
            over_relaxation: TRACE_OVER_RELAXATION,
        }
    }
}

impl TraceOptions {
    /// The defaults with the hit tolerance in proportion to `scene`: 10⁻⁴ of the half-side
    /// of its frame ([`Scene::frame`]), the default's 10⁻⁴ for a scene of half-side 1. What
    /// `query --rays` uses.
    pub fn for_scene(scene: &Scene) -> Self {
        let defaults = TraceOptions::default();
        TraceOptions {
            tolerance: defaults.tolerance * scene_half_side(scene),
            ..defaults
        }
    }
}

/// The half-side of `scene`'s frame at level 0: the length its default tolerances scale by.
fn scene_half_side(scene: &Scene) -> f32 {
    1.0 / scene.frame(0.0).scale
}

/// Spheres of consecutive points must overlap by this fraction of the step between them: ones
/// that only touch do not count, since an unsigned field's sheet (room 0 on it) met head-on
/// lies exactly where they touch. The renderer's pixel loop uses the same rule.
const OVERLAP_SLACK: f64 = 1e-3;

/// One ray's over-relaxed march (the WGSL twin is `trace_element` in
/// `shaders/scene_query.wgsl`).
#[derive(Clone, Copy, Debug)]
struct March {
    /// Distance along the ray.
    t: f64,
    /// The factor of the next step: the options' until a step fails, then 1.
    omega: f64,
    /// The safe step (room) at the previous point.
    prev_room: f64,
    /// The step taken from the previous point (0 before the first).
    prev_step: f64,
}

/// What a ray does after one evaluation of the field.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Stride {
    /// March on from the new `t`.
    On,
    /// `|d − c| ≤ tolerance` at `t`.
    Hit,
    /// Past the maximum distance, or a NaN.
    Miss,
}

impl March {
    fn new(omega: f64) -> Self {
        March {
            t: 0.0,
            omega,
            prev_room: 0.0,
            prev_step: 0.0,
        }
    }

    /// Takes the field's `gap` (`d − c`) and safe step `room` at `t`.
    fn advance(&mut self, gap: f64, room: f64, tolerance: f64, max_distance: f64) -> Stride {
        // A NaN room (a broken model) proves no overlap either.
        let overlap = room + self.prev_room >= self.prev_step * (1.0 + OVERLAP_SLACK);
        if self.omega > 1.0 && self.prev_step > 0.0 && !overlap {
            // The segment from the previous point may hold the surface: back to its plain step.
            self.plain_step();
            return Stride::On;
        }
        if gap.abs() <= tolerance {
            return Stride::Hit;
        }
        // NaN from a broken model ends the ray as a miss.
        if !gap.is_finite() {
            return Stride::Miss;
        }
        self.prev_room = room;
        self.prev_step = self.omega * room;
        self.t += self.prev_step;
        let within = self.t <= max_distance;
        if !within && self.omega > 1.0 {
            // A long step went past the end: the plain one may not have.
            self.plain_step();
        }
        if self.t <= max_distance {
            Stride::On
        } else {
            Stride::Miss
        }
    }

    /// Replaces the last step by the plain one, and steps plainly from there on.
    fn plain_step(&mut self) {
        self.t += self.prev_room - self.prev_step;
        self.prev_step = self.prev_room;
        self.omega = 1.0;
    }
}

/// Where a ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayHit {
    /// Distance along the ray.
    pub t: f32,
    /// The point `origin + t · direction`.
    pub point: Vec3,
    /// The unit normal there (the normalised gradient).
    pub normal: Vec3,
    /// The leaf hit ([`SceneSample::leaf`] at the point).
    pub leaf: usize,
    /// Sphere-tracing steps taken.
    pub steps: u32,
}

/// How points are projected onto the surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectOptions {
    /// The level `c`: points are projected onto the set `d = c`.
    pub level: f32,
    /// Stop when `|d − c| < tolerance` (scene units).
    pub tolerance: f32,
    /// Steps before giving up (the point is then reported with `converged: false`).
    pub max_iterations: u32,
}

/// Absolute tolerances, as [`TraceOptions`]'s defaults are; `for_scene` scales them.
impl Default for ProjectOptions {
    fn default() -> Self {
        ProjectOptions {
            level: 0.0,
            tolerance: 1e-5,
            max_iterations: 32,
        }
    }
}

impl ProjectOptions {
    /// The defaults with the convergence tolerance in proportion to `scene`: 10⁻⁵ of the
    /// half-side of its frame ([`Scene::frame`]). What `query --closest` uses.
    pub fn for_scene(scene: &Scene) -> Self {
        let defaults = ProjectOptions::default();
        ProjectOptions {
            tolerance: defaults.tolerance * scene_half_side(scene),
            ..defaults
        }
    }
}

/// A point projected onto the surface by `x ← x − (d − c) ∇d / |∇d|²`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClosestPoint {
    /// The last iterate.
    pub point: Vec3,
    /// `|d − c|` there.
    pub residual: f32,
    /// Steps taken.
    pub iterations: u32,
    /// Whether the residual is below the tolerance (else the steps ran out or the gradient
    /// vanished).
    pub converged: bool,
    /// The leaf that decides the value there.
    pub leaf: usize,
}

/// A value on the evaluation stack, in f64.
#[derive(Clone, Copy, Debug)]
struct Value {
    d: f64,
    g: DVec3,
    leaf: u32,
}

impl std::ops::Neg for Value {
    type Output = Value;
    fn neg(self) -> Value {
        Value {
            d: -self.d,
            g: -self.g,
            ..self
        }
    }
}

/// A leaf's placement in f64.
struct Placed {
    rotation: DQuat,
    inverse: DQuat,
    translation: DVec3,
    scale: f64,
}

impl Placed {
    fn new(t: &Transform) -> Self {
        let rotation = t.rotation.as_dquat().normalize();
        Placed {
            rotation,
            inverse: rotation.inverse(),
            translation: t.translation.as_dvec3(),
            scale: t.scale as f64,
        }
    }

    fn to_local(&self, p: DVec3) -> DVec3 {
        self.inverse * (p - self.translation) / self.scale
    }
}

/// A leaf's (distance, gradient) at each point of a batch, for model leaves (`None` for
/// primitives, which are evaluated inline).
type LeafValues = Option<Vec<(f64, DVec3)>>;

/// Most values held per batch for the models' answers; larger batches are split.
const MODEL_VALUES_PER_CHUNK: usize = 1 << 22;

impl Scene {
    /// `d − c` at `p`.
    pub fn distance(&self, p: Vec3, level: f32) -> f32 {
        self.distances(&[p], level)[0]
    }

    /// `d − c` at each point.
    pub fn distances(&self, points: &[Vec3], level: f32) -> Vec<f32> {
        let points: Vec<DVec3> = points.iter().map(|p| p.as_dvec3()).collect();
        let c = level as f64;
        self.evaluate(&points, false)
            .into_iter()
            .map(|v| (v.d - c) as f32)
            .collect()
    }

    /// `d − c`, its gradient and the deciding leaf at `p`.
    pub fn distance_and_gradient(&self, p: Vec3, level: f32) -> SceneSample {
        self.distances_and_gradients(&[p], level)[0]
    }

    /// `d − c`, its gradient and the deciding leaf at each point.
    pub fn distances_and_gradients(&self, points: &[Vec3], level: f32) -> Vec<SceneSample> {
        let points: Vec<DVec3> = points.iter().map(|p| p.as_dvec3()).collect();
        let c = level as f64;
        self.evaluate(&points, true)
            .into_iter()
            .map(|v| SceneSample {
                distance: (v.d - c) as f32,
                gradient: v.g.as_vec3(),
                leaf: v.leaf as usize,
            })
            .collect()
    }

    /// Traces one ray (see [`Scene::trace_rays`]).
    pub fn trace_ray(
        &self,
        ray: &Ray,
        options: &TraceOptions,
    ) -> Result<Option<RayHit>, SceneQueryError> {
        Ok(self.trace_rays(std::slice::from_ref(ray), options)?[0])
    }

    /// Sphere-traces each ray to the first point where `|d − c| ≤ tolerance`. Each step is
    /// the radius of a ball about the point that holds no crossing of the level set, with the
    /// sign of `d − c`: the sharp unions, intersections and differences of the tree taken over
    /// their operands' radii, each operand's its value less the level over its Lipschitz bound
    /// near the point (1 for a primitive; for a model, the bound of the cell of its box, or
    /// the block of cells, that holds the ball, else its whole-box estimate:
    /// [`super::lipschitz::LocalLipschitz`]), and any other node's its value less the level
    /// over the largest of its models' local bounds ([`Scene::trace_plan`]). No step crosses
    /// the level set where the measured bounds bound the models' slopes, and every step is at
    /// least `|d − c| / L` with `L` the scene's largest estimate ([`Scene::lipschitz`]): near
    /// a primitive and away from the models, a step of the primitive's whole distance. An
    /// origin inside (`d < c`) finds where the ray leaves. `None` for a ray that goes past its
    /// maximum distance or runs out of steps.
    ///
    /// Steps are over-relaxed ([`TraceOptions::over_relaxation`] ω): ω times that safe step
    /// while the free spheres of consecutive points overlap (their radii, the safe steps, sum to
    /// more than the step between them), so the segment between them holds no surface either.
    /// Where they do not, the ray goes back to the previous point and steps plainly from there
    /// on; so does a long step that passes the maximum distance. The guarantee is the plain
    /// tracer's; the evaluation that found the gap counts as a step.
    pub fn trace_rays(
        &self,
        rays: &[Ray],
        options: &TraceOptions,
    ) -> Result<Vec<Option<RayHit>>, SceneQueryError> {
        check_trace_options(options)?;
        for (index, ray) in rays.iter().enumerate() {
            check_ray(index, ray)?;
        }
        let plan = self.trace_plan();
        let (c, tol) = (options.level as f64, options.tolerance as f64);
        let origins: Vec<DVec3> = rays.iter().map(|r| r.origin.as_dvec3()).collect();
        let dirs: Vec<DVec3> = rays
            .iter()
            .map(|r| r.direction.as_dvec3().normalize())
            .collect();
        let mut march = vec![March::new(options.over_relaxation as f64); rays.len()];
        let mut steps = vec![0u32; rays.len()];
        let mut hit = vec![false; rays.len()];
        let mut active: Vec<usize> = (0..rays.len()).collect();
        for step in 0..options.max_steps {
            if active.is_empty() {
                break;
            }
            let points: Vec<DVec3> = active
                .iter()
                .map(|&i| origins[i] + dirs[i] * march[i].t)
                .collect();
            let values = self.trace_values(&points, c, &plan);
            active = active
                .into_iter()
                .zip(values)
                .filter_map(|(i, (gap, bound))| {
                    steps[i] = step + 1;
                    let max_distance = rays[i].max_distance as f64;
                    match march[i].advance(gap, bound.abs(), tol, max_distance) {
                        Stride::On => Some(i),
                        Stride::Hit => {
                            hit[i] = true;
                            None
                        }
                        Stride::Miss => None,
                    }
                })
                .collect();
        }
        let hits: Vec<usize> = (0..rays.len()).filter(|&i| hit[i]).collect();
        let points: Vec<DVec3> = hits
            .iter()
            .map(|&i| origins[i] + dirs[i] * march[i].t)
            .collect();
        let mut out = vec![None; rays.len()];
        for (&i, (v, p)) in hits
            .iter()
            .zip(self.evaluate(&points, true).into_iter().zip(points))
        {
            out[i] = Some(RayHit {
                t: march[i].t as f32,
                point: p.as_vec3(),
                normal: v.g.normalize_or(-dirs[i]).as_vec3(),
                leaf: v.leaf as usize,
                steps: steps[i],
            });
        }
        Ok(out)
    }

    /// Projects one point (see [`Scene::closest_points`]).
    pub fn closest_point(
        &self,
        point: Vec3,
        options: &ProjectOptions,
    ) -> Result<ClosestPoint, SceneQueryError> {
        Ok(self.closest_points(&[point], options)?[0])
    }

    /// Projects each point onto the level set `d = c` by `x ← x − (d − c) ∇d / |∇d|²`, until
    /// `|d − c| < tolerance` or `max_iterations` steps; the residual `|d − c|` at the returned
    /// point is reported. For an exact distance one step lands on the closest surface point;
    /// for a bound or a trained model the iteration converges to a nearby surface point, not
    /// always the closest one.
    pub fn closest_points(
        &self,
        points: &[Vec3],
        options: &ProjectOptions,
    ) -> Result<Vec<ClosestPoint>, SceneQueryError> {
        check_level_and_tolerance(options.level, options.tolerance)?;
        check_points(points)?;
        let (c, tol) = (options.level as f64, options.tolerance as f64);
        let mut x: Vec<DVec3> = points.iter().map(|p| p.as_dvec3()).collect();
        let mut out: Vec<Option<ClosestPoint>> = vec![None; points.len()];
        let mut active: Vec<usize> = (0..points.len()).collect();
        for iteration in 0..=options.max_iterations {
            if active.is_empty() {
                break;
            }
            let at: Vec<DVec3> = active.iter().map(|&i| x[i]).collect();
            let values = self.evaluate(&at, true);
            active = active
                .into_iter()
                .zip(values)
                .filter_map(|(i, v)| {
                    let gap = v.d - c;
                    let g2 = v.g.length_squared();
                    let converged = gap.abs() < tol;
                    // A vanished gradient or a NaN cannot be stepped from.
                    if converged
                        || iteration == options.max_iterations
                        || g2 < 1e-24
                        || !gap.is_finite()
                    {
                        out[i] = Some(ClosestPoint {
                            point: x[i].as_vec3(),
                            residual: gap.abs() as f32,
                            iterations: iteration,
                            converged,
                            leaf: v.leaf as usize,
                        });
                        return None;
                    }
                    x[i] -= v.g * (gap / g2);
                    Some(i)
                })
                .collect();
        }
        Ok(out
            .into_iter()
            .map(|p| p.expect("every point ends in the loop"))
            .collect())
    }

    /// The scene's values at `points` (gradients of models only when `gradients`; those of
    /// primitives always, they cost nothing), in chunks that bound the models' buffers.
    fn evaluate(&self, points: &[DVec3], gradients: bool) -> Vec<Value> {
        let placed: Vec<Placed> = self
            .leaves()
            .iter()
            .map(|l| Placed::new(&l.transform))
            .collect();
        let mut out = Vec::with_capacity(points.len());
        for part in points.chunks(self.points_per_chunk()) {
            let models = self.model_values(part, &placed, gradients);
            let values: Vec<Value> = part
                .par_iter()
                .enumerate()
                .map_init(
                    || Vec::with_capacity(MAX_DEPTH + 2),
                    |stack, (i, &p)| self.run(stack, p, i, &placed, &models),
                )
                .collect();
            out.extend(values);
        }
        out
    }

    /// Points per chunk of an evaluation: the models' values of a chunk (one per point and
    /// model leaf) stay within [`MODEL_VALUES_PER_CHUNK`].
    fn points_per_chunk(&self) -> usize {
        let model_leaves = self
            .leaves()
            .iter()
            .filter(|l| matches!(l.kind, LeafKind::Model(_)))
            .count();
        (MODEL_VALUES_PER_CHUNK / model_leaves.max(1)).clamp(256, 1 << 16)
    }

    /// Each model leaf's (distance, gradient) at `points`, in the scene's frame and units: one
    /// batch per leaf. `None` for primitive leaves.
    fn model_values(
        &self,
        points: &[DVec3],
        placed: &[Placed],
        gradients: bool,
    ) -> Vec<LeafValues> {
        self.leaves()
            .iter()
            .zip(placed)
            .map(|(leaf, at)| {
                let LeafKind::Model(m) = leaf.kind else {
                    return None;
                };
                let model = &self.models()[m];
                let local: Vec<Vec3> = points
                    .par_iter()
                    .map(|&p| at.to_local(p).as_vec3())
                    .collect();
                Some(if gradients {
                    model
                        .eval_with_normals_cpu(&local)
                        .into_iter()
                        .map(|(d, n)| (d as f64 * at.scale, at.rotation * n.as_dvec3()))
                        .collect()
                } else {
                    model
                        .eval_cpu(&local)
                        .into_iter()
                        .map(|d| (d as f64 * at.scale, DVec3::ZERO))
                        .collect()
                })
            })
            .collect()
    }

    /// At each point, `d − c` and the tracer's step bound: the signed radius of a ball free of
    /// the level set, each sharp union, intersection and difference taken over its operands'
    /// radii, and any other instruction's radius its value less its level over the largest
    /// local Lipschitz bound of the models under it (1 without models). An operand's ball holds
    /// no crossing of its own level set, so the min (or max) of the signed radii is the radius
    /// of a ball that holds none of the combined one: outside every operand of a union, a ball
    /// outside each; inside one, that one's ball. It has the sign of `d − c` (dividing each
    /// operand of a min or max by a positive number keeps the sign of the result), so its
    /// magnitude is a safe step, also for cones and over-relaxed steps, which need free balls;
    /// and it is at least `|d − c| / L` with `L` the scene's largest estimate, often much more
    /// (near a primitive, far from the models, near a model where its slope is small).
    /// In chunks as [`Self::evaluate`]: a million rays on 64 placed models asked 2 GB a step.
    fn trace_values(&self, points: &[DVec3], c: f64, plan: &[TraceStep]) -> Vec<(f64, f64)> {
        let placed: Vec<Placed> = self
            .leaves()
            .iter()
            .map(|l| Placed::new(&l.transform))
            .collect();
        let subtree_models: Vec<Vec<usize>> = plan
            .iter()
            .enumerate()
            .map(|(i, step)| self.subtree_models(i, step))
            .collect();
        let mut out = Vec::with_capacity(points.len());
        for part in points.chunks(self.points_per_chunk()) {
            let models = self.model_values(part, &placed, false);
            out.extend(self.trace_part(part, c, plan, &placed, &models, &subtree_models));
        }
        out
    }

    /// [`Self::trace_values`] of one chunk, its models' values given.
    fn trace_part(
        &self,
        points: &[DVec3],
        c: f64,
        plan: &[TraceStep],
        placed: &[Placed],
        models: &[Option<Vec<(f64, DVec3)>>],
        subtree_models: &[Vec<usize>],
    ) -> Vec<(f64, f64)> {
        let at = |i: usize, p: DVec3| Point {
            p,
            i,
            placed,
            models,
        };
        points
            .par_iter()
            .enumerate()
            .map_init(
                || Vec::with_capacity(MAX_DEPTH + 2),
                |stack: &mut Vec<(Value, f64)>, (i, &p)| {
                    stack.clear();
                    for (k, (&instruction, step)) in self.program().iter().zip(plan).enumerate() {
                        // The operands' bounds, last operand first.
                        let mut bounds = [0.0f64; 2];
                        let mut taken = 0;
                        let v = self.instruction_value(instruction, &at(i, p), &mut || {
                            let (v, bound) = stack.pop().expect("the program is balanced");
                            bounds[taken] = bound;
                            taken += 1;
                            v
                        });
                        let [tb, ta] = bounds;
                        let bound = match instruction {
                            Instruction::Union => ta.min(tb),
                            Instruction::Intersection => ta.max(tb),
                            // The subtracted operand was traced against the opposite level.
                            Instruction::Difference => ta.max(-tb),
                            _ => {
                                // Its value less its level over the largest local bound of
                                // the models under it (1 without models).
                                let gap = v.d - if step.flipped { -c } else { c };
                                let bound = subtree_models[k]
                                    .iter()
                                    .map(|&l| self.leaf_local_lipschitz(l, &placed[l], p, gap))
                                    .fold(1.0, f64::max);
                                gap / bound
                            }
                        };
                        stack.push((v, bound));
                    }
                    let (v, bound) = stack.pop().expect("the program is balanced");
                    (v.d - c, bound)
                },
            )
            .collect()
    }

    /// Model leaf `leaf`'s local Lipschitz bound at `p` for a ball of radius `gap` over the
    /// bound ([`super::lipschitz::LocalLipschitz::bound`], asked in the model's normalised
    /// frame; at least 1); 1 for a primitive.
    fn leaf_local_lipschitz(&self, leaf: usize, placed: &Placed, p: DVec3, gap: f64) -> f64 {
        let LeafKind::Model(m) = self.leaves()[leaf].kind else {
            return 1.0;
        };
        let local = self.model_local_lipschitz(m).expect("a model of the scene");
        let normalization = self.models()[m].normalization();
        let q = normalization.to_normalized_f64(placed.to_local(p));
        // Scene units → the model's mesh units → its normalised units.
        let gap_normalized = gap / placed.scale * normalization.scale as f64;
        local.bound(q, gap_normalized as f32) as f64
    }

    /// Runs the program at point `p` (number `i` of the batch whose model values are `models`).
    fn run(
        &self,
        stack: &mut Vec<Value>,
        p: DVec3,
        i: usize,
        placed: &[Placed],
        models: &[LeafValues],
    ) -> Value {
        stack.clear();
        let at = Point {
            p,
            i,
            placed,
            models,
        };
        for &instruction in self.program() {
            let value = self.instruction_value(instruction, &at, &mut || pop(stack));
            stack.push(value);
        }
        pop(stack)
    }

    /// One instruction's value at `at`: a leaf's, or an operator's on the operands `operand`
    /// takes off the stack (the last operand first).
    fn instruction_value(
        &self,
        instruction: Instruction,
        at: &Point<'_>,
        operand: &mut impl FnMut() -> Value,
    ) -> Value {
        match instruction {
            Instruction::Leaf(l) => {
                let leaf = l as usize;
                let (d, g) = match (&self.leaves()[leaf].kind, &at.models[leaf]) {
                    (_, Some(values)) => values[at.i],
                    (LeafKind::Primitive(prim), None) => {
                        let placed = &at.placed[leaf];
                        let (d, g) = prim.distance_and_gradient(placed.to_local(at.p));
                        (d * placed.scale, placed.rotation * g)
                    }
                    (LeafKind::Model(_), None) => unreachable!("model leaves have values"),
                };
                Value { d, g, leaf: l }
            }
            Instruction::Offset(r) => {
                let a = operand();
                Value {
                    d: a.d - r as f64,
                    ..a
                }
            }
            Instruction::Shell(t) => {
                let a = operand();
                let sign = if a.d < 0.0 { -1.0 } else { 1.0 };
                Value {
                    d: a.d.abs() - t as f64,
                    g: a.g * sign,
                    ..a
                }
            }
            binary => {
                let b = operand();
                let a = operand();
                combine(binary, a, b)
            }
        }
    }
}

/// Where the program runs: point `p`, number `i` of the batch whose model leaves' values are
/// `models`, the leaves placed by `placed`.
struct Point<'a> {
    p: DVec3,
    i: usize,
    placed: &'a [Placed],
    models: &'a [LeafValues],
}

/// The top of the stack (the compiler balanced the program).
fn pop(stack: &mut Vec<Value>) -> Value {
    stack.pop().expect("the scene's program is balanced")
}

/// A binary operator on two values.
fn combine(op: Instruction, a: Value, b: Value) -> Value {
    let pick_min = |a: Value, b: Value| if b.d < a.d { b } else { a };
    let pick_max = |a: Value, b: Value| if b.d > a.d { b } else { a };
    match op {
        Instruction::Union => pick_min(a, b),
        Instruction::Intersection => pick_max(a, b),
        Instruction::Difference => pick_max(a, -b),
        Instruction::SmoothUnion(k) => smooth_min(a, b, k as f64),
        Instruction::SmoothIntersection(k) => -smooth_min(-a, -b, k as f64),
        Instruction::SmoothDifference(k) => -smooth_min(-a, b, k as f64),
        Instruction::Leaf(_) | Instruction::Offset(_) | Instruction::Shell(_) => {
            unreachable!("not a binary operator")
        }
    }
}

/// The polynomial smooth minimum `min(a, b) − h²k/4`, `h = max(k − |a − b|, 0)/k`, and its
/// gradient: the smaller child has weight `1 − h/2`, the larger `h/2`.
fn smooth_min(a: Value, b: Value, k: f64) -> Value {
    let (lo, hi) = if a.d <= b.d { (a, b) } else { (b, a) };
    let h = (k - (hi.d - lo.d)).max(0.0) / k;
    Value {
        d: lo.d - h * h * k * 0.25,
        g: lo.g * (1.0 - 0.5 * h) + hi.g * (0.5 * h),
        leaf: lo.leaf,
    }
}

pub(crate) fn check_level_and_tolerance(level: f32, tolerance: f32) -> Result<(), SceneQueryError> {
    if !level.is_finite() {
        return Err(SceneQueryError::Level(level));
    }
    if !(tolerance.is_finite() && tolerance > 0.0) {
        return Err(SceneQueryError::Tolerance(tolerance));
    }
    Ok(())
}

/// Checks a trace's level, tolerance and over-relaxation.
pub(crate) fn check_trace_options(options: &TraceOptions) -> Result<(), SceneQueryError> {
    check_level_and_tolerance(options.level, options.tolerance)?;
    let omega = options.over_relaxation;
    if !(1.0..2.0).contains(&omega) {
        return Err(SceneQueryError::OverRelaxation(omega));
    }
    Ok(())
}

/// Checks that every query point is finite.
pub(crate) fn check_points(points: &[Vec3]) -> Result<(), SceneQueryError> {
    match points.iter().position(|p| !p.is_finite()) {
        Some(index) => Err(SceneQueryError::Point {
            index,
            point: points[index],
        }),
        None => Ok(()),
    }
}

pub(crate) fn check_ray(index: usize, ray: &Ray) -> Result<(), SceneQueryError> {
    if !ray.origin.is_finite() {
        return Err(SceneQueryError::Point {
            index,
            point: ray.origin,
        });
    }
    let d = ray.direction.as_dvec3();
    if !d.is_finite() || d.length_squared() == 0.0 {
        return Err(SceneQueryError::Direction {
            index,
            direction: ray.direction,
        });
    }
    if ray.max_distance.is_nan() || ray.max_distance < 0.0 {
        return Err(SceneQueryError::MaxDistance {
            index,
            value: ray.max_distance,
        });
    }
    Ok(())
}
