//! NGLOD's sample pool: blocks of one epoch's worth of labelled points, when each is drawn
//! ([`PoolSchedule`]), how one is sampled and labelled, and the order in which an epoch visits
//! the pool. Why a pool: see [the trainer's module](super::train).

use std::collections::VecDeque;
use std::ops::Range;
use std::time::Instant;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use sdf_geom::Mesh;

use super::{DistanceMode, NglodTrainConfig};
use crate::ground_truth::{GroundTruthError, Labeller};

/// When each block of the sample pool is drawn and which blocks an epoch draws from. Block `k`
/// is sampled with a seed derived from `k`, so the pool of any epoch can be rebuilt (resume).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PoolSchedule {
    /// Blocks kept.
    pub blocks: usize,
    /// Epochs between new blocks once the pool is full.
    pub refresh_every: usize,
}

impl PoolSchedule {
    /// The first epoch that draws from block `k`: one new block per epoch until the pool is full
    /// (so the first epoch waits for one block only), then one every `refresh_every` epochs.
    pub fn due(&self, k: usize) -> usize {
        let p = self.blocks.max(1);
        if k < p {
            k
        } else {
            (p - 1) + (k - p + 1) * self.refresh_every.max(1)
        }
    }

    /// The blocks in the pool during `epoch`.
    pub fn blocks_at(&self, epoch: usize) -> Range<usize> {
        let p = self.blocks.max(1);
        let last = if epoch < p {
            epoch
        } else {
            (p - 1) + (epoch - (p - 1)) / self.refresh_every.max(1)
        };
        (last + 1).saturating_sub(p)..last + 1
    }
}

/// One block of the pool: an epoch's worth of labelled points (not shuffled: epochs draw from
/// the pool in random order). The first `uniform_points` are the uniform box points.
pub(super) struct Block {
    pub(super) points: Vec<Vec3>,
    pub(super) targets: Vec<f32>,
    pub(super) seconds: f64,
}

/// Draws and labels block `k` of the pool (on the calling thread plus rayon's pool).
pub(super) fn sample_block(
    mesh: &Mesh,
    labels: &Labeller<'_>,
    c: &NglodTrainConfig,
    k: usize,
) -> Result<Block, GroundTruthError> {
    let t = Instant::now();
    // Each sampler draws its own stream of the block's seed.
    let seed = sdf_geom::sample::sub_seed(c.seed, k as u64);
    let mut points = sdf_geom::sample::uniform_box(c.uniform_points, seed);
    points.extend(sdf_geom::sample::near_surface(
        mesh,
        c.near_points,
        c.sigma,
        seed,
    ));
    let mut targets = match c.distance {
        DistanceMode::Signed => labels.signed_distance_batch(&points)?,
        // No winding number needed: the closest point alone gives |d|.
        DistanceMode::Unsigned => labels.unsigned_distance_batch(&points)?,
    };
    // Surface samples lie on the mesh by construction: their exact distance is 0, so the
    // distance query is skipped for them (40% of the points).
    let surface = sdf_geom::sample::surface(mesh, c.surface_points, seed).points;
    targets.resize(points.len() + surface.len(), 0.0);
    points.extend(surface);
    Ok(Block {
        points,
        targets,
        seconds: t.elapsed().as_secs_f64(),
    })
}

/// The order in which epoch `epoch` visits the pool: `n` distinct indices below `pool_len`, in
/// random order (a partial Fisher–Yates shuffle seeded by the run's seed and the epoch).
fn epoch_order(pool_len: usize, n: usize, seed: u64, epoch: usize) -> Vec<u32> {
    let mut rng = Pcg64::seed_from_u64(sdf_geom::sample::sub_seed(
        seed ^ 0xD1B5_4A32_D192_ED03,
        epoch as u64,
    ));
    let mut idx: Vec<u32> = (0..pool_len as u32).collect();
    let n = n.min(pool_len);
    for i in 0..n {
        let j = rng.random_range(i..pool_len);
        idx.swap(i, j);
    }
    idx.truncate(n);
    idx
}

/// The labelled pool: the blocks of [`PoolSchedule::blocks_at`] for the current epoch.
pub(super) struct Pool {
    pub(super) blocks: VecDeque<(usize, Block)>,
    pub(super) cap: usize,
}

impl Pool {
    pub(super) fn push(&mut self, k: usize, b: Block) {
        self.blocks.push_back((k, b));
        while self.blocks.len() > self.cap {
            self.blocks.pop_front();
        }
    }

    fn len(&self) -> usize {
        self.blocks.iter().map(|(_, b)| b.points.len()).sum()
    }

    /// The fraction of the oldest block's uniform box points labelled inside (negative): close
    /// to 0 for a mesh without an inside. `None` for unsigned targets or an empty pool.
    pub(super) fn inside_fraction(&self, config: &NglodTrainConfig) -> Option<f64> {
        let (_, b) = self.blocks.front()?;
        if config.distance != DistanceMode::Signed {
            return None;
        }
        let u = &b.targets[..config.uniform_points.min(b.targets.len())];
        Some(u.iter().filter(|&&d| d < 0.0).count() as f64 / u.len().max(1) as f64)
    }

    /// Epoch `epoch`'s points and targets in its order.
    pub(super) fn draw(&self, n: usize, seed: u64, epoch: usize) -> (Vec<Vec3>, Vec<f32>) {
        let order = epoch_order(self.len(), n, seed, epoch);
        let mut starts = Vec::with_capacity(self.blocks.len());
        let mut acc = 0usize;
        for (_, b) in &self.blocks {
            starts.push(acc);
            acc += b.points.len();
        }
        order
            .par_iter()
            .with_min_len(4096)
            .map(|&i| {
                let i = i as usize;
                let b = starts.partition_point(|&s| s <= i) - 1;
                let blk = &self.blocks[b].1;
                (blk.points[i - starts[b]], blk.targets[i - starts[b]])
            })
            .unzip()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spot() -> (Mesh, Labeller<'static>) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/data/spot.obj");
        let (mesh, _) = sdf_geom::load_mesh(path).expect("tests/data/spot.obj");
        let (unit, _) = mesh.normalized();
        let sdf = sdf_geom::SignedDistance::new(&unit).unwrap();
        (unit, Labeller::cpu(std::sync::Arc::new(sdf)))
    }

    fn small_config(seed: u64) -> NglodTrainConfig {
        NglodTrainConfig {
            uniform_points: 500,
            near_points: 1000,
            surface_points: 1000,
            seed,
            ..Default::default()
        }
    }

    fn pool_at(
        mesh: &Mesh,
        sdf: &Labeller<'_>,
        c: &NglodTrainConfig,
        epoch: usize,
    ) -> (Vec<usize>, Pool) {
        let blocks = c.pool().blocks_at(epoch);
        let mut pool = Pool {
            blocks: VecDeque::new(),
            cap: c.pool_blocks,
        };
        for k in blocks.clone() {
            pool.push(k, sample_block(mesh, sdf, c, k).unwrap());
        }
        (blocks.collect(), pool)
    }

    #[test]
    fn schedule_fills_the_pool_then_replaces_one_block_every_few_epochs() {
        let s = PoolSchedule {
            blocks: 4,
            refresh_every: 3,
        };
        // The pool grows by one block per epoch, so epoch 0 waits for one block only.
        assert_eq!(s.blocks_at(0), 0..1);
        assert_eq!(s.blocks_at(3), 0..4);
        // Then the oldest block is replaced every third epoch: a partial redraw.
        assert_eq!(s.blocks_at(5), 0..4);
        assert_eq!(s.blocks_at(6), 1..5);
        assert_eq!(s.blocks_at(9), 2..6);
        // `due` and `blocks_at` agree: an epoch holds the newest blocks already due.
        for e in 0..60 {
            let r = s.blocks_at(e);
            assert!(r.clone().all(|k| s.due(k) <= e), "epoch {e}: {r:?}");
            assert!(s.due(r.end) > e, "epoch {e}: {r:?}");
            assert_eq!(r.len(), (e + 1).min(4));
        }
        // One block, refreshed every epoch: fresh points every epoch, as before the pool.
        let old = PoolSchedule {
            blocks: 1,
            refresh_every: 1,
        };
        for e in 0..10 {
            assert_eq!(old.blocks_at(e), e..e + 1);
        }
    }

    #[test]
    fn epoch_orders_are_fresh_every_epoch_and_deterministic_in_the_seed() {
        let a = epoch_order(10_000, 2_500, 7, 3);
        assert_eq!(a, epoch_order(10_000, 2_500, 7, 3));
        assert_ne!(a, epoch_order(10_000, 2_500, 7, 4));
        assert_ne!(a, epoch_order(10_000, 2_500, 8, 3));
        // Distinct indices in range: a draw without replacement.
        let mut s = a.clone();
        s.sort_unstable();
        s.dedup();
        assert_eq!(s.len(), 2_500);
        assert!(s.iter().all(|&i| i < 10_000));
        // Drawing the whole pool is a permutation.
        let mut all = epoch_order(1_000, 1_000, 1, 0);
        all.sort_unstable();
        assert_eq!(all, (0..1_000).collect::<Vec<u32>>());
    }

    #[test]
    fn pool_draws_are_deterministic_fresh_and_partly_redrawn() {
        let (mesh, sdf) = spot();
        let c = small_config(5);
        let n = c.points_per_epoch();
        let (ids, pool) = pool_at(&mesh, &sdf, &c, 4);
        assert_eq!(ids, vec![0, 1, 2, 3]);
        assert_eq!(pool.len(), 4 * n);
        let (p, t) = pool.draw(n, c.seed, 4);
        assert_eq!(p.len(), n);
        // The same seed rebuilds the same pool and draw (what a resume relies on).
        let (_, again) = pool_at(&mesh, &sdf, &c, 4);
        assert_eq!(again.draw(n, c.seed, 4), (p.clone(), t.clone()));
        // Another seed gives other points.
        let (_, other) = pool_at(&mesh, &sdf, &small_config(6), 4);
        assert_ne!(other.draw(n, 6, 4).0, p);
        // The next epoch draws the same pool in a fresh order, and from all of it.
        let (p5, _) = pool.draw(n, c.seed, 5);
        assert_ne!(p5, p);
        let blocks_hit = |pts: &[Vec3]| {
            let mut hit = [false; 4];
            for q in pts {
                for (b, (_, blk)) in pool.blocks.iter().enumerate() {
                    if blk.points.contains(q) {
                        hit[b] = true;
                    }
                }
            }
            hit
        };
        assert_eq!(blocks_hit(&p[..200]), [true; 4]);
        // Every drawn point keeps its label.
        for (q, d) in p.iter().zip(&t).take(300) {
            let exact = sdf.sdf().signed_distance(*q);
            assert!(*d == 0.0 || (*d - exact).abs() < 1e-6, "{q} {d} {exact}");
        }
        // Partial redraw: at epoch 7 (refresh every 4) block 4 replaces block 0, the rest stay.
        let (ids7, pool7) = pool_at(&mesh, &sdf, &c, 7);
        assert_eq!(ids7, vec![1, 2, 3, 4]);
        for i in 0..3 {
            assert_eq!(pool7.blocks[i].1.points, pool.blocks[i + 1].1.points);
        }
        assert_ne!(pool7.blocks[3].1.points, pool.blocks[3].1.points);
    }

    #[test]
    fn unsigned_targets_are_absolute_distances() {
        let (mesh, sdf) = spot();
        let signed = sample_block(&mesh, &sdf, &small_config(1), 0).unwrap();
        let unsigned = sample_block(
            &mesh,
            &sdf,
            &NglodTrainConfig {
                distance: DistanceMode::Unsigned,
                ..small_config(1)
            },
            0,
        )
        .unwrap();
        assert_eq!(signed.points, unsigned.points);
        assert!(signed.targets.iter().any(|&d| d < 0.0));
        for (s, u) in signed.targets.iter().zip(&unsigned.targets) {
            assert!((s.abs() - u).abs() < 1e-6, "{s} {u}");
        }
    }
}
