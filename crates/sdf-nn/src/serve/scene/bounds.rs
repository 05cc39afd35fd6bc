//! Where a scene's surface can be: a box that holds it, for the renderer's camera and the
//! extraction's grid.
//!
//! ```
//! use glam::Vec3;
//! use sdf_nn::serve::scene::{Primitive, Scene, SceneNode, Transform};
//!
//! let ball = |x: f32| SceneNode::primitive(
//!     Primitive::Sphere { radius: 1.0 },
//!     Transform::from_translation(Vec3::X * x),
//! );
//! let scene = Scene::new(SceneNode::Union(vec![ball(-2.0), ball(2.0)]))?;
//! assert_eq!(scene.bounds(), Some((Vec3::new(-3.0, -1.0, -1.0), Vec3::new(3.0, 1.0, 1.0))));
//! # Ok::<(), sdf_nn::serve::scene::SceneError>(())
//! ```
//!
//! A leaf's box is its shape's (a model's: its normalised cube in the scene, since its surface
//! lies inside the cube it was trained in), placed by its transform. Operators combine the boxes
//! of their children: a union holds the union of its children's boxes, an intersection their
//! intersection, a difference its first child's; a smooth operator grows its result by `k/4`
//! (the most the polynomial smooth minimum lowers a value), an offset by `r > 0` and a shell by
//! `t`. A plane is unbounded, and so is a union that holds one.

use glam::{DMat3, Vec3};

use crate::model_file::Normalization;
use crate::serve::scene::primitive::Primitive;
use crate::serve::scene::tree::{Instruction, Leaf, LeafKind, Scene};

/// An axis-aligned box (`None`: unbounded).
type Bounds = Option<(Vec3, Vec3)>;

impl Scene {
    /// A box that holds the scene's surface (at level 0), or `None` if the surface may be
    /// unbounded (a plane under a union).
    pub fn bounds(&self) -> Bounds {
        let mut stack: Vec<Bounds> = Vec::new();
        let grow =
            |b: Bounds, by: f32| b.map(|(lo, hi)| (lo - Vec3::splat(by), hi + Vec3::splat(by)));
        for instruction in self.program() {
            let value = match *instruction {
                Instruction::Leaf(l) => self.leaf_bounds(&self.leaves()[l as usize]),
                Instruction::Offset(r) => grow(pop(&mut stack), r.max(0.0)),
                Instruction::Shell(t) => grow(pop(&mut stack), t),
                binary => {
                    let b = pop(&mut stack);
                    let a = pop(&mut stack);
                    match binary {
                        Instruction::Union => union(a, b),
                        Instruction::SmoothUnion(k) => grow(union(a, b), k * 0.25),
                        Instruction::Intersection => intersection(a, b),
                        Instruction::SmoothIntersection(k) => grow(intersection(a, b), k * 0.25),
                        Instruction::Difference => a,
                        Instruction::SmoothDifference(k) => grow(a, k * 0.25),
                        _ => unreachable!("unary instructions are matched above"),
                    }
                }
            };
            stack.push(value);
        }
        pop(&mut stack)
    }

    /// The cube the renderer frames and the extraction grids for level `level`: centred on
    /// [`Scene::bounds`] grown by the level (if positive), its half side the box's largest
    /// half extent. An unbounded scene is framed by its bounded leaves (a plane is then cut at
    /// their box); a scene of planes alone by the cube `[-1, 1]³`. As a [`Normalization`]:
    /// `scale` is one over the half side.
    pub fn frame(&self, level: f32) -> Normalization {
        let bounds = self.bounds().or_else(|| {
            self.leaves()
                .iter()
                .map(|l| self.leaf_bounds(l))
                .fold(None, |acc: Bounds, b| match (acc, b) {
                    (None, b) => b,
                    (a, None) => a,
                    (a, b) => union(a, b),
                })
        });
        let Some((lo, hi)) = bounds else {
            return Normalization::identity();
        };
        let grown = level.max(0.0);
        let half = ((hi - lo) * 0.5).max_element() + grown;
        Normalization {
            center: ((lo + hi) * 0.5).as_dvec3(),
            scale: 1.0 / half.max(1e-6),
        }
    }

    /// The box of one leaf in the scene's frame.
    fn leaf_bounds(&self, leaf: &Leaf) -> Bounds {
        let (lo, hi) = match leaf.kind {
            LeafKind::Model(m) => {
                let n = self.models()[m].normalization();
                let half = Vec3::splat(1.0 / n.scale);
                let c = n.center.as_vec3();
                (c - half, c + half)
            }
            LeafKind::Primitive(p) => {
                let half = match p {
                    Primitive::Sphere { radius } => Vec3::splat(radius),
                    Primitive::Box { half_extents } => half_extents,
                    Primitive::RoundBox { half_extents, .. } => half_extents,
                    Primitive::Capsule { a, b, radius } => {
                        let (lo, hi) = (
                            a.min(b) - Vec3::splat(radius),
                            a.max(b) + Vec3::splat(radius),
                        );
                        return Some(place(leaf, lo, hi));
                    }
                    Primitive::Torus { major, minor } => {
                        Vec3::new(major + minor, minor, major + minor)
                    }
                    Primitive::Plane { .. } => return None,
                    Primitive::Cylinder {
                        radius,
                        half_height,
                    } => Vec3::new(radius, half_height, radius),
                };
                (-half, half)
            }
        };
        Some(place(leaf, lo, hi))
    }
}

/// The box of the box `lo..hi` of a leaf's frame, placed in the scene.
fn place(leaf: &Leaf, lo: Vec3, hi: Vec3) -> (Vec3, Vec3) {
    let t = &leaf.transform;
    let centre = t.apply((lo + hi) * 0.5);
    // |R| · half extents: the half extents of the rotated box.
    let r = DMat3::from_quat(t.rotation.as_dquat().normalize());
    let abs = DMat3::from_cols(r.x_axis.abs(), r.y_axis.abs(), r.z_axis.abs());
    let half = (abs * ((hi - lo) * 0.5 * t.scale).as_dvec3()).as_vec3();
    (centre - half, centre + half)
}

fn union(a: Bounds, b: Bounds) -> Bounds {
    let ((a0, a1), (b0, b1)) = (a?, b?);
    Some((a0.min(b0), a1.max(b1)))
}

fn intersection(a: Bounds, b: Bounds) -> Bounds {
    match (a, b) {
        (None, b) => b,
        (a, None) => a,
        (Some((a0, a1)), Some((b0, b1))) => {
            let (lo, hi) = (a0.max(b0), a1.min(b1));
            // Disjoint boxes: an empty surface; keep a point so that the box stays valid.
            Some((lo.min(hi), hi.max(lo.min(hi))))
        }
    }
}

fn pop(stack: &mut Vec<Bounds>) -> Bounds {
    stack.pop().expect("the scene's program is balanced")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::serve::scene::{SceneNode, Transform};
    use glam::Quat;

    fn prim(p: Primitive, t: Transform) -> SceneNode {
        SceneNode::primitive(p, t)
    }

    /// Every point where the scene is at or below zero lies in its box (sampled), and the box
    /// is not much larger than the shapes.
    #[test]
    fn the_surface_lies_in_the_box() {
        let turn = Transform::new(Vec3::new(1.0, 2.0, 0.0), Quat::from_rotation_z(0.7), 1.5);
        let scene = Scene::new(SceneNode::SmoothUnion {
            k: 0.4,
            children: vec![
                prim(
                    Primitive::Box {
                        half_extents: Vec3::new(1.0, 0.2, 0.5),
                    },
                    turn,
                ),
                prim(
                    Primitive::Capsule {
                        a: Vec3::ZERO,
                        b: Vec3::X * 2.0,
                        radius: 0.3,
                    },
                    Transform::from_translation(Vec3::Y * -2.0),
                ),
                SceneNode::Offset {
                    r: 0.2,
                    child: Box::new(prim(
                        Primitive::Torus {
                            major: 1.0,
                            minor: 0.2,
                        },
                        Transform::from_translation(Vec3::Z * 3.0),
                    )),
                },
            ],
        })
        .unwrap();
        let (lo, hi) = scene.bounds().unwrap();
        let grid = 40;
        let (glo, ghi) = (lo - Vec3::splat(1.0), hi + Vec3::splat(1.0));
        let mut inside = 0;
        for i in 0..grid * grid * grid {
            let f = Vec3::new(
                (i % grid) as f32,
                (i / grid % grid) as f32,
                (i / grid / grid) as f32,
            ) / (grid - 1) as f32;
            let p = glo + (ghi - glo) * f;
            if scene.distance(p, 0.0) <= 0.0 {
                inside += 1;
                assert!(
                    p.cmpge(lo).all() && p.cmple(hi).all(),
                    "{p} is inside the scene, outside {lo}..{hi}"
                );
            }
        }
        assert!(inside > 100);
        // A plane under a union makes it unbounded; the frame falls back to the other leaves.
        let with_plane = Scene::new(SceneNode::Union(vec![
            prim(
                Primitive::Sphere { radius: 1.0 },
                Transform::from_translation(Vec3::X * 5.0),
            ),
            prim(
                Primitive::Plane {
                    normal: Vec3::Y,
                    offset: 0.0,
                },
                Transform::IDENTITY,
            ),
        ]))
        .unwrap();
        assert_eq!(with_plane.bounds(), None);
        let frame = with_plane.frame(0.0);
        assert_eq!((frame.center, frame.scale), (glam::DVec3::X * 5.0, 1.0));
        // An intersection with a plane is bounded by the other child.
        let cut = Scene::new(SceneNode::Intersection(vec![
            prim(Primitive::Sphere { radius: 1.0 }, Transform::IDENTITY),
            prim(
                Primitive::Plane {
                    normal: Vec3::Y,
                    offset: 0.0,
                },
                Transform::IDENTITY,
            ),
        ]))
        .unwrap();
        assert_eq!(cut.bounds(), Some((Vec3::splat(-1.0), Vec3::splat(1.0))));
    }
}
