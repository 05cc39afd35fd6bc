//! Mesh loading: Wavefront OBJ (through `tobj`) and glTF / GLB (through `gltf`).

use std::cell::RefCell;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use base64::Engine as _;
use glam::{Mat4, Vec3};

use crate::GeomError;
use crate::mesh::{LoadReport, Mesh, clean};

/// Loads a triangle mesh, dispatching on the file extension (`obj`, `gltf`, `glb`, case-insensitive).
///
/// All objects (OBJ) or all mesh primitives of the default scene, or else the first scene, with node
/// transforms applied (glTF) are merged into one mesh. Polygons are fan-triangulated; glTF strips and
/// fans are converted. The result is cleaned as described in [`Mesh::from_raw`]; what was dropped or
/// converted is counted in the [`LoadReport`].
///
/// Material libraries and textures are never read, so a missing or broken `.mtl` or image never stops
/// the geometry from loading (a missing `.mtl` is noted in [`LoadReport::warnings`]).
///
/// # Errors
/// [`GeomError::UnknownExtension`], [`GeomError::Io`] (missing or unreadable file),
/// [`GeomError::Parse`], [`GeomError::NoTriangles`], [`GeomError::NonFiniteVertex`],
/// [`GeomError::IndexOutOfRange`], [`GeomError::UnsupportedPrimitiveMode`] (glTF points and lines),
/// [`GeomError::Unsupported`] (Draco, meshopt, quantised positions, and any required glTF extension other
/// than appearance-only ones such as `KHR_materials_*`) and [`GeomError::MissingBuffer`].
pub fn load_mesh(path: impl AsRef<Path>) -> Result<(Mesh, LoadReport), GeomError> {
    let path = path.as_ref();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    match ext.as_str() {
        "obj" => load_obj(path),
        "gltf" => load_gltf(path, "gltf"),
        "glb" => load_gltf(path, "glb"),
        _ => Err(GeomError::UnknownExtension {
            path: path.to_path_buf(),
            extension: ext,
        }),
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>, GeomError> {
    std::fs::read(path).map_err(|source| GeomError::Io {
        path: path.to_path_buf(),
        source,
    })
}

// ---------------------------------------------------------------------------------------------------
// OBJ

fn load_obj(path: &Path) -> Result<(Mesh, LoadReport), GeomError> {
    let bytes = read_file(path)?;
    let mut report = LoadReport {
        format: "obj",
        ..Default::default()
    };
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are never needed: the loader only records which libraries were named.
    let mtllibs: RefCell<Vec<PathBuf>> = RefCell::new(Vec::new());
    let result = tobj::load_obj_buf(&mut Cursor::new(&bytes), &options, |p| {
        mtllibs.borrow_mut().push(p.to_path_buf());
        Ok(Default::default())
    });
    let models = match result {
        Ok((models, _materials)) => models,
        Err(err) => return Err(obj_error(path, &bytes, err)),
    };
    let dir = path.parent().unwrap_or(Path::new("."));
    for lib in mtllibs.into_inner() {
        if !dir.join(&lib).is_file() {
            report.warnings.push(format!(
                "material library {} not found (ignored: materials are not needed)",
                lib.display()
            ));
        }
    }

    let mut vertices: Vec<Vec3> = Vec::new();
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    for model in &models {
        let m = &model.mesh;
        let base = vertices.len() as u64;
        vertices.extend(
            m.positions
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2])),
        );
        let idx = |i: u32| -> Result<u32, GeomError> {
            let g = base + i as u64;
            u32::try_from(g).map_err(|_| GeomError::Parse {
                path: path.to_path_buf(),
                line: None,
                message: "more than 2^32 vertices".into(),
            })
        };
        if m.face_arities.is_empty() {
            for f in m.indices.chunks_exact(3) {
                triangles.push([idx(f[0])?, idx(f[1])?, idx(f[2])?]);
            }
        } else {
            let mut start = 0usize;
            for &arity in &m.face_arities {
                let arity = arity as usize;
                let Some(face) = m.indices.get(start..start + arity) else {
                    break;
                };
                start += arity;
                if arity < 3 {
                    continue;
                }
                if arity > 3 {
                    report.polygons_triangulated += 1;
                }
                for k in 1..arity - 1 {
                    triangles.push([idx(face[0])?, idx(face[k])?, idx(face[k + 1])?]);
                }
            }
        }
    }
    let mesh = clean(vertices, triangles, &mut report)?;
    Ok((mesh, report))
}

/// Turns a `tobj` error into a typed error, finding the offending line by re-scanning the text.
fn obj_error(path: &Path, bytes: &[u8], err: tobj::LoadError) -> GeomError {
    let text = String::from_utf8_lossy(bytes);
    let found = scan_obj(&text);
    if err == tobj::LoadError::FaceVertexOutOfBounds {
        if let Some(ScanIssue::IndexOutOfRange {
            face,
            index,
            vertex_count,
            ..
        }) = found
        {
            return GeomError::IndexOutOfRange {
                triangle: face,
                index: index.unsigned_abs(),
                vertex_count,
            };
        }
    }
    let (line, detail) = match found {
        Some(ScanIssue::Bad { line, text }) => (Some(line), format!(": {text:?}")),
        Some(ScanIssue::IndexOutOfRange { line, index, .. }) => {
            (Some(line), format!(": index {index} out of range"))
        }
        None => (None, String::new()),
    };
    GeomError::Parse {
        path: path.to_path_buf(),
        line,
        message: format!("{err}{detail}"),
    }
}

enum ScanIssue {
    Bad {
        line: usize,
        text: String,
    },
    IndexOutOfRange {
        line: usize,
        face: usize,
        index: i64,
        vertex_count: usize,
    },
}

/// A light re-scan of an OBJ file that finds the first line `tobj` would have rejected.
fn scan_obj(text: &str) -> Option<ScanIssue> {
    let mut nv = 0usize;
    let mut nvt = 0usize;
    let mut nvn = 0usize;
    let mut faces = 0usize;
    let floats_ok = |rest: &[&str], min: usize, max: usize| {
        rest.len() >= min && rest.len() <= max && rest.iter().all(|t| t.parse::<f32>().is_ok())
    };
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let l = raw.split('#').next().unwrap_or("").trim();
        let mut tok = l.split_whitespace();
        let Some(head) = tok.next() else { continue };
        let rest: Vec<&str> = tok.collect();
        let bad = || {
            Some(ScanIssue::Bad {
                line,
                text: raw.chars().take(80).collect(),
            })
        };
        match head {
            "v" => {
                if !floats_ok(&rest, 3, 7) {
                    return bad();
                }
                nv += 1;
            }
            "vt" => {
                if !floats_ok(&rest, 1, 3) {
                    return bad();
                }
                nvt += 1;
            }
            "vn" => {
                if !floats_ok(&rest, 3, 3) {
                    return bad();
                }
                nvn += 1;
            }
            "f" => {
                if rest.len() < 3 {
                    // tobj accepts these only with ignore_points / ignore_lines, which we set.
                    continue;
                }
                for corner in &rest {
                    let parts: Vec<&str> = corner.split('/').collect();
                    if parts.is_empty() || parts.len() > 3 {
                        return bad();
                    }
                    for (k, p) in parts.iter().enumerate() {
                        if k > 0 && p.is_empty() {
                            continue;
                        }
                        let Ok(v) = p.parse::<i64>() else {
                            return bad();
                        };
                        let count = [nv, nvt, nvn][k];
                        let ok = v != 0 && v.unsigned_abs() as usize <= count;
                        if !ok {
                            if k == 0 {
                                return Some(ScanIssue::IndexOutOfRange {
                                    line,
                                    face: faces,
                                    index: v,
                                    vertex_count: nv,
                                });
                            }
                            return bad();
                        }
                    }
                }
                faces += 1;
            }
            _ => {}
        }
    }
    None
}

// ---------------------------------------------------------------------------------------------------
// glTF / GLB

const MAX_NODE_DEPTH: usize = 256;

fn load_gltf(path: &Path, format: &'static str) -> Result<(Mesh, LoadReport), GeomError> {
    let bytes = read_file(path)?;
    let parse_err = |message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message,
    };
    let (json_bytes, blob): (Vec<u8>, Option<Vec<u8>>) = if bytes.starts_with(b"glTF") {
        let glb = gltf::Glb::from_slice(&bytes).map_err(|e| parse_err(format!("bad GLB: {e}")))?;
        (glb.json.into_owned(), glb.bin.map(|b| b.into_owned()))
    } else {
        (bytes, None)
    };
    let mut root: gltf::json::Root = gltf::json::deserialize::from_slice(&json_bytes)
        .map_err(|e| parse_err(format!("bad glTF JSON: {e}")))?;
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
            return Err(GeomError::Unsupported {
                path: path.to_path_buf(),
                feature: what.to_string(),
            });
        }
    }
    // A required extension we do not read could change the geometry (quantised attributes,
    // GPU instancing) or is unknown: refuse it by name rather than load something wrong.
    // Extensions that only concern appearance do not touch the triangles.
    let appearance_only = |e: &str| {
        [
            "KHR_materials_",
            "KHR_texture_",
            "EXT_texture_",
            "MSFT_texture_",
        ]
        .iter()
        .any(|p| e.starts_with(p))
            || matches!(e, "KHR_lights_punctual" | "KHR_xmp_json_ld")
    };
    if let Some(ext) = root
        .extensions_required
        .iter()
        .find(|e| !appearance_only(e))
    {
        return Err(GeomError::Unsupported {
            path: path.to_path_buf(),
            feature: format!("the required glTF extension {ext}"),
        });
    }
    // gltf's validation refuses required extensions it does not implement itself; the ones
    // left are appearance only and are never read here.
    root.extensions_required.clear();
    let doc =
        gltf::Document::from_json(root).map_err(|e| parse_err(format!("invalid glTF: {e}")))?;

    let mut report = LoadReport {
        format,
        ..Default::default()
    };

    // Buffers: GLB blob, data: URIs, or files relative to the .gltf. Images are never touched.
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut buffers: Vec<Vec<u8>> = Vec::new();
    for buffer in doc.buffers() {
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => blob.clone().ok_or_else(|| {
                parse_err("buffer refers to a GLB BIN chunk that is missing".into())
            })?,
            gltf::buffer::Source::Uri(uri) => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let Some((_, payload)) = rest.split_once(";base64,") else {
                        return Err(parse_err(format!(
                            "buffer {}: only base64 data: URIs are supported",
                            buffer.index()
                        )));
                    };
                    base64::engine::general_purpose::STANDARD
                        .decode(payload.trim())
                        .map_err(|e| {
                            parse_err(format!("buffer {}: bad base64: {e}", buffer.index()))
                        })?
                } else {
                    let file = dir.join(percent_decode(uri));
                    std::fs::read(&file).map_err(|source| GeomError::MissingBuffer {
                        gltf: path.to_path_buf(),
                        buffer: file.clone(),
                        source,
                    })?
                }
            }
        };
        if data.len() < buffer.length() {
            return Err(parse_err(format!(
                "buffer {} has {} bytes but declares {}",
                buffer.index(),
                data.len(),
                buffer.length()
            )));
        }
        buffers.push(data);
    }

    let mut vertices: Vec<Vec3> = Vec::new();
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    let scene = doc.default_scene().or_else(|| doc.scenes().next());
    match scene {
        Some(scene) => {
            let mut stack: Vec<(gltf::Node, Mat4, usize)> =
                scene.nodes().map(|n| (n, Mat4::IDENTITY, 0)).collect();
            stack.reverse();
            while let Some((node, parent, depth)) = stack.pop() {
                if depth > MAX_NODE_DEPTH {
                    return Err(parse_err(format!(
                        "node hierarchy deeper than {MAX_NODE_DEPTH} (cyclic?)"
                    )));
                }
                let local = Mat4::from_cols_array_2d(&node.transform().matrix());
                let world = parent * local;
                if let Some(mesh) = node.mesh() {
                    report.instances += 1;
                    add_gltf_mesh(
                        path,
                        &mesh,
                        world,
                        &buffers,
                        &mut vertices,
                        &mut triangles,
                        &mut report,
                    )?;
                }
                for child in node.children() {
                    stack.push((child, world, depth + 1));
                }
            }
        }
        None => {
            report
                .warnings
                .push("no scene: every mesh taken once with the identity transform".into());
            for mesh in doc.meshes() {
                report.instances += 1;
                add_gltf_mesh(
                    path,
                    &mesh,
                    Mat4::IDENTITY,
                    &buffers,
                    &mut vertices,
                    &mut triangles,
                    &mut report,
                )?;
            }
        }
    }
    let mesh = clean(vertices, triangles, &mut report)?;
    Ok((mesh, report))
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            let hex = std::str::from_utf8(&b[i + 1..i + 3]).unwrap_or("");
            if let Ok(v) = u8::from_str_radix(hex, 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[allow(clippy::too_many_arguments)]
fn add_gltf_mesh(
    path: &Path,
    mesh: &gltf::Mesh,
    world: Mat4,
    buffers: &[Vec<u8>],
    vertices: &mut Vec<Vec3>,
    triangles: &mut Vec<[u32; 3]>,
    report: &mut LoadReport,
) -> Result<(), GeomError> {
    use gltf::mesh::Mode;
    let flip = world.determinant() < 0.0;
    for prim in mesh.primitives() {
        let mode = prim.mode();
        let mode_name = match mode {
            Mode::Points => Some("POINTS"),
            Mode::Lines => Some("LINES"),
            Mode::LineLoop => Some("LINE_LOOP"),
            Mode::LineStrip => Some("LINE_STRIP"),
            _ => None,
        };
        if let Some(mode) = mode_name {
            return Err(GeomError::UnsupportedPrimitiveMode {
                path: path.to_path_buf(),
                mesh: mesh.index(),
                primitive: prim.index(),
                mode,
            });
        }
        let Some(pos_acc) = prim.get(&gltf::Semantic::Positions) else {
            report.warnings.push(format!(
                "mesh {} primitive {} has no POSITION attribute (skipped)",
                mesh.index(),
                prim.index()
            ));
            continue;
        };
        if pos_acc.data_type() != gltf::accessor::DataType::F32
            || pos_acc.dimensions() != gltf::accessor::Dimensions::Vec3
        {
            return Err(GeomError::Unsupported {
                path: path.to_path_buf(),
                feature: format!(
                    "POSITION accessor of type {:?} {:?} (only float32 VEC3; quantised positions are not supported)",
                    pos_acc.data_type(),
                    pos_acc.dimensions()
                ),
            });
        }
        if pos_acc.count() == 0 {
            continue;
        }
        let reader = prim.reader(|b| buffers.get(b.index()).map(|v| v.as_slice()));
        let Some(positions) = reader.read_positions() else {
            return Err(GeomError::Parse {
                path: path.to_path_buf(),
                line: None,
                message: format!(
                    "mesh {} primitive {}: POSITION data lies outside its buffer",
                    mesh.index(),
                    prim.index()
                ),
            });
        };
        let base = vertices.len();
        vertices.extend(positions.map(|p| world.transform_point3(Vec3::from_array(p))));
        let n = vertices.len() - base;
        if n != pos_acc.count() {
            return Err(GeomError::Parse {
                path: path.to_path_buf(),
                line: None,
                message: format!(
                    "mesh {} primitive {}: POSITION data truncated",
                    mesh.index(),
                    prim.index()
                ),
            });
        }
        let indices: Vec<u32> = match prim.indices() {
            Some(acc) if acc.count() == 0 => Vec::new(),
            Some(_) => match reader.read_indices() {
                Some(r) => r.into_u32().collect(),
                None => {
                    return Err(GeomError::Parse {
                        path: path.to_path_buf(),
                        line: None,
                        message: format!(
                            "mesh {} primitive {}: index data lies outside its buffer",
                            mesh.index(),
                            prim.index()
                        ),
                    });
                }
            },
            None => (0..n as u32).collect(),
        };
        let local: Vec<[u32; 3]> = match mode {
            Mode::TriangleStrip => {
                report.strips_fans_converted += 1;
                (0..indices.len().saturating_sub(2))
                    .map(|i| {
                        if i % 2 == 0 {
                            [indices[i], indices[i + 1], indices[i + 2]]
                        } else {
                            [indices[i + 1], indices[i], indices[i + 2]]
                        }
                    })
                    .collect()
            }
            Mode::TriangleFan => {
                report.strips_fans_converted += 1;
                (0..indices.len().saturating_sub(2))
                    .map(|i| [indices[i + 1], indices[i + 2], indices[0]])
                    .collect()
            }
            _ => indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
        };
        for (k, t) in local.iter().enumerate() {
            for &i in t {
                if i as usize >= n {
                    return Err(GeomError::IndexOutOfRange {
                        triangle: triangles.len() + k,
                        index: i as u64,
                        vertex_count: n,
                    });
                }
            }
        }
        triangles.extend(local.into_iter().map(|t| {
            let t = t.map(|i| i + base as u32);
            if flip { [t[0], t[2], t[1]] } else { t }
        }));
    }
    Ok(())
}
