//! The binary radix tree both LBVH hierarchy builders fill (Karras top-down, Apetrei bottom-up)
//! and its parallel bottom-up pass: bounds, primitive counts and the optimal SAH-collapse
//! decision per node, each node finished by the second child to arrive. Iterative only.

use std::sync::atomic::{AtomicU32, AtomicU64, AtomicU8, Ordering};

use emc_core::Aabb;
use glam::Vec3;
use rayon::prelude::*;

use super::sah::area;

/// "No node" in parent and child slots.
pub const NONE: u32 = u32::MAX;

/// Leaves handled per rayon task in the bottom-up passes.
pub(crate) const LEAVES_PER_TASK: usize = 4096;

/// Parameters of the SAH leaf collapse.
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct CollapseParams {
    /// Cost of an inner node (traversal), `Ct`.
    pub ct: f64,
    /// Cost of a primitive (intersection), `Ci`.
    pub ci: f64,
    /// Largest leaf the collapse may create (1 = keep one primitive per leaf).
    pub max_leaf: u32,
}

impl Default for CollapseParams {
    /// `Ct = 1.2`, `Ci = 1`, at most 8 primitives per leaf.
    fn default() -> Self {
        CollapseParams {
            ct: 1.2,
            ci: 1.0,
            max_leaf: 8,
        }
    }
}

impl CollapseParams {
    /// Costs `ct` (inner node) and `ci` (primitive), leaves of at most `max_leaf`.
    #[inline]
    pub const fn new(ct: f64, ci: f64, max_leaf: u32) -> CollapseParams {
        CollapseParams { ct, ci, max_leaf }
    }

    /// With leaves of at most `max_leaf` primitives.
    #[inline]
    pub const fn with_max_leaf(mut self, max_leaf: u32) -> CollapseParams {
        self.max_leaf = max_leaf;
        self
    }

    /// No collapse: one primitive per leaf.
    pub const NONE: CollapseParams = CollapseParams {
        ct: 1.0,
        ci: 1.0,
        max_leaf: 1,
    };
}

/// What the bottom-up pass knows of one internal node once both children are done. Every field
/// is an atomic written once (relaxed) by the finishing thread and published by the release half
/// of the parent's arrival counter, so no `unsafe` is needed.
#[derive(Debug, Default)]
pub struct Slot {
    bounds: [AtomicU32; 6],
    cost: AtomicU64,
    first: AtomicU32,
    count: AtomicU32,
    out: AtomicU32,
}

/// Plain copy of a finished [`Slot`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlotData {
    /// Union of the children's boxes.
    pub bounds: Aabb,
    /// Optimal collapsed SAH cost of the subtree (unnormalised).
    pub cost: f64,
    /// First sorted position under the node.
    pub first: u32,
    /// Primitives under the node.
    pub count: u32,
    /// Nodes the subtree emits after collapse (1 when it becomes a leaf).
    pub out: u32,
}

impl Slot {
    #[inline]
    fn store(&self, d: &SlotData) {
        let b = [
            d.bounds.min.x,
            d.bounds.min.y,
            d.bounds.min.z,
            d.bounds.max.x,
            d.bounds.max.y,
            d.bounds.max.z,
        ];
        for (a, v) in self.bounds.iter().zip(b) {
            a.store(v.to_bits(), Ordering::Relaxed);
        }
        self.cost.store(d.cost.to_bits(), Ordering::Relaxed);
        self.first.store(d.first, Ordering::Relaxed);
        self.count.store(d.count, Ordering::Relaxed);
        self.out.store(d.out, Ordering::Relaxed);
    }

    /// Read the slot (after the pass, or after acquiring the node's completion).
    #[inline]
    pub fn load(&self) -> SlotData {
        let f = |i: usize| f32::from_bits(self.bounds[i].load(Ordering::Relaxed));
        SlotData {
            bounds: Aabb::new(Vec3::new(f(0), f(1), f(2)), Vec3::new(f(3), f(4), f(5))),
            cost: f64::from_bits(self.cost.load(Ordering::Relaxed)),
            first: self.first.load(Ordering::Relaxed),
            count: self.count.load(Ordering::Relaxed),
            out: self.out.load(Ordering::Relaxed),
        }
    }
}

/// Types whose all-zero bit pattern is a valid value, so buffers of them can come straight from
/// the allocator's zeroed pages (no initialising pass over memory the build overwrites anyway).
///
/// # Safety
/// Implement only for types for which all-zero bytes are a valid, initialised value.
pub(crate) unsafe trait Zeroable: Sized {}
// SAFETY: an atomic integer is an integer in a cell; zero is a valid value.
unsafe impl Zeroable for AtomicU8 {}
// SAFETY: as above.
unsafe impl Zeroable for AtomicU32 {}
// SAFETY: an array of zeroable values is zeroable.
unsafe impl Zeroable for [AtomicU32; 2] {}
// SAFETY: `Slot` holds only atomic integers (and padding), each valid at zero.
unsafe impl Zeroable for Slot {}
// SAFETY: all-zero bits are the float +0.0.
unsafe impl Zeroable for f64 {}
// SAFETY: `Node` is plain `f32`s and `u32`s (`#[repr(C)]`, no padding); zero is a valid inner
// node value (it is always overwritten before the tree is used).
unsafe impl Zeroable for super::node::Node {}

/// `n` zero values from zeroed allocator memory (lazily faulted in by the OS).
pub(crate) fn zeroed<T: Zeroable>(n: usize) -> Vec<T> {
    if n == 0 || std::mem::size_of::<T>() == 0 {
        return Vec::new();
    }
    let layout = std::alloc::Layout::array::<T>(n).expect("at most 2^31 nodes of ≤ 64 bytes");
    // SAFETY: the layout has a non-zero size (checked above).
    let p = unsafe { std::alloc::alloc_zeroed(layout) }.cast::<T>();
    if p.is_null() {
        std::alloc::handle_alloc_error(layout);
    }
    // SAFETY: `p` comes from the global allocator with the layout of `[T; n]` (what `Vec` frees
    // with), is non-null and holds `n` zeroed `T`, each a valid value by `Zeroable`.
    unsafe { Vec::from_raw_parts(p, n, n) }
}

/// A binary radix tree over `n` sorted leaves. Node ids: internal nodes `0..n−1`, leaf of sorted
/// position `p` = `n − 1 + p` (so with one primitive the root is the leaf, id 0).
#[derive(Debug)]
pub struct RadixTree {
    /// Number of leaves.
    pub n: usize,
    /// Children `[left, right]` of each internal node (node ids).
    pub children: Vec<[AtomicU32; 2]>,
    /// Parent of every node (internal then leaves); [`NONE`] for the root. Empty when the
    /// builder does not need parent links (Apetrei).
    pub parents: Vec<AtomicU32>,
    /// Per-internal-node results of the bottom-up pass.
    pub slots: Vec<Slot>,
    /// Root node id.
    pub root: u32,
}

/// The primitive boxes in sorted order (`sorted[p] = aabbs[order[p]]`), gathered in parallel
/// once so that the tree passes read leaves sequentially instead of chasing `order`.
pub fn gather_sorted(aabbs: &[Aabb], order: &[u32]) -> Vec<Aabb> {
    crate::buffers::collect(
        order
            .par_iter()
            .with_min_len(1 << 14)
            .map(|&i| aabbs[i as usize]),
    )
}

/// Leaf box, count and cost of sorted position `p` (`sorted` as from [`gather_sorted`]).
#[inline]
pub(crate) fn leaf_data(sorted: &[Aabb], p: usize, k: &CollapseParams) -> SlotData {
    let b = sorted[p];
    SlotData {
        bounds: b,
        cost: k.ci * area(&b),
        first: p as u32,
        count: 1,
        out: 1,
    }
}

impl RadixTree {
    /// An empty tree shell for `n ≥ 1` leaves: children and slots zero (every one is written by
    /// the builder before it is read), parent links zero except node 0's, which is [`NONE`]
    /// (node 0 is Karras' root; the builder sets every other node's parent).
    pub(crate) fn with_leaves(n: usize, parents: bool) -> RadixTree {
        let inner = n.saturating_sub(1);
        let parents = if parents {
            let p: Vec<AtomicU32> = zeroed(inner + n);
            p[0].store(NONE, Ordering::Relaxed);
            p
        } else {
            Vec::new()
        };
        RadixTree {
            n,
            children: zeroed(inner),
            parents,
            slots: zeroed(inner),
            root: 0,
        }
    }

    /// Is node id `c` a leaf?
    #[inline]
    pub fn is_leaf(&self, c: u32) -> bool {
        c as usize >= self.n - 1
    }

    /// Children of internal node `i`.
    #[inline]
    pub fn children_of(&self, i: u32) -> (u32, u32) {
        let c = &self.children[i as usize];
        (c[0].load(Ordering::Relaxed), c[1].load(Ordering::Relaxed))
    }

    /// Data of any node: a leaf from the primitive boxes, an internal node from its slot.
    #[inline]
    pub(crate) fn data(&self, c: u32, sorted: &[Aabb], k: &CollapseParams) -> SlotData {
        if self.is_leaf(c) {
            leaf_data(sorted, c as usize - (self.n - 1), k)
        } else {
            self.slots[c as usize].load()
        }
    }

    /// Finish internal node `i` from its two (finished) children and store the result.
    #[inline]
    pub(crate) fn finish(&self, i: u32, l: u32, r: u32, sorted: &[Aabb], k: &CollapseParams) {
        let a = self.data(l, sorted, k);
        let b = self.data(r, sorted, k);
        self.slots[i as usize].store(&combine(&a, &b, k));
    }

    /// Bounds of the whole tree (`sorted` as from [`gather_sorted`]).
    pub fn root_bounds(&self, sorted: &[Aabb]) -> Aabb {
        self.data(self.root, sorted, &CollapseParams::NONE).bounds
    }

    /// Output-subtree size of node id `c` (1 for a leaf or a collapsed node).
    #[inline]
    pub fn out_of(&self, c: u32) -> u32 {
        if self.is_leaf(c) {
            1
        } else {
            self.slots[c as usize].out.load(Ordering::Relaxed)
        }
    }

    /// Headline SAH of the uncollapsed tree (`Ct = Ci = 1`, one primitive per leaf, root counted
    /// as inner), summed in fixed-size chunks in a fixed order: independent of the thread count.
    pub fn sah_headline(&self, aabbs: &[Aabb]) -> f64 {
        const CH: usize = 1 << 15;
        let inner: Vec<f64> = self
            .slots
            .par_chunks(CH)
            .map(|c| c.iter().map(|s| area(&s.load().bounds)).sum())
            .collect();
        let leaves: Vec<f64> = aabbs
            .par_chunks(CH)
            .map(|c| c.iter().map(area).sum())
            .collect();
        let total = inner.iter().sum::<f64>() + leaves.iter().sum::<f64>();
        let root = if self.n == 1 {
            aabbs[0]
        } else {
            self.slots[self.root as usize].load().bounds
        };
        let ra = area(&root);
        if ra > 0.0 {
            total / ra
        } else {
            (self.slots.len() + self.n) as f64
        }
    }
}

/// Combine two finished children into their parent, deciding the optimal collapse: the subtree
/// becomes one leaf when `ci·A·N < ct·A + cost(l) + cost(r)` and `N ≤ max_leaf`.
#[inline]
pub(crate) fn combine(a: &SlotData, b: &SlotData, k: &CollapseParams) -> SlotData {
    combine_with_area(a, b, k).0
}

/// [`combine`], also returning the parent's surface area (the one-pass sweep sums it for the
/// headline SAH).
#[inline(always)]
pub(crate) fn combine_with_area(a: &SlotData, b: &SlotData, k: &CollapseParams) -> (SlotData, f64) {
    let bounds = a.bounds.union(&b.bounds);
    let ar = area(&bounds);
    let count = a.count + b.count;
    let split = k.ct * ar + a.cost + b.cost;
    let as_leaf = k.ci * ar * count as f64;
    // Without a branch (the decision is data-dependent, a mispredicted branch costs more than
    // the select): the mask is all ones when the subtree becomes a leaf.
    let leafy = (count <= k.max_leaf) & (as_leaf < split);
    let mask = (leafy as u64).wrapping_neg();
    let cost = f64::from_bits((as_leaf.to_bits() & mask) | (split.to_bits() & !mask));
    let out = if leafy { 1 } else { 1 + a.out + b.out };
    let d = SlotData {
        bounds,
        cost,
        first: a.first.min(b.first),
        count,
        out,
    };
    (d, ar)
}

/// Parallel bottom-up pass over a tree with parent links (Karras): one walk per leaf, stopping
/// at the first arrival on each internal node; the second arrival finishes the node. Each
/// arrival counter is a byte; the `AcqRel` increment publishes the child's slot to the finisher.
/// `sorted` holds the primitive boxes in sorted order ([`gather_sorted`]).
pub fn refit(tree: &RadixTree, sorted: &[Aabb], k: &CollapseParams) {
    let n = tree.n;
    if n < 2 {
        return;
    }
    let flags: Vec<AtomicU8> = zeroed(n - 1);
    (0..n)
        .into_par_iter()
        .with_min_len(LEAVES_PER_TASK)
        .for_each(|p| {
            let mut cur = (n - 1 + p) as u32;
            loop {
                let parent = tree.parents[cur as usize].load(Ordering::Relaxed);
                if parent == NONE {
                    break;
                }
                if flags[parent as usize].fetch_add(1, Ordering::AcqRel) == 0 {
                    break;
                }
                let (l, r) = tree.children_of(parent);
                tree.finish(parent, l, r, sorted, k);
                cur = parent;
            }
        });
}
