//! The 4-wide trees the queries walk: the binary BVH and its winding-number moments collapsed
//! into SoA nodes of four children, with the leaves' triangles packed four to a packet.

use glam::{Vec3, Vec3A};

use super::build::Node;
use super::closest::Node4;
use super::simd::P4;
use super::triangle::TriPacket;
use super::winding::{WNode4, WindingNode};

/// Collapses the binary BVH below `root` into 4-wide nodes (appended to `out` in depth-first order,
/// leaves' triangles appended to `packets` in the same order): an inner node's slots are filled by
/// repeatedly opening the inner child with the largest box surface area. Returns the new node's
/// index.
pub(super) fn collapse4(
    nodes: &[Node],
    wnodes: &[WindingNode],
    tris: &[[Vec3A; 3]],
    root: u32,
    out: &mut Vec<Node4>,
    wout: &mut Vec<WNode4>,
    packets: &mut Vec<TriPacket>,
) -> u32 {
    let half_area = |n: &Node| {
        let e = (n.max - n.min).max(Vec3::ZERO);
        e.x * e.y + e.y * e.z + e.z * e.x
    };
    let mut kids = [root; 4];
    let mut m = 1;
    while m < 4 {
        let open = (0..m)
            .filter(|&k| nodes[kids[k] as usize].count == 0)
            .max_by(|&a, &b| {
                half_area(&nodes[kids[a] as usize]).total_cmp(&half_area(&nodes[kids[b] as usize]))
            });
        let Some(k) = open else { break };
        let first = nodes[kids[k] as usize].first;
        kids[k] = first;
        kids[m] = first + 1;
        m += 1;
    }
    let idx = out.len();
    out.push(Node4::EMPTY);
    wout.push(WNode4::EMPTY);
    let mut node = Node4::EMPTY;
    let mut wnode = WNode4::EMPTY;
    for (k, &c) in kids[..m].iter().enumerate() {
        let n = &nodes[c as usize];
        for axis in 0..3 {
            node.min[axis][k] = n.min[axis];
            node.max[axis][k] = n.max[axis];
        }
        let w = &wnodes[c as usize];
        for axis in 0..3 {
            wnode.center[axis][k] = w.center[axis];
            wnode.area_normal[axis][k] = w.area_normal[axis];
            wnode.sym_diag3[axis][k] = 3.0 * w.sym_diag[axis];
            wnode.sym_off6[axis][k] = 6.0 * w.sym_off[axis];
        }
        wnode.radius2[k] = w.radius2;
        wnode.trace[k] = w.trace;
        if n.count > 0 {
            node.child[k] = packets.len() as u32;
            node.count[k] = n.count.div_ceil(4);
            wnode.child[k] = node.child[k];
            wnode.count[k] = n.count;
            for chunk in (n.first..n.first + n.count).collect::<Vec<u32>>().chunks(4) {
                let slot: [u32; 4] =
                    std::array::from_fn(|l| chunk[if l < chunk.len() { l } else { 0 }]);
                let corner = |j: usize| P4::from_lanes(slot.map(|s| tris[s as usize][j]));
                packets.push(TriPacket {
                    a: corner(0),
                    b: corner(1),
                    c: corner(2),
                    slot,
                });
            }
        } else {
            node.child[k] = collapse4(nodes, wnodes, tris, c, out, wout, packets);
            wnode.child[k] = node.child[k];
        }
    }
    out[idx] = node;
    wout[idx] = wnode;
    idx as u32
}
