//! Model files: safetensors with named tensors and JSON metadata, shared by SIREN, NGLOD and
//! the hash grid. Weights are f32, NGLOD's grid features and the hash grid's tables f16 (their rounding, a relative 2^-11, is far below a
//! fit's error) and index tensors u32; in memory every value is an `f32`.
//!
//! A PyTorch user loads one with `safetensors.torch.load_file(path)` and gets tensors named and
//! shaped like an `nn.Module`'s state dict (`net.0.weight` as `[out, in]`, row-major); the
//! metadata (`safetensors.safe_open(path, "pt").metadata()`) holds, as strings:
//!
//! | key | value |
//! | --- | --- |
//! | `format` | `"hwsdf"` |
//! | `architecture` | `"siren"`, `"nglod"` or `"hashgrid"` |
//! | `config` | JSON of the architecture's hyperparameters |
//! | `training` | JSON of the training run (loss weights, steps, seed, ...) |
//! | `normalization` | JSON `{"center": [x, y, z], "scale": s}`: `normalized = (p - center) * scale` |
//! | `hwsdf_version` | the crate version that wrote it |
//!
//! Writes are atomic (temporary file in the same directory, then rename), so an interrupted
//! save never leaves a truncated model behind.

use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};

/// Errors reading or writing model files.
///
/// The variants found by checking a model file already in memory against an architecture
/// ([`ModelFileError::MissingTensor`], [`ModelFileError::ShapeMismatch`],
/// [`ModelFileError::WrongArchitecture`], [`ModelFileError::DeclaredSize`], a `config` that does
/// not validate) name no file: [`crate::NeuralSdf::load`] adds it
/// ([`crate::NeuralSdfError::InvalidModel`]).
#[derive(Debug, thiserror::Error)]
pub enum ModelFileError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Not a valid safetensors file.
    #[error("{path}: not a valid safetensors model file: {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A metadata key is missing or malformed.
    #[error("{}metadata `{key}` is missing or invalid{detail}", in_file(.path))]
    Metadata {
        /// The file (empty for a model file in memory, whose messages then name none).
        path: PathBuf,
        /// The key.
        key: &'static str,
        /// Extra detail, starting with ": " when present.
        detail: String,
    },
    /// A tensor the model needs is absent.
    #[error("model file has no tensor `{name}` (it has: {available})")]
    MissingTensor {
        /// Tensor name.
        name: String,
        /// The names present.
        available: String,
    },
    /// A tensor has the wrong shape or type.
    #[error("tensor `{name}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        /// Tensor name.
        name: String,
        /// Shape in the file.
        found: Vec<usize>,
        /// Shape the model needs.
        expected: Vec<usize>,
    },
    /// The file holds another architecture than the one asked for.
    #[error("model file holds a `{found}` model, expected `{expected}`")]
    WrongArchitecture {
        /// Architecture in the file.
        found: String,
        /// Architecture asked for.
        expected: String,
    },
    /// A tensor holds NaN or an infinity: such a model evaluates to garbage everywhere.
    #[error(
        "{}tensor `{name}` value {index} is {value}; a model's weights must be finite",
        in_file(.path)
    )]
    NonFinite {
        /// The file (empty for a model in memory, whose messages then name none).
        path: PathBuf,
        /// The first tensor with a bad value.
        name: String,
        /// Index of that value (row-major).
        index: usize,
        /// The value.
        value: f32,
    },
    /// The configuration declares more parameters than the file's tensors hold; checked before
    /// anything is allocated for them.
    #[error(
        "the `config` metadata declares {declared} parameters but the file's tensors hold {available}"
    )]
    DeclaredSize {
        /// Parameters the configuration needs.
        declared: u64,
        /// Values in the file.
        available: u64,
    },
    /// A tensor's data length does not match its shape (only when building a file in memory).
    #[error("tensor `{name}` has {len} values but shape {shape:?}")]
    BadTensor {
        /// Tensor name.
        name: String,
        /// Number of values.
        len: usize,
        /// Declared shape.
        shape: Vec<usize>,
    },
    /// Two tensors share a name (only when building a file in memory): the file would hold one
    /// of them and a gap where the other's data lies.
    #[error("two tensors are named `{name}`")]
    DuplicateTensor {
        /// Tensor name.
        name: String,
    },
    /// A value its tensor's type cannot hold (only when building a file in memory): an f16
    /// tensor's finite value beyond ±65504, an index that is not an integer in `0..2^24`.
    #[error("tensor `{name}` holds {value}, which {dtype:?} cannot store")]
    Unrepresentable {
        /// Tensor name.
        name: String,
        /// The value.
        value: f32,
        /// The tensor's type.
        dtype: TensorDtype,
    },
}

/// `"path: "` before a message about a file, or nothing for a model file in memory (an empty
/// path): never a bare `": "`.
fn in_file(path: &Path) -> String {
    if path.as_os_str().is_empty() {
        String::new()
    } else {
        format!("{}: ", path.display())
    }
}

pub use sdf_geom::Normalization;

/// The name ending of tensors that hold indices ([`TensorDtype::U32`] in files written now), not
/// parameters.
pub const INDEX_SUFFIX: &str = ".vertices";

/// The JSON form of a normalisation in the file's metadata: the centre as f32 numbers where it
/// is an f32 (every mesh near the origin: the files are as they always were), else as f64 (a
/// mesh loaded far from the origin, whose centre f32 would round).
fn normalization_json(n: &Normalization) -> String {
    let c32 = n.center.as_vec3();
    if c32.as_dvec3() == n.center {
        serde_json::json!({"center": c32.to_array(), "scale": n.scale}).to_string()
    } else {
        serde_json::json!({"center": n.center.to_array(), "scale": n.scale}).to_string()
    }
}

fn normalization_from_json(v: &serde_json::Value) -> Option<Normalization> {
    let c = v.get("center")?.as_array()?;
    if c.len() != 3 {
        return None;
    }
    let mut center = [0.0f64; 3];
    for (dst, src) in center.iter_mut().zip(c) {
        let x = src.as_f64()?;
        // A number written from an f32 is that f32, as it always was read (serde_json may read
        // it an ulp or two of f64 off); one farther from every f32 is an f64 centre.
        let x32 = f64::from(x as f32);
        *dst = if (x32 - x).abs() <= 4.0 * f64::EPSILON * x.abs() {
            x32
        } else {
            x
        };
    }
    Some(Normalization {
        center: glam::DVec3::from_array(center),
        scale: v.get("scale")?.as_f64()? as f32,
    })
}

/// Everything in a model file besides the tensors.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelMetadata {
    /// `"siren"` or `"nglod"`.
    pub architecture: String,
    /// Architecture hyperparameters.
    pub config: serde_json::Value,
    /// Training settings and summary.
    pub training: serde_json::Value,
    /// Mesh-to-model transform.
    pub normalization: Normalization,
    /// Version of hwsdf that wrote the file.
    pub hwsdf_version: String,
}

/// How a tensor is stored in the file. In memory its values are `f32`s that this type holds
/// exactly, so a model evaluates the same before and after a save and a load.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TensorDtype {
    /// 32-bit floats.
    #[default]
    F32,
    /// IEEE 16-bit floats.
    F16,
    /// Unsigned integers below 2^24 (exact as `f32`): indices.
    U32,
}

impl TensorDtype {
    /// Whether a value can be written as this type without turning into another kind of
    /// value: an f16's finite value within its range (rounding is the type's), an index an
    /// integer in `0..2^24`. Non-finite floats pass (a load refuses them, naming the tensor).
    fn holds(self, v: f32) -> bool {
        match self {
            TensorDtype::F32 => true,
            TensorDtype::F16 => !v.is_finite() || half::f16::from_f32(v).is_finite(),
            TensorDtype::U32 => v.fract() == 0.0 && (0.0..=MAX_INDEX as f32).contains(&v),
        }
    }
}

/// One named tensor, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Name, PyTorch state-dict style (`net.0.weight`).
    pub name: String,
    /// Shape, outermost first.
    pub shape: Vec<usize>,
    /// Values, row-major, exactly representable in `dtype`.
    pub data: Vec<f32>,
    /// How the file stores the values.
    pub dtype: TensorDtype,
}

/// The largest integer of a [`TensorDtype::U32`] tensor: every smaller one is exact in `f32`.
pub const MAX_INDEX: u32 = (1 << 24) - 1;

impl Tensor {
    /// An f32 tensor.
    pub fn f32(name: impl Into<String>, shape: Vec<usize>, data: Vec<f32>) -> Self {
        Tensor {
            name: name.into(),
            shape,
            data,
            dtype: TensorDtype::F32,
        }
    }

    /// A tensor stored as f16, its values rounded to the nearest f16 here. Values beyond f16's
    /// range (±65504) would become infinities: such a tensor stays f32.
    pub fn f16(name: impl Into<String>, shape: Vec<usize>, data: Vec<f32>) -> Self {
        if data.iter().any(|v| v.abs() > f32::from(half::f16::MAX)) {
            return Tensor::f32(name, shape, data);
        }
        Tensor {
            name: name.into(),
            shape,
            data: data
                .into_iter()
                .map(|v| half::f16::from_f32(v).to_f32())
                .collect(),
            dtype: TensorDtype::F16,
        }
    }

    /// A tensor of indices, each at most [`MAX_INDEX`] (larger ones are clamped to it).
    pub fn indices(name: impl Into<String>, shape: Vec<usize>, data: &[u32]) -> Self {
        Tensor {
            name: name.into(),
            shape,
            data: data.iter().map(|&v| v.min(MAX_INDEX) as f32).collect(),
            dtype: TensorDtype::U32,
        }
    }
}

/// What a file that is not a model looks like, from its first bytes: a mesh passed where the
/// model goes is the likely mistake.
fn looks_like(bytes: &[u8]) -> Option<&'static str> {
    let text = bytes
        .iter()
        .take(512)
        .all(|&b| b.is_ascii_graphic() || b.is_ascii_whitespace());
    match bytes {
        [] => Some("an empty file"),
        [b'g', b'l', b'T', b'F', ..] => Some("a binary glTF (.glb) mesh"),
        _ if bytes.trim_ascii_start().starts_with(b"{") => Some("JSON, a glTF mesh perhaps"),
        _ if text => Some("a text file, an OBJ mesh perhaps"),
        _ => None,
    }
}

/// A model file in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelFile {
    /// Metadata.
    pub metadata: ModelMetadata,
    /// Tensors; [`ModelFile::load`] returns them sorted by name.
    pub tensors: Vec<Tensor>,
}

/// Largest model file read, in bytes (2 GiB): thousands of times the presets' files (under
/// 600 kB, three times that for a checkpoint with its optimiser moments), so that a path to a
/// huge file fails at once instead of being read whole into memory.
pub const MAX_MODEL_FILE_BYTES: u64 = 2 << 30;

/// Largest metadata value (`config`, `training`, ...) a model file may hold, in bytes of JSON
/// text: hundreds of times what hwsdf writes (about 1 kB), and small enough that reading one
/// parses into tens of megabytes at most.
pub const MAX_METADATA_BYTES: usize = 1 << 20;

/// The error for a metadata value of `len` bytes, above [`MAX_METADATA_BYTES`].
fn oversized(key: &'static str, len: usize, path: &Path) -> ModelFileError {
    ModelFileError::Metadata {
        path: path.to_owned(),
        key,
        detail: format!(
            ": {len} bytes of JSON, more than the {MAX_METADATA_BYTES} a model file may hold"
        ),
    }
}

/// The crate version written into new files.
pub const HWSDF_VERSION: &str = env!("CARGO_PKG_VERSION");

impl ModelFile {
    /// The file's bytes in safetensors format.
    ///
    /// The header is written here rather than by `safetensors::serialize`, whose metadata map
    /// has no fixed order: the same model always gives the same bytes. Tensors are laid out in
    /// name order, f16 ones last; keys in the JSON header are sorted.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ModelFileError> {
        let mut tensors: Vec<&Tensor> = self.tensors.iter().collect();
        // 4-byte tensors before the f16 ones, so that every tensor starts aligned to its type
        // (the format forbids gaps to pad with), each group in name order.
        tensors.sort_by_key(|t| (t.dtype == TensorDtype::F16, t.name.clone()));
        let m = &self.metadata;
        // Nothing is written that could not be read back.
        let (config, training) = (m.config.to_string(), m.training.to_string());
        for (key, text) in [("config", &config), ("training", &training)] {
            if text.len() > MAX_METADATA_BYTES {
                return Err(oversized(key, text.len(), Path::new("")));
            }
        }
        let mut header = serde_json::Map::new();
        header.insert(
            "__metadata__".into(),
            serde_json::json!({
                "format": "hwsdf",
                "architecture": m.architecture,
                "config": config,
                "training": training,
                "normalization": normalization_json(&m.normalization),
                "hwsdf_version": m.hwsdf_version,
            }),
        );
        let mut offset = 0usize;
        for t in &tensors {
            if t.shape.iter().product::<usize>() != t.data.len() || t.name == "__metadata__" {
                return Err(ModelFileError::BadTensor {
                    name: t.name.clone(),
                    len: t.data.len(),
                    shape: t.shape.clone(),
                });
            }
            if header.contains_key(&t.name) {
                return Err(ModelFileError::DuplicateTensor {
                    name: t.name.clone(),
                });
            }
            if let Some(&value) = t.data.iter().find(|&&v| !t.dtype.holds(v)) {
                return Err(ModelFileError::Unrepresentable {
                    name: t.name.clone(),
                    value,
                    dtype: t.dtype,
                });
            }
            let (dtype, size) = match t.dtype {
                TensorDtype::F32 => ("F32", 4),
                TensorDtype::F16 => ("F16", 2),
                TensorDtype::U32 => ("U32", 4),
            };
            let end = offset + size * t.data.len();
            header.insert(
                t.name.clone(),
                serde_json::json!({"dtype": dtype, "shape": t.shape, "data_offsets": [offset, end]}),
            );
            offset = end;
        }
        let mut json = serde_json::Value::Object(header).to_string().into_bytes();
        // The format pads the header with spaces so the data starts 8-byte aligned.
        json.resize(json.len().next_multiple_of(8), b' ');
        let mut out = Vec::with_capacity(8 + json.len() + offset);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        for t in tensors {
            for &v in &t.data {
                match t.dtype {
                    TensorDtype::F32 => out.extend_from_slice(&v.to_le_bytes()),
                    TensorDtype::F16 => {
                        out.extend_from_slice(&half::f16::from_f32(v).to_le_bytes())
                    }
                    TensorDtype::U32 => out.extend_from_slice(&(v as u32).to_le_bytes()),
                }
            }
        }
        Ok(out)
    }

    /// Writes the file atomically.
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        let bytes = self.to_bytes()?;
        write_atomic(path, &bytes).map_err(|source| ModelFileError::Io {
            path: path.to_owned(),
            source,
        })
    }

    /// Reads and checks a file: a regular file of at most [`MAX_MODEL_FILE_BYTES`], safetensors
    /// structure, finite f32 tensors, and the metadata keys.
    pub fn load(path: &Path) -> Result<Self, ModelFileError> {
        let bytes =
            sdf_geom::io::read_regular_file(path, MAX_MODEL_FILE_BYTES).map_err(|source| {
                ModelFileError::Io {
                    path: path.to_owned(),
                    source,
                }
            })?;
        Self::from_bytes(&bytes, path)
    }

    /// Parses a file's bytes; `path` is only used in error messages.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, ModelFileError> {
        let corrupt = |reason: String| ModelFileError::Corrupt {
            path: path.to_owned(),
            reason,
        };
        // A safetensors file is an 8-byte header length, then the JSON header. Say what another
        // kind of file looks like instead of "header too large" from its first 8 bytes.
        if bytes.get(8) != Some(&b'{') {
            return Err(corrupt(match looks_like(bytes) {
                Some(kind) => format!("no safetensors header (it looks like {kind})"),
                None => "no safetensors header".to_owned(),
            }));
        }
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| corrupt(e.to_string()))?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| corrupt(e.to_string()))?;
        let metadata = metadata_from_header(header.metadata().clone().unwrap_or_default(), path)?;
        let mut tensors = st
            .tensors()
            .into_iter()
            .map(|(name, view)| tensor_from_view(name, &view, path))
            .collect::<Result<Vec<_>, _>>()?;
        tensors.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(ModelFile { metadata, tensors })
    }

    /// The values of tensor `name`, checked to have exactly `shape`.
    pub fn tensor(&self, name: &str, shape: &[usize]) -> Result<&[f32], ModelFileError> {
        let t = self.find(name)?;
        if t.shape != shape {
            return Err(ModelFileError::ShapeMismatch {
                name: name.to_owned(),
                found: t.shape.clone(),
                expected: shape.to_vec(),
            });
        }
        Ok(&t.data)
    }

    /// The length of the one-dimensional tensor `name` (whose size the file, not the
    /// configuration, decides: a sparse level's vertex list).
    pub fn tensor_len(&self, name: &str) -> Result<usize, ModelFileError> {
        let t = self.find(name)?;
        match t.shape[..] {
            [n] => Ok(n),
            _ => Err(ModelFileError::ShapeMismatch {
                name: name.to_owned(),
                found: t.shape.clone(),
                expected: vec![t.data.len()],
            }),
        }
    }

    fn find(&self, name: &str) -> Result<&Tensor, ModelFileError> {
        self.tensors
            .iter()
            .find(|t| t.name == name)
            .ok_or_else(|| ModelFileError::MissingTensor {
                name: name.to_owned(),
                available: self
                    .tensors
                    .iter()
                    .map(|t| t.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// Errors unless the file holds `architecture`.
    pub fn expect_architecture(&self, architecture: &str) -> Result<(), ModelFileError> {
        if self.metadata.architecture == architecture {
            Ok(())
        } else {
            Err(ModelFileError::WrongArchitecture {
                found: self.metadata.architecture.clone(),
                expected: architecture.to_owned(),
            })
        }
    }

    /// Errors unless the tensors hold at least `declared` values: a configuration claiming more
    /// parameters than the file has cannot match it, and is refused before its size is allocated.
    pub fn ensure_holds(&self, declared: u64) -> Result<(), ModelFileError> {
        let available = self.param_count() as u64;
        if declared > available {
            return Err(ModelFileError::DeclaredSize {
                declared,
                available,
            });
        }
        Ok(())
    }

    /// Errors on the first tensor value that is NaN or infinite (a trained model about to be
    /// saved, or one built in memory).
    pub fn check_finite(&self) -> Result<(), ModelFileError> {
        for t in &self.tensors {
            if let Some(index) = t.data.iter().position(|v| !v.is_finite()) {
                return Err(ModelFileError::NonFinite {
                    path: PathBuf::new(),
                    name: t.name.clone(),
                    index,
                    value: t.data[index],
                });
            }
        }
        Ok(())
    }

    /// Total number of parameters: the values of every tensor but the index tensors (names
    /// ending in [`INDEX_SUFFIX`], a sparse NGLOD level's vertex list), which are not trained.
    pub fn param_count(&self) -> usize {
        self.tensors
            .iter()
            .filter(|t| !t.name.ends_with(INDEX_SUFFIX))
            .map(|t| t.data.len())
            .sum()
    }
}

/// The metadata of a model file's header, checked: the format, the normalisation (finite, and
/// mapping the box to finite coordinates) and the keys every model file has.
fn metadata_from_header(
    meta: std::collections::HashMap<String, String>,
    path: &Path,
) -> Result<ModelMetadata, ModelFileError> {
    let get = |key: &'static str| {
        meta.get(key).ok_or_else(|| ModelFileError::Metadata {
            path: path.to_owned(),
            key,
            detail: String::new(),
        })
    };
    let parse = |key: &'static str| -> Result<serde_json::Value, ModelFileError> {
        let text = get(key)?;
        // Parsed, a JSON text takes up to 16 times its bytes (`[0,0,…]`: 32 bytes a value for
        // every 2 characters): a 100 MB header would become gigabytes before any check.
        if text.len() > MAX_METADATA_BYTES {
            return Err(oversized(key, text.len(), path));
        }
        serde_json::from_str(text).map_err(|e| ModelFileError::Metadata {
            path: path.to_owned(),
            key,
            detail: format!(": {e}"),
        })
    };
    if get("format")? != "hwsdf" {
        return Err(ModelFileError::Metadata {
            path: path.to_owned(),
            key: "format",
            detail: ": not written by hwsdf".into(),
        });
    }
    let normalization = normalization_from_json(&parse("normalization")?).ok_or_else(|| {
        ModelFileError::Metadata {
            path: path.to_owned(),
            key: "normalization",
            detail: ": expected {\"center\": [x, y, z], \"scale\": s}".into(),
        }
    })?;
    // The box [-1, 1]³ must map back to finite coordinates: a scale of 1e-45 or a centre
    // near f32::MAX would put every extracted vertex and evaluated distance at infinity.
    let half = 1.0 / normalization.scale;
    let corner = (normalization.center.abs() + half as f64).as_vec3();
    if !normalization.scale.is_finite()
        || normalization.scale <= 0.0
        || !normalization.center.is_finite()
        || !half.is_finite()
        || !corner.is_finite()
    {
        return Err(ModelFileError::Metadata {
            path: path.to_owned(),
            key: "normalization",
            detail: ": center must be finite, scale finite and positive, and the box they map [-1, 1]³ to finite in float32".into(),
        });
    }
    Ok(ModelMetadata {
        architecture: get("architecture")?.clone(),
        config: parse("config")?,
        training: parse("training")?,
        normalization,
        hwsdf_version: get("hwsdf_version")?.clone(),
    })
}

/// One tensor of a model file, checked: a dtype we write, indices in range, finite values.
fn tensor_from_view(
    name: String,
    view: &safetensors::tensor::TensorView<'_>,
    path: &Path,
) -> Result<Tensor, ModelFileError> {
    let corrupt = |reason: String| ModelFileError::Corrupt {
        path: path.to_owned(),
        reason,
    };
    let bytes = view.data();
    let (data, dtype): (Vec<f32>, _) = match view.dtype() {
        Dtype::F32 => (bytemuck::pod_collect_to_vec(bytes), TensorDtype::F32),
        Dtype::F16 => (
            bytes
                .chunks_exact(2)
                .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            TensorDtype::F16,
        ),
        Dtype::U32 => {
            let ints: Vec<u32> = bytemuck::pod_collect_to_vec(bytes);
            if let Some(v) = ints.iter().find(|&&v| v > MAX_INDEX) {
                return Err(corrupt(format!(
                    "tensor `{name}` holds the index {v}, above {MAX_INDEX}"
                )));
            }
            (ints.iter().map(|&v| v as f32).collect(), TensorDtype::U32)
        }
        other => {
            return Err(corrupt(format!(
                "tensor `{name}` is {other:?}; hwsdf models hold F32, F16 and U32 tensors"
            )));
        }
    };
    if let Some(index) = data.iter().position(|v| !v.is_finite()) {
        return Err(ModelFileError::NonFinite {
            path: path.to_owned(),
            value: data[index],
            name,
            index,
        });
    }
    Ok(Tensor {
        shape: view.shape().to_vec(),
        data,
        name,
        dtype,
    })
}

pub use sdf_geom::io::write_atomic;

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> ModelFile {
        ModelFile {
            metadata: ModelMetadata {
                architecture: "siren".into(),
                config: serde_json::json!({"hidden": [4, 4], "omega0": 30.0}),
                training: serde_json::json!({"steps": 3}),
                normalization: Normalization {
                    center: glam::Vec3::new(0.5, -1.0, 2.0).as_dvec3(),
                    scale: 0.25,
                },
                hwsdf_version: HWSDF_VERSION.into(),
            },
            tensors: vec![
                // Odd-sized f16 data: the f32 tensors must still start 4-byte aligned.
                Tensor::f16("grids.0", vec![5], vec![0.1, -3.0e-7, 1.0e5, 65504.0, -0.0]),
                Tensor::indices("grids.0.vertices", vec![3], &[0, 7, MAX_INDEX]),
                Tensor::f32(
                    "net.0.bias",
                    vec![4],
                    vec![0.1, -0.2, f32::MIN_POSITIVE, -0.0],
                ),
                Tensor::f32(
                    "net.0.weight",
                    vec![4, 3],
                    (0..12).map(|i| i as f32 * 0.37 - 1.0).collect(),
                ),
            ],
        }
    }

    /// A centre that is an f32 is written and read as the f32 it is (files as they always
    /// were); one that is not (a mesh far from the origin) keeps its f64 digits.
    #[test]
    fn normalisation_centres_keep_their_precision() {
        let p = Path::new("n.safetensors");
        for center in [
            glam::Vec3::new(0.1, -1.3e-5, 7.25).as_dvec3(),
            glam::DVec3::new(1e7 + 0.123456789, -2e7 - 1e-3, 3e7 + 0.5),
        ] {
            let mut f = sample();
            f.metadata.normalization.center = center;
            let back = ModelFile::from_bytes(&f.to_bytes().unwrap(), p).unwrap();
            let got = back.metadata.normalization.center;
            if center.as_vec3().as_dvec3() == center {
                assert_eq!(got, center);
            } else {
                // serde_json reads f64 to within an ulp or two.
                assert!((got - center).abs().max_element() < 1e-8, "{got} {center}");
                assert_ne!(got.as_vec3().as_dvec3(), got);
            }
        }
        // An f32 centre is written as it always was (its f32 values).
        let c = glam::Vec3::new(0.1, 0.2, 0.3);
        let json = normalization_json(&Normalization {
            center: c.as_dvec3(),
            scale: 1.0,
        });
        let before = serde_json::json!({"center": c.to_array(), "scale": 1.0f32}).to_string();
        assert_eq!(json, before);
    }

    #[test]
    fn round_trips_bit_for_bit() {
        let dir = std::env::temp_dir().join(format!("hwsdf-mf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.safetensors");
        let file = sample();
        file.save(&path).unwrap();
        let back = ModelFile::load(&path).unwrap();
        assert_eq!(back, file);
        for (a, b) in back.tensors.iter().zip(&file.tensors) {
            let (a, b): (Vec<u32>, Vec<u32>) = (
                a.data.iter().map(|x| x.to_bits()).collect(),
                b.data.iter().map(|x| x.to_bits()).collect(),
            );
            assert_eq!(a, b);
        }
        // Deterministic bytes: saving what was loaded gives the same file.
        assert_eq!(std::fs::read(&path).unwrap(), back.to_bytes().unwrap());
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn tensor_lookup_checks_name_and_shape() {
        let f = sample();
        assert_eq!(f.tensor("net.0.bias", &[4]).unwrap().len(), 4);
        assert!(matches!(
            f.tensor("net.0.bias", &[5]),
            Err(ModelFileError::ShapeMismatch { .. })
        ));
        let err = f.tensor("net.9.weight", &[1]).unwrap_err();
        assert!(err.to_string().contains("net.0.weight"), "{err}");
        assert!(f.expect_architecture("nglod").is_err());
        // The index tensor is not counted.
        assert_eq!(f.param_count(), 21);
    }

    #[test]
    fn f16_and_index_tensors_keep_what_they_can_store() {
        // 1e5 is beyond f16's range: that tensor stays f32 rather than holding an infinity.
        let big = Tensor::f16("g", vec![2], vec![0.1, 1.0e5]);
        assert_eq!(big.dtype, TensorDtype::F32);
        assert_eq!(big.data, [0.1, 1.0e5]);
        let t = Tensor::f16("g", vec![3], vec![0.1, 1.0 / 3.0, -2.5]);
        assert_eq!(t.dtype, TensorDtype::F16);
        assert_eq!(t.data[2], -2.5);
        for (&stored, want) in t.data.iter().zip([0.1f32, 1.0 / 3.0]) {
            assert!(stored != want && (stored - want).abs() <= want * 2f32.powi(-11));
        }
        let f = sample();
        assert_eq!(
            f.tensors[0].dtype,
            TensorDtype::F32,
            "1e5 kept the tensor f32"
        );
        assert_eq!(
            Tensor::indices("i", vec![1], &[u32::MAX]).data,
            [MAX_INDEX as f32]
        );
        // The bytes: f16 tensors last, each tensor's offset a multiple of its element size.
        let mut g = sample();
        g.tensors[0] = Tensor::f16("grids.0", vec![5], vec![0.5; 5]);
        let bytes = g.to_bytes().unwrap();
        let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
        let infos = header.tensors();
        let f16_start = infos["grids.0"].data_offsets.0;
        for (name, info) in &infos {
            let size = if name == "grids.0" { 2 } else { 4 };
            assert_eq!(info.data_offsets.0 % size, 0, "{name}");
            if name != "grids.0" {
                assert!(
                    info.data_offsets.1 <= f16_start,
                    "{name} after the f16 tensor"
                );
            }
        }
        let back = ModelFile::from_bytes(&bytes, Path::new("g")).unwrap();
        assert_eq!(back, g);
        // A u32 index above 2^24 - 1 is not exact as f32: refused.
        let mut over = bytes.clone();
        let at = 8
            + u64::from_le_bytes(over[..8].try_into().unwrap()) as usize
            + infos["grids.0.vertices"].data_offsets.0;
        over[at..at + 4].copy_from_slice(&(MAX_INDEX + 1).to_le_bytes());
        assert!(matches!(
            ModelFile::from_bytes(&over, Path::new("g")),
            Err(ModelFileError::Corrupt { .. })
        ));
    }

    #[test]
    fn corrupt_files_are_typed_errors() {
        let p = Path::new("x.safetensors");
        let good = sample().to_bytes().unwrap();
        for bad in [
            &b""[..],
            &b"garbage"[..],
            &good[..good.len() - 3],
            &good[..20],
        ] {
            assert!(
                matches!(
                    ModelFile::from_bytes(bad, p),
                    Err(ModelFileError::Corrupt { .. })
                ),
                "{} bytes",
                bad.len()
            );
        }
        // A valid safetensors file that hwsdf did not write.
        let view = safetensors::tensor::TensorView::new(Dtype::F32, vec![1], &[0u8; 4]).unwrap();
        let foreign = safetensors::serialize([("w", view)], None).unwrap();
        assert!(matches!(
            ModelFile::from_bytes(&foreign, p),
            Err(ModelFileError::Metadata { key: "format", .. })
        ));
        // Bad normalisation: no scale, or a box [-1, 1]³ that maps to infinity (a subnormal
        // scale, or a centre whose box passes f32::MAX).
        for (center, scale) in [
            (glam::DVec3::ZERO, 0.0),
            (glam::DVec3::ZERO, 1e-45),
            (glam::DVec3::new(3.4e38, 0.0, 0.0), 1e-38),
        ] {
            let mut f = sample();
            f.metadata.normalization.scale = scale;
            f.metadata.normalization.center = center;
            assert!(
                matches!(
                    ModelFile::from_bytes(&f.to_bytes().unwrap(), p),
                    Err(ModelFileError::Metadata {
                        key: "normalization",
                        ..
                    })
                ),
                "{center} {scale}"
            );
        }
        let missing = ModelFile::load(Path::new("/nonexistent/model.safetensors")).unwrap_err();
        assert!(matches!(missing, ModelFileError::Io { .. }));
    }

    /// A metadata value too large to parse safely is refused, reading and writing, by name.
    #[test]
    fn oversized_metadata_is_refused_before_it_is_parsed() {
        let mut f = sample();
        f.metadata.training = serde_json::json!(vec![0; MAX_METADATA_BYTES / 2]);
        assert!(matches!(
            f.to_bytes(),
            Err(ModelFileError::Metadata {
                key: "training",
                ..
            })
        ));
        // A file written by another tool: the same header with the array spliced in.
        let small = sample().to_bytes().unwrap();
        let json_len = u64::from_le_bytes(small[..8].try_into().unwrap()) as usize;
        let mut header: serde_json::Value =
            serde_json::from_slice(&small[8..8 + json_len]).unwrap();
        header["__metadata__"]["training"] = f.metadata.training.to_string().into();
        let mut json = header.to_string().into_bytes();
        json.resize(json.len().next_multiple_of(8), b' ');
        let mut big = (json.len() as u64).to_le_bytes().to_vec();
        big.extend_from_slice(&json);
        big.extend_from_slice(&small[8 + json_len..]);
        let err = ModelFile::from_bytes(&big, Path::new("x.safetensors")).unwrap_err();
        assert!(
            matches!(
                err,
                ModelFileError::Metadata {
                    key: "training",
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().contains("more than the 1048576"), "{err}");
    }

    #[test]
    fn non_finite_values_name_the_tensor() {
        let p = Path::new("x.safetensors");
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut f = sample();
            f.tensors[3].data[5] = bad;
            let err = ModelFile::from_bytes(&f.to_bytes().unwrap(), p).unwrap_err();
            match &err {
                ModelFileError::NonFinite { name, index, .. } => {
                    assert_eq!((name.as_str(), *index), ("net.0.weight", 5))
                }
                other => panic!("{other:?}"),
            }
            assert!(f.check_finite().is_err());
        }
        sample().check_finite().unwrap();
    }

    /// Errors about a model file in memory (no path) name no file, and do not start with the
    /// `": "` an empty path used to leave; those about a file name it.
    #[test]
    fn a_mesh_passed_as_a_model_is_named_for_what_it_is() {
        let p = Path::new("m.safetensors");
        for (bytes, says) in [
            (
                &b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"[..],
                "a text file, an OBJ mesh perhaps",
            ),
            (
                b"glTF\x02\x00\x00\x00\x10\x00\x00\x00",
                "a binary glTF (.glb) mesh",
            ),
            (
                b"  {\"asset\": {\"version\": \"2.0\"}}",
                "JSON, a glTF mesh perhaps",
            ),
            (b"", "an empty file"),
        ] {
            let msg = ModelFile::from_bytes(bytes, p).unwrap_err().to_string();
            assert!(
                msg.contains("no safetensors header (it looks like"),
                "{msg}"
            );
            assert!(msg.contains(says), "{msg}");
        }
        let msg = ModelFile::from_bytes(&[0xff; 64], p)
            .unwrap_err()
            .to_string();
        assert!(msg.ends_with("no safetensors header"), "{msg}");
        // A real file still parses.
        let f = sample();
        assert!(ModelFile::from_bytes(&f.to_bytes().unwrap(), p).is_ok());
    }

    #[test]
    fn messages_name_the_file_only_when_there_is_one() {
        let mut f = sample();
        f.tensors[2].data[1] = f32::NAN;
        let msg = f.check_finite().unwrap_err().to_string();
        assert!(
            msg.starts_with("tensor `net.0.bias` value 1 is NaN"),
            "{msg}"
        );
        let metadata = |path: &str| ModelFileError::Metadata {
            path: PathBuf::from(path),
            key: "config",
            detail: ": width 0".into(),
        };
        assert_eq!(
            metadata("").to_string(),
            "metadata `config` is missing or invalid: width 0"
        );
        assert_eq!(
            metadata("m.safetensors").to_string(),
            "m.safetensors: metadata `config` is missing or invalid: width 0"
        );
        let msg = ModelFile::from_bytes(&f.to_bytes().unwrap(), Path::new("m.safetensors"))
            .unwrap_err()
            .to_string();
        assert!(
            msg.starts_with("m.safetensors: tensor `net.0.bias`"),
            "{msg}"
        );
    }

    #[test]
    fn declared_sizes_are_checked_against_the_tensors() {
        let f = sample();
        f.ensure_holds(21).unwrap();
        assert!(matches!(
            f.ensure_holds(4096 * 4096 * 64),
            Err(ModelFileError::DeclaredSize { available: 21, .. })
        ));
    }

    #[test]
    fn inconsistent_tensor_is_rejected_before_writing() {
        let mut f = sample();
        f.tensors[0].data.pop();
        assert!(matches!(
            f.to_bytes(),
            Err(ModelFileError::BadTensor { .. })
        ));
    }

    /// A file that would not load back, or would load other values, is refused before writing:
    /// two tensors of one name (the header kept one and left a gap), an f16 beyond its range
    /// (written as infinity), an index that is no integer (written truncated).
    #[test]
    fn unwritable_tensors_are_rejected_before_writing() {
        let mut f = sample();
        let twin = f.tensors[0].clone();
        f.tensors.push(twin.clone());
        assert!(matches!(
            f.to_bytes(),
            Err(ModelFileError::DuplicateTensor { name }) if name == twin.name
        ));
        for (dtype, value) in [
            (TensorDtype::F16, 70_000.0),
            (TensorDtype::U32, 2.5),
            (TensorDtype::U32, -1.0),
            (TensorDtype::U32, 16_777_216.0),
        ] {
            let mut f = sample();
            f.tensors.push(Tensor {
                name: "extra".into(),
                shape: vec![2],
                data: vec![1.0, value],
                dtype,
            });
            assert!(
                matches!(
                    f.to_bytes(),
                    Err(ModelFileError::Unrepresentable { value: v, .. }) if v == value
                ),
                "{dtype:?} {value}"
            );
        }
        // What each type holds still writes and reads back.
        let mut f = sample();
        for (name, dtype, data) in [
            ("half", TensorDtype::F16, vec![65504.0, -0.5]),
            ("index", TensorDtype::U32, vec![0.0, 16_777_215.0]),
        ] {
            f.tensors.push(Tensor {
                name: name.into(),
                shape: vec![2],
                data,
                dtype,
            });
        }
        let back = ModelFile::from_bytes(&f.to_bytes().unwrap(), Path::new("")).unwrap();
        assert_eq!(back.tensors.len(), f.tensors.len());
    }
}
