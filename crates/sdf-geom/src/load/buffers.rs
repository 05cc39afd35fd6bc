//! glTF buffers: the GLB blob, base64 `data:` URIs, and files, which stay inside the asset's
//! folder unless [`LoadOptions::allow_external_uris`] says otherwise.

use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};
use std::rc::Rc;

use base64::Engine as _;

use super::{LoadOptions, in_message, parse_error, read_input_file};
use crate::GeomError;

/// The document's buffers, index for index: the GLB blob, `data:` URIs, or files inside the
/// .gltf's folder (see [`resolve_uri`]). Images are never touched. Only buffers that an
/// accessor's view uses are read, and not for accessors of animations and skins alone (the
/// others are empty: a buffer of textures alone, which an image's view names, or of animation
/// keyframes, may be missing or broken without stopping the geometry); the BIN chunk is copied once and a file named by
/// several buffers is read once, so a small file that lists thousands of buffers over the same
/// bytes cannot multiply them in memory.
pub(super) fn read_buffers(
    path: &Path,
    doc: &gltf::Document,
    blob: Option<&[u8]>,
    dir: Option<&Path>,
    options: &LoadOptions,
) -> Result<Vec<Rc<[u8]>>, GeomError> {
    let mut used = vec![false; doc.buffers().len()];
    let animation_only = animation_only_accessors(doc);
    for accessor in doc.accessors() {
        if animation_only[accessor.index()] {
            continue;
        }
        let sparse = accessor.sparse();
        let views = accessor.view().into_iter().chain(
            sparse
                .iter()
                .flat_map(|s| [s.indices().view(), s.values().view()]),
        );
        for view in views {
            used[view.buffer().index()] = true;
        }
    }
    let mut bin: Option<Rc<[u8]>> = None;
    let mut files: HashMap<PathBuf, Rc<[u8]>> = HashMap::new();
    let mut buffers: Vec<Rc<[u8]>> = Vec::new();
    for buffer in doc.buffers() {
        if !used[buffer.index()] {
            buffers.push(Rc::from(Vec::new()));
            continue;
        }
        let data: Rc<[u8]> = match buffer.source() {
            gltf::buffer::Source::Bin => match &bin {
                Some(b) => b.clone(),
                None => {
                    let b: Rc<[u8]> = blob
                        .ok_or_else(|| {
                            parse_error(
                                path,
                                "buffer refers to a GLB BIN chunk that is missing".into(),
                            )
                        })?
                        .into();
                    bin = Some(b.clone());
                    b
                }
            },
            gltf::buffer::Source::Uri(uri) => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    data_uri(path, buffer.index(), rest)?
                } else {
                    let file = resolve_uri(path, dir, buffer.index(), uri, options)?;
                    // By canonical path: `a.bin`, `./a.bin` and `x/../a.bin` are one file.
                    let key = std::fs::canonicalize(&file).unwrap_or_else(|_| file.clone());
                    match files.get(&key) {
                        Some(data) => data.clone(),
                        None => {
                            let data = buffer_file(path, buffer.index(), uri, &file)?;
                            files.insert(key, data.clone());
                            data
                        }
                    }
                }
            }
        };
        if data.len() < buffer.length() {
            return Err(parse_error(
                path,
                format!(
                    "buffer {} has {} bytes but declares {}",
                    buffer.index(),
                    data.len(),
                    buffer.length()
                ),
            ));
        }
        buffers.push(data);
    }
    Ok(buffers)
}

/// Per accessor, whether only animations (their samplers' keyframes) and skins (their inverse
/// bind matrices) use it: the rest pose the loader reads needs neither, so their buffers (an
/// `anim.bin` beside the geometry's) are not read. An accessor a mesh or a node's instances
/// also use is needed.
fn animation_only_accessors(doc: &gltf::Document) -> Vec<bool> {
    let mut only = vec![false; doc.accessors().len()];
    let animations = doc.animations().flat_map(|a| {
        a.samplers()
            .flat_map(|s| [s.input().index(), s.output().index()])
            .collect::<Vec<_>>()
    });
    let skins = doc
        .skins()
        .filter_map(|s| s.inverse_bind_matrices().map(|a| a.index()));
    for i in animations.chain(skins) {
        only[i] = true;
    }
    for prim in doc
        .meshes()
        .flat_map(|m| m.primitives().collect::<Vec<_>>())
    {
        let targets = prim.morph_targets().flat_map(|t| {
            [t.positions(), t.normals(), t.tangents()]
                .into_iter()
                .flatten()
                .map(|a| a.index())
                .collect::<Vec<_>>()
        });
        let attributes = prim.attributes().map(|(_, a)| a.index());
        for i in attributes
            .chain(prim.indices().map(|a| a.index()))
            .chain(targets)
        {
            only[i] = false;
        }
    }
    // EXT_mesh_gpu_instancing's instances (validated where they are read).
    let instancing = doc.nodes().filter_map(|n| {
        n.extension_value("EXT_mesh_gpu_instancing")?
            .get("attributes")
            .cloned()
    });
    for attributes in instancing {
        let indices = attributes.as_object().into_iter().flat_map(|a| a.values());
        for i in indices.filter_map(|v| usize::try_from(v.as_u64()?).ok()) {
            if let Some(o) = only.get_mut(i) {
                *o = false;
            }
        }
    }
    only
}

/// The bytes of a `data:` URI (`rest` follows `data:`); only base64 ones are supported.
fn data_uri(path: &Path, buffer: usize, rest: &str) -> Result<Rc<[u8]>, GeomError> {
    let Some((_, payload)) = rest.split_once(";base64,") else {
        return Err(parse_error(
            path,
            format!("buffer {buffer}: only base64 data: URIs are supported"),
        ));
    };
    Ok(base64::engine::general_purpose::STANDARD
        .decode(payload.trim())
        .map_err(|e| parse_error(path, format!("buffer {buffer}: bad base64: {e}")))?
        .into())
}

/// Reads the file a buffer's `uri` resolved to. Errors name the glTF and the buffer, not only
/// the file it leads to.
fn buffer_file(path: &Path, index: usize, uri: &str, file: &Path) -> Result<Rc<[u8]>, GeomError> {
    Ok(read_input_file(file)
        .map_err(|e| match e {
            GeomError::Io { source, .. } => GeomError::MissingBuffer {
                gltf: path.to_path_buf(),
                index,
                uri: in_message(uri),
                buffer: file.to_path_buf(),
                source,
            },
            GeomError::NotARegularFile { path: buffer, kind } => GeomError::BufferNotARegularFile {
                gltf: path.to_path_buf(),
                index,
                uri: in_message(uri),
                buffer,
                kind,
            },
            e => e,
        })?
        .into())
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
    // Then through symbolic links. A missing file inside the folder is reported as missing.
    let file = dir.join(rel);
    match resolve_inside(dir, &file) {
        Some(real) => Ok(real.unwrap_or(file)),
        None => Err(refuse(
            "a symbolic link takes it out of the glTF's folder (allow_external_uris is off)",
        )),
    }
}

/// `file`, a path lexically inside `dir`, through symbolic links: `Some(Some(real))` for a file
/// that exists inside `dir`, `Some(None)` for a missing one whose deepest existing part is inside
/// (or a folder that does not resolve), `None` where a link takes it out or does not resolve. The deepest existing
/// part decides, so that a link out of the folder is refused whether or not its target exists:
/// told apart, "refused" and "missing" would say which files outside exist.
pub(super) fn resolve_inside(dir: &Path, file: &Path) -> Option<Option<PathBuf>> {
    let Ok(real_dir) = dir.canonicalize() else {
        return Some(None);
    };
    let mut existing = file;
    let real = loop {
        match existing.canonicalize() {
            Ok(real) => break real,
            // A link that does not resolve (dangling, a loop) points wherever it points: refused
            // whatever is there, or "missing" would say that nothing is.
            Err(_) if existing.symlink_metadata().is_ok_and(|m| m.is_symlink()) => return None,
            Err(_) => match existing.parent() {
                Some(parent) => existing = parent,
                None => return Some(None),
            },
        }
    };
    real.starts_with(&real_dir)
        .then(|| (existing == file).then_some(real))
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
