//! Building the trees: the binary BVH (split top-down into parts of at most [`PLOC_PART`]
//! triangles with a binned SAH, each part built by obvhs in parallel), renumbered depth first,
//! and collapsed into the 4-wide nodes, winding nodes and triangle packets the queries traverse.

use std::time::Duration;

use glam::{DVec3, Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::triangle::Triangle;
use rayon::prelude::*;

use crate::{GeomError, Mesh};

/// A node of the binary BVH (the tree obvhs builds, before it is collapsed into 4-wide nodes).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(16))]
pub(super) struct Node {
    pub(super) min: Vec3,
    /// Inner node: index of the first child (the second is `first + 1`). Leaf: first triangle slot.
    pub(super) first: u32,
    pub(super) max: Vec3,
    /// 0 for inner nodes, else number of triangles in the leaf.
    pub(super) count: u32,
}

/// Meshes whose largest coordinate magnitude lies outside `[2^-16, 2^16]` are rescaled internally
/// by a power of two (exact in floating point) so that the f32 search and winding sums neither
/// overflow (coordinates near 1e38) nor underflow; distances and points are scaled back on output.
/// Meshes inside that range are used as they are, bit for bit.
const TAME_EXPONENT: i32 = 16;

/// The power of two (its exponent) that brings a mesh with these bounds into the tame range of
/// [`TAME_EXPONENT`]: 0, the mesh as it is, for all but extreme meshes.
pub(super) fn tame_exponent(bounds: &crate::Aabb) -> i32 {
    let max_abs = bounds.min.abs().max(bounds.max.abs()).max_element() as f64;
    if max_abs > 0.0 && (max_abs > 2f64.powi(TAME_EXPONENT) || max_abs < 2f64.powi(-TAME_EXPONENT))
    {
        // Largest magnitude into [0.5, 1).
        -(max_abs.log2().floor() as i32) - 1
    } else {
        0
    }
}

/// The mesh's triangles of non-zero area, with corners mapped by `internal`, and their indices in
/// [`Mesh::triangles`].
///
/// # Errors
/// [`GeomError::NoTriangles`] if none is left.
pub(super) fn area_triangles(
    mesh: &Mesh,
    internal: impl Fn(Vec3) -> Vec3,
) -> Result<(Vec<Triangle>, Vec<u32>), GeomError> {
    let mut prims = Vec::with_capacity(mesh.triangles.len());
    let mut ids = Vec::with_capacity(mesh.triangles.len());
    for (i, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|k| internal(mesh.vertices[k as usize]));
        if (b - a).as_dvec3().cross((c - a).as_dvec3()) == DVec3::ZERO {
            continue;
        }
        prims.push(Triangle {
            v0: a.into(),
            v1: b.into(),
            v2: c.into(),
        });
        ids.push(i as u32);
    }
    if prims.is_empty() {
        return Err(GeomError::NoTriangles {
            dropped: mesh.triangles.len(),
        });
    }
    Ok((prims, ids))
}

/// The nodes reachable from the root, each before its children (a stack traversal, right child
/// first), and the deepest that stack grew: the traversals' stack size hint.
pub(super) fn depth_first_order(nodes: &[Node]) -> (Vec<u32>, usize) {
    let mut order = Vec::with_capacity(nodes.len());
    let mut stack = vec![0u32];
    let mut max_stack = 1;
    while let Some(i) = stack.pop() {
        order.push(i);
        let n = &nodes[i as usize];
        if n.count == 0 {
            stack.push(n.first);
            stack.push(n.first + 1);
            max_stack = max_stack.max(stack.len());
        }
    }
    (order, max_stack)
}

/// Triangles per obvhs build: larger meshes are first split top-down ([`sah_split`]) until each
/// part has at most this many. PLOC (obvhs's builder) merges only
/// mutual nearest neighbours in each pass, and on triangles whose spacing shrinks geometrically
/// that is one merge per pass: 60 000 such triangles took 13 s and a million would take about an
/// hour. Parts of this size bound that worst case to a fraction of a second each.
const PLOC_PART: usize = 1024;

/// The BVH over `prims`: nodes (inner nodes' children adjacent, the root first) and the order of
/// the triangles in its leaves. The parts are split off first, built by obvhs in parallel, and
/// placed in the order a depth-first build would place them, so the tree does not depend on the
/// thread count.
pub(super) fn build_nodes(prims: &[Triangle], params: BvhBuildParams) -> (Vec<Node>, Vec<u32>) {
    let mut refs = prim_refs(prims);
    let plan = plan_parts(&mut refs, 0);
    let indices: Vec<u32> = refs.iter().map(|r| r.index).collect();
    drop(refs);
    let mut ranges = Vec::new();
    plan.leaves(&mut ranges);
    let bvhs: Vec<Bvh2> = ranges
        .par_iter()
        .map(|r| {
            let part: Vec<Triangle> = indices[r.clone()]
                .iter()
                .map(|&k| prims[k as usize])
                .collect();
            build_bvh2_from_tris(&part, params, &mut Duration::default())
        })
        .collect();
    let mut nodes = vec![Node::default()];
    let mut order = Vec::with_capacity(prims.len());
    let mut built = bvhs.iter();
    place(&plan, &indices, 0, &mut nodes, &mut order, &mut built);
    (depth_first(&nodes), order)
}

/// The same tree with its nodes renumbered in depth-first order (each inner node's two children
/// still adjacent, the left one's subtree next): obvhs numbers a part's nodes in the order PLOC
/// made them, so the bottom-up and top-down passes that follow jumped around memory, 3.4 s of
/// the build on 5.5 M triangles.
fn depth_first(nodes: &[Node]) -> Vec<Node> {
    let mut out = Vec::with_capacity(nodes.len());
    out.push(nodes[0]);
    // Inner nodes placed whose children are not yet: (old index, new index).
    let mut stack = vec![(0usize, 0usize)];
    while let Some((old, new)) = stack.pop() {
        let n = nodes[old];
        if n.count > 0 {
            continue;
        }
        let first = out.len();
        out.push(nodes[n.first as usize]);
        out.push(nodes[n.first as usize + 1]);
        out[new].first = first as u32;
        stack.push((n.first as usize + 1, first + 1));
        stack.push((n.first as usize, first));
    }
    out
}

/// What the top-down split reads of a triangle, kept beside its index so that each split streams
/// through one array instead of gathering corners from `prims` in an order that the splits above
/// it shuffled (on 1.4 M triangles the gathers made planning take 4 s of CPU).
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    /// The mean of the corners.
    centroid: Vec3,
    /// The triangle's bounds.
    lo: Vec3,
    hi: Vec3,
    /// The triangle in `prims`.
    index: u32,
}

/// Each triangle's [`PrimRef`], in the order of `prims`.
fn prim_refs(prims: &[Triangle]) -> Vec<PrimRef> {
    prims
        .par_iter()
        .enumerate()
        .map(|(k, t)| PrimRef {
            centroid: ((t.v0 + t.v1 + t.v2) / 3.0).into(),
            lo: t.v0.min(t.v1).min(t.v2).into(),
            hi: t.v0.max(t.v1).max(t.v2).into(),
            index: k as u32,
        })
        .collect()
}

/// How [`build_nodes`] splits the triangles: ranges of the reordered triangles, each of at most
/// [`PLOC_PART`], under a binary tree of [`sah_split`]s.
enum PartPlan {
    Part(std::ops::Range<usize>),
    Split(Box<PartPlan>, Box<PartPlan>),
}

impl PartPlan {
    /// The parts' ranges, depth first, left before right.
    fn leaves(&self, out: &mut Vec<std::ops::Range<usize>>) {
        match self {
            PartPlan::Part(r) => out.push(r.clone()),
            PartPlan::Split(l, r) => {
                l.leaves(out);
                r.leaves(out);
            }
        }
    }
}

/// Splits `refs` (which start at `offset` in the whole list) until every part has at most
/// [`PLOC_PART`] triangles; the two sides of a split are planned in parallel.
fn plan_parts(refs: &mut [PrimRef], offset: usize) -> PartPlan {
    if refs.len() <= PLOC_PART {
        return PartPlan::Part(offset..offset + refs.len());
    }
    let mid = sah_split(refs, SAH_CHUNK);
    let (left, right) = refs.split_at_mut(mid);
    let (l, r) = rayon::join(
        || plan_parts(left, offset),
        || plan_parts(right, offset + mid),
    );
    PartPlan::Split(Box::new(l), Box::new(r))
}

/// Fills `nodes[slot]` with the subtree of `plan`, taking the parts' BVHs from `built` in the
/// order of [`PartPlan::leaves`].
fn place(
    plan: &PartPlan,
    indices: &[u32],
    slot: usize,
    nodes: &mut Vec<Node>,
    order: &mut Vec<u32>,
    built: &mut std::slice::Iter<Bvh2>,
) {
    let range = match plan {
        PartPlan::Split(l, r) => {
            let first = nodes.len();
            nodes.extend([Node::default(), Node::default()]);
            place(l, indices, first, nodes, order, built);
            place(r, indices, first + 1, nodes, order, built);
            let (l, r) = (nodes[first], nodes[first + 1]);
            nodes[slot] = Node {
                min: l.min.min(r.min),
                first: first as u32,
                max: l.max.max(r.max),
                count: 0,
            };
            return;
        }
        PartPlan::Part(range) => range,
    };
    let bvh = built.next().expect("one BVH per part");
    let part = &indices[range.clone()];
    // obvhs's root goes to `slot`, its other nodes after the existing ones (in their order, so
    // siblings stay adjacent), its leaves' triangles after those already placed.
    let base = nodes.len() - 1;
    let at = |j: u32| if j == 0 { slot as u32 } else { base as u32 + j };
    let first_triangle = order.len() as u32;
    order.extend(bvh.primitive_indices.iter().map(|&k| part[k as usize]));
    for (j, n) in bvh.nodes.iter().enumerate() {
        let node = Node {
            min: n.aabb.min.into(),
            first: if n.prim_count == 0 {
                at(n.first_index)
            } else {
                first_triangle + n.first_index
            },
            max: n.aabb.max.into(),
            count: n.prim_count,
        };
        if j == 0 {
            nodes[slot] = node;
        } else {
            nodes.push(node);
        }
    }
}

/// Bins per axis of [`sah_split`].
const SAH_BINS: usize = 16;

/// Triangles per task of [`sah_split`]'s passes over a large split (the top levels, where
/// `rayon::join` has not yet spread the work).
const SAH_CHUNK: usize = 1 << 14;

/// Per-axis bins of a split: counts and bounds (what [`sah_split`] accumulates). Counts and
/// min/max are exact in any order, so the chunks' sums give the sequential pass's bins.
#[derive(Clone, Copy)]
struct SahBins {
    count: [[usize; SAH_BINS]; 3],
    lo: [[Vec3A; SAH_BINS]; 3],
    hi: [[Vec3A; SAH_BINS]; 3],
}

impl SahBins {
    fn new() -> Self {
        SahBins {
            count: [[0; SAH_BINS]; 3],
            lo: [[Vec3A::splat(f32::INFINITY); SAH_BINS]; 3],
            hi: [[Vec3A::splat(f32::NEG_INFINITY); SAH_BINS]; 3],
        }
    }

    fn merge(mut self, o: &SahBins) -> Self {
        for a in 0..3 {
            for b in 0..SAH_BINS {
                self.count[a][b] += o.count[a][b];
                self.lo[a][b] = self.lo[a][b].min(o.lo[a][b]);
                self.hi[a][b] = self.hi[a][b].max(o.hi[a][b]);
            }
        }
        self
    }
}

/// Reorders `refs` into two non-empty halves at the returned position: the split of the
/// triangles' centroids into [`SAH_BINS`] bins per axis with the least surface
/// area cost (the count of each side times the area of its box), so that the top levels of the
/// tree are as tight as PLOC's; the median of the longest axis where every centroid coincides.
/// Splits of more than `chunk` triangles bin in parallel chunks of that many.
fn sah_split(refs: &mut [PrimRef], chunk: usize) -> usize {
    let empty = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY));
    let union = |(a, b): (Vec3A, Vec3A), (c, d): (Vec3A, Vec3A)| (a.min(c), b.max(d));
    let centroid_bounds = |chunk: &[PrimRef]| {
        chunk.iter().fold(empty, |(lo, hi), r| {
            let c = Vec3A::from(r.centroid);
            (lo.min(c), hi.max(c))
        })
    };
    let (lo, hi) = if refs.len() > chunk {
        refs.par_chunks(chunk)
            .map(centroid_bounds)
            .reduce(|| empty, union)
    } else {
        centroid_bounds(refs)
    };
    let half_area = |(a, b): (Vec3A, Vec3A)| {
        let d = (b - a).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    };
    let extent = hi - lo;
    let bin_of = |r: &PrimRef, axis: usize| {
        let f = (r.centroid[axis] - lo[axis]) / extent[axis] * SAH_BINS as f32;
        (f as usize).min(SAH_BINS - 1)
    };
    let axes: Vec<usize> = (0..3)
        .filter(|&a| !extent[a].is_nan() && extent[a] > 0.0)
        .collect();
    let fill = |chunk: &[PrimRef]| {
        let mut bins = SahBins::new();
        for r in chunk {
            let (l, h) = (Vec3A::from(r.lo), Vec3A::from(r.hi));
            for &a in &axes {
                let b = bin_of(r, a);
                bins.count[a][b] += 1;
                bins.lo[a][b] = bins.lo[a][b].min(l);
                bins.hi[a][b] = bins.hi[a][b].max(h);
            }
        }
        bins
    };
    let bins = if refs.len() > chunk {
        refs.par_chunks(chunk)
            .map(fill)
            .reduce(SahBins::new, |a, b| a.merge(&b))
    } else {
        fill(refs)
    };
    let mut best: Option<(f32, usize, usize)> = None;
    for &axis in &axes {
        let count = &bins.count[axis];
        let boxes: [(Vec3A, Vec3A); SAH_BINS] =
            std::array::from_fn(|b| (bins.lo[axis][b], bins.hi[axis][b]));
        // Cost of splitting after bin i: left bins 0..=i, right the rest.
        let mut right = [(0.0f32, 0usize); SAH_BINS];
        let (mut acc, mut n) = (empty, 0);
        for i in (1..SAH_BINS).rev() {
            acc = union(acc, boxes[i]);
            n += count[i];
            right[i - 1] = (half_area(acc), n);
        }
        let (mut acc, mut n) = (empty, 0);
        for i in 0..SAH_BINS - 1 {
            acc = union(acc, boxes[i]);
            n += count[i];
            let (right_area, right_n) = right[i];
            if n == 0 || right_n == 0 {
                continue;
            }
            let cost = half_area(acc) * n as f32 + right_area * right_n as f32;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, i));
            }
        }
    }
    match best {
        Some((_, axis, bin)) => {
            let mut left = 0;
            for i in 0..refs.len() {
                if bin_of(&refs[i], axis) <= bin {
                    refs.swap(i, left);
                    left += 1;
                }
            }
            left
        }
        None => {
            let axis = extent.max_position();
            let mid = refs.len() / 2;
            refs.select_nth_unstable_by(mid, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
            mid
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The parts' plan bins the large splits in parallel chunks: the tree must still be the one a
    /// single thread builds (81 920 triangles: the first splits run over several chunks).
    #[test]
    fn parts_build_the_same_tree_at_any_thread_count() {
        let mesh = Mesh::icosphere(1.0, 6);
        let prims: Vec<Triangle> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|k| Vec3A::from(mesh.vertices[k as usize]));
                Triangle {
                    v0: a,
                    v1: b,
                    v2: c,
                }
            })
            .collect();
        assert!(prims.len() > 4 * SAH_CHUNK);
        let build = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| build_nodes(&prims, BvhBuildParams::fast_build()))
        };
        // Binned in chunks as the top splits are, and in one pass: the same split.
        let mut refs = prim_refs(&prims);
        let mut whole = refs.clone();
        let mid = sah_split(&mut refs, 1000);
        assert_eq!(mid, sah_split(&mut whole, usize::MAX));
        assert!(
            refs.iter()
                .map(|r| r.index)
                .eq(whole.iter().map(|r| r.index))
        );
        assert!(0 < mid && mid < prims.len());
        let (one_nodes, one_order) = build(1);
        let (nodes, order) = build(4);
        assert_eq!(order, one_order);
        assert!(nodes == one_nodes, "the trees differ");
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.iter().copied().eq(0..prims.len() as u32));
        // Depth-first numbering: children after their parent, every node reached once, every
        // triangle slot in one leaf.
        let (mut stack, mut seen, mut slots) = (vec![0usize], 0, vec![0u8; prims.len()]);
        while let Some(i) = stack.pop() {
            seen += 1;
            let n = nodes[i];
            if n.count > 0 {
                for s in n.first..n.first + n.count {
                    slots[s as usize] += 1;
                }
            } else {
                assert!(n.first as usize > i);
                stack.extend([n.first as usize + 1, n.first as usize]);
            }
        }
        assert_eq!(seen, nodes.len());
        assert!(slots.iter().all(|&c| c == 1));
    }
}
