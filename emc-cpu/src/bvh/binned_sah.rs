//! `binned-sah`: the top-down binned surface-area-heuristic builder, the quality reference the
//! LBVH builders are measured against. Centroid binning (32 bins per axis by default), one
//! primitive per leaf, parallel with rayon, and bit-identical output for any thread count.
//!
//! Each node bins its primitives' centroids along all three axes inside the node's centroid
//! box, sweeps the bins for the split with the lowest `A_L·N_L + A_R·N_R` (areas of the exact
//! unions of the bins' primitive boxes, in `f64`) and partitions its index range stably. When
//! every centroid of a node is the same point, the range is halved instead, so the depth stays
//! bounded even for a million identical primitives. Large nodes bin and partition in parallel
//! over fixed-size chunks; subtrees run in parallel through `rayon::join` down to a bounded
//! join depth and finish on an explicit work stack, so no input can exhaust the call stack.
//!
//! The hot loops (binning, partitioning) have an AVX2 path for the `f64` centroid and bin
//! arithmetic of all three axes at once (`mod simd`, the file's only `unsafe`), chosen at run
//! time and equal to the scalar one bit for bit (same IEEE operations per lane). Binning also
//! records every primitive's three bins (`tags`) for the partition that follows, and which bins
//! are in use (bit masks), so the split sweep visits only non-empty bins. The bins of an axis
//! are a fixed array of [`MAX_BINS`] indexed by masked bytes, so no bin access is
//! bounds-checked. A bin is eight lanes (its minimum and count, its negated maximum: one `min`
//! and one integer add per axis and primitive), and where the tags come in runs of equal bins
//! (a coherent mesh, whose order the stable partitions keep) a run is merged in registers and
//! added once. The root's references, box check and bounds are one pass.
//!
//! [`build_binned_sah_leaves`] stops at the leaves an SAH rule makes (the library's quality
//! preset): the same splits above them, nothing built below.
#![deny(unsafe_code)]

use emc_core::Aabb;
use glam::{Vec3A, Vec4};
use rayon::prelude::*;
use thiserror::Error;

use super::node::{Bvh, Node};

/// Set by [`force_scalar`].
static SCALAR_ONLY: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Make every later build use the scalar binning and partition loops (`true`) or the fastest
/// this CPU has (`false`, the default). Both give the same tree bit for bit; the switch exists
/// so tests can hold the SIMD path against the scalar one on the same machine.
#[doc(hidden)]
pub fn force_scalar(on: bool) {
    SCALAR_ONLY.store(on, std::sync::atomic::Ordering::Relaxed);
}

/// Bins per axis used when the caller has no reason to choose otherwise.
pub const DEFAULT_BINS: usize = 32;

/// Largest accepted number of bins per axis (the bins in use are kept as bits of a 64-bit word).
pub const MAX_BINS: usize = 64;

/// Largest accepted number of primitives: the `2n − 1` nodes must be addressable by the 31-bit
/// child indices of [`Node`].
pub const MAX_PRIMS: usize = 1 << 30;

/// Primitives per chunk when a node is binned and partitioned in parallel. Fixed, so the work
/// split (and the order of every reduction) does not depend on the number of threads.
const CHUNK: usize = 8192;

/// Nodes with at least this many primitives bin and partition in parallel.
const PAR_NODE_MIN: usize = 4 * CHUNK;

/// Subtrees with at least this many primitives are split off with `rayon::join`.
const PAR_SUBTREE_MIN: usize = 2048;

/// Bound on nested `rayon::join` calls; deeper subtrees continue on an explicit work stack.
const MAX_JOIN_DEPTH: u32 = 48;

/// Why a binned-SAH build was refused.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum BinnedSahError {
    /// The number of bins per axis is outside `2..=MAX_BINS`.
    #[error("binned SAH needs between 2 and {MAX_BINS} bins per axis, got {0}")]
    BinCount(usize),
    /// A [`LeafRule`] with `max_leaf = 0` or a non-finite cost.
    #[error("a leaf rule needs max_leaf >= 1 and finite costs")]
    LeafRule,
    /// The input holds no primitive.
    #[error("binned SAH needs at least one primitive")]
    NoPrimitives,
    /// More primitives than the node format can address.
    #[error("{count} primitives exceed the node format's limit of {MAX_PRIMS}")]
    TooManyPrimitives {
        /// Number of primitives given.
        count: usize,
    },
    /// A primitive box has a non-finite coordinate or `min > max` on some axis.
    #[error("primitive {index} has a non-finite or inverted box")]
    InvalidBox {
        /// Index of the first offending primitive.
        index: usize,
    },
}

/// A finished build: the hierarchy and its depth.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BinnedSahBuild {
    /// The hierarchy: `2n − 1` nodes in depth-first order (root at 0, left subtree before the
    /// right one), one primitive per leaf.
    pub bvh: Bvh,
    /// Edges on the longest root-to-leaf path (0 for a single primitive).
    pub depth: u32,
}

/// Builds a binned-SAH BVH over `aabbs` with `bins` centroid bins per axis
/// ([`DEFAULT_BINS`] is the reference setting), one primitive per leaf.
///
/// The result does not depend on the size of the rayon thread pool it runs in.
pub fn build_binned_sah(aabbs: &[Aabb], bins: usize) -> Result<Bvh, BinnedSahError> {
    build_binned_sah_detailed(aabbs, bins).map(|b| b.bvh)
}

/// As [`build_binned_sah`], also reporting the depth of the tree.
pub fn build_binned_sah_detailed(
    aabbs: &[Aabb],
    bins: usize,
) -> Result<BinnedSahBuild, BinnedSahError> {
    build_with(aabbs, bins, None, &mut BinnedScratch::default())
}

/// When a node of the top-down build becomes a leaf instead of being split: it holds at most
/// `max_leaf` primitives and `Ci·A·n < Ct·A + Ci·(A_L·n_L + A_R·n_R)` for the split binning
/// chose (its children priced as leaves), the rule of the bottom-up collapse with the
/// children's costs taken one level deep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeafRule {
    /// Largest leaf (≥ 1).
    pub max_leaf: u32,
    /// Cost of a node visit.
    pub ct: f64,
    /// Cost of a primitive test.
    pub ci: f64,
}

impl LeafRule {
    /// True when a node of `n` primitives and area `area` is cheaper as a leaf than split into
    /// sides of `n_left` primitives and area `area_left` and the rest of area `area_right`.
    #[inline]
    fn leaf(&self, n: usize, area: f64, n_left: usize, area_left: f64, area_right: f64) -> bool {
        let split = self.ct * area
            + self.ci * (area_left * n_left as f64 + area_right * (n - n_left) as f64);
        n <= self.max_leaf as usize && self.ci * area * (n as f64) < split
    }
}

/// The binned-SAH build cut at the leaves `rule` makes: a node that becomes a leaf is not
/// split further, so the nodes above the leaves, and every split they make, are those of
/// [`build_binned_sah`] (the same bins, the same partitions), and only the subtrees below the
/// leaves are never built. The nodes are compact, in depth-first order. `max_leaf = 1` gives
/// [`build_binned_sah`]'s tree.
pub fn build_binned_sah_leaves(
    aabbs: &[Aabb],
    bins: usize,
    rule: LeafRule,
) -> Result<BinnedSahBuild, BinnedSahError> {
    if rule.max_leaf == 0 || !(rule.ct.is_finite() && rule.ci.is_finite()) {
        return Err(BinnedSahError::LeafRule);
    }
    build_with(
        aabbs,
        bins,
        (rule.max_leaf > 1).then_some(rule),
        &mut BinnedScratch::default(),
    )
}

/// The buffers of a binned-SAH build, kept for the next one (see
/// [`build_binned_sah_leaves_in`]): two primitive arrays, the node array, the tags and the
/// primitive order. A build's result does not depend on what the scratch held before.
#[derive(Clone, Debug, Default)]
pub struct BinnedScratch {
    src: Vec<PrimRef>,
    dst: Vec<PrimRef>,
    nodes: Vec<Node>,
    compact: Vec<Node>,
    prim_indices: Vec<u32>,
    tags: Vec<[u8; 4]>,
}

impl BinnedScratch {
    /// Take back the node and primitive arrays of a finished build for the next one.
    pub fn recycle(&mut self, bvh: Bvh) {
        if bvh.nodes.capacity() > self.nodes.capacity() {
            self.nodes = bvh.nodes;
        } else {
            self.compact = bvh.nodes;
        }
        self.prim_indices = bvh.prim_indices;
    }
}

/// [`build_binned_sah_leaves`] in the buffers of `scratch` (a warm build faults no fresh
/// pages for them). Hand the result's hierarchy back with [`BinnedScratch::recycle`].
pub fn build_binned_sah_leaves_in(
    aabbs: &[Aabb],
    bins: usize,
    rule: LeafRule,
    scratch: &mut BinnedScratch,
) -> Result<BinnedSahBuild, BinnedSahError> {
    if rule.max_leaf == 0 || !(rule.ct.is_finite() && rule.ci.is_finite()) {
        return Err(BinnedSahError::LeafRule);
    }
    build_with(aabbs, bins, (rule.max_leaf > 1).then_some(rule), scratch)
}

fn build_with(
    aabbs: &[Aabb],
    bins: usize,
    rule: Option<LeafRule>,
    scratch: &mut BinnedScratch,
) -> Result<BinnedSahBuild, BinnedSahError> {
    if !(2..=MAX_BINS).contains(&bins) {
        return Err(BinnedSahError::BinCount(bins));
    }
    let n = aabbs.len();
    if n == 0 {
        return Err(BinnedSahError::NoPrimitives);
    }
    if n > MAX_PRIMS {
        return Err(BinnedSahError::TooManyPrimitives { count: n });
    }
    // Every element of these is written before it is read (the nodes a build uses, every
    // primitive's slot, every tag), so reused buffers keep their old contents.
    let s = scratch;
    crate::buffers::resized_par(&mut s.src, n, PrimRef::default());
    // One pass writes the references, checks every box and takes the root's bounds (those of
    // `ordered_bounds`: the same chunks, folded in the same order).
    let (bounds, cbounds, valid) = prim_refs(aabbs, &mut s.src);
    if !valid {
        let index = aabbs
            .iter()
            .position(|b| !(b.is_finite() && b.is_valid()))
            .unwrap_or_default();
        return Err(BinnedSahError::InvalidBox { index });
    }
    crate::buffers::resized(&mut s.dst, n, PrimRef::default());
    crate::buffers::resized(&mut s.nodes, 2 * n - 1, Node::default());
    crate::buffers::resized(&mut s.prim_indices, n, 0u32);
    crate::buffers::resized(&mut s.tags, n, [0u8; 4]);
    let ctx = Ctx {
        src: &mut s.src,
        dst: &mut s.dst,
        nodes: &mut s.nodes,
        out: &mut s.prim_indices,
        tags: &mut s.tags,
        prim_base: 0,
        node_base: 0,
    };
    let task = Task {
        bounds,
        cbounds,
        depth: 0,
    };
    let (depth, used) = build_parallel(ctx, task, bins, rule, 0);
    let nodes = if used < s.nodes.len() {
        let mut out = std::mem::take(&mut s.compact);
        compact_into(&s.nodes, used, &mut out);
        out
    } else {
        std::mem::take(&mut s.nodes)
    };
    Ok(BinnedSahBuild {
        bvh: Bvh {
            nodes,
            prim_indices: std::mem::take(&mut s.prim_indices),
            root: 0,
        },
        depth,
    })
}

/// The `used` nodes reachable from root 0 of `nodes` (a tree whose subtrees own contiguous
/// ranges with unused slots at their ends), renumbered in depth-first order into `out`
/// (emptied first; its allocation reused when large enough).
fn compact_into(nodes: &[Node], used: usize, out: &mut Vec<Node>) {
    out.clear();
    if out.capacity() < used {
        *out = Vec::with_capacity(used);
        crate::hugepage::advise(out);
    }
    // (old index, new index of the parent whose right child this is, or u32::MAX)
    let mut stack: Vec<(u32, u32)> = vec![(0, u32::MAX)];
    while let Some((i, parent)) = stack.pop() {
        let me = out.len() as u32;
        if parent != u32::MAX {
            let p = out[parent as usize];
            out[parent as usize] = Node::inner(p.bounds, p.left(), me);
        }
        let node = nodes[i as usize];
        if node.is_leaf() {
            out.push(node);
        } else {
            out.push(Node::inner(node.bounds, me + 1, 0));
            stack.push((node.right(), me));
            stack.push((node.left(), u32::MAX));
        }
    }
    debug_assert_eq!(out.len(), used);
}

/// A primitive while the tree is built: its box in two 16-byte lanes, the id in the bits of
/// the fourth lane of `min` (32 bytes, moved by partitioning).
///
/// ```text
///   lo: min.x | min.y | min.z | id (u32 bits)      hi: max.x | max.y | max.z | 0
/// ```
#[derive(Clone, Copy, Debug, Default)]
struct PrimRef {
    lo: Vec4,
    hi: Vec4,
}

impl PrimRef {
    #[inline]
    fn new(b: &Aabb, id: u32) -> PrimRef {
        PrimRef {
            lo: b.min.extend(f32::from_bits(id)),
            hi: b.max.extend(0.0),
        }
    }

    #[inline]
    fn id(&self) -> u32 {
        self.lo.w.to_bits()
    }

    /// The box as two SIMD vectors (the id lane dropped).
    #[inline]
    fn simd(&self) -> (Vec3A, Vec3A) {
        (Vec3A::from_vec4(self.lo), Vec3A::from_vec4(self.hi))
    }

    /// Centroid, exact in `f64` (half the sum of two `f32`).
    #[inline]
    fn centroid(&self) -> [f64; 3] {
        [
            (self.lo.x as f64 + self.hi.x as f64) * 0.5,
            (self.lo.y as f64 + self.hi.y as f64) * 0.5,
            (self.lo.z as f64 + self.hi.z as f64) * 0.5,
        ]
    }

    #[inline]
    fn aabb(&self) -> Aabb {
        Aabb::new(self.lo.truncate(), self.hi.truncate())
    }

    /// Surface area of the box, as [`Box3::area`].
    #[inline]
    fn area(&self) -> f64 {
        let (min, max) = self.simd();
        Box3 { min, max }.area()
    }
}

/// An `f32` box in SIMD registers, for the binning loop.
#[derive(Clone, Copy, Debug)]
struct Box3 {
    min: Vec3A,
    max: Vec3A,
}

impl Box3 {
    const EMPTY: Box3 = Box3 {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };

    #[inline]
    fn grow_ref(&mut self, r: &PrimRef) {
        let (lo, hi) = r.simd();
        self.min = self.min.min(lo);
        self.max = self.max.max(hi);
    }

    #[inline]
    fn union(&self, o: &Box3) -> Box3 {
        Box3 {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    /// Surface area in `f64` (the same arithmetic as [`Aabb::area_f64`]; by SSE2 `f64`
    /// lanes on x86-64, operation for operation).
    #[inline]
    fn area(&self) -> f64 {
        #[cfg(target_arch = "x86_64")]
        {
            simd::area(self)
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.aabb().area_f64()
    }

    #[inline]
    fn aabb(&self) -> Aabb {
        Aabb::new(self.min.into(), self.max.into())
    }
}

/// The box of a set of centroids, in `f64`.
#[derive(Clone, Copy, Debug)]
struct CentroidBox {
    min: [f64; 3],
    max: [f64; 3],
}

impl CentroidBox {
    const EMPTY: CentroidBox = CentroidBox {
        min: [f64::INFINITY; 3],
        max: [f64::NEG_INFINITY; 3],
    };

    #[inline]
    fn grow(&mut self, c: [f64; 3]) {
        self.min = std::array::from_fn(|a| self.min[a].min(c[a]));
        self.max = std::array::from_fn(|a| self.max[a].max(c[a]));
    }

    #[inline]
    fn union(&self, o: &CentroidBox) -> CentroidBox {
        CentroidBox {
            min: std::array::from_fn(|a| self.min[a].min(o.min[a])),
            max: std::array::from_fn(|a| self.max[a].max(o.max[a])),
        }
    }
}

/// Maps a centroid coordinate to its bin on each axis of one node.
#[derive(Clone, Copy, Debug)]
struct BinMap {
    origin: [f64; 3],
    /// `bins / extent`, or 0 on an axis without centroid extent (everything in bin 0).
    scale: [f64; 3],
    /// Axes with a positive centroid extent.
    active: [bool; 3],
    bins: usize,
}

impl BinMap {
    fn new(cb: &CentroidBox, bins: usize) -> BinMap {
        let mut m = BinMap {
            origin: cb.min,
            scale: [0.0; 3],
            active: [false; 3],
            bins,
        };
        for a in 0..3 {
            let extent = cb.max[a] - cb.min[a];
            // Centroids are halves of sums of f32, so a positive extent is at least 2^-150 and
            // `bins / extent` stays finite in f64.
            if extent > 0.0 {
                m.scale[a] = bins as f64 / extent;
                m.active[a] = true;
            }
        }
        m
    }

    /// Bin of coordinate `c` on `axis`: `floor((c − origin) · bins / extent)`, the maximum
    /// clamped into the last bin. Monotone in `c`; the node's smallest centroid lands in bin 0
    /// and its largest in bin `bins − 1`, so a split between them always exists.
    #[inline]
    fn bin(&self, c: f64, axis: usize) -> usize {
        let t = (c - self.origin[axis]) * self.scale[axis];
        // t is never negative or NaN for a centroid inside the node; clamping in f64 first
        // keeps the conversion to a plain truncation.
        t.min((self.bins - 1) as f64) as u32 as usize
    }

    /// The three bins of `r`'s centroid (byte 3 unused).
    #[inline]
    fn tag(&self, r: &PrimRef) -> [u8; 4] {
        let c = r.centroid();
        [
            self.bin(c[0], 0) as u8,
            self.bin(c[1], 1) as u8,
            self.bin(c[2], 2) as u8,
            0,
        ]
    }

    fn any_active(&self) -> bool {
        self.active.iter().any(|&a| a)
    }
}

/// Capacity of one axis of [`Bins`]: indices are masked with `BIN_MASK`, so no bin access
/// needs a bounds check.
const BIN_CAP: usize = MAX_BINS;
const BIN_MASK: usize = BIN_CAP - 1;

/// One bin: its box and its primitive count in eight lanes, so that one 8-lane `min` against
/// a primitive's [`BinBox::of`] grows the box and one integer add counts it:
/// ```text
///   lo:  min.x  min.y  min.z  count (the lane's bits; min with the primitive's +inf keeps it)
///   nhi: -max.x -max.y -max.z +inf
/// ```
/// `min(−a, −b) = −max(a, b)` exactly, with the same operand taken on ties (the second), so
/// the box is bit for bit the one `min`/`max` would grow.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct BinBox {
    lo: Vec4,
    nhi: Vec4,
}

impl BinBox {
    /// An empty bin.
    const EMPTY: BinBox = BinBox {
        lo: Vec4::new(f32::INFINITY, f32::INFINITY, f32::INFINITY, 0.0),
        nhi: Vec4::splat(f32::INFINITY),
    };

    /// Primitive `r` as a one-primitive bin whose count lane is +inf (so a `min` keeps the
    /// bin's count).
    #[inline(always)]
    fn of(r: &PrimRef) -> BinBox {
        let (lo, hi) = r.simd();
        BinBox {
            lo: lo.extend(f32::INFINITY),
            nhi: (-hi).extend(f32::INFINITY),
        }
    }

    /// Grow by `o` (`o` second in every `min`), the count lane left as it is.
    #[inline(always)]
    fn grow(&mut self, o: &BinBox) {
        let count = self.lo.w;
        self.lo = self.lo.min(o.lo);
        self.nhi = self.nhi.min(o.nhi);
        self.lo.w = count;
    }

    /// The primitives counted in the bin.
    #[inline(always)]
    fn count(&self) -> u32 {
        self.lo.w.to_bits()
    }

    /// Add `n` to the count.
    #[inline(always)]
    fn add_count(&mut self, n: u32) {
        self.lo.w = f32::from_bits(self.lo.w.to_bits() + n);
    }

    /// The box.
    #[inline(always)]
    fn box3(&self) -> Box3 {
        Box3 {
            min: Vec3A::from_vec4(self.lo),
            max: -Vec3A::from_vec4(self.nhi),
        }
    }
}

/// The bins of one node, all three axes, with the sweep's scratch space. Between nodes every
/// bin is empty ([`BinBox::EMPTY`]): [`Bins::clear_used`] restores that by visiting only the
/// bins a node used (bit `k` of `used[axis]`).
#[derive(Clone, Debug)]
struct Bins {
    bins: [[BinBox; BIN_CAP]; 3],
    used: [u64; 3],
    /// Sweep scratch: the areas and counts of the suffixes of one axis's non-empty bins.
    suffix_area: [f64; BIN_CAP],
    suffix_count: [u32; BIN_CAP],
}

impl Bins {
    fn new(nb: usize) -> Box<Bins> {
        debug_assert!(nb <= BIN_CAP);
        Box::new(Bins {
            bins: [[BinBox::EMPTY; BIN_CAP]; 3],
            used: [0; 3],
            suffix_area: [0.0; BIN_CAP],
            suffix_count: [0; BIN_CAP],
        })
    }

    /// Adds `refs` to the (empty) bins and writes each primitive's three bins to `tags`
    /// (same length).
    fn fill(&mut self, refs: &[PrimRef], tags: &mut [[u8; 4]], map: &BinMap) {
        debug_assert!(self.used == [0; 3]);
        debug_assert_eq!(refs.len(), tags.len());
        #[cfg(target_arch = "x86_64")]
        if simd::fill(self, refs, tags, map) {
            return;
        }
        for (r, t) in refs.iter().zip(tags.iter_mut()) {
            *t = map.tag(r);
        }
        let mut used = [0u64; 3];
        for (r, t) in refs.iter().zip(tags.iter()) {
            let p = BinBox::of(r);
            for (a, u) in used.iter_mut().enumerate() {
                let k = t[a] as usize & BIN_MASK;
                let b = &mut self.bins[a][k];
                b.grow(&p);
                b.add_count(1);
                *u |= 1u64 << k;
            }
        }
        self.used = used;
    }

    /// Empties the bins again, touching only the non-empty ones.
    fn clear_used(&mut self) {
        for a in 0..3 {
            let mut m = self.used[a];
            while m != 0 {
                let k = m.trailing_zeros() as usize & BIN_MASK;
                self.bins[a][k] = BinBox::EMPTY;
                m &= m - 1;
            }
        }
        self.used = [0; 3];
    }

    /// Adds the bins of `o` (same bin map) to these.
    fn merge(&mut self, o: &Bins) {
        for a in 0..3 {
            self.used[a] |= o.used[a];
            let mut m = o.used[a];
            while m != 0 {
                let k = m.trailing_zeros() as usize & BIN_MASK;
                let ob = &o.bins[a][k];
                let b = &mut self.bins[a][k];
                b.grow(ob);
                b.add_count(ob.count());
                m &= m - 1;
            }
        }
    }

    /// Primitives in bins below `split` on `axis`.
    fn count_below(&self, axis: usize, split: usize) -> usize {
        self.bins[axis][..split.min(BIN_CAP)]
            .iter()
            .map(|b| b.count() as usize)
            .sum()
    }

    /// Sweeps the bins for the lowest `A_L·N_L + A_R·N_R`; ties go to the lowest axis, then the
    /// lowest split position. `None` when no axis has a split with both sides non-empty.
    ///
    /// Positions that only move an empty bin from one side to the other give the same split,
    /// so only the lowest of each such run is evaluated: the position just after each
    /// non-empty bin (`split` = that bin + 1).
    fn choose_split(&mut self, map: &BinMap) -> Option<Plan> {
        let mut best: Option<(f64, usize, usize)> = None;
        for axis in 0..3 {
            if !map.active[axis] {
                continue;
            }
            let used = self.used[axis];
            let bins = &self.bins[axis];
            // suffix_*[k] describe the non-empty bins from k on; the lowest non-empty bin
            // has no split before it.
            let first = used.trailing_zeros() as usize & BIN_MASK;
            let mut acc = BinBox::EMPTY;
            let mut cnt = 0u32;
            let mut m = used & !(1u64 << first);
            while m != 0 {
                // Highest first.
                let k = (63 - m.leading_zeros()) as usize & BIN_MASK;
                acc.grow(&bins[k]);
                cnt += bins[k].count();
                self.suffix_area[k] = acc.box3().area();
                self.suffix_count[k] = cnt;
                m &= !(1u64 << k);
            }
            let mut left = BinBox::EMPTY;
            let mut n_left = 0u32;
            let mut prev = first;
            let mut m = used & !(1u64 << prev);
            while m != 0 {
                let k = m.trailing_zeros() as usize & BIN_MASK;
                left.grow(&bins[prev]);
                n_left += bins[prev].count();
                let cost = left.box3().area() * n_left as f64
                    + self.suffix_area[k] * self.suffix_count[k] as f64;
                if best.is_none_or(|(c, _, _)| cost < c) {
                    best = Some((cost, axis, prev + 1));
                }
                prev = k;
                m &= m - 1;
            }
        }
        let (_, axis, split) = best?;
        let (mut left, mut right) = (BinBox::EMPTY, BinBox::EMPTY);
        let mut n_left = 0usize;
        let mut m = self.used[axis];
        while m != 0 {
            let k = m.trailing_zeros() as usize & BIN_MASK;
            let b = &self.bins[axis][k];
            if k < split {
                left.grow(b);
                n_left += b.count() as usize;
            } else {
                right.grow(b);
            }
            m &= m - 1;
        }
        Some(Plan::Binned {
            axis,
            split,
            n_left,
            left: left.box3(),
            right: right.box3(),
        })
    }
}

/// The chosen split of a node.
#[derive(Clone, Copy, Debug)]
enum Plan {
    /// Primitives whose bin on `axis` is below `split` go left.
    Binned {
        axis: usize,
        split: usize,
        n_left: usize,
        left: Box3,
        right: Box3,
    },
    /// All centroids coincide: halve the range.
    Median,
}

/// Stable partition of `src` into `left` (bin below `split` on `axis`, read from the
/// primitives' `tags`) and `right`, which must have exactly the right lengths. Returns the
/// centroid boxes of both sides.
fn partition_into(
    src: &[PrimRef],
    tags: &[[u8; 4]],
    left: &mut [PrimRef],
    right: &mut [PrimRef],
    axis: usize,
    split: usize,
) -> (CentroidBox, CentroidBox) {
    #[cfg(target_arch = "x86_64")]
    if let Some(r) = simd::partition(src, tags, left, right, axis, split) {
        return r;
    }
    let (mut cl, mut cr) = (CentroidBox::EMPTY, CentroidBox::EMPTY);
    let (mut li, mut ri) = (0usize, 0usize);
    for (r, t) in src.iter().zip(tags) {
        let c = r.centroid();
        if (t[axis] as usize) < split {
            left[li] = *r;
            li += 1;
            cl.grow(c);
        } else {
            right[ri] = *r;
            ri += 1;
            cr.grow(c);
        }
    }
    debug_assert!(li == left.len() && ri == right.len());
    (cl, cr)
}

/// The split when binning finds none (every centroid in one bin): the two halves in range
/// order, each with its own bounds and the parent's centroid box.
fn median_halves(
    refs: &[PrimRef],
    cbounds: CentroidBox,
    parallel: bool,
) -> (usize, (Box3, CentroidBox), (Box3, CentroidBox)) {
    let half = refs.len() / 2;
    let (bl, _) = ordered_bounds(&refs[..half], parallel);
    let (br, _) = ordered_bounds(&refs[half..], parallel);
    (half, (bl, cbounds), (br, cbounds))
}

/// Box and centroid box of `refs`; with `parallel`, over fixed chunks folded in chunk order
/// (so even the sign of a zero bound does not depend on the thread count).
fn ordered_bounds(refs: &[PrimRef], parallel: bool) -> (Box3, CentroidBox) {
    let serial = |rs: &[PrimRef]| {
        let mut b = Box3::EMPTY;
        let mut c = CentroidBox::EMPTY;
        for r in rs {
            b.grow_ref(r);
            c.grow(r.centroid());
        }
        (b, c)
    };
    if !parallel || refs.len() < PAR_NODE_MIN {
        return serial(refs);
    }
    let parts: Vec<(Box3, CentroidBox)> = refs.par_chunks(CHUNK).map(serial).collect();
    parts
        .iter()
        .fold((Box3::EMPTY, CentroidBox::EMPTY), |(b, c), (pb, pc)| {
            (b.union(pb), c.union(pc))
        })
}

/// The reference of every box into `refs` (as long as `aabbs`), with what
/// [`ordered_bounds`]`(refs, true)` would return and whether every box is finite and valid.
fn prim_refs(aabbs: &[Aabb], refs: &mut [PrimRef]) -> (Box3, CentroidBox, bool) {
    let chunk = |base: usize, bs: &[Aabb], rs: &mut [PrimRef]| {
        let mut b = Box3::EMPTY;
        let mut c = CentroidBox::EMPTY;
        let mut ok = true;
        for (i, (a, r)) in bs.iter().zip(rs.iter_mut()).enumerate() {
            ok &= a.is_finite() && a.is_valid();
            *r = PrimRef::new(a, (base + i) as u32);
            b.grow_ref(r);
            c.grow(r.centroid());
        }
        (b, c, ok)
    };
    if refs.len() < PAR_NODE_MIN {
        return chunk(0, aabbs, refs);
    }
    let parts: Vec<(Box3, CentroidBox, bool)> = aabbs
        .par_chunks(CHUNK)
        .zip(refs.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(k, (bs, rs))| chunk(k * CHUNK, bs, rs))
        .collect();
    parts.iter().fold(
        (Box3::EMPTY, CentroidBox::EMPTY, true),
        |(b, c, ok), (pb, pc, pok)| (b.union(pb), c.union(pc), ok && *pok),
    )
}

/// The slices one subtree owns: its primitive range in both ping-pong buffers (current data
/// in `src`), its `2n − 1` nodes and its `n` output slots.
struct Ctx<'a> {
    src: &'a mut [PrimRef],
    dst: &'a mut [PrimRef],
    nodes: &'a mut [Node],
    out: &'a mut [u32],
    /// Each position's three bins, written by binning, read by the partition after it.
    tags: &'a mut [[u8; 4]],
    prim_base: u32,
    node_base: u32,
}

/// What a node knows before it is split: the exact box of its primitives, their centroid box
/// and its depth.
#[derive(Clone, Copy, Debug)]
struct Task {
    bounds: Box3,
    cbounds: CentroidBox,
    depth: u32,
}

/// Builds the subtree of `ctx` in parallel; returns its deepest leaf depth and the nodes it
/// used (`2n − 1` without a leaf rule; the first ones of each serial subtree's range else).
fn build_parallel(
    ctx: Ctx<'_>,
    task: Task,
    nb: usize,
    rule: Option<LeafRule>,
    joins: u32,
) -> (u32, usize) {
    let n = ctx.src.len();
    if n < PAR_SUBTREE_MIN
        || joins >= MAX_JOIN_DEPTH
        || rule.is_some_and(|r| n <= r.max_leaf as usize)
    {
        return build_serial(ctx, task, nb, rule);
    }
    let map = BinMap::new(&task.cbounds, nb);
    let big = n >= PAR_NODE_MIN;

    // Plan the split; for big nodes keep the per-chunk bins to place the partition's pieces.
    let mut chunk_bins: Vec<Box<Bins>> = Vec::new();
    let plan = if !map.any_active() {
        Plan::Median
    } else if big {
        chunk_bins = ctx
            .src
            .par_chunks(CHUNK)
            .zip(ctx.tags.par_chunks_mut(CHUNK))
            .map(|(rs, ts)| {
                let mut b = Bins::new(nb);
                b.fill(rs, ts, &map);
                b
            })
            .collect();
        let mut total = Bins::new(nb);
        for cb in &chunk_bins {
            total.merge(cb);
        }
        total.choose_split(&map).unwrap_or(Plan::Median)
    } else {
        let mut b = Bins::new(nb);
        b.fill(ctx.src, ctx.tags, &map);
        b.choose_split(&map).unwrap_or(Plan::Median)
    };

    let Ctx {
        src,
        dst,
        nodes,
        out,
        tags,
        prim_base,
        node_base,
    } = ctx;
    let (n_left, lt, rt, swap) = match plan {
        Plan::Binned {
            axis,
            split,
            n_left,
            left,
            right,
        } => {
            let (cl, cr) = if big {
                parallel_partition(src, tags, dst, &chunk_bins, axis, split, n_left)
            } else {
                let (dl, dr) = dst.split_at_mut(n_left);
                partition_into(src, tags, dl, dr, axis, split)
            };
            (n_left, (left, cl), (right, cr), true)
        }
        Plan::Median => {
            let (half, l, r) = median_halves(src, task.cbounds, true);
            (half, l, r, false)
        }
    };

    let left_nodes = 2 * n_left - 1;
    let (me, rest) = nodes
        .split_first_mut()
        .expect("a subtree owns at least one node");
    *me = Node::inner(
        task.bounds.aabb(),
        node_base + 1,
        node_base + 1 + left_nodes as u32,
    );
    let (nodes_l, nodes_r) = rest.split_at_mut(left_nodes);
    let (out_l, out_r) = out.split_at_mut(n_left);
    let (tags_l, tags_r) = tags.split_at_mut(n_left);
    let (src_l, src_r) = src.split_at_mut(n_left);
    let (dst_l, dst_r) = dst.split_at_mut(n_left);
    // After a binned partition the data lives in `dst`: the buffers trade roles.
    let ((cur_l, spare_l), (cur_r, spare_r)) = if swap {
        ((dst_l, src_l), (dst_r, src_r))
    } else {
        ((src_l, dst_l), (src_r, dst_r))
    };
    let left_ctx = Ctx {
        src: cur_l,
        dst: spare_l,
        nodes: nodes_l,
        out: out_l,
        tags: tags_l,
        prim_base,
        node_base: node_base + 1,
    };
    let right_ctx = Ctx {
        src: cur_r,
        dst: spare_r,
        nodes: nodes_r,
        out: out_r,
        tags: tags_r,
        prim_base: prim_base + n_left as u32,
        node_base: node_base + 1 + left_nodes as u32,
    };
    let depth = task.depth + 1;
    let ((dl, ul), (dr, ur)) = rayon::join(
        || {
            build_parallel(
                left_ctx,
                Task {
                    bounds: lt.0,
                    cbounds: lt.1,
                    depth,
                },
                nb,
                rule,
                joins + 1,
            )
        },
        || {
            build_parallel(
                right_ctx,
                Task {
                    bounds: rt.0,
                    cbounds: rt.1,
                    depth,
                },
                nb,
                rule,
                joins + 1,
            )
        },
    );
    (dl.max(dr), 1 + ul + ur)
}

/// Stable parallel partition of `src` into `dst` over the chunks the bins were taken on: each
/// chunk's left count comes from its own bins, so every chunk knows where its pieces go.
fn parallel_partition(
    src: &[PrimRef],
    tags: &[[u8; 4]],
    dst: &mut [PrimRef],
    chunk_bins: &[Box<Bins>],
    axis: usize,
    split: usize,
    n_left: usize,
) -> (CentroidBox, CentroidBox) {
    let (mut lrest, mut rrest) = dst.split_at_mut(n_left);
    let mut pieces: Vec<(&mut [PrimRef], &mut [PrimRef])> = Vec::with_capacity(chunk_bins.len());
    for (chunk, bins) in src.chunks(CHUNK).zip(chunk_bins) {
        let l = bins.count_below(axis, split);
        let (pl, tl) = std::mem::take(&mut lrest).split_at_mut(l);
        let (pr, tr) = std::mem::take(&mut rrest).split_at_mut(chunk.len() - l);
        lrest = tl;
        rrest = tr;
        pieces.push((pl, pr));
    }
    debug_assert!(lrest.is_empty() && rrest.is_empty());
    let parts: Vec<(CentroidBox, CentroidBox)> = src
        .par_chunks(CHUNK)
        .zip(tags.par_chunks(CHUNK))
        .zip(pieces.into_par_iter())
        .map(|((chunk, ts), (pl, pr))| partition_into(chunk, ts, pl, pr, axis, split))
        .collect();
    parts.iter().fold(
        (CentroidBox::EMPTY, CentroidBox::EMPTY),
        |(l, r), (pl, pr)| (l.union(pl), r.union(pr)),
    )
}

/// A node waiting on the serial work stack; offsets are local to the subtree.
#[derive(Clone, Copy, Debug)]
struct SerialTask {
    lo: usize,
    hi: usize,
    /// Local index of the parent when this is its right child (patched once this node gets
    /// its index), `usize::MAX` otherwise (a left child sits right after its parent).
    right_of: usize,
    /// The node's primitives are in the spare buffer (`ctx.dst`) rather than `ctx.src`.
    in_spare: bool,
    task: Task,
}

/// Builds the subtree of `ctx` on one thread with an explicit work stack; returns its deepest
/// leaf depth and the nodes it used. Nodes get their indices in depth-first order as they are
/// taken from the stack (left child right after its parent), so without a leaf rule node `i`
/// with `n_left` primitives on its left has its right child at `i + 2·n_left`, and with one the
/// used nodes are the first of the range.
fn build_serial(ctx: Ctx<'_>, root: Task, nb: usize, rule: Option<LeafRule>) -> (u32, usize) {
    let Ctx {
        src: buf_a,
        dst: buf_b,
        nodes,
        out,
        tags,
        prim_base,
        node_base,
    } = ctx;
    let mut bins = Bins::new(nb);
    let mut stack = vec![SerialTask {
        lo: 0,
        hi: buf_a.len(),
        right_of: usize::MAX,
        in_spare: false,
        task: root,
    }];
    let mut max_depth = 0u32;
    let mut next = 0usize;
    let leaf = |r: &PrimRef, slot: usize| Node::leaf(r.aabb(), prim_base + slot as u32, 1);
    let max_leaf = rule.map_or(1, |r| r.max_leaf as usize);

    while let Some(st) = stack.pop() {
        let SerialTask {
            lo,
            hi,
            right_of,
            in_spare,
            task,
        } = st;
        let node = next;
        next += 1;
        if right_of != usize::MAX {
            let p = nodes[right_of];
            nodes[right_of] = Node::inner(p.bounds, p.left(), node_base + node as u32);
        }
        let n = hi - lo;
        let (cur, spare): (&mut [PrimRef], &mut [PrimRef]) = if in_spare {
            (&mut buf_b[lo..hi], &mut buf_a[lo..hi])
        } else {
            (&mut buf_a[lo..hi], &mut buf_b[lo..hi])
        };
        // A leaf of all `n` primitives, in their current order.
        let mut as_leaf = |cur: &[PrimRef], nodes: &mut [Node]| {
            nodes[node] = Node::leaf(task.bounds.aabb(), prim_base + lo as u32, n as u32);
            for (o, r) in out[lo..hi].iter_mut().zip(cur) {
                *o = r.id();
            }
            max_depth = max_depth.max(task.depth);
        };
        if n == 1 {
            nodes[node] = leaf(&cur[0], lo);
            out[lo] = cur[0].id();
            max_depth = max_depth.max(task.depth);
            continue;
        }
        if n == 2 {
            if let Some(r) = rule.filter(|_| max_leaf >= 2) {
                let (a0, a1) = (cur[0].area(), cur[1].area());
                if r.leaf(2, task.bounds.area(), 1, a0, a1) {
                    as_leaf(cur, nodes);
                    continue;
                }
            }
            // Any split of two primitives gives the same tree: two leaves in range order.
            let g = node_base + node as u32;
            nodes[node] = Node::inner(task.bounds.aabb(), g + 1, g + 2);
            nodes[node + 1] = leaf(&cur[0], lo);
            nodes[node + 2] = leaf(&cur[1], lo + 1);
            next += 2;
            out[lo] = cur[0].id();
            out[lo + 1] = cur[1].id();
            max_depth = max_depth.max(task.depth + 1);
            continue;
        }

        let map = BinMap::new(&task.cbounds, nb);
        let plan = if map.any_active() {
            bins.fill(cur, &mut tags[lo..hi], &map);
            let plan = bins.choose_split(&map).unwrap_or(Plan::Median);
            bins.clear_used();
            plan
        } else {
            Plan::Median
        };
        if let Some(r) = rule.filter(|_| n <= max_leaf) {
            let a = task.bounds.area();
            let leafy = match plan {
                Plan::Binned {
                    n_left,
                    left,
                    right,
                    ..
                } => r.leaf(n, a, n_left, left.area(), right.area()),
                // Coincident centroids: halving rarely separates anything.
                Plan::Median => {
                    let half = n / 2;
                    let (bl, _) = ordered_bounds(&cur[..half], false);
                    let (br, _) = ordered_bounds(&cur[half..], false);
                    r.leaf(n, a, half, bl.area(), br.area())
                }
            };
            if leafy {
                as_leaf(cur, nodes);
                continue;
            }
        }
        let (n_left, lt, rt, child_in_spare) = match plan {
            Plan::Binned {
                axis,
                split,
                n_left,
                left,
                right,
            } => {
                let (dl, dr) = spare.split_at_mut(n_left);
                let (cl, cr) = partition_into(cur, &tags[lo..hi], dl, dr, axis, split);
                (n_left, (left, cl), (right, cr), !in_spare)
            }
            Plan::Median => {
                let (half, l, r) = median_halves(cur, task.cbounds, false);
                (half, l, r, in_spare)
            }
        };
        // The right child's index is patched in when it is taken from the stack.
        nodes[node] = Node::inner(task.bounds.aabb(), node_base + node as u32 + 1, 0);
        let depth = task.depth + 1;
        stack.push(SerialTask {
            lo: lo + n_left,
            hi,
            right_of: node,
            in_spare: child_in_spare,
            task: Task {
                bounds: rt.0,
                cbounds: rt.1,
                depth,
            },
        });
        stack.push(SerialTask {
            lo,
            hi: lo + n_left,
            right_of: usize::MAX,
            in_spare: child_in_spare,
            task: Task {
                bounds: lt.0,
                cbounds: lt.1,
                depth,
            },
        });
    }
    (max_depth, next)
}

/// The AVX2 kernels of binning and partitioning: the `f64` centroid and bin arithmetic of the
/// three axes in the lanes of one register, operation for operation the scalar
/// [`PrimRef::centroid`] and [`BinMap::bin`] (the same IEEE additions, multiplications,
/// minimum and truncation per lane), so every bin and centroid box equals the scalar one.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod simd {
    use core::arch::x86_64::*;

    use super::{BinBox, BinMap, Bins, Box3, CentroidBox, PrimRef, BIN_CAP, BIN_MASK};

    /// [`Box3::area`]: `2 · ((dx·dy + dy·dz) + dz·dx)` with `d = max(hi − lo, 0)` in `f64`,
    /// the operations of `Aabb::area_f64` in the same order (SSE2, part of x86-64).
    #[inline(always)]
    pub fn area(b: &Box3) -> f64 {
        // SAFETY: SSE2 is part of the x86-64 baseline; the loads read the two `Vec3A` of `b`
        // (16 bytes each, the fourth lane unused and dropped by the conversion of lanes 0-1
        // and 2).
        unsafe {
            let lo = _mm_loadu_ps(&b.min as *const _ as *const f32);
            let hi = _mm_loadu_ps(&b.max as *const _ as *const f32);
            // Lanes x, y as f64 and lane z as f64.
            let lxy = _mm_cvtps_pd(lo);
            let hxy = _mm_cvtps_pd(hi);
            let lz = _mm_cvtps_pd(_mm_movehl_ps(lo, lo));
            let hz = _mm_cvtps_pd(_mm_movehl_ps(hi, hi));
            let zero = _mm_setzero_pd();
            let dxy = _mm_max_pd(_mm_sub_pd(hxy, lxy), zero);
            let dz = _mm_max_sd(_mm_sub_sd(hz, lz), zero);
            let dx = _mm_cvtsd_f64(dxy);
            let dy = _mm_cvtsd_f64(_mm_unpackhi_pd(dxy, dxy));
            let dz = _mm_cvtsd_f64(dz);
            2.0 * (dx * dy + dy * dz + dz * dx)
        }
    }

    /// True when the SIMD kernels run: the CPU has AVX2 (checked once, then cached by the
    /// standard library) and [`super::force_scalar`] has not switched them off.
    #[inline]
    pub fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx2")
            && !super::SCALAR_ONLY.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// [`super::Bins::fill`] by AVX2 (bins and tags of the primitives in one pass); false
    /// (nothing written) without it.
    pub fn fill(bins: &mut Bins, refs: &[PrimRef], tags: &mut [[u8; 4]], map: &BinMap) -> bool {
        if !available() {
            return false;
        }
        // SAFETY: AVX2 is present (checked just above).
        unsafe { fill_avx2(bins, refs, tags, map) };
        true
    }

    /// The partition by AVX2; `None` (nothing written) without it.
    pub fn partition(
        src: &[PrimRef],
        tags: &[[u8; 4]],
        left: &mut [PrimRef],
        right: &mut [PrimRef],
        axis: usize,
        split: usize,
    ) -> Option<(CentroidBox, CentroidBox)> {
        if !available() {
            return None;
        }
        // SAFETY: AVX2 is present (checked just above).
        Some(unsafe { partition_avx2(src, tags, left, right, axis, split) })
    }

    /// `(lo + hi) · 0.5` of the three axes (lane 3: 0), the exact centroid.
    ///
    /// # Safety
    /// AVX2 must be enabled in the caller.
    #[inline(always)]
    unsafe fn centroid(r: &PrimRef) -> __m256d {
        // SAFETY: AVX2 is enabled in the caller; the loads read the two 16-byte lanes of `r`.
        unsafe {
            let keep = _mm_castsi128_ps(_mm_setr_epi32(-1, -1, -1, 0));
            let lo = _mm_and_ps(_mm_loadu_ps(&r.lo as *const _ as *const f32), keep);
            let hi = _mm_and_ps(_mm_loadu_ps(&r.hi as *const _ as *const f32), keep);
            _mm256_mul_pd(
                _mm256_add_pd(_mm256_cvtps_pd(lo), _mm256_cvtps_pd(hi)),
                _mm256_set1_pd(0.5),
            )
        }
    }

    /// The fill merges runs of primitives with the same bins when the runs average at least
    /// this many primitives.
    const RUNS_FROM: usize = 4;

    /// Every primitive's three bins into `tags`, and the primitive into those bins.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    unsafe fn fill_avx2(bins: &mut Bins, refs: &[PrimRef], tags: &mut [[u8; 4]], map: &BinMap) {
        let origin = _mm256_setr_pd(map.origin[0], map.origin[1], map.origin[2], 0.0);
        let scale = _mm256_setr_pd(map.scale[0], map.scale[1], map.scale[2], 0.0);
        let top = _mm256_set1_pd((map.bins - 1) as f64);
        // Two passes: the tags first, then the bins. In one pass the bin addresses come at
        // the end of a long chain (centroid, scale, convert, pack), and a primitive in the
        // same bins as the one before (the rule in a coherent mesh) waits for its stores;
        // read back from the tags, the addresses are known early (dragon quality build
        // 5-10% faster, alternating in one process).
        let mut prev = u32::MAX;
        let mut changes = 0usize;
        for (r, t) in refs.iter().zip(tags.iter_mut()) {
            // SAFETY: AVX2 is enabled; `centroid` reads `r` only.
            let c = unsafe { centroid(r) };
            // `min(t, top)` with `t` first: `vminpd` returns its second operand when the
            // first is NaN, as `f64::min` returns the non-NaN one (t is never NaN here).
            let b = _mm256_min_pd(_mm256_mul_pd(_mm256_sub_pd(c, origin), scale), top);
            let i = _mm256_cvttpd_epi32(b);
            // Lane 3 is (0 − 0) · 0 = 0: the tag's fourth byte is 0.
            let packed = _mm_packus_epi16(_mm_packus_epi32(i, i), _mm_setzero_si128());
            let w = _mm_cvtsi128_si32(packed) as u32;
            changes += (w != prev) as usize;
            prev = w;
            *t = w.to_le_bytes();
        }
        // A bin is eight lanes (`BinBox`): one `min` grows its box, one add counts.
        let base = bins.bins.as_mut_ptr().cast::<BinBox>();
        let one = _mm256_setr_epi32(0, 0, 0, 1, 0, 0, 0, 0);
        let inf = _mm_set1_ps(f32::INFINITY);
        let sign = _mm_set1_ps(-0.0);
        // `BinBox::of(r)`: (lo, +inf, −hi, +inf).
        let of = |r: &PrimRef| -> __m256 {
            // SAFETY: AVX2 is enabled; the loads read the two 16-byte halves of `r`.
            unsafe {
                let lo = _mm_blend_ps::<0b1000>(_mm_loadu_ps(&r.lo as *const _ as *const f32), inf);
                let hi = _mm_loadu_ps(&r.hi as *const _ as *const f32);
                let nhi = _mm_blend_ps::<0b1000>(_mm_xor_ps(hi, sign), inf);
                _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(lo), nhi)
            }
        };
        let mut used = [0u64; 3];
        // Grow bin `(a, k)` by the eight lanes `p` (`p` second, as `BinBox::grow`) and add
        // `n` to its count.
        let mut add = |w: u32, p: __m256, n: __m256i| {
            for (a, u) in used.iter_mut().enumerate() {
                let k = (w >> (8 * a)) as usize & BIN_MASK;
                // SAFETY: `base` is the first of the 3 · BIN_CAP contiguous `BinBox`es of
                // `bins.bins` (32-byte aligned); `a < 3` and `k < BIN_CAP` (masked) keep the
                // offset in range; the aligned accesses read and write that one bin whole.
                unsafe {
                    let at = base.add(a * BIN_CAP + k).cast::<f32>();
                    let v = _mm256_min_ps(_mm256_load_ps(at), p);
                    let v = _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(v), n));
                    _mm256_store_ps(at, v);
                }
                *u |= 1u64 << k;
            }
        };
        if changes * RUNS_FROM > refs.len() {
            // Short runs: one primitive at a time (a branch per run would mispredict).
            for (r, t) in refs.iter().zip(tags.iter()) {
                add(u32::from_le_bytes(*t), of(r), one);
            }
        } else {
            // Runs of primitives with the same three bins (the rule in a coherent mesh, whose
            // order the stable partitions keep) are merged in registers and added to their
            // bins once, so consecutive primitives do not wait on each other's stores.
            let mut pairs = refs.iter().zip(tags.iter());
            if let Some((r, t)) = pairs.next() {
                let mut cur = u32::from_le_bytes(*t);
                let mut acc = of(r);
                let mut run = 1i32;
                for (r, t) in pairs {
                    let w = u32::from_le_bytes(*t);
                    let p = of(r);
                    if w == cur {
                        acc = _mm256_min_ps(acc, p);
                        run += 1;
                    } else {
                        add(cur, acc, _mm256_setr_epi32(0, 0, 0, run, 0, 0, 0, 0));
                        (cur, acc, run) = (w, p, 1);
                    }
                }
                add(cur, acc, _mm256_setr_epi32(0, 0, 0, run, 0, 0, 0, 0));
            }
        }
        bins.used = used;
    }

    /// The stable partition of `super::partition_into`, centroid boxes in `f64` lanes.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    unsafe fn partition_avx2(
        src: &[PrimRef],
        tags: &[[u8; 4]],
        left: &mut [PrimRef],
        right: &mut [PrimRef],
        axis: usize,
        split: usize,
    ) -> (CentroidBox, CentroidBox) {
        assert_eq!(src.len(), left.len() + right.len());
        assert_eq!(src.len(), tags.len());
        let inf = _mm256_set1_pd(f64::INFINITY);
        let ninf = _mm256_set1_pd(f64::NEG_INFINITY);
        let (mut lmin, mut lmax, mut rmin, mut rmax) = (inf, ninf, inf, ninf);
        let (mut li, mut ri) = (0usize, 0usize);
        for (r, t) in src.iter().zip(tags) {
            // SAFETY: AVX2 is enabled; `centroid` reads `r` only.
            let c = unsafe { centroid(r) };
            if (t[axis] as usize) < split {
                left[li] = *r;
                li += 1;
                lmin = _mm256_min_pd(c, lmin);
                lmax = _mm256_max_pd(c, lmax);
            } else {
                right[ri] = *r;
                ri += 1;
                rmin = _mm256_min_pd(c, rmin);
                rmax = _mm256_max_pd(c, rmax);
            }
        }
        let out = |v: __m256d| {
            let mut a = [0.0f64; 4];
            // SAFETY: AVX2 is enabled; the store writes the four lanes of `a`.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
            [a[0], a[1], a[2]]
        };
        (
            CentroidBox {
                min: out(lmin),
                max: out(lmax),
            },
            CentroidBox {
                min: out(rmin),
                max: out(rmax),
            },
        )
    }
}
