//! Mesh loading: Wavefront OBJ (through `tobj`) and glTF / GLB (own validation and accessor reading,
//! `gltf` for the JSON document and the GLB container).
//!
//! Everything here treats the file as hostile: only regular files of at most [`MAX_FILE_BYTES`] are
//! read, glTF documents are validated (accessor types, strides, offsets, counts, sparse indices, the
//! node graph) before any data is read, external buffer URIs stay inside the asset's folder, the
//! instanced size of a scene is bounded, and a panic in a dependency becomes [`GeomError::ReaderPanic`].

use std::cell::RefCell;
use std::collections::HashMap;
use std::io::{Cursor, Read};
use std::path::{Component, Path, PathBuf};
use std::rc::Rc;

use base64::Engine as _;
use glam::{Mat4, Vec3};
use rayon::prelude::*;

use crate::GeomError;
use crate::mesh::{LoadReport, Mesh, clean};

/// Largest file read whole as a mesh, a glTF buffer or a `.npy` point set: 2 GiB. Checked from the
/// file's metadata before reading (and enforced while reading, in case it grows).
pub const MAX_FILE_BYTES: u64 = 2 << 30;
/// Most triangles a glTF scene may produce with every mesh instance expanded (about 1 GB of
/// loader memory at the limit).
pub const MAX_INSTANCED_TRIANGLES: u64 = 20_000_000;
/// Most vertices a glTF scene may produce with every mesh instance expanded.
pub const MAX_INSTANCED_VERTICES: u64 = 20_000_000;
/// Most mesh instances (node-to-mesh references, counted through shared nodes) in a glTF scene.
pub const MAX_INSTANCES: u64 = 1_000_000;

/// Options for [`load_mesh_with`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct LoadOptions {
    /// Follow glTF buffer URIs that are absolute paths or lead out of the asset's folder (after
    /// percent-decoding, `..` and symbolic links). Off by default: a service that loads uploaded
    /// files must not let them read (or probe) other files. URI schemes other than `data:` are
    /// refused either way.
    pub allow_external_uris: bool,
}

impl LoadOptions {
    /// The defaults, with [`LoadOptions::allow_external_uris`] set to `allow`.
    pub fn with_external_uris(allow: bool) -> Self {
        LoadOptions {
            allow_external_uris: allow,
        }
    }
}

/// Loads a triangle mesh, dispatching on the file extension (`obj`, `gltf`, `glb`, case-insensitive),
/// with the default [`LoadOptions`].
///
/// All objects (OBJ) or all mesh primitives of the default scene, or else the first scene, with node
/// transforms applied (glTF) are merged into one mesh. Polygons are fan-triangulated; glTF strips and
/// fans are converted. The result is cleaned as described in [`Mesh::from_raw`]; what was dropped or
/// converted is counted in the [`LoadReport`].
///
/// Material libraries and textures are never read, so a missing or broken `.mtl` or image never stops
/// the geometry from loading (a missing `.mtl` is noted in [`LoadReport::warnings`]). OBJ text may
/// start with a UTF-8 byte-order mark, have trailing `#` comments, and contain names that are not
/// UTF-8 (decoded lossily; geometry never depends on names). glTF meshes are taken in their default
/// pose: morph targets with their default weights (the node's, else the mesh's), and every instance
/// of an `EXT_mesh_gpu_instancing` node. Quantised positions (`KHR_mesh_quantization`: 8- or
/// 16-bit integers, normalised or not, which node transforms scale back) are read.
///
/// # Errors
/// [`GeomError::UnknownExtension`], [`GeomError::Io`] (missing or unreadable file),
/// [`GeomError::NotARegularFile`], [`GeomError::FileTooLarge`],
/// [`GeomError::Parse`] (also every failed glTF validation), [`GeomError::NoTriangles`],
/// [`GeomError::NonFiniteVertex`], [`GeomError::ObjIndexOutOfRange`],
/// [`GeomError::GltfIndexOutOfRange`], [`GeomError::NodeTransform`],
/// [`GeomError::UnsupportedPrimitiveMode`] (glTF points and lines), [`GeomError::Unsupported`]
/// (Draco and meshopt compression without an uncompressed fallback, positions of other types
/// than float32 or 8- or 16-bit integers, and any required glTF extension other than
/// appearance-only ones such as `KHR_materials_*`,
/// `EXT_mesh_gpu_instancing` and `KHR_mesh_quantization`), [`GeomError::MissingBuffer`],
/// [`GeomError::BufferNotARegularFile`], [`GeomError::UriRefused`],
/// [`GeomError::SceneTooLarge`] and [`GeomError::ReaderPanic`].
pub fn load_mesh(path: impl AsRef<Path>) -> Result<(Mesh, LoadReport), GeomError> {
    load_mesh_with(path, &LoadOptions::default())
}

/// [`load_mesh`] with explicit [`LoadOptions`].
pub fn load_mesh_with(
    path: impl AsRef<Path>,
    options: &LoadOptions,
) -> Result<(Mesh, LoadReport), GeomError> {
    let path = path.as_ref();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    let format = match ext.as_str() {
        "obj" => "obj",
        "gltf" => "gltf",
        "glb" => "glb",
        _ => {
            return Err(GeomError::UnknownExtension {
                path: path.to_path_buf(),
                extension: ext,
            });
        }
    };
    let bytes = read_input_file(path)?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    guarded(path, || parse(path, format, &bytes, Some(dir), options))
}

/// Parses a mesh held in memory: `format` is `"obj"`, `"gltf"` or `"glb"`; `path` is used only in
/// messages. glTF buffers must be in the GLB container or `data:` URIs (there is no folder to resolve
/// file URIs against). This is what the fuzz targets call.
///
/// # Errors
/// As [`load_mesh`]; an unknown `format` is [`GeomError::UnknownExtension`].
pub fn parse_mesh(
    bytes: &[u8],
    format: &str,
    path: &Path,
) -> Result<(Mesh, LoadReport), GeomError> {
    let format = match format {
        "obj" => "obj",
        "gltf" => "gltf",
        "glb" => "glb",
        other => {
            return Err(GeomError::UnknownExtension {
                path: path.to_path_buf(),
                extension: other.to_string(),
            });
        }
    };
    guarded(path, || {
        parse(path, format, bytes, None, &LoadOptions::default())
    })
}

fn parse(
    path: &Path,
    format: &'static str,
    bytes: &[u8],
    dir: Option<&Path>,
    options: &LoadOptions,
) -> Result<(Mesh, LoadReport), GeomError> {
    if format == "obj" {
        load_obj(path, bytes, dir)
    } else {
        load_gltf(path, format, bytes, dir, options)
    }
}

/// Runs a loader, turning a panic (a bug, ours or a dependency's) into [`GeomError::ReaderPanic`].
/// The last line of defence only: inputs are validated before the readers run.
fn guarded<T>(path: &Path, f: impl FnOnce() -> Result<T, GeomError>) -> Result<T, GeomError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(GeomError::ReaderPanic {
                path: path.to_path_buf(),
                message,
            })
        }
    }
}

fn file_kind(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "FIFO";
        }
        if t.is_char_device() {
            return "character device";
        }
        if t.is_block_device() {
            return "block device";
        }
        if t.is_socket() {
            return "socket";
        }
    }
    if t.is_dir() {
        "directory"
    } else {
        "special file"
    }
}

/// Reads a whole input file (mesh, glTF buffer, `.npy`): only a regular file (symbolic links are
/// followed; FIFOs and devices are refused before they are opened, so nothing blocks), and only up
/// to [`MAX_FILE_BYTES`], checked before reading.
///
/// # Errors
/// [`GeomError::Io`], [`GeomError::NotARegularFile`], [`GeomError::FileTooLarge`].
pub fn read_input_file(path: &Path) -> Result<Vec<u8>, GeomError> {
    read_file_within(path, MAX_FILE_BYTES)
}

/// [`read_input_file`] with another size limit (model files use it through
/// [`crate::io::read_regular_file`]).
pub(crate) fn read_file_within(path: &Path, max_bytes: u64) -> Result<Vec<u8>, GeomError> {
    let io = |source| GeomError::Io {
        path: path.to_path_buf(),
        source,
    };
    let check = |meta: &std::fs::Metadata| {
        if !meta.is_file() {
            return Err(GeomError::NotARegularFile {
                path: path.to_path_buf(),
                kind: file_kind(&meta.file_type()),
            });
        }
        if meta.len() > max_bytes {
            return Err(GeomError::FileTooLarge {
                path: path.to_path_buf(),
                size: meta.len(),
                limit: max_bytes,
            });
        }
        Ok(meta.len())
    };
    // stat before open: opening a FIFO for reading blocks until a writer appears.
    check(&std::fs::metadata(path).map_err(io)?)?;
    let file = std::fs::File::open(path).map_err(io)?;
    // And again on the open handle, in case the path was swapped in between.
    let len = check(&file.metadata().map_err(io)?)?;
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(max_bytes + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > max_bytes {
        return Err(GeomError::FileTooLarge {
            path: path.to_path_buf(),
            size: bytes.len() as u64,
            limit: max_bytes,
        });
    }
    Ok(bytes)
}

// ---------------------------------------------------------------------------------------------------
// OBJ

/// OBJ text as `tobj` can take it, keeping only what the geometry needs:
/// - no byte-order mark, and lossy UTF-8 (names in Latin-1 and the like only lose their odd
///   characters; numbers are ASCII);
/// - `#` comments cut off every line (`tobj` only skips whole-line comments and reads a trailing
///   one as vertex colours);
/// - no polyline (`l`) or point (`p`) elements, which `tobj` would read as faces once they have
///   three or more vertices, and no faces of fewer than three vertices;
/// - no texture coordinates, normals or material uses (`vt`, `vn`, `vp`, `usemtl`), and faces
///   reduced to their vertex indices: `tobj` refuses valid files over them (`vt 0.5`, a tab
///   after `usemtl`, a bare `usemtl`, a texture index out of range) although no distance
///   depends on them;
/// - no vertex colours: `v x y z r g b` and `v x y z r g b a` (as exporters write them; `tobj`
///   refuses the second) become `v x y z`. `v x y z w` stays, for `tobj` to divide by w; any
///   other count is left for `tobj` to refuse and [`scan_obj`] to place.
///
/// Removed lines stay as empty lines, so line numbers in errors still match the file.
fn obj_text(bytes: &[u8]) -> (String, ObjCounts) {
    obj_text_in_chunks(bytes, OBJ_CHUNK)
}

/// Bytes of OBJ text per task of [`obj_text`], which rewrites chunks of whole lines in parallel
/// (on a 52 MB file the rewrite took 0.4-0.7 s on one core).
const OBJ_CHUNK: usize = 1 << 20;

/// [`obj_text`] in chunks of about `chunk` bytes, each cut at a line end.
fn obj_text_in_chunks(bytes: &[u8], chunk: usize) -> (String, ObjCounts) {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let mut text = String::from_utf8_lossy(bytes);
    // Classic Mac OS ended lines with a lone CR, which tobj reads as one line of garbage.
    if text.contains('\r') {
        text = text.replace("\r\n", "\n").replace('\r', "\n").into();
    }
    let mut pieces = Vec::new();
    let mut start = 0;
    while start < text.len() {
        let from = start.saturating_add(chunk.max(1)).min(text.len());
        // A line end is a char boundary: '\n' is never part of a longer UTF-8 sequence.
        let end = text.as_bytes()[from..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(text.len(), |i| from + i + 1);
        pieces.push(&text[start..end]);
        start = end;
    }
    let parts: Vec<(String, ObjCounts, usize)> =
        pieces.par_iter().map(|piece| obj_lines(piece)).collect();
    let mut out = String::with_capacity(parts.iter().map(|p| p.0.len()).sum());
    let mut counts = ObjCounts::default();
    let mut lines_before = 0;
    for (piece, c, lines) in parts {
        out.push_str(&piece);
        counts.vertices += c.vertices;
        counts.triangles += c.triangles;
        counts.skipped_elements += c.skipped_elements;
        counts.short_faces += c.short_faces;
        if counts.bad_w.is_none() {
            counts.bad_w = c.bad_w.map(|(line, text)| (lines_before + line, text));
        }
        lines_before += lines;
    }
    (out, counts)
}

/// [`obj_text`]'s rewrite of whole lines, numbered from 1, and how many there were.
fn obj_lines(text: &str) -> (String, ObjCounts, usize) {
    let mut out = String::with_capacity(text.len());
    let mut counts = ObjCounts::default();
    let mut lines = 0;
    for (i, line) in text.split_inclusive('\n').enumerate() {
        let line_no = i + 1;
        lines = line_no;
        let content = match line.find('#') {
            Some(i) => &line[..i],
            None => line.strip_suffix('\n').unwrap_or(line),
        };
        let mut tokens = content.split_whitespace();
        match tokens.next() {
            Some("l" | "p") => counts.skipped_elements += 1,
            Some("v") => {
                counts.vertices += 1;
                let numbers: Vec<&str> = tokens.collect();
                // tobj divides by w: an infinite one would silently put the vertex at 0.
                if numbers.len() == 4
                    && counts.bad_w.is_none()
                    && numbers[3]
                        .parse::<f32>()
                        .is_ok_and(|w| !w.is_finite() || w == 0.0)
                {
                    counts.bad_w = Some((line_no, content.trim().chars().take(80).collect()));
                }
                if matches!(numbers.len(), 6 | 7) {
                    out.push('v');
                    for x in &numbers[..3] {
                        out.push(' ');
                        out.push_str(x);
                    }
                } else {
                    out.push_str(content);
                }
            }
            Some("f") => {
                // A face of one or two vertices encloses nothing either; tobj would keep its
                // indices, and a list of triangles read three at a time would shift.
                let corners: Vec<&str> = tokens.collect();
                if corners.len() < 3 {
                    counts.short_faces += 1;
                } else if corners.iter().any(|c| c.starts_with('/')) {
                    // A corner without its vertex index (`/1`): left as it is, for tobj to
                    // refuse and `scan_obj` to place, rather than dropped with the vertex.
                    out.push_str(content);
                } else {
                    counts.triangles += corners.len() as u64 - 2;
                    out.push('f');
                    for c in corners {
                        out.push(' ');
                        out.push_str(c.split('/').next().unwrap_or(c));
                    }
                }
            }
            Some("vt" | "vn" | "vp" | "usemtl") => {}
            _ => out.push_str(content),
        }
        if line.ends_with('\n') {
            out.push('\n');
        }
    }
    (out, counts, lines)
}

/// [`GeomError::SceneTooLarge`] for the first `(what, count, limit)` whose count passes its limit.
fn check_limits<const N: usize>(
    path: &Path,
    counts: [(&'static str, u64, u64); N],
) -> Result<(), GeomError> {
    match counts.into_iter().find(|&(_, count, limit)| count > limit) {
        Some((what, count, limit)) => Err(GeomError::SceneTooLarge {
            path: path.to_path_buf(),
            what,
            count,
            limit,
        }),
        None => Ok(()),
    }
}

/// What [`obj_text`] saw: the vertices and (fan-triangulated) triangles that `tobj` will build,
/// counted before it builds them, and the elements it removed.
#[derive(Debug, Default)]
struct ObjCounts {
    vertices: u64,
    triangles: u64,
    skipped_elements: usize,
    short_faces: usize,
    /// The first vertex line whose w is infinite, NaN or 0, and its text.
    bad_w: Option<(usize, String)>,
}

fn load_obj(
    path: &Path,
    bytes: &[u8],
    dir: Option<&Path>,
) -> Result<(Mesh, LoadReport), GeomError> {
    let (text, counts) = obj_text(bytes);
    if let Some((line, text)) = counts.bad_w {
        return Err(GeomError::Parse {
            path: path.to_path_buf(),
            line: Some(line),
            message: format!("a vertex's w must be a finite number other than 0: {text:?}"),
        });
    }
    let mut report = LoadReport {
        format: "obj",
        ..Default::default()
    };
    // The limits glTF scenes have: tobj's index lists cost about 16 bytes per file byte.
    check_limits(
        path,
        [
            ("triangles", counts.triangles, MAX_INSTANCED_TRIANGLES),
            ("vertices", counts.vertices, MAX_INSTANCED_VERTICES),
        ],
    )?;
    if counts.skipped_elements > 0 {
        report.warnings.push(format!(
            "{} polyline (l) and point (p) elements ignored: they enclose nothing",
            counts.skipped_elements
        ));
    }
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are never needed: the loader only records which libraries were named.
    let mtllibs: RefCell<Vec<PathBuf>> = RefCell::new(Vec::new());
    let result = tobj::load_obj_buf(&mut Cursor::new(text.as_bytes()), &options, |p| {
        mtllibs.borrow_mut().push(p.to_path_buf());
        Ok(Default::default())
    });
    let models = match result {
        Ok((models, _materials)) => models,
        Err(err) => return Err(obj_error(path, &text, err)),
    };
    for lib in mtllibs.into_inner() {
        if dir.is_some_and(|d| !d.join(&lib).is_file()) {
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
    if counts.short_faces > 0 {
        report.warnings.push(format!(
            "{} faces with fewer than three vertices ignored",
            counts.short_faces
        ));
    }
    let mesh = clean(vertices, triangles, &mut report)?;
    Ok((mesh, report))
}

/// Turns a `tobj` error into a typed error, finding the offending line by re-scanning the text.
fn obj_error(path: &Path, text: &str, err: tobj::LoadError) -> GeomError {
    // Only an index error is looked for among the indices: a face may use vertices defined
    // after it (tobj checks them when the object ends), so another error lies elsewhere.
    let found = scan_obj(text, err == tobj::LoadError::FaceVertexOutOfBounds);
    if err == tobj::LoadError::FaceVertexOutOfBounds {
        if let Some(ScanIssue::IndexOutOfRange {
            line,
            face,
            index,
            vertex_count,
        }) = found
        {
            return GeomError::ObjIndexOutOfRange {
                path: path.to_path_buf(),
                line,
                face,
                index,
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

/// A light re-scan of an OBJ file that finds the first line `tobj` would have rejected. With
/// `check_ranges`, vertex indices are checked as tobj does: a relative (negative) one against
/// the vertices before it, a positive one against those defined when its object ends (the next
/// `o` or `g`, or the end of the file).
fn scan_obj(text: &str, check_ranges: bool) -> Option<ScanIssue> {
    // It reads the text `obj_text` gave tobj: no texture coordinates or normals are left.
    let mut nv = 0usize;
    let mut faces = 0usize;
    // The largest positive vertex index of the object so far: (index, line, face).
    let mut pending: Option<(i64, usize, usize)> = None;
    let out_of_range = |p: Option<(i64, usize, usize)>, nv: usize| {
        p.filter(|&(v, _, _)| v as u64 > nv as u64)
            .map(|(index, line, face)| ScanIssue::IndexOutOfRange {
                line,
                face,
                index,
                vertex_count: nv,
            })
    };
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
                // As `obj_text` passes them on: x y z, x y z w (w ≠ 0), or x y z and three or
                // four colour components, which it drops.
                let ok = match rest.len() {
                    3 | 6 | 7 => floats_ok(&rest[..3], 3, 3),
                    4 => floats_ok(&rest, 4, 4) && rest[3].parse::<f32>().is_ok_and(|w| w != 0.0),
                    _ => false,
                };
                if !ok {
                    return bad();
                }
                nv += 1;
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
                    // Texture and normal indices never reach tobj (`obj_text`).
                    if let Some(p) = parts.first() {
                        let Ok(v) = p.parse::<i64>() else {
                            return bad();
                        };
                        if v == 0 {
                            return bad();
                        }
                        if !check_ranges {
                            continue;
                        }
                        if v > 0 {
                            if pending.is_none_or(|(p, _, _)| v > p) {
                                pending = Some((v, line, faces));
                            }
                        } else if v.unsigned_abs() > nv as u64 {
                            return Some(ScanIssue::IndexOutOfRange {
                                line,
                                face: faces,
                                index: v,
                                vertex_count: nv,
                            });
                        }
                    }
                }
                faces += 1;
            }
            "o" | "g" => {
                if let Some(issue) = out_of_range(pending.take(), nv) {
                    return Some(issue);
                }
            }
            _ => {}
        }
    }
    out_of_range(pending, nv)
}

// ---------------------------------------------------------------------------------------------------
// glTF / GLB

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

fn load_gltf(
    path: &Path,
    format: &'static str,
    bytes: &[u8],
    dir: Option<&Path>,
    options: &LoadOptions,
) -> Result<(Mesh, LoadReport), GeomError> {
    let parse_err = |message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message,
    };
    let glb;
    let (json_bytes, blob): (&[u8], Option<&[u8]>) = if bytes.starts_with(b"glTF") {
        glb = gltf::Glb::from_slice(bytes).map_err(|e| parse_err(format!("bad GLB: {e}")))?;
        (&glb.json, glb.bin.as_deref())
    } else {
        (bytes, None)
    };
    let mut root: gltf::json::Root = gltf::json::deserialize::from_slice(json_bytes)
        .map_err(|e| parse_err(format!("bad glTF JSON: {e}")))?;
    // Compressed geometry we cannot decode. Listed as used but not required, the file must
    // also hold the geometry uncompressed (the glTF specification's fallback): read that.
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
            if required || !has_uncompressed_fallback(&root, ext) {
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
    // A required extension we do not read could change the geometry or is unknown: refuse it
    // by name rather than load something wrong. Extensions that only concern appearance do not
    // touch the triangles; EXT_mesh_gpu_instancing and KHR_mesh_quantization are read.
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
    if let Some(ext) = root.extensions_required.iter().find(|e| !understood(e)) {
        return Err(GeomError::Unsupported {
            path: path.to_path_buf(),
            feature: format!("the required glTF extension {ext}"),
        });
    }
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
                return Err(parse_err(format!(
                    "mesh {m} primitive {k}: POSITION accessor {} does not exist ({} accessors)",
                    i.value(),
                    root.accessors.len()
                )));
            }
        }
    }
    let doc = gltf::Document::from_json(root).map_err(|e| parse_err(e.to_string()))?;

    let mut report = LoadReport {
        format,
        ..Default::default()
    };
    for what in fallbacks {
        report.warnings.push(format!(
            "the file also holds its geometry without {what}, which is not supported: that \
             uncompressed copy was read"
        ));
    }

    // The scene's shape first (cheap, no buffer is read): cycles, instance counts, limits.
    let scene = doc.default_scene().or_else(|| doc.scenes().next());
    let graph = match &scene {
        Some(scene) => Some(node_graph(path, &doc, scene)?),
        None => None,
    };
    // Nodes drawn many times by EXT_mesh_gpu_instancing (validated here, read below).
    let accessors: Vec<gltf::Accessor> = doc.accessors().collect();
    let instancing: Vec<Option<GpuInstancing>> = doc
        .nodes()
        .map(|node| gpu_instancing(path, &accessors, &node))
        .collect::<Result<_, _>>()?;
    // Which meshes are used, how often, and what they would add.
    let mut mesh_uses = vec![0u64; doc.meshes().len()];
    match &graph {
        Some(g) => {
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
            ("instanced triangles", tris, MAX_INSTANCED_TRIANGLES),
            ("instanced vertices", verts, MAX_INSTANCED_VERTICES),
        ],
    )?;

    // Buffers: GLB blob, data: URIs, or files inside the .gltf's folder. Images are never touched.
    // Only buffers that a buffer view uses are read; the BIN chunk is copied once and a file
    // named by several buffers is read once, so a small file that lists thousands of buffers
    // over the same bytes cannot multiply them in memory.
    let mut used = vec![false; doc.buffers().len()];
    for view in doc.views() {
        used[view.buffer().index()] = true;
    }
    let mut bin: Option<Rc<[u8]>> = None;
    let mut files: HashMap<PathBuf, Rc<[u8]>> = HashMap::new();
    let mut buffers: Vec<Rc<[u8]>> = Vec::new();
    for buffer in doc.buffers() {
        let buffer_index = buffer.index();
        if !used[buffer_index] {
            buffers.push(Rc::from(Vec::new()));
            continue;
        }
        let data: Rc<[u8]> = match buffer.source() {
            gltf::buffer::Source::Bin => match &bin {
                Some(b) => b.clone(),
                None => {
                    let b: Rc<[u8]> = blob
                        .ok_or_else(|| {
                            parse_err("buffer refers to a GLB BIN chunk that is missing".into())
                        })?
                        .into();
                    bin = Some(b.clone());
                    b
                }
            },
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
                        .into()
                } else {
                    let file = resolve_uri(path, dir, buffer.index(), uri, options)?;
                    // By canonical path: `a.bin`, `./a.bin` and `x/../a.bin` are one file.
                    let key = std::fs::canonicalize(&file).unwrap_or_else(|_| file.clone());
                    match files.get(&key) {
                        Some(data) => data.clone(),
                        None => {
                            // Name the glTF and the buffer, not only the file it leads to.
                            let data: Rc<[u8]> = read_input_file(&file)
                                .map_err(|e| match e {
                                    GeomError::Io { source, .. } => GeomError::MissingBuffer {
                                        gltf: path.to_path_buf(),
                                        index: buffer_index,
                                        uri: in_message(uri),
                                        buffer: file.clone(),
                                        source,
                                    },
                                    GeomError::NotARegularFile { path: buffer, kind } => {
                                        GeomError::BufferNotARegularFile {
                                            gltf: path.to_path_buf(),
                                            index: buffer_index,
                                            uri: in_message(uri),
                                            buffer,
                                            kind,
                                        }
                                    }
                                    e => e,
                                })?
                                .into();
                            files.insert(key, data.clone());
                            data
                        }
                    }
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
    // A mesh's warnings are given at its first instance only (a million instances, one warning).
    let mut warned = vec![false; doc.meshes().len()];
    match (scene, graph) {
        (Some(scene), Some(graph)) => {
            // Expand instance paths, skipping subtrees without meshes: the counts above bound this.
            let mut stack: Vec<(gltf::Node, Mat4)> = scene
                .nodes()
                .filter(|n| graph.mesh_below[n.index()])
                .map(|n| (n, Mat4::IDENTITY))
                .collect();
            stack.reverse();
            while let Some((node, parent)) = stack.pop() {
                let local = node_matrix(path, &node)?;
                let world = parent * local;
                if !world.is_finite() {
                    return Err(node_error(
                        path,
                        &node,
                        "its transform composed with its ancestors' is not finite in float32"
                            .into(),
                    ));
                }
                if let Some(mesh) = node.mesh() {
                    let weights = node.weights().or_else(|| mesh.weights());
                    // The instances' transforms apply after the node's, and to its mesh only.
                    let worlds = match &instancing[node.index()] {
                        Some(inst) => instance_matrices(path, node.index(), inst, &buffers)?
                            .into_iter()
                            .enumerate()
                            .map(|(i, m)| {
                                let w = world * m;
                                if w.is_finite() {
                                    Ok(w)
                                } else {
                                    Err(node_error(
                                        path,
                                        &node,
                                        format!(
                                            "EXT_mesh_gpu_instancing instance {i} composed with the node's transform is not finite in float32"
                                        ),
                                    ))
                                }
                            })
                            .collect::<Result<_, _>>()?,
                        None => vec![world],
                    };
                    for world in worlds {
                        report.instances += 1;
                        add_gltf_mesh(
                            path,
                            Some(&node),
                            &mesh,
                            world,
                            weights.unwrap_or_default(),
                            !std::mem::replace(&mut warned[mesh.index()], true),
                            &buffers,
                            &mut vertices,
                            &mut triangles,
                            &mut report,
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
        }
        _ => {
            report
                .warnings
                .push("no scene: every mesh taken once with the identity transform".into());
            for mesh in doc.meshes() {
                report.instances += 1;
                add_gltf_mesh(
                    path,
                    None,
                    &mesh,
                    Mat4::IDENTITY,
                    mesh.weights().unwrap_or_default(),
                    true,
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

/// The node graph of one scene, checked and counted without expanding shared nodes.
struct NodeGraph {
    /// How many times each node is instanced (number of paths from the scene's roots), saturating.
    multiplicity: Vec<u64>,
    /// Whether the node or a descendant has a mesh.
    mesh_below: Vec<bool>,
}

/// Checks the scene's node graph for cycles and counts node instances through shared children.
fn node_graph(
    path: &Path,
    doc: &gltf::Document,
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
    })
}

/// Triangles and vertices one instance of `mesh` adds (from accessor counts; nothing is read).
fn mesh_size(mesh: &gltf::Mesh) -> (u64, u64) {
    use gltf::mesh::Mode;
    let (mut tris, mut verts) = (0u64, 0u64);
    for prim in mesh.primitives() {
        let Some(pos) = prim.get(&gltf::Semantic::Positions) else {
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
            .saturating_add(pos.count() as u64)
            .saturating_add(targets.saturating_mul(per_target));
    }
    (tris, verts)
}

/// Where a glTF buffer `uri` that is not a `data:` URI points: a file inside the asset's folder
/// (after percent-decoding, `..` and symbolic links), unless `allow_external_uris`.
fn resolve_uri(
    gltf: &Path,
    dir: Option<&Path>,
    buffer: usize,
    uri: &str,
    options: &LoadOptions,
) -> Result<PathBuf, GeomError> {
    let refuse = |reason: &'static str| GeomError::UriRefused {
        gltf: gltf.to_path_buf(),
        buffer,
        uri: in_message(uri),
        reason,
    };
    // An empty reference means the document itself (and joined to the folder, the folder).
    if uri.is_empty() {
        return Err(refuse("it is empty"));
    }
    // A URI scheme: letters, digits, `+`, `-`, `.` before a `:`. (A Windows drive letter looks like
    // one too, and is an absolute path anyway.)
    if let Some((scheme, _)) = uri.split_once(':') {
        let mut chars = scheme.chars();
        if chars.next().is_some_and(|c| c.is_ascii_alphabetic())
            && chars.all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
        {
            return Err(refuse(
                "only data: URIs and relative file paths are supported",
            ));
        }
    }
    let Some(dir) = dir else {
        return Err(refuse(
            "the glTF was given without a folder, so only data: and GLB buffers can be used",
        ));
    };
    let decoded = percent_decode(uri);
    if decoded.contains('\0') {
        return Err(refuse("the path contains a NUL byte"));
    }
    let rel = Path::new(&decoded);
    if options.allow_external_uris {
        return Ok(dir.join(rel));
    }
    // Lexically first, so that nothing outside the folder is even looked at.
    let mut depth = 0usize;
    for c in rel.components() {
        match c {
            Component::Normal(_) => depth += 1,
            Component::CurDir => {}
            Component::ParentDir => {
                if depth == 0 {
                    return Err(refuse(
                        "it leads out of the glTF's folder (allow_external_uris is off)",
                    ));
                }
                depth -= 1;
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(refuse(
                    "it is an absolute path (allow_external_uris is off)",
                ));
            }
        }
    }
    let file = dir.join(rel);
    // Then through symbolic links. A missing file inside the folder is reported as missing.
    let (Ok(real_dir), Ok(real_file)) = (dir.canonicalize(), file.canonicalize()) else {
        return Ok(file);
    };
    if !real_file.starts_with(&real_dir) {
        return Err(refuse(
            "a symbolic link takes it out of the glTF's folder (allow_external_uris is off)",
        ));
    }
    Ok(real_file)
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

/// A name or uri from the file as errors quote it: at most 200 characters, so that a hostile
/// file cannot fill a terminal.
fn in_message(text: &str) -> String {
    text.chars().take(200).collect()
}

/// [`GeomError::NodeTransform`] for `node`.
fn node_error(path: &Path, node: &gltf::Node, reason: String) -> GeomError {
    GeomError::NodeTransform {
        path: path.to_path_buf(),
        node: node.index(),
        name: node.name().map(in_message),
        reason,
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
struct GpuInstancing<'a> {
    translation: Option<(gltf::Accessor<'a>, Vec3Format)>,
    rotation: Option<gltf::Accessor<'a>>,
    scale: Option<(gltf::Accessor<'a>, Vec3Format)>,
    count: usize,
}

/// `node`'s [`GpuInstancing`], validated (accessors that exist, of the types the extension
/// allows, of one count), if it has the extension. Reads no buffer.
fn gpu_instancing<'a>(
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

/// The bytes of `count` elements of `elem` bytes, `offset` bytes into a buffer view, after checking
/// the view against its buffer and the elements against the view (the checks the `gltf` crate's
/// reader leaves to assertions).
fn view_elements<'b>(
    view: &gltf::buffer::View,
    offset: usize,
    count: usize,
    elem: usize,
    buffers: &'b [Rc<[u8]>],
    what: &str,
) -> Result<Vec<&'b [u8]>, String> {
    let stride = view.stride().unwrap_or(elem);
    if stride < elem {
        return Err(format!(
            "{what}: buffer view {} has byteStride {stride}, smaller than its {elem}-byte elements",
            view.index()
        ));
    }
    let data = buffers
        .get(view.buffer().index())
        .ok_or_else(|| format!("{what}: buffer {} is missing", view.buffer().index()))?;
    let (start, len) = (view.offset(), view.length());
    let bytes = start
        .checked_add(len)
        .and_then(|end| data.get(start..end))
        .ok_or_else(|| {
            format!(
                "{what}: buffer view {} (byteOffset {start}, byteLength {len}) lies outside buffer {} ({} bytes)",
                view.index(),
                view.buffer().index(),
                data.len()
            )
        })?;
    if count == 0 {
        return Ok(Vec::new());
    }
    let need = (count - 1)
        .checked_mul(stride)
        .and_then(|x| x.checked_add(elem))
        .and_then(|x| x.checked_add(offset));
    match need {
        Some(need) if need <= len => Ok((0..count)
            .map(|k| &bytes[offset + k * stride..offset + k * stride + elem])
            .collect()),
        _ => Err(format!(
            "{what}: {count} elements of {elem} bytes with stride {stride} from byteOffset {offset} do not fit in buffer view {} ({len} bytes)",
            view.index()
        )),
    }
}

/// Reads an accessor's elements as raw bytes (`elem` bytes each), applying sparse substitution.
/// Everything is validated: view bounds, strides, the sparse index type, order and range.
fn read_accessor<'b>(
    acc: &gltf::Accessor,
    elem: usize,
    buffers: &'b [Rc<[u8]>],
    what: &str,
) -> Result<Vec<&'b [u8]>, String> {
    static ZEROS: [u8; 16] = [0; 16];
    let count = acc.count();
    // No accessor a loadable scene reads is longer (three indices per triangle at most); a
    // longer one, which the sums of the scene limits may not catch, is refused before its
    // element list is allocated.
    if count as u64 > 3 * MAX_INSTANCED_TRIANGLES {
        return Err(format!(
            "{what}: count {count} is above the most any loadable scene reads ({})",
            3 * MAX_INSTANCED_TRIANGLES
        ));
    }
    let mut out: Vec<&'b [u8]> = match acc.view() {
        Some(view) => view_elements(&view, acc.offset(), count, elem, buffers, what)?,
        // No view: zeros, normally replaced in part by sparse values.
        None => vec![&ZEROS[..elem.min(16)]; count],
    };
    if let Some(sparse) = acc.sparse() {
        let n = sparse.count();
        if n == 0 || n > count {
            return Err(format!(
                "{what}: sparse count {n} is not within 1..={count} (the accessor's count)"
            ));
        }
        let indices = sparse.indices();
        let isize = indices.index_type().size();
        let idx = view_elements(
            &indices.view(),
            indices.offset(),
            n,
            isize,
            buffers,
            &format!("{what} (sparse indices)"),
        )?;
        let values = sparse.values();
        let vals = view_elements(
            &values.view(),
            values.offset(),
            n,
            elem,
            buffers,
            &format!("{what} (sparse values)"),
        )?;
        let mut prev: Option<u64> = None;
        for (i, v) in idx.iter().zip(vals) {
            let mut a = [0u8; 8];
            a[..i.len()].copy_from_slice(i);
            let k = u64::from_le_bytes(a);
            if k >= count as u64 || prev.is_some_and(|p| k <= p) {
                return Err(format!(
                    "{what}: sparse index {k} is out of range or out of order (count {count})"
                ));
            }
            prev = Some(k);
            out[k as usize] = v;
        }
    }
    Ok(out)
}

/// How a VEC3 accessor's elements decode: float32, or (`KHR_mesh_quantization`, as gltfpack
/// writes by default) signed or unsigned 8- or 16-bit integers, normalised or not.
#[derive(Clone, Copy, Debug)]
struct Vec3Format {
    ty: gltf::accessor::DataType,
    normalized: bool,
}

impl Vec3Format {
    /// `acc`'s format, if it is a VEC3 of one of those types.
    fn of(acc: &gltf::Accessor) -> Option<Self> {
        use gltf::accessor::{DataType, Dimensions};
        let ty = acc.data_type();
        (acc.dimensions() == Dimensions::Vec3
            && matches!(
                ty,
                DataType::F32 | DataType::I8 | DataType::U8 | DataType::I16 | DataType::U16
            ))
        .then_some(Vec3Format {
            ty,
            normalized: acc.normalized() && ty != DataType::F32,
        })
    }

    /// [`Vec3Format::of`], or what `what` (an attribute) has that is not one.
    fn described(acc: &gltf::Accessor, what: &str) -> Result<Self, String> {
        Self::of(acc).ok_or_else(|| {
            format!(
                "{what} accessor of type {:?} {:?} (only VEC3 of float32, or of 8- or 16-bit integers)",
                acc.data_type(),
                acc.dimensions()
            )
        })
    }

    /// Bytes per element.
    fn size(self) -> usize {
        3 * self.ty.size()
    }

    /// One element (`size` little-endian bytes; see [`component`]).
    fn decode(self, b: &[u8]) -> Vec3 {
        let c = |k: usize| component(self.ty, self.normalized, b, k);
        Vec3::new(c(0), c(1), c(2))
    }

    /// The elements of `acc` (whose format this is), decoded.
    fn read(
        self,
        acc: &gltf::Accessor,
        buffers: &[Rc<[u8]>],
        what: &str,
    ) -> Result<Vec<Vec3>, String> {
        Ok(read_accessor(acc, self.size(), buffers, what)?
            .into_iter()
            .map(|b| self.decode(b))
            .collect())
    }
}

/// Component `k` of an accessor element `b` of type `ty` (little-endian; float32, or 8- or 16-bit
/// integers). Normalised integers map as glTF says: c / 127 clamped at -1, c / 255, c / 32767
/// clamped at -1, c / 65535; others are their value.
fn component(ty: gltf::accessor::DataType, normalized: bool, b: &[u8], k: usize) -> f32 {
    use gltf::accessor::DataType;
    let (v, max) = match ty {
        DataType::I8 => (f32::from(b[k] as i8), 127.0),
        DataType::U8 => (f32::from(b[k]), 255.0),
        DataType::I16 => (
            f32::from(i16::from_le_bytes([b[2 * k], b[2 * k + 1]])),
            32767.0,
        ),
        DataType::U16 => (
            f32::from(u16::from_le_bytes([b[2 * k], b[2 * k + 1]])),
            65535.0,
        ),
        _ => return f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]),
    };
    if normalized { (v / max).max(-1.0) } else { v }
}

/// The [`Vec3Format`] of `acc`, or [`GeomError::Unsupported`] naming `what` and its type.
fn vec3_format(path: &Path, acc: &gltf::Accessor, what: &str) -> Result<Vec3Format, GeomError> {
    Vec3Format::described(acc, what).map_err(|feature| GeomError::Unsupported {
        path: path.to_path_buf(),
        feature,
    })
}

/// Adds `weights[i]` times morph target i's POSITION displacements to `positions` (the
/// primitive's own, in mesh space): the default pose. Targets without POSITION, and weights of 0,
/// change nothing; returns whether any position moved. Weights beyond the targets (or targets
/// beyond the weights) are a warning in `report`, if given, as the glTF specification wants the
/// counts equal.
fn morph(
    prim: &gltf::Primitive,
    mesh: usize,
    weights: &[f32],
    buffers: &[Rc<[u8]>],
    positions: &mut [Vec3],
    report: Option<&mut LoadReport>,
) -> Result<bool, String> {
    if weights.iter().all(|&w| w == 0.0) || prim.morph_targets().len() == 0 {
        return Ok(false);
    }
    let targets: Vec<_> = prim.morph_targets().collect();
    if let Some(report) = report
        && targets.len() != weights.len()
    {
        report.warnings.push(format!(
            "mesh {mesh} primitive {}: {} morph targets but {} weights (the extra ones ignored)",
            prim.index(),
            targets.len(),
            weights.len()
        ));
    }
    let mut moved = false;
    for (t, (target, &w)) in targets.iter().zip(weights).enumerate() {
        if !w.is_finite() {
            return Err(format!("morph target {t} has weight {w}"));
        }
        let Some(acc) = target.positions() else {
            continue;
        };
        if w == 0.0 {
            continue;
        }
        let format = Vec3Format::described(&acc, &format!("morph target {t}: POSITION"))?;
        if acc.count() != positions.len() {
            return Err(format!(
                "morph target {t}: {} POSITION displacements for {} vertices",
                acc.count(),
                positions.len()
            ));
        }
        let what = format!("morph target {t} POSITION");
        for (p, d) in positions.iter_mut().zip(format.read(&acc, buffers, &what)?) {
            *p += w * d;
        }
        moved = true;
    }
    Ok(moved)
}

#[allow(clippy::too_many_arguments)]
fn add_gltf_mesh(
    path: &Path,
    node: Option<&gltf::Node>,
    mesh: &gltf::Mesh,
    world: Mat4,
    morph_weights: &[f32],
    warn: bool,
    buffers: &[Rc<[u8]>],
    vertices: &mut Vec<Vec3>,
    triangles: &mut Vec<[u32; 3]>,
    report: &mut LoadReport,
) -> Result<(), GeomError> {
    use gltf::accessor::{DataType, Dimensions};
    use gltf::mesh::Mode;
    let flip = world.determinant() < 0.0;
    let parse_err = |prim: usize, message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message: format!("mesh {} primitive {prim}: {message}", mesh.index()),
    };
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
            if !warn {
                continue;
            }
            report.warnings.push(format!(
                "mesh {} primitive {} has no POSITION attribute (skipped)",
                mesh.index(),
                prim.index()
            ));
            continue;
        };
        let pos_format = vec3_format(path, &pos_acc, "POSITION")?;
        if pos_acc.count() == 0 {
            continue;
        }
        // Indices are validated before any position is read: type, then bounds.
        let index_size = match prim.indices() {
            Some(acc) => {
                if acc.dimensions() != Dimensions::Scalar {
                    return Err(parse_err(
                        prim.index(),
                        format!(
                            "index accessor {} has type {:?}; indices must be SCALAR",
                            acc.index(),
                            acc.dimensions()
                        ),
                    ));
                }
                match acc.data_type() {
                    DataType::U8 => Some(1),
                    DataType::U16 => Some(2),
                    DataType::U32 => Some(4),
                    t => {
                        return Err(parse_err(
                            prim.index(),
                            format!(
                                "index accessor {} has component type {t:?}; indices must be unsigned byte, short or int",
                                acc.index()
                            ),
                        ));
                    }
                }
            }
            None => None,
        };
        let mut local_positions = pos_format
            .read(&pos_acc, buffers, "POSITION")
            .map_err(|m| parse_err(prim.index(), m))?;
        let n = local_positions.len();
        let indices: Vec<u32> = match (prim.indices(), index_size) {
            (Some(acc), Some(size)) => read_accessor(&acc, size, buffers, "indices")
                .map_err(|m| parse_err(prim.index(), m))?
                .iter()
                .map(|b| {
                    let mut a = [0u8; 4];
                    a[..b.len()].copy_from_slice(b);
                    u32::from_le_bytes(a)
                })
                .collect(),
            _ => (0..n as u32).collect(),
        };
        if morph(
            &prim,
            mesh.index(),
            morph_weights,
            buffers,
            &mut local_positions,
            warn.then_some(&mut *report),
        )
        .map_err(|m| parse_err(prim.index(), m))?
        {
            report.morphed_primitives += 1;
        }
        let base = vertices.len();
        vertices.extend(local_positions.iter().map(|&p| world.transform_point3(p)));
        // A finite transform can still overflow a finite vertex: blame the transform, not the
        // vertex data (a non-finite position in the data is left for `clean` to report).
        if let Some(node) = node
            && let Some(i) =
                (0..n).find(|&i| local_positions[i].is_finite() && !vertices[base + i].is_finite())
        {
            return Err(node_error(
                path,
                node,
                format!(
                    "its transform takes mesh {} primitive {} vertex {i} from {} to {}, which is not finite in float32",
                    mesh.index(),
                    prim.index(),
                    local_positions[i],
                    vertices[base + i]
                ),
            ));
        }
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
            _ => {
                if warn && !indices.len().is_multiple_of(3) {
                    report.warnings.push(format!(
                        "mesh {} primitive {}: {} indices, not a multiple of 3; the last {} ignored",
                        mesh.index(),
                        prim.index(),
                        indices.len(),
                        indices.len() % 3
                    ));
                }
                indices
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect()
            }
        };
        for (k, t) in local.iter().enumerate() {
            for &i in t {
                if i as usize >= n {
                    return Err(GeomError::GltfIndexOutOfRange {
                        path: path.to_path_buf(),
                        mesh: mesh.index(),
                        mesh_name: mesh.name().map(in_message),
                        primitive: prim.index(),
                        triangle: k,
                        index: i,
                        vertex_count: n,
                    });
                }
            }
        }
        let base = u32::try_from(base + n)
            .map(|_| base as u32)
            .map_err(|_| parse_err(prim.index(), "more than 2^32 vertices".into()))?;
        triangles.extend(local.into_iter().map(|t| {
            let t = t.map(|i| i + base);
            if flip { [t[0], t[2], t[1]] } else { t }
        }));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Chunks are cut at line ends, and the bad-w line is numbered in the whole file: the same
    /// text and counts for every chunk size, with multi-byte characters, CR LF ends, removed
    /// lines, colours, a missing last newline and two bad w's.
    #[test]
    fn obj_text_is_the_same_in_any_chunks() {
        let text = "# en-tête\r\no naïve 名前\nv 0 0 0 1 0 0\nv 1 0 0\r\nv 0 1 0 0.5 0.5 0.5 1\n\
                    vt 0.5\nvn 0 0 1\nf 1/1/1 2/2/2 3/3/3 # c\nl 1 2\np 1\nf 1 2\nusemtl x\n\
                    v 0 0 1 0\nf 1 2 3 4\nv 2 2 2 inf\ng 名前 no newline at the end";
        let (whole, counts) = obj_text_in_chunks(text.as_bytes(), usize::MAX);
        let bad = text
            .replace("\r\n", "\n")
            .lines()
            .position(|l| l.starts_with("v 0 0 1 0"))
            .unwrap()
            + 1;
        assert_eq!(counts.bad_w.as_ref().map(|b| b.0), Some(bad));
        assert_eq!((counts.vertices, counts.triangles), (5, 3));
        for chunk in [0, 1, 2, 3, 5, 7, 16, 40, 1000] {
            let (t, c) = obj_text_in_chunks(text.as_bytes(), chunk);
            assert_eq!(t, whole, "chunks of {chunk}");
            assert_eq!(format!("{c:?}"), format!("{counts:?}"), "chunks of {chunk}");
        }
    }
}
