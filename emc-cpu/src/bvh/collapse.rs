//! Optimal bottom-up SAH leaf collapse, emitted as a compact BVH in depth-first order (left child
//! right after its parent): step 6 of the LBVH pipeline. The decisions come from the bottom-up
//! pass (`refit`/`apetrei`); this file writes the nodes, in parallel over disjoint subtrees.
#![forbid(unsafe_code)]

use emc_core::Aabb;
use rayon::prelude::*;

use super::node::{Bvh, Node};
use super::refit::{combine, CollapseParams, RadixTree, SlotData};
use super::sah::area;

/// Subtrees smaller than this are never split further into parallel tasks.
const MIN_TASK_NODES: usize = 4096;

/// A subtree to write: node id, its output position and its depth.
#[derive(Clone, Copy, Debug)]
struct Task {
    node: u32,
    pos: u32,
    depth: u32,
}

/// Output-subtree size of node id `c` of `tree`.
#[inline]
fn out_of(tree: &RadixTree, c: u32) -> u32 {
    tree.out_of(c)
}

/// Write node `t` into `dst` (at `t.pos − base`) and return its children's tasks, if any.
#[inline]
fn emit_one(
    tree: &RadixTree,
    sorted: &[Aabb],
    t: Task,
    dst: &mut [Node],
    base: u32,
) -> Option<[Task; 2]> {
    let at = (t.pos - base) as usize;
    if tree.is_leaf(t.node) {
        let p = t.node as usize - (tree.n - 1);
        dst[at] = Node::leaf(sorted[p], p as u32, 1);
        return None;
    }
    let s: SlotData = tree.slots[t.node as usize].load();
    if s.out == 1 {
        dst[at] = Node::leaf(s.bounds, s.first, s.count);
        return None;
    }
    let (l, r) = tree.children_of(t.node);
    let lpos = t.pos + 1;
    let rpos = lpos + out_of(tree, l);
    dst[at] = Node::inner(s.bounds, lpos, rpos);
    let d = t.depth + 1;
    Some([
        Task {
            node: r,
            pos: rpos,
            depth: d,
        },
        Task {
            node: l,
            pos: lpos,
            depth: d,
        },
    ])
}

/// Write the subtree of `t` into `dst`, whose first element is output position `t.pos`;
/// returns the largest leaf depth.
fn emit_subtree(tree: &RadixTree, sorted: &[Aabb], t: Task, dst: &mut [Node]) -> u32 {
    let base = t.pos;
    let mut depth = 0;
    let mut stack = vec![t];
    while let Some(t) = stack.pop() {
        match emit_one(tree, sorted, t, dst, base) {
            Some(ch) => stack.extend_from_slice(&ch),
            None => depth = depth.max(t.depth),
        }
    }
    depth
}

/// Emit the collapsed tree (decisions already taken by the bottom-up pass with the same
/// [`CollapseParams`]) as a [`Bvh`] in depth-first order; `sorted` holds the primitive boxes in
/// sorted order and `order` (sorted position → primitive) becomes the primitive order (every
/// subtree covers a contiguous run of sorted positions). Returns the BVH and its depth.
pub fn emit(tree: &RadixTree, sorted: &[Aabb], order: Vec<u32>) -> (Bvh, usize) {
    let total = out_of(tree, tree.root) as usize;
    let mut nodes = crate::buffers::from_fn(total, |_| Node::default());
    let cutoff = (total / (rayon::current_num_threads() * 8)).max(MIN_TASK_NODES) as u32;
    // Top of the tree, sequentially, down to subtrees of at most `cutoff` nodes.
    let mut tasks = Vec::new();
    let mut depth = 0u32;
    let mut stack = vec![Task {
        node: tree.root,
        pos: 0,
        depth: 0,
    }];
    while let Some(t) = stack.pop() {
        if out_of(tree, t.node) <= cutoff {
            tasks.push(t);
            continue;
        }
        match emit_one(tree, sorted, t, &mut nodes, 0) {
            Some(ch) => stack.extend_from_slice(&ch),
            None => depth = depth.max(t.depth),
        }
    }
    // The subtrees own disjoint runs of the output: hand each its own slice.
    tasks.sort_unstable_by_key(|t| t.pos);
    let mut jobs: Vec<(Task, &mut [Node])> = Vec::with_capacity(tasks.len());
    let mut rest: &mut [Node] = &mut nodes;
    let mut offset = 0u32;
    for t in tasks {
        let size = out_of(tree, t.node) as usize;
        let (_, tail) = std::mem::take(&mut rest).split_at_mut((t.pos - offset) as usize);
        let (mine, tail) = tail.split_at_mut(size);
        jobs.push((t, mine));
        rest = tail;
        offset = t.pos + size as u32;
    }
    let sub_depth = jobs
        .into_par_iter()
        .map(|(t, dst)| emit_subtree(tree, sorted, t, dst))
        .max()
        .unwrap_or(0);
    let depth = depth.max(sub_depth) as usize;
    (
        Bvh {
            nodes,
            prim_indices: order,
            root: 0,
        },
        depth,
    )
}

/// Optimal SAH leaf collapse of any BVH (for builders without a radix tree, such as binned
/// SAH): same rule as [`emit`], sequential and iterative. Leaves that already hold several
/// primitives are kept as they are (their cost is `ci·A·|l|`). Expects a valid tree (see
/// [`Bvh::validate`]); a node index outside the array is skipped.
pub fn collapse_bvh(bvh: &Bvh, k: &CollapseParams) -> Bvh {
    let n = bvh.nodes.len();
    if n == 0 || bvh.root as usize >= n {
        return bvh.clone();
    }
    // Pre-order list; its reverse visits children before parents.
    let mut pre = Vec::with_capacity(n);
    let mut stack = vec![bvh.root];
    while let Some(i) = stack.pop() {
        let Some(node) = bvh.nodes.get(i as usize) else {
            continue;
        };
        pre.push(i);
        if !node.is_leaf() {
            stack.push(node.right());
            stack.push(node.left());
        }
    }
    let mut data = vec![
        SlotData {
            bounds: Aabb::EMPTY,
            cost: 0.0,
            first: 0,
            count: 0,
            out: 0,
        };
        n
    ];
    for &i in pre.iter().rev() {
        let node = &bvh.nodes[i as usize];
        data[i as usize] = if node.is_leaf() {
            SlotData {
                bounds: node.bounds,
                cost: k.ci * area(&node.bounds) * node.count() as f64,
                first: node.first(),
                count: node.count(),
                out: 1,
            }
        } else {
            let get = |c: u32| data.get(c as usize).copied();
            match (get(node.left()), get(node.right())) {
                (Some(a), Some(b)) => {
                    let mut d = combine(&a, &b, k);
                    d.bounds = node.bounds;
                    d
                }
                _ => continue,
            }
        };
    }
    // Emit in depth-first order, gathering the primitives of collapsed subtrees.
    let mut nodes: Vec<Node> = Vec::with_capacity(data[bvh.root as usize].out as usize);
    let mut prims: Vec<u32> = Vec::with_capacity(bvh.prim_indices.len());
    // (input node, output index of the parent to patch, is right child)
    let mut stack: Vec<(u32, u32, bool)> = vec![(bvh.root, u32::MAX, false)];
    let mut inner_stack = Vec::new();
    while let Some((i, parent, is_right)) = stack.pop() {
        let node = &bvh.nodes[i as usize];
        let d = data[i as usize];
        let me = nodes.len() as u32;
        if parent != u32::MAX && is_right {
            let p = nodes[parent as usize];
            nodes[parent as usize] = Node::inner(p.bounds, p.left(), me);
        }
        if node.is_leaf() || d.out == 1 {
            let first = prims.len() as u32;
            inner_stack.clear();
            inner_stack.push(i);
            while let Some(j) = inner_stack.pop() {
                let Some(m) = bvh.nodes.get(j as usize) else {
                    continue;
                };
                if m.is_leaf() {
                    let (f, c) = (m.first() as usize, m.count() as usize);
                    if let Some(s) = bvh.prim_indices.get(f..f + c) {
                        prims.extend_from_slice(s);
                    }
                } else {
                    inner_stack.push(m.right());
                    inner_stack.push(m.left());
                }
            }
            let count = prims.len() as u32 - first;
            nodes.push(Node::leaf(node.bounds, first, count.max(1)));
        } else {
            // Left child will sit right after; the right index is patched when it is written.
            nodes.push(Node::inner(node.bounds, me + 1, 0));
            stack.push((node.right(), me, true));
            stack.push((node.left(), me, false));
        }
    }
    Bvh {
        nodes,
        prim_indices: prims,
        root: 0,
    }
}
