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
    /// A vertex has a NaN or infinite coordinate.
    #[error("vertex {vertex} has a non-finite coordinate {position:?}")]
    NonFiniteVertex {
        /// Index of the vertex (after merging all objects / primitives).
        vertex: usize,
        /// Its coordinates.
        position: [f32; 3],
    },
    /// A triangle refers to a vertex that does not exist.
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
    /// A glTF primitive uses a mode other than triangles, triangle strips or triangle fans.
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
    #[error("{gltf}: cannot read buffer {buffer}: {source}")]
    MissingBuffer {
        /// The glTF file.
        gltf: PathBuf,
        /// The buffer file it refers to.
        buffer: PathBuf,
        /// The underlying I/O error.
        source: std::io::Error,
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
