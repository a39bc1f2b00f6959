//! One-pass LBVH (the engine of builder `lbvh`): the Karras/Apetrei radix tree built by a
//! right-to-left stack sweep over the sorted codes, each node finished (bounds, cost, SAH-collapse
//! decision) the moment it closes and written straight into depth-first order; a streaming copy
//! then moves the blocks to their output places. Same tree and same BVH as Karras + refit + emit.
//!
//! The radix tree is the Cartesian tree of the split levels (see `level`): the split with the
//! highest level in a leaf range is that range's root. Two equal levels are always separated by
//! a higher one, so the tree is unique. The sweep keeps the open splits on a stack (levels
//! decreasing towards the top), each holding its finished right subtree; a new split first closes
//! every open split of lower level (the current subtree becomes its left child), then opens with
//! the current subtree as its right child. Everything the sweep touches is either sequential
//! (keys, order, records) or on the small stack; the only scattered reads are the primitive boxes.
//!
//! Records are written from the end of the buffer downwards. Going right to left, a subtree's
//! right block is written first (highest), its left block below it, its root below that: the
//! block reads root, left block, right block — depth first, left child right after its parent.
//! A node that collapses into a leaf drops its block and writes one leaf record at the block's
//! top, so the buffer always holds exactly the collapsed tree, and no depth is ever needed.
//!
//! ```text
//!   buffer:  ... free ... | P | [ left block ] | [ right block ] | (blocks closed earlier)
//!                           ^ written last       ^ written first
//!   inner record P: (bounds, position of left root, position of right root)
//! ```
//!
//! Parallel: the top of the tree is found top-down (each range's root split by binary search)
//! until the ranges are small enough; each range is swept as a task into its own buffer, the few
//! top nodes are then finished serially, and the blocks are copied to their output slices in
//! parallel pieces, child links moved by the block's displacement.
//!
//! The headline SAH needs the sum of every split's area; it is summed exactly (`AreaSum`),
//! so it does not depend on how the range was cut into tasks.

use emc_core::Aabb;
use rayon::prelude::*;

use super::node::{Bvh, Node};
use super::refit::{zeroed, CollapseParams, SlotData};
use super::sah::area;
use crate::sort::RadixKey;

/// Smallest leaf range handed to a task.
const MIN_TASK: usize = 1 << 14;
/// Nodes per parallel piece of the final copy.
const PLACE: usize = 1 << 16;
/// Primitive boxes prefetched ahead of the sweep.
const PREFETCH: usize = 16;

/// Most open splits at once: their levels strictly decrease towards the top and lie in
/// `1..=96` (see [`level`]).
const STACK: usize = 97;

/// A closed subtree: its data and its block of records, `root..end` (root first).
#[derive(Clone, Copy, Debug)]
struct Closed {
    d: SlotData,
    root: u32,
    end: u32,
}

/// An open split: its level and its finished right subtree.
#[derive(Clone, Copy, Debug)]
struct Open {
    lvl: u32,
    right: Closed,
}

/// Level of split `s` (between sorted positions `s` and `s + 1`): one plus the highest set bit
/// of the index-augmented distance `Δ(s)` of `apetrei.rs`, counted over the 96-bit word
/// (key xor, then position xor):
///
/// ```text
///   Δ(s) = ( x = k_s ⊕ k_{s+1} ,  y = s ⊕ (s+1) )
///   level(s) = 32 + (64 − clz64(x))   if x ≠ 0      (33..=96)
///            = 32 − clz32(y)           if x = 0      (1..=32)
/// ```
///
/// Comparing levels instead of full distances builds the same Cartesian tree: two splits
/// `a < b` of equal level always have a split of higher level between them (with keys sorted,
/// positions `a + 1` and `b` cannot agree above that bit), so the largest level of a range is
/// unique and a new split never meets an open one of its own level on the stack.
#[inline(always)]
pub(crate) fn level<K: RadixKey>(keys: &[K], s: usize) -> u32 {
    let x = keys[s].widen() ^ keys[s + 1].widen();
    let by_key = 96 - x.leading_zeros();
    let by_pos = 32 - ((s as u32) ^ (s as u32 + 1)).leading_zeros();
    if x != 0 {
        by_key
    } else {
        by_pos
    }
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

/// The record buffer of one sweep, filled from its end: `buf[free..]` holds the records.
struct Records<'a> {
    buf: &'a mut [Node],
    free: usize,
}

impl<K: RadixKey> Input<'_, K> {
    /// The leaf of sorted position `p`, written just below the records.
    #[inline(always)]
    fn leaf(&self, p: usize, rec: &mut Records) -> Closed {
        if let Some(&q) = p.checked_sub(PREFETCH).and_then(|i| self.order.get(i)) {
            prefetch(&self.aabbs[q as usize]);
        }
        let b = self.aabbs[self.order[p] as usize];
        let at = rec.free - 1;
        rec.buf[at] = Node::leaf(b, p as u32, 1);
        rec.free = at;
        Closed {
            d: SlotData {
                bounds: b,
                cost: self.k.ci * area(&b),
                first: p as u32,
                count: 1,
                out: 1,
            },
            root: at as u32,
            end: at as u32 + 1,
        }
    }

    /// Close split `o` with left subtree `left` (whose block lies just below the right
    /// subtree's); its area is added to `areas`. A subtree that collapses overwrites its block
    /// with one leaf record at the block's top, one that does not writes its inner record just
    /// below the block: either way one store, no branch.
    #[inline(always)]
    fn close(&self, o: &Open, left: &Closed, rec: &mut Records, areas: &mut AreaSum) -> Closed {
        let (d, ar) = join(&left.d, &o.right.d, self.k);
        areas.add(ar);
        let end = o.right.end;
        let (pos, node) = if d.out == 1 {
            (end as usize - 1, Node::leaf(d.bounds, d.first, d.count))
        } else {
            (
                left.root as usize - 1,
                Node::inner(d.bounds, left.root, o.right.root),
            )
        };
        rec.buf[pos] = node;
        rec.free = pos;
        Closed {
            d,
            root: pos as u32,
            end,
        }
    }

    /// Sweep the leaves `lo..=hi` from right to left: the collapsed subtree is written depth
    /// first at the end of `buf` (at least `2·(hi − lo) + 1` long; child links are positions in
    /// `buf`), the areas of the splits `lo..hi` are added to `areas`. Returns the subtree root
    /// and its block.
    fn sweep(&self, lo: usize, hi: usize, buf: &mut [Node], areas: &mut AreaSum) -> Closed {
        let free = buf.len();
        let mut rec = Records { buf, free };
        for p in (hi + 1).saturating_sub(PREFETCH).max(lo)..=hi {
            prefetch(&self.aabbs[self.order[p] as usize]);
        }
        let empty = Open {
            lvl: 0,
            right: Closed {
                d: SlotData {
                    bounds: Aabb::EMPTY,
                    cost: 0.0,
                    first: 0,
                    count: 0,
                    out: 0,
                },
                root: 0,
                end: 0,
            },
        };
        let mut stack = [empty; STACK];
        let mut top = 0usize;
        let mut cur = self.leaf(hi, &mut rec);
        for s in (lo..hi).rev() {
            let l = level(self.keys, s);
            while top > 0 && stack[top - 1].lvl < l {
                top -= 1;
                let o = stack[top];
                cur = self.close(&o, &cur, &mut rec, areas);
            }
            stack[top] = Open { lvl: l, right: cur };
            top += 1;
            cur = self.leaf(s, &mut rec);
        }
        while top > 0 {
            top -= 1;
            let o = stack[top];
            cur = self.close(&o, &cur, &mut rec, areas);
        }
        cur
    }
}

/// Copy a depth-first block whose child links are positions in its record buffer (`src[0]`
/// sits at position `from`) to output position `to`: every inner node's links move by
/// `to − from`.
fn place(src: &[Node], dst: &mut [Node], from: u32, to: u32) {
    let delta = to.wrapping_sub(from);
    for (d, s) in dst.iter_mut().zip(src) {
        *d = s.with_children_moved(delta);
    }
}

/// One swept leaf range: its subtree root and its record buffer (the block `root.root..
/// root.end`).
#[derive(Debug)]
struct Task {
    root: Closed,
    rec: Vec<Node>,
}

/// Where a top node's child lives.
#[derive(Clone, Copy, Debug)]
enum Ref {
    Top(u32),
    Task(u32),
}

/// A node above the tasks: its children.
#[derive(Clone, Copy, Debug)]
struct TopNode {
    l: Ref,
    r: Ref,
}

/// The split of highest level among the splits `a..b` of the leaves `a..=b` (`a < b`): the
/// root of that leaf range, found by binary search, as in Karras' top-down construction.
///
/// The keys of the range share every bit above the highest bit `h` in which `k_a` and `k_b`
/// differ, and bit `h` goes from 0 to 1 exactly once: the split is just before the first key
/// with bit `h` set. When `k_a = k_b` all keys of the range are equal and the positions decide:
/// the split is just before the one multiple of `2^h` in `a+1..=b`, `h` the highest bit of
/// `a ⊕ b`.
fn top_split<K: RadixKey>(keys: &[K], a: usize, b: usize) -> usize {
    let x = keys[a].widen() ^ keys[b].widen();
    if x != 0 {
        let h = 63 - x.leading_zeros();
        let (mut lo, mut hi) = (a + 1, b);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if (keys[mid].widen() >> h) & 1 != 0 {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        lo - 1
    } else {
        let h = 31 - ((a as u32) ^ (b as u32)).leading_zeros();
        ((b >> h) << h) - 1
    }
}

/// The finished radix tree of [`sweep_tree`]: per-task post-order records, the top nodes and
/// the exact sum of the split areas; [`Swept::emit`] turns it into the depth-first BVH.
#[derive(Debug)]
pub struct Swept {
    n: usize,
    order: Vec<u32>,
    areas: AreaSum,
    tops: Vec<TopNode>,
    top_data: Vec<SlotData>,
    tasks: Vec<Task>,
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

/// Buffers of the sweep kept between builds (see `build::BuildArena`): the record buffers of
/// the tasks.
#[derive(Debug, Default)]
pub struct SweepScratch {
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
    let target = (n / (threads * 8)).max(MIN_TASK);

    // Top of the tree, down to leaf ranges of at most `target` (none when one task does).
    let mut tops: Vec<TopNode> = Vec::new();
    let mut ranges: Vec<(usize, usize)> = Vec::new();
    if threads == 1 || n <= target {
        ranges.push((0, n - 1));
    } else {
        // (leaf range, slot to fill: None = root, Some((top, is_right)))
        type Pending = ((usize, usize), Option<(usize, bool)>);
        let mut stack: Vec<Pending> = vec![((0, n - 1), None)];
        while let Some(((lo, hi), slot)) = stack.pop() {
            let r = if hi - lo < target {
                ranges.push((lo, hi));
                Ref::Task(ranges.len() as u32 - 1)
            } else {
                let s = top_split(keys, lo, hi);
                tops.push(TopNode {
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
    // Ranges are in left-to-right order (the stack pops left ranges first); sweep them in
    // parallel.
    let input = Input {
        keys,
        order: &order,
        aabbs,
        k,
    };
    let mut jobs = ranges;
    // One record buffer per task, reused from earlier builds where one is long enough, else
    // fresh zeroed memory (faulted in only as far as the sweep writes).
    let mut recs: Vec<Vec<Node>> = Vec::with_capacity(jobs.len());
    for &(lo, hi) in &jobs {
        let need = 2 * (hi - lo) + 1;
        let b = match scratch.records.iter().position(|b| b.len() >= need) {
            Some(i) => scratch.records.swap_remove(i),
            None => zeroed(need),
        };
        recs.push(b);
    }
    let run = |(lo, hi): (usize, usize), mut rec: Vec<Node>| {
        let mut areas = AreaSum::new();
        let root = input.sweep(lo, hi, &mut rec, &mut areas);
        (Task { root, rec }, areas)
    };
    let (tasks, sums): (Vec<Task>, Vec<AreaSum>) = if jobs.len() == 1 {
        let job = jobs.pop().expect("one job");
        let (t, a) = run(job, recs.pop().expect("one buffer"));
        (vec![t], vec![a])
    } else {
        jobs.into_par_iter()
            .zip(recs)
            .with_max_len(1)
            .map(|(job, rec)| run(job, rec))
            .unzip()
    };
    let mut areas = AreaSum::new();
    for s in &sums {
        areas.merge(s);
    }
    // Finish the top nodes bottom-up (children were created after their parents).
    let mut top_data: Vec<SlotData> = vec![tasks[0].root.d; tops.len()];
    for t in (0..tops.len()).rev() {
        let a = data_of(tops[t].l, &top_data, &tasks);
        let b = data_of(tops[t].r, &top_data, &tasks);
        let (d, ar) = join(&a, &b, k);
        top_data[t] = d;
        areas.add(ar);
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
fn data_of(r: Ref, top_data: &[SlotData], tasks: &[Task]) -> SlotData {
    match r {
        Ref::Top(t) => top_data[t as usize],
        Ref::Task(t) => tasks[t as usize].root.d,
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
            tops,
            top_data,
            tasks,
            root,
            ..
        } = self;
        let total = data_of(root, &top_data, &tasks).out as usize;
        // Every output slot is written below (top nodes, then each task's run).
        if nodes.len() >= total {
            // A recycled buffer: no pass over memory that is about to be overwritten.
            nodes.truncate(total);
        } else if nodes.capacity() >= total {
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
        // Each task's block goes to its output slice, in pieces of at most `PLACE` nodes.
        type Job<'a> = (&'a [Node], &'a mut [Node], u32, u32);
        let mut jobs: Vec<Job> = Vec::with_capacity(placed.len());
        let mut rest: &mut [Node] = &mut nodes;
        let mut offset = 0u32;
        for &(t, pos) in &placed {
            let task = &tasks[t as usize];
            let (from, end) = (task.root.root, task.root.end);
            let rec = &task.rec[from as usize..end as usize];
            let (_, tail) = std::mem::take(&mut rest).split_at_mut((pos - offset) as usize);
            let (mine, tail) = tail.split_at_mut(rec.len());
            for (i, (src, dst)) in rec.chunks(PLACE).zip(mine.chunks_mut(PLACE)).enumerate() {
                let skip = (i * PLACE) as u32;
                jobs.push((src, dst, from + skip, pos + skip));
            }
            rest = tail;
            offset = pos + rec.len() as u32;
        }
        if rayon::current_num_threads() == 1 {
            for (src, dst, from, to) in jobs {
                place(src, dst, from, to);
            }
        } else {
            jobs.into_par_iter()
                .with_max_len(1)
                .for_each(|(src, dst, from, to)| place(src, dst, from, to));
        }
        scratch.records.extend(tasks.into_iter().map(|t| t.rec));
        Bvh {
            nodes,
            prim_indices: order,
            root: 0,
        }
    }
}

/// Headline SAH from the exact sum of the split areas, the primitive boxes (their areas summed
/// in fixed chunks in index order) and the root box; as `RadixTree::sah_headline` defines it.
fn headline(areas: &AreaSum, aabbs: &[Aabb], root: &Aabb, n: usize) -> f64 {
    const CH: usize = 1 << 15;
    let leaves: Vec<f64> = aabbs
        .par_chunks(CH)
        .map(|c| c.iter().map(area).sum())
        .collect();
    let total = areas.value() + leaves.iter().sum::<f64>();
    let ra = area(root);
    if ra > 0.0 {
        total / ra
    } else {
        (n - 1 + n) as f64
    }
}

/// Exact sum of non-negative finite `f64` values (the split areas of the headline SAH), so that
/// the result does not depend on how the sweep was cut into tasks: each value's 53-bit
/// significand is added, as an integer, to the 128-bit bucket of its exponent.
///
/// ```text
///   bits of x:  0 | e (11) | f (52)        x = m · 2^(max(e,1) − 1075),  m = f | [e ≠ 0]·2^52
///   bucket[e] += m                         (< 2^85 after 2^32 values: no overflow)
/// ```
#[derive(Clone, Debug)]
pub(crate) struct AreaSum {
    bucket: Box<[u128; 2048]>,
}

impl AreaSum {
    /// Zero.
    pub(crate) fn new() -> AreaSum {
        AreaSum {
            bucket: Box::new([0; 2048]),
        }
    }

    /// Add `x` (non-negative and finite; the sign bit is ignored).
    #[inline(always)]
    pub(crate) fn add(&mut self, x: f64) {
        let b = x.to_bits();
        let e = ((b >> 52) & 0x7ff) as usize;
        let m = (b & ((1 << 52) - 1)) | (((e != 0) as u64) << 52);
        self.bucket[e] += m as u128;
    }

    /// Add another sum.
    pub(crate) fn merge(&mut self, o: &AreaSum) {
        for (a, b) in self.bucket.iter_mut().zip(o.bucket.iter()) {
            *a += *b;
        }
    }

    /// The sum, rounded: each bucket converted and scaled by its power of two (exact), added
    /// from the smallest exponent up. A function of the bucket contents only.
    pub(crate) fn value(&self) -> f64 {
        let mut total = 0.0f64;
        for (e, &m) in self.bucket.iter().enumerate() {
            if m != 0 {
                total += m as f64 * pow2(e.max(1) as i32 - 1075);
            }
        }
        total
    }
}

/// `2^k` for `−1074 ≤ k ≤ 1023`, exactly (subnormal below −1022).
fn pow2(k: i32) -> f64 {
    if k >= -1022 {
        f64::from_bits(((k + 1023) as u64) << 52)
    } else {
        f64::from_bits(1u64 << (k + 1074))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// xorshift64*: deterministic test input.
    fn rng(s: &mut u64) -> u64 {
        *s ^= *s >> 12;
        *s ^= *s << 25;
        *s ^= *s >> 27;
        s.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    #[test]
    fn area_sum_is_exact_and_order_free() {
        let mut s = 7u64;
        let mut xs: Vec<f64> = (0..50_000)
            .map(|_| match rng(&mut s) % 4 {
                0 => 0.0,
                1 => f64::from_bits(rng(&mut s) % 1000), // subnormal
                _ => f64::from_bits(rng(&mut s) & 0x7fef_ffff_ffff_ffff) * 1e-200,
            })
            .filter(|x| x.is_finite())
            .collect();
        let mut a = AreaSum::new();
        xs.iter().for_each(|&x| a.add(x));
        // Another order, split into two partial sums.
        xs.reverse();
        let (l, r) = xs.split_at(xs.len() / 3);
        let (mut b, mut c) = (AreaSum::new(), AreaSum::new());
        l.iter().for_each(|&x| b.add(x));
        r.iter().for_each(|&x| c.add(x));
        b.merge(&c);
        assert_eq!(a.value().to_bits(), b.value().to_bits());
        // Small integers are summed exactly.
        let mut e = AreaSum::new();
        for i in 0..1000 {
            e.add(i as f64 * 0.5);
        }
        assert_eq!(e.value(), 249_750.0);
        assert_eq!(AreaSum::new().value(), 0.0);
        assert_eq!(pow2(-1074), f64::from_bits(1));
        assert_eq!(pow2(0), 1.0);
    }

    #[test]
    fn top_split_is_the_highest_level() {
        let mut s = 3u64;
        for round in 0..300 {
            let n = 2 + (rng(&mut s) % 200) as usize;
            // Few distinct keys (runs of equal keys) or many.
            let m = if round % 2 == 0 { 4 } else { 1 << 40 };
            let mut keys: Vec<u64> = (0..n).map(|_| rng(&mut s) % m).collect();
            keys.sort_unstable();
            for _ in 0..20 {
                let a = (rng(&mut s) % (n as u64 - 1)) as usize;
                let b = a + 1 + (rng(&mut s) % (n - 1 - a) as u64) as usize;
                let best = (a..b).max_by_key(|&x| level(&keys, x)).unwrap();
                let top = level(&keys, best);
                assert_eq!((a..b).filter(|&x| level(&keys, x) == top).count(), 1);
                assert_eq!(top_split(&keys, a, b), best, "{keys:?} {a} {b}");
            }
        }
    }
}
