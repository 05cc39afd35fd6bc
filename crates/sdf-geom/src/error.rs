//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong while loading a mesh, validating it, or reading and writing `.npy` files.
///
/// Each validation failure named in the project's issue has its own variant, so callers (and tests) can
/// match on the cause rather than on message text.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GeomError {
    /// The file could not be opened or read (missing, a directory, permissions, ...).
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file that could not be read.
        path: PathBuf,
        /// The underlying I/O error.
        source: std::io::Error,
    },
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file that could not be written.
        path: PathBuf,
        /// The underlying I/O error.
        source: std::io::Error,
    },
    /// The file extension is not one of `obj`, `gltf` or `glb`.
    #[error(
        "unknown mesh format for {path}: extension {extension:?} (expected .obj, .gltf or .glb)"
    )]
    UnknownExtension {
        /// The offending file.
        path: PathBuf,
        /// The extension found (empty if none).
        extension: String,
    },
    /// The file's contents could not be parsed.
    #[error("parse error in {path}{}: {message}", line.map(|l| format!(" at line {l}")).unwrap_or_default())]
    Parse {
        /// The file being parsed.
        path: PathBuf,
        /// 1-based line number where known (OBJ).
        line: Option<usize>,
        /// What went wrong.
        message: String,
    },
    /// No usable (non-degenerate) triangle was found.
    #[error("the mesh has no triangles{}", if *.dropped > 0 { format!(" ({} degenerate or duplicate faces were dropped)", .dropped) } else { String::new() })]
    NoTriangles {
        /// How many faces were found but dropped as degenerate or duplicate.
        dropped: usize,
    },
    /// The mesh is so small (its longest half-extent below about 3e-39) that no f32 scale maps it
    /// into [-1, 1]³: every distance about it would be computed on unscaled subnormal numbers.
    #[error(
        "the mesh spans only {half_extent:e} from its centre, too small to normalise in float32; scale it up first"
    )]
    TooSmall {
        /// The longest half-extent of its bounding box.
        half_extent: f64,
    },
    /// A vertex has a NaN or infinite coordinate.
    #[error("vertex {vertex} has a non-finite coordinate {position:?}")]
    NonFiniteVertex {
        /// Index of the vertex (after merging all objects / primitives).
        vertex: usize,
        /// Its coordinates.
        position: [f32; 3],
    },
    /// A triangle of a mesh built in memory ([`crate::Mesh::from_raw`]) refers to a vertex that
    /// does not exist. Files have their own variants, which say where the index is written:
    /// [`GeomError::ObjIndexOutOfRange`] and [`GeomError::GltfIndexOutOfRange`].
    #[error(
        "triangle {triangle} uses vertex index {index}, but there are only {vertex_count} vertices"
    )]
    IndexOutOfRange {
        /// Index of the triangle.
        triangle: usize,
        /// The offending vertex index.
        index: u64,
        /// Number of vertices available.
        vertex_count: usize,
    },
    /// An OBJ face refers to a vertex that does not exist: a positive index beyond the file's
    /// vertices, or a negative (relative) one reaching before the first vertex.
    #[error(
        "{path}: line {line}: face {face} uses {}vertex index {index}, but {}",
        if *.index < 0 { "relative " } else { "" },
        if *.index < 0 {
            format!("only {} vertices come before it", .vertex_count)
        } else {
            format!("there are only {} vertices", .vertex_count)
        }
    )]
    ObjIndexOutOfRange {
        /// The file.
        path: PathBuf,
        /// 1-based line of the face.
        line: usize,
        /// Index of the face among the file's faces (0-based).
        face: usize,
        /// The index as written: 1-based, or negative to count back from the last vertex read.
        index: i64,
        /// Vertices it may refer to: those read before the face for a negative index, else
        /// the file's.
        vertex_count: usize,
    },
    /// A glTF primitive's indices refer to a vertex beyond its POSITION accessor.
    #[error(
        "{path}: mesh {mesh}{} primitive {primitive}: triangle {triangle} uses vertex index {index}, but the primitive has only {vertex_count} vertices",
        .mesh_name.as_ref().map(|n| format!(" ({n:?})")).unwrap_or_default()
    )]
    GltfIndexOutOfRange {
        /// The file.
        path: PathBuf,
        /// glTF mesh index.
        mesh: usize,
        /// The mesh's name, if it has one.
        mesh_name: Option<String>,
        /// Primitive index within the mesh.
        primitive: usize,
        /// Index of the triangle within the primitive (after strips and fans are converted).
        triangle: usize,
        /// The offending index (into the primitive's vertices).
        index: u32,
        /// Number of vertices of the primitive (its POSITION accessor's count).
        vertex_count: usize,
    },
    /// A glTF node's transform is unusable: a component that is not finite, a rotation that is
    /// not a unit quaternion, a projective matrix, or a transform that (composed with its
    /// ancestors' and, with `EXT_mesh_gpu_instancing`, its instances') is not finite or takes a
    /// vertex to a non-finite position.
    #[error(
        "{path}: node {node}{}: {reason}",
        .name.as_ref().map(|n| format!(" ({n:?})")).unwrap_or_default()
    )]
    NodeTransform {
        /// The file.
        path: PathBuf,
        /// glTF node index.
        node: usize,
        /// The node's name, if it has one.
        name: Option<String>,
        /// What is wrong.
        reason: String,
    },
    /// A glTF file's primitives are points and lines alone (the first one named): nothing
    /// encloses a volume. Beside triangles they are skipped with a warning.
    #[error(
        "{path}: mesh {mesh} primitive {primitive} has mode {mode}; only TRIANGLES, TRIANGLE_STRIP and TRIANGLE_FAN are supported"
    )]
    UnsupportedPrimitiveMode {
        /// The file.
        path: PathBuf,
        /// glTF mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The mode, e.g. `POINTS` or `LINES`.
        mode: &'static str,
    },
    /// A feature of the file format that is not supported (Draco or meshopt compression, quantised positions, ...).
    #[error("{path}: {feature} is not supported")]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is not supported.
        feature: String,
    },
    /// A buffer (e.g. a `.bin` file) referenced by a glTF file is missing or unreadable.
    #[error("{gltf}: buffer {index} (uri {uri:?}): cannot read {buffer}: {source}")]
    MissingBuffer {
        /// The glTF file.
        gltf: PathBuf,
        /// Index of the buffer.
        index: usize,
        /// The URI as written in the file (truncated to 200 characters).
        uri: String,
        /// The buffer file it refers to.
        buffer: PathBuf,
        /// The underlying I/O error.
        source: std::io::Error,
    },
    /// A glTF buffer's `uri` names something other than a regular file (its folder, a FIFO, a
    /// device): refused unread, as [`GeomError::NotARegularFile`] is for the files given.
    #[error(
        "{gltf}: buffer {index} (uri {uri:?}): {buffer} is not a regular file (it is a {kind})"
    )]
    BufferNotARegularFile {
        /// The glTF file.
        gltf: PathBuf,
        /// Index of the buffer.
        index: usize,
        /// The URI as written in the file (truncated to 200 characters).
        uri: String,
        /// Where the URI leads (after following symbolic links).
        buffer: PathBuf,
        /// What it is instead, e.g. `"directory"` or `"FIFO"`.
        kind: &'static str,
    },
    /// A path given as a mesh, points file or glTF buffer is not a regular file (a directory, FIFO,
    /// device, socket): reading it could block forever or never end, so it is refused unread.
    #[error("{path} is not a regular file (it is a {kind})")]
    NotARegularFile {
        /// The path (after following symbolic links).
        path: PathBuf,
        /// What it is instead, e.g. `"FIFO"` or `"character device"`.
        kind: &'static str,
    },
    /// A file is larger than [`crate::MAX_FILE_BYTES`], checked before it is read.
    #[error("{path} has {size} bytes, more than the limit of {limit} bytes")]
    FileTooLarge {
        /// The file.
        path: PathBuf,
        /// Its size in bytes.
        size: u64,
        /// The limit ([`crate::MAX_FILE_BYTES`]).
        limit: u64,
    },
    /// A glTF buffer `uri` that is not followed: a scheme other than `data:`, an absolute path, or a
    /// path that leaves the asset's folder (see [`crate::LoadOptions::allow_external_uris`]). The
    /// message names the URI as written, never anything about the file it points at.
    #[error("{gltf}: buffer {buffer} has uri {uri:?}, which is refused: {reason}")]
    UriRefused {
        /// The glTF file.
        gltf: PathBuf,
        /// Index of the buffer.
        buffer: usize,
        /// The URI as written in the file (truncated to 200 characters).
        uri: String,
        /// Why it is refused.
        reason: &'static str,
    },
    /// A glTF scene expands (or an OBJ file holds) more instanced triangles, vertices or mesh
    /// instances than the stated limit ([`crate::MAX_INSTANCED_TRIANGLES`], [`crate::MAX_INSTANCED_VERTICES`],
    /// [`crate::MAX_INSTANCES`]); counted through shared nodes without expanding them.
    #[error("{path}: the scene has {count} {what}, more than the limit of {limit}")]
    SceneTooLarge {
        /// The glTF file.
        path: PathBuf,
        /// What was counted: `"instanced triangles"`, `"instanced vertices"`, `"mesh instances"`
        /// or `"node visits"`.
        what: &'static str,
        /// The count (saturating at `u64::MAX`).
        count: u64,
        /// The limit.
        limit: u64,
    },
    /// A mesh reader panicked. Input is validated before the readers run, so this is a bug (ours or
    /// a dependency's) that the loader turned into an error instead of a crash.
    #[error("internal error while reading {path}: {message} (please report this file)")]
    ReaderPanic {
        /// The file being read.
        path: PathBuf,
        /// The panic message.
        message: String,
    },
    /// A `.npy` file is malformed or has an unsupported dtype or shape.
    #[error("bad .npy file {path}: {message}")]
    Npy {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
}
