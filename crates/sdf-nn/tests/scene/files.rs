//! Bad trees built in code, and scene files: loading, depth, and every bad input.

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{Quat, Vec3};
use sdf_nn::serve::scene::{
    MAX_DEPTH, MAX_LEAVES, MAX_MODELS, Primitive, Scene, SceneError, SceneFileError, SceneNode,
    Transform,
};
use sdf_nn::{NeuralSdf, Nglod, Normalization};

use crate::models::{MODEL_RADIUS, normalization};
use crate::{assert_close, sphere_at};

/// Every bad tree built in code is refused with its typed error, naming the node.
#[test]
fn bad_trees_are_typed_errors() {
    let s = || sphere_at(Vec3::ZERO, 1.0);
    let err = |node: SceneNode| Scene::new(node).unwrap_err();
    let mut deep = s();
    for _ in 0..MAX_DEPTH {
        deep = SceneNode::Offset {
            r: 0.0,
            child: Box::new(deep),
        };
    }
    match err(deep) {
        SceneError::TooDeep { node, limit } => {
            assert_eq!(limit, MAX_DEPTH);
            assert_eq!(node.matches("children[0]").count(), MAX_DEPTH, "{node}");
        }
        e => panic!("{e:?}"),
    }
    let mut deepest = s();
    for _ in 1..MAX_DEPTH {
        deepest = SceneNode::Offset {
            r: 0.0,
            child: Box::new(deepest),
        };
    }
    assert_eq!(Scene::new(deepest).unwrap().depth(), MAX_DEPTH);
    assert!(matches!(
        err(SceneNode::Union((0..=MAX_LEAVES).map(|_| s()).collect())),
        SceneError::TooManyLeaves {
            limit: MAX_LEAVES,
            ..
        }
    ));
    let models: Vec<SceneNode> = (0..=MAX_MODELS)
        .map(|_| {
            let m = Nglod::from_sdf(2, |p| p.length() - 0.5).unwrap();
            let file = m.to_model_file(Normalization::identity(), serde_json::Value::Null);
            SceneNode::model(
                Arc::new(NeuralSdf::from_model_file(file).unwrap()),
                Transform::IDENTITY,
            )
        })
        .collect();
    match err(SceneNode::Union(models)) {
        SceneError::TooManyModels { node, limit } => {
            assert_eq!(limit, MAX_MODELS);
            assert_eq!(node, format!("root.children[{MAX_MODELS}]"));
        }
        e => panic!("{e:?}"),
    }
    let k_bad = |k| {
        err(SceneNode::SmoothUnion {
            k,
            children: vec![s(), s()],
        })
    };
    assert!(matches!(
        k_bad(0.0),
        SceneError::Parameter { field: "k", .. }
    ));
    assert!(matches!(
        k_bad(-1.0),
        SceneError::Parameter { field: "k", .. }
    ));
    assert!(matches!(
        k_bad(f32::NAN),
        SceneError::NonFinite { field: "k", .. }
    ));
    let placed = |t: Transform| err(SceneNode::Union(vec![s(), s().transformed(t)]));
    match placed(Transform {
        scale: 0.0,
        ..Transform::IDENTITY
    }) {
        SceneError::Scale { node, scale } => {
            assert_eq!((node.as_str(), scale), ("root.children[1]", 0.0))
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        placed(Transform {
            scale: -2.0,
            ..Transform::IDENTITY
        }),
        SceneError::Scale { .. }
    ));
    assert!(matches!(
        placed(Transform::from_translation(Vec3::new(
            0.0,
            f32::INFINITY,
            0.0
        ))),
        SceneError::NonFinite {
            field: "translation",
            ..
        }
    ));
    assert!(matches!(
        placed(Transform {
            rotation: Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
            ..Transform::IDENTITY
        }),
        SceneError::Rotation { .. }
    ));
    // Each transform fine alone, their composition out of f32's normal range: named, not left
    // to answer NaN on the CPU and zero scales on the GPU.
    let scaled = |scale| Transform {
        scale,
        ..Transform::IDENTITY
    };
    // (A subnormal scale, which a GPU may flush to zero, is refused on its own node.)
    for (scale, at) in [
        (1e20, "root.children[1].children[0]"),
        (1e-23, "root.children[1].children[0]"),
        (1e-40, "root.children[1]"),
    ] {
        let nested = s().transformed(scaled(scale)).transformed(scaled(scale));
        match err(SceneNode::Union(vec![s(), nested])) {
            SceneError::Placement { node, what, .. } => {
                assert_eq!((node.as_str(), what), (at, "scale"), "{scale}")
            }
            e => panic!("{scale}: {e:?}"),
        }
    }
    let far = Transform::from_translation(Vec3::X * 3e38);
    assert!(matches!(
        err(SceneNode::Union(vec![
            s(),
            s().transformed(far).transformed(far)
        ])),
        SceneError::Placement {
            what: "translation",
            ..
        }
    ));
    // An operator's parameter in the scene's units: k = 1e-30 under a scale of 1e-10.
    let tiny_blend = SceneNode::SmoothUnion {
        k: 1e-30,
        children: vec![s(), s()],
    }
    .transformed(scaled(1e-10));
    assert!(matches!(
        err(SceneNode::Union(vec![s(), tiny_blend])),
        SceneError::Placement { what: "k", .. }
    ));
    match err(SceneNode::Shell {
        t: 0.1,
        child: Box::new(sphere_at(Vec3::ZERO, -1.0)),
    }) {
        SceneError::Parameter {
            node, field, value, ..
        } => {
            assert_eq!(
                (node.as_str(), field, value),
                ("root.children[0]", "radius", -1.0)
            )
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        err(SceneNode::Shell {
            t: 0.0,
            child: Box::new(s())
        }),
        SceneError::Parameter { field: "t", .. }
    ));
    assert!(matches!(
        err(SceneNode::Union(vec![])),
        SceneError::Children {
            op: "union",
            found: 0,
            ..
        }
    ));
    // A rotation quaternion of any length is normalised.
    let long = Transform {
        rotation: Quat::from_rotation_z(FRAC_PI_2) * 3.0,
        ..Transform::IDENTITY
    };
    let scene = Scene::new(sphere_at(Vec3::X, 1.0).transformed(long)).unwrap();
    assert_close(
        scene.distance(Vec3::new(0.0, 1.0, 0.0), 0.0),
        -1.0,
        1e-6,
        "normalised",
    );
}

/// A fresh folder for one test's files.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hwsdf-scene-{name}-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("models")).unwrap();
    dir
}

/// Writes the sphere model to `dir/models/ball.safetensors`.
fn write_model(dir: &Path) {
    let model = Nglod::from_sdf(16, |p| p.length() - MODEL_RADIUS).unwrap();
    model
        .to_model_file(normalization(), serde_json::Value::Null)
        .save(&dir.join("models/ball.safetensors"))
        .unwrap();
}

/// A scene file with a model placed twice, primitives and operators, in both TOML styles
/// (dotted headers and inline tables), loads into the scene it describes.
#[test]
fn scene_files_load() {
    let dir = temp_dir("load");
    write_model(&dir);
    let text = r#"
# Two trained spheres and a box, the box drilled.
[models]
ball = "models/ball.safetensors"

[root]
type = "union"

[[root.children]]
type = "model"
model = "ball"
translation = [-10, 0, 0]
rotation = { axis = [0, 0, 2], degrees = 90 }
scale = 0.5

[[root.children]]
type = "transform"
translation = [10, 0, 0]
scale = [2, 2, 2]

[[root.children.children]]
type = "model"
model = "ball"

[[root.children]]
type = "difference"
children = [
    { type = "box", half_extents = [1, 1, 1], translation = [0, 0, 30] },
    { type = "cylinder", radius = 0.5, half_height = 2.0, translation = [0, 0, 30], rotation = { axis = [1, 0, 0], degrees = 90.0 } },
]
"#;
    std::fs::write(dir.join("scene.toml"), text).unwrap();
    let scene = Scene::load(dir.join("scene.toml")).unwrap();
    assert_eq!(
        (scene.models().len(), scene.leaves().len(), scene.depth()),
        (1, 4, 3)
    );
    // Two names of one file (spelt two ways) are one model: one copy of its weights.
    let twice = text.replace(
        "ball = \"models/ball.safetensors\"",
        "ball = \"models/ball.safetensors\"\nagain = \"./models/../models/ball.safetensors\"",
    );
    let twice = twice.replacen("model = \"ball\"", "model = \"again\"", 1);
    assert!(twice.contains("again\"\n") && twice.contains("model = \"again\""));
    std::fs::write(dir.join("twice.toml"), twice).unwrap();
    let scene = Scene::load(dir.join("twice.toml")).unwrap();
    assert_eq!((scene.models().len(), scene.leaves().len()), (1, 4));
    let n = normalization();
    let turn = Quat::from_rotation_z(FRAC_PI_2);
    let a = Transform::new(Vec3::new(-10.0, 0.0, 0.0), turn, 0.5).apply(n.center.as_vec3());
    let b = Vec3::new(10.0, 0.0, 0.0) + 2.0 * n.center.as_vec3();
    let r = MODEL_RADIUS / n.scale;
    for (p, want, tol) in [
        // Inside the models' boxes (half size 4 mesh units: 1.67 radii).
        (a + Vec3::Y * 1.5 * r * 0.5, r as f64 * 0.25, 0.02),
        (b + Vec3::Z * 1.5 * r * 2.0, r as f64, 0.08),
        (Vec3::new(0.0, 0.0, 28.0), 1.0, 1e-5),
        // Drilled along z by the turned cylinder: the hole's wall is 0.5 from the axis.
        (Vec3::new(0.25, 0.0, 30.0), 0.25, 1e-5),
    ] {
        assert_close(scene.distance(p, 0.0), want, tol, &format!("{p}"));
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A tree of exactly the depth limit in dotted headers parses (nothing runs out of stack); one
/// level more is refused, and a very deep file is refused before it is parsed.
#[test]
fn deep_files_are_refused_not_crashed() {
    let headers = |depth: usize| {
        let mut text = String::from("[root]\ntype = \"union\"\n");
        let mut path = String::from("root");
        for level in 2..=depth {
            path.push_str(".children");
            let ty = if level == depth {
                "sphere\"\nradius = 1"
            } else {
                "union\""
            };
            text.push_str(&format!("[[{path}]]\ntype = \"{ty}\n"));
        }
        text
    };
    let inline = |depth: usize| {
        let mut text = String::from("root = ");
        for _ in 1..depth {
            text.push_str("{ type = \"offset\", r = 0.0, children = [");
        }
        text.push_str("{ type = \"sphere\", radius = 1 }");
        for _ in 1..depth {
            text.push_str("] }");
        }
        text
    };
    let scene = Scene::from_toml(&headers(MAX_DEPTH), Path::new(".")).unwrap();
    assert_eq!(scene.depth(), MAX_DEPTH);
    match Scene::from_toml(&headers(MAX_DEPTH + 1), Path::new(".")) {
        Err(SceneFileError::Scene(SceneError::TooDeep { node, limit })) => {
            assert_eq!(limit, MAX_DEPTH);
            assert_eq!(node.matches(".children[0]").count(), MAX_DEPTH);
        }
        other => panic!("{other:?}"),
    }
    // The TOML parser's own limit on nested inline tables and arrays comes first: a syntax
    // error with its place, not a crash.
    assert_eq!(
        Scene::from_toml(&inline(30), Path::new("."))
            .unwrap()
            .depth(),
        30
    );
    match Scene::from_toml(&inline(MAX_DEPTH), Path::new(".")) {
        Err(SceneFileError::Syntax {
            line: 1, message, ..
        }) => {
            assert!(message.contains("recurs"), "{message}")
        }
        other => panic!("{other:?}"),
    }
    for (style, make) in [
        ("headers", &headers as &dyn Fn(usize) -> String),
        ("inline", &inline),
    ] {
        match Scene::from_toml(&make(1000), Path::new(".")) {
            Err(SceneFileError::TooDeep { limit, .. }) => assert_eq!(limit, MAX_DEPTH),
            other => panic!("{style}: {other:?}"),
        }
    }
    // Brackets in strings and comments do not count.
    let text = format!(
        "# {}\n[root]\ntype = \"sphere\" # {}\nradius = 1\n",
        "[".repeat(500),
        "{".repeat(500)
    );
    Scene::from_toml(&text, Path::new(".")).unwrap();
}

/// Every bad scene file gives its typed error, saying what and where.
#[test]
fn bad_scene_files_are_typed_errors() {
    let dir = temp_dir("bad");
    write_model(&dir);
    std::fs::write(dir.join("models/garbage.safetensors"), b"not a model").unwrap();
    let parse = |text: &str| Scene::from_toml(text, &dir).unwrap_err();
    let ok_leaf = "[root]\ntype = \"sphere\"\nradius = 1\n";
    Scene::from_toml(ok_leaf, &dir).unwrap();

    match parse("[root]\ntype = \"sphere\"\nradius = = 1\n") {
        SceneFileError::Syntax { line, column, .. } => assert_eq!((line, column), (3, 10)),
        e => panic!("{e:?}"),
    }
    match parse("[root]\ntype = \"sphere\"\nradius = 1\nradiuss = 2\n") {
        SceneFileError::UnknownKey { key, line, .. } => {
            assert_eq!((key.as_str(), line), ("radiuss", 4))
        }
        e => panic!("{e:?}"),
    }
    // A key another node type takes is unknown to this one; in inline tables too.
    let text = "[root]\ntype = \"union\"\nchildren = [\n  { type = \"sphere\", radius = 1 },\n  \
                { type = \"box\", radius = 1, half_extents = [1, 1, 1] },\n]\n";
    match parse(text) {
        SceneFileError::UnknownKey {
            key,
            line,
            column,
            message,
        } => {
            assert_eq!((key.as_str(), line, column), ("radius", 5, 28), "{message}");
            assert!(message.contains("half_extents"), "{message}");
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse("[root]\ntype = \"union\"\nchildren = []\nscale = 2\n"),
        SceneFileError::UnknownKey { key, line: 4, .. } if key == "scale"
    ));
    assert!(matches!(
        parse("scene = 1\n[root]\ntype = \"sphere\"\nradius = 1\n"),
        SceneFileError::UnknownKey { key, line: 1, .. } if key == "scene"
    ));
    match parse("[root]\ntype = \"union\"\n[[root.children]]\ntype = \"unoin\"\n") {
        SceneFileError::UnknownOperator {
            name,
            line,
            column,
            message,
        } => {
            assert_eq!((name.as_str(), line, column), ("unoin", 4, 8));
            assert!(message.contains("smooth_union"), "{message}");
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse("[root]\ntype = \"union\"\n[[root.children]]\ntype = \"sphere\"\n"),
        SceneFileError::MissingKey {
            key: "radius",
            node_type: "sphere",
            line: 3,
            ..
        }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"smooth_union\"\nk = 1\n"),
        SceneFileError::MissingKey {
            key: "children",
            line: 1,
            ..
        }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"sphere\"\nradius = \"big\"\n"),
        SceneFileError::Schema { line: 3, .. }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"box\"\nhalf_extents = [1, 2]\n"),
        SceneFileError::Schema { line: 3, .. }
    ));
    assert!(
        matches!(parse("[models]\n"), SceneFileError::Schema { message, .. } if message.contains("root"))
    );
    let model =
        |file: &str| format!("[models]\nm = \"{file}\"\n[root]\ntype = \"model\"\nmodel = \"m\"\n");
    match parse(&model("models/missing.safetensors")) {
        SceneFileError::Model { name, path, .. } => {
            assert_eq!(name, "m");
            assert_eq!(path, dir.join("models/missing.safetensors"));
        }
        e => panic!("{e:?}"),
    }
    match parse(&model("models/garbage.safetensors")) {
        e @ SceneFileError::Model { .. } => assert!(e.to_string().contains("garbage.safetensors")),
        e => panic!("{e:?}"),
    }
    Scene::from_toml(&model("models/ball.safetensors"), &dir).unwrap();
    assert!(matches!(
        parse("[models]\nm = \"models/ball.safetensors\"\n[root]\ntype = \"model\"\nmodel = \"n\"\n"),
        SceneFileError::UnknownModel { node, name } if node == "root" && name == "n"
    ));
    // More model files than a scene holds, refused before any is read; as many names of one
    // file are one model.
    let many: String = (0..=MAX_MODELS)
        .map(|i| format!("m{i} = \"models/m{i}.safetensors\"\n"))
        .collect();
    assert!(matches!(
        parse(&format!(
            "[models]\n{many}[root]\ntype = \"sphere\"\nradius = 1\n"
        )),
        SceneFileError::TooManyModels {
            limit: MAX_MODELS,
            ..
        }
    ));
    let names: String = (0..=MAX_MODELS)
        .map(|i| format!("m{i} = \"models/ball.safetensors\"\n"))
        .collect();
    let one = Scene::from_toml(
        &format!("[models]\n{names}[root]\ntype = \"model\"\nmodel = \"m3\"\n"),
        &dir,
    )
    .unwrap();
    assert_eq!(one.models().len(), 1);

    // Placements and parameters, on the second child so the path says which.
    let child = |keys: &str| {
        format!(
            "[root]\ntype = \"union\"\n[[root.children]]\ntype = \"sphere\"\nradius = 1\n\
             [[root.children]]\ntype = \"sphere\"\nradius = 1\n{keys}\n"
        )
    };
    assert!(matches!(
        parse(&child("scale = [1, 2]")),
        SceneFileError::Schema { line: 9, .. }
    ));
    match parse(&child("scale = [1, 2, 1]")) {
        SceneFileError::NonUniformScale { node, scale } => {
            assert_eq!(
                (node.as_str(), scale),
                ("root.children[1]", [1.0, 2.0, 1.0])
            )
        }
        e => panic!("{e:?}"),
    }
    assert!(matches!(
        parse(&child("scale = 0")),
        SceneFileError::Scene(SceneError::Scale { node, .. }) if node == "root.children[1]"
    ));
    assert!(matches!(
        parse(&child("scale = -1.0")),
        SceneFileError::Scene(SceneError::Scale { .. })
    ));
    for (keys, field) in [
        ("translation = [0, nan, 0]", "translation"),
        ("scale = inf", "scale"),
        (
            "rotation = { axis = [0, 1, 0], degrees = -inf }",
            "rotation.degrees",
        ),
    ] {
        match parse(&child(keys)) {
            SceneFileError::NonFinite { node, field: f, .. } => {
                assert_eq!((node.as_str(), f), ("root.children[1]", field), "{keys}")
            }
            e => panic!("{keys}: {e:?}"),
        }
    }
    assert!(matches!(
        parse("[root]\ntype = \"sphere\"\nradius = 1e39\n"),
        SceneFileError::NonFinite {
            field: "radius",
            ..
        }
    ));
    // Too small for f32: refused, not rounded to zero (an offset of 1e-50 became none, a blend
    // radius of 1e-50 was reported as 0); zero itself is a number.
    for (text, field) in [
        ("[root]\ntype = \"sphere\"\nradius = 1e-50\n", "radius"),
        (
            "[root]\ntype = \"offset\"\nr = 1e-50\nchildren = [{ type = \"sphere\", radius = 1 }]\n",
            "r",
        ),
    ] {
        match parse(text) {
            SceneFileError::NonFinite {
                field: f, value, ..
            } => {
                assert_eq!((f, value), (field, 1e-50), "{text}")
            }
            e => panic!("{text}: {e:?}"),
        }
    }
    Scene::from_toml(&child("translation = [0, 0.0, -0.0]"), &dir).unwrap();
    assert!(matches!(
        parse(&child("rotation = { axis = [0, 0, 0], degrees = 10 }")),
        SceneFileError::ZeroAxis { node } if node == "root.children[1]"
    ));
    assert!(matches!(
        parse(&child("rotation = { axis = [0, 0, 1], degree = 10 }")),
        SceneFileError::UnknownKey { key, .. } if key == "degree"
    ));
    let smooth = |k: &str| {
        format!(
            "[root]\ntype = \"smooth_union\"\nk = {k}\nchildren = [{{ type = \"sphere\", radius = 1 }}]\n"
        )
    };
    for k in ["0", "-0.5"] {
        assert!(matches!(
            parse(&smooth(k)),
            SceneFileError::Scene(SceneError::Parameter { field: "k", .. })
        ));
    }
    assert!(matches!(
        parse(&smooth("nan")),
        SceneFileError::NonFinite { field: "k", .. }
    ));
    assert!(matches!(
        parse("[root]\ntype = \"offset\"\nr = 1\nchildren = []\n"),
        SceneFileError::Children {
            op: "offset",
            found: 0,
            ..
        }
    ));
    match Scene::load(dir.join("nowhere.toml")) {
        Err(SceneFileError::Io { path, .. }) => assert_eq!(path, dir.join("nowhere.toml")),
        other => panic!("{other:?}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Every node type read from a file is the node built in code.
#[test]
fn every_node_type_reads_as_built() {
    let text = r#"
[root]
type = "smooth_union"
k = 0.3

[[root.children]]
type = "intersection"
children = [
    { type = "round_box", half_extents = [0.8, 0.5, 0.6], radius = 0.1, translation = [-1, 0, 0] },
    { type = "plane", normal = [0, 1, 0.2], offset = 0.1 },
]

[[root.children]]
type = "smooth_intersection"
k = 0.2
children = [
    { type = "capsule", a = [-0.5, 0, 0], b = [0.5, 0, 0], radius = 0.2, scale = 1.5 },
    { type = "torus", major = 0.7, minor = 0.15, rotation = { axis = [1, 0, 0], degrees = 30 } },
]

[[root.children]]
type = "smooth_difference"
k = 0.1
children = [
    { type = "cylinder", radius = 0.4, half_height = 0.3, translation = [0, 1, 0] },
    { type = "shell", t = 0.05, children = [{ type = "sphere", radius = 0.3, translation = [0, 1.2, 0] }] },
]

[[root.children]]
type = "transform"
translation = [0.5, -1, 0]
rotation = { axis = [0, 0, 1], degrees = -45 }
scale = 0.8

[[root.children.children]]
type = "offset"
r = 0.05
children = [{ type = "box", half_extents = [0.3, 0.3, 0.3] }]
"#;
    let from_file = Scene::from_toml(text, Path::new(".")).unwrap();
    let prim = |p: Primitive, t: Transform| SceneNode::primitive(p, t);
    let at = Transform::from_translation;
    let built = SceneNode::SmoothUnion {
        k: 0.3,
        children: vec![
            SceneNode::Intersection(vec![
                prim(
                    Primitive::RoundBox {
                        half_extents: Vec3::new(0.8, 0.5, 0.6),
                        radius: 0.1,
                    },
                    at(Vec3::new(-1.0, 0.0, 0.0)),
                ),
                prim(
                    Primitive::Plane {
                        normal: Vec3::new(0.0, 1.0, 0.2),
                        offset: 0.1,
                    },
                    Transform::IDENTITY,
                ),
            ]),
            SceneNode::SmoothIntersection {
                k: 0.2,
                children: vec![
                    prim(
                        Primitive::Capsule {
                            a: Vec3::new(-0.5, 0.0, 0.0),
                            b: Vec3::new(0.5, 0.0, 0.0),
                            radius: 0.2,
                        },
                        Transform::new(Vec3::ZERO, Quat::IDENTITY, 1.5),
                    ),
                    prim(
                        Primitive::Torus {
                            major: 0.7,
                            minor: 0.15,
                        },
                        Transform::new(Vec3::ZERO, Quat::from_rotation_x(30f32.to_radians()), 1.0),
                    ),
                ],
            },
            SceneNode::SmoothDifference {
                k: 0.1,
                children: vec![
                    prim(
                        Primitive::Cylinder {
                            radius: 0.4,
                            half_height: 0.3,
                        },
                        at(Vec3::Y),
                    ),
                    SceneNode::Shell {
                        t: 0.05,
                        child: Box::new(sphere_at(Vec3::new(0.0, 1.2, 0.0), 0.3)),
                    },
                ],
            },
            SceneNode::Offset {
                r: 0.05,
                child: Box::new(prim(
                    Primitive::Box {
                        half_extents: Vec3::splat(0.3),
                    },
                    Transform::IDENTITY,
                )),
            }
            .transformed(Transform::new(
                Vec3::new(0.5, -1.0, 0.0),
                Quat::from_rotation_z(-FRAC_PI_4),
                0.8,
            )),
        ],
    };
    let built = Scene::new(built).unwrap();
    assert_eq!(from_file.program(), built.program());
    let points: Vec<Vec3> = (0..1000)
        .map(|i| {
            let t = i as f32 * 0.618;
            Vec3::new(t.sin() * 2.0, (1.7 * t).cos() * 2.0, (0.3 * t).sin() * 2.0)
        })
        .collect();
    for (p, (a, b)) in points.iter().zip(
        from_file
            .distances(&points, 0.0)
            .into_iter()
            .zip(built.distances(&points, 0.0)),
    ) {
        assert_close(a, b as f64, 1e-5, &format!("{p}"));
    }
}
