//! Reading glTF accessors, validated before a byte is read: buffer views against their buffers,
//! elements against their views, sparse substitution, and the decoding of VEC3 elements (float32
//! or `KHR_mesh_quantization` integers).

use std::path::Path;
use std::rc::Rc;

use glam::Vec3;

use super::MAX_INSTANCED_TRIANGLES;
use crate::GeomError;

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
pub(super) fn read_accessor<'b>(
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
pub(super) struct Vec3Format {
    ty: gltf::accessor::DataType,
    normalized: bool,
}

impl Vec3Format {
    /// `acc`'s format, if it is a VEC3 of one of those types.
    pub(super) fn of(acc: &gltf::Accessor) -> Option<Self> {
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
    pub(super) fn described(acc: &gltf::Accessor, what: &str) -> Result<Self, String> {
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
    pub(super) fn read(
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
pub(super) fn component(ty: gltf::accessor::DataType, normalized: bool, b: &[u8], k: usize) -> f32 {
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
pub(super) fn vec3_format(
    path: &Path,
    acc: &gltf::Accessor,
    what: &str,
) -> Result<Vec3Format, GeomError> {
    Vec3Format::described(acc, what).map_err(|feature| GeomError::Unsupported {
        path: path.to_path_buf(),
        feature,
    })
}
