//! Refit of a traced wide BVH: new vertex positions under the same topology. The triangle
//! packets take the moved corners, every leaf lane the box of its triangles, every inner lane
//! the union of its child node's lanes, level by level from the deepest (the nodes of a level
//! in parallel), and the culling pad follows the new coordinate range. No node moves.
#![forbid(unsafe_code)]

use emc_core::Aabb;
use glam::{Vec3, Vec3A};
use rayon::prelude::*;

use crate::trace::wide::{WideBvh, WideNodeN, EMPTY, LEAF, WIDTH, WIDTH8};
use crate::trace::TraceError;

/// Packets per rayon task.
const PACKETS_PER_TASK: usize = 1024;

/// The order of a refit, from the topology alone: each tree's nodes grouped by depth (root
/// level first). Computed once per build and kept while only the vertices move.
#[derive(Clone, Debug)]
pub struct RefitPlan {
    order4: Order,
    order8: Order,
    /// Per packet: whether it ends its leaf (the packets' own flag, kept compact so that the
    /// node pass does not touch the packets again).
    last: Vec<bool>,
    /// Per packet, each lane's three vertex indices: read in packet order, where going
    /// through the triangle ids gathered the index list at random (48 bytes per packet).
    corners: Vec<[[u32; 3]; WIDTH]>,
    /// The largest vertex index in `corners`, and the node counts of the trees the plan was
    /// made for (what [`WideBvh::refit`] checks before it indexes anything).
    max_vertex: u32,
    nodes: (usize, usize),
    /// Scratch kept between refits (fresh buffers of this size cost page faults each time):
    /// the packets' boxes and the nodes' unpadded boxes.
    packet_boxes: Vec<Aabb>,
    node_boxes: Vec<Aabb>,
}

impl RefitPlan {
    /// The levels of both trees of `bvh` (breadth first from node 0) over the mesh triangles
    /// `indices`; fails when a packet names a triangle `indices` does not have.
    pub fn new(bvh: &WideBvh, indices: &[[u32; 3]]) -> Result<RefitPlan, TraceError> {
        let n = indices.len();
        if let Some(id) = bvh
            .packets
            .iter()
            .flat_map(|p| p.id)
            .find(|&id| id as usize >= n)
        {
            return Err(TraceError::MissingTriangle {
                tri: id,
                triangles: n,
            });
        }
        let corners: Vec<[[u32; 3]; WIDTH]> = bvh
            .packets
            .par_iter()
            .map(|p| p.id.map(|id| indices[id as usize]))
            .collect();
        let max_vertex = corners
            .par_iter()
            .map(|c| c.iter().flatten().copied().max().unwrap_or(0))
            .max()
            .unwrap_or(0);
        Ok(RefitPlan {
            order4: Order::of(&bvh.nodes),
            order8: Order::of(&bvh.nodes8),
            last: bvh.packets.iter().map(|p| p.last != 0).collect(),
            corners,
            max_vertex,
            nodes: (bvh.nodes.len(), bvh.nodes8.len()),
            packet_boxes: Vec::new(),
            node_boxes: Vec::new(),
        })
    }
}

/// How one tree is walked bottom-up: disjoint subtrees that each occupy a contiguous index
/// range with every child after its parent (pre-order) or every child before it (post-order)
/// (`tasks`: start, end, post-order; refitted in parallel, each by one pass over its range
/// from the leaves' end, a stream through memory rather than a walk), then the nodes above
/// them (`top`, in breadth-first order, refitted in reverse). A tree without such ranges is
/// all `top`.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Order {
    tasks: Vec<(u32, u32, bool)>,
    top: Vec<u32>,
}

/// Subtrees above this share of the nodes are split into their children's.
const TASK_SHARE: usize = 16;

impl Order {
    fn of<const W: usize>(nodes: &[WideNodeN<W>]) -> Order {
        let n = nodes.len();
        if n == 0 {
            return Order {
                tasks: Vec::new(),
                top: Vec::new(),
            };
        }
        let inner = |i: usize| {
            nodes[i]
                .child
                .into_iter()
                .filter(|&c| c != EMPTY && c & LEAF == 0)
                .map(|c| c as usize)
        };
        // Per node: subtree size and lowest and highest index, bottom-up over the levels.
        let lv = levels(nodes);
        let mut count = vec![1usize; n];
        let mut lo: Vec<usize> = (0..n).collect();
        let mut hi: Vec<usize> = (0..n).collect();
        // pre[i]: every node of i's subtree precedes its children; post[i]: follows them.
        let mut pre = vec![true; n];
        let mut post = vec![true; n];
        for level in lv.iter().rev() {
            for &i in level {
                let i = i as usize;
                for c in inner(i) {
                    pre[i] &= c > i && pre[c];
                    post[i] &= c < i && post[c];
                    count[i] += count[c];
                    lo[i] = lo[i].min(lo[c]);
                    hi[i] = hi[i].max(hi[c]);
                }
            }
        }
        let shape = |i: usize| {
            let dense = hi[i] + 1 - lo[i] == count[i];
            if dense && pre[i] && lo[i] == i {
                Some(false)
            } else if dense && post[i] && hi[i] == i {
                Some(true)
            } else {
                None
            }
        };
        let mut tasks = Vec::new();
        let mut top = Vec::new();
        let mut queue = std::collections::VecDeque::from([0usize]);
        while let Some(i) = queue.pop_front() {
            let small = count[i] * TASK_SHARE <= n || count[i] == 1;
            if let (Some(post_order), true) = (shape(i), small) {
                tasks.push((lo[i] as u32, (hi[i] + 1) as u32, post_order));
            } else {
                top.push(i as u32);
                queue.extend(inner(i));
            }
        }
        tasks.sort_unstable();
        Order { tasks, top }
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

/// Union of the packet boxes of the leaf whose first packet is `first`.
#[inline]
fn leaf_box(last: &[bool], boxes: &[Aabb], first: usize) -> Aabb {
    let mut b = Aabb::EMPTY;
    for (&l, pb) in last[first..].iter().zip(&boxes[first..]) {
        b = b.union(pb);
        if l {
            break;
        }
    }
    b
}

/// The lanes of `node` from its children's unpadded boxes (`inner(code)`) and its leaves'
/// packet boxes; returns the node's own unpadded box.
#[inline(always)]
fn refit_node<const W: usize>(
    node: &mut WideNodeN<W>,
    (last, packet_boxes): (&[bool], &[Aabb]),
    pad: f32,
    inner: impl Fn(u32) -> Aabb,
) -> Aabb {
    let mut all = Aabb::EMPTY;
    for lane in 0..W {
        let code = node.child[lane];
        if code == EMPTY {
            continue;
        }
        let b = if code & LEAF != 0 {
            leaf_box(last, packet_boxes, (code & !LEAF) as usize)
        } else {
            inner(code)
        };
        node.set(lane, &b, code, pad);
        all = all.union(&b);
    }
    all
}

/// Refit nodes `base..base + nodes.len()`, one whole subtree in pre-order (children after
/// parents: walked from the end) or post-order (walked from the start); `boxes` receives
/// their unpadded boxes.
fn refit_range<const W: usize>(
    nodes: &mut [WideNodeN<W>],
    boxes: &mut [Aabb],
    base: usize,
    post_order: bool,
    leaves: (&[bool], &[Aabb]),
    pad: f32,
) {
    let n = nodes.len();
    for k in 0..n {
        let i = if post_order { k } else { n - 1 - k };
        let b = refit_node(&mut nodes[i], leaves, pad, |c| boxes[c as usize - base]);
        boxes[i] = b;
    }
}

/// Refit one tree in `order`.
fn refit_tree<const W: usize>(
    nodes: &mut [WideNodeN<W>],
    order: &Order,
    leaves: (&[bool], &[Aabb]),
    pad: f32,
    boxes: &mut Vec<Aabb>,
) {
    boxes.clear();
    boxes.resize(nodes.len(), Aabb::EMPTY);
    // The subtree ranges, as disjoint slices of the nodes and their boxes.
    let mut parts = Vec::with_capacity(order.tasks.len());
    let (mut rest, mut brest, mut at) = (&mut nodes[..], &mut boxes[..], 0usize);
    for &(a, b, post_order) in &order.tasks {
        let (_, r) = rest.split_at_mut(a as usize - at);
        let (_, br) = brest.split_at_mut(a as usize - at);
        let (part, r) = r.split_at_mut((b - a) as usize);
        let (bpart, br) = br.split_at_mut((b - a) as usize);
        parts.push((a as usize, post_order, part, bpart));
        (rest, brest, at) = (r, br, b as usize);
    }
    parts
        .into_par_iter()
        .for_each(|(base, post_order, n, bx)| refit_range(n, bx, base, post_order, leaves, pad));
    for &i in order.top.iter().rev() {
        let mut node = nodes[i as usize];
        let b = refit_node(&mut node, leaves, pad, |c| boxes[c as usize]);
        nodes[i as usize] = node;
        boxes[i as usize] = b;
    }
}

impl WideBvh {
    /// Refit the tree to moved vertices: `vertices` are the mesh's new positions (the
    /// indices the plan was made with name them) and `max_abs` the largest absolute coordinate
    /// of the triangles' corners (the culling pad and the traversal's slack follow it). The
    /// topology, node order and packet order stay; `plan` must be [`RefitPlan::new`] of this
    /// tree. Refitting to unmoved triangles gives the same nodes bit for bit.
    pub fn refit(
        &mut self,
        plan: &mut RefitPlan,
        vertices: &[Vec3],
        max_abs: f32,
    ) -> Result<(), TraceError> {
        if plan.corners.len() != self.packets.len()
            || plan.nodes != (self.nodes.len(), self.nodes8.len())
        {
            return Err(TraceError::RefitPlanMismatch);
        }
        if plan.max_vertex as usize >= vertices.len() {
            let (p, lane, index) = plan
                .corners
                .iter()
                .enumerate()
                .flat_map(|(p, c)| (0..WIDTH).flat_map(move |l| c[l].map(|i| (p, l, i))))
                .find(|&(_, _, i)| i as usize >= vertices.len())
                .expect("the largest index is one of them");
            return Err(TraceError::BadIndex {
                tri: self.packets[p].id[lane] as usize,
                index,
                vertices: vertices.len(),
            });
        }
        let mut packet_boxes = std::mem::take(&mut plan.packet_boxes);
        packet_boxes.resize(self.packets.len(), Aabb::EMPTY);
        self.packets
            .par_iter_mut()
            .zip(packet_boxes.par_iter_mut())
            .zip(plan.corners.par_iter())
            .with_min_len(PACKETS_PER_TASK)
            .for_each(|((p, b), corners)| {
                // The box from the corners in registers (reading the rows back after the
                // lane-by-lane stores stalled on store forwarding).
                let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
                for lane in 0..WIDTH {
                    let [v0, v1, v2] = corners[lane].map(|i| vertices[i as usize]);
                    let v = &mut p.v;
                    (v[0][lane], v[1][lane], v[2][lane]) = (v0.x, v0.y, v0.z);
                    (v[3][lane], v[4][lane], v[5][lane]) = (v1.x, v1.y, v1.z);
                    (v[6][lane], v[7][lane], v[8][lane]) = (v2.x, v2.y, v2.z);
                    let (a, c, d) = (Vec3A::from(v0), Vec3A::from(v1), Vec3A::from(v2));
                    lo = lo.min(a.min(c).min(d));
                    hi = hi.max(a.max(c).max(d));
                }
                *b = Aabb::new(lo.into(), hi.into());
            });
        self.max_abs = max_abs;
        let pad = max_abs * (1.0 / 65536.0);
        let mut boxes = std::mem::take(&mut plan.node_boxes);
        refit_tree::<WIDTH>(
            &mut self.nodes,
            &plan.order4,
            (&plan.last, &packet_boxes),
            pad,
            &mut boxes,
        );
        refit_tree::<WIDTH8>(
            &mut self.nodes8,
            &plan.order8,
            (&plan.last, &packet_boxes),
            pad,
            &mut boxes,
        );
        plan.node_boxes = boxes;
        plan.packet_boxes = packet_boxes;
        Ok(())
    }
}
