//! The `atrbvh` post-pass: agglomerative treelet restructuring (Domingues & Pedrini 2015) of a
//! finished binary BVH, in parallel bottom-up waves with per-node atomic counters. It rewrites
//! only inner nodes in place (same node slots, same leaves), so the result stays a valid [`Bvh`].
//!
//! One pass, for a threshold `γ`:
//!
//! 1. Every leaf starts a climb (rayon over the leaves). At each parent an atomic counter is
//!    bumped; the first child to arrive stops, the second goes on, so a node is handled exactly
//!    once and only after both of its subtrees are final.
//! 2. The node's box, primitive count and subtree cost `c(n) = ct·A(n) + c(l) + c(r)` (a leaf:
//!    `ci·A(l)·|l|`) are computed from its children.
//! 3. If its subtree holds at least `γ` primitives the node becomes a treelet root: starting from
//!    its two children, the treelet leaf with the largest surface area that is not a real leaf is
//!    replaced by its two children until the treelet has `treelet_size` leaves.
//! 4. The treelet leaves are re-clustered agglomeratively: a distance matrix
//!    `d(i, j) = A(box_i ∪ box_j)` ([`half_area`], `f32`) is kept, and `k − 1` times the closest
//!    pair merges into a new cluster. The live clusters form a list; the merged cluster takes the
//!    lower position of the pair and the last cluster moves into the higher one. Ties go to the
//!    first pair `i < j` in row-major order of that list.
//! 5. If the new topology costs less, it is written back into the treelet's own inner-node slots
//!    (the treelet root keeps its slot, so nothing above it changes).
//!
//! Passes repeat `iterations` times with `γ` doubled each time. Since a node's result depends
//! only on its own subtree, the output does not depend on the number of threads or on timing.

use std::marker::PhantomData;
use std::sync::atomic::{AtomicU32, Ordering};

use emc_core::Aabb;
use glam::{Vec3, Vec3A};
use rayon::prelude::*;

use super::node::{Bvh, Node};
use super::sah::{sah_cost, SahConstants};
use super::validate::ValidateError;

/// Smallest accepted treelet size.
pub const MIN_TREELET_SIZE: usize = 7;
/// Largest accepted treelet size.
pub const MAX_TREELET_SIZE: usize = 9;

/// Marks "no parent" (the root) in the parent array.
const NO_PARENT: u32 = u32::MAX;

/// Settings of [`restructure`]. [`AtrConfig::default`] is the ATRBVH shipped configuration:
/// treelets of 9 leaves, 2 iterations, `γ` starting at the treelet size, `ct = 1.2`, `ci = 1`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct AtrConfig {
    /// Leaves per treelet, in [`MIN_TREELET_SIZE`]`..=`[`MAX_TREELET_SIZE`].
    pub treelet_size: usize,
    /// Number of bottom-up passes (0 only refits the boxes).
    pub iterations: u32,
    /// Minimum subtree primitive count of a treelet root in the first pass (doubled in each
    /// later pass); `None` means the treelet size.
    pub gamma: Option<u32>,
    /// Cost of one inner node (traversal); finite and positive.
    pub ct: f64,
    /// Cost of one primitive test (intersection); finite and positive.
    pub ci: f64,
}

impl Default for AtrConfig {
    fn default() -> Self {
        AtrConfig {
            treelet_size: 9,
            iterations: 2,
            gamma: None,
            ct: 1.2,
            ci: 1.0,
        }
    }
}

impl AtrConfig {
    /// With this many leaves per treelet.
    #[inline]
    pub fn with_treelet_size(mut self, treelet_size: usize) -> AtrConfig {
        self.treelet_size = treelet_size;
        self
    }

    /// With this many bottom-up passes.
    #[inline]
    pub fn with_iterations(mut self, iterations: u32) -> AtrConfig {
        self.iterations = iterations;
        self
    }

    /// With this minimum subtree size of a first-pass treelet root (`None`: the treelet size).
    #[inline]
    pub fn with_gamma(mut self, gamma: Option<u32>) -> AtrConfig {
        self.gamma = gamma;
        self
    }

    /// With this cost of an inner node.
    #[inline]
    pub fn with_ct(mut self, ct: f64) -> AtrConfig {
        self.ct = ct;
        self
    }

    /// With this cost of a primitive test.
    #[inline]
    pub fn with_ci(mut self, ci: f64) -> AtrConfig {
        self.ci = ci;
        self
    }

    /// Check every field; [`restructure`] calls this first.
    pub fn check(&self) -> Result<(), AtrError> {
        if !(MIN_TREELET_SIZE..=MAX_TREELET_SIZE).contains(&self.treelet_size) {
            return Err(AtrError::TreeletSize(self.treelet_size));
        }
        if self.gamma == Some(0) {
            return Err(AtrError::Gamma);
        }
        for (name, v) in [("ct", self.ct), ("ci", self.ci)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(AtrError::Constant { name, value: v });
            }
        }
        Ok(())
    }

    /// The threshold `γ` of pass `iteration` (0-based): the start value doubled per pass,
    /// saturating at `u32::MAX`.
    pub fn gamma_at(&self, iteration: u32) -> u32 {
        let g0 = self.gamma.unwrap_or(self.treelet_size as u32) as u64;
        let g = g0 << iteration.min(32);
        g.min(u32::MAX as u64) as u32
    }
}

/// Why [`restructure`] refused to run. The tree is left untouched in every case.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AtrError {
    /// The treelet size is outside the supported range.
    #[error(
        "treelet size {0} is outside {min}..={max}",
        min = MIN_TREELET_SIZE,
        max = MAX_TREELET_SIZE
    )]
    TreeletSize(usize),
    /// `γ` was given as 0.
    #[error("gamma must be at least 1")]
    Gamma,
    /// A cost constant is not a finite positive number.
    #[error("cost constant {name} = {value} must be finite and positive")]
    Constant {
        /// `"ct"` or `"ci"`.
        name: &'static str,
        /// The value given.
        value: f64,
    },
    /// The input tree does not pass [`Bvh::validate`] against the primitive boxes.
    #[error("input BVH is malformed: {0}")]
    Invalid(#[from] ValidateError),
}

/// What [`restructure`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AtrStats {
    /// Treelets formed (summed over passes).
    pub treelets_formed: u64,
    /// Treelets whose topology was replaced by a cheaper one (summed over passes).
    pub treelets_improved: u64,
    /// `(formed, improved)` per pass.
    pub per_iteration: Vec<(u64, u64)>,
    /// SAH of the input tree with the configured `ct`/`ci` ([`sah_cost`]).
    pub sah_before: f64,
    /// SAH of the output tree with the configured `ct`/`ci` ([`sah_cost`]).
    pub sah_after: f64,
}

/// Half the surface area of a box in `f32`, `(dx·dy + dy·dz) + dz·dx` with negative extents
/// clamped to 0: the clustering distance (only compared, never summed).
#[inline]
pub fn half_area(b: &Aabb) -> f32 {
    let d = (b.max - b.min).max(Vec3::ZERO);
    d.x * d.y + d.y * d.z + d.z * d.x
}

/// Per-node bookkeeping of a pass: the subtree cost, the parent and the primitive count.
#[derive(Clone, Copy, Debug, Default)]
struct Aux {
    cost: f64,
    parent: u32,
    count: u32,
}

/// Restructure `bvh` in place by agglomerative treelet restructuring; `aabbs[p]` is the box of
/// primitive `p`. The input must pass [`Bvh::validate`] (any leaf size is accepted; the
/// reference use is one primitive per leaf, before collapse). Leaf boxes are recomputed from
/// `aabbs` and (when `iterations ≥ 1`) inner boxes refitted, so the output is tight.
///
/// The set of leaves and every leaf's primitives are unchanged; only inner nodes are rewritten,
/// and only where the subtree cost strictly drops, so the SAH never rises. The result is
/// bit-identical for any number of rayon threads.
pub fn restructure(bvh: &mut Bvh, aabbs: &[Aabb], cfg: &AtrConfig) -> Result<AtrStats, AtrError> {
    restructure_with(
        bvh,
        aabbs,
        cfg,
        true,
        true,
        false,
        &mut AtrScratch::default(),
        &Unwatched,
    )
}

/// [`restructure`] without the SAH figures of [`AtrStats`] (`sah_before` and `sah_after` are
/// 0): the same tree, two whole-tree SAH passes cheaper, for builds that report nothing.
pub fn restructure_quiet(
    bvh: &mut Bvh,
    aabbs: &[Aabb],
    cfg: &AtrConfig,
) -> Result<AtrStats, AtrError> {
    restructure_with(
        bvh,
        aabbs,
        cfg,
        false,
        true,
        false,
        &mut AtrScratch::default(),
        &Unwatched,
    )
}

/// [`restructure_quiet`] of a tree this crate's LBVH builders just made, which are valid by
/// construction (and by their tests): the whole-tree validation runs in debug builds only
/// (5% of a San Francisco balanced build), and a leaf of one primitive keeps its box, which
/// those builders copy from the primitive's (the refit of every leaf reads the boxes in
/// random order: 3-5% of a one-thread balanced build). The last pass shows `watch` every node
/// of the output as it becomes final (see [`FinalNodes`]; [`Unwatched`] for nobody), so that
/// work over the finished tree can be done while its nodes are still in the cache; with
/// `cfg.iterations == 0` no pass runs and `watch` sees nothing.
pub(crate) fn restructure_built(
    bvh: &mut Bvh,
    aabbs: &[Aabb],
    cfg: &AtrConfig,
    scratch: &mut AtrScratch,
    watch: &impl FinalNodes,
) -> Result<AtrStats, AtrError> {
    restructure_with(
        bvh,
        aabbs,
        cfg,
        false,
        cfg!(debug_assertions),
        true,
        scratch,
        watch,
    )
}

/// What the last pass of a restructuring shows of the output tree: every node, children
/// before parents, whenever it writes the node (a treelet root's refit that an improved
/// treelet then replaces is shown only as replaced); the last time a node is shown it is
/// final. A node
/// is shown on the thread that owns its subtree at that moment (the pass's ownership rule), so
/// a watcher may keep per-node data in shared arrays without locks: a node's own entry is
/// written only by that thread, and its children's entries were written before, by threads
/// whose work the pass's counters have made visible.
pub(crate) trait FinalNodes: Sync {
    /// Node `i` is `node` (a leaf or an inner node whose children were shown before).
    ///
    /// # Safety
    /// Called only by the pass, under the ownership rule above.
    unsafe fn node(&self, i: u32, node: &Node);
}

/// A pass nobody watches.
pub(crate) struct Unwatched;

impl FinalNodes for Unwatched {
    #[inline(always)]
    unsafe fn node(&self, _: u32, _: &Node) {}
}

/// A watcher, or nobody.
impl<W: FinalNodes> FinalNodes for Option<W> {
    #[inline(always)]
    unsafe fn node(&self, i: u32, node: &Node) {
        if let Some(w) = self {
            // SAFETY: the caller keeps the contract, passed on as it is.
            unsafe { w.node(i, node) }
        }
    }
}

/// The per-node arrays of a restructuring (parents, bookkeeping, leaves, arrival counters),
/// kept between builds: made afresh they are ~40 bytes per node of new pages to fault in
/// (stanford-dragon: 10 of the 18 ms the restructuring spends before its first pass).
#[derive(Debug, Default)]
pub struct AtrScratch {
    parent: Vec<AtomicU32>,
    aux: Vec<Aux>,
    leaves: Vec<u32>,
    counters: Vec<AtomicU32>,
}

#[allow(clippy::too_many_arguments)]
fn restructure_with(
    bvh: &mut Bvh,
    aabbs: &[Aabb],
    cfg: &AtrConfig,
    sah: bool,
    validate: bool,
    single_exact: bool,
    scratch: &mut AtrScratch,
    watch: &impl FinalNodes,
) -> Result<AtrStats, AtrError> {
    cfg.check()?;
    if validate {
        bvh.validate(aabbs)?;
    }
    let k = SahConstants {
        ct: cfg.ct,
        ci: cfg.ci,
    };
    let mut stats = AtrStats {
        sah_before: if sah { sah_cost(bvh, k) } else { 0.0 },
        ..AtrStats::default()
    };
    let n = bvh.nodes.len();
    if n > 1 {
        // Parents and leaves, in parallel: the validated (or crate-built) tree gives every
        // non-root node exactly one parent, so the stores to real nodes never collide.
        // One pass over the nodes, in parallel chunks: the parents (a leaf's two stores go to
        // the spare slot `n`, so no branch depends on the node kind), the leaves in index order
        // (written at every node, kept at leaves), and tight leaf boxes from the primitives (a
        // one-primitive leaf of a crate-built tree already has its primitive's box, bit for
        // bit: the fold would give it again). With the arrays kept in `scratch`, this set-up
        // went from 18.5 to 7-9 ms of stanford-dragon's 145 ms of restructuring (three passes
        // over fresh arrays, the leaves filtered by a branch per node, before).
        let AtrScratch {
            parent,
            aux,
            leaves,
            counters,
        } = scratch;
        refill(parent, n + 1, NO_PARENT);
        let parent = &*parent;
        const CHUNK: usize = 1 << 14;
        let prim_indices = &bvh.prim_indices;
        let leaf_runs: Vec<Vec<u32>> = bvh
            .nodes
            .par_chunks_mut(CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let base = (c * CHUNK) as u32;
                let mut run = vec![0u32; chunk.len()];
                let mut kept = 0;
                for (k, node) in chunk.iter_mut().enumerate() {
                    let i = base + k as u32;
                    let leaf = node.is_leaf();
                    let (l, r) = if leaf {
                        (n, n)
                    } else {
                        (node.left() as usize, node.right() as usize)
                    };
                    parent[l].store(i, Ordering::Relaxed);
                    parent[r].store(i, Ordering::Relaxed);
                    run[kept] = i;
                    kept += usize::from(leaf);
                    let (f, c) = (node.first() as usize, node.count() as usize);
                    if leaf && !(single_exact && c == 1) {
                        node.bounds = prim_indices[f..f + c]
                            .iter()
                            .fold(Aabb::EMPTY, |b, &p| b.union(&aabbs[p as usize]));
                    }
                    debug_assert!(
                        !(leaf && single_exact && c == 1)
                            || node.bounds == aabbs[prim_indices[f] as usize]
                    );
                }
                run.truncate(kept);
                run
            })
            .collect();
        leaves.clear();
        leaves.extend(leaf_runs.iter().flatten());
        aux.clear();
        aux.par_extend(parent[..n].par_iter().map(|p| Aux {
            cost: 0.0,
            parent: p.load(Ordering::Relaxed),
            count: 0,
        }));
        refill(counters, n, 0);
        let counters = &*counters;
        let serial = rayon::current_num_threads() == 1;
        for it in 0..cfg.iterations {
            counters
                .par_iter()
                .for_each(|c| c.store(0, Ordering::Relaxed));
            let gamma = cfg.gamma_at(it);
            // The same pass, shown to `watch` when it is the last.
            macro_rules! pass {
                ($watch:expr) => {
                    Pass {
                        nodes: SharedSlice::new(&mut bvh.nodes),
                        aux: SharedSlice::new(aux),
                        counters,
                        serial,
                        gamma,
                        size: cfg.treelet_size,
                        ct: cfg.ct,
                        ci: cfg.ci,
                        watch: $watch,
                    }
                };
            }
            let (formed, improved) = if it + 1 == cfg.iterations {
                run_pass(&pass!(watch), leaves)
            } else {
                run_pass(&pass!(&Unwatched), leaves)
            };
            stats.treelets_formed += formed;
            stats.treelets_improved += improved;
            stats.per_iteration.push((formed, improved));
        }
    }
    if n <= 1 {
        // A lone leaf: no inner node to restructure; refit its box like every other leaf.
        if let Some(root) = bvh.nodes.first_mut() {
            let (f, c) = (root.first() as usize, root.count() as usize);
            root.bounds = bvh.prim_indices[f..f + c]
                .iter()
                .fold(Aabb::EMPTY, |b, &p| b.union(&aabbs[p as usize]));
            if cfg.iterations > 0 {
                // SAFETY: no pass runs: this thread owns the whole (one-node) tree.
                unsafe { watch.node(0, root) };
            }
        }
        stats.per_iteration = vec![(0, 0); cfg.iterations as usize];
    }
    if sah {
        stats.sah_after = sah_cost(bvh, k);
    }
    Ok(stats)
}

/// Every climb of `pass` (in any order: the tree does not depend on it); returns the treelets
/// (formed, improved).
fn run_pass<W: FinalNodes>(pass: &Pass<'_, W>, leaves: &[u32]) -> (u64, u64) {
    if pass.serial {
        leaves
            .iter()
            .map(|&leaf| pass.climb(leaf))
            .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    } else {
        leaves
            .par_iter()
            .map(|&leaf| pass.climb(leaf))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }
}

/// `v` as `n` counters holding `value`, its allocation reused (set in parallel).
fn refill(v: &mut Vec<AtomicU32>, n: usize, value: u32) {
    v.truncate(n);
    v.par_iter().for_each(|c| c.store(value, Ordering::Relaxed));
    let more = n - v.len();
    v.extend((0..more).map(|_| AtomicU32::new(value)));
}

/// A slice that several threads index at once, each touching only elements it owns.
///
/// The ownership rule of a pass: the thread that wins the counter race at node `n` owns `n`'s
/// whole subtree from then on (all other threads have finished with it, and none will come back:
/// they only climb above their own finished nodes). Every access goes through the bounds-checked
/// `get`/`set` below.
struct SharedSlice<'a, T> {
    ptr: *mut T,
    len: usize,
    /// Ties the pointer to the exclusive borrow it came from.
    _borrow: PhantomData<&'a mut [T]>,
}

// SAFETY: a `SharedSlice` is only built from a `&mut [T]` that outlives the pass, and elements
// are only accessed under the ownership rule above, so no element is accessed by two threads
// without a happens-before edge (the AcqRel counters provide it).
unsafe impl<T: Send> Sync for SharedSlice<'_, T> {}

impl<'a, T: Copy> SharedSlice<'a, T> {
    fn new(s: &'a mut [T]) -> Self {
        SharedSlice {
            ptr: s.as_mut_ptr(),
            len: s.len(),
            _borrow: PhantomData,
        }
    }

    /// Read element `i`.
    ///
    /// # Safety
    /// The calling thread owns element `i` under the pass's ownership rule.
    #[inline]
    unsafe fn get(&self, i: u32) -> T {
        let i = i as usize;
        assert!(i < self.len, "node index out of range");
        // SAFETY: in bounds (checked above); no concurrent writer by the caller's contract.
        unsafe { *self.ptr.add(i) }
    }

    /// Write element `i`.
    ///
    /// # Safety
    /// The calling thread owns element `i` under the pass's ownership rule.
    #[inline]
    unsafe fn set(&self, i: u32, v: T) {
        let i = i as usize;
        assert!(i < self.len, "node index out of range");
        // SAFETY: in bounds (checked above); no concurrent reader or writer by the contract.
        unsafe { *self.ptr.add(i) = v }
    }
}

/// One bottom-up pass over the tree.
struct Pass<'a, W> {
    nodes: SharedSlice<'a, Node>,
    aux: SharedSlice<'a, Aux>,
    counters: &'a [AtomicU32],
    /// The climbs run one after another on this thread (so the counters need no locked add).
    serial: bool,
    gamma: u32,
    size: usize,
    ct: f64,
    ci: f64,
    /// Shown every node the pass writes.
    watch: &'a W,
}

/// A treelet under construction: its leaves (node indices) and its inner-node slots, the root
/// first.
struct Treelet {
    leaves: [u32; MAX_TREELET_SIZE],
    n_leaves: usize,
    slots: [u32; MAX_TREELET_SIZE - 1],
    n_slots: usize,
}

impl<W: FinalNodes> Pass<'_, W> {
    /// Start at `leaf`, climb while this thread is the second to arrive; returns the treelets
    /// (formed, improved) on the way.
    fn climb(&self, leaf: u32) -> (u64, u64) {
        // SAFETY: every leaf is the start of exactly one climb and nobody else touches a leaf's
        // bookkeeping before its climb has passed the parent's counter.
        unsafe {
            let node = self.nodes.get(leaf);
            let mut a = self.aux.get(leaf);
            a.count = node.count();
            a.cost = self.ci * node.bounds.area_f64() * node.count() as f64;
            self.aux.set(leaf, a);
            self.watch.node(leaf, &node);
        }
        let (mut formed, mut improved) = (0u64, 0u64);
        let mut cur = leaf;
        loop {
            // SAFETY: `cur` is owned by this thread (a leaf it started at, or a node it won).
            let p = unsafe { self.aux.get(cur) }.parent;
            if p == NO_PARENT {
                break;
            }
            let first = if self.serial {
                // One thread walks every climb in turn: a plain read and write (a locked add
                // per node was 6% of a one-thread bathroom balanced build).
                let c = &self.counters[p as usize];
                let seen = c.load(Ordering::Relaxed);
                c.store(seen + 1, Ordering::Relaxed);
                seen == 0
            } else {
                // AcqRel: releases this subtree's writes to the sibling's thread, and acquires
                // the sibling subtree's writes when this thread arrives second.
                self.counters[p as usize].fetch_add(1, Ordering::AcqRel) == 0
            };
            if first {
                break;
            }
            // SAFETY: this thread arrived second at `p`, so both subtrees of `p` are final and
            // their writers are done; `p`'s subtree is now owned by this thread alone.
            let (f, i) = unsafe { self.process(p) };
            formed += f as u64;
            improved += i as u64;
            cur = p;
        }
        (formed, improved)
    }

    /// Refit `p`, compute its cost, and restructure its treelet if it is large enough.
    /// Returns (treelet formed, treelet improved).
    ///
    /// # Safety
    /// The calling thread owns `p`'s subtree.
    unsafe fn process(&self, p: u32) -> (bool, bool) {
        // SAFETY: every index touched below is `p` or lies in `p`'s subtree, which the caller
        // owns.
        unsafe {
            let node = self.nodes.get(p);
            let (l, r) = (node.left(), node.right());
            let (nl, nr) = (self.nodes.get(l), self.nodes.get(r));
            let (al, ar) = (self.aux.get(l), self.aux.get(r));
            let bounds = nl.bounds.union(&nr.bounds);
            let count = al.count.saturating_add(ar.count);
            let cost = self.ct * bounds.area_f64() + al.cost + ar.cost;
            let refit = Node::inner(bounds, l, r);
            self.nodes.set(p, refit);
            let mut ap = self.aux.get(p);
            ap.count = count;
            ap.cost = cost;
            self.aux.set(p, ap);
            if count < self.gamma {
                self.watch.node(p, &refit);
                return (false, false);
            }
            let t = self.form_treelet(p, l, r);
            if t.n_leaves < 3 {
                self.watch.node(p, &refit);
                return (false, false);
            }
            // A rewritten treelet shows its nodes as it writes them.
            let improved = self.recluster(p, &t, cost);
            if !improved {
                self.watch.node(p, &refit);
            }
            (true, improved)
        }
    }

    /// Grow the treelet of `p` by repeatedly opening its largest-area non-leaf treelet leaf.
    ///
    /// # Safety
    /// The calling thread owns `p`'s subtree.
    unsafe fn form_treelet(&self, p: u32, l: u32, r: u32) -> Treelet {
        let mut t = Treelet {
            leaves: [0; MAX_TREELET_SIZE],
            n_leaves: 2,
            slots: [0; MAX_TREELET_SIZE - 1],
            n_slots: 1,
        };
        t.leaves[0] = l;
        t.leaves[1] = r;
        t.slots[0] = p;
        let mut areas = [0.0f64; MAX_TREELET_SIZE];
        let mut open = [false; MAX_TREELET_SIZE];
        for i in 0..2 {
            // SAFETY: the children of `p` are in `p`'s subtree.
            let nd = unsafe { self.nodes.get(t.leaves[i]) };
            areas[i] = nd.bounds.area_f64();
            open[i] = !nd.is_leaf();
        }
        while t.n_leaves < self.size {
            let mut best = usize::MAX;
            let mut best_area = f64::NEG_INFINITY;
            for i in 0..t.n_leaves {
                if open[i] && areas[i] > best_area {
                    best = i;
                    best_area = areas[i];
                }
            }
            if best == usize::MAX {
                break;
            }
            let x = t.leaves[best];
            // SAFETY: `x` is a treelet leaf, hence in `p`'s subtree, and so are its children.
            let (nx, c0, c1) = unsafe {
                let nx = self.nodes.get(x);
                (nx, self.nodes.get(nx.left()), self.nodes.get(nx.right()))
            };
            t.slots[t.n_slots] = x;
            t.n_slots += 1;
            let j = t.n_leaves;
            t.leaves[best] = nx.left();
            areas[best] = c0.bounds.area_f64();
            open[best] = !c0.is_leaf();
            t.leaves[j] = nx.right();
            areas[j] = c1.bounds.area_f64();
            open[j] = !c1.is_leaf();
            t.n_leaves += 1;
        }
        t
    }

    /// Agglomerative clustering of the treelet leaves; writes the new topology into the treelet's
    /// slots if it is cheaper than `old_cost`. Returns whether it did.
    ///
    /// # Safety
    /// The calling thread owns `p`'s subtree.
    unsafe fn recluster(&self, p: u32, t: &Treelet, old_cost: f64) -> bool {
        const M: usize = MAX_TREELET_SIZE;
        let k = t.n_leaves;
        // The live clusters sit at positions 0..live; a merge keeps the lower position and moves
        // the last cluster into the higher one (a swap-remove).
        // Boxes in SIMD lanes: `Vec3A::min`/`max` give the same bits as `Aabb::union` (both
        // return the second operand on equal values, and boxes here hold no NaN).
        let mut lo = [Vec3A::ZERO; M];
        let mut hi = [Vec3A::ZERO; M];
        let mut costs = [0.0f64; M];
        let mut counts = [0u32; M];
        let mut refs = [0u32; M];
        for i in 0..k {
            // SAFETY: treelet leaves lie in `p`'s subtree.
            let (nd, a) = unsafe { (self.nodes.get(t.leaves[i]), self.aux.get(t.leaves[i])) };
            lo[i] = nd.bounds.min.into();
            hi[i] = nd.bounds.max.into();
            costs[i] = a.cost;
            counts[i] = a.count;
            refs[i] = t.leaves[i];
        }
        // `half_area` of the union of two boxes, on lanes.
        let dist_of = |al: Vec3A, ah: Vec3A, bl: Vec3A, bh: Vec3A| {
            let d = (ah.max(bh) - al.min(bl)).max(Vec3A::ZERO);
            d.x * d.y + d.y * d.z + d.z * d.x
        };
        // Symmetric distance matrix (the diagonal is never read).
        let mut dist = [[0.0f32; M]; M];
        for i in 0..k {
            for j in i + 1..k {
                let d = dist_of(lo[i], hi[i], lo[j], hi[j]);
                dist[i][j] = d;
                dist[j][i] = d;
            }
        }
        // Merge `m` (0-based) goes to slot `slots[k - 2 - m]`: the last merge is the root `p`.
        let mut merges = [(Aabb::EMPTY, 0u32, 0u32, 0.0f64, 0u32); M - 1];
        let mut live = k;
        for (m, merge) in merges.iter_mut().enumerate().take(k - 1) {
            // Closest pair; ties go to the first pair in row-major order.
            let (mut bi, mut bj, mut bd) = (0usize, 1usize, dist[0][1]);
            for (i, row) in dist.iter().enumerate().take(live) {
                for (j, &d) in row.iter().enumerate().take(live).skip(i + 1) {
                    if d < bd {
                        (bi, bj, bd) = (i, j, d);
                    }
                }
            }
            let (bl, bh) = (lo[bi].min(lo[bj]), hi[bi].max(hi[bj]));
            let b = Aabb::new(bl.into(), bh.into());
            let c = self.ct * b.area_f64() + costs[bi] + costs[bj];
            let count = counts[bi].saturating_add(counts[bj]);
            *merge = (b, refs[bi], refs[bj], c, count);
            lo[bi] = bl;
            hi[bi] = bh;
            costs[bi] = c;
            counts[bi] = count;
            refs[bi] = t.slots[k - 2 - m];
            let last = live - 1;
            if bj != last {
                lo[bj] = lo[last];
                hi[bj] = hi[last];
                costs[bj] = costs[last];
                counts[bj] = counts[last];
                refs[bj] = refs[last];
                dist[bj] = dist[last];
                for row in dist.iter_mut().take(live) {
                    row[bj] = row[last];
                }
            }
            live = last;
            for o in 0..live {
                if o != bi {
                    let d = dist_of(bl, bh, lo[o], hi[o]);
                    dist[bi][o] = d;
                    dist[o][bi] = d;
                }
            }
        }
        let new_cost = merges[k - 2].3;
        // A relative margin keeps rounding noise from being taken for a gain, so that the SAH
        // summed over the whole tree cannot rise.
        if new_cost >= old_cost * (1.0 - 1e-9) {
            return false;
        }
        for (m, &(b, left, right, cost, count)) in merges[..k - 1].iter().enumerate() {
            let slot = t.slots[k - 2 - m];
            // SAFETY: `slot`, `left` and `right` are treelet slots or treelet leaves, all in
            // `p`'s subtree.
            unsafe {
                let node = Node::inner(b, left, right);
                self.nodes.set(slot, node);
                // Its children are treelet leaves (unchanged) or earlier merges (shown).
                self.watch.node(slot, &node);
                let mut a = self.aux.get(slot);
                a.cost = cost;
                a.count = count;
                self.aux.set(slot, a);
                for c in [left, right] {
                    let mut ac = self.aux.get(c);
                    ac.parent = slot;
                    self.aux.set(c, ac);
                }
            }
        }
        debug_assert_eq!(t.slots[0], p);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tree over `n` unit boxes on a jittered line, built by halving, with its nodes stored
    /// in the order `order` gives (the root wherever that puts it).
    fn tree(n: usize, seed: u32, reversed: bool) -> (Bvh, Vec<Aabb>) {
        let mut x = seed | 1;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x % 1000) as f32 / 100.0
        };
        let aabbs: Vec<Aabb> = (0..n)
            .map(|i| {
                let o = Vec3::new(i as f32 + next(), next(), next());
                Aabb::new(o, o + Vec3::ONE)
            })
            .collect();
        fn make(aabbs: &[Aabb], b: usize, e: usize, nodes: &mut Vec<Node>) -> u32 {
            let at = nodes.len();
            nodes.push(Node::default());
            let node = if e - b == 1 {
                Node::leaf(aabbs[b], b as u32, 1)
            } else {
                let m = b + (e - b) / 2;
                let l = make(aabbs, b, m, nodes);
                let r = make(aabbs, m, e, nodes);
                let bx = nodes[l as usize].bounds.union(&nodes[r as usize].bounds);
                Node::inner(bx, l, r)
            };
            nodes[at] = node;
            at as u32
        }
        let mut nodes = Vec::new();
        make(&aabbs, 0, n, &mut nodes);
        let mut bvh = Bvh {
            nodes,
            prim_indices: (0..n as u32).collect(),
            root: 0,
        };
        if reversed {
            // Node i moves to n − 1 − i: the root last, every child before its parent.
            let last = bvh.nodes.len() as u32 - 1;
            bvh.nodes.reverse();
            for node in &mut bvh.nodes {
                if !node.is_leaf() {
                    *node = Node::inner(node.bounds, last - node.left(), last - node.right());
                }
            }
            bvh.root = last;
        }
        (bvh, aabbs)
    }

    #[test]
    fn reused_scratch_changes_no_tree() {
        // Trees of both sizes, roots first and last, one scratch: each equals a fresh run.
        let mut scratch = AtrScratch::default();
        for (n, seed, reversed) in [
            (700, 1, false),
            (300, 2, true),
            (900, 3, true),
            (50, 4, false),
        ] {
            let (bvh, aabbs) = tree(n, seed, reversed);
            let cfg = AtrConfig::default();
            let (mut fresh, mut reused) = (bvh.clone(), bvh);
            let a = restructure_built(
                &mut fresh,
                &aabbs,
                &cfg,
                &mut AtrScratch::default(),
                &Unwatched,
            );
            let b = restructure_built(&mut reused, &aabbs, &cfg, &mut scratch, &Unwatched);
            assert_eq!(a, b);
            assert!(a.expect("valid tree").treelets_improved > 0);
            assert_eq!(fresh, reused, "{n} primitives, reversed {reversed}");
        }
    }

    /// Records every node the last pass shows, in order.
    struct Recorder(std::sync::Mutex<Vec<(u32, Node)>>);

    impl FinalNodes for Recorder {
        unsafe fn node(&self, i: u32, node: &Node) {
            self.0.lock().expect("not poisoned").push((i, *node));
        }
    }

    #[test]
    fn the_last_pass_shows_every_node_final_and_children_first() {
        for (n, seed, reversed, iterations, threads) in [
            (700, 5, false, 2, 1),
            (900, 6, true, 2, 3),
            (400, 7, false, 1, 2),
            (1, 8, false, 2, 1),
            (2, 9, true, 3, 1),
            (300, 10, false, 0, 1),
        ] {
            let (bvh, aabbs) = tree(n, seed, reversed);
            let cfg = AtrConfig::default().with_iterations(iterations);
            let (mut plain, mut watched) = (bvh.clone(), bvh);
            let watch = Recorder(std::sync::Mutex::new(Vec::new()));
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool");
            let stats = pool.install(|| {
                restructure_built(
                    &mut plain,
                    &aabbs,
                    &cfg,
                    &mut AtrScratch::default(),
                    &Unwatched,
                )
                .expect("valid tree");
                restructure_built(
                    &mut watched,
                    &aabbs,
                    &cfg,
                    &mut AtrScratch::default(),
                    &watch,
                )
                .expect("valid tree")
            });
            // Watching changes nothing.
            assert_eq!(plain, watched, "{n} primitives");
            let shown = watch.0.into_inner().expect("not poisoned");
            if iterations == 0 {
                assert!(shown.is_empty(), "no pass, nothing shown");
                continue;
            }
            // The last pass rewrote treelets (so their nodes were shown as rewritten).
            let last_pass = stats.per_iteration.last().expect("a pass");
            assert!(
                n < 100 || last_pass.1 > 0,
                "{n} primitives: no treelet improved"
            );
            // The last time each node is shown, it is the output's node, and each inner node's
            // children were last shown before it.
            let mut last = vec![usize::MAX; watched.nodes.len()];
            for (k, &(i, _)) in shown.iter().enumerate() {
                last[i as usize] = k;
            }
            for (i, node) in watched.nodes.iter().enumerate() {
                let k = last[i];
                assert_ne!(k, usize::MAX, "node {i} of {n} never shown");
                assert_eq!(shown[k].1, *node, "node {i} shown other than final");
                if !node.is_leaf() {
                    assert!(last[node.left() as usize] < k && last[node.right() as usize] < k);
                }
            }
            // Whenever a node is shown, its children as shown then were shown before.
            let mut seen = vec![false; watched.nodes.len()];
            for &(i, node) in &shown {
                if !node.is_leaf() {
                    assert!(seen[node.left() as usize] && seen[node.right() as usize]);
                }
                seen[i as usize] = true;
            }
        }
    }
}
