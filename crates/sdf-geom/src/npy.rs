//! A minimal NumPy `.npy` reader and writer for point sets and distance arrays.
//!
//! Reads version 1, 2 and 3 files holding a C- or Fortran-ordered `(N, 3)` array of little- or
//! big-endian float32 or float64. Writes version 1 little-endian float32 or float64 files,
//! atomically (a temporary file in the same directory, then a rename).

use std::path::Path;

use glam::{DVec3, Vec3};

use crate::GeomError;

const MAGIC: &[u8] = b"\x93NUMPY";

fn bad(path: &Path, message: impl Into<String>) -> GeomError {
    GeomError::Npy {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// The parsed header of a `.npy` file.
#[derive(Clone, Debug, PartialEq)]
struct Header {
    descr: String,
    fortran: bool,
    shape: Vec<usize>,
}

/// The header's dict entries, `(key, the text after its colon)` in order, once the header is
/// found to be a plain dict literal: its keys plain quoted strings, its values strings,
/// booleans, numbers, lists and tuples, with no two strings side by side and no escapes. numpy
/// reads the header with Python's `literal_eval`, which also takes comments (`# 'descr': '<f4'`),
/// adjacent strings that join (`'des' 'cr'`, `'des' u'cr'`, triple quotes), escapes
/// (`'desc\x72'`) and keys in parentheses (`('descr')`): read otherwise here, a crafted header
/// gave another dtype or shape than numpy's. No writer emits those; they are refused. Only the
/// dict's own keys are entries: a string elsewhere (a structured dtype's field named
/// `x', 'descr': '<f4`) is not, where a search of the text had read that file's float64 fields
/// as float32.
fn header_entries<'a>(path: &Path, h: &'a str) -> Result<Vec<(&'a str, &'a str)>, GeomError> {
    let refuse = |what: &str| Err(bad(path, format!("header {what}")));
    let b = h.as_bytes();
    let (mut i, mut depth, mut entries) = (0, 0usize, Vec::new());
    // Whether the last thing outside whitespace was a string, and whether a key of the dict
    // (a plain string) or its end comes next.
    let (mut after_string, mut key_next) = (false, false);
    while i < b.len() {
        let c = b[i];
        let known = c.is_ascii_alphanumeric() || b"'\"{}[](),:_.+-".contains(&c);
        if !known && !c.is_ascii_whitespace() {
            return refuse(&format!("has {:?} outside its strings", char::from(c)));
        }
        let key_or_end = matches!(c, b'\'' | b'"' | b'}') || c.is_ascii_whitespace();
        if key_next && depth == 1 && !key_or_end {
            return refuse("has a key that is not a plain string");
        }
        match c {
            quote @ (b'\'' | b'"') => {
                if after_string {
                    return refuse("has strings side by side (or triple quotes)");
                }
                if i > 0 && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_') {
                    return refuse("has a prefixed string");
                }
                // Quotes are ASCII, so `start` and the closing quote are character boundaries.
                let start = i + 1;
                i = start;
                while i < b.len() && b[i] != quote {
                    if b[i] == b'\\' {
                        return refuse("has an escape in a string");
                    }
                    i += 1;
                }
                let value = h[(i + 1).min(h.len())..].trim_start().strip_prefix(':');
                if let (true, Some(value)) = (key_next, value) {
                    entries.push((&h[start..i], value.trim_start()));
                }
                (after_string, key_next) = (true, false);
            }
            c if c.is_ascii_whitespace() => {}
            b'{' | b'[' | b'(' => {
                depth += 1;
                (after_string, key_next) = (false, c == b'{' && depth == 1);
            }
            b'}' | b']' | b')' => {
                depth = depth.saturating_sub(1);
                (after_string, key_next) = (false, false);
            }
            b',' => (after_string, key_next) = (false, depth == 1),
            // The rest of the known bytes: letters, digits and `:_.+-`.
            _ => (after_string, key_next) = (false, false),
        }
        i += 1;
    }
    Ok(entries)
}

fn parse_header(path: &Path, h: &str) -> Result<Header, GeomError> {
    let entries = header_entries(path, h)?;
    // Of a key given twice, the last: Python's rule for dict literals, so what `numpy.load`
    // reads.
    let dict_value = |key: &str| entries.iter().rev().find(|e| e.0 == key).map(|e| e.1);
    let descr_v = dict_value("descr").ok_or_else(|| bad(path, "header has no 'descr'"))?;
    let q = descr_v.chars().next().unwrap_or(' ');
    if q != '\'' && q != '"' {
        return Err(bad(
            path,
            "unsupported dtype description (structured dtype?)",
        ));
    }
    let descr: String = descr_v[1..].chars().take_while(|&c| c != q).collect();
    let fortran_v =
        dict_value("fortran_order").ok_or_else(|| bad(path, "header has no 'fortran_order'"))?;
    let fortran = if fortran_v.starts_with("True") {
        true
    } else if fortran_v.starts_with("False") {
        false
    } else {
        return Err(bad(path, "bad 'fortran_order' value"));
    };
    let shape_v = dict_value("shape").ok_or_else(|| bad(path, "header has no 'shape'"))?;
    let inner = shape_v
        .strip_prefix('(')
        .and_then(|s| s.split_once(')'))
        .map(|(s, _)| s)
        .ok_or_else(|| bad(path, "bad 'shape' value"))?;
    let mut shape = Vec::new();
    for part in inner.split(',') {
        let part = part.trim().trim_end_matches('L');
        if part.is_empty() {
            continue;
        }
        shape.push(
            part.parse::<usize>()
                .map_err(|_| bad(path, format!("bad shape entry {part:?}")))?,
        );
    }
    Ok(Header {
        descr,
        fortran,
        shape,
    })
}

/// Reads an `(N, 3)` float32 or float64 array of points. float64 values are rounded to float32.
///
/// # Errors
/// [`GeomError::Io`] if the file cannot be read, [`GeomError::NotARegularFile`] or
/// [`GeomError::FileTooLarge`] (see [`crate::read_input_file`]), [`GeomError::Npy`] for a bad magic string, an
/// unsupported version, dtype or shape, or truncated data.
pub fn read_points(path: impl AsRef<Path>) -> Result<Vec<Vec3>, GeomError> {
    let path = path.as_ref();
    parse_points(path, &crate::read_input_file(path)?)
}

/// Parses `.npy` bytes (see [`read_points`]); `path` is only used in error messages.
pub fn parse_points(path: &Path, bytes: &[u8]) -> Result<Vec<Vec3>, GeomError> {
    let table = Table::parse(path, bytes, 3)?;
    Ok((0..table.rows).map(|r| table.point(r).as_vec3()).collect())
}

/// [`read_points`] keeping float64 input in f64 (float32 input is widened exactly): points far
/// from the origin, where f32 would round them, for a mesh loaded relative to its
/// [`crate::LoadReport::origin`].
///
/// # Errors
/// As [`read_points`].
pub fn read_points_f64(path: impl AsRef<Path>) -> Result<Vec<DVec3>, GeomError> {
    let path = path.as_ref();
    parse_points_f64(path, &crate::read_input_file(path)?)
}

/// Parses `.npy` bytes (see [`read_points_f64`]); `path` is only used in error messages. The
/// points are decoded straight from the bytes: a flat table first, then points, took 5 times
/// the file's size (a 2 GiB file of float32 points, 10 GiB) before any check.
pub fn parse_points_f64(path: &Path, bytes: &[u8]) -> Result<Vec<DVec3>, GeomError> {
    let table = Table::parse(path, bytes, 3)?;
    Ok((0..table.rows).map(|r| table.point(r)).collect())
}

/// Reads an `(N, columns)` float32 or float64 `.npy` file (C or Fortran order) as `N · columns`
/// f32 values, row after row. Errors as [`read_points`].
pub fn read_table(path: impl AsRef<Path>, columns: usize) -> Result<Vec<f32>, GeomError> {
    Ok(read_table_f64(path, columns)?
        .into_iter()
        .map(|v| v as f32)
        .collect())
}

/// [`read_table`] keeping float64 input in f64 (float32 input is widened exactly).
pub fn read_table_f64(path: impl AsRef<Path>, columns: usize) -> Result<Vec<f64>, GeomError> {
    let path = path.as_ref();
    parse_table_f64(path, &crate::read_input_file(path)?, columns)
}

/// Parses `.npy` bytes as an `(N, columns)` table of f64 values, row after row (see
/// [`read_table`]); `path` is only used in error messages.
pub fn parse_table_f64(path: &Path, bytes: &[u8], columns: usize) -> Result<Vec<f64>, GeomError> {
    let table = Table::parse(path, bytes, columns)?;
    Ok((0..table.rows * columns)
        .map(|k| table.value(k / columns, k % columns))
        .collect())
}

/// An `(N, columns)` float32 or float64 array in a `.npy` file's bytes, checked, read value by
/// value.
struct Table<'a> {
    data: &'a [u8],
    rows: usize,
    columns: usize,
    /// Bytes per value: 4 or 8.
    size: usize,
    big_endian: bool,
    fortran: bool,
}

impl<'a> Table<'a> {
    /// The header checked (magic, version, dtype, shape `(N, columns)`) and the data long enough.
    fn parse(path: &Path, bytes: &'a [u8], columns: usize) -> Result<Self, GeomError> {
        if bytes.len() < 10 || &bytes[..6] != MAGIC {
            return Err(bad(path, "not a .npy file (missing \\x93NUMPY magic)"));
        }
        let major = bytes[6];
        let (hlen, hstart) = match major {
            1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
            2 | 3 => {
                if bytes.len() < 12 {
                    return Err(bad(path, "truncated header"));
                }
                (
                    u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                    12,
                )
            }
            v => return Err(bad(path, format!("unsupported .npy version {v}"))),
        };
        let data_start = hstart
            .checked_add(hlen)
            .filter(|&e| e <= bytes.len())
            .ok_or_else(|| bad(path, "truncated header"))?;
        let h = std::str::from_utf8(&bytes[hstart..data_start])
            .map_err(|_| bad(path, "header is not text"))?;
        let header = parse_header(path, h)?;
        let (size, big_endian) = match header.descr.as_str() {
            "<f4" | "=f4" | "f4" => (4, false),
            ">f4" => (4, true),
            "<f8" | "=f8" | "f8" => (8, false),
            ">f8" => (8, true),
            d => {
                return Err(bad(
                    path,
                    format!(
                        "dtype {d:?} is not supported (expected float32 '<f4' or float64 '<f8')"
                    ),
                ));
            }
        };
        let n = match header.shape.as_slice() {
            [n, c] if *c == columns => *n,
            s => {
                return Err(bad(
                    path,
                    format!("shape {s:?} is not supported (expected (N, {columns}))"),
                ));
            }
        };
        let count = n
            .checked_mul(columns)
            .ok_or_else(|| bad(path, "shape too large"))?;
        let need = count
            .checked_mul(size)
            .ok_or_else(|| bad(path, "shape too large"))?;
        let data = &bytes[data_start..];
        if data.len() < need {
            return Err(bad(
                path,
                format!(
                    "truncated data: {} bytes for {n}×{columns} values of {size} bytes ({need} needed)",
                    data.len()
                ),
            ));
        }
        Ok(Table {
            data,
            rows: n,
            columns,
            size,
            big_endian,
            fortran: header.fortran,
        })
    }

    /// Row `row` (in range) of a table of three columns, as a point.
    fn point(&self, row: usize) -> DVec3 {
        DVec3::new(self.value(row, 0), self.value(row, 1), self.value(row, 2))
    }

    /// The value at `row`, `column` (both in range), widened to f64.
    fn value(&self, row: usize, column: usize) -> f64 {
        let k = if self.fortran {
            column * self.rows + row
        } else {
            row * self.columns + column
        };
        let b = &self.data[k * self.size..(k + 1) * self.size];
        if self.size == 8 {
            let a: [u8; 8] = b.try_into().unwrap_or([0; 8]);
            if self.big_endian {
                f64::from_be_bytes(a)
            } else {
                f64::from_le_bytes(a)
            }
        } else {
            let a: [u8; 4] = b.try_into().unwrap_or([0; 4]);
            f64::from(if self.big_endian {
                f32::from_be_bytes(a)
            } else {
                f32::from_le_bytes(a)
            })
        }
    }
}

fn npy_bytes(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic + version + len + header + '\n' is a multiple of 64.
    let unpadded = MAGIC.len() + 2 + 2 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

/// [`crate::io::write_atomic`] with the error typed for this module.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), GeomError> {
    crate::io::write_atomic(path, bytes).map_err(|source| GeomError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes a 1-D float32 array (shape `(N,)`), atomically.
pub fn write_f32(path: impl AsRef<Path>, values: &[f32]) -> Result<(), GeomError> {
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    write_atomic(
        path.as_ref(),
        &npy_bytes("<f4", &format!("({},)", values.len()), &data),
    )
}

/// Writes an `(N, 3)` float32 array of points, atomically.
pub fn write_points(path: impl AsRef<Path>, points: &[Vec3]) -> Result<(), GeomError> {
    let data: Vec<u8> = points
        .iter()
        .flat_map(|p| p.to_array())
        .flat_map(|v| v.to_le_bytes())
        .collect();
    write_atomic(
        path.as_ref(),
        &npy_bytes("<f4", &format!("({}, 3)", points.len()), &data),
    )
}

/// Writes an `(N, columns)` float32 array (`values` row after row), atomically.
pub fn write_table(
    path: impl AsRef<Path>,
    values: &[f32],
    columns: usize,
) -> Result<(), GeomError> {
    let rows = whole_rows(path.as_ref(), values.len(), columns)?;
    let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    write_rows(path.as_ref(), "<f4", rows, columns, data)
}

/// Writes an `(N, columns)` float64 array (`values` row after row), atomically: coordinates far
/// from the origin, which float32 would round.
pub fn write_table_f64(
    path: impl AsRef<Path>,
    values: &[f64],
    columns: usize,
) -> Result<(), GeomError> {
    let rows = whole_rows(path.as_ref(), values.len(), columns)?;
    let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    write_rows(path.as_ref(), "<f8", rows, columns, data)
}

/// The rows `len` values make in `columns` columns; an error (nothing written) unless they make
/// whole rows: a header of fewer values than follow it would hide the rest from readers.
fn whole_rows(path: &Path, len: usize, columns: usize) -> Result<usize, GeomError> {
    if columns == 0 || !len.is_multiple_of(columns) {
        return Err(bad(
            path,
            format!("{len} values do not make whole rows of {columns} columns"),
        ));
    }
    Ok(len / columns)
}

/// Writes `rows × columns` values of type `descr` (their little-endian bytes), atomically.
fn write_rows(
    path: &Path,
    descr: &str,
    rows: usize,
    columns: usize,
    data: Vec<u8>,
) -> Result<(), GeomError> {
    write_atomic(
        path,
        &npy_bytes(descr, &format!("({rows}, {columns})"), &data),
    )
}

/// Reads a 1-D float32 array (as written by [`write_f32`]).
pub fn read_f32(path: impl AsRef<Path>) -> Result<Vec<f32>, GeomError> {
    let path = path.as_ref();
    let bytes = crate::read_input_file(path)?;
    if bytes.len() < 10 || &bytes[..6] != MAGIC || bytes[6] != 1 {
        return Err(bad(path, "not a version-1 .npy file"));
    }
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let end = 10 + hlen;
    if end > bytes.len() {
        return Err(bad(path, "truncated header"));
    }
    let h = std::str::from_utf8(&bytes[10..end]).map_err(|_| bad(path, "header is not text"))?;
    let header = parse_header(path, h)?;
    if header.descr != "<f4" || header.shape.len() != 1 {
        return Err(bad(path, "expected a 1-D '<f4' array"));
    }
    let n = header.shape[0];
    let data = &bytes[end..];
    let need = n
        .checked_mul(4)
        .filter(|&need| need <= data.len())
        .ok_or_else(|| bad(path, "truncated data"))?;
    Ok(data[..need]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}
