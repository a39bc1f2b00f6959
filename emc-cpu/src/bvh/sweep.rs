//! One-pass LBVH (the engine of builder `lbvh`): the Karras/Apetrei radix tree built by a
//! left-to-right stack sweep over the sorted codes, each node finished (bounds, cost, SAH-collapse
//! decision) the moment it closes and written as a post-order record; a relabelling pass then
//! writes the collapsed BVH in depth-first order. Same tree and same BVH as Karras + refit + emit.
//!
//! The radix tree is the Cartesian tree of the split distances `Δ(k)` (see `apetrei.rs`): the
//! split with the largest distance in a leaf range is that range's root. Two equal distances are
//! always separated by a larger one, so the tree is unique. The sweep keeps the open splits on a
//! stack (distances decreasing towards the top); a new split first closes every open split of
//! smaller distance (the current subtree becomes its right child), then opens with the current
//! subtree as its left child. Everything the sweep touches is either sequential (keys, order,
//! records) or on the small stack; the only scattered reads are the primitive boxes.
//!
//! Records: a closed subtree's records form one contiguous block ending with its root (post
//! order), so a node that collapses into a leaf just truncates its block and writes one leaf
//! record; the buffer always holds exactly the collapsed tree.
//!
//! ```text
//!   records:  s(T) → [ left block ][ right block ] T     inner record: (bounds, s(T), left)
//!   output:   T [ left block, depth first ][ right block, depth first ]
//!   position: pre(v) = s(v) + depth(v)                    (nodes left of v, then ancestors)
//! ```
//!
//! The relabelling reads the records backwards, sequentially, keeping the block starts of the
//! open ancestors on a stack (its height is the depth), and writes each node at `pre(v)`.
//!
//! Parallel: the top of the tree is found top-down (range arg-max of `Δ` from per-block maxima)
//! until the ranges are small enough; each range is swept as a task, the few top nodes are then
//! finished serially, and every task relabels its records into its own slice of the output.

use emc_core::Aabb;
use rayon::prelude::*;

use super::apetrei::dist;
use super::node::{Bvh, Node};
use super::refit::{zeroed, CollapseParams, SlotData};
use super::sah::area;
use crate::sort::RadixKey;

/// Splits per block of the arg-max index.
const BLOCK: usize = 4096;
/// Smallest leaf range handed to a task.
const MIN_TASK: usize = 1 << 14;
/// Primitive boxes prefetched ahead of the sweep.
const PREFETCH: usize = 16;

/// A closed subtree: its data, its root record and the first record of its block.
#[derive(Clone, Copy, Debug)]
struct Closed {
    d: SlotData,
    rec: u32,
    start: u32,
}

/// An open split: its distance, its index and its finished left subtree.
#[derive(Clone, Copy, Debug)]
struct Open {
    dist: (u64, u32),
    k: u32,
    left: Closed,
}

/// Parent data of two finished children and the parent's area.
#[inline(always)]
fn join(a: &SlotData, b: &SlotData, k: &CollapseParams) -> (SlotData, f64) {
    super::refit::combine_with_area(a, b, k)
}

/// Hint the cache to fetch `x` (no effect on results).
#[inline(always)]
fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is only a hint: it never faults, reads no value into the program and
    // SSE (its target feature) is part of the x86_64 baseline. `x` is a valid reference anyway.
    unsafe {
        core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(
            (x as *const T).cast::<i8>(),
        );
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// Inputs shared by every sweep of one build.
struct Input<'a, K> {
    keys: &'a [K],
    order: &'a [u32],
    aabbs: &'a [Aabb],
    k: &'a CollapseParams,
}

impl<K: RadixKey> Input<'_, K> {
    /// The leaf of sorted position `p`, appended as a record.
    #[inline(always)]
    fn leaf(&self, p: usize, rec: &mut Vec<Node>) -> Closed {
        if let Some(&q) = self.order.get(p + PREFETCH) {
            prefetch(&self.aabbs[q as usize]);
        }
        let b = self.aabbs[self.order[p] as usize];
        let at = rec.len() as u32;
        rec.push(Node::leaf(b, p as u32, 1));
        Closed {
            d: SlotData {
                bounds: b,
                cost: self.k.ci * area(&b),
                first: p as u32,
                count: 1,
                out: 1,
            },
            rec: at,
            start: at,
        }
    }

    /// Close split `o` with right subtree `right`; its area goes to `areas[o.k − base]`.
    #[inline(always)]
    fn close(
        &self,
        o: &Open,
        right: &Closed,
        rec: &mut Vec<Node>,
        areas: &mut [f64],
        base: usize,
    ) -> Closed {
        let (d, ar) = join(&o.left.d, &right.d, self.k);
        areas[o.k as usize - base] = ar;
        let start = o.left.start;
        if d.out == 1 {
            rec.truncate(start as usize);
            rec.push(Node::leaf(d.bounds, d.first, d.count));
        } else {
            // An inner record keeps its block start and its left child; the right child is the
            // record just before it.
            rec.push(Node::inner(d.bounds, start, o.left.rec));
        }
        Closed {
            d,
            rec: rec.len() as u32 - 1,
            start,
        }
    }

    /// Sweep the leaves `lo..=hi`: records of the collapsed subtree go to `rec` (which must be
    /// empty), split `s ∈ lo..hi` stores its area at `areas[s − lo]`. Returns the subtree root.
    fn sweep(
        &self,
        lo: usize,
        hi: usize,
        rec: &mut Vec<Node>,
        areas: &mut [f64],
        stack: &mut Vec<Open>,
    ) -> Closed {
        stack.clear();
        for p in lo..(lo + PREFETCH).min(hi + 1) {
            prefetch(&self.aabbs[self.order[p] as usize]);
        }
        let mut cur = self.leaf(lo, rec);
        for s in lo..hi {
            let ds = dist(self.keys, s);
            while let Some(top) = stack.last() {
                if top.dist >= ds {
                    break;
                }
                let o = *top;
                stack.pop();
                cur = self.close(&o, &cur, rec, areas, lo);
            }
            stack.push(Open {
                dist: ds,
                k: s as u32,
                left: cur,
            });
            cur = self.leaf(s + 1, rec);
        }
        while let Some(o) = stack.pop() {
            cur = self.close(&o, &cur, rec, areas, lo);
        }
        cur
    }
}

/// Write the post-order records `rec` (root last) depth first into `dst`, whose first element
/// is output position `base`.
fn relabel(rec: &[Node], dst: &mut [Node], base: u32) {
    let mut open: Vec<u32> = Vec::with_capacity(64);
    for i in (0..rec.len()).rev() {
        let nd = rec[i];
        let i = i as u32;
        while open.last().is_some_and(|&s| s > i) {
            open.pop();
        }
        let depth = open.len() as u32;
        if nd.is_leaf() {
            dst[(i + depth) as usize] = nd;
        } else {
            let (start, l) = (nd.left(), nd.right());
            let pre = start + depth;
            let lpos = base + pre + 1;
            let rpos = lpos + (l - start + 1);
            dst[pre as usize] = Node::inner(nd.bounds, lpos, rpos);
            open.push(start);
        }
    }
}

/// Where a top node's child lives.
#[derive(Clone, Copy, Debug)]
enum Ref {
    Top(u32),
    Task(u32),
}

/// A node above the tasks: its split and children.
#[derive(Clone, Copy, Debug)]
struct TopNode {
    k: usize,
    l: Ref,
    r: Ref,
}

/// Arg-max of `Δ` over splits `a..b` (non-empty) from per-block maxima.
fn argmax<K: RadixKey>(keys: &[K], blocks: &[((u64, u32), u32)], a: usize, b: usize) -> usize {
    let mut best = (dist(keys, a), a);
    let scan = |best: &mut ((u64, u32), usize), from: usize, to: usize| {
        for s in from..to {
            let d = dist(keys, s);
            if d > best.0 {
                *best = (d, s);
            }
        }
    };
    let head_end = b.min((a / BLOCK + 1) * BLOCK);
    scan(&mut best, a + 1, head_end);
    if head_end < b {
        let (fb, lb) = (head_end / BLOCK, b / BLOCK);
        for &(d, s) in &blocks[fb..lb] {
            if d > best.0 {
                best = (d, s as usize);
            }
        }
        scan(&mut best, (lb * BLOCK).max(head_end), b);
    }
    best.1
}

/// The finished radix tree of [`sweep_tree`]: per-task post-order records, the top nodes and
/// the per-split areas; [`Swept::emit`] turns it into the depth-first BVH.
#[derive(Debug)]
pub struct Swept {
    n: usize,
    order: Vec<u32>,
    areas: Vec<f64>,
    tops: Vec<TopNode>,
    top_data: Vec<SlotData>,
    tasks: Vec<(Closed, Vec<Node>)>,
    root: Ref,
}

/// What [`Swept::emit`] returns.
#[derive(Clone, Debug)]
pub struct SweepOutput {
    /// The collapsed BVH, depth first, `prim_indices` = the sort order.
    pub bvh: Bvh,
    /// Headline SAH of the uncollapsed radix tree (`Ct = Ci = 1`, one primitive per leaf, root
    /// counted as inner), summed in a fixed order (independent of the thread count).
    pub sah_headline: f64,
}

/// Buffers of the sweep kept between builds (see `build::BuildArena`): the per-split areas and
/// the record buffers of the tasks.
#[derive(Debug, Default)]
pub struct SweepScratch {
    areas: Vec<f64>,
    records: Vec<Vec<Node>>,
}

/// Build the radix tree with bounds, costs and collapse decisions over `keys` (sorted
/// ascending, 1 to `u32::MAX` of them), `order` (sorted position → primitive id, as long as
/// `keys`) and the primitive boxes `aabbs` (indexed by primitive id), on the current rayon pool.
/// Panics if `keys` is empty or `order` has another length (the pipeline driver checks both).
pub fn sweep_tree<K: RadixKey>(
    keys: &[K],
    order: Vec<u32>,
    aabbs: &[Aabb],
    k: &CollapseParams,
) -> Swept {
    sweep_tree_in(keys, order, aabbs, k, &mut SweepScratch::default())
}

/// [`sweep_tree`] with buffers taken from `scratch` (give them back with [`Swept::emit_in`]).
pub fn sweep_tree_in<K: RadixKey>(
    keys: &[K],
    order: Vec<u32>,
    aabbs: &[Aabb],
    k: &CollapseParams,
    scratch: &mut SweepScratch,
) -> Swept {
    let n = keys.len();
    assert!(
        n >= 1 && order.len() == n,
        "sweep_tree needs n ≥ 1 keys and as many ids"
    );
    let threads = rayon::current_num_threads();
    // Every split's area is written (by its task or as a top node) before it is read.
    let mut areas = std::mem::take(&mut scratch.areas);
    crate::buffers::refill(&mut areas, n - 1, 0.0);
    let target = (n / (threads * 8)).max(MIN_TASK);

    // Top of the tree, down to leaf ranges of at most `target` (none when one task does).
    let mut tops: Vec<TopNode> = Vec::new();
    let mut ranges: Vec<(usize, usize)> = Vec::new();
    if threads == 1 || n <= target {
        ranges.push((0, n - 1));
    } else {
        let nb = (n - 1).div_ceil(BLOCK);
        let blocks: Vec<((u64, u32), u32)> = (0..nb)
            .into_par_iter()
            .map(|b| {
                let (a, e) = (b * BLOCK, ((b + 1) * BLOCK).min(n - 1));
                let mut best = (dist(keys, a), a as u32);
                for s in a + 1..e {
                    let d = dist(keys, s);
                    if d > best.0 {
                        best = (d, s as u32);
                    }
                }
                best
            })
            .collect();
        // (leaf range, slot to fill: None = root, Some((top, is_right)))
        type Pending = ((usize, usize), Option<(usize, bool)>);
        let mut stack: Vec<Pending> = vec![((0, n - 1), None)];
        while let Some(((lo, hi), slot)) = stack.pop() {
            let r = if hi - lo < target {
                ranges.push((lo, hi));
                Ref::Task(ranges.len() as u32 - 1)
            } else {
                let s = argmax(keys, &blocks, lo, hi);
                tops.push(TopNode {
                    k: s,
                    l: Ref::Task(u32::MAX),
                    r: Ref::Task(u32::MAX),
                });
                let t = tops.len() - 1;
                stack.push(((s + 1, hi), Some((t, true))));
                stack.push(((lo, s), Some((t, false))));
                Ref::Top(t as u32)
            };
            match slot {
                None => {}
                Some((t, false)) => tops[t].l = r,
                Some((t, true)) => tops[t].r = r,
            }
        }
    }
    // Ranges are in left-to-right order (the stack pops left ranges first): hand each task its
    // own run of split areas (splits lo..hi) and sweep them in parallel.
    let input = Input {
        keys,
        order: &order,
        aabbs,
        k,
    };
    let mut jobs: Vec<(usize, usize, &mut [f64])> = Vec::with_capacity(ranges.len());
    let mut rest: &mut [f64] = &mut areas;
    let mut offset = 0usize;
    for &(lo, hi) in &ranges {
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(lo - offset);
        let (mine, tail) = tail.split_at_mut(hi - lo);
        jobs.push((lo, hi, mine));
        rest = tail;
        offset = hi;
    }
    // One record buffer per task, reused from earlier builds where there are some.
    let mut recs: Vec<Vec<Node>> = Vec::with_capacity(jobs.len());
    for _ in 0..jobs.len() {
        recs.push(scratch.records.pop().unwrap_or_default());
    }
    let tasks: Vec<(Closed, Vec<Node>)> = if jobs.len() == 1 {
        let (lo, hi, a) = jobs.pop().expect("one job");
        let mut rec = recs.pop().expect("one buffer");
        rec.clear();
        rec.reserve(2 * (hi - lo) + 1);
        let c = input.sweep(lo, hi, &mut rec, a, &mut Vec::new());
        vec![(c, rec)]
    } else {
        jobs.into_par_iter()
            .zip(recs)
            .with_max_len(1)
            .map_init(Vec::new, |stack, ((lo, hi, a), mut rec)| {
                rec.clear();
                rec.reserve(2 * (hi - lo) + 1);
                let c = input.sweep(lo, hi, &mut rec, a, stack);
                (c, rec)
            })
            .collect()
    };
    // Finish the top nodes bottom-up (children were created after their parents).
    let mut top_data: Vec<SlotData> = vec![tasks[0].0.d; tops.len()];
    for t in (0..tops.len()).rev() {
        let a = data_of(tops[t].l, &top_data, &tasks);
        let b = data_of(tops[t].r, &top_data, &tasks);
        let (d, ar) = join(&a, &b, k);
        top_data[t] = d;
        areas[tops[t].k] = ar;
    }
    let root = if tops.is_empty() {
        Ref::Task(0)
    } else {
        Ref::Top(0)
    };
    Swept {
        n,
        order,
        areas,
        tops,
        top_data,
        tasks,
        root,
    }
}

/// Data of a top node or task root.
#[inline]
fn data_of(r: Ref, top_data: &[SlotData], tasks: &[(Closed, Vec<Node>)]) -> SlotData {
    match r {
        Ref::Top(t) => top_data[t as usize],
        Ref::Task(t) => tasks[t as usize].0.d,
    }
}

impl Swept {
    /// Bounds of the whole tree.
    pub fn root_bounds(&self) -> Aabb {
        data_of(self.root, &self.top_data, &self.tasks).bounds
    }

    /// Headline SAH of the uncollapsed radix tree (`Ct = Ci = 1`, one primitive per leaf, root
    /// counted as inner): split areas and primitive areas (`aabbs`, by primitive id) each summed
    /// in fixed chunks in index order, so independent of the thread count.
    pub fn sah_headline(&self, aabbs: &[Aabb]) -> f64 {
        headline(&self.areas, aabbs, &self.root_bounds(), self.n)
    }

    /// Write the collapsed BVH in depth-first order (left child right after its parent), tasks
    /// in parallel on the current rayon pool.
    pub fn emit(self) -> Bvh {
        self.emit_in(Vec::new(), &mut SweepScratch::default())
    }

    /// [`Swept::emit`] into `nodes` (its allocation reused when large enough) and giving the
    /// sweep's buffers back to `scratch`.
    pub fn emit_in(self, mut nodes: Vec<Node>, scratch: &mut SweepScratch) -> Bvh {
        let Swept {
            order,
            areas,
            tops,
            top_data,
            tasks,
            root,
            ..
        } = self;
        let total = data_of(root, &top_data, &tasks).out as usize;
        // Every output slot is written below (top nodes, then each task's run).
        if nodes.capacity() >= total {
            nodes.clear();
            nodes.resize(total, Node::default());
        } else {
            nodes = zeroed(total);
        }
        // Top nodes, depth first; tasks get their output positions.
        let mut placed: Vec<(u32, u32)> = Vec::new(); // (task, position)
        let mut stack = vec![(root, 0u32)];
        while let Some((r, pos)) = stack.pop() {
            match r {
                Ref::Task(t) => placed.push((t, pos)),
                Ref::Top(t) => {
                    let d = top_data[t as usize];
                    if d.out == 1 {
                        nodes[pos as usize] = Node::leaf(d.bounds, d.first, d.count);
                        continue;
                    }
                    let tn = tops[t as usize];
                    let lpos = pos + 1;
                    let rpos = lpos + data_of(tn.l, &top_data, &tasks).out;
                    nodes[pos as usize] = Node::inner(d.bounds, lpos, rpos);
                    stack.push((tn.r, rpos));
                    stack.push((tn.l, lpos));
                }
            }
        }
        placed.sort_unstable_by_key(|p| p.1);
        let mut jobs: Vec<(&[Node], &mut [Node], u32)> = Vec::with_capacity(placed.len());
        let mut rest: &mut [Node] = &mut nodes;
        let mut offset = 0u32;
        for &(t, pos) in &placed {
            let rec = &tasks[t as usize].1;
            let (_, tail) = std::mem::take(&mut rest).split_at_mut((pos - offset) as usize);
            let (mine, tail) = tail.split_at_mut(rec.len());
            jobs.push((rec, mine, pos));
            rest = tail;
            offset = pos + rec.len() as u32;
        }
        if jobs.len() == 1 {
            let (rec, dst, base) = jobs.pop().expect("one job");
            relabel(rec, dst, base);
        } else {
            jobs.into_par_iter()
                .with_max_len(1)
                .for_each(|(rec, dst, base)| relabel(rec, dst, base));
        }
        scratch.areas = areas;
        scratch.records.extend(tasks.into_iter().map(|t| t.1));
        Bvh {
            nodes,
            prim_indices: order,
            root: 0,
        }
    }
}

/// Headline SAH from the per-split areas (summed in fixed chunks in index order), the primitive
/// boxes (likewise) and the root box; as `RadixTree::sah_headline` defines it.
fn headline(areas: &[f64], aabbs: &[Aabb], root: &Aabb, n: usize) -> f64 {
    const CH: usize = 1 << 15;
    let inner: Vec<f64> = areas.par_chunks(CH).map(|c| c.iter().sum()).collect();
    let leaves: Vec<f64> = aabbs
        .par_chunks(CH)
        .map(|c| c.iter().map(area).sum())
        .collect();
    let total = inner.iter().sum::<f64>() + leaves.iter().sum::<f64>();
    let ra = area(root);
    if ra > 0.0 {
        total / ra
    } else {
        (areas.len() + n) as f64
    }
}
