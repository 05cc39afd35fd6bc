//! The counter-based random numbers of the GPU sampler ([`super::sample`]) and their CPU
//! reference: Philox4x32-10 (Salmon et al., "Parallel random numbers: as easy as 1, 2, 3",
//! SC 2011; the generator of Random123, cuRAND and PyTorch), a keyed Feistel permutation that
//! shuffles the kinds of points in a draw, and what one point of a [`SampleSpec`] is made of.
//! `shaders/sample.wgsl` computes the same, integer for integer.
//!
//! Every random word is a pure function of the seed (the 64-bit key) and a 128-bit counter
//! `[rank, kind, stream, block]`: a point's numbers do not depend on the other points, on the
//! dispatch or on the thread that computes them, so a seed gives the same points on every run.

use glam::Vec3;

/// Philox4x32's multipliers and Weyl key increments (Random123's `PHILOX_M4x32_*`,
/// `PHILOX_W32_*`).
const M0: u32 = 0xD251_1F53;
const M1: u32 = 0xCD9E_8D57;
const W0: u32 = 0x9E37_79B9;
const W1: u32 = 0xBB67_AE85;

/// Philox4x32 with 10 rounds: four random words from a 128-bit `counter` and a 64-bit `key`.
/// The test vectors of Random123 (`kat_vectors`) hold.
pub fn philox4x32_10(counter: [u32; 4], key: [u32; 2]) -> [u32; 4] {
    let mut c = counter;
    let mut k = key;
    for round in 0..10 {
        if round > 0 {
            k = [k[0].wrapping_add(W0), k[1].wrapping_add(W1)];
        }
        let p0 = u64::from(M0) * u64::from(c[0]);
        let p1 = u64::from(M1) * u64::from(c[2]);
        c = [
            (p1 >> 32) as u32 ^ c[1] ^ k[0],
            p1 as u32,
            (p0 >> 32) as u32 ^ c[3] ^ k[1],
            p0 as u32,
        ];
    }
    c
}

/// The top 24 bits of `x` as a float in `[0, 1)` (exact: a multiple of 2⁻²⁴).
pub fn unit_float(x: u32) -> f32 {
    (x >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// The top 24 bits of `x` as a float in `(0, 1]`: the radius draw of Box–Muller, whose
/// logarithm must be finite.
pub fn unit_float_open(x: u32) -> f32 {
    ((x >> 8) + 1) as f32 * (1.0 / 16_777_216.0)
}

/// Two standard normal variates from two random words by Box–Muller, in f32 as the kernel
/// computes them: `R = sqrt(max(-2 ln u₁, 0))`, `θ = π (2 u₂ − 1)`, `(R cos θ, R sin θ)` (the
/// clamp changes nothing here; WGSL's `log` may err above 0 near 1).
pub fn gaussian_pair(a: u32, b: u32) -> [f32; 2] {
    let r = (-2.0 * unit_float_open(a).ln()).max(0.0).sqrt();
    let theta = std::f32::consts::PI * (2.0 * unit_float(b) - 1.0);
    [r * theta.cos(), r * theta.sin()]
}

/// A 32-bit integer hash (Wellons' `lowbias32`): the round function of [`Shuffle`].
pub fn lowbias32(x: u32) -> u32 {
    let mut x = x;
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// Which sampler a point of a draw comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Kind {
    /// Uniform in the box `[-1, 1]³` ([`sdf_geom::sample::uniform_box`]).
    Uniform = 0,
    /// On the surface plus an isotropic Gaussian offset ([`sdf_geom::sample::near_surface`]).
    Near = 1,
    /// On the surface, uniform with respect to area ([`sdf_geom::sample::surface`]).
    Surface = 2,
}

/// The counter word of the shuffle's keys (no point kind uses it).
const SHUFFLE_KIND: u32 = 3;

/// One draw of the GPU sampler: how many points of each kind, the near-surface σ, and the seed
/// and stream of the random numbers. Point `i` of the draw (of `uniform + near + surface`)
/// comes from [`SampleSpec::source`]: without `shuffle` the uniform points first, then the
/// near-surface ones, then the surface ones (the layout of a pool block); with it the kinds
/// are spread by a random permutation, so that any run of consecutive points (an optimiser
/// step's batch) holds the three kinds in about their proportions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampleSpec {
    /// Points uniform in `[-1, 1]³`.
    pub uniform: u32,
    /// Points near the surface.
    pub near: u32,
    /// Points on the surface.
    pub surface: u32,
    /// Standard deviation of the near-surface offsets, in the mesh's units.
    pub sigma: f32,
    /// The generator's key.
    pub seed: u64,
    /// Separates draws of one seed (an epoch, a block): a counter word.
    pub stream: u32,
    /// Spread the kinds over the draw (see above).
    pub shuffle: bool,
}

impl SampleSpec {
    /// Points in the draw, or `None` above `u32::MAX`.
    pub fn len(&self) -> Option<u32> {
        self.uniform
            .checked_add(self.near)?
            .checked_add(self.surface)
    }

    /// Whether the draw has no points.
    pub fn is_empty(&self) -> bool {
        self.len() == Some(0)
    }

    /// The key of the generator: the seed's two halves.
    pub fn key(&self) -> [u32; 2] {
        [self.seed as u32, (self.seed >> 32) as u32]
    }

    /// The shuffle of this draw (the identity without `shuffle`).
    pub fn shuffle(&self) -> Shuffle {
        self.shuffle_over(self.len().unwrap_or(u32::MAX))
    }

    /// This draw's shuffle keys on a domain of `n` points (the identity without `shuffle`):
    /// the first [`SampleSpec::len`] of its images pick distinct points of a pool of `n`
    /// ([`super::LabelledDraw::record_gather`]).
    pub fn shuffle_over(&self, n: u32) -> Shuffle {
        Shuffle::new(n, self, self.shuffle)
    }

    /// Where point `i` of the draw comes from: its kind and its rank among the points of that
    /// kind (the counter of its random numbers). `shuffle` is [`SampleSpec::shuffle`]'s.
    pub fn source(&self, shuffle: &Shuffle, i: u32) -> (Kind, u32) {
        let j = shuffle.apply(i);
        if j < self.uniform {
            (Kind::Uniform, j)
        } else if j - self.uniform < self.near {
            (Kind::Near, j - self.uniform)
        } else {
            (Kind::Surface, j - self.uniform - self.near)
        }
    }

    /// The random words of block `block` (0 or 1) of a point of `kind` and `rank`.
    pub fn words(&self, kind: Kind, rank: u32, block: u32) -> [u32; 4] {
        philox4x32_10([rank, kind as u32, self.stream, block], self.key())
    }

    /// A point uniform in `[-1, 1]³` from its random words (exact in f32).
    pub fn uniform_point(w: [u32; 4]) -> Vec3 {
        Vec3::new(unit_float(w[0]), unit_float(w[1]), unit_float(w[2])) * 2.0 - Vec3::ONE
    }

    /// The Gaussian offset of a near-surface point of standard deviation `sigma`, from the
    /// fourth word of its first block and its second block.
    pub fn offset(w0: [u32; 4], w1: [u32; 4], sigma: f32) -> Vec3 {
        let [x, y] = gaussian_pair(w1[0], w1[1]);
        let [z, _] = gaussian_pair(w0[3], w1[2]);
        Vec3::new(x, y, z) * sigma
    }
}

/// A bijection of `0..n` (a keyed 4-round Feistel network on the smallest even number of bits
/// that holds `n`, walked until it lands below `n`), or the identity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shuffle {
    /// Points in the domain: the draw's, or a pool's.
    pub n: u32,
    /// Bits of each Feistel half (0: the identity).
    pub half: u32,
    /// The round keys.
    pub keys: [u32; 4],
}

impl Shuffle {
    fn new(n: u32, spec: &SampleSpec, shuffle: bool) -> Self {
        if !shuffle || n < 2 {
            return Shuffle {
                n,
                half: 0,
                keys: [0; 4],
            };
        }
        let bits = 32 - (n - 1).leading_zeros();
        Shuffle {
            n,
            half: bits.div_ceil(2),
            keys: philox4x32_10([u32::MAX, SHUFFLE_KIND, spec.stream, 0], spec.key()),
        }
    }

    /// The image of `i < n`.
    pub fn apply(&self, i: u32) -> u32 {
        if self.half == 0 {
            return i;
        }
        let h = self.half;
        let mask = (1u32 << h) - 1;
        let mut x = i;
        loop {
            let (mut l, mut r) = (x >> h, x & mask);
            for k in self.keys {
                let t = l ^ (lowbias32(r ^ k) & mask);
                l = r;
                r = t;
            }
            x = (l << h) | r;
            if x < self.n {
                return x;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random123's known answers for philox4x32 with 10 rounds.
    #[test]
    fn philox_matches_random123() {
        assert_eq!(
            philox4x32_10([0; 4], [0; 2]),
            [0x6627e8d5, 0xe169c58d, 0xbc57ac4c, 0x9b00dbd8]
        );
        assert_eq!(
            philox4x32_10([u32::MAX; 4], [u32::MAX; 2]),
            [0x408f276d, 0x41c83b0e, 0xa20bc7c6, 0x6d5451fd]
        );
        assert_eq!(
            philox4x32_10(
                [0x243f6a88, 0x85a308d3, 0x13198a2e, 0x03707344],
                [0xa4093822, 0x299f31d0]
            ),
            [0xd16cfe09, 0x94fdcceb, 0x5001e420, 0x24126ea1]
        );
    }

    /// The shuffle is a bijection for every size class (odd and even bit counts, powers of two
    /// and their neighbours), and the kinds come out in their counts.
    #[test]
    fn shuffle_is_a_bijection_with_exact_counts() {
        for n in [1u32, 2, 3, 4, 5, 7, 8, 9, 63, 64, 65, 1000, 4096, 5000] {
            let spec = SampleSpec {
                uniform: n / 5,
                near: n / 3,
                surface: n - n / 5 - n / 3,
                sigma: 0.01,
                seed: 0x1234_5678_9abc,
                stream: n,
                shuffle: true,
            };
            let s = spec.shuffle();
            let mut seen = vec![false; n as usize];
            let mut counts = [0u32; 3];
            for i in 0..n {
                let j = s.apply(i);
                assert!(j < n && !seen[j as usize], "n = {n}: {i} -> {j}");
                seen[j as usize] = true;
                counts[spec.source(&s, i).0 as usize] += 1;
            }
            assert_eq!(counts, [spec.uniform, spec.near, spec.surface]);
            if n >= 64 {
                assert!((0..n).filter(|&i| s.apply(i) == i).count() < n as usize / 4);
            }
        }
    }

    /// Box–Muller gives standard normals: mean 0, variance 1, kurtosis 3 over 10⁵ pairs.
    #[test]
    fn box_muller_moments() {
        let mut m = [0f64; 4];
        let n = 100_000u32;
        for i in 0..n {
            let w = philox4x32_10([i, 9, 9, 9], [1, 2]);
            for g in gaussian_pair(w[0], w[1]) {
                let g = f64::from(g);
                m[0] += g;
                m[1] += g * g;
                m[3] += g * g * g * g;
            }
        }
        let k = f64::from(2 * n);
        assert!((m[0] / k).abs() < 0.01, "{m:?}");
        assert!((m[1] / k - 1.0).abs() < 0.01, "{m:?}");
        assert!((m[3] / k - 3.0).abs() < 0.06, "{m:?}");
    }
}
