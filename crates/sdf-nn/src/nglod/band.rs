//! The band of a sparse level: the vertices of the cells near the surface that hold features,
//! placed from the mesh's distance before training, and the table from a level's vertices to
//! their feature slots.

use glam::Vec3;
use rayon::prelude::*;

use super::{MAX_SPARSE_RESOLUTION, NO_SLOT, NglodError};

/// The vertices of a sparse level that hold features, in increasing linear index
/// `(ix·s + iy)·s + iz` (`s = r + 1`); the `k`-th of them holds the level's `k`-th feature vector.
/// A vertex outside the band has zero features, so a sparse level's field stays continuous and
/// fades to nothing within one cell of the band's edge.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Band {
    pub(super) resolution: u32,
    pub(super) vertices: Vec<u32>,
    /// One entry per vertex of the level: its slot, or [`NO_SLOT`].
    pub(super) table: Vec<u32>,
}

impl Band {
    /// A band from its vertices' linear indices, which must increase and lie in the level.
    pub fn new(resolution: u32, vertices: Vec<u32>) -> Result<Self, NglodError> {
        if !(1..=MAX_SPARSE_RESOLUTION).contains(&resolution) {
            return Err(NglodError::InvalidConfig(format!(
                "sparse resolution {resolution}; must be in 1..={MAX_SPARSE_RESOLUTION}"
            )));
        }
        let n = (resolution as usize + 1).pow(3);
        let mut table = vec![NO_SLOT; n];
        let mut last = None;
        for (k, &v) in vertices.iter().enumerate() {
            if (v as usize) >= n || last.is_some_and(|l| l >= v) {
                return Err(NglodError::InvalidConfig(format!(
                    "sparse level of {resolution} cells: vertex index {v} at position {k} is out \
                     of range or not increasing"
                )));
            }
            last = Some(v);
            table[v as usize] = k as u32;
        }
        Ok(Band {
            resolution,
            vertices,
            table,
        })
    }

    /// An empty band: the level contributes nothing until [`Nglod::place_bands`] fills it.
    pub(super) fn empty(resolution: u32) -> Self {
        Band::new(resolution, Vec::new()).expect("validated resolution")
    }

    /// The band around a surface: the vertices of every cell whose centre lies within
    /// `(√3/2 + band_cells)` cell widths of it, by `distance` (unsigned, normalised units).
    /// Blocks of 4³ cells that cannot reach the surface are skipped with one query each.
    pub fn around(
        resolution: u32,
        band_cells: u32,
        distance: impl Fn(Vec3) -> f32 + Sync,
    ) -> Result<Self, NglodError> {
        const BLOCK: u32 = 4;
        let r = resolution;
        let h = 2.0 / r as f32;
        let half_diag = 0.5 * 3f32.sqrt();
        let reach = h * (half_diag + band_cells as f32);
        let centre = |c: [f32; 3]| Vec3::from_array(c.map(|i| -1.0 + (i + 0.5) * h));
        let nb = r.div_ceil(BLOCK);
        let cells: Vec<[u32; 3]> = (0..nb * nb * nb)
            .into_par_iter()
            .flat_map_iter(|b| {
                let bi = [b / (nb * nb), (b / nb) % nb, b % nb];
                // Every cell centre of the block is within (BLOCK-1)·h·√3/2 of its middle.
                let mid = bi.map(|i| (i * BLOCK) as f32 + 0.5 * (BLOCK - 1) as f32);
                let skip = distance(centre(mid)) - (BLOCK - 1) as f32 * h * half_diag > reach;
                let lo = bi.map(|i| i * BLOCK);
                let hi = bi.map(|i| ((i + 1) * BLOCK).min(r));
                let distance = &distance;
                (lo[0]..hi[0])
                    .flat_map(move |x| (lo[1]..hi[1]).map(move |y| (x, y)))
                    .flat_map(move |(x, y)| (lo[2]..hi[2]).map(move |z| [x, y, z]))
                    .filter(move |c| !skip && distance(centre(c.map(|i| i as f32))) <= reach)
            })
            .collect();
        let s = r as usize + 1;
        let mut used = vec![false; s * s * s];
        for c in cells {
            for k in 0..8u32 {
                let v =
                    [c[0] + (k >> 2 & 1), c[1] + (k >> 1 & 1), c[2] + (k & 1)].map(|i| i as usize);
                used[(v[0] * s + v[1]) * s + v[2]] = true;
            }
        }
        let vertices = (0..used.len() as u32)
            .filter(|&v| used[v as usize])
            .collect();
        Band::new(resolution, vertices)
    }

    /// The vertices' linear indices.
    pub fn vertices(&self) -> &[u32] {
        &self.vertices
    }

    /// Number of vertices holding features.
    pub fn len(&self) -> usize {
        self.vertices.len()
    }

    /// Whether no vertex holds features.
    pub fn is_empty(&self) -> bool {
        self.vertices.is_empty()
    }

    /// The slot of every vertex of the level, [`NO_SLOT`] outside the band (the GPU table).
    pub(crate) fn table(&self) -> &[u32] {
        &self.table
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nglod::cell;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    /// With a band of b cells, every point within b cell widths of the surface (on it, for
    /// b = 0) interpolates eight band vertices, and no vertex far from it is in the band; wider
    /// bands hold narrower ones.
    #[test]
    fn band_covers_its_cells_around_the_surface_and_no_more() {
        let r = 24u32;
        let h = 2.0 / r as f32;
        let radius = 0.55;
        let sphere = |p: Vec3| (p.length() - radius).abs();
        let s = r as usize + 1;
        let mut rng = Pcg64::seed_from_u64(5);
        let mut narrower: Option<Band> = None;
        for b in 0..=2u32 {
            let band = Band::around(r, b, sphere).unwrap();
            assert!(
                band.len() > 100 && band.len() < s * s * s / 2,
                "{}",
                band.len()
            );
            for _ in 0..3000 {
                // A point at most b cells off the sphere.
                let dir = Vec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0f32),
                )
                .normalize_or(Vec3::X);
                let off = b as f32 * h * rng.random_range(-1.0..=1.0f32);
                let p = dir * (radius + off);
                let (i0, _) = cell([p.x, p.y, p.z].map(f64::from), r);
                for c in 0..8 {
                    let v = [i0[0] + (c >> 2 & 1), i0[1] + (c >> 1 & 1), i0[2] + (c & 1)];
                    let linear = (v[0] * s + v[1]) * s + v[2];
                    assert_ne!(
                        band.table()[linear],
                        NO_SLOT,
                        "b = {b}: {p} near the surface, corner {v:?}"
                    );
                }
            }
            // A band vertex is a corner of a cell whose centre is within the reach.
            let reach = h * (0.5 * 3f32.sqrt() + b as f32) + h * 0.5 * 3f32.sqrt();
            for &v in band.vertices() {
                let v = v as usize;
                let x =
                    Vec3::new((v / (s * s)) as f32, ((v / s) % s) as f32, (v % s) as f32) * h - 1.0;
                assert!(
                    sphere(x) <= reach * 1.0001,
                    "b = {b}: vertex {x} is {} away",
                    sphere(x)
                );
            }
            if let Some(n) = narrower {
                assert!(n.len() < band.len(), "b = {b}");
                assert!(
                    n.vertices()
                        .iter()
                        .all(|&v| band.table()[v as usize] != NO_SLOT)
                );
            }
            narrower = Some(band);
        }
        assert!(matches!(
            Band::new(r, vec![3, 3]),
            Err(NglodError::InvalidConfig(_))
        ));
        assert!(Band::new(r, vec![(s * s * s) as u32]).is_err());
        assert!(Band::new(MAX_SPARSE_RESOLUTION + 1, vec![]).is_err());
    }
}
