//! The grid models' architecture: [`NglodConfig`] (NGLOD's summed levels or the hash grid's
//! concatenated, hashed ones: [`Encoding`]), its presets and limits, how each level stores its
//! features ([`LevelStorage`], [`hash_vertex`]) and where everything sits in the flat parameter
//! vector ([`ParamLayout`]).

use serde::{Deserialize, Serialize};

use super::{
    Band, DEFAULT_BAND_CELLS, HASH_TABLE_LOG2, LEGACY_BAND_CELLS, MAX_BAND_CELLS, MAX_FEATURE_DIM,
    MAX_HASHED_RESOLUTION, MAX_LEVELS, MAX_MLP_FLOATS, MAX_SPARSE_RESOLUTION, MAX_TABLE_ENTRIES,
    NglodError,
};

/// How the levels' features reach the MLP, and how a level stores them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "kind")]
pub enum Encoding {
    /// NGLOD: the levels' features are summed into `F` values; a level stores every vertex
    /// (dense) or its band's (sparse, [`NglodConfig::sparse_levels`]).
    #[default]
    Summed,
    /// instant-ngp's multiresolution hash encoding: the levels' features are concatenated into
    /// `K·F` values; a level whose `(r + 1)³` vertices fit in `2^log2_table_size` entries stores
    /// them all, a finer one hashes its vertices into a table of that many entries ([`hash_vertex`];
    /// colliding vertices share their features, and training sorts out which matters).
    Hashed {
        /// `log2` of the table size `T` of every hashed level ([`HASH_TABLE_LOG2`]).
        log2_table_size: u32,
    },
}

/// How one level keeps its features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LevelStorage {
    /// Every vertex of the grid, in row-major order.
    Dense,
    /// The vertices of its band, through a vertex table (NGLOD's sparse levels).
    Sparse,
    /// A table of this many entries (a power of two) indexed by [`hash_vertex`].
    Hashed(u32),
}

/// instant-ngp's spatial hash of a grid vertex into a table of `mask + 1` entries (a power of
/// two): `(ix·1 ⊕ iy·2654435761 ⊕ iz·805459861) mod T`, in wrapping u32 arithmetic as the
/// kernels compute it.
#[inline]
pub fn hash_vertex(v: [u32; 3], mask: u32) -> u32 {
    (v[0] ^ v[1].wrapping_mul(2_654_435_761) ^ v[2].wrapping_mul(805_459_861)) & mask
}

/// Architecture hyperparameters.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct NglodConfig {
    /// Cells per axis of each level's grid, coarse to fine (level `l` has `(r_l+1)³` vertices).
    pub resolutions: Vec<u32>,
    /// Feature dimension `F` of every grid vertex.
    pub feature_dim: u32,
    /// Hidden width `H` of the MLP.
    pub hidden: u32,
    /// Seed of the initialisation.
    pub seed: u64,
    /// How many of the finest levels are sparse: they hold features only at the vertices of the
    /// cells the surface passes through, and [`Self::band_cells`] more (see [`Band`]), so a fine
    /// level costs storage in proportion to the surface's area rather than the box's volume (the
    /// design document's "possible improvement", and NGLOD's own sparse octree). Elsewhere a
    /// sparse level contributes nothing. 0 (the default in older files): every level is dense.
    #[serde(default)]
    pub sparse_levels: usize,
    /// How far a sparse level reaches beyond the cells the surface can pass through, in cells
    /// ([`DEFAULT_BAND_CELLS`]; every file from before it was a setting was made with 1, and
    /// reads so). Dense levels ignore it.
    #[serde(default = "legacy_band_cells")]
    pub band_cells: u32,
    /// Summed levels (NGLOD, the default of every older file) or a hash grid's concatenated,
    /// hashed ones.
    #[serde(default)]
    pub encoding: Encoding,
}

fn legacy_band_cells() -> u32 {
    LEGACY_BAND_CELLS
}

impl Default for NglodConfig {
    fn default() -> Self {
        Self::default_preset()
    }
}

impl NglodConfig {
    /// The default: [`NglodConfig::design_document`]'s three dense levels and a fourth, sparse
    /// level of 48 cells around the surface. Its size depends on the mesh: 146 601 parameters
    /// plus 8 per band vertex. Measured on the 20 shared meshes: 0.18–0.30 M parameters
    /// (0.39–0.68 MB as saved, f16 grids; median 0.56 MB) on 17 of them, 0.44–0.59 M
    /// (1.0–1.4 MB) on the three made of many boxes (many-cubes, boxframe, cubegrid), whose
    /// surface is large for their box.
    ///
    /// Why: the 24-cell finest grid cannot resolve parts thinner than a cell (0.08 of the box),
    /// and near-surface F1 is limited by it. A dense 48-cell level raises near-surface F1 by
    /// 0.02–0.08 but costs 1.09 M parameters; the sparse one does as well or better for a
    /// quarter of that (docs/benchmarks, "Sparse levels").
    pub fn default_preset() -> Self {
        NglodConfig {
            resolutions: vec![6, 12, 24, 48],
            sparse_levels: 1,
            ..Self::design_document()
        }
    }

    /// The design document's model: K = 3 dense levels of 6, 12 and 24 cells (7³ + 13³ + 25³ =
    /// 18165 vertices), F = 8 features, H = 128: 146 601 parameters, 0.586 MB in f32, against
    /// the document's ~140k / 0.56 MB.
    ///
    /// Why these: resolutions double per level like octree levels; for a fixed budget, a finer
    /// finest grid with fewer features resolves more geometry than a 16³ grid with F = 24 (the
    /// other ~140k option), and a small F keeps the MLP (128·F) and the per-point work cheap.
    pub fn design_document() -> Self {
        NglodConfig {
            resolutions: vec![6, 12, 24],
            feature_dim: 8,
            hidden: 128,
            seed: 0,
            sparse_levels: 0,
            band_cells: DEFAULT_BAND_CELLS,
            encoding: Encoding::Summed,
        }
    }

    /// A small model for tests and quick fits: levels of 4, 8 and 16 cells, F = 4, H = 32
    /// (23 261 parameters).
    pub fn small() -> Self {
        NglodConfig {
            resolutions: vec![4, 8, 16],
            feature_dim: 4,
            hidden: 32,
            seed: 0,
            sparse_levels: 0,
            band_cells: DEFAULT_BAND_CELLS,
            encoding: Encoding::Summed,
        }
    }

    /// A multiresolution hash grid ([`Encoding::Hashed`]): `levels` levels from `coarsest` to
    /// `finest` cells per axis in a geometric progression (rounded down, as instant-ngp's
    /// `N_l = ⌊N_min · b^l⌋`), `feature_dim` features per level, tables of `2^log2_table_size`
    /// entries, and an MLP of `hidden` ReLU units on the `levels · feature_dim` concatenated
    /// features. [`NglodConfig::validate`] checks it.
    pub fn hashgrid(
        levels: usize,
        coarsest: u32,
        finest: u32,
        feature_dim: u32,
        log2_table_size: u32,
        hidden: u32,
    ) -> Self {
        let growth = if levels > 1 {
            (f64::from(finest.max(1)) / f64::from(coarsest.max(1))).powf(1.0 / (levels - 1) as f64)
        } else {
            1.0
        };
        let resolutions = (0..levels)
            .map(|l| {
                // The last level is `finest` exactly, whatever the rounding on the way.
                if l + 1 == levels {
                    finest
                } else {
                    (f64::from(coarsest) * growth.powi(l as i32) + 1e-9).floor() as u32
                }
            })
            .collect();
        NglodConfig {
            resolutions,
            feature_dim,
            hidden,
            seed: 0,
            sparse_levels: 0,
            band_cells: DEFAULT_BAND_CELLS,
            encoding: Encoding::Hashed { log2_table_size },
        }
    }

    /// The hash grid's default: 16 levels of 2 features from 16 to 512 cells, tables of 2¹⁸
    /// entries, 64 hidden units (instant-ngp's SDF setting with the table one step smaller, the
    /// MLP of one hidden layer that the kernels share with NGLOD).
    pub fn hashgrid_default() -> Self {
        Self::hashgrid(16, 16, 512, 2, 18, 64)
    }

    /// The hash grid at NGLOD's storage: 16 levels of 2 features from 8 to 256 cells, tables of
    /// 2¹⁴ entries, 32 hidden units.
    pub fn hashgrid_small() -> Self {
        Self::hashgrid(16, 8, 256, 2, 14, 32)
    }

    /// `"hashgrid"` for a hash grid, `"nglod"` otherwise: the model file's architecture.
    pub fn architecture(&self) -> &'static str {
        match self.encoding {
            Encoding::Summed => "nglod",
            Encoding::Hashed { .. } => "hashgrid",
        }
    }

    /// Number of levels K.
    pub fn levels(&self) -> usize {
        self.resolutions.len()
    }

    /// Width of the MLP's input: `F` summed, `K·F` concatenated.
    pub fn input_dim(&self) -> u32 {
        match self.encoding {
            Encoding::Summed => self.feature_dim,
            // Saturating, as every size here: an unvalidated configuration (a public value) must
            // not panic before `validate` names what is wrong with it.
            Encoding::Hashed { .. } => (self.feature_dim)
                .saturating_mul(self.resolutions.len().min(u32::MAX as usize) as u32),
        }
    }

    /// Where level `l`'s features start in the MLP's input: 0 summed, `l·F` concatenated.
    pub fn input_offset(&self, l: usize) -> usize {
        match self.encoding {
            Encoding::Summed => 0,
            Encoding::Hashed { .. } => l.saturating_mul(self.feature_dim as usize),
        }
    }

    /// How level `l` keeps its features.
    pub fn storage(&self, l: usize) -> LevelStorage {
        let vertices = (u64::from(self.resolutions[l]) + 1).saturating_pow(3);
        // Clamped so that an unvalidated configuration cannot overflow the shift.
        let entries = 1u64
            << match self.encoding {
                Encoding::Hashed { log2_table_size } => log2_table_size.min(31),
                Encoding::Summed => 0,
            };
        match self.encoding {
            Encoding::Hashed { .. } if vertices > entries => LevelStorage::Hashed(entries as u32),
            _ if self.is_sparse(l) => LevelStorage::Sparse,
            _ => LevelStorage::Dense,
        }
    }

    /// Entries of level `l` whatever the bands: every vertex of a dense level, the table of a
    /// hashed one; `None` for a sparse level.
    pub(super) fn fixed_entries(&self, l: usize) -> Option<usize> {
        match self.storage(l) {
            LevelStorage::Dense => Some((self.resolutions[l] as usize + 1).saturating_pow(3)),
            LevelStorage::Hashed(t) => Some(t as usize),
            LevelStorage::Sparse => None,
        }
    }

    /// Checks the configuration against the model's and the kernels' limits.
    pub fn validate(&self) -> Result<(), NglodError> {
        let bad = |m: String| Err(NglodError::InvalidConfig(m));
        if self.resolutions.is_empty() || self.resolutions.len() > MAX_LEVELS {
            return bad(format!(
                "{} levels; between 1 and {MAX_LEVELS} are supported",
                self.resolutions.len()
            ));
        }
        let max_resolution = match self.encoding {
            Encoding::Summed => 1024,
            Encoding::Hashed { .. } => MAX_HASHED_RESOLUTION,
        };
        if let Some(r) = self
            .resolutions
            .iter()
            .find(|&&r| !(1..=max_resolution).contains(&r))
        {
            return bad(format!(
                "resolution {r}; each must be in 1..={max_resolution} cells"
            ));
        }
        if !(1..=MAX_FEATURE_DIM).contains(&self.feature_dim) {
            return bad(format!(
                "feature_dim {}; must be in 1..={MAX_FEATURE_DIM}",
                self.feature_dim
            ));
        }
        if let Encoding::Hashed { log2_table_size } = self.encoding {
            if !HASH_TABLE_LOG2.contains(&log2_table_size) {
                return bad(format!(
                    "a hash table of 2^{log2_table_size} entries; log2_table_size must be in \
                     {}..={}",
                    HASH_TABLE_LOG2.start(),
                    HASH_TABLE_LOG2.end()
                ));
            }
            if self.sparse_levels != 0 {
                return bad("a hash grid has no sparse levels (its fine levels are hashed)".into());
            }
            // Checked before input_dim() multiplies: K ≤ MAX_LEVELS and F ≤ 32 here.
            let input = u64::from(self.feature_dim) * self.resolutions.len() as u64;
            if input > u64::from(MAX_FEATURE_DIM) {
                return bad(format!(
                    "{} levels of {} features concatenate to {input} MLP inputs; the kernels \
                     take at most {MAX_FEATURE_DIM}",
                    self.resolutions.len(),
                    self.feature_dim
                ));
            }
        }
        let h = u64::from(self.hidden);
        let mlp = h * u64::from(self.input_dim()) + 2 * h + 1;
        if self.hidden == 0 || mlp > u64::from(MAX_MLP_FLOATS) {
            return bad(format!(
                "hidden {} with {} MLP inputs needs {mlp} MLP floats; the kernels keep at most \
                 {MAX_MLP_FLOATS} in workgroup memory (hidden >= 1)",
                self.hidden,
                self.input_dim()
            ));
        }
        if self.sparse_levels > self.resolutions.len() {
            return bad(format!(
                "{} sparse levels in a model of {} levels",
                self.sparse_levels,
                self.resolutions.len()
            ));
        }
        if self.band_cells > MAX_BAND_CELLS {
            return bad(format!(
                "a band of {} cells; at most {MAX_BAND_CELLS} (wider bands cost a dense level's \
                 storage at a sparse level's price per vertex)",
                self.band_cells
            ));
        }
        // A model file's vertex indices are f32 in memory, exact up to MAX_INDEX.
        if let Some(r) = self.resolutions[self.dense_levels()..]
            .iter()
            .find(|&&r| r > MAX_SPARSE_RESOLUTION)
        {
            return bad(format!(
                "sparse resolution {r}; sparse levels have at most {MAX_SPARSE_RESOLUTION} cells"
            ));
        }
        // A sparse level's vertex table has an entry per vertex of the level, whatever its band:
        // bounded so that a small model file cannot make us allocate gigabytes.
        let table: u64 = self.resolutions[self.dense_levels()..]
            .iter()
            .map(|&r| (u64::from(r) + 1).pow(3))
            .sum();
        if table > MAX_TABLE_ENTRIES {
            return bad(format!(
                "the sparse levels' vertex tables would hold {table} entries; at most \
                 {MAX_TABLE_ENTRIES}"
            ));
        }
        // The kernels index params with u32; a sparse level holds at most every vertex.
        let total: u64 = (0..self.levels())
            .map(|l| {
                let entries = match self.storage(l) {
                    LevelStorage::Hashed(t) => u64::from(t),
                    _ => (u64::from(self.resolutions[l]) + 1).pow(3),
                };
                entries * u64::from(self.feature_dim)
            })
            .sum::<u64>()
            + mlp;
        if total > u64::from(u32::MAX / 4) {
            return bad(format!("{total} parameters is too many for the kernels"));
        }
        Ok(())
    }

    /// Levels stored densely (the coarsest ones); the rest are sparse.
    pub fn dense_levels(&self) -> usize {
        self.resolutions.len().saturating_sub(self.sparse_levels)
    }

    /// One empty band per sparse level (a validated configuration).
    pub(super) fn empty_bands(&self) -> Vec<Band> {
        self.resolutions[self.dense_levels()..]
            .iter()
            .map(|&r| Band::empty(r))
            .collect()
    }

    /// Where sparse level `l`'s vertex table, one entry per vertex of the level, starts in the
    /// sparse levels' tables laid one after the other ([`Nglod::sparse_tables`]); `None` for a
    /// dense level.
    pub(crate) fn table_offset(&self, l: usize) -> Option<usize> {
        self.is_sparse(l).then(|| {
            self.resolutions[self.dense_levels()..l]
                .iter()
                .map(|&r| (r as usize + 1).saturating_pow(3))
                .fold(0usize, usize::saturating_add)
        })
    }

    /// Whether level `l` is sparse.
    pub fn is_sparse(&self, l: usize) -> bool {
        l >= self.dense_levels()
    }

    /// The parameter layout with `bands` as the sparse levels' bands, which must match them.
    pub(super) fn layout_for(&self, bands: &[Band]) -> Result<ParamLayout, NglodError> {
        let dense = self.dense_levels();
        if bands.len() != self.sparse_levels
            || bands
                .iter()
                .zip(&self.resolutions[dense..])
                .any(|(b, &r)| b.resolution != r)
        {
            return Err(NglodError::InvalidConfig(
                "the bands do not match the configuration's sparse levels".into(),
            ));
        }
        Ok(self.layout_with(|l| bands[l - dense].len()))
    }

    /// Parameters of the dense and hashed levels and the MLP: all but the sparse levels' bands
    /// (known once the mesh is), so a lower bound to check against the device before any is
    /// allocated.
    pub fn fixed_param_count(&self) -> usize {
        self.layout_with(|_| 0).len
    }

    /// The parameter layout when sparse level `l` holds `band_vertices(l)` vertices.
    pub(super) fn layout_with(&self, band_vertices: impl Fn(usize) -> usize) -> ParamLayout {
        let f = self.feature_dim as usize;
        let h = self.hidden as usize;
        let mut grid_offsets = Vec::with_capacity(self.resolutions.len());
        let mut off = 0usize;
        for l in 0..self.resolutions.len() {
            grid_offsets.push(off);
            let entries = self.fixed_entries(l).unwrap_or_else(|| band_vertices(l));
            off = off.saturating_add(entries.saturating_mul(f));
        }
        let w0 = off;
        let b0 = w0.saturating_add(h.saturating_mul(self.input_dim() as usize));
        let w1 = b0.saturating_add(h);
        let b1 = w1.saturating_add(h);
        ParamLayout {
            grid_offsets,
            w0,
            b0,
            w1,
            b1,
            len: b1.saturating_add(1),
        }
    }

    /// Resolves a level of detail: `None` is all levels, `Some(k)` must be in `1..=levels`.
    pub fn lod(&self, lod: Option<usize>) -> Result<usize, NglodError> {
        let k = self.levels();
        match lod {
            None => Ok(k),
            Some(l) if (1..=k).contains(&l) => Ok(l),
            Some(l) => Err(NglodError::InvalidLod {
                requested: l,
                levels: k,
            }),
        }
    }
}

/// Offsets of each block in the flat parameter vector (see the module docs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamLayout {
    /// Start of each level's grid.
    pub grid_offsets: Vec<usize>,
    /// Start of `W0` (`H×F`).
    pub w0: usize,
    /// Start of `b0` (`H`).
    pub b0: usize,
    /// Start of `W1` (`H`).
    pub w1: usize,
    /// Index of `b1`.
    pub b1: usize,
    /// Total length.
    pub len: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The public size helpers saturate on a configuration nobody validated (resolutions of
    /// u32::MAX cubed overflowed u64: a panic in debug builds, a wrapped "dense" in release),
    /// and `validate` then names what is wrong.
    #[test]
    fn sizes_of_unvalidated_configurations_saturate() {
        for config in [
            NglodConfig {
                resolutions: vec![u32::MAX, u32::MAX],
                feature_dim: u32::MAX,
                hidden: u32::MAX,
                ..NglodConfig::hashgrid_small()
            },
            NglodConfig {
                resolutions: vec![u32::MAX; 3],
                ..NglodConfig::default_preset()
            },
        ] {
            if let Encoding::Hashed { log2_table_size } = config.encoding {
                assert_eq!(
                    config.storage(0),
                    LevelStorage::Hashed(1 << log2_table_size)
                );
            }
            assert_eq!(config.fixed_param_count(), usize::MAX);
            let _ = (config.input_dim(), config.input_offset(1));
            assert!(config.validate().is_err());
        }
    }
}
