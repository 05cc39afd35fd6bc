//! Wavefront OBJ, through `tobj`: the text rewritten first to what the geometry needs (and what
//! `tobj` reads correctly), counted against the limits before `tobj` allocates, and a light
//! re-scan to place `tobj`'s errors on a line.

use std::cell::RefCell;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use glam::DVec3;
use rayon::prelude::*;

use super::polygon::Polygons;
use super::{MAX_INSTANCED_TRIANGLES, MAX_INSTANCED_VERTICES, check_limits, in_message};
use crate::GeomError;
use crate::mesh::{LoadReport, Mesh, clean, recentre};

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
                // tobj divides by w: an infinite one would silently put the vertex at 0. In f64,
                // as tobj reads it (1e-50 is no zero there, nor 1e39 infinite).
                if numbers.len() == 4
                    && counts.bad_w.is_none()
                    && numbers[3]
                        .parse::<f64>()
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
            // Objects and groups are merged anyway, and tobj would build a model (nine lists
            // and its own copy of the vertices it uses) for each: 20 M one-face groups over
            // three vertices pass every count and take gigabytes.
            Some("vt" | "vn" | "vp" | "usemtl" | "o" | "g") => {}
            _ => out.push_str(content),
        }
        if line.ends_with('\n') {
            out.push('\n');
        }
    }
    (out, counts, lines)
}

/// What [`obj_text`] saw: the vertices and triangles (`n − 2` a polygon) that `tobj` will build,
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

/// Loads OBJ text: rewritten for `tobj` ([`obj_text`]), bounded, parsed, triangulated and
/// merged over all objects. `dir` (the file's folder, if any) is where named material
/// libraries are looked for, only to warn when one is missing.
pub(super) fn load_obj(
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
    // Only names inside the file's folder are looked for, through links too: a file must not
    // learn (from whether a warning appears) which paths elsewhere exist, as glTF URIs may not.
    // One warning for the first missing library, however many lines name one.
    let missing: Vec<PathBuf> = mtllibs
        .into_inner()
        .into_iter()
        .filter(|lib| {
            let inside = lib
                .components()
                .all(|c| matches!(c, std::path::Component::Normal(_)));
            inside
                && dir.is_some_and(|d| {
                    matches!(super::buffers::resolve_inside(d, &d.join(lib)), Some(real)
                        if !real.as_ref().is_some_and(|r| r.is_file()))
                })
        })
        .collect();
    if let Some(first) = missing.first() {
        let more = match missing.len() {
            1 => String::new(),
            n => format!(" and {} more", n - 1),
        };
        report.warnings.push(format!(
            "material library {}{more} not found (ignored: materials are not needed)",
            in_message(&first.display().to_string())
        ));
    }

    // Positions in f64 (tobj's `use_f64`), recentred before they become f32 ([`recentre`]).
    let mut positions: Vec<DVec3> = Vec::new();
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    let mut polygons = Polygons::default();
    for model in &models {
        let m = &model.mesh;
        let base = positions.len() as u64;
        positions.extend(
            m.positions
                .chunks_exact(3)
                .map(|c| DVec3::new(c[0], c[1], c[2])),
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
                if arity == 3 {
                    triangles.push([idx(face[0])?, idx(face[1])?, idx(face[2])?]);
                    continue;
                }
                report.polygons_triangulated += 1;
                // An index past the positions (refused by the clean-up) reads as NaN: a fan.
                let at = |i: u32| positions.get(base as usize + i as usize).copied();
                let corners = face.iter().map(|&i| at(i).unwrap_or(DVec3::NAN));
                for t in polygons.triangulate(corners) {
                    triangles.push([idx(face[t[0]])?, idx(face[t[1]])?, idx(face[t[2]])?]);
                }
            }
        }
    }
    polygons.report(&mut report);
    if counts.short_faces > 0 {
        report.warnings.push(format!(
            "{} faces with fewer than three vertices ignored",
            counts.short_faces
        ));
    }
    let vertices = recentre(&positions, &triangles, &mut report);
    drop(positions);
    let mesh = clean(vertices, triangles, &mut report)?;
    Ok((mesh, report))
}

/// Turns a `tobj` error into a typed error, finding the offending line by re-scanning the text.
fn obj_error(path: &Path, text: &str, err: tobj::LoadError) -> GeomError {
    // Only an index error is looked for among the indices: a face may use vertices defined
    // after it (tobj checks them at the end), so another error lies elsewhere.
    let found = scan_obj(text, err == tobj::LoadError::FaceVertexOutOfBounds);
    if err == tobj::LoadError::FaceVertexOutOfBounds
        && let Some(ScanIssue::IndexOutOfRange {
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
/// the vertices before it, a positive one against those of the whole file (objects and groups
/// are gone from the text it reads, which tobj reads as one object).
fn scan_obj(text: &str, check_ranges: bool) -> Option<ScanIssue> {
    // It reads the text `obj_text` gave tobj: no texture coordinates or normals are left.
    let mut nv = 0usize;
    let mut faces = 0usize;
    // The largest positive vertex index so far: (index, line, face).
    let mut pending: Option<(i64, usize, usize)> = None;
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
            _ => {}
        }
    }
    pending
        .filter(|&(v, _, _)| v as u64 > nv as u64)
        .map(|(index, line, face)| ScanIssue::IndexOutOfRange {
            line,
            face,
            index,
            vertex_count: nv,
        })
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
