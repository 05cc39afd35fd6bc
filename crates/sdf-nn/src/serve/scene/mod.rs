//! Scenes of neural SDFs: trained models and analytic primitives, each placed by a rigid
//! transform with a uniform scale, combined by constructive solid geometry, blended, offset and
//! shelled; queried for distances, gradients, ray hits and closest points.
//!
//! ```
//! use glam::{Quat, Vec3};
//! use sdf_nn::serve::scene::{ProjectOptions, Primitive, Scene, SceneNode, Transform};
//!
//! let at = |x: f32| Transform::from_translation(Vec3::new(x, 0.0, 0.0));
//! let ball = |x| SceneNode::primitive(Primitive::Sphere { radius: 1.0 }, at(x));
//! // Two balls blended over a radius of 0.5, with a cylinder drilled through both.
//! let drill = SceneNode::primitive(
//!     Primitive::Cylinder { radius: 0.25, half_height: 3.0 },
//!     Transform::new(Vec3::ZERO, Quat::from_rotation_z(std::f32::consts::FRAC_PI_2), 1.0),
//! );
//! let blend = SceneNode::SmoothUnion { k: 0.5, children: vec![ball(-1.0), ball(1.0)] };
//! let scene = Scene::new(SceneNode::Difference(vec![blend, drill]))?;
//!
//! let p = scene.closest_point(Vec3::new(0.0, 3.0, 0.0), &ProjectOptions::default())?;
//! assert!(p.converged && scene.distance(p.point, 0.0).abs() < 1e-5);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! The rooms, each depending only on those before it: [`primitive`] (the analytic shapes and
//! their exact distances), [`lipschitz`] (a model's measured Lipschitz estimate), [`tree`]
//! (the tree, its validation, and its compiled form: a flat post-order program that every
//! evaluator walks), [`cpu`] (the CPU reference: distances, gradients, rays, closest points),
//! [`embed`] (the scene as WGSL for the caller's shader, and its weights' bind group),
//! [`gpu`] (batch queries on the GPU, [`GpuScene`]) and [`file`](mod@file) (the TOML scene
//! file).

pub mod bounds;
pub mod cpu;
pub mod embed;
pub mod file;
pub mod gpu;
pub mod lipschitz;
pub mod primitive;
mod program_wgsl;
mod trace_wgsl;
pub mod tree;

pub use cpu::{
    ClosestPoint, ProjectOptions, Ray, RayHit, SceneQueryError, SceneSample, TRACE_OVER_RELAXATION,
    TraceOptions,
};
pub use embed::{MAX_SCENE_PREFIX, SceneBindGroup, SceneGpuError};
pub use file::{SceneFileError, tree_from_toml};
pub use gpu::{GpuScene, SceneQueryBuffers, SceneQueryKind, SceneQueryParams};
pub use primitive::Primitive;
pub use tree::{
    Instruction, Leaf, LeafKind, MAX_DEPTH, MAX_LEAVES, MAX_MODELS, Scene, SceneError, SceneNode,
    TraceStep, Transform,
};
