//! A batch's points grouped by cell on the GPU (`shaders/bin.wgsl`): a counting sort by the
//! Morton code of each point's cell in a grid over a box (about one cell per point, at most
//! 64³), recorded before a ground-truth kernel, which then takes its points in that order.
//! Neighbouring invocations query neighbouring points, so a SIMD group walks mostly the same
//! nodes: on a GPU, random points make each group of 32 pay for 32 different walks. The
//! points never leave the GPU (the training draw's), and a large batch costs no host sort (the
//! `sdf` command's).

use glam::{DVec3, Vec3};
use rayon::prelude::*;

use crate::gpu::{GpuContext, GpuError, GridLaunch, Launch, entry};
use crate::shaders;

/// Invocations per workgroup of `bin_count` and `bin_scatter` (`WG` in `bin.wgsl`).
const WG: u32 = 64;
/// Bits per axis of the finest grid, and its cells (`MAX_CELLS` in `bin.wgsl`): a finer grid
/// would cost the one-workgroup scan more than the order gains.
const MAX_BITS: u32 = 6;
const MAX_CELLS: u32 = 1 << (3 * MAX_BITS);

/// The kernels' uniform (`BinParams` in `bin.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct BinParams {
    n_points: u32,
    bits: u32,
    n_cells: u32,
    _pad0: u32,
    lo: [f32; 3],
    _pad1: f32,
    scale: [f32; 3],
    _pad2: f32,
}

impl BinParams {
    /// The first `n` points over a grid spanning `lo..hi` (finite corners) with about a cell
    /// per point (2^bits per axis, 8^bits ≥ n but for the cap). An axis of no extent, or one
    /// too small or too large for an f32 scale, gets a scale that still keeps every key
    /// finite: grouping is a matter of speed, never of results.
    pub(crate) fn new(n: u32, lo: Vec3, hi: Vec3) -> Self {
        let log2_n = 32 - (n.max(2) - 1).leading_zeros();
        let bits = log2_n.div_ceil(3).clamp(1, MAX_BITS);
        let extent = hi.as_dvec3() - lo.as_dvec3();
        let scale = DVec3::splat(f64::from(1u32 << bits)) / extent;
        let scale = scale.to_array().map(|s| {
            if s.is_finite() && s > 0.0 {
                // Normal: a GPU that flushes subnormals would make inf · 0 = NaN of it.
                s.clamp(f64::from(f32::MIN_POSITIVE), f64::from(f32::MAX)) as f32
            } else {
                1.0
            }
        });
        BinParams {
            n_points: n,
            bits,
            n_cells: 1 << (3 * bits),
            _pad0: 0,
            lo: lo.to_array(),
            _pad1: 0.0,
            scale,
            _pad2: 0.0,
        }
    }

    /// The Morton code of `p`'s cell, as `cell_key` in `bin.wgsl` computes it.
    #[cfg(test)]
    fn cell_key(&self, p: Vec3) -> u32 {
        if !p.is_finite() {
            return self.n_cells - 1;
        }
        let top = ((1u32 << self.bits) - 1) as f32;
        let c = ((p - Vec3::from(self.lo)) * Vec3::from(self.scale))
            .clamp(Vec3::ZERO, Vec3::splat(top));
        (spread10(c.x as u32) << 2) | (spread10(c.y as u32) << 1) | spread10(c.z as u32)
    }
}

/// The low 10 bits of `v`, two zero bits between each.
#[cfg(test)]
fn spread10(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    x = (x | (x << 2)) & 0x0924_9249;
    x
}

/// The bounding box of the finite points (the origin for none).
pub(crate) fn finite_box(points: &[Vec3]) -> (Vec3, Vec3) {
    let (lo, hi) = points
        .par_iter()
        .filter(|p| p.is_finite())
        .fold(
            || (Vec3::INFINITY, Vec3::NEG_INFINITY),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        )
        .reduce(
            || (Vec3::INFINITY, Vec3::NEG_INFINITY),
            |a, b| (a.0.min(b.0), a.1.max(b.1)),
        );
    if lo.cmple(hi).all() {
        (lo, hi)
    } else {
        (Vec3::ZERO, Vec3::ZERO)
    }
}

/// The grouping of up to `capacity` points of one buffer: its uniform, counts and order, and
/// its three launches.
#[derive(Debug)]
pub(crate) struct CellOrder {
    uniform: wgpu::Buffer,
    counts: wgpu::Buffer,
    order: wgpu::Buffer,
    count: Launch,
    scan: Launch,
    scatter: Launch,
    capacity: u32,
}

impl CellOrder {
    /// Binds the kernels to `points` (3 f32 per point) for batches of at most `capacity`.
    ///
    /// # Errors
    /// The GPU's (pipelines, an order buffer beyond the device's limits).
    pub(crate) fn new(
        gpu: &GpuContext,
        points: &wgpu::Buffer,
        capacity: u32,
    ) -> Result<Self, GpuError> {
        let uniform = gpu.uniform("bin params", &BinParams::new(0, Vec3::ZERO, Vec3::ZERO));
        let counts = gpu.storage_zeroed("bin counts", u64::from(MAX_CELLS) * 4)?;
        let order = gpu.storage_zeroed("bin order", u64::from(capacity.max(1)) * 4)?;
        let shader = &shaders::GROUND_TRUTH_BIN;
        let launch = |name: &str, entries: &[wgpu::BindGroupEntry<'_>]| {
            let pipeline = gpu.pipeline(shader, name, &[])?;
            Ok::<_, GpuError>(Launch::new(gpu, &pipeline, name, entries, (0, 0, 0)))
        };
        let count = launch(
            "bin_count",
            &[entry(0, &uniform), entry(1, points), entry(2, &counts)],
        )?;
        let scan = launch("bin_scan", &[entry(0, &uniform), entry(2, &counts)])?;
        let scatter = launch(
            "bin_scatter",
            &[
                entry(0, &uniform),
                entry(1, points),
                entry(2, &counts),
                entry(3, &order),
            ],
        )?;
        Ok(CellOrder {
            uniform,
            counts,
            order,
            count,
            scan,
            scatter,
            capacity,
        })
    }

    /// The point indices, grouped by cell once the launches have run.
    pub(crate) fn order(&self) -> &wgpu::Buffer {
        &self.order
    }

    /// Prepares the grouping of the first `n` points (at most the capacity) over the box
    /// `lo..hi`: writes the uniform (through the queue: it applies to the next submission),
    /// records the clear of the counts into `enc` (the first 8^bits), and returns the launches
    /// to record after it, with their grids.
    pub(crate) fn prepare(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        n: u32,
        (lo, hi): (Vec3, Vec3),
    ) -> Result<[GridLaunch<'_>; 3], GpuError> {
        debug_assert!(
            n <= self.capacity,
            "{n} points in a grouping of {}",
            self.capacity
        );
        let params = BinParams::new(n, lo, hi);
        gpu.write(&self.uniform, &[params])?;
        enc.clear_buffer(&self.counts, 0, Some(u64::from(params.n_cells) * 4));
        let (x, y) = gpu.dispatch_size(n.div_ceil(WG));
        Ok([
            (&self.count, (x, y, 1)),
            (&self.scan, (1, 1, 1)),
            (&self.scatter, (x, y, 1)),
        ])
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::{BinParams, CellOrder, MAX_CELLS};
    use crate::gpu::{GpuContext, record_launches};
    use crate::shaders;

    /// The uniform has the layout the kernels read, and the constants are the shader's.
    #[test]
    fn params_mirror_the_shader() {
        shaders::assert_mirrors!(
            BinParams,
            shaders::GROUND_TRUTH_BIN,
            "BinParams",
            [n_points, bits, n_cells, lo, scale]
        );
        let source = shaders::GROUND_TRUTH_BIN.source;
        assert!(source.contains(&format!("const WG: u32 = {}u;", super::WG)));
        assert!(source.contains(&format!("const MAX_CELLS: u32 = {MAX_CELLS}u;")));
    }

    /// About a cell per point, at most 64³; keys follow the Z curve (x the most significant of
    /// each triple of bits), the corner cells are the first and last, every cell has its own key.
    #[test]
    fn keys_follow_the_z_curve() {
        let bits = |n| BinParams::new(n, Vec3::ZERO, Vec3::ONE).bits;
        assert_eq!(
            [bits(0), bits(8), bits(9), bits(3000), bits(262_144)],
            [1, 1, 2, 4, 6]
        );
        assert_eq!(bits(u32::MAX), 6);
        let p = BinParams::new(32_768, Vec3::splat(-1.0), Vec3::splat(1.0));
        assert_eq!((p.bits, p.n_cells), (5, 32_768));
        assert_eq!(p.cell_key(Vec3::splat(-1.0)), 0);
        assert_eq!(p.cell_key(Vec3::splat(1.0)), p.n_cells - 1);
        assert_eq!(p.cell_key(Vec3::new(-0.99, -0.99, -0.9)), 1);
        assert_eq!(p.cell_key(Vec3::new(-0.9, -0.99, -0.99)), 4);
        let mut seen = vec![false; p.n_cells as usize];
        for x in 0..32 {
            for y in 0..32 {
                for z in 0..32 {
                    let c = Vec3::new(x as f32, y as f32, z as f32) + 0.5;
                    let k = p.cell_key(c / 16.0 - 1.0) as usize;
                    assert!(!seen[k], "two cells share key {k}");
                    seen[k] = true;
                }
            }
        }
        // Hostile points still get a key.
        for q in [
            Vec3::NAN,
            Vec3::new(3e38, -3e38, 0.0),
            Vec3::splat(f32::INFINITY),
        ] {
            assert!(p.cell_key(q) < p.n_cells);
        }
        let flat = BinParams::new(1, Vec3::ZERO, Vec3::ZERO);
        assert!(flat.scale.iter().all(|s| s.is_finite() && *s > 0.0));
    }

    /// On the GPU: the order is a permutation of the points whose keys (computed by the CPU
    /// twin) never decrease, and each cell ends where the CPU's histogram says; on a draw of
    /// spot's near-surface points with hostile points mixed in.
    #[test]
    fn the_gpu_groups_points_by_cell() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let (mesh, _) = sdf_geom::load_mesh(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/data/spot.obj"
        ))
        .unwrap();
        let mesh = mesh.normalized().0;
        let mut points = sdf_geom::sample::near_surface(&mesh, 5000, 0.02, 7);
        points.extend(sdf_geom::sample::uniform_box(3000, 8));
        points.extend([
            Vec3::NAN,
            Vec3::new(3e38, -3e38, 1.0),
            Vec3::new(0.0, f32::INFINITY, 0.0),
            Vec3::splat(5.0),
        ]);
        let n = points.len() as u32;
        let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
        let buffer = gpu.storage_from_slice("bin test points", &flat).unwrap();
        // Capacity above the batch: the grouping covers the first n only.
        let bins = CellOrder::new(gpu, &buffer, n + 100).unwrap();
        let (lo, hi) = (Vec3::splat(-1.0), Vec3::splat(1.0));
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        let launches = bins.prepare(gpu, &mut enc, n, (lo, hi)).unwrap();
        record_launches(&mut enc, "bin test", &launches, None);
        gpu.queue().submit([enc.finish()]);
        let order: Vec<u32> = gpu.read_back_range(bins.order(), 0, u64::from(n)).unwrap();
        let params = BinParams::new(n, lo, hi);
        let ends: Vec<u32> = gpu
            .read_back_range(&bins.counts, 0, u64::from(params.n_cells))
            .unwrap();

        let keys: Vec<u32> = points.iter().map(|p| params.cell_key(*p)).collect();
        let mut seen = vec![false; points.len()];
        for &i in &order {
            assert!(!seen[i as usize], "point {i} twice in the order");
            seen[i as usize] = true;
        }
        for w in order.windows(2) {
            assert!(
                keys[w[0] as usize] <= keys[w[1] as usize],
                "keys out of order: {w:?}"
            );
        }
        let mut histogram = vec![0u32; params.n_cells as usize];
        for &k in &keys {
            histogram[k as usize] += 1;
        }
        let mut end = 0u32;
        for (cell, (&gpu_end, &count)) in ends.iter().zip(&histogram).enumerate() {
            end += count;
            assert_eq!(gpu_end, end, "cell {cell}");
        }
    }
}
