//! The nearest-triangle search: a best-first depth-first traversal of the 4-wide BVH (four box
//! distances per SIMD pass, four triangles per packet), and the far path's f64 distance.

use glam::{DVec3, Vec3, Vec3A, Vec4};

use super::SignedDistance;
use super::simd::P4;
use super::triangle::closest_on_triangle;

/// A node of the 4-wide BVH used by the closest-point search (collapsed from the binary one): the
/// boxes of up to four children in SoA form, so that one SIMD pass gives all four box distances.
/// `Pod` so that [`GpuTrees`](super::GpuTrees) lends it to the GPU as it is.
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(64))]
pub(super) struct Node4 {
    /// Per-axis (x, y, z) lower corners of the four children's boxes; +∞ in unused slots.
    pub(super) min: [Vec4; 3],
    /// Per-axis upper corners; −∞ in unused slots (so their box distance is +∞).
    pub(super) max: [Vec4; 3],
    /// Inner child: index into `nodes4`. Leaf child: first index into `packets`.
    pub(super) child: [u32; 4],
    /// 0 for an inner child (or an unused slot), else the number of triangle packets in the leaf.
    pub(super) count: [u32; 4],
}

impl Node4 {
    pub(super) const EMPTY: Node4 = Node4 {
        min: [Vec4::INFINITY; 3],
        max: [Vec4::NEG_INFINITY; 3],
        child: [0; 4],
        count: [0; 4],
    };

    /// Squared distances from `p` (splatted per axis) to the four children's boxes.
    #[inline(always)]
    fn box_dist2(&self, px: Vec4, py: Vec4, pz: Vec4) -> Vec4 {
        let dx = (self.min[0] - px).max(px - self.max[0]).max(Vec4::ZERO);
        let dy = (self.min[1] - py).max(py - self.max[1]).max(Vec4::ZERO);
        let dz = (self.min[2] - pz).max(pz - self.max[2]).max(Vec4::ZERO);
        dx * dx + dy * dy + dz * dz
    }
}

impl SignedDistance {
    /// The far path (see [`FAR_QUERY_RADII`](super::FAR_QUERY_RADII)): distance, closest point, slot and barycentrics, all
    /// internal and in f64.
    pub(super) fn far_closest(
        &self,
        q: DVec3,
        stack: &mut Vec<(f32, u32, u32)>,
    ) -> (f64, DVec3, u32, DVec3) {
        let dir = q - self.center;
        let proxy = self.center + dir * (self.far / dir.length());
        let (_, slot) = self.nearest(proxy.as_vec3().into(), stack, u32::MAX);
        let t = self.tris[slot as usize].map(|v| Vec3::from(v).as_dvec3());
        let (c, bary) = closest_on_triangle(q, t[0], t[1], t[2]);
        (q.distance(c), c, slot, bary)
    }

    /// Squared distance from `p` to the triangle in `slot`.
    #[inline(always)]
    fn tri_dist2(&self, p: Vec3A, slot: usize) -> f32 {
        let t = &self.tris[slot];
        let (q, _) = closest_on_triangle(p, t[0], t[1], t[2]);
        (q - p).length_squared()
    }

    /// Best squared distance and slot of the nearest triangle. `seed` (a triangle slot, or
    /// `u32::MAX`) is tested first to start with a finite bound; the distance is the same either way
    /// (the minimum over all triangles), only the slot may differ between equally near triangles.
    #[inline]
    pub(super) fn nearest(
        &self,
        p: Vec3A,
        stack: &mut Vec<(f32, u32, u32)>,
        seed: u32,
    ) -> (f32, u32) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { self.nearest_avx(p, stack, seed) };
        }
        self.nearest_impl(p, stack, seed)
    }

    /// [`nearest`](Self::nearest) compiled with AVX: the same SSE operations in VEX encoding (three
    /// operands, fewer register copies and spills), so the results are bit-identical. No FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    fn nearest_avx(&self, p: Vec3A, stack: &mut Vec<(f32, u32, u32)>, seed: u32) -> (f32, u32) {
        self.nearest_impl(p, stack, seed)
    }

    #[inline(always)]
    pub(super) fn nearest_impl(
        &self,
        p: Vec3A,
        stack: &mut Vec<(f32, u32, u32)>,
        seed: u32,
    ) -> (f32, u32) {
        stack.clear();
        let (mut best, mut best_slot) = if (seed as usize) < self.tris.len() {
            (self.tri_dist2(p, seed as usize), seed)
        } else {
            (f32::INFINITY, 0)
        };
        let (px, py, pz) = (Vec4::splat(p.x), Vec4::splat(p.y), Vec4::splat(p.z));
        let p4 = P4 {
            x: px,
            y: py,
            z: pz,
        };
        // Current entry: (node or first packet, packet count; 0 for an inner node).
        let (mut c, mut count) = (0u32, 0u32);
        loop {
            if count > 0 {
                let start = c as usize;
                for t in &self.packets[start..start + count as usize] {
                    let d2 = t.dist2(p4);
                    if d2.cmplt(Vec4::splat(best)).any() {
                        // Lanes in slot order with a strict `<`: the same triangle as a scalar scan.
                        for (&d, &slot) in d2.to_array().iter().zip(&t.slot) {
                            if d < best {
                                best = d;
                                best_slot = slot;
                            }
                        }
                    }
                }
            } else {
                let n = &self.nodes4[c as usize];
                let d2 = n.box_dist2(px, py, pz);
                let mut mask = d2.cmplt(Vec4::splat(best)).bitmask();
                if mask != 0 {
                    if mask & (mask - 1) == 0 {
                        // One child left: go straight on.
                        let k = mask.trailing_zeros() as usize;
                        (c, count) = (n.child[k], n.count[k]);
                        continue;
                    }
                    // Several: sort by decreasing box distance, push all but the nearest, which is
                    // visited next.
                    let d = d2.to_array();
                    let mut cand = [(0.0f32, 0u32, 0u32); 4];
                    let mut m = 0;
                    while mask != 0 {
                        let k = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let e = (d[k], n.child[k], n.count[k]);
                        let mut j = m;
                        while j > 0 && cand[j - 1].0 < e.0 {
                            cand[j] = cand[j - 1];
                            j -= 1;
                        }
                        cand[j] = e;
                        m += 1;
                    }
                    for e in &cand[..m - 1] {
                        stack.push(*e);
                    }
                    (c, count) = (cand[m - 1].1, cand[m - 1].2);
                    continue;
                }
            }
            // Pop the next entry that can still hold something closer.
            loop {
                match stack.pop() {
                    Some((d, i, k)) if d < best => {
                        (c, count) = (i, k);
                        break;
                    }
                    Some(_) => {}
                    None => return (best, best_slot),
                }
            }
        }
    }
}
