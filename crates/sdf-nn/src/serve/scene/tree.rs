//! The scene tree ([`SceneNode`]), its validation, and its compiled form ([`Scene`]): a flat,
//! post-order program of leaves and binary operators that the CPU reference walks, and that a
//! WGSL generator can walk the same way.
//!
//! ```
//! use glam::{Quat, Vec3};
//! use sdf_nn::serve::scene::{Primitive, Scene, SceneNode, Transform};
//!
//! let ball = SceneNode::primitive(Primitive::Sphere { radius: 1.0 }, Transform::IDENTITY);
//! let slab = SceneNode::primitive(
//!     Primitive::Box { half_extents: Vec3::new(2.0, 0.25, 2.0) },
//!     Transform::new(Vec3::Y, Quat::IDENTITY, 1.0),
//! );
//! let scene = Scene::new(SceneNode::SmoothUnion { k: 0.2, children: vec![ball, slab] })?;
//! assert_eq!(scene.leaves().len(), 2);
//! # Ok::<(), sdf_nn::serve::scene::SceneError>(())
//! ```
//!
//! # What each operator returns
//!
//! Sphere tracing needs `|f(x)| ≤` the distance from `x` to the surface `f = 0` (a *bound*);
//! collision checks want more, the *exact* distance. Any 1-Lipschitz `f` is a bound on the
//! distance to its own zero set, and every operator below keeps the Lipschitz constant of its
//! children (min, max, `|·|`, a shift, a rigid motion, a uniform scale with the distance
//! scaled alike, and the smooth minimum, whose partial derivatives are `1 − h/2` and `h/2`,
//! both in `[0, 1]`).
//!
//! | node | value | with exact children |
//! | --- | --- | --- |
//! | primitives | exact | — |
//! | trained model | neither: a fitted approximation, `≈` the distance within its fitting error; divided by its Lipschitz estimate a bound ([`super::lipschitz`]) | — |
//! | [`SceneNode::Union`] `min` | bound | exact outside, a bound inside |
//! | [`SceneNode::Intersection`] `max` | bound | exact inside, a bound outside |
//! | [`SceneNode::Difference`] `max(a, −b, −c, …)` | bound | exact inside, a bound outside |
//! | smooth union / intersection / difference | bound | a bound (the blend changes the surface) |
//! | [`SceneNode::Offset`] `d − r` | bound | exact outside the new surface for `r ≥ 0` (inside for `r ≤ 0`), a bound elsewhere |
//! | [`SceneNode::Shell`] `|d| − t` | bound | exact outside the shell, a bound inside |
//! | [`SceneNode::Transform`] | as its child | exact |
//!
//! "Bound" everywhere assumes 1-Lipschitz children; with a trained model in the tree, the whole
//! scene is `L`-Lipschitz with `L` the largest model estimate. The ray tracer divides each
//! operand of the sharp operators by its own bound instead, a model's measured near the point
//! ([`Scene::trace_plan`], [`super::cpu`]'s `trace_rays`, [`super::lipschitz::LocalLipschitz`]),
//! which keeps the surface and takes longer steps.
//!
//! The n-ary smooth operators and difference are left folds: `smooth_union(a, b, c)` is
//! `smin(smin(a, b), c)` (the smooth minimum is not associative), `difference(a, b, c)` is
//! `a − b − c`.
//!
//! # Limits
//!
//! A tree is at most [`MAX_DEPTH`] nodes deep (the root is depth 1), has at most
//! [`MAX_LEAVES`] leaves and at most [`MAX_MODELS`] distinct models (one model placed many times
//! counts once: the leaves share its weights through the [`Arc`]). The compiled program's
//! evaluation stack never holds more than `MAX_DEPTH + 1` values, so a shader can use a
//! fixed-size array.

use std::sync::{Arc, OnceLock};

use glam::{Quat, Vec3};

use crate::NeuralSdf;
use crate::serve::scene::lipschitz::{CellFloors, LocalLipschitz};
use crate::serve::scene::primitive::Primitive;

/// The deepest tree [`Scene::new`] accepts (the root is depth 1).
pub const MAX_DEPTH: usize = 64;

/// The most leaves (primitives and placed models) a scene may have.
pub const MAX_LEAVES: usize = 4096;

/// The most distinct models a scene may hold. A GPU evaluator binds each model's weights, so it
/// may name a lower limit: the device's storage-buffer bindings.
pub const MAX_MODELS: usize = 16;

/// Errors of building a [`Scene`]. `node` is where, as a path from the root in the scene file's
/// terms: `root`, `root.children[2]`, `root.children[2].children[0]`.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The tree is deeper than [`MAX_DEPTH`].
    #[error("{node}: the tree is deeper than the limit of {limit} levels")]
    TooDeep {
        /// The first node below the limit.
        node: String,
        /// [`MAX_DEPTH`].
        limit: usize,
    },
    /// More leaves than [`MAX_LEAVES`].
    #[error("{node}: the scene has more than {limit} leaves")]
    TooManyLeaves {
        /// The first leaf over the limit.
        node: String,
        /// [`MAX_LEAVES`].
        limit: usize,
    },
    /// More distinct models than [`MAX_MODELS`].
    #[error("{node}: the scene holds more than {limit} distinct models")]
    TooManyModels {
        /// The first leaf with a model over the limit.
        node: String,
        /// [`MAX_MODELS`].
        limit: usize,
    },
    /// A number is NaN or infinite.
    #[error("{node}: `{field}` is not finite")]
    NonFinite {
        /// The node.
        node: String,
        /// The parameter.
        field: &'static str,
    },
    /// A transform's scale is zero or negative (a mirror is not a rigid motion).
    #[error("{node}: scale {scale} is not > 0")]
    Scale {
        /// The node.
        node: String,
        /// The scale.
        scale: f32,
    },
    /// A node's placement composed with its parents' (or a parameter in the scene's units)
    /// leaves f32's normal range: scales of 1e20 under 1e20 overflow, 1e-23 under 1e-23 vanish
    /// (and a GPU may flush a subnormal to zero).
    #[error(
        "{node}: {what} = {value} in the scene's units (composed with the parents' transforms) is \
         outside f32's normal range"
    )]
    Placement {
        /// The node.
        node: String,
        /// What left the range: `scale`, `translation` or an operator's parameter.
        what: &'static str,
        /// Its value in the scene's units (the scale, the largest translation component).
        value: f32,
    },
    /// A rotation quaternion is zero (it is normalised otherwise).
    #[error("{node}: the rotation quaternion is zero")]
    Rotation {
        /// The node.
        node: String,
    },
    /// A parameter is out of its range (a blend radius `k ≤ 0`, a radius `≤ 0`, ...).
    #[error("{node}: `{field}` = {value} must be {requirement}")]
    Parameter {
        /// The node.
        node: String,
        /// The parameter.
        field: &'static str,
        /// Its value.
        value: f32,
        /// What it must be.
        requirement: &'static str,
    },
    /// An operator has the wrong number of children.
    #[error("{node}: `{op}` needs {expected} children, it has {found}")]
    Children {
        /// The node.
        node: String,
        /// The operator.
        op: &'static str,
        /// What it needs ("1", "at least 1").
        expected: &'static str,
        /// What it has.
        found: usize,
    },
    /// [`Scene::set_model_lipschitz`] was given a model index or value it cannot take.
    #[error(
        "model {model}: Lipschitz bound {value} (the scene has {models} models; bounds are finite and > 0)"
    )]
    Lipschitz {
        /// The model index.
        model: usize,
        /// The value.
        value: f32,
        /// How many models the scene has.
        models: usize,
    },
}

/// A similarity transform: `x ↦ translation + rotation · (scale · x)`, from a node's own frame
/// to its parent's. The scale is uniform and `> 0`, so distances scale by it exactly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Where the node's origin goes.
    pub translation: Vec3,
    /// Rotation (normalised by [`Scene::new`]; must not be zero).
    pub rotation: Quat,
    /// Uniform scale `> 0`.
    pub scale: f32,
}

impl Transform {
    /// The identity.
    pub const IDENTITY: Transform = Transform {
        translation: Vec3::ZERO,
        rotation: Quat::IDENTITY,
        scale: 1.0,
    };

    /// A transform from its parts.
    pub fn new(translation: Vec3, rotation: Quat, scale: f32) -> Self {
        Transform {
            translation,
            rotation,
            scale,
        }
    }

    /// A translation.
    pub fn from_translation(translation: Vec3) -> Self {
        Transform {
            translation,
            ..Self::IDENTITY
        }
    }

    /// `self ∘ inner`: first `inner`, then `self`.
    pub fn compose(&self, inner: &Transform) -> Transform {
        Transform {
            translation: self.translation + self.rotation * (self.scale * inner.translation),
            rotation: (self.rotation * inner.rotation).normalize(),
            scale: self.scale * inner.scale,
        }
    }

    /// Maps `p` from the node's frame to its parent's.
    pub fn apply(&self, p: Vec3) -> Vec3 {
        self.translation + self.rotation * (self.scale * p)
    }

    /// Maps `p` from the parent's frame to the node's.
    pub fn apply_inverse(&self, p: Vec3) -> Vec3 {
        self.rotation.inverse() * (p - self.translation) / self.scale
    }

    /// Checks the parts and returns the transform with its rotation normalised.
    fn checked(&self, node: &str) -> Result<Transform, SceneError> {
        let non_finite = |field| SceneError::NonFinite {
            node: node.to_owned(),
            field,
        };
        if !self.translation.is_finite() {
            return Err(non_finite("translation"));
        }
        if !self.rotation.is_finite() {
            return Err(non_finite("rotation"));
        }
        if !self.scale.is_finite() {
            return Err(non_finite("scale"));
        }
        if self.scale <= 0.0 {
            return Err(SceneError::Scale {
                node: node.to_owned(),
                scale: self.scale,
            });
        }
        let len = self.rotation.as_dquat().length();
        if len < 1e-12 {
            return Err(SceneError::Rotation {
                node: node.to_owned(),
            });
        }
        Ok(Transform {
            rotation: (self.rotation.as_dquat() / len).as_quat(),
            ..*self
        })
    }
}

impl Default for Transform {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// A node of a scene tree. Distances are in the parent's units: a [`SceneNode::Transform`]'s
/// scale scales its subtree's distances and its operators' parameters alike.
#[derive(Clone, Debug)]
pub enum SceneNode {
    /// A trained model placed by `transform` (its mesh coordinates are the node's frame).
    Model {
        /// The model, shared by every leaf that places it.
        model: Arc<NeuralSdf>,
        /// Its placement.
        transform: Transform,
    },
    /// An analytic primitive placed by `transform`.
    Primitive {
        /// The shape.
        primitive: Primitive,
        /// Its placement.
        transform: Transform,
    },
    /// `min` of the children (at least one).
    Union(Vec<SceneNode>),
    /// `max` of the children (at least one).
    Intersection(Vec<SceneNode>),
    /// The first child minus all the others: `max(a, −b, −c, …)` (at least one child).
    Difference(Vec<SceneNode>),
    /// Polynomial smooth minimum with blend radius `k > 0`, a left fold over the children.
    SmoothUnion {
        /// Blend radius: the children are blended where their values differ by less than `k`.
        k: f32,
        /// At least one.
        children: Vec<SceneNode>,
    },
    /// Smooth maximum, `−smin(−a, −b)`, a left fold.
    SmoothIntersection {
        /// Blend radius `> 0`.
        k: f32,
        /// At least one.
        children: Vec<SceneNode>,
    },
    /// Smooth difference, `−smin(−a, b)`, a left fold.
    SmoothDifference {
        /// Blend radius `> 0`.
        k: f32,
        /// At least one.
        children: Vec<SceneNode>,
    },
    /// `d − r`: grows the shape by `r` (shrinks it for `r < 0`).
    Offset {
        /// The offset, finite.
        r: f32,
        /// The shape.
        child: Box<SceneNode>,
    },
    /// `|d| − t`: a shell of thickness `2t` around the surface.
    Shell {
        /// Half the thickness, `> 0`.
        t: f32,
        /// The shape.
        child: Box<SceneNode>,
    },
    /// A subtree placed by `transform`.
    Transform {
        /// Its placement.
        transform: Transform,
        /// The subtree.
        child: Box<SceneNode>,
    },
}

impl SceneNode {
    /// A placed model.
    pub fn model(model: Arc<NeuralSdf>, transform: Transform) -> Self {
        SceneNode::Model { model, transform }
    }

    /// A placed primitive.
    pub fn primitive(primitive: Primitive, transform: Transform) -> Self {
        SceneNode::Primitive {
            primitive,
            transform,
        }
    }

    /// This node inside a [`SceneNode::Transform`].
    pub fn transformed(self, transform: Transform) -> Self {
        SceneNode::Transform {
            transform,
            child: Box::new(self),
        }
    }

    /// The operator's name in scene files (`"union"`, `"smooth_union"`, `"model"`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            SceneNode::Model { .. } => "model",
            SceneNode::Primitive { primitive, .. } => primitive.name(),
            SceneNode::Union(_) => "union",
            SceneNode::Intersection(_) => "intersection",
            SceneNode::Difference(_) => "difference",
            SceneNode::SmoothUnion { .. } => "smooth_union",
            SceneNode::SmoothIntersection { .. } => "smooth_intersection",
            SceneNode::SmoothDifference { .. } => "smooth_difference",
            SceneNode::Offset { .. } => "offset",
            SceneNode::Shell { .. } => "shell",
            SceneNode::Transform { .. } => "transform",
        }
    }
}

/// What a leaf evaluates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LeafKind {
    /// The model at this index of [`Scene::models`].
    Model(usize),
    /// A primitive.
    Primitive(Primitive),
}

/// A leaf of the compiled scene: what it evaluates and its placement in the scene's frame (all
/// the transforms above it composed). Its value in the scene is `scale · d(apply_inverse(x))`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Leaf {
    /// The shape.
    pub kind: LeafKind,
    /// From the leaf's frame to the scene's.
    pub transform: Transform,
}

/// One step of the compiled program, run on a stack of values. Parameters are in the scene's
/// units (the scales of the transforms above the operator applied).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Instruction {
    /// Push leaf `i` of [`Scene::leaves`].
    Leaf(u32),
    /// Pop `b`, `a`; push `min(a, b)`.
    Union,
    /// Pop `b`, `a`; push `max(a, b)`.
    Intersection,
    /// Pop `b`, `a`; push `max(a, −b)`.
    Difference,
    /// Pop `b`, `a`; push `smin(a, b, k)`.
    SmoothUnion(f32),
    /// Pop `b`, `a`; push `−smin(−a, −b, k)`.
    SmoothIntersection(f32),
    /// Pop `b`, `a`; push `−smin(−a, b, k)`.
    SmoothDifference(f32),
    /// Pop `d`; push `d − r`.
    Offset(f32),
    /// Pop `d`; push `|d| − t`.
    Shell(f32),
}

/// A validated, compiled scene: its leaves, its distinct models and the post-order program
/// that combines them. Build it with [`Scene::new`] or load it with
/// [`Scene::load`]; query it with the methods of
/// [`crate::serve::scene::cpu`].
#[derive(Debug)]
pub struct Scene {
    program: Vec<Instruction>,
    leaves: Vec<Leaf>,
    models: Vec<Arc<NeuralSdf>>,
    /// Each model's Lipschitz estimate and local bounds, measured on first use.
    lipschitz: Vec<OnceLock<LocalLipschitz>>,
    /// Each model's value floors per cell ([`CellFloors`]), measured on first use.
    floors: Vec<OnceLock<CellFloors>>,
    /// Each leaf's place in the tree.
    leaf_paths: Vec<String>,
    depth: usize,
}

impl Scene {
    /// Validates and compiles a tree. Every error names the node (see [`SceneError`]).
    pub fn new(root: SceneNode) -> Result<Scene, SceneError> {
        let mut c = Compiler::default();
        c.node(&root, "root".to_owned(), 1, &Transform::IDENTITY)?;
        let lipschitz = c.models.iter().map(|_| OnceLock::new()).collect();
        let floors = c.models.iter().map(|_| OnceLock::new()).collect();
        Ok(Scene {
            program: leaves_first(&c.program),
            leaves: c.leaves,
            models: c.models,
            lipschitz,
            floors,
            leaf_paths: c.paths,
            depth: c.depth,
        })
    }

    /// The post-order program: run it on a stack; one value is left, the scene's.
    pub fn program(&self) -> &[Instruction] {
        &self.program
    }

    /// The leaves, in the tree's order (depth first, children in order): the numbers that
    /// [`Instruction::Leaf`] and query results name. The program may push them in another
    /// order (a union's leaves before its sub-trees).
    pub fn leaves(&self) -> &[Leaf] {
        &self.leaves
    }

    /// The distinct models, in order of first appearance.
    pub fn models(&self) -> &[Arc<NeuralSdf>] {
        &self.models
    }

    /// Where leaf `leaf` is in the tree, as a path (`root.children[2]`).
    pub fn leaf_path(&self, leaf: usize) -> Option<&str> {
        self.leaf_paths.get(leaf).map(String::as_str)
    }

    /// The depth of the tree (the root alone is 1).
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// The Lipschitz estimate of model `model` (see [`super::lipschitz`]), measured on first
    /// call; `None` for an index past [`Scene::models`].
    pub fn model_lipschitz(&self, model: usize) -> Option<f32> {
        Some(self.model_local_lipschitz(model)?.global())
    }

    /// Model `model`'s bounds per cell of its box ([`LocalLipschitz`]), measured with its
    /// estimate on first call (the same bound everywhere after
    /// [`Scene::set_model_lipschitz`]); `None` for an index past [`Scene::models`].
    pub fn model_local_lipschitz(&self, model: usize) -> Option<&LocalLipschitz> {
        let cell = self.lipschitz.get(model)?;
        Some(cell.get_or_init(|| LocalLipschitz::measure(&self.models[model])))
    }

    /// A floor of model `model`'s network value over its normalised cube: the smallest of
    /// [`Scene::model_cell_floors`]; `None` for an index past [`Scene::models`].
    pub fn model_value_floor(&self, model: usize) -> Option<f32> {
        Some(self.model_cell_floors(model)?.min())
    }

    /// Floors of model `model`'s network value per cell of its normalised cube, which the
    /// GPU's culling reads ([`CellFloors`], with [`Scene::model_local_lipschitz`]'s bounds;
    /// raised to the weights' interval bound, rigorous but loose: −3.03 against a smallest
    /// value of −0.40 for a trained spot), measured on first call; `None` for an index past
    /// [`Scene::models`].
    pub fn model_cell_floors(&self, model: usize) -> Option<&CellFloors> {
        let cell = self.floors.get(model)?;
        let local = self.model_local_lipschitz(model)?;
        Some(cell.get_or_init(|| {
            let network = &self.models[model];
            let mut floors = CellFloors::measure(network, local);
            floors.raise_to(crate::serve::wgsl::phi_lower_bound(
                network.network(),
                network.lod(),
            ));
            floors
        }))
    }

    /// Replaces model `model`'s measured estimate by a bound the caller knows (finite, `> 0`)
    /// of its network's slope in its box: its local bounds ([`Scene::model_local_lipschitz`])
    /// become that bound, and its estimate ([`Scene::model_lipschitz`]) `√(1 + value²)`, which
    /// also bounds the model's distance outside its box (the network's at the clamped point plus
    /// the distance to the box).
    pub fn set_model_lipschitz(&mut self, model: usize, value: f32) -> Result<(), SceneError> {
        let models = self.models.len();
        match self.lipschitz.get_mut(model) {
            Some(cell) if value.is_finite() && value > 0.0 => {
                *cell = OnceLock::from(LocalLipschitz::uniform(value));
                // The floor depends on the slope bound.
                self.floors[model] = OnceLock::new();
                Ok(())
            }
            _ => Err(SceneError::Lipschitz {
                model,
                value,
                models,
            }),
        }
    }

    /// The Lipschitz constant of the whole scene: 1 for a scene of primitives, else the
    /// largest model estimate (at least 1). Measures the models not measured yet.
    pub fn lipschitz(&self) -> f32 {
        (0..self.models.len())
            .filter_map(|m| self.model_lipschitz(m))
            .fold(1.0, f32::max)
    }

    /// Leaf `leaf`'s Lipschitz bound: 1 for a primitive, its model's estimate (at least 1).
    pub(crate) fn leaf_lipschitz(&self, leaf: usize) -> f32 {
        match self.leaves[leaf].kind {
            LeafKind::Model(m) => self.model_lipschitz(m).unwrap_or(1.0).max(1.0),
            LeafKind::Primitive(_) => 1.0,
        }
    }

    /// What the ray tracer's step needs of each instruction of [`Scene::program`] (see
    /// [`Scene::trace_rays`]): where its sub-tree starts (its models' local Lipschitz bounds
    /// bound its slope near a point), and whether its value is traced against `−c` instead of
    /// `c` (an odd number of subtracted operands of differences above it).
    pub fn trace_plan(&self) -> Vec<TraceStep> {
        let program = &self.program;
        let start = subtree_starts(program);
        // Backward: the level's sign, from the root down (children come before parents).
        let mut flipped = vec![false; program.len()];
        for i in (0..program.len()).rev() {
            let binary = !matches!(
                program[i],
                Instruction::Leaf(_) | Instruction::Offset(_) | Instruction::Shell(_)
            );
            if matches!(program[i], Instruction::Leaf(_)) {
                continue;
            }
            // The last operand ends right before its parent; the first before the last.
            let last = i - 1;
            flipped[last] = flipped[i] ^ matches!(program[i], Instruction::Difference);
            if binary {
                flipped[start[last] - 1] = flipped[i];
            }
        }
        flipped
            .into_iter()
            .zip(start)
            .map(|(flipped, first)| TraceStep { flipped, first })
            .collect()
    }
}

/// Each instruction's sub-tree's first instruction: its sub-tree is `program[start..=i]`.
fn subtree_starts(program: &[Instruction]) -> Vec<usize> {
    let mut start = vec![0usize; program.len()];
    let mut stack: Vec<usize> = Vec::new();
    for (i, instruction) in program.iter().enumerate() {
        start[i] = match *instruction {
            Instruction::Leaf(_) => i,
            Instruction::Offset(_) | Instruction::Shell(_) => start[stack.pop().expect("balanced")],
            _ => {
                stack.pop().expect("balanced");
                start[stack.pop().expect("balanced")]
            }
        };
        stack.push(i);
    }
    start
}

/// `program` with each chain of sharp unions taking its leaves first (in their order), then
/// its other operands: `min` does not depend on the order, and the GPU code can skip a
/// union's later operands where their floors say they cannot change it (a sub-tree first would
/// always be evaluated). Leaf numbers stay those of the tree.
fn leaves_first(program: &[Instruction]) -> Vec<Instruction> {
    let start = subtree_starts(program);
    let mut out = Vec::with_capacity(program.len());
    if let Some(root) = program.len().checked_sub(1) {
        emit_leaves_first(program, &start, root, &mut out);
    }
    out
}

/// Appends the sub-tree ending at `end`, its unions' leaves first.
fn emit_leaves_first(
    program: &[Instruction],
    start: &[usize],
    end: usize,
    out: &mut Vec<Instruction>,
) {
    match program[end] {
        Instruction::Leaf(_) => out.push(program[end]),
        Instruction::Offset(_) | Instruction::Shell(_) => {
            emit_leaves_first(program, start, end - 1, out);
            out.push(program[end]);
        }
        Instruction::Union => {
            // The chain's operands (each ends right before its union, the first before the
            // deepest union), collected without recursing down the chain.
            let mut operands = Vec::new();
            let mut node = end;
            while program[node] == Instruction::Union {
                operands.push(node - 1);
                node = start[node - 1] - 1;
            }
            operands.push(node);
            operands.reverse();
            let (leaves, others): (Vec<usize>, Vec<usize>) = operands
                .into_iter()
                .partition(|&o| matches!(program[o], Instruction::Leaf(_)));
            for (k, operand) in leaves.into_iter().chain(others).enumerate() {
                emit_leaves_first(program, start, operand, out);
                if k > 0 {
                    out.push(Instruction::Union);
                }
            }
        }
        binary => {
            let last = end - 1;
            emit_leaves_first(program, start, start[last] - 1, out);
            emit_leaves_first(program, start, last, out);
            out.push(binary);
        }
    }
}

/// One instruction's part in the ray tracer's step (see [`Scene::trace_plan`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceStep {
    /// Whether its value is traced against `−c` (under a difference's subtracted operand).
    pub flipped: bool,
    /// The sub-tree's first instruction: it is `program[first..=i]`, its leaves those pushed
    /// there.
    pub first: usize,
}

impl Scene {
    /// The model leaves of instruction `i`'s sub-tree (`step` its [`TraceStep`]): the leaves
    /// whose local Lipschitz bounds bound its slope near a point.
    pub(crate) fn subtree_models(&self, i: usize, step: &TraceStep) -> Vec<usize> {
        self.program[step.first..=i]
            .iter()
            .filter_map(|instruction| match *instruction {
                Instruction::Leaf(l)
                    if matches!(self.leaves[l as usize].kind, LeafKind::Model(_)) =>
                {
                    Some(l as usize)
                }
                _ => None,
            })
            .collect()
    }
}

/// Walks the tree depth first, validating and emitting the program.
#[derive(Default)]
struct Compiler {
    program: Vec<Instruction>,
    leaves: Vec<Leaf>,
    models: Vec<Arc<NeuralSdf>>,
    paths: Vec<String>,
    depth: usize,
}

impl Compiler {
    /// Emits `node` (at `path`, `depth`, under the composed transform `outer`).
    fn node(
        &mut self,
        node: &SceneNode,
        path: String,
        depth: usize,
        outer: &Transform,
    ) -> Result<(), SceneError> {
        if depth > MAX_DEPTH {
            return Err(SceneError::TooDeep {
                node: path,
                limit: MAX_DEPTH,
            });
        }
        self.depth = self.depth.max(depth);
        // Operator parameters are in the subtree's units: the scene's are `outer.scale` times.
        let s = outer.scale;
        match node {
            SceneNode::Model { model, transform } => {
                let index = match self.models.iter().position(|m| Arc::ptr_eq(m, model)) {
                    Some(i) => i,
                    None if self.models.len() == MAX_MODELS => {
                        return Err(SceneError::TooManyModels {
                            node: path,
                            limit: MAX_MODELS,
                        });
                    }
                    None => {
                        self.models.push(model.clone());
                        self.models.len() - 1
                    }
                };
                self.leaf(LeafKind::Model(index), transform, path, outer)
            }
            SceneNode::Primitive {
                primitive,
                transform,
            } => {
                if let Err((field, requirement)) = primitive.check() {
                    return Err(parameter_error(path, primitive, field, requirement));
                }
                self.leaf(LeafKind::Primitive(*primitive), transform, path, outer)
            }
            SceneNode::Union(children) => {
                self.fold(node, children, path, depth, outer, || Instruction::Union)
            }
            SceneNode::Intersection(children) => {
                self.fold(node, children, path, depth, outer, || {
                    Instruction::Intersection
                })
            }
            SceneNode::Difference(children) => {
                self.fold(node, children, path, depth, outer, || {
                    Instruction::Difference
                })
            }
            SceneNode::SmoothUnion { k, children } => {
                let k = in_scene_units(&path, "k", blend(&path, *k)?, s)?;
                self.fold(node, children, path, depth, outer, || {
                    Instruction::SmoothUnion(k)
                })
            }
            SceneNode::SmoothIntersection { k, children } => {
                let k = in_scene_units(&path, "k", blend(&path, *k)?, s)?;
                self.fold(node, children, path, depth, outer, || {
                    Instruction::SmoothIntersection(k)
                })
            }
            SceneNode::SmoothDifference { k, children } => {
                let k = in_scene_units(&path, "k", blend(&path, *k)?, s)?;
                self.fold(node, children, path, depth, outer, || {
                    Instruction::SmoothDifference(k)
                })
            }
            SceneNode::Offset { r, child } => {
                if !r.is_finite() {
                    return Err(SceneError::NonFinite {
                        node: path,
                        field: "r",
                    });
                }
                let r = if *r == 0.0 {
                    0.0
                } else {
                    in_scene_units(&path, "r", *r, s)?
                };
                self.unary(child, &path, depth, outer)?;
                self.program.push(Instruction::Offset(r));
                Ok(())
            }
            SceneNode::Shell { t, child } => {
                if !t.is_finite() {
                    return Err(SceneError::NonFinite {
                        node: path,
                        field: "t",
                    });
                }
                if *t <= 0.0 {
                    return Err(SceneError::Parameter {
                        node: path,
                        field: "t",
                        value: *t,
                        requirement: "> 0",
                    });
                }
                let t = in_scene_units(&path, "t", *t, s)?;
                self.unary(child, &path, depth, outer)?;
                self.program.push(Instruction::Shell(t));
                Ok(())
            }
            SceneNode::Transform { transform, child } => {
                let composed = placed(outer, transform, &path)?;
                self.node(child, format!("{path}.children[0]"), depth + 1, &composed)
            }
        }
    }

    /// Emits a leaf placed by `transform` under `outer`.
    fn leaf(
        &mut self,
        kind: LeafKind,
        transform: &Transform,
        path: String,
        outer: &Transform,
    ) -> Result<(), SceneError> {
        if self.leaves.len() == MAX_LEAVES {
            return Err(SceneError::TooManyLeaves {
                node: path,
                limit: MAX_LEAVES,
            });
        }
        let transform = placed(outer, transform, &path)?;
        self.program
            .push(Instruction::Leaf(self.leaves.len() as u32));
        self.leaves.push(Leaf { kind, transform });
        self.paths.push(path);
        Ok(())
    }

    /// The only child of a unary operator.
    fn unary(
        &mut self,
        child: &SceneNode,
        path: &str,
        depth: usize,
        outer: &Transform,
    ) -> Result<(), SceneError> {
        self.node(child, format!("{path}.children[0]"), depth + 1, outer)
    }

    /// An n-ary operator as a left fold of binary instructions, so the stack stays shallow.
    fn fold(
        &mut self,
        node: &SceneNode,
        children: &[SceneNode],
        path: String,
        depth: usize,
        outer: &Transform,
        op: impl Fn() -> Instruction,
    ) -> Result<(), SceneError> {
        if children.is_empty() {
            return Err(SceneError::Children {
                node: path,
                op: node.name(),
                expected: "at least 1",
                found: 0,
            });
        }
        for (i, child) in children.iter().enumerate() {
            self.node(child, format!("{path}.children[{i}]"), depth + 1, outer)?;
            if i > 0 {
                self.program.push(op());
            }
        }
        Ok(())
    }
}

/// `transform` (checked) composed under `outer`: an error where the composition leaves f32's
/// normal range, which no node's own check sees.
fn placed(outer: &Transform, transform: &Transform, path: &str) -> Result<Transform, SceneError> {
    let t = outer.compose(&transform.checked(path)?);
    let placement = |what, value| SceneError::Placement {
        node: path.to_owned(),
        what,
        value,
    };
    // Normal: finite, not zero, not subnormal (the scale is positive).
    if !t.scale.is_normal() {
        return Err(placement("scale", t.scale));
    }
    if !t.translation.is_finite() {
        return Err(placement("translation", t.translation.abs().max_element()));
    }
    Ok(t)
}

/// An operator's parameter `value` (non-zero, finite) in the scene's units: times the scale
/// `s` of the transforms above it, which must leave it finite and normal.
fn in_scene_units(path: &str, field: &'static str, value: f32, s: f32) -> Result<f32, SceneError> {
    let v = value * s;
    if v.is_normal() {
        Ok(v)
    } else {
        Err(SceneError::Placement {
            node: path.to_owned(),
            what: field,
            value: v,
        })
    }
}

/// Checks a blend radius.
fn blend(path: &str, k: f32) -> Result<f32, SceneError> {
    if !k.is_finite() {
        return Err(SceneError::NonFinite {
            node: path.to_owned(),
            field: "k",
        });
    }
    if k <= 0.0 {
        return Err(SceneError::Parameter {
            node: path.to_owned(),
            field: "k",
            value: k,
            requirement: "> 0",
        });
    }
    Ok(k)
}

/// The error for a primitive's bad parameter `field`.
fn parameter_error(
    node: String,
    primitive: &Primitive,
    field: &'static str,
    requirement: &'static str,
) -> SceneError {
    if requirement == "finite" {
        return SceneError::NonFinite { node, field };
    }
    let value = match (*primitive, field) {
        (Primitive::Sphere { radius }, _) => radius,
        (Primitive::Box { half_extents }, _) => half_extents.min_element(),
        (Primitive::RoundBox { half_extents, .. }, "half_extents") => half_extents.min_element(),
        (Primitive::RoundBox { radius, .. }, _) => radius,
        (Primitive::Capsule { radius, .. }, _) => radius,
        (Primitive::Torus { major, .. }, "major") => major,
        (Primitive::Torus { minor, .. }, _) => minor,
        (Primitive::Plane { normal, .. }, _) => normal.length(),
        (Primitive::Cylinder { radius, .. }, "radius") => radius,
        (Primitive::Cylinder { half_height, .. }, _) => half_height,
    };
    SceneError::Parameter {
        node,
        field,
        value,
        requirement,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ball(x: f32) -> SceneNode {
        SceneNode::primitive(
            Primitive::Sphere { radius: 1.0 },
            Transform::from_translation(Vec3::X * x),
        )
    }

    /// The most values the program's stack holds.
    fn stack_height(program: &[Instruction]) -> usize {
        let (mut height, mut most) = (0usize, 0usize);
        for i in program {
            match i {
                Instruction::Leaf(_) => height += 1,
                Instruction::Offset(_) | Instruction::Shell(_) => {}
                _ => height -= 1,
            }
            most = most.max(height);
        }
        assert_eq!(height, 1, "one value is left");
        most
    }

    /// A union's leaves come first, its sub-trees after them in their order, its nested
    /// unions reordered the same way; other operators keep their operands' order, and leaves
    /// their tree numbers.
    #[test]
    fn unions_take_their_leaves_first() {
        use Instruction::*;
        let scene = Scene::new(SceneNode::Union(vec![
            SceneNode::Offset {
                r: 0.1,
                child: Box::new(ball(0.0)),
            },
            SceneNode::Union(vec![
                SceneNode::Difference(vec![ball(1.0), ball(2.0)]),
                ball(3.0),
            ]),
            ball(4.0),
        ]))
        .unwrap();
        assert_eq!(
            scene.program(),
            &[
                Leaf(4),
                Leaf(0),
                Offset(0.1),
                Union,
                Leaf(3),
                Leaf(1),
                Leaf(2),
                Difference,
                Union,
                Union,
            ]
        );
        assert_eq!(scene.leaf_path(3), Some("root.children[1].children[1]"));
        // Without sub-trees, or with them last already, nothing moves.
        let plain = Scene::new(SceneNode::Union(vec![ball(0.0), ball(1.0), ball(2.0)])).unwrap();
        assert_eq!(plain.program(), &[Leaf(0), Leaf(1), Union, Leaf(2), Union]);
    }

    /// A shader can size its stack by the depth: wide n-ary nodes fold as they go, so the
    /// stack holds at most one pending value per level plus the current one.
    #[test]
    fn the_stack_stays_within_the_depth() {
        let mut node = ball(0.0);
        for level in 1..MAX_DEPTH {
            let children = vec![ball(level as f32), node, ball(-(level as f32)), ball(0.5)];
            node = match level % 4 {
                0 => SceneNode::Union(children),
                1 => SceneNode::SmoothDifference { k: 0.1, children },
                2 => SceneNode::Intersection(children),
                _ => SceneNode::SmoothUnion { k: 0.2, children },
            };
        }
        let scene = Scene::new(node).unwrap();
        assert_eq!(scene.depth(), MAX_DEPTH);
        let height = stack_height(scene.program());
        assert!(height <= MAX_DEPTH + 1, "{height}");
        // The deep child is second: every level waits on one value.
        assert!(height >= MAX_DEPTH - 1, "{height}");
    }

    /// Transforms fold into the leaves, and operator parameters take the scale above them.
    #[test]
    fn transforms_fold_into_leaves_and_parameters() {
        let inner = SceneNode::SmoothUnion {
            k: 0.5,
            children: vec![ball(1.0), ball(-1.0)],
        };
        let outer = Transform::new(Vec3::Y, Quat::from_rotation_z(1.0), 3.0);
        let scene = Scene::new(
            SceneNode::Offset {
                r: 0.25,
                child: Box::new(inner),
            }
            .transformed(outer),
        )
        .unwrap();
        assert_eq!(
            scene.program(),
            [
                Instruction::Leaf(0),
                Instruction::Leaf(1),
                Instruction::SmoothUnion(1.5),
                Instruction::Offset(0.75),
            ]
        );
        let leaf = scene.leaves()[0].transform;
        assert!((leaf.apply(Vec3::ZERO) - outer.apply(Vec3::X)).length() < 1e-6);
        assert_eq!(leaf.scale, 3.0);
        assert_eq!(
            scene.leaf_path(1),
            Some("root.children[0].children[0].children[1]")
        );
    }
}
