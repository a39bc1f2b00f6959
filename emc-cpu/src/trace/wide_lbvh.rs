//! The fast preset's builder: triangles → codes → radix sort → a `W`-wide BVH made straight
//! from the sorted codes, in the core's cache, leaf packets written as leaves are finalised and
//! every box computed once. No binary tree of the whole scene is stored.
//!
//! ```text
//!   1. partition  the LBVH radix tree's top (Karras 2012: a range splits at the highest bit in
//!                 which its first and last codes differ, found by binary search) down to
//!                 blocks of at most BLOCK primitives; topology only
//!   2. blocks     in code order, each in cache: gather its triangles, sweep its binary radix
//!                 tree left to right (boxes, SAH leaf decisions), open it into wide nodes
//!                 (inner children by largest area, then the leaves whose halves save most)
//!                 and write nodes and packets
//!   3. top        the SAH-optimal cover of the top tree by W-wide nodes (the DP of wide.rs),
//!                 the blocks' roots as fixed children; its root is node 0, the rest follow
//!                 the blocks' nodes
//! ```
//!
//! Packets come out in code order (leaf after leaf), nodes depth-first within each block.
#![deny(unsafe_code)]

use emc_core::Aabb;
use glam::{Vec3, Vec3A};

use crate::sort::RadixKey;
use crate::trace::traverse::{prefetch, prefetch_at};
use crate::trace::wide::{TriPacket, WideNodeN, EMPTY, LEAF, MAX_DEPTH, WIDTH};
use crate::trace::TraceError;

/// Ranges of at most this many primitives are built as one block, in the core's cache.
pub const BLOCK: u32 = 1024;
// The sweep indexes its fixed-size arrays under masks of `BLOCK` and `2 · BLOCK`.
const _: () = assert!(BLOCK.is_power_of_two());

/// How far ahead of the block's gather its index loads are prefetched (its corner loads half
/// as far): a one-thread warm fast build of stanford-dragon gathers in 5.6 ms at 128 against
/// 8.9 ms at 16 (the loop is short, so the misses need many iterations to overlap).
const GATHER_AHEAD: usize = 128;

/// Largest leaf: two triangle packets.
pub const LEAF_MAX: u32 = 2 * WIDTH as u32;

/// Cost of testing a wide node, per unit of its half area (as in the SAH collapse of
/// `wide.rs`).
const COST_NODE: f32 = 1.0;
/// Cost of testing one triangle packet, per unit of its leaf's half area.
const COST_PACKET: f32 = 1.0;
/// What keeping a subtree of at most [`LEAF_MAX`] primitives open (instead of one leaf) is
/// charged per unit of its area: such a subtree often ends as a wide node of its own.
const COST_SMALL_SPLIT: f32 = 0.5;
/// What one larger binary split is charged per unit of its area: a wide node of `W` children
/// stands for `W − 1` splits (`COST_NODE / 7` for eight children).
const COST_SPLIT: f32 = COST_NODE / 7.0;

/// Read-only inputs of the build.
#[derive(Debug)]
pub struct Inputs<'a, K> {
    /// Codes in sorted order.
    pub keys: &'a [K],
    /// `ids[p]`: the triangle at sorted position `p`.
    pub ids: &'a [u32],
    /// Mesh vertices.
    pub vertices: &'a [Vec3],
    /// Mesh triangles (validated: every index names a vertex).
    pub indices: &'a [[u32; 3]],
    /// Child box padding (see `WideBvh::from_bvh2`).
    pub pad: f32,
    /// Largest leaf, `1..=`[`LEAF_MAX`] (1: every primitive its own leaf).
    pub leaf_max: u32,
}

/// Output buffers of the build (appended to).
#[derive(Debug)]
pub struct Outputs<'a, const W: usize> {
    /// Wide nodes: the root, every block's nodes depth-first, then the top's other nodes.
    pub nodes: &'a mut Vec<WideNodeN<W>>,
    /// Triangle packets in leaf order.
    pub packets: &'a mut Vec<TriPacket>,
    /// Leaves written.
    pub leaves: usize,
    /// Scratch of the block builder.
    pub block: &'a mut BlockScratch,
}

/// One node of a block's binary radix tree (post-order: children before parents).
#[derive(Clone, Copy, Debug)]
struct BNode {
    /// Box (SIMD lanes: one `minps` / `maxps` per union).
    lo: Vec3A,
    hi: Vec3A,
    /// Children (binary node indices; unused for a primitive).
    left: u32,
    right: u32,
    /// First local position.
    first: u32,
    /// Number of primitives.
    count: u32,
    /// SAH cost of the subtree as the leaf decisions price it.
    cost: f32,
    /// The subtree's [`open_priority`] (which also says whether it is one leaf).
    prio: u32,
    /// The children's priorities (left, right): opening this node reads no child.
    kids_prio: [u32; 2],
}

const _: () = assert!(core::mem::size_of::<BNode>() == 64);

const NO_NODE: BNode = BNode {
    lo: Vec3A::INFINITY,
    hi: Vec3A::NEG_INFINITY,
    left: 0,
    right: 0,
    first: 0,
    count: 0,
    cost: 0.0,
    prio: 0,
    kids_prio: [0; 2],
};

/// Buffers of the block builder (kept between blocks and builds).
#[derive(Clone, Debug, Default)]
pub struct BlockScratch {
    /// The block's triangles in sorted order.
    tris: Vec<[Vec3A; 3]>,
    /// Binary nodes (`2 · BLOCK − 1` slots, written by index).
    nodes: Vec<BNode>,
}

/// A finished block: its root as a child of a wide node.
#[derive(Clone, Copy, Debug)]
struct Fixed {
    /// Child code (a leaf, or the block's first wide node).
    code: u32,
    /// Unpadded box.
    bx: Aabb,
    /// SAH cost of the block's wide subtree (node areas, leaf areas times packets).
    cost: f32,
    /// Wide levels below the block's root (0 for a leaf, 1 for a node of leaves).
    height: usize,
}

/// Flag of a reference to a block in the top tree (else: a top node).
const REF_FLAG: u32 = 1 << 31;

/// A node of the top tree (above the blocks), post-order: its children's references.
#[derive(Clone, Copy, Debug)]
struct TopNode {
    left: u32,
    right: u32,
}

impl<K: RadixKey> Inputs<'_, K> {
    /// Where `[b, e)` (at least two primitives) splits: the first position whose code has the
    /// highest bit set in which the first and last codes differ; the middle when they agree.
    #[inline(always)]
    fn split(&self, b: u32, e: u32) -> u32 {
        let x = self.keys[b as usize].widen() ^ self.keys[e as usize - 1].widen();
        if x == 0 {
            return b + (e - b) / 2;
        }
        let bit = 1u64 << (63 - x.leading_zeros());
        let (mut lo, mut hi) = (b + 1, e - 1);
        // Invariant: keys[lo - 1] has the bit clear, keys[hi] has it set.
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            // Both possible next probes fetched while this one's key arrives: in a large range
            // every probe misses the cache, and this overlaps one miss with the next.
            if hi - lo > 64 {
                prefetch(&self.keys[(lo + (mid - lo) / 2) as usize], 1);
                prefetch(&self.keys[(mid + 1 + (hi - mid - 1) / 2) as usize], 1);
            }
            if self.keys[mid as usize].widen() & bit != 0 {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        lo
    }

    /// Level of the split between sorted positions `p` and `p + 1`, over the index-augmented
    /// key (`K::BITS` key bits above 32 position bits):
    ///
    /// ```text
    ///   level(p) = 32 + (63 − clz64(k_p ⊕ k_{p+1}))   if the keys differ
    ///            = 31 − clz32(p ⊕ (p + 1))            if they are equal
    /// ```
    /// The radix tree is the Cartesian tree of these levels (two equal levels always have a
    /// higher one between them). Equal codes split at the highest position bit that changes,
    /// as Karras' tree does; [`Inputs::split`] above the blocks splits them in the middle.
    #[inline(always)]
    fn level_at(&self, p: u32) -> u32 {
        let x = self.keys[p as usize].widen() ^ self.keys[p as usize + 1].widen();
        if x != 0 {
            32 + (63 - x.leading_zeros())
        } else {
            31 - (p ^ (p + 1)).leading_zeros()
        }
    }
}

/// Ranges of more primitives than this have their two halves partitioned as parallel tasks
/// (when the pool has several threads): the binary searches of the top levels miss the cache
/// at nearly every step (san-miguel-pbrtv3: 12.6 ms on one thread).
pub const PARTITION_PAR_MIN: u32 = 1 << 17;

/// Step 1: split `[b, e)` down to blocks (appended to `blocks` in order), recording the top
/// nodes (post-order); returns the reference of `[b, e)`. The same lists at any thread count.
fn partition<K: RadixKey>(
    inp: &Inputs<'_, K>,
    b: u32,
    e: u32,
    blocks: &mut Vec<(u32, u32)>,
    top: &mut Vec<TopNode>,
) -> u32 {
    if e - b <= BLOCK {
        blocks.push((b, e));
        return REF_FLAG | (blocks.len() as u32 - 1);
    }
    let s = inp.split(b, e);
    let (left, right) = if e - b > PARTITION_PAR_MIN && rayon::current_num_threads() > 1 {
        // The right half into lists of its own, appended after the left half's: its
        // references move by the left lists' lengths (a block reference keeps its flag).
        let (mut rb, mut rt) = (Vec::new(), Vec::new());
        let (left, right) = rayon::join(
            || partition(inp, b, s, blocks, top),
            || partition(inp, s, e, &mut rb, &mut rt),
        );
        let (bo, to) = (blocks.len() as u32, top.len() as u32);
        let moved = |r: u32| if r & REF_FLAG != 0 { r + bo } else { r + to };
        blocks.extend_from_slice(&rb);
        top.extend(rt.iter().map(|t| TopNode {
            left: moved(t.left),
            right: moved(t.right),
        }));
        (left, moved(right))
    } else {
        let left = partition(inp, b, s, blocks, top);
        (left, partition(inp, s, e, blocks, top))
    };
    top.push(TopNode { left, right });
    top.len() as u32 - 1
}

/// The per-block builders (step 2), written once and compiled twice: for the x86-64 baseline
/// and, chosen at run time ([`tree_isa`]), for x86-64-v3 (AVX2, BMI1/2, LZCNT, FMA: VEX
/// encodings of the same SSE arithmetic, single-instruction bit scans for the radix levels and
/// lane masks). No float operation changes (Rust never fuses a multiply and an add), so both
/// copies build the same tree, bit for bit (tested); the v3 copy's tree phase was 6% faster
/// (pbrt-crown, one thread).
macro_rules! block_builders {
    ($(#[$isa:meta])* $blocks:ident, $build_block:ident, $emit_wide:ident) => {
        /// Build the blocks `ranges` in turn into `out`, each block's [`Fixed`] pushed to
        /// `sink`.
        $(#[$isa])*
        fn $blocks<K: RadixKey, const W: usize>(
            inp: &Inputs<'_, K>,
            ranges: &[(u32, u32)],
            out: &mut Outputs<'_, W>,
            sink: &mut Vec<Fixed>,
        ) {
            for &(b, e) in ranges {
                sink.push($build_block(inp, b, e, out));
            }
            stream_fence();
        }

        /// Step 2: build block `[b, e)` (1 ≤ e − b ≤ [`BLOCK`]): gather its triangles, sweep its
        /// binary radix tree with boxes and leaf decisions, then write its wide nodes and packets.
        $(#[$isa])*
                fn $build_block<K: RadixKey, const W: usize>(
            inp: &Inputs<'_, K>,
            b: u32,
            e: u32,
            out: &mut Outputs<'_, W>,
        ) -> Fixed {
            let m = (e - b) as usize;
            let s = &mut *out.block;
            if s.nodes.len() < 2 * BLOCK as usize {
                s.nodes.resize(2 * BLOCK as usize, NO_NODE);
                s.tris.resize(BLOCK as usize, [Vec3A::ZERO; 3]);
            }
            let ids = &inp.ids[b as usize..e as usize];
            // The gather is the one scattered read of the build: the triangle `GATHER_AHEAD`
            // positions on has its index fetched, and the one half as far on its corners (their
            // indices are in cache by then), so the misses overlap instead of stalling each load.
            let all = inp.ids;
            for (k, (t, &id)) in s.tris[..m].iter_mut().zip(ids).enumerate() {
                let p = b as usize + k;
                if let Some(&f) = all.get(p + GATHER_AHEAD) {
                    prefetch_at(inp.indices, f as usize);
                }
                if let Some(&f) = all.get(p + GATHER_AHEAD / 2) {
                    if let Some(c) = inp.indices.get(f as usize) {
                        for &v in c {
                            prefetch_at(inp.vertices, v as usize);
                        }
                    }
                }
                *t = inp.indices[id as usize].map(|i| Vec3A::from(inp.vertices[i as usize]));
            }
            // The sweep: left to right, every primitive a leaf node; an open subtree on the stack
            // is merged with the current one while its right boundary's level is below the
            // current one's. The stack's levels strictly decrease upwards (two equal levels
            // have a higher one between them, which would have popped the first), so it holds
            // at most one entry per level (0..=95, and the last primitive's `u32::MAX − 1`)
            // above a sentinel of level `u32::MAX` that nothing pops. Fixed-size arrays
            // indexed under a mask: no bounds checks, and no lengths reloaded from the scratch
            // after each store.
            const STACK: usize = 128;
            const NODES: usize = 2 * BLOCK as usize;
            const _: () = assert!(STACK.is_power_of_two() && STACK > 97);
            let mut stack = [(0u32, u32::MAX); STACK];
            let mut sp = 0usize;
            let nodes: &mut [BNode; NODES] = (&mut s.nodes[..NODES]).try_into().expect("sized");
            let tris: &[[Vec3A; 3]; BLOCK as usize] =
                (&s.tris[..BLOCK as usize]).try_into().expect("sized");
            let mut next = 0usize;
            for p in 0..m {
                let t = &tris[p & (BLOCK as usize - 1)];
                let (lo, hi) = (t[0].min(t[1]).min(t[2]), t[0].max(t[1]).max(t[2]));
                let area = half_area_a(lo, hi);
                let mut cur = next as u32;
                // The current subtree stays in registers: merging re-reads only the stack's
                // nodes (written long before), never the one just stored.
                let mut node = BNode {
                    lo,
                    hi,
                    left: 0,
                    right: 0,
                    first: p as u32,
                    count: 1,
                    cost: COST_PACKET * area,
                    prio: 0,
                    kids_prio: [0; 2],
                };
                nodes[next & (NODES - 1)] = node;
                next += 1;
                let lvl = if p + 1 < m {
                    inp.level_at(b + p as u32)
                } else {
                    u32::MAX - 1
                };
                loop {
                    let (top, tl) = stack[sp & (STACK - 1)];
                    if tl >= lvl {
                        break;
                    }
                    sp -= 1;
                    node = merge(&nodes[top as usize & (NODES - 1)], &node, top, cur, inp.leaf_max);
                    nodes[next & (NODES - 1)] = node;
                    cur = next as u32;
                    next += 1;
                }
                sp += 1;
                debug_assert!(sp < STACK);
                stack[sp & (STACK - 1)] = (cur, lvl);
            }
            let root = stack[1].0;
            let rn = s.nodes[root as usize];
            let bx = rn.aabb();
            if rn.is_leaf() {
                let (code, cost) = emit_leaf(out, ids, rn.first, rn.count, rn.area());
                return Fixed {
                    code,
                    bx,
                    cost,
                    height: 0,
                };
            }
            // A block has fewer wide nodes than primitives (each has two children or more).
            if out.nodes.capacity() - out.nodes.len() < m {
                // Growing copies the nodes stored so far: order them first.
                stream_fence();
                out.nodes.reserve(m);
            }
            let mut next = out.nodes.len();
            let (code, cost, height) = $emit_wide(inp, out, ids, root, &mut next);
            // SAFETY: `emit_wide` stored a whole node into each slot it took, `len..next`,
            // all within the capacity reserved above.
            #[allow(unsafe_code)]
            unsafe {
                out.nodes.set_len(next)
            };
            Fixed {
                code,
                bx,
                cost,
                height,
            }
        }

        /// Write the wide node made of the block's inner binary node `bn` and its subtree: its
        /// children come from opening the largest inner child until there are `W` (an inner
        /// child left over would cost a wide node of its own), then, with lanes to spare, the
        /// leaves whose two halves cost least against them. Returns its code (node index), SAH
        /// cost and height. The node takes slot `*next` of `out.nodes` (its spare capacity: the
        /// caller reserved room and sets the length once the block is written), its subtree the
        /// slots after.
        $(#[$isa])*
                fn $emit_wide<K: RadixKey, const W: usize>(
            inp: &Inputs<'_, K>,
            out: &mut Outputs<'_, W>,
            ids: &[u32],
            bn: u32,
            next: &mut usize,
        ) -> (u32, f32, usize) {
            let me = *next;
            *next += 1;
            let mut wide = WideNodeN::<W>::empty();
            let nodes = &out.block.nodes;
            let root = &nodes[bn as usize];
            let mut kids = [0u32; W];
            // Each child's opening priority, kept beside it so the choice reads no node (and
            // an opened node holds its children's).
            let mut prio = [0u32; W];
            kids[0] = root.left;
            kids[1] = root.right;
            [prio[0], prio[1]] = root.kids_prio;
            let mut n = 2;
            while n < W {
                // The first of the highest priority (selects, not branches: the keys are
                // integers).
                let mut best = 0;
                let mut bk = prio[0];
                #[allow(clippy::needless_range_loop)]
                for i in 1..n {
                    let k = prio[i];
                    best = if k > bk { i } else { best };
                    bk = bk.max(k);
                }
                if bk == 0 {
                    break;
                }
                let k = &nodes[kids[best] as usize];
                let (l, r) = (k.left, k.right);
                let kp = k.kids_prio;
                // Shift the children after `best` one lane on (a loop of at most W − 2
                // moves; `copy_within` would call `memmove` for each opening).
                let mut i = n;
                while i > best + 1 {
                    kids[i] = kids[i - 1];
                    prio[i] = prio[i - 1];
                    i -= 1;
                }
                kids[best] = l;
                kids[best + 1] = r;
                [prio[best], prio[best + 1]] = kp;
                n += 1;
            }
            let mut cost = COST_NODE * root.area();
            let mut height = 1;
            for (lane, &k) in kids[..n].iter().enumerate() {
                let kn = out.block.nodes[k as usize];
                let code = if kn.is_leaf() {
                    let (code, c) = emit_leaf(out, ids, kn.first, kn.count, kn.area());
                    cost += c;
                    code
                } else {
                    let (code, c, h) = $emit_wide(inp, out, ids, k, next);
                    cost += c;
                    height = height.max(h + 1);
                    code
                };
                wide.set(lane, &kn.aabb(), code, inp.pad);
            }
            assert!(me < out.nodes.capacity());
            // SAFETY: slot `me` is within the capacity (checked), past the length, and taken
            // by this node alone.
            #[allow(unsafe_code)]
            unsafe {
                store_streaming(out.nodes.as_mut_ptr().add(me), &wide)
            };
            (me as u32, cost, height)
        }
    };
}

block_builders!(blocks_base, build_block_base, emit_wide_base);
#[cfg(target_arch = "x86_64")]
block_builders!(
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,fma")]
    blocks_v3,
    build_block_v3,
    emit_wide_v3
);

/// Set by [`force_baseline_tree`].
static BASELINE_ONLY: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Make later fast builds run the per-block builders' baseline copy (`true`) or the one
/// [`tree_isa`] picks (`false`, the default). Both build the same tree; the switch exists so
/// tests can hold one against the other on the same machine.
#[doc(hidden)]
pub fn force_baseline_tree(on: bool) {
    BASELINE_ONLY.store(on, std::sync::atomic::Ordering::Relaxed);
}

/// Whether the CPU runs the x86-64-v3 copy of the per-block builders (checked once, then
/// cached by the standard library).
fn v3_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("lzcnt")
            && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Whether builds run the x86-64-v3 copy of the per-block builders now.
#[cfg(target_arch = "x86_64")]
fn use_v3() -> bool {
    !BASELINE_ONLY.load(std::sync::atomic::Ordering::Relaxed) && v3_available()
}

/// Which copy of the fast build's per-block builders this CPU runs, and why.
pub fn tree_isa() -> (&'static str, &'static str) {
    if BASELINE_ONLY.load(std::sync::atomic::Ordering::Relaxed) {
        ("baseline", "forced")
    } else if v3_available() {
        (
            "x86-64-v3",
            "AVX2, BMI1, BMI2, LZCNT and FMA detected at run time",
        )
    } else {
        (
            "baseline",
            "the CPU lacks one of AVX2, BMI1, BMI2, LZCNT, FMA",
        )
    }
}

/// Build the blocks `ranges` in turn into `out` with the copy [`tree_isa`] picks.
fn build_blocks<K: RadixKey, const W: usize>(
    inp: &Inputs<'_, K>,
    ranges: &[(u32, u32)],
    out: &mut Outputs<'_, W>,
    sink: &mut Vec<Fixed>,
) {
    #[cfg(target_arch = "x86_64")]
    if use_v3() {
        // SAFETY: the CPU has every feature `blocks_v3` is compiled for (`use_v3` checked).
        #[allow(unsafe_code)]
        unsafe {
            blocks_v3(inp, ranges, out, sink)
        };
        return;
    }
    blocks_base(inp, ranges, out, sink);
}

/// The inner node over subtrees `a` (node `l`) and `c` (node `r`): its box and leaf decision
/// (a leaf of at most `leaf_max` primitives).
#[inline(always)]
fn merge(a: &BNode, c: &BNode, l: u32, r: u32, leaf_max: u32) -> BNode {
    let (lo, hi) = (a.lo.min(c.lo), a.hi.max(c.hi));
    let area = half_area_a(lo, hi);
    let count = a.count + c.count;
    let (leaf, cost) = if count <= leaf_max {
        let leaf_cost = COST_PACKET * area * count.div_ceil(WIDTH as u32) as f32;
        let split = COST_SMALL_SPLIT * area + a.cost + c.cost;
        (leaf_cost <= split, leaf_cost.min(split))
    } else {
        (false, COST_SPLIT * area + a.cost + c.cost)
    };
    BNode {
        lo,
        hi,
        left: l,
        right: r,
        first: a.first,
        count,
        cost,
        prio: open_priority(leaf, count, area, cost - a.cost - c.cost),
        kids_prio: [a.prio, c.prio],
    }
}

impl BNode {
    /// Whether the subtree is one leaf (inner subtrees have priority class 2).
    #[inline(always)]
    fn is_leaf(&self) -> bool {
        self.prio < PRIO_INNER
    }

    /// Half area of the box.
    #[inline(always)]
    fn area(&self) -> f32 {
        half_area_a(self.lo, self.hi)
    }

    /// The box as the wide nodes store it.
    #[inline(always)]
    fn aabb(&self) -> Aabb {
        Aabb::new(self.lo.into(), self.hi.into())
    }
}

/// Half the surface area of the box `[lo, hi]`.
#[inline(always)]
fn half_area_a(lo: Vec3A, hi: Vec3A) -> f32 {
    let e = hi - lo;
    (e * Vec3A::new(e.y, e.z, e.x)).element_sum()
}

/// Half the surface area of `b`.
#[inline(always)]
fn half_area(b: &Aabb) -> f32 {
    let e = b.max - b.min;
    e.x * e.y + e.y * e.z + e.z * e.x
}

/// Write the packets of the block's leaf at local positions `[first, first + count)` (half
/// area `area`; `ids`: the block's triangle ids); returns its child code and SAH cost.
#[inline(always)]
fn emit_leaf<const W: usize>(
    out: &mut Outputs<'_, W>,
    ids: &[u32],
    first: u32,
    count: u32,
    area: f32,
) -> (u32, f32) {
    let code = LEAF | out.packets.len() as u32;
    let (f, c) = (first as usize, count as usize);
    let tris = &out.block.tris[f..f + c];
    let ids = &ids[f..f + c];
    let k = c.div_ceil(WIDTH);
    for j in 0..k {
        let lo = j * WIDTH;
        let real = (c - lo).min(WIDTH);
        let lane = |l: usize| lo + l.min(real - 1);
        push_streaming(
            out.packets,
            TriPacket::from_lanes(
                core::array::from_fn(|l| &tris[lane(l)]),
                core::array::from_fn(|l| ids[lane(l)]),
                real as u32,
                j + 1 == k,
            ),
        );
    }
    out.leaves += 1;
    (code, COST_PACKET * area * k as f32)
}

/// Store `v` at `dst` by streaming (non-temporal) stores on x86-64: the build writes its nodes
/// and packets once and reads none of them back while it writes (only the parallel copy of
/// the back groups reads them, after a fence), so fetching their lines first (as a plain
/// store must) only doubles the traffic to memory. The stores are weakly ordered until
/// [`stream_fence`].
///
/// # Safety
/// `dst` must be valid for a write of a `T`, and nothing (this thread included) may read or
/// write `*dst` before the writer's next [`stream_fence`]; `T` must have no padding bytes (it
/// is read in 16-byte pieces).
#[inline(always)]
#[allow(unsafe_code)]
unsafe fn store_streaming<T: Copy>(dst: *mut T, v: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use core::arch::x86_64::{__m128, _mm_loadu_ps, _mm_stream_ps};
        const {
            assert!(
                core::mem::size_of::<T>().is_multiple_of(16) && core::mem::align_of::<T>() >= 16
            )
        };
        let (d, s) = (dst.cast::<f32>(), (v as *const T).cast::<f32>());
        for i in 0..core::mem::size_of::<T>() / 16 {
            // SAFETY: 16-byte pieces of `*v` and of `*dst` (valid by the caller's contract, and
            // 16-byte aligned by the assertion above); SSE is in the x86-64 baseline.
            unsafe {
                let x: __m128 = _mm_loadu_ps(s.add(4 * i));
                _mm_stream_ps(d.add(4 * i), x);
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    // SAFETY: the caller's contract.
    unsafe {
        dst.write(*v)
    };
}

/// Order every streaming store of this thread before its later loads and stores (so that it
/// may read them, or another thread that synchronises with it afterwards sees them).
#[inline(always)]
fn stream_fence() {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE is in the x86-64 baseline; a fence has no other effect.
    #[allow(unsafe_code)]
    unsafe {
        core::arch::x86_64::_mm_sfence()
    };
}

/// Append `p` to `packets` by [`store_streaming`].
#[inline(always)]
fn push_streaming(packets: &mut Vec<TriPacket>, p: TriPacket) {
    let n = packets.len();
    if n == packets.capacity() {
        // Growing copies the packets stored so far: order them first.
        stream_fence();
        packets.reserve(BLOCK as usize);
    }
    // SAFETY: slot `n` is within the capacity (reserved above) and past the length; the packet
    // is whole once stored, so the length may cover it.
    #[allow(unsafe_code)]
    unsafe {
        store_streaming(packets.as_mut_ptr().add(n), &p);
        packets.set_len(n + 1);
    }
}

/// The lowest priority of an inner subtree (class 2).
const PRIO_INNER: u32 = 2 << 30;

/// Which child of a wide node under construction is opened next, for a subtree of `count`
/// primitives with half area `area`, one leaf or not, whose opening saves `gain` (its cost
/// less its two children's): every inner child before any leaf, the largest area first; then
/// a leaf of several primitives whose two halves cost least against it (positive gain only);
/// never a single primitive (key 0). Larger is opened first.
///
/// ```text
///   key bits  31 30 | 29 … 0
///             class | the area (class 2) or gain (class 1): f32 bits 30 … 1
/// ```
///
/// Areas and positive gains are non-negative floats, whose bit patterns order as their values;
/// the sign bit is zero and the lowest mantissa bit is dropped (values one ulp apart tie, and
/// the first child wins). The one exception, a NaN area (an infinite extent times a zero one,
/// near the largest floats) with its sign bit set, spills into bit 30 of an inner child's key:
/// it stays an inner key, above the others, as it was above them with the full bits.
#[inline(always)]
fn open_priority(leaf: bool, count: u32, area: f32, gain: f32) -> u32 {
    // Branch-free (which class a child falls in is data, and mispredicted): masks and
    // selects only.
    let inner = !leaf;
    let split = leaf & (count > 1) & (gain > 0.0);
    let class = 2 * u32::from(inner) + u32::from(split);
    let v = if inner { area } else { gain };
    let key = (class << 30) | (v.to_bits() >> 1);
    key & 0u32.wrapping_sub(u32::from(class != 0))
}

/// The SAH-optimal cover of the top tree by `W`-wide nodes (as `Plan` in `wide.rs`, the
/// blocks as children that cannot be opened): `cost[n][i − 1]` is node `n`'s cheapest cover
/// by `i` children, `split[n][j − 1]` the slots its left child gets in the best of `j`.
struct TopPlan<const W: usize> {
    cost: Vec<[f32; W]>,
    split: Vec<[u8; W]>,
    bx: Vec<Aabb>,
}

impl<const W: usize> TopPlan<W> {
    fn new(top: &[TopNode], blocks: &[Fixed]) -> TopPlan<W> {
        let mut plan = TopPlan {
            cost: Vec::with_capacity(top.len()),
            split: Vec::with_capacity(top.len()),
            bx: Vec::with_capacity(top.len()),
        };
        // Post-order: children first.
        for t in top {
            let (cl, bl) = plan.of(t.left, blocks);
            let (cr, br) = plan.of(t.right, blocks);
            let bx = bl.union(&br);
            let (dist, split) = crate::trace::cover::dist(&cl, &cr);
            let mut cost = [0.0f32; W];
            cost[0] = COST_NODE * half_area(&bx) + dist[W - 1];
            for j in 2..=W {
                cost[j - 1] = cost[j - 2].min(dist[j - 1]);
            }
            plan.cost.push(cost);
            plan.split.push(split);
            plan.bx.push(bx);
        }
        plan
    }

    /// Cost row and box of a reference.
    fn of(&self, r: u32, blocks: &[Fixed]) -> ([f32; W], Aabb) {
        if r & REF_FLAG != 0 {
            let b = &blocks[(r & !REF_FLAG) as usize];
            ([b.cost; W], b.bx)
        } else {
            (self.cost[r as usize], self.bx[r as usize])
        }
    }

    /// The references that become the children of the wide node made of top node `n`.
    fn children(&self, top: &[TopNode], n: u32, out: &mut Vec<u32>) {
        out.clear();
        let t = top[n as usize];
        let k = self.split[n as usize][W - 1] as usize;
        let mut todo: Vec<(u32, usize)> = vec![(t.right, W - k), (t.left, k)];
        while let Some((m, mut i)) = todo.pop() {
            if m & REF_FLAG != 0 {
                out.push(m);
                continue;
            }
            let c = &self.cost[m as usize];
            // Fewer slots at the same cost: use fewer (ties go to the smaller cover).
            while i > 1 && c[i - 1] == c[i - 2] {
                i -= 1;
            }
            if i == 1 {
                out.push(m);
            } else {
                let mt = top[m as usize];
                let k = self.split[m as usize][i - 1] as usize;
                todo.push((mt.right, i - k));
                todo.push((mt.left, k));
            }
        }
    }
}

/// Step 3: write the wide node of top node `n` into `slot` (node 0 for the root, else
/// appended) and the top subtree below it; returns the deepest level a block reaches below.
#[allow(clippy::too_many_arguments)]
fn emit_top<const W: usize>(
    top: &[TopNode],
    plan: &TopPlan<W>,
    blocks: &[Fixed],
    n: u32,
    slot: usize,
    depth: usize,
    nodes: &mut Vec<WideNodeN<W>>,
    pad: f32,
) -> usize {
    let mut kids = Vec::with_capacity(W);
    plan.children(top, n, &mut kids);
    let mut node = WideNodeN::<W>::empty();
    let mut deepest = depth;
    for (lane, &r) in kids.iter().enumerate() {
        if r & REF_FLAG != 0 {
            let f = &blocks[(r & !REF_FLAG) as usize];
            node.set(lane, &f.bx, f.code, pad);
            deepest = deepest.max(depth + f.height);
        } else {
            let at = nodes.len();
            nodes.push(WideNodeN::empty());
            let d = emit_top(top, plan, blocks, r, at, depth + 1, nodes, pad);
            node.set(lane, &plan.bx[r as usize], at as u32, pad);
            deepest = deepest.max(d);
        }
    }
    nodes[slot] = node;
    deepest
}

/// Build the whole tree over `inp` (at least one primitive) into `out` (emptied first);
/// returns its depth. Writes the wall ms of step 1 and of step 3 into `times.partition` and
/// `times.top` (0 when the mesh is one block).
pub fn build_tree<K: RadixKey, const W: usize>(
    inp: &Inputs<'_, K>,
    out: &mut Outputs<'_, W>,
    groups: &mut Vec<GroupOut<W>>,
    times: &mut FastTimes,
) -> Result<usize, TraceError> {
    out.leaves = 0;
    let n = inp.keys.len() as u32;
    let mut ranges = Vec::with_capacity((n / BLOCK) as usize * 2 + 1);
    let mut top = Vec::with_capacity(ranges.capacity());
    let t = std::time::Instant::now();
    let root = partition(inp, 0, n, &mut ranges, &mut top);
    times.partition = t.elapsed().as_secs_f64() * 1e3;
    times.top = 0.0;
    let parallel = rayon::current_num_threads() > 1 && ranges.len() > 1;
    // Built by appending (in parallel: the front groups appended, the back ones copied after).
    out.nodes.clear();
    out.packets.clear();
    if root & REF_FLAG != 0 {
        // One block: its root node is node 0, or a root with one lane holds its leaf.
        let mut one = Vec::with_capacity(1);
        build_blocks(inp, &[(0, n)], out, &mut one);
        let f = one[0];
        if f.code & LEAF != 0 {
            let mut node = WideNodeN::<W>::empty();
            node.set(0, &f.bx, f.code, inp.pad);
            out.nodes.push(node);
        }
        return Ok(f.height.saturating_sub(1));
    }
    let blocks = if parallel {
        build_blocks_parallel(inp, &ranges, out, groups)
    } else {
        // Node 0 is kept for the root.
        out.nodes.push(WideNodeN::empty());
        let mut blocks = Vec::with_capacity(ranges.len());
        build_blocks(inp, &ranges, out, &mut blocks);
        blocks
    };
    let t = std::time::Instant::now();
    let plan = TopPlan::<W>::new(&top, &blocks);
    let depth = emit_top(&top, &plan, &blocks, root, 0, 0, out.nodes, inp.pad);
    times.top = t.elapsed().as_secs_f64() * 1e3;
    if depth > MAX_DEPTH {
        return Err(TraceError::TooDeep {
            depth,
            max: MAX_DEPTH,
        });
    }
    Ok(depth)
}

/// The output of one group of consecutive blocks, built on its own (node and packet indices
/// local to the group until they are placed).
#[derive(Clone, Debug, Default)]
pub struct GroupOut<const W: usize> {
    nodes: Vec<WideNodeN<W>>,
    packets: Vec<TriPacket>,
    blocks: Vec<Fixed>,
    leaves: usize,
    block: BlockScratch,
}

/// Groups per thread of the parallel block phase (the unit the workers claim).
const GROUPS_PER_THREAD: usize = 8;

/// Step 2 on the current pool. The ranges are cut into groups of consecutive ranges (about
/// equal primitive counts) that the workers claim one at a time: the calling thread from the
/// front, building each straight into the output (after node 0, as the serial build writes
/// them), the other threads from the back, each group into its own buffers. Where the two ends
/// meet, every group left of it is in place; the others are then copied in parallel after it,
/// child codes moved by the group's offsets. The result equals the serial build's, node for
/// node. (Copying every group instead moved the whole tree twice: stanford-dragon's two-thread
/// tree phase spent 4 of its 18.5 ms in the copy; a fixed direct share waited for the others,
/// as the cost per primitive varies along the curve.)
fn build_blocks_parallel<K: RadixKey, const W: usize>(
    inp: &Inputs<'_, K>,
    ranges: &[(u32, u32)],
    out: &mut Outputs<'_, W>,
    outs: &mut Vec<GroupOut<W>>,
) -> Vec<Fixed> {
    use rayon::prelude::*;
    use std::sync::Mutex;
    let n = inp.keys.len();
    let threads = rayon::current_num_threads();
    let groups = (threads * GROUPS_PER_THREAD).min(ranges.len());
    // Cut the ranges where the primitive count passes each multiple of n / groups.
    let mut cuts = Vec::with_capacity(groups + 1);
    cuts.push(0usize);
    for (i, r) in ranges.iter().enumerate() {
        let g = cuts.len();
        if g < groups && r.0 as usize >= n * g / groups && i > *cuts.last().unwrap() {
            cuts.push(i);
        }
    }
    cuts.push(ranges.len());
    let groups = cuts.len() - 1;
    outs.resize_with(groups, GroupOut::default);
    // Groups not yet claimed: `front..back`.
    let claims = Mutex::new((0usize, groups));
    // The next group from the front (or the back), if any is left.
    let claim = |front: bool| {
        let mut c = claims.lock().unwrap_or_else(|e| e.into_inner());
        (c.0 < c.1).then(|| {
            if front {
                c.0 += 1;
                c.0 - 1
            } else {
                c.1 -= 1;
                c.1
            }
        })
    };
    let mut blocks = Vec::with_capacity(ranges.len());
    // Node 0 is kept for the root.
    out.nodes.push(WideNodeN::empty());
    // Each group's buffers behind its own lock (a group is claimed once, so never contended).
    let slots: Vec<Mutex<&mut GroupOut<W>>> = outs.iter_mut().map(Mutex::new).collect();
    let mut direct = 0;
    rayon::join(
        || {
            while let Some(g) = claim(true) {
                build_blocks(inp, &ranges[cuts[g]..cuts[g + 1]], out, &mut blocks);
                direct = g + 1;
            }
        },
        || {
            (1..threads.max(2)).into_par_iter().for_each(|_| {
                while let Some(g) = claim(false) {
                    let mut o = slots[g].lock().unwrap_or_else(|e| e.into_inner());
                    let o = &mut **o;
                    o.nodes.clear();
                    o.packets.clear();
                    o.blocks.clear();
                    let prims = (ranges[cuts[g + 1] - 1].1 - ranges[cuts[g]].0) as usize;
                    let fresh = o.packets.capacity() == 0;
                    o.packets.reserve(prims / 2 + 1);
                    o.nodes.reserve(prims / (2 * W) + 1);
                    if fresh {
                        crate::hugepage::advise(&o.packets);
                        crate::hugepage::advise(&o.nodes);
                    }
                    let mut go = Outputs {
                        nodes: &mut o.nodes,
                        packets: &mut o.packets,
                        leaves: 0,
                        block: &mut o.block,
                    };
                    build_blocks(inp, &ranges[cuts[g]..cuts[g + 1]], &mut go, &mut o.blocks);
                    o.leaves = go.leaves;
                }
            })
        },
    );
    drop(slots);
    let copied = &outs[direct..];
    // Offsets of every copied group's nodes and packets, after the direct ones'.
    let (mut node_off, mut packet_off) = (
        Vec::with_capacity(copied.len()),
        Vec::with_capacity(copied.len()),
    );
    let (n0, p0) = (out.nodes.len(), out.packets.len());
    let (mut nn, mut np) = (n0, p0);
    for o in copied {
        node_off.push(nn as u32);
        packet_off.push(np as u32);
        nn += o.nodes.len();
        np += o.packets.len();
        out.leaves += o.leaves;
    }
    let shift = |c: u32, no: u32, po: u32| {
        if c == EMPTY {
            c
        } else if c & LEAF != 0 {
            c + po
        } else {
            c + no
        }
    };
    // Each group copied into its place in parallel, straight into the buffers' spare capacity
    // (nothing written twice): one pass per group for the packets, one shifting the child
    // codes for the nodes.
    out.nodes.reserve(nn - n0);
    out.packets.reserve(np - p0);
    let node_slices = split_by_len(
        &mut out.nodes.spare_capacity_mut()[..nn - n0],
        copied.iter().map(|o| o.nodes.len()),
    );
    let packet_slices = split_by_len(
        &mut out.packets.spare_capacity_mut()[..np - p0],
        copied.iter().map(|o| o.packets.len()),
    );
    node_slices
        .into_par_iter()
        .zip(packet_slices)
        .zip(copied)
        .enumerate()
        .for_each(|(g, ((dn, dp), o))| {
            for (d, s) in dp.iter_mut().zip(&o.packets) {
                // SAFETY: a slot of this group's piece, which no other thread touches (the
                // closure fences its stores before it returns).
                #[allow(unsafe_code)]
                unsafe {
                    store_streaming(d.as_mut_ptr(), s)
                };
            }
            for (d, s) in dn.iter_mut().zip(&o.nodes) {
                let mut s = *s;
                for c in s.child.iter_mut() {
                    *c = shift(*c, node_off[g], packet_off[g]);
                }
                // SAFETY: as above.
                #[allow(unsafe_code)]
                unsafe {
                    store_streaming(d.as_mut_ptr(), &s)
                };
            }
            stream_fence();
        });
    // SAFETY: the pieces above cover the `nn - n0` node and `np - p0` packet slots after the
    // buffers' lengths exactly (`split_by_len` of the copied groups' lengths, which sum to
    // them), and the loop over each group wrote every slot of its pieces.
    #[allow(unsafe_code)]
    unsafe {
        out.nodes.set_len(nn);
        out.packets.set_len(np);
    }
    for (g, o) in copied.iter().enumerate() {
        for f in &o.blocks {
            blocks.push(Fixed {
                code: shift(f.code, node_off[g], packet_off[g]),
                ..*f
            });
        }
    }
    blocks
}

/// `v` cut into consecutive pieces of the given lengths (which must sum to at most its length).
fn split_by_len<T>(mut v: &mut [T], lens: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut out = Vec::new();
    for l in lens {
        let (a, b) = v.split_at_mut(l);
        out.push(a);
        v = b;
    }
    out
}

/// Buffers of the fast build kept between builds ([`crate::trace::Accel::rebuild`] reuses
/// them, so a rebuild writes into memory that is already mapped).
#[derive(Clone, Debug, Default)]
pub struct FastScratch<const W: usize> {
    aabbs: Vec<Aabb>,
    codes64: Vec<u64>,
    kbuf64: Vec<u64>,
    codes32: Vec<u32>,
    kbuf32: Vec<u32>,
    ids: Vec<u32>,
    vbuf: Vec<u32>,
    /// The set-aside lists of a rebuild's sort (32- and 64-bit codes).
    rest32: Vec<(u32, u32)>,
    rest64: Vec<(u64, u32)>,
    /// The structure (its [`build_fast`] `owner`), triangle count and code width (32 or 64)
    /// of the last build, whose sorted codes and `ids` are still here: a rebuild of that
    /// structure sorts only the codes that changed and merges them in.
    hint: Option<SortRecord>,
    /// The serial block builder's scratch.
    block: BlockScratch,
    /// The parallel block groups' buffers.
    groups: Vec<GroupOut<W>>,
}

/// Wall milliseconds of the fast build's phases.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FastTimes {
    /// Index check, triangle boxes and scene bounds.
    pub aabb: f64,
    /// The `auto` layout choice (0 for a fixed layout; counted in `encode` too).
    pub choose: f64,
    /// The layout `auto` chose (`None` for a fixed layout).
    pub layout: Option<emc_core::LayoutSpec>,
    /// Encoder set-up and codes.
    pub encode: f64,
    /// Radix sort (a rebuild's hinted sort: see [`crate::sort`]).
    pub sort: f64,
    /// The top-down wide tree with its leaf packets.
    pub tree: f64,
    /// Of `tree`, the partition of the sorted codes into blocks (serial, but for the halves
    /// of ranges over [`PARTITION_PAR_MIN`] primitives, which run as parallel tasks).
    pub partition: f64,
    /// Of `tree`, the top above the blocks (its cover and nodes; serial, 0 when the mesh is
    /// one block).
    pub top: f64,
}

/// The fast build: a `W`-wide tree over the mesh (`W` = 4 or 8) into `bvh`'s buffers, codes of
/// `layout`, leaves of at most `leaf_max` triangles (`1..=`[`LEAF_MAX`]), scratch from
/// `scratch`. `owner` names the structure built: when the scratch's last build was the same
/// structure's over as many triangles (a rebuild), only the codes that changed since are
/// sorted and merged into that build's order.
/// Fails on a leaf size outside that range, an empty mesh, an index naming no vertex, a
/// non-finite vertex, or too many triangles.
#[allow(clippy::too_many_arguments)]
pub fn build_fast<const W: usize>(
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    layout: &crate::auto::LayoutChoice,
    leaf_max: u32,
    owner: u64,
    scratch: &mut FastScratch<W>,
    nodes: &mut Vec<WideNodeN<W>>,
    packets: &mut Vec<TriPacket>,
    times: &mut FastTimes,
) -> Result<FastTree, TraceError> {
    use crate::trace::wide::MAX_TRIANGLES;
    use std::time::Instant;
    let n = indices.len();
    if !(1..=LEAF_MAX).contains(&leaf_max) {
        return Err(TraceError::FastLeafSize {
            given: leaf_max,
            max: LEAF_MAX,
        });
    }
    if n == 0 {
        return Err(TraceError::NoTriangles);
    }
    if n > MAX_TRIANGLES {
        return Err(TraceError::TooManyTriangles(n));
    }
    let t0 = Instant::now();
    let bounds = mesh_boxes(vertices, indices, &mut scratch.aabbs)?;
    let p = bounds.prim;
    let max_abs = p.min.abs().max_element().max(p.max.abs().max_element());
    let pad = max_abs * (1.0 / 65536.0);
    let t1 = Instant::now();
    times.aabb = (t1 - t0).as_secs_f64() * 1e3;
    let frame = emc_core::Frame::from_bounds(bounds, emc_core::Normalization::CentroidBox)
        .map_err(TraceError::Encode)?;
    let (spec, _) = layout
        .resolve(&scratch.aabbs, &frame)
        .map_err(TraceError::Layout)?;
    times.choose = t1.elapsed().as_secs_f64() * 1e3;
    times.layout = layout.is_auto().then_some(spec);
    let enc = emc_core::Encoder::new(&spec, &frame);
    let s = &mut *scratch;
    let bits = if enc.layout().fits_u32() { 32 } else { 64 };
    let setup = Setup {
        vertices,
        indices,
        pad,
        leaf_max,
        max_abs,
        t1,
    };
    let hint = (&mut s.hint, (owner, n, bits));
    let bufs = (&mut s.ids, &mut s.vbuf, &mut s.block, &mut s.groups);
    let tree = if bits == 32 {
        let encode = |out: &mut [u32]| crate::encode::encode_parallel_u32(&enc, &s.aabbs, out);
        let keys = (&mut s.codes32, &mut s.kbuf32, &mut s.rest32);
        codes_to_tree(keys, bufs, hint, encode, &setup, nodes, packets, times)?
    } else {
        let encode = |out: &mut [u64]| crate::encode::encode_parallel(&enc, &s.aabbs, out);
        let keys = (&mut s.codes64, &mut s.kbuf64, &mut s.rest64);
        codes_to_tree(keys, bufs, hint, encode, &setup, nodes, packets, times)?
    };
    Ok(tree)
}

/// Which sort a fast scratch holds the result of: the structure built (the `owner` of
/// [`build_fast`]), its triangle count and its code bits (32 or 64).
type SortRecord = (u64, usize, u32);

/// What [`codes_to_tree`] needs of [`build_fast`] besides the buffers.
struct Setup<'a> {
    vertices: &'a [Vec3],
    indices: &'a [[u32; 3]],
    pad: f32,
    leaf_max: u32,
    max_abs: f32,
    /// When the encoding began.
    t1: std::time::Instant,
}

/// Encode by `encode`, sort, and build the tree over the sorted codes, timing the phases.
/// `keys` are the codes buffer, its sort scratch and a rebuild's set-aside list. `hint` is the
/// scratch's record of its last sort and this build's (owner, triangles, code bits): when they
/// agree (a rebuild of the same structure) the codes buffer still holds that sort's codes (`ids`
/// their order), so the new codes go into the scratch and only those that changed are sorted
/// (`sort_with_ids_hinted`); once sorted, the record is this build's.
#[allow(clippy::too_many_arguments)]
fn codes_to_tree<K: RadixKey, const W: usize>(
    (codes, kbuf, rest): (&mut Vec<K>, &mut Vec<K>, &mut Vec<(K, u32)>),
    (ids, vbuf, block, groups): (
        &mut Vec<u32>,
        &mut Vec<u32>,
        &mut BlockScratch,
        &mut Vec<GroupOut<W>>,
    ),
    (hint, this): (&mut Option<SortRecord>, SortRecord),
    encode: impl FnOnce(&mut [K]) -> Result<(), emc_core::Error>,
    setup: &Setup<'_>,
    nodes: &mut Vec<WideNodeN<W>>,
    packets: &mut Vec<TriPacket>,
    times: &mut FastTimes,
) -> Result<FastTree, TraceError> {
    use std::time::Instant;
    let n = setup.indices.len();
    let hinted = hint.take() == Some(this);
    let out = if hinted { &mut *kbuf } else { &mut *codes };
    crate::buffers::resized(out, n, K::default());
    encode(out).map_err(TraceError::Encode)?;
    let t2 = Instant::now();
    times.encode = (t2 - setup.t1).as_secs_f64() * 1e3;
    if hinted {
        crate::sort::sort_with_ids_hinted(codes, kbuf, ids, vbuf, rest).map(|_| ())
    } else {
        crate::sort::sort_with_ids(codes, ids, kbuf, vbuf).map(|_| ())
    }
    .map_err(TraceError::Sort)?;
    *hint = Some(this);
    let t3 = Instant::now();
    times.sort = (t3 - t2).as_secs_f64() * 1e3;
    let inp = Inputs {
        keys: codes,
        ids,
        vertices: setup.vertices,
        indices: setup.indices,
        pad: setup.pad,
        leaf_max: setup.leaf_max,
    };
    finish_tree(
        &inp,
        nodes,
        packets,
        block,
        groups,
        setup.max_abs,
        times,
        t3,
    )
}

/// What the fast build's tree came to.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FastTree {
    /// Leaves.
    pub leaves: usize,
    /// Depth (root: 0).
    pub depth: usize,
    /// Largest absolute vertex coordinate.
    pub max_abs: f32,
}

#[allow(clippy::too_many_arguments)]
fn finish_tree<K: RadixKey, const W: usize>(
    inp: &Inputs<'_, K>,
    nodes: &mut Vec<WideNodeN<W>>,
    packets: &mut Vec<TriPacket>,
    block: &mut BlockScratch,
    groups: &mut Vec<GroupOut<W>>,
    max_abs: f32,
    times: &mut FastTimes,
    t3: std::time::Instant,
) -> Result<FastTree, TraceError> {
    let n = inp.keys.len();
    let fresh = packets.capacity() == 0;
    // Room for the expected tree (the buffers may still hold a previous build's elements).
    nodes.reserve((n / (2 * W) + 1).saturating_sub(nodes.len()));
    packets.reserve((n / 2 + 1).saturating_sub(packets.len()));
    if fresh {
        crate::hugepage::advise(packets);
        crate::hugepage::advise(nodes);
    }
    let mut out = Outputs {
        nodes,
        packets,
        leaves: 0,
        block,
    };
    let depth = build_tree(inp, &mut out, groups, times)?;
    times.tree = t3.elapsed().as_secs_f64() * 1e3;
    Ok(FastTree {
        leaves: out.leaves,
        depth,
        max_abs,
    })
}

/// Check the mesh (every index names a vertex, every corner is finite) and write its triangle
/// boxes into `aabbs` (resized to one per triangle, its allocation reused), returning their
/// bounds: one SIMD pass over the triangles after the checks.
pub(crate) fn mesh_boxes(
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    aabbs: &mut Vec<Aabb>,
) -> Result<emc_core::SceneBounds, TraceError> {
    check_indices(vertices, indices)?;
    crate::buffers::resized_par(aabbs, indices.len(), Aabb::EMPTY);
    crate::aabbs::triangle_aabbs_bounds(vertices, indices, aabbs).map_err(|e| match e {
        emc_core::Error::NonFinite(i) | emc_core::Error::InvertedBox(i) => TraceError::NonFinite(i),
        e => TraceError::Encode(e),
    })
}

/// Every index names a vertex and every vertex a triangle uses is finite (two branch-free
/// passes; the slow search for the culprit runs only when one of them fails). Both folds are
/// written so that the x86-64 baseline vectorises them (a compare and an or per index; an and,
/// an add and an or per coordinate): a `u32` maximum has no SSE2 instruction, and
/// its emulation made the check cost as much as the boxes (stanford-dragon, fast preset: 7.1 →
/// 3.x ns per triangle for the whole boxes phase).
fn check_indices(vertices: &[Vec3], indices: &[[u32; 3]]) -> Result<(), TraceError> {
    use rayon::prelude::*;
    let nv = vertices.len();
    // Indices at or past `nv` (`nv` ≥ 2^32 admits every index).
    let limit = u32::try_from(nv).unwrap_or(u32::MAX);
    let all_below = nv > u32::MAX as usize;
    let over = indices
        .as_flattened()
        .par_chunks(3 << 16)
        .map(|c| c.iter().fold(0u32, |m, &x| m | (x >= limit) as u32))
        .reduce(|| 0, |a, b| a | b);
    if over != 0 && !all_below {
        let (tri, index) = indices
            .iter()
            .enumerate()
            .find_map(|(i, t)| t.iter().find(|&&x| x as usize >= nv).map(|&x| (i, x)))
            .expect("some index is out of range");
        return Err(TraceError::BadIndex {
            tri,
            index,
            vertices: nv,
        });
    }
    // A coordinate is not finite exactly when its exponent field is all ones, that is when
    // adding one to the field carries into the sign bit.
    const EXP: u32 = 0x7f80_0000;
    let carry = |x: f32| (x.to_bits() & EXP) + (1 << 23);
    let any = vertices
        .par_chunks(1 << 16)
        .map(|c| {
            c.iter()
                .fold(0u32, |m, v| m | carry(v.x) | carry(v.y) | carry(v.z))
        })
        .reduce(|| 0, |a, b| a | b);
    if any & (1 << 31) != 0 {
        if let Some(tri) = indices
            .iter()
            .position(|t| t.iter().any(|&i| !vertices[i as usize].is_finite()))
        {
            return Err(TraceError::NonFinite(tri));
        }
    }
    Ok(())
}
