//! Every WGSL shader of the crate, with the device features each one needs. Each file lives
//! beside the Rust that dispatches it (`nglod/shaders/`, `siren/shaders/`, `serve/shaders/`,
//! `ground_truth/shaders/`, `adam.wgsl`) and is embedded with `include_str!`, so the crate
//! packages alone.

/// A WGSL source file and what it needs from the device.
#[derive(Clone, Copy, Debug)]
pub struct Shader {
    /// File name (without its folder), also the cache key and the debug label.
    pub name: &'static str,
    /// WGSL source.
    pub source: &'static str,
    /// Device features the shader uses; the context refuses to compile it without them.
    pub required_features: wgpu::Features,
}

macro_rules! shader {
    ($dir:literal $name:literal, $features:expr) => {
        Shader {
            name: $name,
            source: include_str!(concat!($dir, $name)),
            required_features: $features,
        }
    };
    // A shader completed by shared WGSL files, prepended in order (WGSL has no includes).
    ($dir:literal $name:literal with [$($pdir:literal $part:literal),+], $features:expr) => {
        Shader {
            name: $name,
            source: concat!(
                $(include_str!(concat!($pdir, $part)), "\n",)+
                include_str!(concat!($dir, $name))
            ),
            required_features: $features,
        }
    };
    // One file completed in two ways: the name gets `+variant`, so that the variants keep
    // their own pipeline cache keys.
    ($dir:literal $name:literal + $variant:literal with [$($pdir:literal $part:literal),+], $features:expr) => {
        Shader {
            name: concat!($name, "+", $variant),
            source: concat!(
                $(include_str!(concat!($pdir, $part)), "\n",)+
                include_str!(concat!($dir, $name))
            ),
            required_features: $features,
        }
    };
    // A shader file (named) followed by shared WGSL files: for a file of `enable` directives
    // and definitions that must come before the code they configure.
    ($dir:literal $name:literal then [$($pdir:literal $part:literal),+], $features:expr) => {
        Shader {
            name: $name,
            source: concat!(
                include_str!(concat!($dir, $name)),
                $("\n", include_str!(concat!($pdir, $part)),)+
            ),
            required_features: $features,
        }
    };
}

/// The shared Adam optimiser step.
pub const ADAM: Shader = shader!("" "adam.wgsl", wgpu::Features::empty());

/// NGLOD inference (grid interpolation + MLP).
pub const NGLOD_FORWARD: Shader = shader!(
    "nglod/shaders/" "nglod_forward.wgsl" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl"],
    wgpu::Features::empty()
);
/// NGLOD and hash-grid serving with one point per subgroup (completed by [`NGLOD_FORWARD`],
/// whose uniforms, bindings and serving rule it shares).
pub const NGLOD_QUERY_SUBGROUP: Shader = shader!(
    "nglod/shaders/" "nglod_query_subgroup.wgsl" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl", "nglod/shaders/" "nglod_forward.wgsl"],
    wgpu::Features::SUBGROUP
);
/// NGLOD forward + backward per row, grid scatter with native float atomics.
pub const NGLOD_TRAIN_ATOMIC: Shader = shader!(
    "nglod/shaders/" "nglod_train.wgsl" + "atomic" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl", "nglod/shaders/" "nglod_scatter_atomic.wgsl"],
    wgpu::Features::SHADER_FLOAT32_ATOMIC
);
/// NGLOD forward + backward per row, grid scatter by compare-exchange (any adapter).
pub const NGLOD_TRAIN_CAS: Shader = shader!(
    "nglod/shaders/" "nglod_train.wgsl" + "cas" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl", "nglod/shaders/" "nglod_scatter_cas.wgsl"],
    wgpu::Features::empty()
);
/// NGLOD forward + backward with one row per subgroup, grid scatter with native float atomics
/// (completed by the files of [`NGLOD_TRAIN_ATOMIC`], whose bindings, row layout and scatter it
/// shares).
pub const NGLOD_TRAIN_SUBGROUP_ATOMIC: Shader = shader!(
    "nglod/shaders/" "nglod_train_subgroup.wgsl" + "atomic" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl", "nglod/shaders/" "nglod_scatter_atomic.wgsl", "nglod/shaders/" "nglod_train.wgsl"],
    wgpu::Features::SUBGROUP.union(wgpu::Features::SHADER_FLOAT32_ATOMIC)
);
/// NGLOD forward + backward with one row per subgroup, grid scatter by compare-exchange
/// (completed by the files of [`NGLOD_TRAIN_CAS`]).
pub const NGLOD_TRAIN_SUBGROUP_CAS: Shader = shader!(
    "nglod/shaders/" "nglod_train_subgroup.wgsl" + "cas" with ["nglod/shaders/" "nglod_grid.wgsl", "serve/shaders/" "query_map.wgsl", "nglod/shaders/" "nglod_scatter_cas.wgsl", "nglod/shaders/" "nglod_train.wgsl"],
    wgpu::Features::SUBGROUP
);
/// NGLOD MLP-gradient and loss reduction.
pub const NGLOD_REDUCE: Shader =
    shader!("nglod/shaders/" "nglod_reduce.wgsl", wgpu::Features::empty());

/// SIREN's tiled GEMM with the sine forward / backward epilogues.
pub const SIREN_GEMM: Shader = shader!("siren/shaders/" "siren_gemm.wgsl", wgpu::Features::empty());
/// SIREN's hidden layers with the weights in uniform-buffer windows (forward, backward and
/// weight-gradient partials).
pub const SIREN_DENSE: Shader =
    shader!("siren/shaders/" "siren_dense.wgsl", wgpu::Features::empty());
/// SIREN's tiled per-layer GEMM for GPUs, with the layer epilogues fused in.
pub const SIREN_TILED_LAYER: Shader =
    shader!("siren/shaders/" "siren_tiled_layer.wgsl", wgpu::Features::empty());
/// SIREN inference in one dispatch for GPUs: every layer of a tile of points, activations in
/// workgroup memory.
pub const SIREN_TILED_FUSED: Shader = shader!(
    "siren/shaders/" "siren_tiled_fused.wgsl" with ["serve/shaders/" "query_map.wgsl"],
    wgpu::Features::empty()
);
/// The features of the cooperative-matrix kernels.
const COOP: wgpu::Features = wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX
    .union(wgpu::Features::SHADER_F16)
    .union(wgpu::Features::SUBGROUP);
/// SIREN inference on f16 16 × 16 cooperative matrices (tensor cores), every layer in one
/// dispatch.
pub const SIREN_COOP_16: Shader = shader!(
    "siren/shaders/" "siren_coop_16x16.wgsl" then ["serve/shaders/" "query_map.wgsl", "siren/shaders/" "siren_coop.wgsl"],
    COOP
);
/// [`SIREN_COOP_16`] on 8 × 8 tiles.
pub const SIREN_COOP_8: Shader = shader!(
    "siren/shaders/" "siren_coop_8x8.wgsl" then ["serve/shaders/" "query_map.wgsl", "siren/shaders/" "siren_coop.wgsl"],
    COOP
);
/// SIREN's output layer, loss and its derivative.
pub const SIREN_HEAD: Shader = shader!(
    "siren/shaders/" "siren_head.wgsl" with ["siren/shaders/" "siren_loss.wgsl"],
    wgpu::Features::empty()
);
/// The elementwise and per-point kernels of SIREN's reverse-over-reverse training step.
pub const SIREN_ROR: Shader = shader!(
    "siren/shaders/" "siren_ror.wgsl" with ["siren/shaders/" "siren_loss.wgsl"],
    wgpu::Features::empty()
);
/// SIREN's batch sampling and reductions.
pub const SIREN_TRAIN: Shader =
    shader!("siren/shaders/" "siren_train.wgsl", wgpu::Features::empty());

/// The serving path's ends: points to network input, network output to distances and normals.
pub const QUERY: Shader = shader!("serve/shaders/" "query.wgsl" with ["serve/shaders/" "query_map.wgsl"], wgpu::Features::empty());

/// The sphere tracer of [`mod@crate::serve::render`]. It calls `hwsdf_trace` / `hwsdf_normal`, so it
/// compiles only after a model's [`crate::NeuralSdf::wgsl`] snippet (listed in [`NEEDS_MODEL`]).
pub const SPHERE_TRACE: Shader =
    shader!("serve/shaders/" "sphere_trace.wgsl", wgpu::Features::empty());

/// The batch queries of a scene ([`crate::serve::scene::GpuScene`]). They call
/// `scene_distance` / `scene_sample`, so they compile only after a scene's snippet (listed in
/// [`NEEDS_MODEL`]).
pub const SCENE_QUERY: Shader =
    shader!("serve/scene/shaders/" "scene_query.wgsl", wgpu::Features::empty());

/// The scene's queries with one element per subgroup. They call the element functions of
/// [`SCENE_QUERY`] and a scene snippet of the subgroup form, so they compile only after both.
pub const SCENE_QUERY_SUBGROUP: Shader = shader!(
    "serve/scene/shaders/" "scene_query_subgroup.wgsl",
    wgpu::Features::SUBGROUP
);

/// The analytic primitives and operators of a scene's snippet
/// ([`crate::serve::scene::Scene::wgsl_with_prefix`], which renames them).
pub const SCENE_PRIMITIVES: Shader =
    shader!("serve/scene/shaders/" "primitives.wgsl", wgpu::Features::empty());

/// Ground truth on the GPU: the nearest triangle on the mesh's 4-wide BVH, the closest point.
pub const GROUND_TRUTH_CLOSEST: Shader =
    shader!("ground_truth/shaders/" "closest.wgsl", wgpu::Features::empty());
/// Ground truth on the GPU: the fast winding number and the signed distance (after
/// `closest.wgsl`, whose search and bindings it uses).
pub const GROUND_TRUTH_WINDING: Shader = shader!(
    "ground_truth/shaders/" "winding.wgsl" with ["ground_truth/shaders/" "closest.wgsl"],
    wgpu::Features::empty()
);
/// Ground truth on the GPU: a batch's points grouped by cell (a counting sort by Morton code),
/// the order the other ground-truth kernels take them in.
pub const GROUND_TRUTH_BIN: Shader =
    shader!("ground_truth/shaders/" "bin.wgsl", wgpu::Features::empty());
/// Training points on the GPU: uniform, on and near the surface, from Philox4x32-10.
pub const GROUND_TRUTH_SAMPLE: Shader =
    shader!("ground_truth/shaders/" "sample.wgsl", wgpu::Features::empty());

/// Files of shared WGSL that the `shader!` macro prepends to the shaders that use them; they
/// are validated as part of those.
pub const SHARED_PARTS: &[&str] = &[
    "siren_loss.wgsl",
    "siren_coop.wgsl",
    "nglod_grid.wgsl",
    "nglod_scatter_atomic.wgsl",
    "nglod_scatter_cas.wgsl",
    "query_map.wgsl",
];

/// Shaders that are completed by a model's WGSL snippet (prepended at group 1).
pub const NEEDS_MODEL: &[&str] = &[
    SPHERE_TRACE.name,
    SCENE_QUERY.name,
    SCENE_QUERY_SUBGROUP.name,
];

/// Every shader, for validation.
pub const ALL: &[Shader] = &[
    SPHERE_TRACE,
    ADAM,
    SIREN_GEMM,
    SIREN_DENSE,
    SIREN_TILED_LAYER,
    SIREN_TILED_FUSED,
    SIREN_COOP_16,
    SIREN_COOP_8,
    SIREN_HEAD,
    SIREN_ROR,
    SIREN_TRAIN,
    NGLOD_FORWARD,
    NGLOD_QUERY_SUBGROUP,
    NGLOD_TRAIN_ATOMIC,
    NGLOD_TRAIN_CAS,
    NGLOD_TRAIN_SUBGROUP_ATOMIC,
    NGLOD_TRAIN_SUBGROUP_CAS,
    NGLOD_REDUCE,
    QUERY,
    SCENE_QUERY,
    SCENE_QUERY_SUBGROUP,
    SCENE_PRIMITIVES,
    GROUND_TRUTH_CLOSEST,
    GROUND_TRUTH_WINDING,
    GROUND_TRUTH_BIN,
    GROUND_TRUTH_SAMPLE,
];

/// Asserts, in a test, that the Rust struct `$rust`, written into a uniform or storage buffer,
/// has the layout of the WGSL struct `$wgsl` of `$shader` that reads it: each listed field at
/// the offset of the WGSL member of the same name, every WGSL member listed, and the Rust
/// struct at least as large. Padding fields (`_pad`) need not be listed. One check per pair
/// keeps the hand-written mirrors in step with the shaders.
#[cfg(test)]
macro_rules! assert_mirrors {
    ($rust:ty, $shader:expr, $wgsl:literal, [$($field:ident),* $(,)?]) => {
        $crate::shaders::check_mirror(
            &$shader,
            $wgsl,
            std::mem::size_of::<$rust>(),
            &[$((stringify!($field), std::mem::offset_of!($rust, $field))),*],
        )
    };
}
#[cfg(test)]
pub(crate) use assert_mirrors;

/// Stand-ins for what a model's or a scene's snippet defines, for [`check_mirror`] of the
/// shaders in [`NEEDS_MODEL`] (only their own types matter there).
#[cfg(test)]
const MODEL_STAND_INS: &str =
    "fn hwsdf_trace(p: vec3<f32>, c: f32) -> vec2<f32> { return vec2<f32>(0.0); }
fn hwsdf_normal(p: vec3<f32>) -> vec3<f32> { return p; }
struct scene_Sample { d: f32, g: vec3<f32>, leaf: u32 }
fn scene_distance(p: vec3<f32>) -> f32 { return 0.0; }
fn scene_sample(p: vec3<f32>) -> scene_Sample { return scene_Sample(0.0, p, 0u); }
fn scene_trace(p: vec3<f32>, c: f32) -> vec2<f32> { return vec2<f32>(0.0); }";

/// The check of [`assert_mirrors`]: `fields` are the Rust fields' names and byte offsets.
#[cfg(test)]
pub(crate) fn check_mirror(
    shader: &Shader,
    wgsl: &str,
    rust_size: usize,
    fields: &[(&str, usize)],
) {
    // A shader that calls a model's snippet gets stand-ins: only its own types matter here.
    let source = if NEEDS_MODEL.contains(&shader.name) {
        format!("{MODEL_STAND_INS}\n{}", shader.source)
    } else {
        shader.source.to_owned()
    };
    let module = naga::front::wgsl::parse_str(&source)
        .unwrap_or_else(|e| panic!("{}: {}", shader.name, e.emit_to_string(&source)));
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).expect("layout");
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(wgsl))
        .unwrap_or_else(|| panic!("{}: no struct {wgsl}", shader.name));
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{}: {wgsl} is not a struct", shader.name);
    };
    let wgsl_fields: Vec<(&str, usize)> = members
        .iter()
        .filter_map(|m| Some((m.name.as_deref()?, m.offset as usize)))
        .filter(|(name, _)| !name.starts_with('_'))
        .collect();
    assert_eq!(
        wgsl_fields, fields,
        "{}: the Rust mirror of {wgsl} (left: WGSL members and offsets) differs",
        shader.name
    );
    assert!(
        rust_size >= *span as usize,
        "{}: the Rust mirror of {wgsl} has {rust_size} bytes, the WGSL struct {span}",
        shader.name
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::SirenActivations;
    use crate::serve::wgsl::{self, Lanes};

    /// naga capabilities that correspond to a set of wgpu features. Validating with only these
    /// makes accidental use of any other capability fail.
    fn capabilities_for(features: wgpu::Features) -> naga::valid::Capabilities {
        use naga::valid::Capabilities as C;
        let mut caps = C::empty();
        if features.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC) {
            caps |= C::SHADER_FLOAT32_ATOMIC;
        }
        if features.contains(wgpu::Features::SUBGROUP) {
            caps |= C::SUBGROUP;
        }
        if features.contains(wgpu::Features::SHADER_F16) {
            caps |= C::SHADER_FLOAT16;
        }
        if features.contains(wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX) {
            caps |= C::COOPERATIVE_MATRIX;
        }
        caps
    }

    #[test]
    fn compile_shaders() {
        for shader in ALL {
            // A shader completed by a model's snippet is validated with the snippet of a small
            // model of each architecture, its SIRENs' activations in private arrays and in
            // scratch (behind the scratch's declarations); every other one on its own.
            let forms = [SirenActivations::Private, SirenActivations::Scratch];
            let prelude = |form| match form {
                SirenActivations::Private => String::new(),
                SirenActivations::Scratch => wgsl::scratch_source(2, 64),
            };
            let sources: Vec<String> = if shader.name == SCENE_QUERY.name {
                forms
                    .map(|form| {
                        let scene = small_scene_wgsl(Lanes::One, form);
                        format!("{}{scene}\n{}", prelude(form), shader.source)
                    })
                    .to_vec()
            } else if shader.name == SCENE_QUERY_SUBGROUP.name {
                forms
                    .map(|form| {
                        let scene = small_scene_wgsl(Lanes::Subgroup, form);
                        let query = SCENE_QUERY.source;
                        format!("{}{scene}\n{query}\n{}", prelude(form), shader.source)
                    })
                    .to_vec()
            } else if NEEDS_MODEL.contains(&shader.name) {
                small_models()
                    .iter()
                    .flat_map(|m| {
                        forms.map(|form| {
                            let snippet = m.wgsl_with_activations(1, form);
                            format!("{}{snippet}\n{}", prelude(form), shader.source)
                        })
                    })
                    .collect()
            } else {
                vec![shader.source.to_owned()]
            };
            for source in &sources {
                validate(shader, source);
            }
        }
    }

    /// The snippet (prefix `scene`, group 1, in the form for `lanes`) of a scene of the small
    /// models and every primitive under every operator.
    fn small_scene_wgsl(lanes: Lanes, activations: SirenActivations) -> String {
        use crate::serve::scene::{Primitive as P, Scene, SceneNode as N, Transform};
        use glam::{Quat, Vec3};
        use std::sync::Arc;
        let at = |x: f32| Transform::new(Vec3::X * x, Quat::from_rotation_y(x), 1.0 + x);
        let prim = |p, x| N::primitive(p, at(x));
        let e = Vec3::new(0.3, 0.4, 0.5);
        let prims = [
            prim(P::Sphere { radius: 0.5 }, 0.1),
            prim(P::Box { half_extents: e }, 0.2),
            prim(
                P::RoundBox {
                    half_extents: e,
                    radius: 0.1,
                },
                0.3,
            ),
            prim(
                P::Capsule {
                    a: -e,
                    b: e,
                    radius: 0.2,
                },
                0.4,
            ),
            prim(
                P::Torus {
                    major: 0.5,
                    minor: 0.1,
                },
                0.5,
            ),
            prim(
                P::Plane {
                    normal: e,
                    offset: 0.1,
                },
                0.6,
            ),
            prim(
                P::Cylinder {
                    radius: 0.3,
                    half_height: 0.6,
                },
                0.7,
            ),
        ];
        let models: Vec<N> = small_models()
            .into_iter()
            .map(|m| N::model(Arc::new(m), at(0.8)))
            .collect();
        // A union of leaves with models compiles to the nearest-bound chain.
        let mut leaves = models.clone();
        leaves.push(prims[0].clone());
        let root = N::Union(vec![
            N::Union(leaves),
            N::SmoothUnion {
                k: 0.1,
                children: models,
            },
            N::SmoothIntersection {
                k: 0.2,
                children: prims[..2].to_vec(),
            },
            N::SmoothDifference {
                k: 0.3,
                children: prims[2..4].to_vec(),
            },
            N::Intersection(prims[4..6].to_vec()),
            N::Difference(vec![prims[6].clone(), prims[0].clone()]),
            N::Offset {
                r: 0.1,
                child: Box::new(prims[1].clone()),
            },
            N::Shell {
                t: 0.05,
                child: Box::new(prims[2].clone()),
            },
        ]);
        Scene::new(root)
            .expect("a valid scene")
            .wgsl_with_lanes(1, "scene", &wgpu::Limits::default(), lanes, activations)
            .expect("fits the default limits")
    }

    /// A tiny SIREN, a tiny NGLOD model and a tiny hash grid.
    fn small_models() -> Vec<crate::NeuralSdf> {
        let n = crate::Normalization::identity();
        let siren = crate::Siren::new(
            crate::SirenConfig {
                width: 8,
                hidden_layers: 2,
                omega0: 30.0,
            },
            1,
        )
        .expect("valid config");
        let nglod = crate::Nglod::new(crate::NglodConfig::small()).expect("valid config");
        // Three levels, the finest (17³ vertices) hashed into 1024 entries.
        let hashgrid = crate::Nglod::new(crate::NglodConfig::hashgrid(3, 4, 16, 2, 10, 8))
            .expect("valid config");
        [
            siren.to_model_file(n, serde_json::Value::Null),
            nglod.to_model_file(n, serde_json::Value::Null),
            hashgrid.to_model_file(n, serde_json::Value::Null),
        ]
        .into_iter()
        .map(|f| crate::NeuralSdf::from_model_file(f).expect("a model we just made"))
        .collect()
    }

    fn validate(shader: &Shader, source: &str) {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{}: {}", shader.name, e.emit_to_string(source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            capabilities_for(shader.required_features),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}: {}", shader.name, e.emit_to_string(source)));
    }

    /// Every `.wgsl` file under `src/`, by file name, with its contents.
    fn wgsl_files() -> Vec<(String, String)> {
        fn walk(dir: &std::path::Path, out: &mut Vec<(String, String)>) {
            for entry in std::fs::read_dir(dir).expect("src/ is readable").flatten() {
                let path = entry.path();
                if path.is_dir() {
                    walk(&path, out);
                } else if path.extension().is_some_and(|e| e == "wgsl") {
                    let name = entry.file_name().to_string_lossy().into_owned();
                    out.push((name, std::fs::read_to_string(&path).expect("readable")));
                }
            }
        }
        let mut out = Vec::new();
        walk(
            concat!(env!("CARGO_MANIFEST_DIR"), "/src").as_ref(),
            &mut out,
        );
        out.sort();
        out
    }

    /// A shader file that is not in [`ALL`] would escape validation; two files of one name
    /// would share a pipeline cache key.
    #[test]
    fn every_shader_file_is_registered() {
        let files = wgsl_files();
        let on_disk: Vec<String> = files.iter().map(|(n, _)| n.clone()).collect();
        let mut unique = on_disk.clone();
        unique.dedup();
        assert_eq!(on_disk, unique, "two shader files share a name");
        // A file completed in several ways is registered once per variant (`file+variant`).
        let mut registered: Vec<String> = ALL
            .iter()
            .map(|s| s.name.split('+').next().unwrap_or(s.name).to_owned())
            .collect();
        for part in SHARED_PARTS {
            let (_, text) = files
                .iter()
                .find(|(n, _)| n == part)
                .expect("shared part exists");
            assert!(
                ALL.iter().any(|s| s.source.contains(text.as_str())),
                "{part} is prepended to no shader"
            );
            registered.push((*part).to_owned());
        }
        registered.sort();
        registered.dedup();
        assert_eq!(on_disk, registered);
    }
}
