//! A whole scene as WGSL: `fn {prefix}_distance(p)`, `fn {prefix}_normal(p)`,
//! `fn {prefix}_trace(p, c)` (for sphere tracers) and `fn {prefix}_sample(p)` (distance,
//! gradient and deciding leaf) for the caller's own shader,
//! and the bind group that feeds it every model's weights in as few buffers as the device
//! allows. The GPU queries of [`super::gpu`] and the scene renderer compile the same snippet.
//!
//! ```no_run
//! # fn demo(scene: &sdf_nn::serve::scene::Scene, device: &wgpu::Device) -> Result<(), sdf_nn::serve::scene::SceneGpuError> {
//! // Two scenes in one shader: each its own prefix and group.
//! let limits = device.limits();
//! let source = format!(
//!     "{}\n{}\n/* the caller's code, calling city_distance(p) and robot_normal(p) */",
//!     scene.wgsl_with_prefix(1, "city", &limits)?,
//!     scene.wgsl_with_prefix(2, "robot", &limits)?,
//! );
//! let weights = scene.bind_group(device)?; // set at group 1 (and a second one at group 2)
//! # let _ = (source, weights); Ok(()) }
//! ```
//!
//! # What the snippet is
//! Every model of [`Scene::models`] once, as [`NeuralSdf::wgsl`](crate::NeuralSdf::wgsl)
//! writes it under the prefix `{prefix}_m{i}`, its weights read at an offset baked into the
//! code from the scene's shared buffers; the primitives of `shaders/primitives.wgsl`; one
//! function per leaf (its placement as constants: the inverse rotation, the translation and the
//! scale); and the compiled program ([`Scene::program`]) as straight-line code, once for the
//! distance alone and once with gradients and the deciding leaf. Every value is the CPU
//! reference's ([`super::cpu`]) in f32: the same operators, the same tie rules, the same
//! gradients.
//!
//! # Bindings
//! `@group(G) @binding(k)`, `k = 0, 1, …`: read-only `array<f32>` buffers holding the models'
//! parameters, each followed by its local Lipschitz tables (`{prefix}_params_k`; 2 × 8³ floats,
//! [`super::lipschitz::LocalLipschitz`]) and its value floors (32³ floats,
//! [`super::lipschitz::CellFloors`]), then read-only `array<u32>` buffers holding NGLOD
//! models' sparse vertex tables (`{prefix}_tables_k`). A buffer holds as many models as fit the
//! device's `max_storage_buffer_binding_size`; usually there is one of each (none for a scene of
//! primitives). [`Scene::bind_group`] creates them with the layout the snippet expects, for the
//! same device limits.

use std::fmt::Write;

use glam::DMat3;

use crate::gpu::GpuError;
use crate::gpu::SirenActivations;
use crate::serve::scene::cpu::SceneQueryError;
use crate::serve::scene::primitive::Primitive;
use crate::serve::scene::program_wgsl::{
    CulledSubtree, Program, distance_expression, sample_expression,
};
use crate::serve::scene::trace_wgsl::{LIPSCHITZ_TABLES, MODEL_TABLES, gap};
use crate::serve::scene::tree::{Instruction, LeafKind, Scene, TraceStep};
use crate::serve::wgsl::{self, EmbedError, Lanes, MAX_PREFIX};

/// The primitives, the sample type and the operators (names `hwsdf_…`, renamed per scene).
const PRIMITIVES: &str = crate::shaders::SCENE_PRIMITIVES.source;

/// Longest scene prefix beyond its first letter: the models' names add `_m{i}`.
pub const MAX_SCENE_PREFIX: usize = MAX_PREFIX - 8;

/// Errors of a scene on the GPU: its WGSL, its weights, its queries.
#[derive(Debug, thiserror::Error)]
pub enum SceneGpuError {
    /// A bad prefix, or a model whose weights exceed one storage binding.
    #[error(transparent)]
    Embed(#[from] EmbedError),
    /// The scene's weights need more storage buffers than a shader stage may bind.
    #[error(
        "the scene's weights need {needed} storage buffers (and its queries {reserved} more), \
         above this device's max_storage_buffers_per_shader_stage = {limit}: use fewer or \
         smaller models"
    )]
    TooManyBuffers {
        /// Buffers the weights need.
        needed: u32,
        /// Buffers the query kernels bind besides them.
        reserved: u32,
        /// The device's `max_storage_buffers_per_shader_stage`.
        limit: u32,
    },
    /// A query's input is refused (a bad ray, level or tolerance).
    #[error(transparent)]
    Query(#[from] SceneQueryError),
    /// [`QueryKernel::PerSubgroup`](crate::serve::query::QueryKernel::PerSubgroup) was asked of a device
    /// without subgroup operations (or with subgroups wider than a query workgroup).
    #[error(
        "{adapter} has no subgroup operations usable by the scene's subgroup kernels: use \
         QueryKernel::PerInvocation"
    )]
    NoSubgroups {
        /// The adapter.
        adapter: String,
    },
    /// The device failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// Where each model's weights go: which buffer and at which element.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Packing {
    /// Per model: (parameter buffer, first element).
    params: Vec<(usize, u64)>,
    /// Per model: the first element of its local Lipschitz tables and value floors, after its
    /// weights in the same buffer.
    lipschitz: Vec<u64>,
    /// Per model: (table buffer, first element), for NGLOD models with sparse levels.
    tables: Vec<Option<(usize, u64)>>,
    /// Elements of each parameter buffer.
    param_lengths: Vec<u64>,
    /// Elements of each table buffer.
    table_lengths: Vec<u64>,
}

impl Packing {
    /// Storage buffers the snippet binds.
    pub(crate) fn bindings(&self) -> u32 {
        (self.param_lengths.len() + self.table_lengths.len()) as u32
    }
}

/// First-fit packing of arrays of `lengths` elements of 4 bytes into buffers of at most
/// `limit` bytes: per array (buffer, offset), and the buffers' lengths.
fn pack(lengths: &[Option<u64>], limit: u64) -> Result<PackedArrays, EmbedError> {
    let mut places = Vec::with_capacity(lengths.len());
    let mut buffers: Vec<u64> = Vec::new();
    for len in lengths {
        let Some(len) = *len else {
            places.push(None);
            continue;
        };
        let bytes = len * 4;
        if bytes > limit {
            return Err(EmbedError::TooLarge { bytes, limit });
        }
        let k = match buffers.iter().position(|used| (used + len) * 4 <= limit) {
            Some(k) => k,
            None => {
                buffers.push(0);
                buffers.len() - 1
            }
        };
        places.push(Some((k, buffers[k])));
        buffers[k] += len;
    }
    Ok((places, buffers))
}

/// Per array its (buffer, offset), and the buffers' lengths.
type PackedArrays = (Vec<Option<(usize, u64)>>, Vec<u64>);

impl Scene {
    /// How the models' weights are packed for a device with `limits`.
    pub(crate) fn packing(&self, limits: &wgpu::Limits) -> Result<Packing, EmbedError> {
        let limit = crate::gpu::binding_limit(limits);
        let weights: Vec<(&[f32], Vec<u32>)> = self
            .models()
            .iter()
            .map(|m| wgsl::weights(m.network()))
            .collect();
        // Each model's weights, then its local Lipschitz tables (`{prefix}_m{i}_lip`) and
        // value floors (`{prefix}_m{i}_floor`).
        let param_lengths: Vec<Option<u64>> = weights
            .iter()
            .map(|(p, _)| Some((p.len() + MODEL_TABLES) as u64))
            .collect();
        let table_lengths: Vec<Option<u64>> = weights
            .iter()
            .map(|(_, t)| (!t.is_empty()).then_some(t.len() as u64))
            .collect();
        let (params, param_buffers) = pack(&param_lengths, limit)?;
        let (tables, table_buffers) = pack(&table_lengths, limit)?;
        let params: Vec<(usize, u64)> = params
            .into_iter()
            .map(|p| p.expect("every model"))
            .collect();
        let lipschitz = params
            .iter()
            .zip(&weights)
            .map(|(&(_, offset), (p, _))| offset + p.len() as u64)
            .collect();
        Ok(Packing {
            params,
            lipschitz,
            tables,
            param_lengths: param_buffers,
            table_lengths: table_buffers,
        })
    }

    /// The whole scene as WGSL, every name it declares starting with `prefix` (`{prefix}_…`,
    /// `{PREFIX}_…`), its weights at `@group(group)` as [`Scene::bind_group`] creates them for a
    /// device with `limits` (see the [module](self)):
    /// - `fn {prefix}_distance(p: vec3<f32>) -> f32`: the scene's signed distance (or bound:
    ///   see [`super::tree`]) at a point of the scene's frame;
    /// - `fn {prefix}_normal(p: vec3<f32>) -> vec3<f32>`: the unit normal (the normalised
    ///   analytic gradient; zero where it vanishes);
    /// - `fn {prefix}_sample(p: vec3<f32>) -> {prefix}_Sample`: the distance, its gradient
    ///   (not normalised) and the index of the deciding leaf ([`Scene::leaves`]);
    /// - `fn {prefix}_trace(p: vec3<f32>, c: f32) -> vec2<f32>`: for sphere tracers, `d − c`
    ///   (x) and the step to take from `p` (y, with the sign of x: the radius of
    ///   [`Scene::trace_rays`], of a ball about `p` that holds no crossing of the level set).
    ///
    /// The prefix is an ASCII letter followed by at most [`MAX_SCENE_PREFIX`] letters, digits
    /// or underscores; two snippets in one shader need prefixes that differ other than in case.
    pub fn wgsl_with_prefix(
        &self,
        group: u32,
        prefix: &str,
        limits: &wgpu::Limits,
    ) -> Result<String, EmbedError> {
        self.wgsl_with_lanes(group, prefix, limits, Lanes::One, SirenActivations::Private)
    }

    /// [`Scene::wgsl_with_prefix`] in the form for `lanes` and `activations` (see
    /// [`Scene::generate`]).
    pub(crate) fn wgsl_with_lanes(
        &self,
        group: u32,
        prefix: &str,
        limits: &wgpu::Limits,
        lanes: Lanes,
        activations: SirenActivations,
    ) -> Result<String, EmbedError> {
        wgsl::check_prefix(prefix, MAX_SCENE_PREFIX)?;
        let packing = self.packing(limits)?;
        Ok(self.generate(group, prefix, &packing, lanes, activations))
    }

    /// The snippet for `packing`, under `prefix` (already checked). With
    /// [`Lanes::Subgroup`] it also declares `var<private> {prefix}_lane` and `{prefix}_lanes`:
    /// a kernel that sets them (its `subgroup_invocation_id` and `subgroup_size`) and calls the
    /// scene's functions with one point per subgroup has every model evaluated by the whole
    /// subgroup together.
    fn generate(
        &self,
        group: u32,
        prefix: &str,
        packing: &Packing,
        lanes: Lanes,
        activations: SirenActivations,
    ) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "// ---- HW SDF scene: {} leaves, {} models; generated by sdf_nn::serve::scene::Scene::wgsl_with_prefix. ----",
            self.leaves().len(),
            self.models().len()
        );
        let np = packing.param_lengths.len();
        for k in 0..np {
            let _ = writeln!(
                s,
                "@group({group}) @binding({k}) var<storage, read> {prefix}_params_{k}: array<f32>;"
            );
        }
        for k in 0..packing.table_lengths.len() {
            let _ = writeln!(
                s,
                "@group({group}) @binding({b}) var<storage, read> {prefix}_tables_{k}: array<u32>;",
                b = np + k
            );
        }
        if lanes == Lanes::Subgroup {
            let _ = writeln!(
                s,
                "// Set by the kernel: this invocation's lane and the subgroup's width (one point per subgroup).\n\
                 var<private> {prefix}_lane: u32 = 0u;\n\
                 var<private> {prefix}_lanes: u32 = 1u;"
            );
        }
        for (i, model) in self.models().iter().enumerate() {
            let name = format!("{prefix}_m{i}");
            let model_wgsl = wgsl::generate(
                model.network(),
                model.normalization(),
                model.lod(),
                group,
                lanes,
                activations,
            );
            let snippet = wgsl::rename(&model_wgsl, &name);
            let (buffer, offset) = packing.params[i];
            let mut snippet: String = snippet
                .lines()
                .filter(|line| !line.starts_with("@group("))
                .collect::<Vec<_>>()
                .join("\n")
                .replace(
                    &format!("{name}_params["),
                    &format!("{prefix}_params_{buffer}[{offset}u + "),
                );
            if let Some((buffer, offset)) = packing.tables[i] {
                snippet = snippet.replace(
                    &format!("{name}_table["),
                    &format!("{prefix}_tables_{buffer}[{offset}u + "),
                );
            }
            s.push_str(&snippet);
            let tables = packing.lipschitz[i];
            self.floor_function(
                &mut s,
                prefix,
                i,
                (buffer, tables + LIPSCHITZ_TABLES as u64),
            );
            self.lipschitz_function(&mut s, prefix, i, (buffer, tables));
        }
        s.push_str(&wgsl::rename(PRIMITIVES, prefix));
        let _ = writeln!(
            s,
            "// A floor of a model's term of the tracer's bound, g / L for a local bound L in\n\
             // [1, its estimate] (inv: 1 / the estimate), from a floor g of its value less the level.\n\
             fn {prefix}_term_floor(g: f32, inv: f32) -> f32 {{\n    return min(g * inv, g);\n}}"
        );
        let up = prefix.to_ascii_uppercase();
        for (l, leaf) in self.leaves().iter().enumerate() {
            self.leaf_functions(&mut s, prefix, &up, l, leaf, lanes);
        }
        self.program_functions(&mut s, prefix);
        let _ = writeln!(s, "// ---- end of HW SDF scene ----");
        s
    }

    /// `{prefix}_leaf_{l}` (value, gradient and leaf in the scene's frame) and
    /// `{prefix}_leaf_{l}_d` (the value alone) of leaf `l`.
    fn leaf_functions(
        &self,
        s: &mut String,
        prefix: &str,
        up: &str,
        l: usize,
        leaf: &crate::serve::scene::tree::Leaf,
        lanes: Lanes,
    ) {
        let t = &leaf.transform;
        let rotation = t.rotation.as_dquat().normalize();
        let (inv, rot) = (
            DMat3::from_quat(rotation.inverse()),
            DMat3::from_quat(rotation),
        );
        let mat = |m: DMat3| {
            let c = |v: glam::DVec3| vec3(v.as_vec3());
            format!(
                "mat3x3<f32>({}, {}, {})",
                c(m.x_axis),
                c(m.y_axis),
                c(m.z_axis)
            )
        };
        let _ = write!(
            s,
            "\n// Leaf {l}: {what}.\n\
             const {up}_L{l}_INV: mat3x3<f32> = {inv};\n\
             const {up}_L{l}_ROT: mat3x3<f32> = {rot};\n\
             const {up}_L{l}_T: vec3<f32> = {tr};\n\
             const {up}_L{l}_S: f32 = {sc};\n",
            what = self.leaf_path(l).unwrap_or(""),
            inv = mat(inv),
            rot = mat(rot),
            tr = vec3(t.translation),
            sc = lit(t.scale),
        );
        let local = format!("{up}_L{l}_INV * (p - {up}_L{l}_T) / {up}_L{l}_S");
        let (value, distance) = match leaf.kind {
            LeafKind::Model(m) if lanes == Lanes::Subgroup => (
                format!("{prefix}_m{m}_distance_normal_sg(q, {prefix}_lane, {prefix}_lanes)"),
                format!("{prefix}_m{m}_distance_sg(q, {prefix}_lane, {prefix}_lanes)"),
            ),
            LeafKind::Model(m) => (
                format!("{prefix}_m{m}_distance_normal(q)"),
                format!("{prefix}_m{m}_distance(q)"),
            ),
            LeafKind::Primitive(p) => {
                let call = primitive_call(prefix, &p);
                (call.clone(), format!("{call}.x"))
            }
        };
        if let LeafKind::Model(m) = leaf.kind {
            // The model's value is (phi(c) + |x − c|) / scale at the normalised point x, c its
            // clamp to the cube: at least (the floor of c's cell + |x − c|) / scale.
            let mp = format!("{up}_M{m}");
            let _ = write!(
                s,
                "fn {prefix}_leaf_{l}_lb(p: vec3<f32>) -> f32 {{\n\
                 \x20   let x = ({local} - {mp}_CENTER) * {mp}_SCALE;\n\
                 \x20   let c = clamp(x, vec3<f32>(-1.0), vec3<f32>(1.0));\n\
                 \x20   return {up}_L{l}_S * (length(x - c) + {prefix}_m{m}_floor(c)) / {mp}_SCALE;\n\
                 }}\n\
                 // The model's local Lipschitz bound at p for a gap g (scene units), and g over it.\n\
                 fn {prefix}_leaf_{l}_lip(p: vec3<f32>, g: f32) -> f32 {{\n\
                 \x20   let x = ({local} - {mp}_CENTER) * {mp}_SCALE;\n\
                 \x20   return {prefix}_m{m}_lip(x, g * {mp}_SCALE / {up}_L{l}_S);\n\
                 }}\n\
                 fn {prefix}_leaf_{l}_t(p: vec3<f32>, g: f32) -> f32 {{\n\
                 \x20   return g / {prefix}_leaf_{l}_lip(p, g);\n\
                 }}\n"
            );
        }
        let _ = write!(
            s,
            "fn {prefix}_leaf_{l}(p: vec3<f32>) -> {prefix}_Sample {{\n\
             \x20   let q = {local};\n\
             \x20   let v = {value};\n\
             \x20   return {prefix}_Sample({up}_L{l}_S * v.x, {up}_L{l}_ROT * v.yzw, {l}u);\n\
             }}\n\
             fn {prefix}_leaf_{l}_d(p: vec3<f32>) -> f32 {{\n\
             \x20   let q = {local};\n\
             \x20   return {up}_L{l}_S * {distance};\n\
             }}\n"
        );
    }

    /// The program as straight-line code: `{prefix}_distance`, `{prefix}_sample`, `{prefix}_trace` and
    /// `{prefix}_normal`.
    fn program_functions(&self, s: &mut String, prefix: &str) {
        let program = self.program();
        let plan = self.trace_plan();
        self.node_term_functions(s, prefix, &plan);
        let subtrees = self.culled_subtrees(&plan);
        for kind in [Program::Distance, Program::Sample, Program::Trace] {
            let mut stack: Vec<usize> = Vec::new();
            let mut body = String::new();
            let code = Code {
                prefix,
                kind,
                plan: &plan,
                subtrees: &subtrees,
            };
            self.emit(&code, 0..program.len(), &mut stack, &mut body);
            let last = stack.pop().expect("a balanced program leaves one value");
            match kind {
                Program::Sample => {
                    let _ = write!(
                        s,
                        "\n// The scene's value, gradient and deciding leaf at a point of its frame.\n\
                         fn {prefix}_sample(p: vec3<f32>) -> {prefix}_Sample {{\n{body}    return v{last};\n}}\n"
                    );
                }
                Program::Distance => {
                    let _ = write!(
                        s,
                        "\n// The scene's signed distance at a point of its frame.\n\
                         fn {prefix}_distance(p: vec3<f32>) -> f32 {{\n{body}    return v{last};\n}}\n"
                    );
                }
                Program::Trace => {
                    let _ = write!(
                        s,
                        "\n// For sphere tracers, at a point of the scene's frame and a level c: x, the distance\n\
                         // less c; y, with the sign of x, the radius of a ball about p free of the level set\n\
                         // (Scene::trace_rays).\n\
                         fn {prefix}_trace(p: vec3<f32>, c: f32) -> vec2<f32> {{\n{body}    return vec2<f32>(v{last} - c, t{last});\n}}\n"
                    );
                }
            }
        }
        let _ = write!(
            s,
            "\n// The unit normal (zero where the gradient vanishes).\n\
             fn {prefix}_normal(p: vec3<f32>) -> vec3<f32> {{\n\
             \x20   let g = {prefix}_sample(p).g;\n\
             \x20   let len = length(g);\n\
             \x20   if len > 0.0 {{\n\
             \x20       return g / len;\n\
             \x20   }}\n\
             \x20   return vec3<f32>(0.0);\n\
             }}\n"
        );
    }

    /// Instructions `range` of the program as code appended to `body`, their operands taken
    /// from and their results pushed on `stack` (variable numbers).
    fn emit(
        &self,
        code: &Code<'_>,
        range: std::ops::Range<usize>,
        stack: &mut Vec<usize>,
        body: &mut String,
    ) {
        let Code {
            prefix,
            kind,
            plan,
            subtrees,
        } = *code;
        let program = self.program();
        let mut v = range.start;
        while v < range.end {
            // A group (a sub-tree of several instructions) before a chain of leaves that may
            // start at its first leaf; a single model leaf after.
            let group = subtrees[v].is_some_and(|(end, _)| end > v);
            if group && let Some(cull) = self.culled_subtree(prefix, v, stack, kind, plan, subtrees)
            {
                v = self.emit_culled(code, v, cull, stack, body);
                continue;
            }
            if kind != Program::Sample
                && let Some((code, end, popped)) = self.leaf_union(prefix, v, stack, kind, plan)
            {
                if popped {
                    stack.pop();
                }
                body.push_str(&code);
                stack.push(end);
                v = end + 1;
                continue;
            }
            if !group
                && let Some(cull) = self.culled_subtree(prefix, v, stack, kind, plan, subtrees)
            {
                v = self.emit_culled(code, v, cull, stack, body);
                continue;
            }
            if kind == Program::Trace
                && let Some(bound) = sharp_bound(&program[v], stack)
            {
                let expr = distance_expression(prefix, &program[v], stack);
                let _ = writeln!(body, "    let v{v} = {expr};\n    let t{v} = {bound};");
                stack.push(v);
                v += 1;
                continue;
            }
            let expr = if kind == Program::Sample {
                sample_expression(prefix, &program[v], stack)
            } else {
                distance_expression(prefix, &program[v], stack)
            };
            let _ = writeln!(body, "    let v{v} = {expr};");
            if kind == Program::Trace {
                let _ = writeln!(
                    body,
                    "    let t{v} = {};",
                    self.trace_term(prefix, &format!("v{v}"), v, plan)
                );
            }
            stack.push(v);
            v += 1;
        }
    }

    /// The operand starting at `v` inside its floor's test ([`Scene::culled_subtree`]): its
    /// parent's left operand is taken off `stack`, the parent pushed. The next instruction.
    fn emit_culled(
        &self,
        code: &Code<'_>,
        v: usize,
        cull: CulledSubtree,
        stack: &mut Vec<usize>,
        body: &mut String,
    ) -> usize {
        stack.pop();
        body.push_str(&cull.open);
        self.emit(code, v..cull.end + 1, &mut Vec::new(), body);
        body.push_str(&cull.close);
        stack.push(cull.parent);
        cull.parent + 1
    }

    /// A union of leaves starting at `v` (`Leaf, Leaf, Union, Leaf, Union, …`, as the
    /// compiler folds an n-ary union whose children are leaves), with at least one model, as
    /// distance-only code that takes the primitives first, then the model whose lower bound is
    /// smallest, then each other model only where its bound is below the minimum so far: a
    /// point near one of many placed models evaluates that one. Exact (`min` does not depend on
    /// the order). The chain may also continue the value on top of `stack` (`Leaf, Union, Leaf,
    /// Union, …` after any sub-tree). `(code, end, popped)`: the code defines `v{end}`, `end`
    /// the chain's last union; `popped`: it consumed the top of the stack. For
    /// [`Program::Trace`] the code also defines `t{end}`, the minimum of the leaves' values less
    /// the level, each divided by its Lipschitz bound, and evaluates a model where it can lower
    /// either minimum.
    fn leaf_union(
        &self,
        prefix: &str,
        v: usize,
        stack: &[usize],
        kind: Program,
        plan: &[TraceStep],
    ) -> Option<(String, usize, bool)> {
        let program = self.program();
        let Instruction::Leaf(first) = program[v] else {
            return None;
        };
        // Either the chain starts with two leaves, or it continues the value on the stack.
        let continues = matches!(program.get(v + 1), Some(Instruction::Union)) && !stack.is_empty();
        let (mut leaves, mut end, init, init_bound) = if continues {
            let a = *stack.last().expect("checked");
            (Vec::new(), v - 1, format!("v{a}"), format!("t{a}"))
        } else {
            let max = "3.4028235e38f".to_owned();
            (vec![first as usize], v, max.clone(), max)
        };
        while let (Some(Instruction::Leaf(l)), Some(Instruction::Union)) =
            (program.get(end + 1), program.get(end + 2))
        {
            leaves.push(*l as usize);
            end += 2;
        }
        let is_model = |l: &usize| matches!(self.leaves()[*l].kind, LeafKind::Model(_));
        let models: Vec<usize> = leaves.iter().copied().filter(is_model).collect();
        if leaves.len() < 2 || models.is_empty() {
            return None;
        }
        let trace = kind == Program::Trace;
        let mut c = format!(
            "    // The union of leaves {leaves:?}: primitives, then the nearest model bound first.\n\
             \x20   var v{end} = {init};\n"
        );
        if trace {
            let _ = writeln!(c, "    var t{end} = {init_bound};");
        }
        // A leaf's term of t{end} for its value `x`, and a floor of it for a lower bound `x`.
        let flipped = plan[end].flipped;
        let term = |x: &str, l: usize| self.leaf_term(prefix, &gap(x, flipped), l);
        let floor = |x: &str, l: usize| self.leaf_term_floor(prefix, &gap(x, flipped), l);
        for l in leaves.iter().filter(|l| !is_model(l)) {
            if trace {
                let _ = writeln!(
                    c,
                    "    let d{end}_{l} = {prefix}_leaf_{l}_d(p);\n\
                     \x20   v{end} = min(v{end}, d{end}_{l});\n\
                     \x20   t{end} = min(t{end}, {});",
                    term(&format!("d{end}_{l}"), *l)
                );
            } else {
                let _ = writeln!(c, "    v{end} = min(v{end}, {prefix}_leaf_{l}_d(p));");
            }
        }
        for (i, l) in models.iter().enumerate() {
            let _ = writeln!(c, "    let b{end}_{i} = {prefix}_leaf_{l}_lb(p);");
        }
        let _ = writeln!(c, "    var lo{end} = b{end}_0;\n    var first{end} = 0u;");
        for i in 1..models.len() {
            let _ = writeln!(
                c,
                "    if b{end}_{i} < lo{end} {{\n        lo{end} = b{end}_{i};\n        first{end} = {i}u;\n    }}"
            );
        }
        // Two passes over one call site per model (a `switch` and a second list would inline
        // every model twice): the nearest bound's model first, then the others that can still
        // lower the minimum.
        let _ = writeln!(
            c,
            "    for (var round{end} = 0u; round{end} < 2u; round{end}++) {{"
        );
        for (i, l) in models.iter().enumerate() {
            if trace {
                let bound = floor(&format!("b{end}_{i}"), *l);
                let _ = writeln!(
                    c,
                    "        if (first{end} == {i}u) == (round{end} == 0u) && (b{end}_{i} < v{end} || {bound} < t{end}) {{\n\
                     \x20           let d = {prefix}_leaf_{l}_d(p);\n\
                     \x20           v{end} = min(v{end}, d);\n\
                     \x20           t{end} = min(t{end}, {});\n\
                     \x20       }}",
                    term("d", *l)
                );
            } else {
                let _ = writeln!(
                    c,
                    "        if (first{end} == {i}u) == (round{end} == 0u) && b{end}_{i} < v{end} {{\n            v{end} = min(v{end}, {prefix}_leaf_{l}_d(p));\n        }}"
                );
            }
        }
        let _ = writeln!(c, "    }}");
        Some((c, end, continues))
    }
}

/// What the generator of one of the scene's functions carries down its sub-trees.
#[derive(Clone, Copy)]
struct Code<'a> {
    prefix: &'a str,
    kind: Program,
    plan: &'a [TraceStep],
    /// [`Scene::culled_subtrees`].
    subtrees: &'a [Option<(usize, usize)>],
}

/// A sharp union's, intersection's or difference's bound from its operands' (the top two of
/// `stack`, not popped); `None` for any other instruction.
fn sharp_bound(instruction: &Instruction, stack: &[usize]) -> Option<String> {
    let (a, b) = match stack {
        [.., a, b] => (*a, *b),
        _ => return None,
    };
    match instruction {
        Instruction::Union => Some(format!("min(t{a}, t{b})")),
        Instruction::Intersection => Some(format!("max(t{a}, t{b})")),
        // The subtracted operand was traced against the opposite level.
        Instruction::Difference => Some(format!("max(t{a}, -t{b})")),
        _ => None,
    }
}

/// The WGSL call that evaluates primitive `p` at the local point `q` (a `vec4<f32>`: distance,
/// gradient).
fn primitive_call(prefix: &str, p: &Primitive) -> String {
    match *p {
        Primitive::Sphere { radius } => format!("{prefix}_sphere(q, {})", lit(radius)),
        Primitive::Box { half_extents } => format!("{prefix}_box(q, {})", vec3(half_extents)),
        Primitive::RoundBox {
            half_extents,
            radius,
        } => format!(
            "{prefix}_round_box(q, {}, {})",
            vec3(half_extents),
            lit(radius)
        ),
        Primitive::Capsule { a, b, radius } => format!(
            "{prefix}_capsule(q, {}, {}, {})",
            vec3(a),
            vec3(b),
            lit(radius)
        ),
        Primitive::Torus { major, minor } => {
            format!("{prefix}_torus(q, {}, {})", lit(major), lit(minor))
        }
        Primitive::Plane { normal, offset } => format!(
            "{prefix}_plane(q, {}, {})",
            vec3(normal.as_dvec3().normalize().as_vec3()),
            lit(offset)
        ),
        Primitive::Cylinder {
            radius,
            half_height,
        } => format!(
            "{prefix}_cylinder(q, {}, {})",
            lit(radius),
            lit(half_height)
        ),
    }
}

fn lit(x: f32) -> String {
    wgsl::lit(x)
}

fn vec3(v: glam::Vec3) -> String {
    wgsl::vec3_lit(v)
}

/// The scene's weights on a device, bound as its snippet expects.
#[derive(Debug)]
pub struct SceneBindGroup {
    /// Layout: the parameter buffers, then the table buffers, read-only storage visible to
    /// compute and fragment shaders. Put it at the snippet's group.
    pub layout: wgpu::BindGroupLayout,
    /// The bind group to set there.
    pub bind_group: wgpu::BindGroup,
    /// The parameter buffers (`{prefix}_params_k`).
    pub params: Vec<wgpu::Buffer>,
    /// The table buffers (`{prefix}_tables_k`).
    pub tables: Vec<wgpu::Buffer>,
}

impl Scene {
    /// Uploads the models' weights to `device`, packed as
    /// [`Scene::wgsl_with_prefix`] expects for this device's limits, and creates the bind
    /// group (and its layout).
    pub fn bind_group(&self, device: &wgpu::Device) -> Result<SceneBindGroup, SceneGpuError> {
        Ok(self.packed_for(device, 0)?.1)
    }

    /// The packing of the weights for `device`, checked to leave `reserved` storage bindings
    /// to the shader that reads them, and the weights uploaded by it.
    fn packed_for(
        &self,
        device: &wgpu::Device,
        reserved: u32,
    ) -> Result<(Packing, SceneBindGroup), SceneGpuError> {
        let limits = device.limits();
        let packing = self.packing(&limits)?;
        check_bindings(&packing, &limits, reserved)?;
        let weights = self.upload(device, &packing);
        Ok((packing, weights))
    }

    /// The snippet in each of `forms` (names `{prefix}_…`, weights at `@group(group)`, SIREN
    /// models' activations as `activations` says) and the weights they share, uploaded, for a
    /// shader of ours that binds `reserved` storage buffers of its own besides them: what the
    /// GPU queries and the scene renderer compile.
    pub(crate) fn compile(
        &self,
        device: &wgpu::Device,
        group: u32,
        prefix: &str,
        reserved: u32,
        forms: &[Lanes],
        activations: SirenActivations,
    ) -> Result<(Vec<String>, SceneBindGroup), SceneGpuError> {
        let (packing, weights) = self.packed_for(device, reserved)?;
        let snippets = forms
            .iter()
            .map(|&lanes| self.generate(group, prefix, &packing, lanes, activations))
            .collect();
        Ok((snippets, weights))
    }

    /// The buffers and bind group of `packing`.
    fn upload(&self, device: &wgpu::Device, packing: &Packing) -> SceneBindGroup {
        let mut params: Vec<Vec<f32>> = packing
            .param_lengths
            .iter()
            .map(|&n| Vec::with_capacity(n as usize))
            .collect();
        let mut tables: Vec<Vec<u32>> = packing
            .table_lengths
            .iter()
            .map(|&n| Vec::with_capacity(n as usize))
            .collect();
        // First fit places each model at the end of its buffer, in model order.
        for (i, model) in self.models().iter().enumerate() {
            let (p, t) = wgsl::weights(model.network());
            let (k, offset) = packing.params[i];
            debug_assert_eq!(params[k].len() as u64, offset);
            params[k].extend_from_slice(p);
            debug_assert_eq!(params[k].len() as u64, packing.lipschitz[i]);
            let (cells, blocks) = self.lipschitz_tables(i);
            params[k].extend(cells.into_iter().chain(blocks));
            let floors = self.model_cell_floors(i).expect("a model of the scene");
            params[k].extend_from_slice(floors.table());
            if let Some((k, offset)) = packing.tables[i] {
                debug_assert_eq!(tables[k].len() as u64, offset);
                tables[k].extend_from_slice(&t);
            }
        }
        let params: Vec<wgpu::Buffer> = params
            .iter()
            .map(|p| wgsl::weight_buffer(device, "scene params", bytemuck::cast_slice(p)))
            .collect();
        let tables: Vec<wgpu::Buffer> = tables
            .iter()
            .map(|t| wgsl::weight_buffer(device, "scene tables", bytemuck::cast_slice(t)))
            .collect();
        let buffers: Vec<&wgpu::Buffer> = params.iter().chain(&tables).collect();
        let (layout, bind_group) = wgsl::read_only_group(device, "scene weights", &buffers);
        SceneBindGroup {
            layout,
            bind_group,
            params,
            tables,
        }
    }
}

/// Checks that `packing`'s buffers and `reserved` more fit the device's storage bindings.
fn check_bindings(
    packing: &Packing,
    limits: &wgpu::Limits,
    reserved: u32,
) -> Result<(), SceneGpuError> {
    let limit = limits.max_storage_buffers_per_shader_stage;
    if packing.bindings() + reserved > limit {
        return Err(SceneGpuError::TooManyBuffers {
            needed: packing.bindings(),
            reserved,
            limit,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// First fit: arrays share a buffer until it is full, an array larger than the limit is
    /// refused with the limit named.
    #[test]
    fn weights_pack_first_fit() {
        let (places, buffers) = pack(&[Some(10), None, Some(20), Some(5)], 100).unwrap();
        assert_eq!(
            places,
            vec![Some((0, 0)), None, Some((1, 0)), Some((0, 10))]
        );
        assert_eq!(buffers, vec![15, 20]);
        let err = pack(&[Some(30)], 100).unwrap_err();
        assert!(
            matches!(
                err,
                EmbedError::TooLarge {
                    bytes: 120,
                    limit: 100
                }
            ),
            "{err}"
        );
    }

    /// Models share buffers up to the binding size; a scene whose weights need more buffers
    /// than a stage binds is refused with the limit named, and one model larger than a binding
    /// with its size.
    #[test]
    fn the_device_limits_are_named() {
        use crate::serve::scene::{SceneNode, Transform};
        use std::sync::Arc;
        let model = |r: f32| {
            let m = crate::Nglod::from_sdf(8, move |p| p.length() - r).unwrap();
            Arc::new(
                crate::NeuralSdf::from_model_file(
                    m.to_model_file(crate::Normalization::identity(), serde_json::Value::Null),
                )
                .unwrap(),
            )
        };
        let models: Vec<_> = (0..3).map(|i| model(0.3 + 0.1 * i as f32)).collect();
        // A model's weights and its tables.
        let bytes = 4 * (models[0].param_count() + MODEL_TABLES) as u64;
        let scene = Scene::new(SceneNode::Union(
            models
                .iter()
                .map(|m| SceneNode::model(m.clone(), Transform::IDENTITY))
                .collect(),
        ))
        .unwrap();
        let limits = |binding: u64, buffers: u32| wgpu::Limits {
            max_storage_buffer_binding_size: binding,
            max_storage_buffers_per_shader_stage: buffers,
            ..wgpu::Limits::default()
        };
        // All three in one buffer.
        let one = scene.packing(&limits(3 * bytes, 8)).unwrap();
        assert_eq!(one.bindings(), 1);
        // One per buffer: three bindings, two more for the queries, a stage of four.
        let three = scene.packing(&limits(bytes, 4)).unwrap();
        assert_eq!(three.bindings(), 3);
        let err = check_bindings(&three, &limits(bytes, 4), 2).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("max_storage_buffers_per_shader_stage = 4") && text.contains("3 storage"),
            "{text}"
        );
        assert!(check_bindings(&three, &limits(bytes, 5), 2).is_ok());
        let err = scene.packing(&limits(bytes - 4, 8)).unwrap_err();
        assert!(matches!(err, EmbedError::TooLarge { .. }), "{err}");
    }
}
