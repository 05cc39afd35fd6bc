//! Skipping a union's sub-tree where it cannot change the union (WGSL): a floor of the
//! sub-tree's value, cheap to evaluate from its models' cell floors
//! ([`super::lipschitz::CellFloors`], `{prefix}_leaf_{l}_lb`) and its primitives' exact values,
//! decides whether its code runs. A group of models blended or carved together and placed
//! among others is then evaluated only near it, as single models already are
//! (`Scene::culled_union` and `Scene::leaf_union` in [`super::embed`]). Exact: `min(a, b) = a`
//! where `b ≥ a`, and the polynomial smooth minimum is `a` where `b ≥ a + k`.

use std::fmt::Write;

use crate::serve::scene::trace_wgsl::gap;
use crate::serve::scene::tree::{Instruction, LeafKind, Scene, TraceStep};
use crate::serve::wgsl::lit;

/// A sub-tree's code wrapped in the test of its floor: `open`, then the sub-tree's own code
/// (which defines `v{end}`, and `t{end}` for the tracer), then `close`, which define
/// `v{parent}` (and `t{parent}`).
pub(super) struct CulledSubtree {
    /// The sub-tree's last instruction.
    pub end: usize,
    /// The union or smooth union whose right operand it is.
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
    /// Per instruction `s`: `Some((end, parent))` where `program[s..=end]` is a sub-tree of more
    /// than one instruction, with a model, that is the right operand of the union or smooth
    /// union `parent` (`end + 1`). The sub-trees [`Scene::culled_subtree`] can skip.
    pub(super) fn culled_subtrees(&self, plan: &[TraceStep]) -> Vec<Option<(usize, usize)>> {
        let program = self.program();
        let mut starts = vec![None; program.len()];
        for (parent, instruction) in program.iter().enumerate() {
            if !matches!(
                instruction,
                Instruction::Union | Instruction::SmoothUnion(_)
            ) {
                continue;
            }
            let end = parent - 1;
            let start = plan[end].first;
            if start < end && !self.subtree_models(end, &plan[end]).is_empty() {
                starts[start] = Some((end, parent));
            }
        }
        starts
    }

    /// A floor of the value of `program[start..=end]` (WGSL): its models' cell floors, its
    /// primitives' values, through each operator's lower bound (a union's the smaller, a smooth
    /// union's less `k/4`, an intersection's the larger, a difference's its first operand's, an
    /// offset's less `r`, a shell's `max(·, 0) − t`).
    pub(super) fn subtree_floor(&self, prefix: &str, start: usize, end: usize) -> String {
        let mut stack: Vec<String> = Vec::new();
        for instruction in &self.program()[start..=end] {
            let floor = match *instruction {
                Instruction::Leaf(l) => match self.leaves()[l as usize].kind {
                    LeafKind::Model(_) => format!("{prefix}_leaf_{l}_lb(p)"),
                    LeafKind::Primitive(_) => format!("{prefix}_leaf_{l}_d(p)"),
                },
                Instruction::Offset(r) => format!("({} - {})", pop(&mut stack), lit(r)),
                Instruction::Shell(t) => {
                    format!("(max({}, 0.0) - {})", pop(&mut stack), lit(t))
                }
                binary => {
                    let (b, a) = (pop(&mut stack), pop(&mut stack));
                    match binary {
                        Instruction::Union => format!("min({a}, {b})"),
                        Instruction::SmoothUnion(k) => {
                            format!("(min({a}, {b}) - {})", lit(k / 4.0))
                        }
                        Instruction::Intersection | Instruction::SmoothIntersection(_) => {
                            format!("max({a}, {b})")
                        }
                        // max(a, −b) ≥ a, and the smooth form adds to it.
                        _ => a,
                    }
                }
            };
            stack.push(floor);
        }
        pop(&mut stack)
    }

    /// The sub-tree starting at `v`, if [`Scene::culled_subtrees`] lists it and the union's left
    /// operand is on top of `stack`: the code around its own that runs it only where its floor
    /// is below the left operand's value (plus `k`), or for the tracer where a floor of its
    /// radius is below the left operand's radius (a radius is at least its value's gap over the
    /// largest estimate of its models, or the gap itself where negative, through every
    /// operator).
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
        let k = match self.program()[parent] {
            Instruction::SmoothUnion(k) => k,
            _ => 0.0,
        };
        let floor = self.subtree_floor(prefix, v, end);
        let mut open = format!(
            "    // Instructions {v}..={end}, where their floor says they can change instruction {parent}.\n\
             \x20   var v{parent} = v{a};\n\
             \x20   let f{parent} = {floor};\n"
        );
        let value = if values == Program::Sample {
            format!("v{a}.d")
        } else {
            format!("v{a}")
        };
        let combine = match (values, k > 0.0) {
            (Program::Sample, false) => format!("{prefix}_pick_min(v{a}, v{end})"),
            (Program::Sample, true) => format!("{prefix}_smin(v{a}, v{end}, {})", lit(k)),
            (_, false) => format!("min(v{a}, v{end})"),
            (_, true) => format!("{prefix}_smin_d(v{a}, v{end}, {})", lit(k)),
        };
        let mut close = format!("        v{parent} = {combine};\n");
        let mut test = if k > 0.0 {
            format!("f{parent} < {value} + {}", lit(k))
        } else {
            format!("f{parent} < {value}")
        };
        if values == Program::Trace && k == 0.0 {
            // A sharp union's radius is the smaller of its operands'.
            let largest = self
                .subtree_models(end, &plan[end])
                .iter()
                .map(|&l| self.leaf_lipschitz(l))
                .fold(1.0f32, f32::max);
            let g = gap(&format!("f{parent}"), plan[end].flipped);
            let _ = writeln!(open, "    var t{parent} = t{a};");
            let _ = write!(
                test,
                " || {prefix}_term_floor({g}, {}) < t{a}",
                lit(1.0 / largest)
            );
            let _ = writeln!(close, "        t{parent} = min(t{a}, t{end});");
        }
        let _ = writeln!(open, "    if {test} {{");
        close.push_str("    }\n");
        if values == Program::Trace && k > 0.0 {
            // A smooth union's radius is its own, from its value.
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

/// The top of a floor expression stack.
fn pop(stack: &mut Vec<String>) -> String {
    stack.pop().expect("a balanced program")
}
