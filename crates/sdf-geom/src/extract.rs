//! Sparse isosurface extraction from any signed distance function: coarse-to-fine pruning with
//! the distance bound, then surface nets on the cells that can hold the surface.
//!
//! A dense `N³` grid is never allocated. Blocks of cells are evaluated at their centres, and a
//! block is kept only if `|Φ(centre)| ≤ lipschitz · half_diagonal + cell`: for a true SDF
//! (1-Lipschitz) a block farther from the surface than its half-diagonal cannot contain it. A
//! fitted network is only approximately 1-Lipschitz, hence the factor (default 1.5). Kept blocks
//! are split in eight until they are single cells; memory and evaluations then grow with the
//! surface area (∝ N²), not the volume.
//!
//! On the surviving cells, surface nets (Gibson 1998): one vertex per cell whose corners change
//! sign, at the mean of its edges' zero crossings; one quad, split in two triangles, per lattice
//! edge with a sign change, joining the four cells around it. Vertices are shared, and triangles
//! are wound so their normals point outwards (towards positive distance).
//!
//! One vertex per cell has a cost: where a cell face's corners alternate in sign (+, −, +, −:
//! two sheets or a saddle within one cell), the quads of that face's four edges all join the
//! same two cell vertices, and up to four triangles share an edge. The mesh stays consistently
//! wound but is not manifold there; a finer resolution separates such sheets.

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::Mesh;

/// Largest accepted resolution: 4096³ cells is far beyond what any network here resolves.
pub const MAX_RESOLUTION: u32 = 4096;

/// Settings of [`extract_surface`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExtractOptions {
    /// Cells per axis over the domain.
    pub resolution: u32,
    /// Half-size of the cubic domain centred at the origin; slightly more than 1 so that a
    /// surface touching the normalised box is closed.
    pub half_size: f32,
    /// Safety factor on the distance bound used to prune blocks.
    pub lipschitz: f32,
    /// Memory budget in bytes. Once the pruning is fine enough to predict the surface's cell
    /// count (blocks of [`PREDICT_BLOCK`] cells), an extraction whose estimate passes it stops
    /// with [`ExtractError::OverBudget`] before the fine levels allocate anything.
    pub max_bytes: u64,
}

/// Default [`ExtractOptions::max_bytes`]: 4 GiB.
pub const EXTRACT_MEMORY_BUDGET: u64 = 4 << 30;

/// Host bytes per kept finest-level cell, all buffers at their peak together (cells, corner
/// keys before deduplication, corner points and values, cell vertices, the mesh), plus the OBJ
/// text and the GPU's evaluation buffers (host memory on a CPU adapter). Measured: the `budget`
/// test at 1024³ peaks at 836 MB for 6.7 M cells (124 B/cell, extraction and mesh only); the
/// OBJ text adds about 26 B/cell. The `extract` binary at 1024³ on a plane model peaks at
/// 745 MB for 5.2 M cells (142 B/cell, lavapipe), so this errs on the safe side by about 40%.
pub const BYTES_PER_CELL: u64 = 200;

/// Block size (cells) at which the kept blocks predict the final cell count.
pub const PREDICT_BLOCK: u32 = 16;

/// Final cells per kept cell of a block at [`PREDICT_BLOCK`] (kept blocks × block² × this):
/// the kept shell is about 4.6 cells thick at the finest level and 2.7 blocks thick at block
/// size 16, so the ratio is about 1.7 for smooth surfaces; 2 leaves a margin.
const PREDICT_RATIO: u64 = 2;

impl ExtractOptions {
    /// Defaults for `resolution`: domain `[-1.05, 1.05]³`, bound factor 1.5.
    pub fn new(resolution: u32) -> Self {
        ExtractOptions {
            resolution,
            half_size: 1.05,
            lipschitz: 1.5,
            max_bytes: EXTRACT_MEMORY_BUDGET,
        }
    }
}

/// Errors of [`extract_surface`]: bad options, or the evaluation's own error.
#[derive(Debug, thiserror::Error)]
pub enum ExtractError<E: std::error::Error + 'static> {
    /// Resolution outside `2..=MAX_RESOLUTION`.
    #[error("resolution {0} is out of range: use 2 to {MAX_RESOLUTION} cells per axis")]
    Resolution(u32),
    /// A non-positive or non-finite domain size or bound factor.
    #[error("invalid extraction option: {0}")]
    Options(&'static str),
    /// The distance evaluation failed.
    #[error(transparent)]
    Eval(E),
    /// The extraction would pass its memory budget.
    #[error(
        "extracting at {resolution}³ would need about {:.1} GiB ({cells} surface cells), over the {:.1} GiB budget; use a lower resolution (the need grows with its square)",
        *.need as f64 / (1u64 << 30) as f64, *.budget as f64 / (1u64 << 30) as f64
    )]
    OverBudget {
        /// The resolution asked.
        resolution: u32,
        /// Predicted cells at the finest level.
        cells: u64,
        /// Estimated bytes.
        need: u64,
        /// The budget.
        budget: u64,
    },
    /// The evaluation returned a different number of values than points.
    #[error("the distance function returned {got} values for {expected} points")]
    EvalLength {
        /// Points asked.
        expected: usize,
        /// Values returned.
        got: usize,
    },
    /// The distance function returned NaN or an infinity (a model whose weights overflow, for
    /// example): no surface can be placed through it.
    #[error(
        "the distance function returned {value} at {point}: the model does not evaluate to finite values"
    )]
    NonFinite {
        /// The first such point (in the extraction's coordinates).
        point: Vec3,
        /// Its value.
        value: f32,
    },
}

/// What the extraction did, for reports and benchmarks.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExtractStats {
    /// Distance evaluations made in total.
    pub evaluations: u64,
    /// `(block size in cells, blocks kept)` per level, coarse to fine.
    pub levels: Vec<(u32, usize)>,
    /// Cells kept at the finest level.
    pub cells: usize,
}

/// Extracts the zero level set of `eval` (points in, signed distances out, negative inside)
/// over the cube `[-half_size, half_size]³`. `eval` is called with batches (one per level, then
/// one for the cell corners); it should split them to fit its device itself.
pub fn extract_surface<E: std::error::Error + 'static>(
    mut eval: impl FnMut(&[Vec3]) -> Result<Vec<f32>, E>,
    options: &ExtractOptions,
) -> Result<(Mesh, ExtractStats), ExtractError<E>> {
    let n = options.resolution;
    if !(2..=MAX_RESOLUTION).contains(&n) {
        return Err(ExtractError::Resolution(n));
    }
    if !(options.half_size.is_finite() && options.half_size > 0.0) {
        return Err(ExtractError::Options(
            "half_size must be finite and positive",
        ));
    }
    if !(options.lipschitz.is_finite() && options.lipschitz > 0.0) {
        return Err(ExtractError::Options(
            "lipschitz must be finite and positive",
        ));
    }
    let h = 2.0 * options.half_size / n as f32;
    let origin = Vec3::splat(-options.half_size);
    let lattice = |p: IVec3| origin + p.as_vec3() * h;
    let mut stats = ExtractStats::default();
    let mut call =
        |points: &[Vec3], stats: &mut ExtractStats| -> Result<Vec<f32>, ExtractError<E>> {
            stats.evaluations += points.len() as u64;
            let v = eval(points).map_err(ExtractError::Eval)?;
            if v.len() != points.len() {
                return Err(ExtractError::EvalLength {
                    expected: points.len(),
                    got: v.len(),
                });
            }
            // A NaN corner would count as outside, and its edge's crossing would be NaN.
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(ExtractError::NonFinite {
                    point: points[i],
                    value: v[i],
                });
            }
            Ok(v)
        };

    let mut cells = surface_cells(options, h, &lattice, &mut call, &mut stats)?;
    cells.par_sort_unstable_by_key(|&c| key(c));
    stats.cells = cells.len();

    // Distances at every corner of every kept cell, each lattice point once.
    let mut corners: Vec<u64> = cells
        .par_iter()
        .flat_map_iter(|&c| (0..8).map(move |i| key(c + corner(i))))
        .collect();
    corners.par_sort_unstable();
    corners.dedup();
    let corner_points: Vec<Vec3> = corners.iter().map(|&k| lattice(unkey(k))).collect();
    let corner_values = call(&corner_points, &mut stats)?;
    drop(corner_points);
    let value_at = |p: IVec3| -> f32 {
        let i = corners
            .binary_search(&key(p))
            .expect("every corner of a kept cell was evaluated");
        corner_values[i]
    };

    let (vertices, vertex_index) = cell_vertices(&cells, &value_at, &lattice, h);
    let triangles = cell_quads(&cells, &vertices, &vertex_index, &value_at);
    Ok((
        Mesh {
            vertices,
            triangles,
        },
        stats,
    ))
}

/// The coarse-to-fine pruning: blocks of cells evaluated at their centres (through `call`, which
/// counts the evaluations in `stats`), those that cannot hold the surface dropped, the others
/// split in eight, down to single cells, which are returned (unsorted). Stops with
/// [`ExtractError::OverBudget`] as soon as the kept blocks predict too many cells.
fn surface_cells<E: std::error::Error + 'static>(
    options: &ExtractOptions,
    h: f32,
    lattice: &impl Fn(IVec3) -> Vec3,
    call: &mut impl FnMut(&[Vec3], &mut ExtractStats) -> Result<Vec<f32>, ExtractError<E>>,
    stats: &mut ExtractStats,
) -> Result<Vec<IVec3>, ExtractError<E>> {
    let n = options.resolution;
    // Top blocks of 2^k cells, about 8 per axis.
    let mut size = (n / 8).max(1).next_power_of_two();
    let per_axis = n.div_ceil(size) as i32;
    // Both powers of two, so the halving levels pass through it.
    let predict_at = size.min(PREDICT_BLOCK);
    let mut blocks: Vec<IVec3> = (0..per_axis)
        .flat_map(|z| {
            (0..per_axis).flat_map(move |y| (0..per_axis).map(move |x| IVec3::new(x, y, z)))
        })
        .map(|b| b * size as i32)
        .collect();
    loop {
        let centers: Vec<Vec3> = blocks
            .iter()
            .map(|&b| lattice(b) + Vec3::splat(0.5 * size as f32 * h))
            .collect();
        let values = call(&centers, stats)?;
        let half_diag = 0.5 * 3f32.sqrt() * size as f32 * h;
        let bound = options.lipschitz * half_diag + h;
        // `call` has refused NaN values already.
        let kept: Vec<IVec3> = blocks
            .iter()
            .zip(&values)
            .filter(|&(_, v)| v.abs() <= bound)
            .map(|(b, _)| *b)
            .collect();
        stats.levels.push((size, kept.len()));
        // Coarser levels overestimate (a block of a thin part counts as a full shell); here the
        // prediction is good and the levels so far have cost little.
        if size == predict_at {
            let cells = kept.len() as u64 * u64::from(size).pow(2) * PREDICT_RATIO;
            let need = cells.saturating_mul(BYTES_PER_CELL);
            if need > options.max_bytes {
                return Err(ExtractError::OverBudget {
                    resolution: n,
                    cells,
                    need,
                    budget: options.max_bytes,
                });
            }
        }
        if size == 1 {
            return Ok(kept);
        }
        let child = size / 2;
        blocks = kept
            .par_iter()
            .flat_map_iter(|&b| {
                (0..8).filter_map(move |c| {
                    let o = IVec3::new(c & 1, (c >> 1) & 1, (c >> 2) & 1) * child as i32;
                    let p = b + o;
                    (p.max_element() < n as i32).then_some(p)
                })
            })
            .collect();
        size = child;
    }
}

/// Surface nets' vertices: one per cell (of the sorted `cells`) whose corners change sign, at the
/// mean of its edges' zero crossings. Returns the vertices and each cell's vertex index
/// (`u32::MAX`: none).
fn cell_vertices(
    cells: &[IVec3],
    value_at: &(impl Fn(IVec3) -> f32 + Sync),
    lattice: &(impl Fn(IVec3) -> Vec3 + Sync),
    h: f32,
) -> (Vec<Vec3>, Vec<u32>) {
    let cell_vertices: Vec<Option<Vec3>> = cells
        .par_iter()
        .map(|&c| {
            let v: [f32; 8] = std::array::from_fn(|i| value_at(c + corner(i)));
            let inside = v.iter().filter(|&&x| x < 0.0).count();
            if inside == 0 || inside == 8 {
                return None;
            }
            let mut sum = Vec3::ZERO;
            let mut count = 0;
            for (a, b) in CUBE_EDGES {
                let (va, vb) = (v[a], v[b]);
                if (va < 0.0) != (vb < 0.0) {
                    let t = va / (va - vb);
                    let pa = corner(a).as_vec3();
                    let pb = corner(b).as_vec3();
                    sum += pa + (pb - pa) * t.clamp(0.0, 1.0);
                    count += 1;
                }
            }
            Some(lattice(c) + sum / count as f32 * h)
        })
        .collect();
    let mut vertex_index = vec![u32::MAX; cells.len()];
    let mut vertices = Vec::new();
    for (i, v) in cell_vertices.iter().enumerate() {
        if let Some(p) = v {
            vertex_index[i] = vertices.len() as u32;
            vertices.push(*p);
        }
    }
    (vertices, vertex_index)
}

/// Surface nets' faces: one quad (two triangles) per lattice edge with a sign change, joining
/// the vertices of the four cells around it, handled by the cell at the edge's start and wound so
/// that its normal points towards positive distance.
fn cell_quads(
    cells: &[IVec3],
    vertices: &[Vec3],
    vertex_index: &[u32],
    value_at: &(impl Fn(IVec3) -> f32 + Sync),
) -> Vec<[u32; 3]> {
    let cell_vertex = |c: IVec3| -> Option<u32> {
        let i = cells.binary_search_by_key(&key(c), |&x| key(x)).ok()?;
        (vertex_index[i] != u32::MAX).then_some(vertex_index[i])
    };
    cells
        .par_iter()
        .enumerate()
        .filter(|&(i, _)| vertex_index[i] != u32::MAX)
        .flat_map_iter(|(_, &c)| {
            let v0 = value_at(c);
            let mut out = Vec::new();
            for axis in 0..3 {
                let e = IVec3::AXES[axis];
                let v1 = value_at(c + e);
                if (v0 < 0.0) == (v1 < 0.0) {
                    continue;
                }
                let (u, w) = (IVec3::AXES[(axis + 1) % 3], IVec3::AXES[(axis + 2) % 3]);
                if (c - u).min_element() < 0 || (c - w).min_element() < 0 {
                    continue;
                }
                let ring = [c, c - u, c - u - w, c - w].map(cell_vertex);
                let [Some(a), Some(b), Some(cc), Some(d)] = ring else {
                    continue;
                };
                // (c, c-u, c-u-w, c-w) turns counter-clockwise seen from +axis (u, w, axis is
                // right-handed), so its normal is +axis: right when the edge runs from inside
                // to outside, reversed otherwise, so normals point towards positive distance.
                let quad = if v0 < 0.0 {
                    [a, b, cc, d]
                } else {
                    [a, d, cc, b]
                };
                out.extend(split_quad(quad, vertices));
            }
            out
        })
        .collect()
}

/// Splits a quad along its shorter diagonal.
fn split_quad([a, b, c, d]: [u32; 4], vertices: &[Vec3]) -> [[u32; 3]; 2] {
    let p = |i: u32| vertices[i as usize];
    if p(a).distance_squared(p(c)) <= p(b).distance_squared(p(d)) {
        [[a, b, c], [a, c, d]]
    } else {
        [[a, b, d], [b, c, d]]
    }
}

/// Offset of corner `i` (bit 0: x, bit 1: y, bit 2: z).
fn corner(i: usize) -> IVec3 {
    IVec3::new((i & 1) as i32, ((i >> 1) & 1) as i32, ((i >> 2) & 1) as i32)
}

/// The 12 edges of a cell as corner pairs.
const CUBE_EDGES: [(usize, usize); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

/// Lattice coordinates (each in `0..=MAX_RESOLUTION`) packed in 21 bits each; the order is z, y, x.
fn key(p: IVec3) -> u64 {
    ((p.z as u64) << 42) | ((p.y as u64) << 21) | p.x as u64
}

fn unkey(k: u64) -> IVec3 {
    let m = (1u64 << 21) - 1;
    IVec3::new((k & m) as i32, ((k >> 21) & m) as i32, (k >> 42) as i32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::convert::Infallible;

    fn sphere(r: f32) -> impl FnMut(&[Vec3]) -> Result<Vec<f32>, Infallible> {
        move |p| Ok(p.iter().map(|p| p.length() - r).collect())
    }

    #[test]
    fn sphere_vertices_lie_on_the_sphere() {
        let r = 0.7;
        let (mesh, stats) = extract_surface(sphere(r), &ExtractOptions::new(64)).unwrap();
        assert!(!mesh.triangles.is_empty());
        let h = 2.1 / 64.0;
        for v in &mesh.vertices {
            assert!((v.length() - r).abs() < 0.1 * h, "{v} at {}", v.length());
        }
        // Sparse: far fewer evaluations than the dense 65³ corner grid.
        assert!(stats.evaluations < 65u64.pow(3) / 2, "{stats:?}");
        // Closed and consistently wound: every edge is shared by exactly two triangles, in
        // opposite directions, and the enclosed volume is the sphere's, positive (outward normals).
        let mut edges = std::collections::HashMap::new();
        for t in &mesh.triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1, "directed edge {a}->{b} used {count} times");
            assert!(edges.contains_key(&(b, a)), "edge {a}->{b} has no twin");
        }
        let volume = mesh.signed_volume() as f32;
        let exact = 4.0 / 3.0 * std::f32::consts::PI * r * r * r;
        assert!((volume - exact).abs() < 0.02 * exact, "{volume} vs {exact}");
    }

    #[test]
    fn pruning_keeps_surface_cells_only() {
        let (_, coarse) = extract_surface(sphere(0.5), &ExtractOptions::new(32)).unwrap();
        let (_, fine) = extract_surface(sphere(0.5), &ExtractOptions::new(128)).unwrap();
        // Cells grow with area: 4x per doubling, so 16x from 32 to 128 (volume would be 64x).
        let ratio = fine.cells as f64 / coarse.cells as f64;
        assert!((10.0..24.0).contains(&ratio), "{ratio}");
    }

    #[test]
    fn bad_options_are_errors() {
        for n in [0, 1, MAX_RESOLUTION + 1] {
            assert!(matches!(
                extract_surface(sphere(0.5), &ExtractOptions::new(n)),
                Err(ExtractError::Resolution(_))
            ));
        }
        let mut o = ExtractOptions::new(16);
        o.lipschitz = f32::NAN;
        assert!(matches!(
            extract_surface(sphere(0.5), &o),
            Err(ExtractError::Options(_))
        ));
        let short = |_: &[Vec3]| Ok::<_, Infallible>(vec![0.0]);
        assert!(matches!(
            extract_surface(short, &ExtractOptions::new(16)),
            Err(ExtractError::EvalLength { .. })
        ));
        // NaN on one side of a surface: an error, not vertices at NaN.
        let half_nan = |p: &[Vec3]| {
            Ok::<_, Infallible>(
                p.iter()
                    .map(|p| {
                        if p.x > 0.0 {
                            f32::NAN
                        } else {
                            p.length() - 0.5
                        }
                    })
                    .collect(),
            )
        };
        match extract_surface(half_nan, &ExtractOptions::new(16)) {
            Err(ExtractError::NonFinite { point, value }) => {
                assert!(point.x > 0.0 && value.is_nan(), "{point} {value}")
            }
            other => panic!("{other:?}"),
        }
    }

    /// The prediction made at block size 16 bounds the real cell count from above, by less than
    /// a factor 2, and a budget below it stops the extraction with the estimate.
    #[test]
    fn budget() {
        let n = std::env::var("HWSDF_EXTRACT_BUDGET_RES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(256);
        let (mesh, stats) = extract_surface(sphere(0.7), &ExtractOptions::new(n)).unwrap();
        let at16 = stats.levels.iter().find(|l| l.0 == PREDICT_BLOCK).unwrap();
        let predicted = at16.1 as u64 * 256 * PREDICT_RATIO;
        let cells = stats.cells as u64;
        eprintln!(
            "{n}: {cells} cells, predicted {predicted}, {} vertices, {} triangles",
            mesh.vertices.len(),
            mesh.triangles.len()
        );
        assert!(
            cells <= predicted && predicted < 2 * cells,
            "{cells} {predicted}"
        );
        let mut options = ExtractOptions::new(n);
        options.max_bytes = predicted * BYTES_PER_CELL - 1;
        match extract_surface(sphere(0.7), &options) {
            Err(ExtractError::OverBudget { cells, need, .. }) => {
                assert_eq!((cells, need), (predicted, predicted * BYTES_PER_CELL))
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn keys_round_trip() {
        for p in [
            IVec3::ZERO,
            IVec3::new(4096, 17, 3),
            IVec3::new(1, 4096, 4096),
        ] {
            assert_eq!(unkey(key(p)), p);
        }
    }
}
