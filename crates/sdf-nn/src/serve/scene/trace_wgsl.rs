//! The tracer's terms in a scene's WGSL (`{prefix}_trace`): each instruction's free-ball radius
//! from its models' local Lipschitz bounds ([`super::lipschitz::LocalLipschitz`]), the lookup
//! functions of those bounds and of the models' value floors that the culling reads
//! ([`super::lipschitz::CellFloors`]), and the tables both read after each model's weights. The
//! CPU reference's twin of the terms is `trace_values` in [`super::cpu`].

use std::fmt::Write;

use crate::serve::scene::lipschitz::{GRID, LOCAL_CELLS};
use crate::serve::scene::tree::{Instruction, LeafKind, Scene, TraceStep};
use crate::serve::wgsl::lit;

/// Floats of a model's local Lipschitz tables (cells and blocks) after its weights.
pub(super) const LIPSCHITZ_TABLES: usize = 2 * LOCAL_CELLS * LOCAL_CELLS * LOCAL_CELLS;

/// Floats of all a model's tables after its weights: the Lipschitz tables, then the value
/// floors of its [`GRID`]³ cells.
pub(super) const MODEL_TABLES: usize = LIPSCHITZ_TABLES + GRID * GRID * GRID;

impl Scene {
    /// Instruction `v`'s term of the tracer's bound for its value `x` (WGSL): the value less
    /// its level over the largest local Lipschitz bound of the models under it (the CPU's
    /// `trace_values`); over 1 without models.
    pub(super) fn trace_term(&self, prefix: &str, x: &str, v: usize, plan: &[TraceStep]) -> String {
        let g = gap(x, plan[v].flipped);
        match self.program()[v] {
            Instruction::Leaf(l) => self.leaf_term(prefix, &g, l as usize),
            _ if self.subtree_models(v, &plan[v]).is_empty() => g,
            _ => format!("{prefix}_node_{v}_t(p, {g})"),
        }
    }

    /// Leaf `l`'s term for a gap `g` (WGSL): `g` for a primitive, `g` over the model's local
    /// bound for a model.
    pub(super) fn leaf_term(&self, prefix: &str, g: &str, l: usize) -> String {
        match self.leaves()[l].kind {
            LeafKind::Model(_) => format!("{prefix}_leaf_{l}_t(p, {g})"),
            LeafKind::Primitive(_) => g.to_owned(),
        }
    }

    /// A floor of leaf `l`'s term from a floor `g` of its gap (WGSL), for culling
    /// ([`Scene::term_floor`] of the leaf's model, if it is one).
    pub(super) fn leaf_term_floor(&self, prefix: &str, g: &str, l: usize) -> String {
        match self.leaves()[l].kind {
            LeafKind::Model(_) => self.term_floor(prefix, g, &[l]),
            LeafKind::Primitive(_) => g.to_owned(),
        }
    }

    /// A floor of the term of a sub-tree whose model leaves are `models` (at least one) from
    /// a floor `g` of its gap (WGSL), for culling: each local bound lies between 1 and its
    /// model's estimate, so the term is at least the smaller of `g` over 1 and over the
    /// largest estimate (through every operator: `Scene::culled_subtree`).
    pub(super) fn term_floor(&self, prefix: &str, g: &str, models: &[usize]) -> String {
        let largest = models
            .iter()
            .map(|&l| self.leaf_lipschitz(l))
            .fold(1.0f32, f32::max);
        format!("{prefix}_term_floor({g}, {})", lit(1.0 / largest))
    }

    /// `{prefix}_node_{v}_t(p, g)` for each instruction `v` other than a leaf or a sharp
    /// operator whose sub-tree holds models: `g` over the largest of their local bounds.
    pub(super) fn node_term_functions(&self, s: &mut String, prefix: &str, plan: &[TraceStep]) {
        for (v, instruction) in self.program().iter().enumerate() {
            if matches!(
                instruction,
                Instruction::Leaf(_)
                    | Instruction::Union
                    | Instruction::Intersection
                    | Instruction::Difference
            ) {
                continue;
            }
            let models = self.subtree_models(v, &plan[v]);
            if models.is_empty() {
                continue;
            }
            // One statement per model: a nested fold of many would pass the WGSL parsers'
            // nesting limits.
            let bound: String = models
                .iter()
                .map(|l| format!("    bound = max(bound, {prefix}_leaf_{l}_lip(p, g));\n"))
                .collect();
            let _ = write!(
                s,
                "\n// Instruction {v}'s term of the tracer's bound: g over its models' largest local bound.\n\
                 fn {prefix}_node_{v}_t(p: vec3<f32>, g: f32) -> f32 {{\n    var bound = 1.0;\n{bound}    return g / bound;\n}}\n"
            );
        }
    }

    /// Model `m`'s local Lipschitz tables as uploaded: the cells' bounds, then the blocks' (each
    /// at least 1, as [`LocalLipschitz`] holds them).
    ///
    /// [`LocalLipschitz`]: super::lipschitz::LocalLipschitz
    pub(super) fn lipschitz_tables(&self, m: usize) -> (Vec<f32>, Vec<f32>) {
        let local = self.model_local_lipschitz(m).expect("a model of the scene");
        let (cells, blocks) = local.tables();
        (cells.to_vec(), blocks.to_vec())
    }

    /// `{prefix}_m{m}_floor(x)`: [`CellFloors::at`] of model `m` at the normalised point `x`
    /// in its cube, its table at `at` (buffer, element).
    ///
    /// [`CellFloors::at`]: super::lipschitz::CellFloors::at
    pub(super) fn floor_function(&self, s: &mut String, prefix: &str, m: usize, at: (usize, u64)) {
        let (buffer, offset) = at;
        let _ = write!(
            s,
            "// Model {m}'s floor of its value over the cell of its {GRID}^3 grid that holds x (culling).\n\
             fn {prefix}_m{m}_floor(x: vec3<f32>) -> f32 {{\n\
             \x20   let c = clamp(floor((x + vec3<f32>(1.0)) * {half}), vec3<f32>(0.0), vec3<f32>({last}));\n\
             \x20   // In range whatever a NaN made of c.\n\
             \x20   let i = min((u32(c.x) * {GRID}u + u32(c.y)) * {GRID}u + u32(c.z), {last_cell}u);\n\
             \x20   return {prefix}_params_{buffer}[{offset}u + i];\n\
             }}\n",
            half = lit(GRID as f32 / 2.0),
            last = lit(GRID as f32 - 1.0),
            last_cell = GRID * GRID * GRID - 1,
        );
    }

    /// `{prefix}_m{m}_lip(x, g)`: [`LocalLipschitz::bound`] of model `m` at the normalised
    /// point `x` for a gap `g` in normalised units, its tables at `at` (buffer, element).
    pub(super) fn lipschitz_function(
        &self,
        s: &mut String,
        prefix: &str,
        m: usize,
        at: (usize, u64),
    ) {
        let (buffer, offset) = at;
        let n = LOCAL_CELLS;
        let global = self
            .model_local_lipschitz(m)
            .expect("a model of the scene")
            .global();
        let cells = format!("{prefix}_params_{buffer}[{offset}u + i]");
        let blocks = format!(
            "{prefix}_params_{buffer}[{}u + i]",
            offset + (n * n * n) as u64
        );
        let _ = write!(
            s,
            "// Model {m}'s local Lipschitz bound (LocalLipschitz::bound): its cell's where the ball\n\
             // of radius |g| / bound fits the cell, its 3x3x3 block's where that ball fits the block,\n\
             // else the estimate (and outside the cube).\n\
             fn {prefix}_m{m}_lip(x: vec3<f32>, g: f32) -> f32 {{\n\
             \x20   let a = abs(x);\n\
             \x20   if !(max(a.x, max(a.y, a.z)) < 1.0) {{\n\
             \x20       return {global};\n\
             \x20   }}\n\
             \x20   let u = (x + vec3<f32>(1.0)) * {half};\n\
             \x20   let c = clamp(floor(u), vec3<f32>(0.0), vec3<f32>({last}));\n\
             \x20   let f = u - c;\n\
             \x20   // In range whatever a NaN made of c.\n\
             \x20   let i = min((u32(c.x) * {n}u + u32(c.y)) * {n}u + u32(c.z), {last_cell}u);\n\
             \x20   let in_cell = min(f, vec3<f32>(1.0) - f);\n\
             \x20   let cell = {cells};\n\
             \x20   if abs(g) <= cell * min(in_cell.x, min(in_cell.y, in_cell.z)) * {side} {{\n\
             \x20       return cell;\n\
             \x20   }}\n\
             \x20   let in_block = min(f + min(c, vec3<f32>(1.0)), vec3<f32>(1.0) - f + min(vec3<f32>({last}) - c, vec3<f32>(1.0)));\n\
             \x20   let block = {blocks};\n\
             \x20   if abs(g) <= block * min(in_block.x, min(in_block.y, in_block.z)) * {side} {{\n\
             \x20       return block;\n\
             \x20   }}\n\
             \x20   return {global};\n\
             }}\n",
            global = lit(global),
            half = lit(n as f32 / 2.0),
            last = lit(n as f32 - 1.0),
            last_cell = n * n * n - 1,
            side = lit(2.0 / n as f32),
        );
    }
}

/// A value `x` less its level as WGSL (`c` is the trace function's level; `−c` under a
/// difference's subtracted operand).
pub(super) fn gap(x: &str, flipped: bool) -> String {
    let sign = if flipped { '+' } else { '-' };
    format!("({x} {sign} c)")
}
