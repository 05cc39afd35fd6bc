//! A read-only view of the trees a [`SignedDistance`] built, for GPU kernels that answer the same
//! queries: the 4-wide BVH, the triangle packets and the winding tree as `#[repr(C)]`, `Pod`
//! structs (the very memory the CPU traversals read, reinterpreted, not copied), and the numbers
//! the CPU's far path and huge-coordinate care need.

use bytemuck::{Pod, Zeroable};
use glam::DVec3;

use super::closest::Node4;
use super::triangle::TriPacket;
use super::winding::WNode4;
use super::{INSIDE_WINDING, SignedDistance};

/// A node of the 4-wide closest-point BVH, in internal coordinates (see [`GpuTrees::exponent`]):
/// the boxes of up to four children in SoA form (`min[axis][child]`). 128 bytes; a WGSL struct of
/// six `vec4<f32>` and two `vec4<u32>` in this order reads it.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct GpuBvhNode {
    /// Lower box corners per axis (x, y, z) and child; +∞ in unused slots.
    pub min: [[f32; 4]; 3],
    /// Upper box corners; −∞ in unused slots (so their box distance is +∞).
    pub max: [[f32; 4]; 3],
    /// Inner child: index into [`GpuTrees::nodes`]. Leaf child: its first packet in
    /// [`GpuTrees::packets`].
    pub child: [u32; 4],
    /// 0 for an inner child or an unused slot, else the number of packets of the leaf.
    pub count: [u32; 4],
}

/// Four triangles of one leaf in SoA form (`a[axis][lane]`), internal coordinates. A leaf whose
/// triangle count is not a multiple of four repeats its packet's first triangle in the spare
/// lanes (harmless for a minimum; the winding sum masks them by [`GpuWindingNode::count`]).
/// 160 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct GpuTriPacket {
    /// First corners per axis and lane.
    pub a: [[f32; 4]; 3],
    /// Second corners.
    pub b: [[f32; 4]; 3],
    /// Third corners.
    pub c: [[f32; 4]; 3],
    /// Each lane's triangle slot: an index into [`GpuTrees::triangle_ids`].
    pub slot: [u32; 4],
}

/// A node of the 4-wide winding tree (same shape and indices as [`GpuBvhNode`]: node `i` here
/// describes the children of node `i` there), internal coordinates. A child farther than
/// β·r from the query (`|center − p|² > β²·radius2`) contributes
/// `(area_normal·d + trace − (Σ sym_diag3_k d_k² + sym_off6 · (dx dy, dx dz, dy dz)) / |d|²) / |d|³`
/// with `d = center − p` (Barill et al.'s dipole and first-order terms, the factors 3 and 6 folded
/// in); a near leaf child adds its triangles' exact solid angles; the sum over all is divided
/// by 4π. 256 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct GpuWindingNode {
    /// Area-weighted centroids per axis and child.
    pub center: [[f32; 4]; 3],
    /// Squared radii of spheres around `center` holding the child's triangles; +∞ in unused
    /// slots (never far).
    pub radius2: [f32; 4],
    /// Summed area vectors per axis.
    pub area_normal: [[f32; 4]; 3],
    /// Traces of the first-order moments.
    pub trace: [f32; 4],
    /// Diagonals of the symmetric parts of the first-order moments, times 3.
    pub sym_diag3: [[f32; 4]; 3],
    /// Their off-diagonals (xy, xz, yz), times 6.
    pub sym_off6: [[f32; 4]; 3],
    /// Inner child: index into [`GpuTrees::winding`]; leaf child: its first packet; unused:
    /// `u32::MAX`.
    pub child: [u32; 4],
    /// Number of triangles (not packets) of a leaf child; 0 otherwise.
    pub count: [u32; 4],
}

// The casts below reinterpret the CPU's nodes: same size, and no stricter alignment.
const _: () = assert!(size_of::<Node4>() == size_of::<GpuBvhNode>());
const _: () = assert!(size_of::<TriPacket>() == size_of::<GpuTriPacket>());
const _: () = assert!(size_of::<WNode4>() == size_of::<GpuWindingNode>());

/// What a GPU needs to compute what [`SignedDistance`] computes, borrowed from it
/// ([`SignedDistance::gpu_trees`]).
///
/// Coordinates in the trees are *internal*: the mesh's times `2^exponent` (a power of two, so
/// exact; `exponent` is 0 except for meshes whose largest coordinate magnitude lies outside
/// `[2^-16, 2^16]`). A query `p` (mesh units) maps to `p · 2^exponent`; distances and points come
/// back times `2^-exponent`.
///
/// A query farther than [`far`](Self::far) from [`center`](Self::center) (internal units) takes
/// the far path: the nearest triangle is searched from the point at distance `far` from the
/// centre in the query's direction, the distance is then measured from the query itself, and
/// the sign is "outside" (see [`FAR_QUERY_RADII`](crate::FAR_QUERY_RADII)). Nearer queries: the
/// nearest triangle by a best-first search of [`nodes`](Self::nodes); within
/// [`surface_eps`](Self::surface_eps) of the surface the distance is unsigned; else inside iff
/// the fast winding number at β = [`beta`](Self::beta) (recomputed at 4β when it lands within
/// [`refine_band`](Self::refine_band) of 1/2) is at least [`inside`](Self::inside).
#[derive(Clone, Copy, Debug)]
pub struct GpuTrees<'a> {
    /// The 4-wide BVH; node 0 is the root (always an inner node).
    pub nodes: &'a [GpuBvhNode],
    /// The leaves' triangles, four to a packet, in the order the leaves reference them.
    pub packets: &'a [GpuTriPacket],
    /// The winding tree, index for index the shape of `nodes`.
    pub winding: &'a [GpuWindingNode],
    /// For each triangle slot ([`GpuTriPacket::slot`]), its index in the mesh's triangles.
    pub triangle_ids: &'a [u32],
    /// The most entries a stack traversal of `nodes` (or `winding`) can hold if, at each inner
    /// node it enters, it pushes all but one of its children: the largest sum of (children − 1)
    /// over a path from the root. A GPU kernel with a fixed stack needs at least this many.
    pub max_stack: u32,
    /// Accuracy parameter β of the fast winding number ([`crate::SignedDistanceOptions::beta`]).
    pub beta: f32,
    /// See [`crate::SignedDistanceOptions::refine_band`].
    pub refine_band: f32,
    /// Unsigned distance (internal units) up to which a point is on the surface and gets its
    /// distance unsigned ([`crate::SignedDistanceOptions::surface_tolerance`] × the diagonal).
    pub surface_eps: f32,
    /// The winding number from which a point is inside (1/2).
    pub inside: f32,
    /// Internal coordinates are the mesh's times `2^exponent`.
    pub exponent: i32,
    /// Bounding-box centre, internal units (f64: the far test of the CPU is in f64).
    pub center: DVec3,
    /// Distance from `center` beyond which a query takes the far path, internal units.
    pub far: f64,
}

impl SignedDistance {
    /// The trees and parameters of this distance, for a GPU implementation of the same queries
    /// (see [`GpuTrees`]). Borrows; nothing is copied but the stack bound, computed by one walk
    /// over the nodes.
    pub fn gpu_trees(&self) -> GpuTrees<'_> {
        GpuTrees {
            nodes: bytemuck::cast_slice(&self.nodes4),
            packets: bytemuck::cast_slice(&self.packets),
            winding: bytemuck::cast_slice(&self.wnodes4),
            triangle_ids: &self.tri_ids,
            max_stack: stack_bound(&self.nodes4),
            beta: self.options.beta,
            refine_band: self.options.refine_band,
            surface_eps: self.surface_eps,
            inside: INSIDE_WINDING,
            // to_internal is 2^exponent exactly.
            exponent: self.to_internal.log2().round() as i32,
            center: self.center,
            far: self.far,
        }
    }
}

/// [`GpuTrees::max_stack`] of `nodes`.
fn stack_bound(nodes: &[Node4]) -> u32 {
    // (node, entries pushed by its ancestors)
    let mut todo = vec![(0u32, 0u32)];
    let mut worst = 0;
    while let Some((i, above)) = todo.pop() {
        let n = &nodes[i as usize];
        // Unused slots have an empty box (min +∞, max −∞).
        let live: Vec<usize> = (0..4).filter(|&k| n.min[0][k] <= n.max[0][k]).collect();
        let here = above + (live.len() as u32).saturating_sub(1);
        worst = worst.max(here);
        for k in live {
            if n.count[k] == 0 {
                todo.push((n.child[k], here));
            }
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::Mesh;

    #[test]
    fn trees_are_the_cpu_trees() {
        let mesh = Mesh::icosphere(2.0, 3);
        let sdf = SignedDistance::new(&mesh).unwrap();
        let t = sdf.gpu_trees();
        assert_eq!(t.nodes.len(), sdf.nodes4.len());
        assert_eq!(t.winding.len(), t.nodes.len());
        assert_eq!(t.packets.len(), sdf.packets.len());
        assert_eq!(t.exponent, 0);
        assert!(t.max_stack >= 3 && t.max_stack < 100);
        // Every triangle slot in exactly one live packet lane.
        let mut seen = vec![0u32; sdf.triangle_count()];
        for (n, w) in t.nodes.iter().zip(t.winding) {
            for k in 0..4 {
                if n.count[k] > 0 {
                    assert_eq!(n.count[k], w.count[k].div_ceil(4));
                    for j in 0..w.count[k] {
                        let p = &t.packets[(n.child[k] + j / 4) as usize];
                        seen[p.slot[(j % 4) as usize] as usize] += 1;
                    }
                }
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
        // A packet lane's corners are its triangle's (internal = mesh coordinates here).
        let p = &t.packets[0];
        let id = t.triangle_ids[p.slot[1] as usize] as usize;
        let a = mesh.vertices[mesh.triangles[id][0] as usize];
        assert_eq!(Vec3::new(p.a[0][1], p.a[1][1], p.a[2][1]), a);
        // A huge mesh is scaled by a power of two.
        let big = Mesh {
            vertices: mesh.vertices.iter().map(|v| *v * 1e30).collect(),
            triangles: mesh.triangles.clone(),
        };
        let t = SignedDistance::new(&big).unwrap().gpu_trees().exponent;
        assert!((-110..-90).contains(&t), "{t}");
    }
}
