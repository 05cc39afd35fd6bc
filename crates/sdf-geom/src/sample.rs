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

fn rng(seed: u64) -> Pcg64Mcg {
    Pcg64Mcg::seed_from_u64(seed)
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
    let mut r = rng(seed);
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
    for _ in 0..n {
        let u = r.random::<f64>() * total;
        let ti = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
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

/// `n` points on the surface, uniform with respect to area, with face normals.
/// A mesh without area gives no samples.
pub fn surface(mesh: &Mesh, n: usize, seed: u64) -> SurfaceSamples {
    sample_surface_with(mesh, n, &mut rng(seed))
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
    let mut r = rng(seed);
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
    let mut r = rng(seed);
    let s = sample_surface_with(mesh, n, &mut r);
    s.points
        .into_iter()
        .map(|p| p + Vec3::new(gaussian(&mut r), gaussian(&mut r), gaussian(&mut r)) * sigma)
        .collect()
}

/// Poisson-disk samples on the surface by weighted sample elimination (Yuksel 2015, "Sample
/// Elimination for Generating Poisson Disk Sample Sets"): draw 5n area-uniform candidates, give each
/// a weight Σ (1 − d̂/2r_max)^8 over neighbours within 2·r_max (Euclidean, with Yuksel's weight
/// limiting d̂ = max(d, 2·r_min)), and repeatedly remove the candidate with the largest weight until
/// `n` remain. Kept samples are returned in candidate order.
///
/// Returns fewer than `n` samples only for a mesh without area.
pub fn poisson_disk(mesh: &Mesh, n: usize, seed: u64) -> PoissonSamples {
    let area = mesh.area();
    if n == 0 || area.is_nan() || area <= 0.0 {
        return PoissonSamples {
            samples: SurfaceSamples::default(),
            min_distance: f32::INFINITY,
            target_radius: 0.0,
        };
    }
    let m = n.saturating_mul(5);
    let cand = surface(mesh, m, seed);
    let m = cand.len();
    let r_max = (area / (2.0 * 3f64.sqrt() * n as f64)).sqrt() as f32;
    let r_min = r_max * 0.65 * (1.0 - (n as f32 / m as f32).powf(1.5));
    let two_r_max = 2.0 * r_max;
    // The grid stores the candidates sorted by cell, so neighbour scans read contiguous memory;
    // all indices below are positions in that order.
    let grid = Grid::new(&cand.points, two_r_max);
    let pts = &grid.points;

    // Neighbour lists with the weight each neighbour contributes.
    let lists: Vec<Vec<(u32, f32)>> = (0..m)
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let p = pts[i];
            let mut v = Vec::with_capacity(32);
            grid.for_each_near(p, |j| {
                if j as usize != i {
                    let d = p.distance(pts[j as usize]);
                    if d < two_r_max {
                        let dh = d.max(2.0 * r_min);
                        let w = (1.0 - dh / two_r_max).powi(8);
                        v.push((j, w));
                    }
                }
            });
            v
        })
        .collect();
    let mut weight: Vec<f32> = lists.iter().map(|l| l.iter().map(|x| x.1).sum()).collect();

    // Max-heap with lazy updates: weights only ever decrease, so a stored key is an upper bound of
    // the current weight. When the top's key is stale it is refreshed and sifted down; a top whose
    // key is current is the true maximum.
    let mut heap = IndexedMaxHeap::new(weight.clone());
    let mut removed = vec![false; m];
    let mut remaining = m;
    while remaining > n {
        let Some(i) = heap.pop_current(&weight) else {
            break;
        };
        let iu = i as usize;
        removed[iu] = true;
        remaining -= 1;
        for &(j, wj) in &lists[iu] {
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
    /// The points, sorted by cell.
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
            points: Vec::with_capacity(points.len()),
            order: Vec::with_capacity(points.len()),
        };
        let mut keyed: Vec<((i32, i32, i32), u32)> = points
            .iter()
            .enumerate()
            .map(|(i, &p)| (g.key(p), i as u32))
            .collect();
        keyed.sort_unstable();
        let mut start = 0usize;
        while start < keyed.len() {
            let k = keyed[start].0;
            let mut end = start;
            while end < keyed.len() && keyed[end].0 == k {
                g.order.push(keyed[end].1);
                g.points.push(points[keyed[end].1 as usize]);
                end += 1;
            }
            g.cells.insert(k, (start as u32, end as u32));
            start = end;
        }
        g
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

/// A binary max-heap over items `0..n` keyed by a weight that can only decrease.
struct IndexedMaxHeap {
    key: Vec<f32>,
    heap: Vec<u32>,
    /// Position of each item in `heap`, `u32::MAX` once popped.
    pos: Vec<u32>,
}

impl IndexedMaxHeap {
    fn new(key: Vec<f32>) -> Self {
        let n = key.len();
        let mut h = IndexedMaxHeap {
            key,
            heap: (0..n as u32).collect(),
            pos: (0..n as u32).collect(),
        };
        for i in (0..n / 2).rev() {
            h.sift_down(i);
        }
        h
    }

    /// Strict order: larger weight first, ties broken by smaller index (deterministic).
    #[inline]
    fn above(&self, a: u32, b: u32) -> bool {
        let (ka, kb) = (self.key[a as usize], self.key[b as usize]);
        ka > kb || (ka == kb && a < b)
    }

    fn sift_down(&mut self, mut i: usize) {
        let n = self.heap.len();
        loop {
            let l = 2 * i + 1;
            if l >= n {
                break;
            }
            let r = l + 1;
            let mut c = l;
            if r < n && self.above(self.heap[r], self.heap[l]) {
                c = r;
            }
            if self.above(self.heap[c], self.heap[i]) {
                self.heap.swap(i, c);
                self.pos[self.heap[i] as usize] = i as u32;
                self.pos[self.heap[c] as usize] = c as u32;
                i = c;
            } else {
                break;
            }
        }
    }

    fn pop(&mut self) -> Option<u32> {
        let top = *self.heap.first()?;
        let last = self.heap.pop()?;
        self.pos[top as usize] = u32::MAX;
        if !self.heap.is_empty() {
            self.heap[0] = last;
            self.pos[last as usize] = 0;
            self.sift_down(0);
        }
        Some(top)
    }

    /// Pops the item with the largest current weight, refreshing stale keys (`current[i]` is never
    /// above the stored key of `i`).
    fn pop_current(&mut self, current: &[f32]) -> Option<u32> {
        loop {
            let top = *self.heap.first()?;
            let w = current[top as usize];
            if w == self.key[top as usize] {
                return self.pop();
            }
            self.key[top as usize] = w;
            self.sift_down(0);
        }
    }
}
