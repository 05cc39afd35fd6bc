//! The scene's program as WGSL expressions ([`distance_expression`], [`sample_expression`]),
//! and the culling that skips an operand where it cannot change its parent: a floor of the
//! operand's value, cheap to evaluate from its models' cell floors
//! ([`super::lipschitz::CellFloors`], `{prefix}_leaf_{l}_lb`) and its primitives' exact values,
//! decides whether its code runs. A model, or a group of models blended or carved together,
//! placed among others is then evaluated only near it. Exact: `min(a, b) = a` where `b ≥ a`,
//! `max(a, −b) = a` where `b ≥ −a`, and the smooth forms where `b` is a further `k` away.
//! (Chains of leaves under one union take the nearest first: `Scene::leaf_union` in
//! [`super::embed`].)

use std::fmt::Write;

use crate::serve::scene::trace_wgsl::gap;
use crate::serve::scene::tree::{Instruction, LeafKind, Scene, TraceStep};
use crate::serve::wgsl::lit;

/// The most instructions of a group that is culled by its floor (a larger group's parts still
/// are).
const MAX_GROUP_INSTRUCTIONS: usize = 512;

/// An operand's code wrapped in the test of its floor: `open`, then the operand's own code
/// (which defines `v{end}`, and `t{end}` for the tracer), then `close`, which define
/// `v{parent}` (and `t{parent}`).
pub(super) struct CulledSubtree {
    /// The operand's last instruction.
    pub end: usize,
    /// The union, difference or their smooth form whose right operand it is.
    pub parent: usize,
    /// Code before the sub-tree's.
    pub open: String,
    /// Code after it.
    pub close: String,
}

/// Which of the scene's functions a program is generated for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Program {
    /// `{prefix}_distance(p)`.
    Distance,
    /// `{prefix}_sample(p)`: value, gradient, leaf.
    Sample,
    /// `{prefix}_trace(p, c)`: `d − c` and the tracer's step bound (`t{i}` beside `v{i}`).
    Trace,
}

impl Scene {
    /// Per instruction `s`: `Some((end, parent))` where `program[s..=end]` is a sub-tree with a
    /// model (a model leaf, or a group) that is the right operand of the union, difference or
    /// their smooth form `parent` (`end + 1`): the operands [`Scene::culled_subtree`] can skip.
    pub(super) fn culled_subtrees(&self, plan: &[TraceStep]) -> Vec<Option<(usize, usize)>> {
        let program = self.program();
        let mut starts = vec![None; program.len()];
        for (parent, instruction) in program.iter().enumerate() {
            if !matches!(
                instruction,
                Instruction::Union
                    | Instruction::SmoothUnion(_)
                    | Instruction::Difference
                    | Instruction::SmoothDifference(_)
            ) {
                continue;
            }
            let end = parent - 1;
            let start = plan[end].first;
            // Each culled group's floor reads all its leaves, and groups nest: a bound on the
            // floors' code (64 nested groups of 4096 leaves would be 2^18 lookups).
            if end - start < MAX_GROUP_INSTRUCTIONS
                && !self.subtree_models(end, &plan[end]).is_empty()
            {
                starts[start] = Some((end, parent));
            }
        }
        starts
    }

    /// A floor of the value of the sub-tree ending at `end` (WGSL statements appended to
    /// `code`, one `let fl{parent}_{i}` per instruction `i` it needs, so that no expression
    /// nests deeper than one operator: a fold of many operands would pass the WGSL parsers'
    /// nesting limits): its models' cell floors, its primitives' values, through each
    /// operator's lower bound (a union's the smaller, a smooth union's less `k/4`, an
    /// intersection's the larger, a difference's its first operand's, an offset's less `r`, a
    /// shell's `max(·, 0) − t`). The name of the floor's variable.
    pub(super) fn subtree_floor(
        &self,
        prefix: &str,
        end: usize,
        parent: usize,
        plan: &[TraceStep],
        code: &mut String,
    ) -> String {
        // Not `f{parent}`: `f16` and `f32` are WGSL's type names.
        let name = |i: usize| format!("fl{parent}_{i}");
        // Post-order over the instructions the floor needs (a difference's second operand is
        // not), without recursion: (instruction, operands done).
        let mut work = vec![(end, false)];
        while let Some((i, done)) = work.pop() {
            let instruction = self.program()[i];
            let unary = matches!(instruction, Instruction::Offset(_) | Instruction::Shell(_));
            // A binary instruction's operands end right before it (the second) and right
            // before the second's sub-tree (the first); a unary one's right before it.
            let (first, second) = match instruction {
                Instruction::Leaf(_) => (i, i),
                _ => (plan[i - 1].first.saturating_sub(1), i - 1),
            };
            let floor = match instruction {
                Instruction::Leaf(l) => match self.leaves()[l as usize].kind {
                    LeafKind::Model(_) => format!("{prefix}_leaf_{l}_lb(p)"),
                    LeafKind::Primitive(_) => format!("{prefix}_leaf_{l}_d(p)"),
                },
                _ if !done => {
                    work.push((i, true));
                    match instruction {
                        Instruction::Difference | Instruction::SmoothDifference(_) => {
                            work.push((first, false))
                        }
                        _ if unary => work.push((second, false)),
                        _ => {
                            work.push((second, false));
                            work.push((first, false));
                        }
                    }
                    continue;
                }
                Instruction::Offset(r) => format!("{} - {}", name(second), lit(r)),
                Instruction::Shell(t) => format!("max({}, 0.0) - {}", name(second), lit(t)),
                Instruction::Union => format!("min({}, {})", name(first), name(second)),
                Instruction::SmoothUnion(k) => {
                    format!("min({}, {}) - {}", name(first), name(second), lit(k / 4.0))
                }
                Instruction::Intersection | Instruction::SmoothIntersection(_) => {
                    format!("max({}, {})", name(first), name(second))
                }
                // max(a, −b) ≥ a, and the smooth form adds to it.
                _ => name(first),
            };
            let _ = writeln!(code, "    let {} = {floor};", name(i));
        }
        name(end)
    }

    /// The operand starting at `v`, if [`Scene::culled_subtrees`] lists it and its parent's
    /// left operand `a` is on top of `stack`: the code around its own that runs it only where
    /// its floor `f` can change the parent (a union: `f < a`, a difference: `f < −a`; `k` more
    /// for the smooth forms), or for the tracer where a floor of its radius can change a sharp
    /// parent's radius (the smaller of the two for a union, the larger of `a`'s and the
    /// negated operand's for a difference). A radius is at least its value's gap over the
    /// largest estimate of its models, or the gap itself where negative, through every
    /// operator.
    pub(super) fn culled_subtree(
        &self,
        prefix: &str,
        v: usize,
        stack: &[usize],
        values: Program,
        plan: &[TraceStep],
        subtrees: &[Option<(usize, usize)>],
    ) -> Option<CulledSubtree> {
        let (end, parent) = subtrees[v]?;
        let a = *stack.last()?;
        let instruction = self.program()[parent];
        let (k, carved) = match instruction {
            Instruction::SmoothUnion(k) => (k, false),
            Instruction::SmoothDifference(k) => (k, true),
            Instruction::Difference => (0.0, true),
            _ => (0.0, false),
        };
        let mut open = format!(
            "    // Instructions {v}..={end}, where their floor says they can change instruction {parent}.\n\
             \x20   var v{parent} = v{a};\n"
        );
        let floor = self.subtree_floor(prefix, end, parent, plan, &mut open);
        let _ = writeln!(open, "    let fl{parent} = {floor};");
        let value = if values == Program::Sample {
            format!("v{a}.d")
        } else {
            format!("v{a}")
        };
        let mut operands = vec![a, end];
        let combine = if values == Program::Sample {
            sample_expression(prefix, &instruction, &mut operands)
        } else {
            distance_expression(prefix, &instruction, &mut operands)
        };
        let mut close = format!("        v{parent} = {combine};\n");
        let threshold = match (carved, k > 0.0) {
            (false, false) => value,
            (false, true) => format!("{value} + {}", lit(k)),
            (true, false) => format!("-{value}"),
            (true, true) => format!("{} - {value}", lit(k)),
        };
        let mut test = format!("fl{parent} < {threshold}");
        if values == Program::Trace && k == 0.0 {
            // A sharp parent's radius is the smaller of its operands' (a union), or the larger
            // of its first's and the negated second's (a difference).
            let models = self.subtree_models(end, &plan[end]);
            let g = gap(&format!("fl{parent}"), plan[end].flipped);
            let (sign, pick) = if carved { ("-", "max") } else { ("", "min") };
            let _ = writeln!(open, "    var t{parent} = t{a};");
            let _ = write!(
                test,
                " || {} < {sign}t{a}",
                self.term_floor(prefix, &g, &models)
            );
            let _ = writeln!(close, "        t{parent} = {pick}(t{a}, {sign}t{end});");
        }
        let _ = writeln!(open, "    if {test} {{");
        close.push_str("    }\n");
        if values == Program::Trace && k > 0.0 {
            // A smooth operator's radius is its own, from its value.
            let _ = writeln!(
                close,
                "    let t{parent} = {};",
                self.trace_term(prefix, &format!("v{parent}"), parent, plan)
            );
        }
        Some(CulledSubtree {
            end,
            parent,
            open,
            close,
        })
    }
}

/// One instruction on distances alone; pops its operands' variable numbers from `stack`.
pub(super) fn distance_expression(
    prefix: &str,
    instruction: &Instruction,
    stack: &mut Vec<usize>,
) -> String {
    let mut pop = || format!("v{}", stack.pop().expect("balanced program"));
    match *instruction {
        Instruction::Leaf(l) => format!("{prefix}_leaf_{l}_d(p)"),
        Instruction::Offset(r) => format!("{} - {}", pop(), lit(r)),
        Instruction::Shell(t) => format!("abs({}) - {}", pop(), lit(t)),
        binary => {
            let (b, a) = (pop(), pop());
            match binary {
                Instruction::Union => format!("min({a}, {b})"),
                Instruction::Intersection => format!("max({a}, {b})"),
                Instruction::Difference => format!("max({a}, -{b})"),
                Instruction::SmoothUnion(k) => format!("{prefix}_smin_d({a}, {b}, {})", lit(k)),
                Instruction::SmoothIntersection(k) => {
                    format!("-{prefix}_smin_d(-{a}, -{b}, {})", lit(k))
                }
                Instruction::SmoothDifference(k) => {
                    format!("-{prefix}_smin_d(-{a}, {b}, {})", lit(k))
                }
                _ => unreachable!("unary instructions are matched above"),
            }
        }
    }
}

/// One instruction on samples (value, gradient, leaf), as the CPU's `combine`.
pub(super) fn sample_expression(
    prefix: &str,
    instruction: &Instruction,
    stack: &mut Vec<usize>,
) -> String {
    let mut pop = || format!("v{}", stack.pop().expect("balanced program"));
    let neg = |x: &str| format!("{prefix}_negate({x})");
    match *instruction {
        Instruction::Leaf(l) => format!("{prefix}_leaf_{l}(p)"),
        Instruction::Offset(r) => {
            let a = pop();
            format!("{prefix}_Sample({a}.d - {}, {a}.g, {a}.leaf)", lit(r))
        }
        Instruction::Shell(t) => format!("{prefix}_shell({}, {})", pop(), lit(t)),
        binary => {
            let (b, a) = (pop(), pop());
            match binary {
                Instruction::Union => format!("{prefix}_pick_min({a}, {b})"),
                Instruction::Intersection => format!("{prefix}_pick_max({a}, {b})"),
                Instruction::Difference => format!("{prefix}_pick_max({a}, {})", neg(&b)),
                Instruction::SmoothUnion(k) => format!("{prefix}_smin({a}, {b}, {})", lit(k)),
                Instruction::SmoothIntersection(k) => neg(&format!(
                    "{prefix}_smin({}, {}, {})",
                    neg(&a),
                    neg(&b),
                    lit(k)
                )),
                Instruction::SmoothDifference(k) => {
                    neg(&format!("{prefix}_smin({}, {b}, {})", neg(&a), lit(k)))
                }
                _ => unreachable!("unary instructions are matched above"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use glam::Vec3;

    use crate::serve::scene::{Primitive, SceneNode, Transform};
    use crate::{NeuralSdf, Nglod, Normalization};

    use super::*;

    /// `n` placed copies of a small baked sphere.
    fn copies(n: usize) -> Vec<SceneNode> {
        let sphere = Nglod::from_sdf(4, |p| p.length() - 0.5).unwrap();
        let model = Arc::new(
            NeuralSdf::from_model_file(
                sphere.to_model_file(Normalization::identity(), serde_json::Value::Null),
            )
            .unwrap(),
        );
        (0..n)
            .map(|i| {
                let at = Vec3::new(i as f32 * 0.3, 0.0, 0.0);
                SceneNode::model(model.clone(), Transform::from_translation(at))
            })
            .collect()
    }

    /// A group of more than [`MAX_GROUP_INSTRUCTIONS`] is not culled by one floor (its code
    /// would read every leaf's), but its models still are, each by its own; a smaller group is.
    #[test]
    fn large_groups_are_culled_by_their_parts() {
        let group = |n: usize| SceneNode::SmoothUnion {
            k: 0.1,
            children: copies(n),
        };
        let ball = || SceneNode::primitive(Primitive::Sphere { radius: 1.0 }, Transform::IDENTITY);
        for (n, groups) in [(10, 1), (300, 0)] {
            let scene = Scene::new(SceneNode::Union(vec![ball(), group(n)])).unwrap();
            let plan = scene.trace_plan();
            let culled = scene.culled_subtrees(&plan);
            let (mut singles, mut whole) = (0, 0);
            for (start, (end, _)) in culled
                .iter()
                .enumerate()
                .filter_map(|(s, c)| Some((s, (*c)?)))
            {
                if end == start {
                    singles += 1;
                } else {
                    whole += 1;
                }
            }
            assert_eq!(whole, groups, "{n} models");
            // Every model right of a smooth union.
            assert_eq!(singles, n - 1, "{n} models");
        }
    }

    /// Wide groups compile: their floors (a group of 250 leaves under a smooth union, 250
    /// carved by a difference) and the tracer's bound of a node over 250 models are flat
    /// statements, within the WGSL parsers' nesting limits (naga's is 200 levels), and no
    /// name the generator makes is a type's (instruction 32's floor was `f32`).
    #[test]
    fn wide_groups_compile() {
        const WIDE: usize = 250;
        let ball = || SceneNode::primitive(Primitive::Sphere { radius: 1.0 }, Transform::IDENTITY);
        let trees = [
            SceneNode::Union(vec![
                ball(),
                SceneNode::SmoothUnion {
                    k: 0.1,
                    children: copies(WIDE),
                },
            ]),
            SceneNode::Difference(vec![ball(), SceneNode::Union(copies(WIDE))]),
            SceneNode::Offset {
                r: 0.1,
                child: Box::new(SceneNode::SmoothUnion {
                    k: 0.1,
                    children: copies(WIDE),
                }),
            },
        ];
        for tree in trees {
            let scene = Scene::new(tree).unwrap();
            let source = scene
                .wgsl_with_prefix(0, "s", &wgpu::Limits::default())
                .unwrap();
            let module = naga::front::wgsl::parse_str(&source)
                .unwrap_or_else(|e| panic!("parse: {}", e.emit_to_string(&source)));
            naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                naga::valid::Capabilities::empty(),
            )
            .validate(&module)
            .unwrap_or_else(|e| panic!("validate: {}", e.emit_to_string(&source)));
        }
    }
}
