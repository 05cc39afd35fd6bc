//! A Lipschitz estimate of a [`NeuralSdf`], measured once per model, so that sphere tracing
//! can step by a bound on a function that is only approximately a distance.
//!
//! ```
//! use sdf_nn::{NeuralSdf, Nglod, Normalization};
//! use sdf_nn::serve::scene::lipschitz::{SAFETY, estimate};
//!
//! let sphere = Nglod::from_sdf(16, |p| p.length() - 0.5).unwrap();
//! let file = sphere.to_model_file(Normalization::identity(), serde_json::Value::Null);
//! let model = NeuralSdf::from_model_file(file).unwrap();
//! // An exact distance has |∇Φ| = 1; outside the box the rule Φ(clamp x) + |x − clamp x|
//! // adds the tangential gradient on the box's faces.
//! let l = estimate(&model);
//! assert!(l >= SAFETY && l < 2.0 * SAFETY);
//! ```
//!
//! **How.** On a grid of [`GRID`]³ cells over the model's normalised box `[-1, 1]³` (its vertices
//! and its cell centres, `(GRID+1)³ + GRID³` points) the network's raw gradient `∇Φ` (SIREN's
//! forward-mode gradient, NGLOD's analytic one, before any normalisation) is evaluated on CPU
//! threads. `L_in` is the largest `|∇Φ|`. Outside the box a model is served as
//! `f(x) = Φ(c(x)) + |x − c(x)|` with `c` the clamp to the box; there `∇f` is the part of `∇Φ`
//! along the box's free axes at `c(x)` plus a unit vector orthogonal to it, so
//! `|∇f|² = |∇_tan Φ|² + 1`. `T` is the largest tangential `|∇_tan Φ|` over the samples on the
//! box's faces (the clamped axes' components zeroed). The estimate is
//! `SAFETY · max(L_in, √(1 + T²))`, in the model's mesh units per mesh unit (the same number as
//! in normalised units: the normalisation scales distances and coordinates alike), and never
//! below `SAFETY`.
//!
//! **What it guarantees.** It is a measurement, not a proof: if the true Lipschitz constant of
//! the served function is at most [`SAFETY`] times the sampled maximum (its gradient does not
//! peak more than 25% above every sample, which holds when the network has no feature much finer
//! than the sample spacing `1/GRID` of the half box), then `|f(x) − f(y)| ≤ L |x − y|`, and a
//! sphere tracer stepping by `(f − c)/L` never steps over a crossing of the level `c`. A model
//! whose features are finer than that can be given a known bound instead
//! ([`crate::serve::scene::Scene::set_model_lipschitz`]).
//!
//! **Near a point.** The same samples give each cell of a [`LOCAL_CELLS`]³ grid over the box
//! its own bound ([`LocalLipschitz`]); the ray tracer divides by the bound of the cell (or
//! block of cells) that holds its step's ball. That assumes more: the gradient does not peak
//! 25 % above the samples *of that cell*, where the estimate had the margin of the whole box's
//! largest sample over any gentler cell. A network with features finer than the samples (an
//! NGLOD level finer than [`GRID`] cells, such as `default`'s sparse 48) is checked less
//! closely in its gentle cells; [`crate::serve::scene::Scene::set_model_lipschitz`] turns the
//! local bounds off with a bound the caller knows.
//!
//! **Floors.** The same samples' values give each cell of the [`GRID`]³ grid a floor of the
//! network's value ([`CellFloors`]), which scenes cull models by.

use glam::Vec3;
use rayon::prelude::*;

use crate::NeuralSdf;
use crate::serve::network::Network;

/// Cells per axis of the sample grid.
pub const GRID: usize = 32;

/// The factor the sampled maximum is multiplied by.
pub const SAFETY: f32 = 1.25;

/// The Lipschitz estimate of `model` (see the module docs): at least [`SAFETY`].
pub fn estimate(model: &NeuralSdf) -> f32 {
    LocalLipschitz::measure(model).global()
}

/// The estimate from the samples' gradients (see the module docs).
fn global_estimate(points: &[Vec3], gradients: &[Vec3]) -> f32 {
    let (inside, tangential) = points
        .par_iter()
        .zip(gradients)
        .map(|(p, g)| {
            // Axes on which the point sits on a face are the clamped ones outside it.
            let on_face = p.abs().cmpge(Vec3::ONE);
            let tangential = Vec3::select(on_face, Vec3::ZERO, *g);
            let t = if on_face.any() {
                tangential.length()
            } else {
                0.0
            };
            (g.length(), t)
        })
        .reduce(|| (0.0f32, 0.0f32), |a, b| (a.0.max(b.0), a.1.max(b.1)));
    let outside = (1.0 + tangential * tangential).sqrt();
    SAFETY * inside.max(outside).max(1.0)
}

/// The farthest any point of a [`GRID`]³ cell is from the cell's vertices and centre, in
/// normalised units: the covering radius of the body-centred cubic lattice, √5/4 of the cell's
/// side (half the side was assumed before: a point such as a quarter of the way along a face's
/// midline is farther from all nine).
pub const COVER: f32 = 2.236_068 / 4.0 * (2.0 / GRID as f32);

/// Floors of a model's network value Φ per cell of the [`GRID`]³ sample grid over its
/// normalised box, for culling: a scene skips a model where the floor at a point says it
/// cannot change a union, so where most of a scene's points are far from most of its models,
/// most model evaluations are skipped (the box's one floor, −0.40 for the example's spot, skips
/// none inside the box).
///
/// **How.** Each cell's floor is the smallest value at its nine samples of [`estimate`] (its
/// vertices and its centre) less [`COVER`] times the local Lipschitz bound of the
/// [`LOCAL_CELLS`]³ cell that holds it ([`LocalLipschitz`]): every point of the cell is within
/// [`COVER`] of one of the nine, along a segment inside that cell. **What it guarantees**: a
/// bound wherever the local bound bounds Φ's slope, which is what the ray tracer assumes of it.
#[derive(Clone, Debug, PartialEq)]
pub struct CellFloors {
    /// Per cell (x major, then y, then z).
    cells: Vec<f32>,
}

impl CellFloors {
    /// Measures `model`'s floors with the slope bounds of `local` (its own, measured by
    /// [`LocalLipschitz::measure`], or a bound the caller knows).
    pub fn measure(model: &NeuralSdf, local: &LocalLipschitz) -> Self {
        let values = model.eval_cpu_normalized(&sample_points());
        let (g, s) = (GRID, GRID + 1);
        let vertex = |x: usize, y: usize, z: usize| values[(x * s + y) * s + z];
        let centres = &values[s * s * s..];
        let per = GRID / LOCAL_CELLS;
        let cells = (0..g * g * g)
            .into_par_iter()
            .map(|i| {
                let (x, y, z) = (i / (g * g), i / g % g, i % g);
                let mut min = centres[i];
                for corner in 0..8 {
                    let (dx, dy, dz) = (corner >> 2, corner >> 1 & 1, corner & 1);
                    min = min.min(vertex(x + dx, y + dy, z + dz));
                }
                let n = LOCAL_CELLS;
                let slope = local.cell[((x / per) * n + y / per) * n + z / per];
                min - slope * COVER
            })
            .collect();
        CellFloors { cells }
    }

    /// The floor at the normalised point `q` (its cell's; a point outside the box is
    /// clamped to it, as a model's value outside its box is taken at the clamped point).
    pub fn at(&self, q: Vec3) -> f32 {
        let g = GRID as f32;
        let c = ((q + Vec3::ONE) * (g / 2.0))
            .floor()
            .clamp(Vec3::ZERO, Vec3::splat(g - 1.0));
        let n = GRID;
        let index = (c.x as usize * n + c.y as usize) * n + c.z as usize;
        self.cells[index.min(self.cells.len() - 1)]
    }

    /// The smallest floor: one floor for the whole box.
    pub fn min(&self) -> f32 {
        self.cells.iter().copied().fold(f32::INFINITY, f32::min)
    }

    /// Raises every floor to at least `floor` (another bound known to hold everywhere).
    pub fn raise_to(&mut self, floor: f32) {
        for c in &mut self.cells {
            *c = c.max(floor);
        }
    }

    /// The cells' floors (x major, then y, then z), in the model's buffers' order.
    pub fn table(&self) -> &[f32] {
        &self.cells
    }
}

/// The grid's vertices and cell centres in `[-1, 1]³`.
fn sample_points() -> Vec<Vec3> {
    let vertex = |i: usize| i as f32 * (2.0 / GRID as f32) - 1.0;
    let centre = |i: usize| (i as f32 + 0.5) * (2.0 / GRID as f32) - 1.0;
    let s = GRID + 1;
    let mut points = Vec::with_capacity(s * s * s + GRID * GRID * GRID);
    for x in 0..s {
        for y in 0..s {
            for z in 0..s {
                points.push(Vec3::new(vertex(x), vertex(y), vertex(z)));
            }
        }
    }
    for x in 0..GRID {
        for y in 0..GRID {
            for z in 0..GRID {
                points.push(Vec3::new(centre(x), centre(y), centre(z)));
            }
        }
    }
    points
}

/// The network's raw gradients at `points` (normalised coordinates).
fn gradients(model: &NeuralSdf, points: &[Vec3]) -> Vec<Vec3> {
    match model.network() {
        Network::Siren(s) => s.gradient_cpu(points),
        Network::Nglod(m) => m
            .gradient_cpu(points, model.lod())
            .expect("the level of detail was validated by NeuralSdf::set_lod"),
    }
}

/// Cells per axis of a [`LocalLipschitz`] grid.
pub const LOCAL_CELLS: usize = 8;

/// Lipschitz bounds of a model per cell of a [`LOCAL_CELLS`]³ grid over its normalised box,
/// for sphere tracers: the model's slope is mostly near 1, and the estimate over the whole box
/// (2.96 for the example's spot model) is set by a few cells (the median cell's is 1.52), so a
/// tracer that steps by the bound where it is gets steps about twice as long near the model.
///
/// **How.** The samples of [`estimate`] (the 32³ grid's vertices and centres, each cell of this
/// grid holding 4³ of them, its faces' included) give each cell `SAFETY · max |∇Φ|` (at least
/// 1, at most the model's estimate), and each cell the largest of the 3³ cells around it
/// (clipped to the box). **What it guarantees**: the estimate's assumption, cell by cell (the
/// gradient does not peak more than 25 % above every sample of the cell; the module docs say
/// what that adds). A ball of radius
/// `|Φ − c| / L` around a point holds no crossing of the level `c` if it lies inside the cell
/// (or the block of 3³ cells) whose bound `L` is: [`LocalLipschitz::bound`] takes the cell's
/// where its ball fits, else the block's where its ball fits, else the model's estimate. A ball
/// free of the crossing is what the tracer's steps, cones and over-relaxation rely on. Every
/// bound it holds is at least 1 (whichever way it was made), as the scene steps by no bound
/// below: the CPU tracer and the GPU's tables use them as they are.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalLipschitz {
    /// Per cell (x major, then y, then z).
    cell: Vec<f32>,
    /// Per cell, the largest bound of the 3³ cells around it.
    block: Vec<f32>,
    /// The model's estimate over the whole box (and outside it).
    global: f32,
}

impl LocalLipschitz {
    /// Measures `model`'s estimate ([`estimate`]) and its grid from the same samples.
    pub fn measure(model: &NeuralSdf) -> Self {
        let points = sample_points();
        let gradients = gradients(model, &points);
        let global = global_estimate(&points, &gradients);
        let n = LOCAL_CELLS;
        let per = (GRID / n) as f32;
        let mut cell = vec![1.0f32; n * n * n];
        for (p, g) in points.iter().zip(&gradients) {
            // A sample on a cell face or edge belongs to every cell it touches.
            let span = |x: f32| {
                let u = (x + 1.0) * (GRID as f32 / 2.0) / per;
                let last = n as i64 - 1;
                let cell = u.floor() as i64;
                // On a face between cells: the cell below too (the box's faces have one).
                let below = if u == u.floor() { cell - 1 } else { cell };
                below.clamp(0, last) as usize..=cell.clamp(0, last) as usize
            };
            let bound = SAFETY * g.length();
            for x in span(p.x) {
                for y in span(p.y) {
                    for z in span(p.z) {
                        let c = &mut cell[(x * n + y) * n + z];
                        *c = c.max(bound);
                    }
                }
            }
        }
        for c in &mut cell {
            *c = c.min(global);
        }
        let mut block = vec![0.0f32; n * n * n];
        for x in 0..n {
            for y in 0..n {
                for z in 0..n {
                    let near = |i: usize| i.saturating_sub(1)..=(i + 1).min(n - 1);
                    let mut m = 0.0f32;
                    for a in near(x) {
                        for b in near(y) {
                            for c in near(z) {
                                m = m.max(cell[(a * n + b) * n + c]);
                            }
                        }
                    }
                    block[(x * n + y) * n + z] = m;
                }
            }
        }
        LocalLipschitz {
            cell,
            block,
            global,
        }
    }

    /// A bound the caller knows of the network's slope in its box
    /// ([`crate::serve::scene::Scene::set_model_lipschitz`]), for every cell and block; the
    /// model's bound, which also holds outside the box, is `√(1 + bound²)`: there the served
    /// distance is the network's at the clamped point plus the distance to the box, whose slope
    /// reaches `√(1 + T²)` for a gradient `T ≤ bound` along the box's face. The cells and blocks
    /// hold at least 1, as every bound the scene steps by does (a bound below 1 had the CPU test
    /// its balls smaller than the GPU's tables, clamped then, and the two tracers' steps
    /// differed).
    pub fn uniform(bound: f32) -> Self {
        let cells = LOCAL_CELLS * LOCAL_CELLS * LOCAL_CELLS;
        LocalLipschitz {
            cell: vec![bound.max(1.0); cells],
            block: vec![bound.max(1.0); cells],
            global: bound.hypot(1.0),
        }
    }

    /// The bound to divide `gap` (the value less the level, normalised units) by at the
    /// normalised point `q`: the cell's if the ball of radius `|gap| / bound` lies in the cell,
    /// else the block's if its ball lies in the block, else the model's estimate (also outside
    /// the box, and for a NaN).
    pub fn bound(&self, q: Vec3, gap: f32) -> f32 {
        if !q.is_finite() || q.abs().max_element() >= 1.0 {
            return self.global;
        }
        let n = LOCAL_CELLS;
        let u = (q + Vec3::ONE) * (n as f32 / 2.0);
        let c = u.floor().clamp(Vec3::ZERO, Vec3::splat(n as f32 - 1.0));
        let f = u - c;
        let side = 2.0 / n as f32;
        let index = ((c.x as usize * n) + c.y as usize) * n + c.z as usize;
        let room_cell = f.min(Vec3::ONE - f).min_element() * side;
        let bound = self.cell[index];
        if gap.abs() <= bound * room_cell {
            return bound;
        }
        // The block reaches a cell further on each side, but not past the box.
        let below = f + c.min(Vec3::ONE);
        let above = (Vec3::ONE - f) + (Vec3::splat(n as f32 - 1.0) - c).min(Vec3::ONE);
        let room_block = below.min(above).min_element() * side;
        let bound = self.block[index];
        if gap.abs() <= bound * room_block {
            return bound;
        }
        self.global
    }

    /// The cells' bounds (x major, then y, then z) and the blocks', in the model's buffers'
    /// order.
    pub fn tables(&self) -> (&[f32], &[f32]) {
        (&self.cell, &self.block)
    }

    /// The model's estimate.
    pub fn global(&self) -> f32 {
        self.global
    }
}
