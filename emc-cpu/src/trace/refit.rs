//! Refit of a traced wide BVH: new vertex positions under the same topology. The triangle
//! packets take the moved corners, every leaf lane the box of its triangles, every inner lane
//! the union of its child node's lanes, level by level from the deepest (the nodes of a level
//! in parallel), and the culling pad follows the new coordinate range. No node moves.
#![forbid(unsafe_code)]

use emc_core::Aabb;
use glam::Vec3;
use rayon::prelude::*;

use crate::trace::wide::{TriPacket, WideBvh, WideNodeN, EMPTY, LEAF, WIDTH, WIDTH8};

/// Nodes per rayon task of a level.
const NODES_PER_TASK: usize = 256;
/// Packets per rayon task.
const PACKETS_PER_TASK: usize = 1024;

/// The order of a refit, from the topology alone: each tree's nodes grouped by depth (root
/// level first). Computed once per build and kept while only the vertices move.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RefitPlan {
    levels4: Vec<Vec<u32>>,
    levels8: Vec<Vec<u32>>,
}

impl RefitPlan {
    /// The levels of both trees of `bvh` (breadth first from node 0).
    pub fn new(bvh: &WideBvh) -> RefitPlan {
        RefitPlan {
            levels4: levels(&bvh.nodes),
            levels8: levels(&bvh.nodes8),
        }
    }

    /// Levels of the 4-wide and the 8-wide tree.
    pub fn depths(&self) -> (usize, usize) {
        (self.levels4.len(), self.levels8.len())
    }
}

fn levels<const W: usize>(nodes: &[WideNodeN<W>]) -> Vec<Vec<u32>> {
    let mut out: Vec<Vec<u32>> = Vec::new();
    if nodes.is_empty() {
        return out;
    }
    let mut level = vec![0u32];
    while !level.is_empty() {
        let next: Vec<u32> = level
            .iter()
            .flat_map(|&n| nodes[n as usize].child)
            .filter(|&c| c != EMPTY && c & LEAF == 0)
            .collect();
        out.push(level);
        level = next;
    }
    out
}

/// Union of the boxes of the triangles of the leaf whose first packet is `first`.
#[inline]
fn leaf_box(packets: &[TriPacket], first: usize) -> Aabb {
    let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
    for p in &packets[first..] {
        for lane in 0..p.count as usize {
            for v in p.lane(lane) {
                let v = Vec3::from(v);
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        if p.last != 0 {
            break;
        }
    }
    Aabb::new(lo, hi)
}

/// Refit one tree: `boxes[n]` receives the unpadded box of node `n`.
fn refit_tree<const W: usize>(
    nodes: &mut [WideNodeN<W>],
    levels: &[Vec<u32>],
    packets: &[TriPacket],
    pad: f32,
    boxes: &mut Vec<Aabb>,
) {
    boxes.clear();
    boxes.resize(nodes.len(), Aabb::EMPTY);
    for level in levels.iter().rev() {
        let done: Vec<(WideNodeN<W>, Aabb)> = level
            .par_iter()
            .with_min_len(NODES_PER_TASK)
            .map(|&n| {
                let mut node = nodes[n as usize];
                let mut all = Aabb::EMPTY;
                for lane in 0..W {
                    let code = node.child[lane];
                    if code == EMPTY {
                        continue;
                    }
                    let b = if code & LEAF != 0 {
                        leaf_box(packets, (code & !LEAF) as usize)
                    } else {
                        boxes[code as usize]
                    };
                    node.set(lane, &b, code, pad);
                    all = all.union(&b);
                }
                (node, all)
            })
            .collect();
        for (&n, (node, b)) in level.iter().zip(done) {
            nodes[n as usize] = node;
            boxes[n as usize] = b;
        }
    }
}

impl WideBvh {
    /// Refit the tree to moved triangles: `tri(id)` gives triangle `id`'s new corners and
    /// `max_abs` their largest absolute coordinate (the culling pad and the traversal's slack
    /// follow it). The topology, node order and packet order stay; `plan` must be
    /// [`RefitPlan::new`] of this tree. Refitting to unmoved triangles gives the same nodes
    /// bit for bit.
    pub fn refit(&mut self, plan: &RefitPlan, tri: impl Fn(u32) -> [Vec3; 3] + Sync, max_abs: f32) {
        self.packets
            .par_iter_mut()
            .with_min_len(PACKETS_PER_TASK)
            .for_each(|p| {
                for lane in 0..WIDTH {
                    let t = tri(p.id[lane]);
                    for (j, v) in t.iter().enumerate() {
                        for a in 0..3 {
                            p.v[3 * j + a][lane] = v[a];
                        }
                    }
                }
            });
        self.max_abs = max_abs;
        let pad = max_abs * (1.0 / 65536.0);
        let mut boxes = Vec::new();
        refit_tree::<WIDTH>(
            &mut self.nodes,
            &plan.levels4,
            &self.packets,
            pad,
            &mut boxes,
        );
        refit_tree::<WIDTH8>(
            &mut self.nodes8,
            &plan.levels8,
            &self.packets,
            pad,
            &mut boxes,
        );
    }
}
