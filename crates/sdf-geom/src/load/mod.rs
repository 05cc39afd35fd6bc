//! Mesh loading: Wavefront OBJ (through `tobj`) and glTF / GLB (own validation and accessor reading,
//! `gltf` for the JSON document and the GLB container).
//!
//! Everything here treats the file as hostile: only regular files of at most [`MAX_FILE_BYTES`] are
//! read, glTF documents are validated (accessor types, strides, offsets, counts, sparse indices, the
//! node graph) before any data is read, external buffer URIs stay inside the asset's folder, the
//! instanced size of a scene is bounded, and a panic in a dependency becomes [`GeomError::ReaderPanic`].
//!
//! This file holds the entry points, the format dispatch, the file reading and the limits shared
//! by both formats; `obj` reads OBJ, `gltf` glTF with its `buffers`, `scene`, `accessors` and
//! `primitive` beside it.

mod accessors;
mod buffers;
mod gltf;
mod obj;
mod polygon;
mod primitive;
mod scene;

use std::io::Read;
use std::path::Path;

use crate::GeomError;
use crate::mesh::{LoadReport, Mesh};

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
/// Most node visits a glTF scene's expansion may make: each path from a root to each node with
/// a mesh below it, a transform composed and the node's children looked at per visit (each
/// child counts one more; about a second's work at this bound).
pub const MAX_NODE_VISITS: u64 = 16 * MAX_INSTANCES;

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
/// 16-bit integers, normalised or not, which node transforms scale back) are read. Point and
/// line primitives beside triangles (a CAD export's edges) are skipped with a warning.
///
/// # Errors
/// [`GeomError::UnknownExtension`], [`GeomError::Io`] (missing or unreadable file),
/// [`GeomError::NotARegularFile`], [`GeomError::FileTooLarge`],
/// [`GeomError::Parse`] (also every failed glTF validation), [`GeomError::NoTriangles`],
/// [`GeomError::NonFiniteVertex`], [`GeomError::ObjIndexOutOfRange`],
/// [`GeomError::GltfIndexOutOfRange`], [`GeomError::NodeTransform`],
/// [`GeomError::UnsupportedPrimitiveMode`] (a glTF file of points and lines alone),
/// [`GeomError::Unsupported`]
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
        obj::load_obj(path, bytes, dir)
    } else {
        self::gltf::load_gltf(path, format, bytes, dir, options)
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

/// [`GeomError::SceneTooLarge`] for the first `(what, count, limit)` whose count passes its limit.
pub(super) fn check_limits<const N: usize>(
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

/// A name or uri from the file as errors quote it: at most 200 characters, so that a hostile
/// file cannot fill a terminal.
pub(super) fn in_message(text: &str) -> String {
    text.chars().take(200).collect()
}

/// [`GeomError::Parse`] without a line: how every failed glTF validation is reported.
pub(super) fn parse_error(path: &Path, message: String) -> GeomError {
    GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message,
    }
}

/// [`GeomError::NodeTransform`] for `node`.
pub(super) fn node_error(path: &Path, node: &::gltf::Node, reason: String) -> GeomError {
    GeomError::NodeTransform {
        path: path.to_path_buf(),
        node: node.index(),
        name: node.name().map(in_message),
        reason,
    }
}
