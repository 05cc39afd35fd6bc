//! Scene files: a scene in TOML, with models by path relative to the file.
//!
//! ```
//! use std::path::Path;
//! use glam::Vec3;
//! use sdf_nn::serve::scene::Scene;
//!
//! let text = r#"
//! [root]
//! type = "difference"
//!
//! [[root.children]]
//! type = "box"
//! half_extents = [1, 1, 1]
//!
//! [[root.children]]
//! type = "sphere"
//! radius = 0.5
//! translation = [1, 1, 1]
//! "#;
//! let scene = Scene::from_toml(text, Path::new("."))?;
//! assert_eq!(scene.distance(Vec3::new(3.0, 0.0, 0.0), 0.0), 2.0);
//! # Ok::<(), sdf_nn::serve::scene::SceneFileError>(())
//! ```
//!
//! # Format
//!
//! ```toml
//! # Models, by a name the tree uses, at paths relative to this file.
//! [models]
//! bunny = "models/bunny.safetensors"
//!
//! # The tree: one table per node, `type` naming the operator or leaf; inner nodes list
//! # their children (arrays of tables nest with dotted headers, or write inline tables).
//! [root]
//! type = "smooth_union"
//! k = 0.1
//!
//! [[root.children]]
//! type = "model"
//! model = "bunny"
//! translation = [0.0, 0.5, 0.0]
//! rotation = { axis = [0, 1, 0], degrees = 90 }
//! scale = 2.0
//!
//! [[root.children]]
//! type = "transform"
//! translation = [2, 0, 0]
//!
//! [[root.children.children]]
//! type = "torus"
//! major = 1.0
//! minor = 0.25
//! ```
//!
//! Leaves (each takes the optional placement keys `translation`, `rotation`, `scale`):
//!
//! | `type` | keys |
//! | --- | --- |
//! | `model` | `model`: a name from `[models]` |
//! | `sphere` | `radius` |
//! | `box` | `half_extents = [x, y, z]` |
//! | `round_box` | `half_extents`, `radius` (the rounding, at most the smallest half extent) |
//! | `capsule` | `a = [x, y, z]`, `b`, `radius` |
//! | `torus` | `major`, `minor` (around the y axis) |
//! | `plane` | `normal = [x, y, z]`, `offset` (the half space `n̂·p ≤ offset`, `n̂ = n/|n|`) |
//! | `cylinder` | `radius`, `half_height` (along the y axis) |
//!
//! Inner nodes (each has `children = [...]`): `union`, `intersection`, `difference` (the first
//! child minus the others), `smooth_union`, `smooth_intersection`, `smooth_difference` (with the
//! blend radius `k > 0`), `offset` (`r`, one child), `shell` (`t > 0`, one child), and
//! `transform` (the placement keys, one child). See [`super::tree`] for what each computes.
//!
//! The TOML parser refuses inline tables and arrays nested more than about 40 deep (a syntax
//! error with its place); write deeper trees with dotted headers, as above, which reach
//! [`MAX_DEPTH`].
//!
//! Placement: `translation = [x, y, z]` (default zero); `rotation = { axis = [x, y, z],
//! degrees = a }`, a right-handed rotation by `a` degrees about the axis (any non-zero length;
//! default none); `scale = s` or `scale = [s, s, s]`, uniform and `> 0` (default 1). A node's
//! point `x` maps to `translation + rotation(scale · x)` in its parent.
//!
//! # Errors
//!
//! Every bad input is a [`SceneFileError`] that says what and where: syntax errors, unknown
//! keys and node types, missing keys and values of the wrong type with the line and column;
//! bad values (a zero scale, `k ≤ 0`, ...) with the node's path (`root.children[1].children[0]`);
//! a model error with the model's name and file. Numbers may be integers or floats; `nan` and `inf` are
//! refused, as are values that overflow f32.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{DQuat, DVec3, Vec3};
use serde::Deserialize;
use toml::Spanned;

use crate::NeuralSdf;
use crate::serve::error::NeuralSdfError;
use crate::serve::scene::primitive::Primitive;
use crate::serve::scene::tree::{MAX_DEPTH, MAX_MODELS, Scene, SceneError, SceneNode, Transform};

/// How deeply the TOML text may nest (tables, arrays, dotted keys), checked before parsing so
/// that no document can exhaust the parser's stack: each tree level costs two (a table and its
/// `children` array), plus a few for a leaf's `rotation`.
pub const MAX_NESTING: usize = 2 * MAX_DEPTH + 8;

/// Errors of reading a scene file.
#[derive(Debug, thiserror::Error)]
pub enum SceneFileError {
    /// The scene file could not be read.
    #[error("cannot read scene file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The text is not TOML.
    #[error("TOML syntax error at line {line}, column {column}: {message}")]
    Syntax {
        /// 1-based line.
        line: usize,
        /// 1-based column (in characters).
        column: usize,
        /// The parser's message.
        message: String,
    },
    /// A table has a key its node does not take (or the file a top-level key other than
    /// `models` and `root`); the place is that of the key's value.
    #[error("unknown key `{key}` at line {line}, column {column}: {message}")]
    UnknownKey {
        /// The key.
        key: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The full message, with the keys expected.
        message: String,
    },
    /// A node's `type` is not an operator or leaf we know.
    #[error("unknown node type `{name}` at line {line}, column {column}: {message}")]
    UnknownOperator {
        /// The name given.
        name: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The full message, with the names expected.
        message: String,
    },
    /// A node lacks a key its type needs.
    #[error("`{node_type}` at line {line}, column {column} needs `{key}`")]
    MissingKey {
        /// The key.
        key: &'static str,
        /// The node's type.
        node_type: &'static str,
        /// 1-based line of the node.
        line: usize,
        /// 1-based column.
        column: usize,
    },
    /// A key has the wrong type, or the file has no `root`.
    #[error("at line {line}, column {column}: {message}")]
    Schema {
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// The text nests deeper than [`MAX_NESTING`] (a tree deeper than [`MAX_DEPTH`]).
    #[error("line {line}: the file nests deeper than a tree of at most {limit} levels needs")]
    TooDeep {
        /// Where the limit was passed.
        line: usize,
        /// [`MAX_DEPTH`].
        limit: usize,
    },
    /// More model files are declared than [`MAX_MODELS`] (names of one file count once).
    #[error("{count} model files are declared; a scene holds at most {limit}")]
    TooManyModels {
        /// Model files declared.
        count: usize,
        /// [`MAX_MODELS`].
        limit: usize,
    },
    /// A model file is missing or does not hold a valid model.
    #[error("model `{name}` ({path}): {source}")]
    Model {
        /// Its name in `[models]`.
        name: String,
        /// The path it was loaded from.
        path: PathBuf,
        /// Why it failed (boxed: it is large, and this error is rare).
        source: Box<NeuralSdfError>,
    },
    /// A node names a model that `[models]` does not declare.
    #[error("{node}: model `{name}` is not declared in [models]")]
    UnknownModel {
        /// The node.
        node: String,
        /// The name.
        name: String,
    },
    /// A number is NaN, infinite, too large for f32, or so small (and not zero) that f32
    /// rounds it to zero or a subnormal (an offset of 1e-50 had become no offset at all).
    #[error(
        "{node}: `{field}` = {value} is not an f32 (NaN, infinite, or outside f32's normal range)"
    )]
    NonFinite {
        /// The node.
        node: String,
        /// The key.
        field: &'static str,
        /// The value read.
        value: f64,
    },
    /// A scale given per axis differs between axes.
    #[error("{node}: scale {scale:?} is not uniform")]
    NonUniformScale {
        /// The node.
        node: String,
        /// The scale.
        scale: [f64; 3],
    },
    /// A rotation's axis is zero.
    #[error("{node}: rotation axis is zero")]
    ZeroAxis {
        /// The node.
        node: String,
    },
    /// A unary node (`offset`, `shell`, `transform`) does not have exactly one child.
    #[error("{node}: `{op}` needs exactly one child, it has {found}")]
    Children {
        /// The node.
        node: String,
        /// Its type.
        op: &'static str,
        /// Children given.
        found: usize,
    },
    /// The tree does not make a valid scene: a bad parameter (`k ≤ 0`, a zero scale, ...), a
    /// tree deeper than [`MAX_DEPTH`], too many leaves.
    #[error(transparent)]
    Scene(#[from] SceneError),
}

impl Scene {
    /// Loads a scene file; model paths are relative to its folder.
    pub fn load(path: impl AsRef<Path>) -> Result<Scene, SceneFileError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| SceneFileError::Io {
            path: path.to_owned(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new(""));
        Scene::from_toml(&text, base)
    }

    /// The model files a scene file names (joined to its folder), read without loading them
    /// or checking the rest of the file: what a command writing beside them must not replace.
    /// A file that cannot be read or parsed names none ([`Scene::load`] says why).
    pub fn model_paths(path: impl AsRef<Path>) -> Vec<PathBuf> {
        /// The `[models]` table alone.
        #[derive(Deserialize)]
        struct Models {
            #[serde(default)]
            models: BTreeMap<String, String>,
        }
        let path = path.as_ref();
        let base = path.parent().unwrap_or(Path::new(""));
        std::fs::read_to_string(path)
            .ok()
            .and_then(|text| toml::from_str::<Models>(&text).ok())
            .map_or_else(Vec::new, |m| {
                m.models.values().map(|rel| base.join(rel)).collect()
            })
    }

    /// A scene from TOML text; model paths are relative to `base_dir`.
    pub fn from_toml(text: &str, base_dir: &Path) -> Result<Scene, SceneFileError> {
        Ok(Scene::new(tree_from_toml(text, base_dir)?)?)
    }
}

/// The tree of a scene file (models loaded), before [`Scene::new`] validates its parameters.
pub fn tree_from_toml(text: &str, base_dir: &Path) -> Result<SceneNode, SceneFileError> {
    if let Some(line) = nesting_exceeded(text) {
        return Err(SceneFileError::TooDeep {
            line,
            limit: MAX_DEPTH,
        });
    }
    let file: FileScene = toml::from_str(text).map_err(|e| toml_error(text, e))?;
    // Names of one file share one copy of its weights (one upload, one Lipschitz measurement,
    // one of the scene's models), whatever path spells it: the limit counts files.
    let keyed: Vec<(String, PathBuf, PathBuf)> = file
        .models
        .into_iter()
        .map(|(name, rel)| {
            let path = base_dir.join(&rel);
            let key = std::fs::canonicalize(&path).unwrap_or_else(|_| path.clone());
            (name, path, key)
        })
        .collect();
    let files: std::collections::BTreeSet<&PathBuf> = keyed.iter().map(|(_, _, k)| k).collect();
    if files.len() > MAX_MODELS {
        return Err(SceneFileError::TooManyModels {
            count: files.len(),
            limit: MAX_MODELS,
        });
    }
    let mut models = BTreeMap::new();
    let mut loaded: BTreeMap<PathBuf, Arc<NeuralSdf>> = BTreeMap::new();
    for (name, path, key) in keyed {
        let model = match loaded.get(&key) {
            Some(model) => model.clone(),
            None => {
                let model = NeuralSdf::load(&path).map_err(|source| SceneFileError::Model {
                    name: name.clone(),
                    path: path.clone(),
                    source: Box::new(source),
                })?;
                let model = Arc::new(model);
                loaded.insert(key, model.clone());
                model
            }
        };
        models.insert(name, model);
    }
    let converter = Converter {
        text,
        models: &models,
    };
    converter.node(file.root, "root".to_owned(), 1)
}

/// The file's top level.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileScene {
    #[serde(default)]
    models: BTreeMap<String, String>,
    root: Spanned<FileNode>,
}

/// `rotation = { axis = [x, y, z], degrees = a }`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileRotation {
    axis: [f64; 3],
    degrees: f64,
}

/// `scale = s` or `scale = [s, s, s]`.
#[derive(Deserialize)]
#[serde(untagged)]
enum FileScale {
    Uniform(f64),
    PerAxis([f64; 3]),
}

/// One node as read: every key that some node takes; `type` says which this one takes, checked
/// with the place of each key by [`Converter`]. A plain struct rather than an enum tagged by
/// `type`: serde buffers tagged enums, and the buffer loses the places of the keys.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileNode {
    #[serde(rename = "type")]
    kind: Spanned<String>,
    model: Option<Spanned<String>>,
    radius: Option<Spanned<f64>>,
    half_extents: Option<Spanned<[f64; 3]>>,
    a: Option<Spanned<[f64; 3]>>,
    b: Option<Spanned<[f64; 3]>>,
    major: Option<Spanned<f64>>,
    minor: Option<Spanned<f64>>,
    normal: Option<Spanned<[f64; 3]>>,
    offset: Option<Spanned<f64>>,
    half_height: Option<Spanned<f64>>,
    k: Option<Spanned<f64>>,
    r: Option<Spanned<f64>>,
    t: Option<Spanned<f64>>,
    translation: Option<Spanned<[f64; 3]>>,
    rotation: Option<Spanned<FileRotation>>,
    scale: Option<Spanned<FileScale>>,
    children: Option<Spanned<Vec<Spanned<FileNode>>>>,
}

impl FileNode {
    /// The keys given besides `type`, each with the place of its value.
    fn given(&self) -> Vec<(&'static str, Range<usize>)> {
        let mut out = Vec::new();
        macro_rules! given {
            ($($key:ident),*) => {$(
                if let Some(v) = &self.$key {
                    out.push((stringify!($key), v.span()));
                }
            )*};
        }
        given!(
            model,
            radius,
            half_extents,
            a,
            b,
            major,
            minor,
            normal,
            offset,
            half_height,
            k,
            r,
            t,
            translation,
            rotation,
            scale,
            children
        );
        out
    }
}

/// The keys of a leaf's placement.
const PLACEMENT: [&str; 3] = ["translation", "rotation", "scale"];

/// Each node type and the keys it takes besides `type` and, for leaves and `transform`, the
/// placement keys.
const NODE_TYPES: [(&str, &[&str]); 17] = [
    ("model", &["model"]),
    ("sphere", &["radius"]),
    ("box", &["half_extents"]),
    ("round_box", &["half_extents", "radius"]),
    ("capsule", &["a", "b", "radius"]),
    ("torus", &["major", "minor"]),
    ("plane", &["normal", "offset"]),
    ("cylinder", &["radius", "half_height"]),
    ("union", &["children"]),
    ("intersection", &["children"]),
    ("difference", &["children"]),
    ("smooth_union", &["k", "children"]),
    ("smooth_intersection", &["k", "children"]),
    ("smooth_difference", &["k", "children"]),
    ("offset", &["r", "children"]),
    ("shell", &["t", "children"]),
    ("transform", &["children"]),
];

/// Turns the file's nodes into [`SceneNode`]s.
struct Converter<'a> {
    text: &'a str,
    models: &'a BTreeMap<String, Arc<NeuralSdf>>,
}

/// A node being converted: its keys, type, place and path.
struct Node<'a> {
    keys: FileNode,
    kind: &'static str,
    at: Range<usize>,
    path: &'a str,
    text: &'a str,
}

impl Node<'_> {
    /// The error for a missing key.
    fn missing(&self, key: &'static str) -> SceneFileError {
        let (line, column) = line_column(self.text, self.at.start);
        SceneFileError::MissingKey {
            key,
            node_type: self.kind,
            line,
            column,
        }
    }

    /// A required number.
    fn number(&self, v: &Option<Spanned<f64>>, key: &'static str) -> Result<f32, SceneFileError> {
        let v = v.as_ref().ok_or_else(|| self.missing(key))?;
        num(self.path, key, *v.get_ref())
    }

    /// A required vector.
    fn vector(
        &self,
        v: &Option<Spanned<[f64; 3]>>,
        key: &'static str,
    ) -> Result<Vec3, SceneFileError> {
        let v = v.as_ref().ok_or_else(|| self.missing(key))?;
        vec3(self.path, key, *v.get_ref())
    }

    /// The placement keys as a transform.
    fn transform(&self) -> Result<Transform, SceneFileError> {
        let k = &self.keys;
        transform(
            self.path,
            k.translation.as_ref().map(|v| *v.get_ref()),
            k.rotation.as_ref().map(|v| v.get_ref()),
            k.scale.as_ref().map(|v| v.get_ref()),
        )
    }

    /// The primitive of a leaf type.
    fn primitive(&self) -> Result<Primitive, SceneFileError> {
        let k = &self.keys;
        Ok(match self.kind {
            "sphere" => Primitive::Sphere {
                radius: self.number(&k.radius, "radius")?,
            },
            "box" => Primitive::Box {
                half_extents: self.vector(&k.half_extents, "half_extents")?,
            },
            "round_box" => Primitive::RoundBox {
                half_extents: self.vector(&k.half_extents, "half_extents")?,
                radius: self.number(&k.radius, "radius")?,
            },
            "capsule" => Primitive::Capsule {
                a: self.vector(&k.a, "a")?,
                b: self.vector(&k.b, "b")?,
                radius: self.number(&k.radius, "radius")?,
            },
            "torus" => Primitive::Torus {
                major: self.number(&k.major, "major")?,
                minor: self.number(&k.minor, "minor")?,
            },
            "plane" => Primitive::Plane {
                normal: self.vector(&k.normal, "normal")?,
                offset: self.number(&k.offset, "offset")?,
            },
            "cylinder" => Primitive::Cylinder {
                radius: self.number(&k.radius, "radius")?,
                half_height: self.number(&k.half_height, "half_height")?,
            },
            other => unreachable!("`{other}` is not a primitive"),
        })
    }
}

impl Converter<'_> {
    /// Converts `node` at `path`, `depth` levels down (the root is 1).
    fn node(
        &self,
        node: Spanned<FileNode>,
        path: String,
        depth: usize,
    ) -> Result<SceneNode, SceneFileError> {
        if depth > MAX_DEPTH {
            return Err(SceneError::TooDeep {
                node: path,
                limit: MAX_DEPTH,
            }
            .into());
        }
        let at = node.span();
        let keys = node.into_inner();
        let kind = self.check_keys(&keys)?;
        let mut n = Node {
            keys,
            kind,
            at,
            path: &path,
            text: self.text,
        };
        let unary = ["offset", "shell", "transform"].contains(&kind);
        let children = match n.keys.children.take() {
            Some(c) => c.into_inner(),
            None if [
                "model",
                "sphere",
                "box",
                "round_box",
                "capsule",
                "torus",
                "plane",
                "cylinder",
            ]
            .contains(&kind) =>
            {
                Vec::new()
            }
            None => return Err(n.missing("children")),
        };
        if unary && children.len() != 1 {
            return Err(SceneFileError::Children {
                node: path.clone(),
                op: kind,
                found: children.len(),
            });
        }
        let convert = |children: Vec<Spanned<FileNode>>| -> Result<Vec<SceneNode>, _> {
            children
                .into_iter()
                .enumerate()
                .map(|(i, c)| self.node(c, format!("{path}.children[{i}]"), depth + 1))
                .collect()
        };
        let k = &n.keys;
        Ok(match kind {
            "model" => {
                let name = k
                    .model
                    .as_ref()
                    .ok_or_else(|| n.missing("model"))?
                    .get_ref();
                let Some(model) = self.models.get(name) else {
                    return Err(SceneFileError::UnknownModel {
                        node: path.clone(),
                        name: name.clone(),
                    });
                };
                SceneNode::model(model.clone(), n.transform()?)
            }
            "union" => SceneNode::Union(convert(children)?),
            "intersection" => SceneNode::Intersection(convert(children)?),
            "difference" => SceneNode::Difference(convert(children)?),
            "smooth_union" => SceneNode::SmoothUnion {
                k: n.number(&k.k, "k")?,
                children: convert(children)?,
            },
            "smooth_intersection" => SceneNode::SmoothIntersection {
                k: n.number(&k.k, "k")?,
                children: convert(children)?,
            },
            "smooth_difference" => SceneNode::SmoothDifference {
                k: n.number(&k.k, "k")?,
                children: convert(children)?,
            },
            "offset" => SceneNode::Offset {
                r: n.number(&k.r, "r")?,
                child: Box::new(convert(children)?.remove(0)),
            },
            "shell" => SceneNode::Shell {
                t: n.number(&k.t, "t")?,
                child: Box::new(convert(children)?.remove(0)),
            },
            "transform" => SceneNode::Transform {
                transform: n.transform()?,
                child: Box::new(convert(children)?.remove(0)),
            },
            _ => SceneNode::primitive(n.primitive()?, n.transform()?),
        })
    }

    /// The node's type, checked, and its keys checked against it.
    fn check_keys(&self, node: &FileNode) -> Result<&'static str, SceneFileError> {
        let name = node.kind.get_ref();
        let Some(&(kind, keys)) = NODE_TYPES.iter().find(|(n, _)| n == name) else {
            let (line, column) = line_column(self.text, node.kind.span().start);
            let known: Vec<&str> = NODE_TYPES.iter().map(|(n, _)| *n).collect();
            return Err(SceneFileError::UnknownOperator {
                name: name.clone(),
                line,
                column,
                message: format!("expected one of `{}`", known.join("`, `")),
            });
        };
        let placed = !keys.contains(&"children") || kind == "transform";
        let takes = |key: &str| keys.contains(&key) || (placed && PLACEMENT.contains(&key));
        if let Some((key, at)) = node.given().into_iter().find(|(key, _)| !takes(key)) {
            let (line, column) = line_column(self.text, at.start);
            let mut all: Vec<&str> = keys.to_vec();
            if placed {
                all.extend(PLACEMENT);
            }
            return Err(SceneFileError::UnknownKey {
                key: key.to_owned(),
                line,
                column,
                message: format!("`{kind}` takes `type`, `{}`", all.join("`, `")),
            });
        }
        Ok(kind)
    }
}

/// A number as a finite f32: zero, or normal (a non-zero number f32 would round to zero or a
/// subnormal is refused, not taken for another value).
fn num(node: &str, field: &'static str, value: f64) -> Result<f32, SceneFileError> {
    let v = value as f32;
    if v.is_normal() || value == 0.0 {
        Ok(v)
    } else {
        Err(SceneFileError::NonFinite {
            node: node.to_owned(),
            field,
            value,
        })
    }
}

/// Three numbers as a finite vector.
fn vec3(node: &str, field: &'static str, v: [f64; 3]) -> Result<Vec3, SceneFileError> {
    Ok(Vec3::new(
        num(node, field, v[0])?,
        num(node, field, v[1])?,
        num(node, field, v[2])?,
    ))
}

/// The placement keys as a [`Transform`] (the scale's sign is checked by [`Scene::new`]).
fn transform(
    node: &str,
    translation: Option<[f64; 3]>,
    rotation: Option<&FileRotation>,
    scale: Option<&FileScale>,
) -> Result<Transform, SceneFileError> {
    let translation = vec3(node, "translation", translation.unwrap_or_default())?;
    let rotation = match rotation {
        None => glam::Quat::IDENTITY,
        Some(r) => {
            let axis = DVec3::from_array(r.axis);
            vec3(node, "rotation.axis", r.axis)?;
            num(node, "rotation.degrees", r.degrees)?;
            if axis.length_squared() == 0.0 {
                return Err(SceneFileError::ZeroAxis {
                    node: node.to_owned(),
                });
            }
            DQuat::from_axis_angle(axis.normalize(), r.degrees.to_radians()).as_quat()
        }
    };
    let scale = match scale {
        None => 1.0,
        Some(FileScale::Uniform(s)) => num(node, "scale", *s)?,
        Some(FileScale::PerAxis(s)) => {
            vec3(node, "scale", *s)?;
            if s[0] != s[1] || s[1] != s[2] {
                return Err(SceneFileError::NonUniformScale {
                    node: node.to_owned(),
                    scale: *s,
                });
            }
            num(node, "scale", s[0])?
        }
    };
    Ok(Transform::new(translation, rotation, scale))
}

/// Classifies a TOML error and locates it.
fn toml_error(text: &str, e: toml::de::Error) -> SceneFileError {
    let (line, column) = e
        .span()
        .map(|s| line_column(text, s.start))
        .unwrap_or((1, 1));
    let message = e.message().trim().to_owned();
    // Serde's own wording (`unknown field `x`, expected ...`) for the top level's keys.
    let quoted = || message.split('`').nth(1).unwrap_or_default().to_owned();
    if toml::from_str::<toml::Table>(text).is_err() {
        SceneFileError::Syntax {
            line,
            column,
            message,
        }
    } else if message.starts_with("unknown field") {
        SceneFileError::UnknownKey {
            key: quoted(),
            line,
            column,
            message,
        }
    } else {
        SceneFileError::Schema {
            line,
            column,
            message,
        }
    }
}

/// The 1-based line and column (in characters) of byte `offset`.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let mut end = offset.min(text.len());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    let before = &text[..end];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().unwrap_or("").chars().count() + 1;
    (line, column)
}

/// The first line where the text nests deeper than [`MAX_NESTING`], by a conservative count
/// (never below the real depth): open brackets and braces, plus the dots of the keys of the
/// statement being read, plus twice the parts of the current table header (an array of tables
/// and its last table per part). Strings and comments are skipped.
fn nesting_exceeded(text: &str) -> Option<usize> {
    #[derive(PartialEq)]
    enum State {
        Code,
        Comment,
        Basic,
        Literal,
        MultiBasic,
        MultiLiteral,
    }
    let b = text.as_bytes();
    let (mut state, mut stack, mut line) = (State::Code, Vec::<u8>::new(), 1usize);
    let (mut table, mut dots, mut key, mut header) = (0usize, 0usize, true, false);
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        let three = |q: u8| b.get(i..i + 3) == Some(&[q, q, q][..]);
        match state {
            State::Comment if c == b'\n' => state = State::Code,
            State::Basic | State::MultiBasic if c == b'\\' => i += 1,
            State::Basic if c == b'"' => state = State::Code,
            State::Literal if c == b'\'' => state = State::Code,
            State::MultiBasic if three(b'"') => (state, i) = (State::Code, i + 2),
            State::MultiLiteral if three(b'\'') => (state, i) = (State::Code, i + 2),
            State::Code => match c {
                b'#' => state = State::Comment,
                b'"' if three(b'"') => (state, i) = (State::MultiBasic, i + 2),
                b'"' => state = State::Basic,
                b'\'' if three(b'\'') => (state, i) = (State::MultiLiteral, i + 2),
                b'\'' => state = State::Literal,
                b'[' | b'{' => {
                    // A `[` at the start of a statement opens a table header.
                    if stack.is_empty() && key && c == b'[' {
                        // The header names the table afresh.
                        (header, table) = (true, 0);
                    }
                    key = header || c == b'{';
                    stack.push(c);
                }
                b']' | b'}' => {
                    stack.pop();
                    key = header;
                }
                b',' => key = stack.last() == Some(&b'{'),
                b'=' => key = false,
                b'.' if key => dots += 1,
                _ => {}
            },
            _ => {}
        }
        if c == b'\n' {
            line += 1;
            if stack.is_empty() && state == State::Code {
                if header {
                    table = 2 * (dots + 1);
                }
                (dots, key, header) = (0, true, false);
            }
        }
        if table + dots + stack.len() > MAX_NESTING {
            return Some(line);
        }
        i += 1;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nesting_skips_strings_and_comments_and_counts_the_rest() {
        let deep = "[".repeat(MAX_NESTING + 1);
        let quiet = [
            format!("a = \"{deep}\"\n"),
            format!("a = '{deep}'\n"),
            format!("a = \"\"\"\n{deep}\n\"\"\"\n"),
            format!("a = '''\n{deep}\n'''\n"),
            format!("a = \"\\\"{deep}\"\n"),
            format!("# {deep}\n"),
            format!("a = [{}]\n", "1.5, ".repeat(1000)),
        ];
        for text in &quiet {
            assert_eq!(nesting_exceeded(text), None, "{text}");
        }
        assert_eq!(nesting_exceeded(&format!("x = 1\na = {deep}")), Some(2));
        let dotted = format!("{} = 1\n", vec!["a"; MAX_NESTING + 2].join("."));
        assert_eq!(nesting_exceeded(&dotted), Some(1));
        let header = format!("[{}]\nx = 1\n", vec!["a"; MAX_NESTING / 2 + 2].join("."));
        assert!(nesting_exceeded(&header).is_some());
        // Values' dots (floats, times) are not keys.
        assert_eq!(nesting_exceeded("[t]\nx = 1.25\ny = 07:32:00.5\n"), None);
    }

    #[test]
    fn places_count_lines_and_characters() {
        let text = "a = 1\nb = \"é\" x\n";
        assert_eq!(line_column(text, 0), (1, 1));
        assert_eq!(line_column(text, 6), (2, 1));
        // Byte 15 is the `x`, after the two-byte é: the 9th character of its line.
        assert_eq!(line_column(text, 15), (2, 9));
        // Inside the é: the character it belongs to.
        assert_eq!(line_column(text, 12), (2, 6));
        assert_eq!(line_column(text, 1000), (3, 1));
    }
}
