//! The glTF scene: its node graph (cycles, instance counts, which subtrees hold meshes), the
//! bound on its expanded size, node transforms and `EXT_mesh_gpu_instancing`, and the walk that
//! adds every mesh instance.

use std::path::Path;
use std::rc::Rc;

use glam::{DMat4, DQuat, DVec3, Mat4, Vec3};

use super::accessors::{Vec3Format, component, read_accessor};
use super::primitive::{Merged, add_gltf_mesh};
use super::{
    MAX_INSTANCED_TRIANGLES, MAX_INSTANCED_VERTICES, MAX_INSTANCES, MAX_NODE_VISITS, check_limits,
    node_error,
};
use crate::GeomError;

/// The node graph of one scene, checked and counted without expanding shared nodes.
pub(super) struct NodeGraph {
    /// How many times each node is instanced (number of paths from the scene's roots), saturating.
    multiplicity: Vec<u64>,
    /// Whether the node or a descendant has a mesh.
    mesh_below: Vec<bool>,
    /// Each node's transform in f64 ([`precise_node_transforms`]).
    precise: Vec<Option<Box<DMat4>>>,
}

/// Checks the scene's node graph for cycles and counts node instances through shared children.
/// `json_bytes` is the document's JSON, whose node transforms are read again in f64.
pub(super) fn node_graph(
    path: &Path,
    doc: &gltf::Document,
    json_bytes: &[u8],
    scene: &gltf::Scene,
) -> Result<NodeGraph, GeomError> {
    let n = doc.nodes().len();
    let children: Vec<Vec<usize>> = doc
        .nodes()
        .map(|node| node.children().map(|c| c.index()).collect())
        .collect();
    // Iterative depth-first search: 0 unseen, 1 on the current path, 2 done.
    let mut state = vec![0u8; n];
    let mut post: Vec<usize> = Vec::with_capacity(n);
    for root in scene.nodes() {
        let r = root.index();
        if state[r] != 0 {
            continue;
        }
        let mut stack: Vec<(usize, usize)> = vec![(r, 0)];
        state[r] = 1;
        while let Some(&mut (node, ref mut next)) = stack.last_mut() {
            if let Some(&child) = children[node].get(*next) {
                *next += 1;
                match state[child] {
                    0 => {
                        state[child] = 1;
                        stack.push((child, 0));
                    }
                    1 => {
                        return Err(GeomError::Parse {
                            path: path.to_path_buf(),
                            line: None,
                            message: format!(
                                "the node graph has a cycle: node {node} has node {child}, one of its ancestors, as a child"
                            ),
                        });
                    }
                    _ => {}
                }
            } else {
                state[node] = 2;
                post.push(node);
                stack.pop();
            }
        }
    }
    let mut mesh_below: Vec<bool> = doc.nodes().map(|x| x.mesh().is_some()).collect();
    for &node in &post {
        mesh_below[node] = mesh_below[node] || children[node].iter().any(|&c| mesh_below[c]);
    }
    let mut multiplicity = vec![0u64; n];
    for root in scene.nodes() {
        multiplicity[root.index()] = multiplicity[root.index()].saturating_add(1);
    }
    // Reverse post-order is a topological order: parents before children.
    for &node in post.iter().rev() {
        let m = multiplicity[node];
        for &c in &children[node] {
            multiplicity[c] = multiplicity[c].saturating_add(m);
        }
    }
    Ok(NodeGraph {
        multiplicity,
        mesh_below,
        precise: precise_node_transforms(json_bytes),
    })
}

/// Triangles and vertices one instance of `mesh` adds (from accessor counts; nothing is read).
fn mesh_size(mesh: &gltf::Mesh) -> (u64, u64) {
    use gltf::mesh::Mode;
    let (mut tris, mut verts) = (0u64, 0u64);
    for prim in mesh.primitives() {
        let Some(pos) = prim.get(&gltf::Semantic::Positions) else {
            // Looked at for every instance all the same: not free either.
            verts = verts.saturating_add(1);
            continue;
        };
        let n = match prim.indices() {
            Some(acc) => acc.count() as u64,
            None => pos.count() as u64,
        };
        tris = tris.saturating_add(match prim.mode() {
            Mode::Triangles => n / 3,
            Mode::TriangleStrip | Mode::TriangleFan => n.saturating_sub(2),
            _ => 0,
        });
        // Each morph target may be read in full for every instance: its positions count as
        // vertices (at least one per target, so that empty targets are not free either).
        let targets = prim.morph_targets().len() as u64;
        let per_target = (pos.count() as u64).max(1);
        verts = verts
            .saturating_add(per_target)
            .saturating_add(targets.saturating_mul(per_target));
    }
    (tris, verts)
}

/// Bounds the scene before anything is read: mesh instances (through shared nodes and
/// `EXT_mesh_gpu_instancing`), and the triangles and vertices they would add, against
/// [`MAX_INSTANCES`], [`MAX_INSTANCED_TRIANGLES`] and [`MAX_INSTANCED_VERTICES`]. Without a
/// scene (`graph` is `None`), every mesh counts once.
pub(super) fn check_scene_size(
    path: &Path,
    doc: &gltf::Document,
    graph: Option<&NodeGraph>,
    instancing: &[Option<GpuInstancing>],
) -> Result<(), GeomError> {
    // Which meshes are used, how often, and what they would add; and how many node visits the
    // expansion makes (every path to every node with a mesh below it, each visit looking at
    // the node's children: a long chain, or a node of many childless children, reached by
    // many paths costs visits, not instances).
    let mut mesh_uses = vec![0u64; doc.meshes().len()];
    let mut visits = 0u64;
    match graph {
        Some(g) => {
            for node in doc.nodes().filter(|n| g.mesh_below[n.index()]) {
                let work = 1 + node.children().len() as u64;
                visits = visits.saturating_add(g.multiplicity[node.index()].saturating_mul(work));
            }
            for node in doc.nodes() {
                if let Some(mesh) = node.mesh() {
                    let copies = instancing[node.index()]
                        .as_ref()
                        .map_or(1, |i| i.count as u64);
                    let m = &mut mesh_uses[mesh.index()];
                    *m = m.saturating_add(g.multiplicity[node.index()].saturating_mul(copies));
                }
            }
        }
        None => mesh_uses.iter_mut().for_each(|m| *m = 1),
    }
    let (mut instances, mut tris, mut verts) = (0u64, 0u64, 0u64);
    for mesh in doc.meshes() {
        let uses = mesh_uses[mesh.index()];
        if uses == 0 {
            continue;
        }
        let (t, v) = mesh_size(&mesh);
        instances = instances.saturating_add(uses);
        tris = tris.saturating_add(uses.saturating_mul(t));
        verts = verts.saturating_add(uses.saturating_mul(v));
    }
    check_limits(
        path,
        [
            ("mesh instances", instances, MAX_INSTANCES),
            ("node visits", visits, MAX_NODE_VISITS),
            ("instanced triangles", tris, MAX_INSTANCED_TRIANGLES),
            ("instanced vertices", verts, MAX_INSTANCED_VERTICES),
        ],
    )
}

/// The nodes' transforms as the file writes them, in f64, by node index (`None` where the file
/// gives none or the JSON does not read as expected: the checked f32 transform serves). `gltf`
/// reads them as f32, which moved a part placed at 6 378 137.1 (an Earth-centred survey
/// coordinate) to 6 378 137.0 and its neighbour at .4 to .5: 0.2 apart that were 0.3. Boxed,
/// so that millions of nodes without a transform cost a pointer each, as they are read and
/// after (`{}` is three bytes of JSON).
fn precise_node_transforms(json_bytes: &[u8]) -> Vec<Option<Box<DMat4>>> {
    #[derive(serde::Deserialize)]
    struct Root {
        #[serde(default)]
        nodes: Vec<Node>,
    }
    #[derive(serde::Deserialize)]
    struct Node {
        matrix: Option<Box<[f64; 16]>>,
        translation: Option<Box<[f64; 3]>>,
        rotation: Option<Box<[f64; 4]>>,
        scale: Option<Box<[f64; 3]>>,
    }
    let Ok(root) = serde_json::from_slice::<Root>(json_bytes) else {
        return Vec::new();
    };
    root.nodes
        .into_iter()
        .map(|n| {
            let m = match n {
                Node {
                    matrix: Some(m), ..
                } => DMat4::from_cols_array(&m),
                Node {
                    matrix: None,
                    translation: None,
                    rotation: None,
                    scale: None,
                } => return None,
                Node {
                    translation,
                    rotation,
                    scale,
                    ..
                } => {
                    let q = DQuat::from_array(rotation.map_or([0.0, 0.0, 0.0, 1.0], |r| *r));
                    DMat4::from_scale_rotation_translation(
                        DVec3::from_array(scale.map_or([1.0; 3], |s| *s)),
                        q / q.length(),
                        DVec3::from_array(translation.map_or([0.0; 3], |t| *t)),
                    )
                }
            };
            m.is_finite().then(|| Box::new(m))
        })
        .collect()
}

/// Adds every mesh instance of `scene` to `out`: the instance paths expanded depth first from
/// the scene's roots, skipping subtrees without meshes (the counts of [`check_scene_size`] bound
/// this), each node's transform composed with its ancestors' and checked to stay finite.
pub(super) fn expand_scene(
    path: &Path,
    doc: &gltf::Document,
    scene: &gltf::Scene,
    graph: &NodeGraph,
    instancing: &[Option<GpuInstancing>],
    buffers: &[Rc<[u8]>],
    out: &mut Merged,
) -> Result<(), GeomError> {
    // A mesh's warnings are given at its first instance only (a million instances, one warning).
    let mut warned = vec![false; doc.meshes().len()];
    let mut stack: Vec<(gltf::Node, DMat4)> = scene
        .nodes()
        .filter(|n| graph.mesh_below[n.index()])
        .map(|n| (n, DMat4::IDENTITY))
        .collect();
    stack.reverse();
    while let Some((node, parent)) = stack.pop() {
        // Checked as `gltf` reads it, composed in f64 as the file writes it: a far translation
        // keeps the mesh's shape and its place (f32 would round both).
        let checked = node_matrix(path, &node)?;
        let local = graph
            .precise
            .get(node.index())
            .and_then(|m| m.as_deref().copied())
            .unwrap_or(checked.as_dmat4());
        let world = parent * local;
        if !world.as_mat4().is_finite() {
            return Err(node_error(
                path,
                &node,
                "its transform composed with its ancestors' is not finite in float32".into(),
            ));
        }
        if let Some(mesh) = node.mesh() {
            let weights = node.weights().or_else(|| mesh.weights());
            let worlds = instance_worlds(path, &node, world, &instancing[node.index()], buffers)?;
            for world in worlds {
                out.report.instances += 1;
                add_gltf_mesh(
                    path,
                    Some(&node),
                    &mesh,
                    world,
                    weights.unwrap_or_default(),
                    !std::mem::replace(&mut warned[mesh.index()], true),
                    buffers,
                    out,
                )?;
            }
        }
        let first = stack.len();
        stack.extend(
            node.children()
                .filter(|c| graph.mesh_below[c.index()])
                .map(|c| (c, world)),
        );
        stack[first..].reverse();
    }
    Ok(())
}

/// Where a node with a mesh draws it: at its `world` transform, or with `EXT_mesh_gpu_instancing`
/// at each instance's, which applies after the node's (and to its mesh only).
fn instance_worlds(
    path: &Path,
    node: &gltf::Node,
    world: DMat4,
    instancing: &Option<GpuInstancing>,
    buffers: &[Rc<[u8]>],
) -> Result<Vec<DMat4>, GeomError> {
    match instancing {
        Some(inst) => instance_matrices(path, node.index(), inst, buffers)?
            .into_iter()
            .enumerate()
            .map(|(i, m)| {
                let w = world * m.as_dmat4();
                if w.as_mat4().is_finite() {
                    Ok(w)
                } else {
                    Err(node_error(
                        path,
                        node,
                        format!(
                            "EXT_mesh_gpu_instancing instance {i} composed with the node's transform is not finite in float32"
                        ),
                    ))
                }
            })
            .collect(),
        None => Ok(vec![world]),
    }
}

/// A node's local transform. glTF requires finite numbers, a unit quaternion and a matrix that
/// decomposes into translation, rotation and scale; the `gltf` crate checks none of them (a
/// scale of 1e39 reads as infinity), and a quaternion of length 2 would silently scale the mesh
/// by 4. A quaternion within 1 % of unit length (rounded by an exporter) is normalised; anything
/// else, a non-finite number and a projective matrix are [`GeomError::NodeTransform`].
fn node_matrix(path: &Path, node: &gltf::Node) -> Result<Mat4, GeomError> {
    let bad = |reason: String| node_error(path, node, reason);
    match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => {
            let m = Mat4::from_cols_array_2d(&matrix);
            if !m.is_finite() {
                return Err(bad(format!(
                    "its matrix {:?} has a component that is not finite",
                    m.to_cols_array()
                )));
            }
            let last = m.row(3);
            if (last - glam::Vec4::W).abs().max_element() > 1e-6 {
                return Err(bad(format!(
                    "its matrix is projective (last row {last}, not 0 0 0 1)"
                )));
            }
            Ok(m)
        }
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            for (what, v) in [
                ("translation", &translation[..]),
                ("rotation", &rotation[..]),
                ("scale", &scale[..]),
            ] {
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(bad(format!("its {what} {v:?} is not finite")));
                }
            }
            let q = glam::Quat::from_array(rotation);
            let len = q.length();
            if !(len - 1.0).abs().le(&0.01) {
                return Err(bad(format!(
                    "its rotation {rotation:?} is not a unit quaternion (length {len})"
                )));
            }
            Ok(Mat4::from_scale_rotation_translation(
                Vec3::from_array(scale),
                q / len,
                Vec3::from_array(translation),
            ))
        }
    }
}

/// A node's `EXT_mesh_gpu_instancing`: its mesh is drawn `count` times, each with the
/// translation, rotation and scale of its index in these accessors (absent: none).
pub(super) struct GpuInstancing<'a> {
    translation: Option<(gltf::Accessor<'a>, Vec3Format)>,
    rotation: Option<gltf::Accessor<'a>>,
    scale: Option<(gltf::Accessor<'a>, Vec3Format)>,
    pub(super) count: usize,
}

/// `node`'s [`GpuInstancing`], validated (accessors that exist, of the types the extension
/// allows, of one count), if it has the extension. Reads no buffer.
pub(super) fn gpu_instancing<'a>(
    path: &Path,
    accessors: &[gltf::Accessor<'a>],
    node: &gltf::Node,
) -> Result<Option<GpuInstancing<'a>>, GeomError> {
    use gltf::accessor::{DataType, Dimensions};
    // Only a node with a mesh is instanced; the extension means nothing on others.
    let Some(ext) = node
        .extension_value("EXT_mesh_gpu_instancing")
        .filter(|_| node.mesh().is_some())
    else {
        return Ok(None);
    };
    let bad = |message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message: format!("node {}: EXT_mesh_gpu_instancing: {message}", node.index()),
    };
    let attributes = ext
        .get("attributes")
        .and_then(|a| a.as_object())
        .ok_or_else(|| bad("no `attributes` object".into()))?;
    let accessor = |name: &str| -> Result<Option<gltf::Accessor<'a>>, GeomError> {
        let Some(v) = attributes.get(name) else {
            return Ok(None);
        };
        let i = v
            .as_u64()
            .ok_or_else(|| bad(format!("{name} is not an accessor index: {v}")))?;
        usize::try_from(i)
            .ok()
            .and_then(|i| accessors.get(i))
            .cloned()
            .map(Some)
            .ok_or_else(|| {
                bad(format!(
                    "{name} accessor {i} does not exist ({} accessors)",
                    accessors.len()
                ))
            })
    };
    let (translation, rotation, scale) = (
        accessor("TRANSLATION")?,
        accessor("ROTATION")?,
        accessor("SCALE")?,
    );
    let unsupported = |name: &str, acc: &gltf::Accessor| GeomError::Unsupported {
        path: path.to_path_buf(),
        feature: format!(
            "EXT_mesh_gpu_instancing {name} of type {:?} {:?}{} (node {})",
            acc.data_type(),
            acc.dimensions(),
            if acc.normalized() { " normalized" } else { "" },
            node.index()
        ),
    };
    // Float, or with KHR_mesh_quantization 8- or 16-bit integers.
    let with_format = |name: &str, acc: Option<gltf::Accessor<'a>>| match acc {
        None => Ok(None),
        Some(acc) => match Vec3Format::of(&acc) {
            Some(format) => Ok(Some((acc, format))),
            None => Err(unsupported(name, &acc)),
        },
    };
    let translation = with_format("TRANSLATION", translation)?;
    let scale = with_format("SCALE", scale)?;
    if let Some(acc) = &rotation {
        let ok_type = match acc.data_type() {
            DataType::F32 => true,
            DataType::I8 | DataType::I16 => acc.normalized(),
            _ => false,
        };
        if !ok_type || acc.dimensions() != Dimensions::Vec4 {
            return Err(unsupported("ROTATION", acc));
        }
    }
    // Custom attributes (`_ID` and the like) count the instances too, even alone.
    let mut counts: Vec<usize> = [
        translation.as_ref().map(|(a, _)| a),
        rotation.as_ref(),
        scale.as_ref().map(|(a, _)| a),
    ]
    .into_iter()
    .flatten()
    .map(|a| a.count())
    .collect();
    for name in attributes.keys() {
        if !matches!(name.as_str(), "TRANSLATION" | "ROTATION" | "SCALE")
            && let Some(acc) = accessor(name)?
        {
            counts.push(acc.count());
        }
    }
    let Some(&count) = counts.first() else {
        return Err(bad("its `attributes` are empty".into()));
    };
    if counts.iter().any(|&c| c != count) {
        return Err(bad(format!(
            "its attributes have different counts {counts:?}"
        )));
    }
    Ok(Some(GpuInstancing {
        translation,
        rotation,
        scale,
        count,
    }))
}

/// The instances' matrices (translation · rotation · scale) of a node's [`GpuInstancing`].
fn instance_matrices(
    path: &Path,
    node: usize,
    inst: &GpuInstancing,
    buffers: &[Rc<[u8]>],
) -> Result<Vec<Mat4>, GeomError> {
    use gltf::accessor::DataType;
    let bad = |message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message: format!("node {node}: EXT_mesh_gpu_instancing: {message}"),
    };
    let vec3s = |attribute: &Option<(gltf::Accessor, Vec3Format)>, what: &str, default: Vec3| {
        match attribute {
            Some((acc, format)) => format.read(acc, buffers, what).map_err(&bad),
            None => Ok(vec![default; inst.count]),
        }
    };
    let translations = vec3s(&inst.translation, "TRANSLATION", Vec3::ZERO)?;
    let scales = vec3s(&inst.scale, "SCALE", Vec3::ONE)?;
    let rotations: Vec<glam::Quat> = match &inst.rotation {
        None => vec![glam::Quat::IDENTITY; inst.count],
        Some(acc) => {
            // Float, or normalised bytes or shorts (checked by `gpu_instancing`).
            let ty = acc.data_type();
            let c = |b: &[u8], k: usize| component(ty, ty != DataType::F32, b, k);
            read_accessor(acc, 4 * ty.size(), buffers, "ROTATION")
                .map_err(&bad)?
                .into_iter()
                .map(|b| glam::Quat::from_xyzw(c(b, 0), c(b, 1), c(b, 2), c(b, 3)))
                .collect()
        }
    };
    // Quantised rotations round each component by up to 1/254 (bytes).
    let tolerance = match inst.rotation.as_ref().map(|a| a.data_type()) {
        Some(DataType::I8) => 0.02,
        _ => 0.01,
    };
    translations
        .into_iter()
        .zip(rotations)
        .zip(scales)
        .enumerate()
        .map(|(i, ((t, q), s))| {
            if !(t.is_finite() && q.is_finite() && s.is_finite()) {
                return Err(bad(format!(
                    "instance {i}: translation {t}, rotation {q}, scale {s}: not all finite"
                )));
            }
            let len = q.length();
            if !(len - 1.0).abs().le(&tolerance) {
                return Err(bad(format!(
                    "instance {i}: rotation {q} is not a unit quaternion (length {len})"
                )));
            }
            Ok(Mat4::from_scale_rotation_translation(s, q / len, t))
        })
        .collect()
}
