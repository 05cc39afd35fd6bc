//! glTF and GLB: the document and its extensions checked, then the scene's size, buffers and
//! mesh instances in turn (each in its own room beside this one).

use std::path::Path;

use glam::DMat4;

use super::buffers::read_buffers;
use super::primitive::{Merged, add_gltf_mesh};
use super::scene::{GpuInstancing, check_scene_size, expand_scene, gpu_instancing, node_graph};
use super::{LoadOptions, parse_error};
use crate::GeomError;
use crate::mesh::{LoadReport, Mesh, clean, recentre};

/// Whether a glTF that lists the compression extension `ext` as used (not required) holds its
/// geometry uncompressed too, as the specification asks of such files: with Draco, every
/// compressed primitive's POSITION and index accessors still have a buffer view; with meshopt,
/// no buffer is a `fallback` one (a placeholder without data). Anything else is refused.
fn has_uncompressed_fallback(root: &gltf::json::Root, ext: &str) -> bool {
    if ext == "KHR_draco_mesh_compression" {
        let stored = |i: &gltf::json::Index<gltf::json::Accessor>| {
            root.accessors
                .get(i.value())
                .is_some_and(|a| a.buffer_view.is_some())
        };
        let positions = gltf::json::validation::Checked::Valid(gltf::Semantic::Positions);
        root.meshes
            .iter()
            .flat_map(|m| &m.primitives)
            .filter(|p| {
                p.extensions
                    .as_ref()
                    .is_some_and(|e| e.others.contains_key(ext))
            })
            .all(|p| {
                p.attributes.get(&positions).is_some_and(stored)
                    && p.indices.as_ref().is_none_or(stored)
            })
    } else {
        root.buffers.iter().all(|b| {
            let fallback = b
                .extensions
                .as_ref()
                .and_then(|e| e.others.get(ext)?.get("fallback"));
            fallback != Some(&gltf::json::Value::Bool(true))
        })
    }
}

/// Loads a glTF or GLB file held in `bytes`: the document validated, the scene's size bounded
/// before any buffer is read, the buffers read, every mesh instance of the scene merged.
pub(super) fn load_gltf(
    path: &Path,
    format: &'static str,
    bytes: &[u8],
    dir: Option<&Path>,
    options: &LoadOptions,
) -> Result<(Mesh, LoadReport), GeomError> {
    let glb;
    let (json_bytes, blob): (&[u8], Option<&[u8]>) = if bytes.starts_with(b"glTF") {
        // `gltf` subtracts the 12-byte header from the length the header declares, unchecked.
        let declared = bytes
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        if declared.is_none_or(|length| length < 12) {
            return Err(parse_error(
                path,
                "bad GLB: the header declares a length below its own 12 bytes".into(),
            ));
        }
        glb =
            gltf::Glb::from_slice(bytes).map_err(|e| parse_error(path, format!("bad GLB: {e}")))?;
        (&glb.json, glb.bin.as_deref())
    } else {
        (bytes, None)
    };
    let (doc, fallbacks, lenient) = document(path, json_bytes)?;

    let mut out = Merged {
        report: LoadReport {
            format,
            ..Default::default()
        },
        ..Default::default()
    };
    out.report.warnings.extend(lenient);
    for what in fallbacks {
        out.report.warnings.push(format!(
            "the file also holds its geometry without {what}, which is not supported: that \
             uncompressed copy was read"
        ));
    }

    // The scene's shape first (cheap, no buffer is read): cycles, instance counts, limits.
    let scene = doc.default_scene().or_else(|| doc.scenes().next());
    let graph = match &scene {
        Some(scene) => Some(node_graph(path, &doc, json_bytes, scene)?),
        None => None,
    };
    // Nodes drawn many times by EXT_mesh_gpu_instancing (validated here, read below).
    let accessors: Vec<gltf::Accessor> = doc.accessors().collect();
    let instancing: Vec<Option<GpuInstancing>> = doc
        .nodes()
        .map(|node| gpu_instancing(path, &accessors, &node))
        .collect::<Result<_, _>>()?;
    check_scene_size(path, &doc, graph.as_ref(), &instancing)?;

    let buffers = read_buffers(path, &doc, blob, dir, options)?;

    match (scene, graph) {
        (Some(scene), Some(graph)) => {
            expand_scene(path, &doc, &scene, &graph, &instancing, &buffers, &mut out)?;
        }
        _ => {
            out.report
                .warnings
                .push("no scene: every mesh taken once with the identity transform".into());
            for mesh in doc.meshes() {
                out.report.instances += 1;
                add_gltf_mesh(
                    path,
                    None,
                    &mesh,
                    DMat4::IDENTITY,
                    mesh.weights().unwrap_or_default(),
                    true,
                    &buffers,
                    &mut out,
                )?;
            }
        }
    }
    // A file of points or lines alone: the first one's mode is the error.
    if out.triangles.is_empty()
        && let Some(err) = out.skipped_mode.take()
    {
        return Err(err);
    }
    let vertices = recentre(&out.vertices, &out.triangles, &mut out.report);
    drop(out.vertices);
    let mesh = clean(vertices, out.triangles, &mut out.report)?;
    Ok((mesh, out.report))
}

/// The glTF document in `json_bytes`, after the checks `gltf` leaves out or gets wrong (the
/// extensions, the POSITION accessors), the compression extensions whose uncompressed fallback
/// is read instead, and the warnings of its lenient validation ([`validate`]).
fn document(
    path: &Path,
    json_bytes: &[u8],
) -> Result<(gltf::Document, Vec<&'static str>, Vec<String>), GeomError> {
    let mut root: gltf::json::Root = gltf::json::deserialize::from_slice(json_bytes)
        .map_err(|e| parse_error(path, format!("bad glTF JSON: {e}")))?;
    let fallbacks = compression_fallbacks(path, &root)?;
    refuse_required_extensions(path, &root)?;
    // gltf's validation refuses required extensions it does not implement itself; the ones
    // left are appearance only (never read here) or read here from the JSON.
    root.extensions_required.clear();
    // gltf-json's own validation indexes `accessors` with the POSITION index before checking it
    // (found by the gltf fuzz target: fuzz/regressions/gltf/position-index-out-of-range.gltf).
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (k, prim) in mesh.primitives.iter().enumerate() {
            if let Some(i) = prim.attributes.get(&gltf::json::validation::Checked::Valid(
                gltf::Semantic::Positions,
            )) && i.value() >= root.accessors.len()
            {
                return Err(parse_error(
                    path,
                    format!(
                        "mesh {m} primitive {k}: POSITION accessor {} does not exist ({} accessors)",
                        i.value(),
                        root.accessors.len()
                    ),
                ));
            }
        }
    }
    let lenient = validate(path, &root)?;
    let doc = gltf::Document::from_json_without_validation(root);
    Ok((doc, fallbacks, lenient))
}

/// `gltf`'s validation of `root`, but for what the specification asks of writers and this loader
/// does without, which exporters leave out: a POSITION accessor's `min` and `max` (the points
/// are measured as they are read), and a primitive's POSITION (the specification lets a loader
/// skip such a primitive, as [`add_gltf_mesh`] does). Either failed the whole file. Returns the
/// warnings for what was let through; any other finding is an error.
fn validate(path: &Path, root: &gltf::json::Root) -> Result<Vec<String>, GeomError> {
    use gltf::json::validation::{Error, Validate};
    let mut findings = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |p, e| {
        findings.push((p(), e))
    });
    let lenient = |p: &gltf::json::Path, e: &Error| {
        let p = p.as_str();
        matches!(e, Error::Missing)
            && p.starts_with("meshes[")
            && [
                ".attributes[\"POSITION\"]",
                ".attributes[\"POSITION\"].min",
                ".attributes[\"POSITION\"].max",
            ]
            .iter()
            .any(|end| p.ends_with(end))
    };
    let errors: Vec<_> = findings
        .into_iter()
        .filter(|(p, e)| !lenient(p, e))
        .collect();
    if !errors.is_empty() {
        return Err(parse_error(
            path,
            gltf::Error::Validation(errors).to_string(),
        ));
    }
    // Counted by accessor: one may serve many primitives, and lack both bounds.
    let positions = gltf::json::validation::Checked::Valid(gltf::Semantic::Positions);
    let unbounded: std::collections::BTreeSet<usize> = root
        .meshes
        .iter()
        .flat_map(|m| &m.primitives)
        .filter_map(|p| p.attributes.get(&positions).map(|i| i.value()))
        .filter(|&i| {
            root.accessors
                .get(i)
                .is_some_and(|a| a.min.is_none() || a.max.is_none())
        })
        .collect();
    Ok((!unbounded.is_empty())
        .then(|| {
            format!(
                "{} POSITION accessors without bounds (min, max), which the glTF specification \
                 requires (ignored: the points are measured)",
                unbounded.len()
            )
        })
        .into_iter()
        .collect())
}

/// Compressed geometry we cannot decode. Listed as used but not required, the file must also
/// hold the geometry uncompressed (the glTF specification's fallback): that is read, and the
/// compressions are returned for the report's warnings. Anything else is
/// [`GeomError::Unsupported`].
fn compression_fallbacks(
    path: &Path,
    root: &gltf::json::Root,
) -> Result<Vec<&'static str>, GeomError> {
    let mut fallbacks = Vec::new();
    for ext in root
        .extensions_used
        .iter()
        .chain(root.extensions_required.iter())
    {
        let what = match ext.as_str() {
            "KHR_draco_mesh_compression" => {
                Some("Draco mesh compression (KHR_draco_mesh_compression)")
            }
            "EXT_meshopt_compression" | "KHR_meshopt_compression" => {
                Some("meshopt compression (EXT_meshopt_compression)")
            }
            _ => None,
        };
        if let Some(what) = what {
            let required = root.extensions_required.contains(ext);
            if required || !has_uncompressed_fallback(root, ext) {
                return Err(GeomError::Unsupported {
                    path: path.to_path_buf(),
                    feature: what.to_string(),
                });
            }
            if !fallbacks.contains(&what) {
                fallbacks.push(what);
            }
        }
    }
    Ok(fallbacks)
}

/// A required extension we do not read could change the geometry or is unknown: refuse it by
/// name rather than load something wrong. Extensions that only concern appearance do not touch
/// the triangles; EXT_mesh_gpu_instancing and KHR_mesh_quantization are read.
fn refuse_required_extensions(path: &Path, root: &gltf::json::Root) -> Result<(), GeomError> {
    let understood = |e: &str| {
        [
            "KHR_materials_",
            "KHR_texture_",
            "EXT_texture_",
            "MSFT_texture_",
        ]
        .iter()
        .any(|p| e.starts_with(p))
            || matches!(
                e,
                "KHR_lights_punctual"
                    | "KHR_xmp_json_ld"
                    | "EXT_mesh_gpu_instancing"
                    | "KHR_mesh_quantization"
            )
    };
    match root.extensions_required.iter().find(|e| !understood(e)) {
        Some(ext) => Err(GeomError::Unsupported {
            path: path.to_path_buf(),
            feature: format!("the required glTF extension {ext}"),
        }),
        None => Ok(()),
    }
}
