//! NGLOD (Takikawa et al. 2021): K levels of 3D feature grids, each trilinearly interpolated,
//! summed, and decoded by a one-hidden-layer ReLU MLP:
//!
//! `sdf(x) = W1 · relu(W0 · Σ_{l<k} Z_l(x) + b0) + b1`
//!
//! where `Z_l(x)` interpolates the `(r_l + 1)³` vertex features of level `l` (a grid of `r_l`
//! cells per axis over the normalised box `[-1, 1]³`; points outside are clamped to the box) and
//! `k ≤ K` is the level of detail: evaluating with the first `k` levels gives a coarser SDF.
//!
//! The coarse levels are dense, as the design document specifies. The finest
//! [`NglodConfig::sparse_levels`] may be sparse, as in NGLOD's own octree: they keep features only
//! at the vertices of the cells near the surface (a [`Band`], placed from the mesh before
//! training), so a fine level costs storage in proportion to the surface's area.
//!
//! The same model family holds instant-ngp's **multiresolution hash grid** (Müller et al. 2022),
//! NGLOD's successor in the design document: with [`Encoding::Hashed`] the levels' features are
//! concatenated rather than summed (`z = [Z_0(x), …, Z_{K-1}(x)]`, `K·F` values), and a level
//! whose `(r_l + 1)³` vertices do not fit its table of `T` entries keeps `T` entries that its
//! vertices share through the spatial hash `(ix ⊕ iy·2654435761 ⊕ iz·805459861) mod T`
//! ([`hash_vertex`]). Its presets are [`NglodConfig::hashgrid_default`] and
//! [`NglodConfig::hashgrid_small`]; its model files say `architecture = "hashgrid"`. The
//! kernels, the trainer, serving and scenes are shared: one grid lookup, one MLP.
//!
//! - [`Nglod`]: the model with its parameters in one flat `f32` vector (CPU evaluation, model files);
//! - [`cpu`]: the f64 reference of the forward pass, loss and gradients;
//! - [`NglodGpu`]: the WGSL kernels' host (inference and gradients);
//! - [`NglodTrainer`]: the training loop with sampling overlapped with GPU work.
//!
//! # Parameter layout
//! One flat vector, in this order (the GPU buffer, Adam's state and the model file share it):
//! grid 0, grid 1, …, grid K-1, then `W0` (`H×F`, row-major), `b0` (`H`), `W1` (`H`), `b1` (1).
//! A dense grid `l` is `[r_l+1, r_l+1, r_l+1, F]` row-major, indexed `[ix, iy, iz, f]`: vertex `ix`
//! sits at `x = -1 + 2·ix/r_l`. A sparse grid is `[n, F]` for the `n` vertices of its band, in
//! the band's order.

mod band;
mod config;
pub mod cpu;
pub(crate) mod gpu;
mod pool;
mod train;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gpu::GpuError;
use crate::model_file::{
    INDEX_SUFFIX, MAX_INDEX, ModelFile, ModelFileError, ModelMetadata, Normalization, Tensor,
};

pub use band::Band;
pub use config::{Encoding, LevelStorage, NglodConfig, ParamLayout, hash_vertex};
pub use gpu::{NglodGpu, ScatterMode};
pub use pool::PoolSchedule;
pub use train::{
    DEFAULT_EPOCHS, DistanceMode, EpochStats, HASHGRID_EPOCHS, NglodTrainConfig, NglodTrainer,
    SampleSource, TimeBudget, TrainReport,
};

/// Largest number of levels the kernels accept (instant-ngp's 16).
pub const MAX_LEVELS: usize = 16;
/// Largest input of the MLP the kernels accept (private arrays in the shaders): `F` summed, or
/// `K·F` concatenated.
pub const MAX_FEATURE_DIM: u32 = 32;
/// Smallest and largest `log2` of a hash grid's table size ([`Encoding::Hashed`]): 2¹⁰ to 2²⁴
/// entries per level.
pub const HASH_TABLE_LOG2: std::ops::RangeInclusive<u32> = 10..=24;
/// The largest resolution of a hashed level: its vertex coordinates are hashed as u32, and a
/// finer grid than 4096 cells over the box resolves nothing a table of 2²⁴ entries could hold.
pub const MAX_HASHED_RESOLUTION: u32 = 4096;
/// Largest MLP (`H·F + 2H + 1` floats) the kernels keep in workgroup memory (15 KiB).
pub const MAX_MLP_FLOATS: u32 = 3840;
/// Largest resolution of a sparse level: a model file's tensors are f32 in memory, exact for
/// vertex indices up to [`MAX_INDEX`] = 256³ − 1.
pub const MAX_SPARSE_RESOLUTION: u32 = 255;
/// Most entries of all sparse levels' vertex tables together (128 MiB of u32): two levels of 255
/// cells.
pub const MAX_TABLE_ENTRIES: u64 = 1 << 25;
/// A sparse level's table entry for a vertex that holds no features (the kernels test for it).
pub(crate) const NO_SLOT: u32 = u32::MAX;
/// How far a sparse level reaches by default ([`NglodConfig::band_cells`]): the cells whose
/// centre lies within this many cell widths plus half a cell diagonal of the surface hold
/// features. 0 keeps only the cells the surface can pass through, as NGLOD's own octree does:
/// every point on the surface interpolates eight real corners, and points off it fall back on
/// the dense levels sooner.
///
/// Why 0: over the 20 shared meshes at the GPU default's 100 epochs it fits within 0.001 of the
/// old band of 1 on average (F1 0.9966 / 0.9814 against 0.9969 / 0.9820) for 15-30 % smaller
/// files (median 0.56 MB against 0.71 MB), docs/benchmarks "Band width".
pub const DEFAULT_BAND_CELLS: u32 = 0;
/// The band of every model file written before the band width was a setting.
const LEGACY_BAND_CELLS: u32 = 1;
/// The widest band [`NglodConfig::validate`] accepts, in cells beyond those the surface can pass
/// through: wider bands approach a dense level at a sparse level's per-vertex cost.
pub const MAX_BAND_CELLS: u32 = 4;

/// Errors of the NGLOD model, its kernels and its trainer.
#[derive(Debug, thiserror::Error)]
pub enum NglodError {
    /// The configuration is outside what the model or the kernels support.
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
    /// A level of detail outside `1..=levels`.
    #[error("level of detail {requested} is out of range: the model has levels 1..={levels}")]
    InvalidLod {
        /// The requested number of levels.
        requested: usize,
        /// The model's number of levels.
        levels: usize,
    },
    /// Slices that must have matching lengths do not.
    #[error("{what}: expected {expected} values, got {got}")]
    LengthMismatch {
        /// What was being checked.
        what: &'static str,
        /// The expected length.
        expected: usize,
        /// The given length.
        got: usize,
    },
    /// Training produced a non-finite loss.
    #[error(
        "training diverged at epoch {epoch}, step {step}: loss is {loss} (try a lower learning rate)"
    )]
    Diverged {
        /// Epoch (0-based).
        epoch: usize,
        /// Step within the run (0-based).
        step: usize,
        /// The non-finite loss.
        loss: f32,
    },
    /// The mesh cannot be trained on (no area, no triangles).
    #[error("cannot train on this mesh: {0}")]
    BadMesh(String),
    /// A GPU error.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// A geometry error (building the distance query).
    #[error(transparent)]
    Geom(#[from] sdf_geom::GeomError),
    /// A model-file error.
    #[error(transparent)]
    ModelFile(#[from] ModelFileError),
    /// The GPU sampler's error ([`SampleSource::Gpu`]).
    #[error(transparent)]
    Sample(#[from] crate::ground_truth::SampleError),
    /// Labelling the samples on the GPU failed: a mesh too large or too deep for the GPU
    /// ground truth.
    #[error("ground truth: {0}")]
    GroundTruth(#[from] crate::ground_truth::GroundTruthError),
}

/// Which loss the trainer and the gradient kernels minimise.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Objective {
    /// MSE of the full model (all K levels).
    #[default]
    Full,
    /// NGLOD's objective: the sum over k = 1..=K of the MSE of the first-k-levels model, so that
    /// every level of detail is a usable SDF.
    AllPrefixes,
}

impl Objective {
    /// The levels-of-detail whose losses are summed: `(first, count)`.
    pub fn prefixes(self, levels: usize) -> (usize, usize) {
        match self {
            Objective::Full => (levels, 1),
            Objective::AllPrefixes => (1, levels),
        }
    }
}

/// Trilinear cell lookup shared by the CPU paths: the base vertex and the fractional position.
/// Mirrors the kernels, including the clamp to the box.
#[inline]
pub(crate) fn cell(p: [f64; 3], res: u32) -> ([usize; 3], [f64; 3]) {
    let r = f64::from(res);
    let mut i0 = [0usize; 3];
    let mut t = [0f64; 3];
    for a in 0..3 {
        let u = ((p[a] + 1.0) * 0.5 * r).clamp(0.0, r);
        // NaN maps to 0 through the saturating cast, as it stays in range on the GPU.
        let i = (u.floor() as usize).min(res as usize - 1);
        i0[a] = i;
        t[a] = u - i as f64;
    }
    (i0, t)
}

/// The NGLOD model with its parameters on the host.
#[derive(Clone, Debug, PartialEq)]
pub struct Nglod {
    config: NglodConfig,
    /// One per sparse level, coarse to fine.
    bands: Vec<Band>,
    layout: ParamLayout,
    params: Vec<f32>,
}

/// A standard normal variate (Box–Muller).
fn normal(rng: &mut Pcg64) -> f64 {
    loop {
        let u1: f64 = rng.random();
        let u2: f64 = rng.random();
        if u1 > 0.0 {
            return (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        }
    }
}

impl Nglod {
    /// A freshly initialised model: grid features `0.01·N(0, 1)`, MLP weights and biases
    /// `U(-1/√fan_in, 1/√fan_in)` (PyTorch's `nn.Linear` default), all from `config.seed`.
    ///
    /// Sparse levels start empty: [`Nglod::place_bands`] (which the trainer calls for a fresh
    /// model) gives them the vertices near a mesh.
    pub fn new(config: NglodConfig) -> Result<Self, NglodError> {
        config.validate()?;
        let bands = config.empty_bands();
        let layout = config.layout_with(|_| 0);
        let mut rng = Pcg64::seed_from_u64(config.seed);
        let mut params = vec![0f32; layout.len];
        for p in &mut params[..layout.w0] {
            *p = (0.01 * normal(&mut rng)) as f32;
        }
        let k0 = 1.0 / f64::from(config.input_dim()).sqrt();
        for p in &mut params[layout.w0..layout.w1] {
            *p = rng.random_range(-k0..k0) as f32;
        }
        let k1 = 1.0 / f64::from(config.hidden).sqrt();
        for p in &mut params[layout.w1..] {
            *p = rng.random_range(-k1..k1) as f32;
        }
        Ok(Nglod {
            config,
            bands,
            layout,
            params,
        })
    }

    /// Whether the model has sparse levels that are all still empty (a fresh model that
    /// [`Nglod::place_bands`] has not seen).
    pub fn needs_bands(&self) -> bool {
        !self.bands.is_empty() && self.bands.iter().all(Band::is_empty)
    }

    /// Gives every sparse level the band around the surface that `distance` (unsigned, in
    /// normalised units) describes, with fresh features `0.01·N(0, 1)` from the seed; dense
    /// levels and the MLP keep their values.
    pub fn place_bands(&mut self, distance: impl Fn(Vec3) -> f32 + Sync) -> Result<(), NglodError> {
        let bands = self.config.resolutions[self.config.dense_levels()..]
            .iter()
            .map(|&r| Band::around(r, self.config.band_cells, &distance))
            .collect::<Result<Vec<_>, _>>()?;
        let c = &self.config;
        let layout = c.layout_for(&bands)?;
        let f = c.feature_dim as usize;
        let mut rng = Pcg64::seed_from_u64(c.seed ^ 0x5ba7_5e1e);
        let mut params = Vec::with_capacity(layout.len);
        for l in 0..c.levels() {
            if c.is_sparse(l) {
                let n = bands[l - c.dense_levels()].len() * f;
                params.extend((0..n).map(|_| (0.01 * normal(&mut rng)) as f32));
            } else {
                let start = self.layout.grid_offsets[l];
                let entries = c.fixed_entries(l).unwrap_or(0);
                params.extend_from_slice(&self.params[start..start + entries * f]);
            }
        }
        params.extend_from_slice(&self.params[self.layout.w0..]);
        debug_assert_eq!(params.len(), layout.len);
        self.bands = bands;
        self.layout = layout;
        self.params = params;
        Ok(())
    }

    /// Every sparse level's vertex table, coarse to fine, one after the other (empty for a dense
    /// model): what the kernels and the embedded WGSL index with a level's table offset.
    pub(crate) fn sparse_tables(&self) -> Vec<u32> {
        self.bands.iter().flat_map(Band::table).copied().collect()
    }

    /// The sparse levels' bands, coarse to fine (empty for a dense model).
    pub fn bands(&self) -> &[Band] {
        &self.bands
    }

    /// The parameter layout (offsets into the flat vector).
    pub fn layout(&self) -> &ParamLayout {
        &self.layout
    }

    /// Total number of parameters.
    pub fn param_count(&self) -> usize {
        self.layout.len
    }

    /// Where vertex `v` (grid coordinates) of level `l` keeps its first feature in the flat
    /// parameters; `None` for a vertex of a sparse level outside its band.
    #[inline]
    pub(crate) fn vertex_base(&self, l: usize, v: [usize; 3]) -> Option<usize> {
        let c = &self.config;
        let f = c.feature_dim as usize;
        let s = c.resolutions[l] as usize + 1;
        let linear = (v[0] * s + v[1]) * s + v[2];
        let slot = match c.storage(l) {
            LevelStorage::Dense => linear,
            LevelStorage::Sparse => match self.bands[l - c.dense_levels()].table[linear] {
                NO_SLOT => return None,
                k => k as usize,
            },
            LevelStorage::Hashed(t) => {
                hash_vertex([v[0] as u32, v[1] as u32, v[2] as u32], t - 1) as usize
            }
        };
        Some(self.layout.grid_offsets[l] + slot * f)
    }

    /// A model that reproduces `sdf` without training: one level of `resolution` cells whose
    /// single feature holds `sdf` at the grid vertices, and an MLP that passes it through
    /// (`h = relu(z + 10)`, output `h − 10`: exact wherever `z > −10`, i.e. for any distance in
    /// the box). Trilinear interpolation of a true SDF is within about `h²/(8ρ)` of it near a
    /// surface of curvature radius ρ (h = 2/resolution). For tests, and for seeding a model
    /// with an analytic shape.
    pub fn from_sdf(resolution: u32, sdf: impl Fn(Vec3) -> f32 + Sync) -> Result<Self, NglodError> {
        const OFFSET: f32 = 10.0;
        let config = NglodConfig {
            resolutions: vec![resolution],
            feature_dim: 1,
            hidden: 1,
            seed: 0,
            sparse_levels: 0,
            band_cells: DEFAULT_BAND_CELLS,
            encoding: Encoding::Summed,
        };
        config.validate()?;
        let layout = config.layout_with(|_| 0);
        let s = resolution as usize + 1;
        let mut params = vec![0f32; layout.len];
        params[..s * s * s]
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, v)| {
                let (ix, iy, iz) = (i / (s * s), (i / s) % s, i % s);
                let p =
                    Vec3::new(ix as f32, iy as f32, iz as f32) * (2.0 / resolution as f32) - 1.0;
                *v = sdf(p);
            });
        params[layout.w0] = 1.0;
        params[layout.b0] = OFFSET;
        params[layout.w1] = 1.0;
        params[layout.b1] = -OFFSET;
        Nglod::from_params(config, params)
    }

    /// A model from explicit parameters (in the layout of [`Nglod::layout`]), its sparse levels
    /// (if any) empty.
    pub fn from_params(config: NglodConfig, params: Vec<f32>) -> Result<Self, NglodError> {
        config.validate()?;
        let bands = config.empty_bands();
        Nglod::from_parts(config, bands, params)
    }

    /// A model from explicit parameters and one band per sparse level (coarse to fine).
    pub fn from_parts(
        config: NglodConfig,
        bands: Vec<Band>,
        params: Vec<f32>,
    ) -> Result<Self, NglodError> {
        config.validate()?;
        let layout = config.layout_for(&bands)?;
        if params.len() != layout.len {
            return Err(NglodError::LengthMismatch {
                what: "NGLOD parameters",
                expected: layout.len,
                got: params.len(),
            });
        }
        Ok(Nglod {
            config,
            bands,
            layout,
            params,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &NglodConfig {
        &self.config
    }

    /// The flat parameters.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// The flat parameters, mutable (the length is fixed by the configuration).
    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// Interpolated features of the first `lod` levels at `p`, summed or concatenated (the
    /// levels beyond `lod` zero), and (optionally) their Jacobian rows d z_f / dp.
    fn features(&self, p: Vec3, lod: usize, z: &mut [f32], dz: Option<&mut [[f32; 3]]>) {
        let f = self.config.feature_dim as usize;
        z.fill(0.0);
        let mut dz = dz;
        if let Some(d) = dz.as_deref_mut() {
            d.fill([0.0; 3]);
        }
        let pd = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
        for (l, &res) in self.config.resolutions[..lod].iter().enumerate() {
            let zo = self.config.input_offset(l);
            let (i0, t) = cell(pd, res);
            let t = t.map(|v| v as f32);
            // d u / d x = r / 2 in the box, faces included (the inside's derivative: a
            // box-shaped mesh's faces lie on them), 0 where clamped.
            let du: [f32; 3] = std::array::from_fn(|a| {
                let u = (pd[a] + 1.0) * 0.5 * f64::from(res);
                if (0.0..=f64::from(res)).contains(&u) {
                    res as f32 * 0.5
                } else {
                    0.0
                }
            });
            for c in 0..8 {
                let d = [(c >> 2) & 1, (c >> 1) & 1, c & 1];
                let wv: [f32; 3] =
                    std::array::from_fn(|a| if d[a] == 1 { t[a] } else { 1.0 - t[a] });
                let w = wv[0] * wv[1] * wv[2];
                let v = [i0[0] + d[0], i0[1] + d[1], i0[2] + d[2]];
                let Some(base) = self.vertex_base(l, v) else {
                    continue;
                };
                let feats = &self.params[base..base + f];
                for (zf, &g) in z[zo..zo + f].iter_mut().zip(feats) {
                    *zf += w * g;
                }
                if let Some(dzs) = dz.as_deref_mut() {
                    let sign = |a: usize| if d[a] == 1 { 1.0 } else { -1.0 };
                    let dw = [
                        sign(0) * wv[1] * wv[2] * du[0],
                        wv[0] * sign(1) * wv[2] * du[1],
                        wv[0] * wv[1] * sign(2) * du[2],
                    ];
                    for (row, &g) in dzs[zo..zo + f].iter_mut().zip(feats) {
                        for a in 0..3 {
                            row[a] += dw[a] * g;
                        }
                    }
                }
            }
        }
    }

    fn eval_one(&self, p: Vec3, lod: usize, grad: bool) -> (f32, Vec3) {
        let f = self.config.input_dim() as usize;
        let h = self.config.hidden as usize;
        let layout = &self.layout;
        let mut z = [0f32; MAX_FEATURE_DIM as usize];
        let mut dz = [[0f32; 3]; MAX_FEATURE_DIM as usize];
        self.features(p, lod, &mut z[..f], grad.then_some(&mut dz[..f]));
        let w0 = &self.params[layout.w0..layout.b0];
        let b0 = &self.params[layout.b0..layout.w1];
        let w1 = &self.params[layout.w1..layout.b1];
        let mut out = self.params[layout.b1];
        let mut g = Vec3::ZERO;
        for j in 0..h {
            let row = &w0[j * f..(j + 1) * f];
            let hj = b0[j] + row.iter().zip(&z[..f]).map(|(a, b)| a * b).sum::<f32>();
            if hj > 0.0 {
                out += w1[j] * hj;
                if grad {
                    for (wf, d) in row.iter().zip(&dz[..f]) {
                        g += w1[j] * wf * Vec3::from_array(*d);
                    }
                }
            }
        }
        (out, g)
    }

    /// Signed distances at `points` (normalised coordinates) using the first `lod` levels
    /// (`None`: all), on CPU threads in f32.
    pub fn eval_cpu(&self, points: &[Vec3], lod: Option<usize>) -> Result<Vec<f32>, NglodError> {
        let k = self.config.lod(lod)?;
        Ok(points
            .par_iter()
            .map(|&p| self.eval_one(p, k, false).0)
            .collect())
    }

    /// Spatial gradients ∇sdf at `points` using the first `lod` levels (`None`: all), on CPU
    /// threads in f32. Zero across the box's faces, where the grids are clamped.
    pub fn gradient_cpu(
        &self,
        points: &[Vec3],
        lod: Option<usize>,
    ) -> Result<Vec<Vec3>, NglodError> {
        let k = self.config.lod(lod)?;
        Ok(points
            .par_iter()
            .map(|&p| self.eval_one(p, k, true).1)
            .collect())
    }

    /// The model as a model file. Tensors (PyTorch state-dict style, row-major):
    /// `grids.{l}` `[r_l+1, r_l+1, r_l+1, F]` indexed `[ix, iy, iz, f]`, `mlp.0.weight` `[H, F]`,
    /// `mlp.0.bias` `[H]`, `mlp.2.weight` `[1, H]`, `mlp.2.bias` `[1]` (an
    /// `nn.Sequential(Linear(F, H), ReLU(), Linear(H, 1))`). A sparse level `l` is
    /// `grids.{l}` `[n, F]` for its `n` band vertices, with `grids.{l}.vertices` `[n]` their
    /// linear indices `(ix·s + iy)·s + iz` (u32). A hashed level `l` ([`Encoding::Hashed`]) is
    /// `grids.{l}` `[T, F]`, entry [`hash_vertex`] of each vertex, and `mlp.0.weight` is
    /// `[H, K·F]` on the concatenated features. Grid features are stored as f16, the MLP as
    /// f32. The metadata `config` is the [`NglodConfig`] as JSON, and `architecture` is
    /// [`NglodConfig::architecture`].
    pub fn to_model_file(
        &self,
        normalization: Normalization,
        training: serde_json::Value,
    ) -> ModelFile {
        let c = &self.config;
        let layout = &self.layout;
        let f = c.feature_dim as usize;
        let h = c.hidden as usize;
        let input = c.input_dim() as usize;
        let dense = c.dense_levels();
        let mut tensors = Vec::with_capacity(c.levels() + c.sparse_levels + 4);
        for (l, &r) in c.resolutions.iter().enumerate() {
            let s = r as usize + 1;
            let start = layout.grid_offsets[l];
            if let LevelStorage::Hashed(t) = c.storage(l) {
                let t = t as usize;
                tensors.push(Tensor::f16(
                    format!("grids.{l}"),
                    vec![t, f],
                    self.params[start..start + t * f].to_vec(),
                ));
            } else if c.is_sparse(l) {
                let band = &self.bands[l - dense];
                let n = band.len();
                tensors.push(Tensor::f16(
                    format!("grids.{l}"),
                    vec![n, f],
                    self.params[start..start + n * f].to_vec(),
                ));
                tensors.push(Tensor::indices(
                    format!("grids.{l}{INDEX_SUFFIX}"),
                    vec![n],
                    &band.vertices,
                ));
            } else {
                tensors.push(Tensor::f16(
                    format!("grids.{l}"),
                    vec![s, s, s, f],
                    self.params[start..start + s * s * s * f].to_vec(),
                ));
            }
        }
        let mut push = |name: &str, shape: Vec<usize>, range: std::ops::Range<usize>| {
            tensors.push(Tensor::f32(name, shape, self.params[range].to_vec()))
        };
        push("mlp.0.weight", vec![h, input], layout.w0..layout.b0);
        push("mlp.0.bias", vec![h], layout.b0..layout.w1);
        push("mlp.2.weight", vec![1, h], layout.w1..layout.b1);
        push("mlp.2.bias", vec![1], layout.b1..layout.len);
        ModelFile {
            metadata: ModelMetadata {
                architecture: c.architecture().into(),
                config: serde_json::to_value(c).unwrap_or(serde_json::Value::Null),
                training,
                normalization,
                hwsdf_version: crate::model_file::HWSDF_VERSION.into(),
            },
            tensors,
        }
    }

    /// The model in a model file written by [`Nglod::to_model_file`] (or by PyTorch with the same
    /// names and shapes): an `"nglod"` or a `"hashgrid"` file, whose configuration must say the
    /// same.
    pub fn from_model_file(file: &ModelFile) -> Result<Self, NglodError> {
        let found = file.metadata.architecture.as_str();
        if found != "hashgrid" {
            file.expect_architecture("nglod")?;
        }
        let config: NglodConfig = serde_json::from_value(file.metadata.config.clone())
            .map_err(|e| NglodError::InvalidConfig(format!("model file `config` metadata: {e}")))?;
        config.validate()?;
        if config.architecture() != found {
            return Err(NglodError::InvalidConfig(format!(
                "the file says `{found}` but its configuration describes a `{}` model",
                config.architecture()
            )));
        }
        let f = config.feature_dim as usize;
        let h = config.hidden as usize;
        let input = config.input_dim() as usize;
        // The config's sizes come from the file: check the dense part against its real tensors
        // before allocating (a sparse level's size is its vertex tensor's, already read).
        file.ensure_holds(config.layout_with(|_| 0).len as u64)?;
        let mut bands = Vec::with_capacity(config.sparse_levels);
        let mut params = Vec::new();
        for (l, &r) in config.resolutions.iter().enumerate() {
            let s = r as usize + 1;
            if let LevelStorage::Hashed(t) = config.storage(l) {
                params.extend_from_slice(file.tensor(&format!("grids.{l}"), &[t as usize, f])?);
            } else if config.is_sparse(l) {
                let name = format!("grids.{l}{INDEX_SUFFIX}");
                let n = file.tensor_len(&name)?;
                let vertices = file
                    .tensor(&name, &[n])?
                    .iter()
                    .map(|&v| {
                        // Exact integers only: anything else is a corrupt file.
                        (v >= 0.0 && v.fract() == 0.0 && v <= MAX_INDEX as f32)
                            .then_some(v as u32)
                            .ok_or_else(|| {
                                NglodError::InvalidConfig(format!(
                                    "tensor `{name}` holds {v}, not a vertex index"
                                ))
                            })
                    })
                    .collect::<Result<Vec<u32>, _>>()?;
                bands.push(Band::new(r, vertices)?);
                params.extend_from_slice(file.tensor(&format!("grids.{l}"), &[n, f])?);
            } else {
                params.extend_from_slice(file.tensor(&format!("grids.{l}"), &[s, s, s, f])?);
            }
        }
        params.extend_from_slice(file.tensor("mlp.0.weight", &[h, input])?);
        params.extend_from_slice(file.tensor("mlp.0.bias", &[h])?);
        params.extend_from_slice(file.tensor("mlp.2.weight", &[1, h])?);
        params.extend_from_slice(file.tensor("mlp.2.bias", &[1])?);
        Nglod::from_parts(config, bands, params)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_sizes() {
        let d = Nglod::new(NglodConfig::design_document()).unwrap();
        assert_eq!(d.param_count(), 146_601);
        // The default adds a sparse level whose band the mesh decides: empty until placed.
        let mut s = Nglod::new(NglodConfig::default_preset()).unwrap();
        assert_eq!(s.param_count(), 146_601);
        s.place_bands(|p| (p.length() - 0.5).abs()).unwrap();
        assert_eq!(s.param_count(), 146_601 + 8 * s.bands()[0].len());
        assert!((d.param_count() * 4) < 600_000);
        assert_eq!(
            Nglod::new(NglodConfig::small()).unwrap().param_count(),
            23_261
        );
        d.config().validate().unwrap();
        NglodConfig::small().validate().unwrap();
    }

    #[test]
    fn configs_of_older_files_read_as_they_were_made() {
        // Before sparse levels (all dense), and before the band width was a setting (1).
        let old: NglodConfig = serde_json::from_str(
            r#"{"resolutions": [6, 12, 24], "feature_dim": 8, "hidden": 128, "seed": 3}"#,
        )
        .unwrap();
        assert_eq!((old.sparse_levels, old.band_cells), (0, 1));
        let round = serde_json::to_string(&NglodConfig::default_preset()).unwrap();
        assert_eq!(
            serde_json::from_str::<NglodConfig>(&round).unwrap(),
            NglodConfig::default_preset()
        );
    }

    #[test]
    fn invalid_configs_are_typed_errors() {
        let mut c = NglodConfig::small();
        c.resolutions = vec![];
        assert!(matches!(c.validate(), Err(NglodError::InvalidConfig(_))));
        let mut c = NglodConfig::small();
        c.resolutions[1] = 0;
        assert!(Nglod::new(c).is_err());
        let mut c = NglodConfig::small();
        c.feature_dim = 33;
        assert!(c.validate().is_err());
        // Eight sparse levels of 255 cells: 134 M table entries, refused.
        let c = NglodConfig {
            resolutions: vec![255; 8],
            sparse_levels: 8,
            ..NglodConfig::small()
        };
        assert!(matches!(c.validate(), Err(NglodError::InvalidConfig(m)) if m.contains("tables")));
        let mut c = NglodConfig::default_preset();
        c.band_cells = MAX_BAND_CELLS + 1;
        assert!(matches!(c.validate(), Err(NglodError::InvalidConfig(m)) if m.contains("band")));
        let mut c = NglodConfig::default_preset();
        c.feature_dim = 32;
        assert!(
            c.validate().is_err(),
            "128×32 MLP does not fit workgroup memory"
        );
        let m = Nglod::new(NglodConfig::small()).unwrap();
        assert!(matches!(
            m.eval_cpu(&[Vec3::ZERO], Some(4)),
            Err(NglodError::InvalidLod { .. })
        ));
        assert!(m.eval_cpu(&[Vec3::ZERO], Some(0)).is_err());
    }
}
