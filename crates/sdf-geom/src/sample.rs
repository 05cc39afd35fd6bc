//! Seeded, deterministic point samplers: in the box, on the surface, Poisson-disk on the surface, and
//! near the surface.
//!
//! Every sampler takes a `seed`; the same seed, inputs and crate version give bit-identical output
//! (the random stream is `rand_pcg::Pcg64Mcg`, and all sampling is sequential, so the thread count does
//! not matter).

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
use rayon::prelude::*;

use crate::{Aabb, Mesh};

/// Each sampler's own stream of a seed: one seed given to two samplers draws unrelated numbers
/// for each. (Before, the pool's box, near-surface and surface points of a block came from
/// `seed`, `seed ^ 1` and `seed ^ 2` of one generator, so seed 0's surface points were seed 3's
/// near-surface ones: runs over consecutive seeds were not independent.)
#[derive(Clone, Copy)]
enum Stream {
    Box = 1,
    Surface,
    NearSurface,
    Perturb,
    PoissonCandidates,
}

fn rng(seed: u64, stream: Stream) -> Pcg64Mcg {
    Pcg64Mcg::seed_from_u64(sub_seed(seed, stream as u64))
}

/// The seed of stream `stream` of `seed` (a pool's block, a worker's share): unrelated seeds
/// for nearby values of either, where `seed ^ stream` gives seed 0's stream 1 to seed 1's
/// stream 0. SplitMix64's finaliser, applied to the stream and then to the seed mixed with it.
pub fn sub_seed(seed: u64, stream: u64) -> u64 {
    splitmix64(seed ^ splitmix64(stream))
}

/// SplitMix64 (Steele, Lea and Flood 2014): a bijection of u64 whose outputs for consecutive
/// inputs look independent.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Points on a surface with the unit normals of the triangles they lie on.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfaceSamples {
    /// Sample positions.
    pub points: Vec<Vec3>,
    /// Unit face normal (from the triangle's winding) at each sample.
    pub normals: Vec<Vec3>,
    /// Index of the triangle each sample lies on.
    pub triangles: Vec<u32>,
}

impl SurfaceSamples {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True if there are no samples.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// Poisson-disk samples on a surface.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoissonSamples {
    /// The samples with their normals.
    pub samples: SurfaceSamples,
    /// The smallest Euclidean distance between two kept samples (`f32::INFINITY` for fewer than two
    /// samples). If no two samples are closer than `2 × target_radius`, this is `2 × target_radius`, a
    /// lower bound.
    pub min_distance: f32,
    /// Yuksel's r_max for this area and count: the Poisson-disk radius of a densest (hexagonal) packing,
    /// `sqrt(A / (2√3 n))`. Sample elimination typically keeps `min_distance` above ~0.6 of this.
    pub target_radius: f32,
}

/// `n` points uniform in the normalised box `[-1, 1]^3`.
pub fn uniform_box(n: usize, seed: u64) -> Vec<Vec3> {
    uniform_in(
        &Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        },
        n,
        seed,
    )
}

/// `n` points uniform in `aabb`.
pub fn uniform_in(aabb: &Aabb, n: usize, seed: u64) -> Vec<Vec3> {
    let mut r = rng(seed, Stream::Box);
    let size = aabb.max - aabb.min;
    (0..n)
        .map(|_| {
            let u = Vec3::new(r.random::<f32>(), r.random::<f32>(), r.random::<f32>());
            aabb.min + u * size
        })
        .collect()
}

/// Cumulative triangle areas (f64) and unit normals; invalid or zero-area triangles get zero weight.
fn area_table(mesh: &Mesh) -> (Vec<f64>, Vec<Vec3>) {
    let mut cdf = Vec::with_capacity(mesh.triangles.len());
    let mut normals = Vec::with_capacity(mesh.triangles.len());
    let mut acc = 0.0f64;
    for t in &mesh.triangles {
        let (area, n) = match mesh.corners(t) {
            Some([a, b, c]) if (a.is_finite() && b.is_finite() && c.is_finite()) => {
                let cr = (b - a).as_dvec3().cross((c - a).as_dvec3());
                let len = cr.length();
                if len > 0.0 {
                    (0.5 * len, (cr / len).as_vec3())
                } else {
                    (0.0, Vec3::ZERO)
                }
            }
            _ => (0.0, Vec3::ZERO),
        };
        acc += area;
        cdf.push(acc);
        normals.push(n);
    }
    (cdf, normals)
}

fn sample_surface_with(mesh: &Mesh, n: usize, r: &mut Pcg64Mcg) -> SurfaceSamples {
    let (cdf, normals) = area_table(mesh);
    let total = cdf.last().copied().unwrap_or(0.0);
    let mut out = SurfaceSamples {
        points: Vec::with_capacity(n),
        normals: Vec::with_capacity(n),
        triangles: Vec::with_capacity(n),
    };
    if total.is_nan() || total <= 0.0 || n == 0 {
        return out;
    }
    let guide = GuideTable::new(&cdf);
    for _ in 0..n {
        let u = r.random::<f64>() * total;
        let ti = guide.partition_point(&cdf, u).min(cdf.len() - 1);
        // Skip back over zero-area triangles at the end (u can round up to `total`).
        let ti = if normals[ti] == Vec3::ZERO {
            cdf.partition_point(|&c| c < cdf[ti]).min(cdf.len() - 1)
        } else {
            ti
        };
        let Some([a, b, c]) = mesh.corners(&mesh.triangles[ti]) else {
            continue;
        };
        let r1 = r.random::<f32>().sqrt();
        let r2 = r.random::<f32>();
        let p = a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2);
        out.points.push(p);
        out.normals.push(normals[ti]);
        out.triangles.push(ti as u32);
    }
    out
}

/// Where to start looking for a value in a cumulative table (Chen and Asau's guide table): the
/// table's range split into as many equal buckets as it has entries, each bucket's first entry
/// above its start. A draw then searches its bucket and the two beside it instead of the whole
/// table: a binary search of a 1.4 M-entry table made 10⁶ surface samples take 2 s, most of it
/// cache misses.
struct GuideTable {
    /// `first[j]`: the entries at most bucket `j`'s start, `j · total / buckets`.
    first: Vec<u32>,
    /// Buckets per unit of the table's range.
    scale: f64,
}

impl GuideTable {
    /// The guide of `cdf` (non-decreasing, finite, with a positive last entry).
    fn new(cdf: &[f64]) -> Self {
        let total = cdf[cdf.len() - 1];
        let buckets = cdf.len();
        let scale = buckets as f64 / total;
        let mut first = Vec::with_capacity(buckets + 1);
        let mut i = 0;
        for j in 0..=buckets {
            let start = j as f64 / scale;
            while i < cdf.len() && cdf[i] <= start {
                i += 1;
            }
            first.push(i as u32);
        }
        // The last start can round to just below the total: every entry is at most the total.
        first[buckets] = cdf.len() as u32;
        GuideTable { first, scale }
    }

    /// `cdf.partition_point(|&c| c <= u)` for `u` in `[0, total]`. Bucket edges are found
    /// with rounding of an ulp or so either way, so the search takes the neighbouring buckets
    /// too: the answer always lies inside, and so the result is the whole table's.
    fn partition_point(&self, cdf: &[f64], u: f64) -> usize {
        let buckets = self.first.len() - 1;
        let j = ((u * self.scale) as usize).min(buckets - 1);
        let lo = self.first[j.saturating_sub(1)] as usize;
        let hi = (self.first[(j + 2).min(buckets)] as usize + 1).min(cdf.len());
        lo + cdf[lo..hi].partition_point(|&c| c <= u)
    }
}

/// `n` points on the surface, uniform with respect to area, with face normals.
/// A mesh without area gives no samples.
pub fn surface(mesh: &Mesh, n: usize, seed: u64) -> SurfaceSamples {
    sample_surface_with(mesh, n, &mut rng(seed, Stream::Surface))
}

/// A standard normal variate by Box–Muller.
fn gaussian(r: &mut Pcg64Mcg) -> f32 {
    loop {
        let u1 = r.random::<f64>();
        let u2 = r.random::<f64>();
        if u1 > 0.0 {
            return ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32;
        }
    }
}

/// Each point moved by isotropic Gaussian noise N(0, σ²) per coordinate, seeded. The
/// evaluation's near-surface set is Poisson-disk samples perturbed this way.
pub fn perturb(points: &[Vec3], sigma: f32, seed: u64) -> Vec<Vec3> {
    let mut r = rng(seed, Stream::Perturb);
    points
        .iter()
        .map(|&p| p + Vec3::new(gaussian(&mut r), gaussian(&mut r), gaussian(&mut r)) * sigma)
        .collect()
}

/// Default σ for [`near_surface`], in normalised units (the design document's 0.01).
pub const DEFAULT_SIGMA: f32 = 0.01;

/// `n` points near the surface: area-uniform surface points plus isotropic Gaussian noise N(0, σ²) on
/// each coordinate. σ is in the mesh's units; use [`DEFAULT_SIGMA`] on a normalised mesh.
pub fn near_surface(mesh: &Mesh, n: usize, sigma: f32, seed: u64) -> Vec<Vec3> {
    let mut r = rng(seed, Stream::NearSurface);
    let s = sample_surface_with(mesh, n, &mut r);
    s.points
        .into_iter()
        .map(|p| p + Vec3::new(gaussian(&mut r), gaussian(&mut r), gaussian(&mut r)) * sigma)
        .collect()
}

/// Candidates drawn per kept sample by [`poisson_disk`]. Yuksel recommends 5; 3 is 2.5× faster
/// (the neighbour lists grow with the square of the candidate density) and on the bunny with 10⁵
/// samples keeps a minimum distance of 1.26·r_max instead of 1.38·r_max.
pub const POISSON_CANDIDATE_FACTOR: usize = 3;

/// Poisson-disk samples on the surface by weighted sample elimination (Yuksel 2015, "Sample
/// Elimination for Generating Poisson Disk Sample Sets"): draw `k·n` area-uniform candidates (k = [`POISSON_CANDIDATE_FACTOR`]), give each
/// a weight Σ (1 − d̂/2r_max)^8 over neighbours within 2·r_max (Euclidean, with Yuksel's weight
/// limiting d̂ = max(d, 2·r_min)), and repeatedly remove the candidate with the largest weight until
/// `n` remain. Kept samples are returned in candidate order.
///
/// Returns fewer than `n` samples only for a mesh without area.
pub fn poisson_disk(mesh: &Mesh, n: usize, seed: u64) -> PoissonSamples {
    poisson_disk_with(mesh, n, POISSON_CANDIDATE_FACTOR, seed)
}

/// [`poisson_disk`] with an explicit number of candidates per kept sample (at least 1; Yuksel uses
/// 5).
pub fn poisson_disk_with(
    mesh: &Mesh,
    n: usize,
    candidates_per_sample: usize,
    seed: u64,
) -> PoissonSamples {
    let area = mesh.area();
    if n == 0 || area.is_nan() || area <= 0.0 {
        return PoissonSamples {
            samples: SurfaceSamples::default(),
            min_distance: f32::INFINITY,
            target_radius: 0.0,
        };
    }
    let m = n.saturating_mul(candidates_per_sample.max(1));
    let cand = sample_surface_with(mesh, m, &mut rng(seed, Stream::PoissonCandidates));
    let m = cand.len();
    let r_max = (area / (2.0 * 3f64.sqrt() * n as f64)).sqrt() as f32;
    let r_min = r_max * 0.65 * (1.0 - (n as f32 / m as f32).powf(1.5));
    let two_r_max = 2.0 * r_max;
    // The grid stores the candidates sorted by cell, so neighbour scans read contiguous memory;
    // all indices below are positions in that order.
    let grid = Grid::new(&cand.points, two_r_max);
    let pts = &grid.points;

    // Neighbour lists (CSR) with the weight each neighbour contributes, built cell by cell: the
    // 27 neighbouring cell ranges are looked up once per cell, not once per point.
    let per_cell: Vec<CellLists> = grid
        .cell_ranges
        .par_iter()
        .with_min_len(64)
        .map(|&(s, e)| {
            let near = grid.ranges_near(pts[s as usize]);
            let mut counts = Vec::with_capacity((e - s) as usize);
            let mut flat = Vec::with_capacity((e - s) as usize * 24);
            for i in s..e {
                let p = pts[i as usize];
                let before = flat.len();
                for &(a, b) in &near {
                    for j in a..b {
                        if j != i {
                            let d = p.distance(pts[j as usize]);
                            if d < two_r_max {
                                let dh = d.max(2.0 * r_min);
                                flat.push((j, (1.0 - dh / two_r_max).powi(8)));
                            }
                        }
                    }
                }
                counts.push((flat.len() - before) as u32);
            }
            (counts, flat)
        })
        .collect();
    let mut offsets = Vec::with_capacity(m + 1);
    offsets.push(0usize);
    let mut neighbours: Vec<(u32, f32)> =
        Vec::with_capacity(per_cell.iter().map(|c| c.1.len()).sum());
    for (counts, flat) in per_cell {
        for c in counts {
            offsets.push(offsets.last().copied().unwrap_or(0) + c as usize);
        }
        neighbours.extend(flat);
    }
    let mut weight: Vec<f32> = (0..m)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            neighbours[offsets[i]..offsets[i + 1]]
                .iter()
                .map(|x| x.1)
                .sum()
        })
        .collect();

    // Max-heap with lazy updates: weights only ever decrease, so a stored key is an upper bound of
    // the current weight. When the top's key is stale it is refreshed and sifted down; a top whose
    // key is current is the true maximum.
    let mut heap = LazyMaxHeap::new(&weight);
    let mut removed = vec![false; m];
    let mut remaining = m;
    while remaining > n {
        let Some(i) = heap.pop_current(&weight) else {
            break;
        };
        let iu = i as usize;
        removed[iu] = true;
        remaining -= 1;
        for &(j, wj) in &neighbours[offsets[iu]..offsets[iu + 1]] {
            if !removed[j as usize] {
                weight[j as usize] -= wj;
            }
        }
    }

    // Kept samples, back in candidate order.
    let mut kept: Vec<u32> = (0..m)
        .filter(|&i| !removed[i])
        .map(|i| grid.order[i])
        .collect();
    kept.sort_unstable();
    let mut samples = SurfaceSamples::default();
    for &i in &kept {
        let i = i as usize;
        samples.points.push(cand.points[i]);
        samples.normals.push(cand.normals[i]);
        samples.triangles.push(cand.triangles[i]);
    }
    let min_distance = min_pair_distance(&samples.points, two_r_max);
    PoissonSamples {
        samples,
        min_distance,
        target_radius: r_max,
    }
}

/// Per cell: neighbour counts of its points, and their (neighbour, weight) pairs back to back.
type CellLists = (Vec<u32>, Vec<(u32, f32)>);

/// Smallest distance between two points, looking only within `radius`; `radius` if no pair is
/// closer, `INFINITY` for fewer than two points.
pub fn min_pair_distance(points: &[Vec3], radius: f32) -> f32 {
    if points.len() < 2 {
        return f32::INFINITY;
    }
    let grid = Grid::new(points, radius);
    (0..points.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let p = grid.points[i];
            let mut best = radius;
            grid.for_each_near(p, |j| {
                if j as usize != i {
                    best = best.min(p.distance(grid.points[j as usize]));
                }
            });
            best
        })
        .reduce(|| radius, f32::min)
}

/// A uniform hash grid over points with a given cell size, for fixed-radius neighbour queries.
struct Grid {
    cell: f32,
    origin: Vec3,
    /// cell key → range into `items`.
    cells: HashMap<(i32, i32, i32), (u32, u32), BuildHasherDefault<CellHasher>>,
    /// `points` ranges of the occupied cells, in storage order.
    cell_ranges: Vec<(u32, u32)>,
    /// The points, sorted by cell (cells in Morton order).
    points: Vec<Vec3>,
    /// Original index of each entry of `points`.
    order: Vec<u32>,
}

impl Grid {
    fn key(&self, p: Vec3) -> (i32, i32, i32) {
        let c = ((p - self.origin) / self.cell).floor();
        (c.x as i32, c.y as i32, c.z as i32)
    }

    fn new(points: &[Vec3], cell: f32) -> Grid {
        let mut b = Aabb::EMPTY;
        for &p in points {
            b.extend(p);
        }
        // Keep cell indices in i32 range even for a tiny radius.
        let span = (b.max - b.min).max_element();
        let cell = if cell > 0.0 && cell.is_finite() {
            cell.max(span / 1.0e6)
        } else {
            span.max(1.0)
        };
        let mut g = Grid {
            cell,
            origin: b.min,
            cells: HashMap::default(),
            cell_ranges: Vec::new(),
            points: Vec::with_capacity(points.len()),
            order: Vec::with_capacity(points.len()),
        };
        let mut keyed: Vec<(u64, (i32, i32, i32), u32)> = points
            .par_iter()
            .enumerate()
            .map(|(i, &p)| {
                let k = g.key(p);
                let m =
                    spread21(k.0 as u32) << 2 | spread21(k.1 as u32) << 1 | spread21(k.2 as u32);
                (m, k, i as u32)
            })
            .collect();
        keyed.par_sort_unstable();
        let mut start = 0usize;
        while start < keyed.len() {
            let k = keyed[start].1;
            let mut end = start;
            while end < keyed.len() && keyed[end].1 == k {
                g.order.push(keyed[end].2);
                g.points.push(points[keyed[end].2 as usize]);
                end += 1;
            }
            g.cells.insert(k, (start as u32, end as u32));
            g.cell_ranges.push((start as u32, end as u32));
            start = end;
        }
        g
    }

    /// The `points` ranges of the 27 cells around `p`'s cell that are occupied.
    fn ranges_near(&self, p: Vec3) -> Vec<(u32, u32)> {
        let (x, y, z) = self.key(p);
        let mut out = Vec::with_capacity(27);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(&r) = self.cells.get(&(x + dx, y + dy, z + dz)) {
                        out.push(r);
                    }
                }
            }
        }
        out
    }

    /// Calls `f` with the (sorted) position of every point in the 27 cells around `p` (a superset of
    /// those within `cell`).
    fn for_each_near(&self, p: Vec3, mut f: impl FnMut(u32)) {
        let (x, y, z) = self.key(p);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(&(s, e)) = self.cells.get(&(x + dx, y + dy, z + dz)) {
                        for j in s..e {
                            f(j);
                        }
                    }
                }
            }
        }
    }
}

/// A small multiplicative hasher for grid cell keys (the std SipHash is needlessly slow here).
#[derive(Default)]
struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        let x = self.0;
        x ^ (x >> 29) ^ (x >> 47)
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }
    fn write_i32(&mut self, i: i32) {
        self.write_u64(i as u32 as u64);
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

/// Spreads the low 21 bits of `v` two bits apart (for 63-bit Morton codes).
fn spread21(v: u32) -> u64 {
    let mut x = (v & 0x1f_ffff) as u64;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// A 4-ary max-heap of (key, item) pairs stored inline (children share a cache line), with lazy
/// updates: keys are upper bounds of the items' current weights and are refreshed when they reach
/// the top. Ties are broken by the smaller item index, so the order is deterministic.
struct LazyMaxHeap {
    heap: Vec<(f32, u32)>,
}

impl LazyMaxHeap {
    fn new(weights: &[f32]) -> Self {
        let mut h = LazyMaxHeap {
            heap: weights
                .iter()
                .enumerate()
                .map(|(i, &w)| (w, i as u32))
                .collect(),
        };
        let n = h.heap.len();
        for i in (0..n.div_ceil(4)).rev() {
            h.sift_down(i);
        }
        h
    }

    #[inline]
    fn above(a: (f32, u32), b: (f32, u32)) -> bool {
        a.0 > b.0 || (a.0 == b.0 && a.1 < b.1)
    }

    fn sift_down(&mut self, mut i: usize) {
        let n = self.heap.len();
        let x = self.heap[i];
        loop {
            let first = 4 * i + 1;
            if first >= n {
                break;
            }
            let mut c = first;
            for k in first + 1..(first + 4).min(n) {
                if Self::above(self.heap[k], self.heap[c]) {
                    c = k;
                }
            }
            if Self::above(self.heap[c], x) {
                self.heap[i] = self.heap[c];
                i = c;
            } else {
                break;
            }
        }
        self.heap[i] = x;
    }

    /// Pops the item with the largest current weight (`current[i]` never exceeds `i`'s key).
    fn pop_current(&mut self, current: &[f32]) -> Option<u32> {
        loop {
            let (key, top) = *self.heap.first()?;
            let w = current[top as usize];
            if w == key {
                let last = self.heap.pop()?;
                if !self.heap.is_empty() {
                    self.heap[0] = last;
                    self.sift_down(0);
                }
                return Some(top);
            }
            self.heap[0].0 = w;
            self.sift_down(0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The guide's search gives the whole table's partition point for every kind of draw:
    /// entries themselves, bucket edges and their neighbouring floats, 0 and the total, over
    /// tables with runs of zero-area entries, one huge entry among tiny ones, and uneven steps.
    #[test]
    fn guide_table_search_is_the_whole_tables() {
        let mut r = rng(11, Stream::Box);
        let mut tables: Vec<Vec<f64>> = vec![
            vec![1.0],
            vec![0.0, 0.0, 3.0, 3.0, 3.0, 5.0],
            // Ends in a run of equal entries, and a total whose last bucket start rounds below it.
            vec![3.320573913939628; 2],
            vec![
                0.1,
                0.7,
                3.320573913939628,
                3.320573913939628,
                3.320573913939628,
            ],
            vec![1e-300, 1e-300, 1e300],
            (1..=1000).map(|k| (k * k) as f64 * 1e-7).collect(),
        ];
        let mut acc = 0.0;
        tables.push(
            (0..5000)
                .map(|k| {
                    // Every seventh triangle has no area; the others span 12 orders of magnitude.
                    acc += if k % 7 == 0 {
                        0.0
                    } else {
                        10f64.powf(r.random::<f64>() * 12.0 - 6.0)
                    };
                    acc
                })
                .collect(),
        );
        for cdf in &tables {
            let guide = GuideTable::new(cdf);
            let total = cdf[cdf.len() - 1];
            let mut draws = vec![0.0, total, f64::MIN_POSITIVE];
            for &c in cdf {
                draws.extend([c, c.next_down(), c.next_up()]);
            }
            for j in 0..=cdf.len() {
                let edge = j as f64 / guide.scale;
                draws.extend([edge, edge.next_down(), edge.next_up()]);
            }
            draws.extend((0..2000).map(|_| r.random::<f64>() * total));
            for u in draws.into_iter().filter(|u| (0.0..=total).contains(u)) {
                assert_eq!(
                    guide.partition_point(cdf, u),
                    cdf.partition_point(|&c| c <= u),
                    "table of {} entries, draw {u:e}",
                    cdf.len()
                );
            }
        }
    }
}
