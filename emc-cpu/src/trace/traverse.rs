//! Single-ray traversal of a [`WideBvh`]: closest hit and any hit, with an SSE node test (one
//! slab test of all four children per instruction) and a scalar node test that is its
//! bit-exact reference. Children are visited nearest first; a node is skipped when its entry
//! distance exceeds the best hit so far (with a rounding slack, [`CULL_SLACK`]; `t ≤ best` is
//! kept, so ties still reach lower ids).

use core::mem::MaybeUninit;

use crate::trace::intersect::{better, slab_test, triangle_test, Hit, PreRay, Ray};
use crate::trace::wide::{WideBvh, WideNode, EMPTY, LAST, LEAF, STACK_CAPACITY, WIDTH};

/// Slack of distance culling: a node is skipped when its entry distance exceeds
/// `best · CULL_SLACK` (or `tfar · CULL_SLACK`). A box entry and a triangle distance are
/// rounded differently, so a triangle whose computed `t` ties or beats the best (e.g. two
/// triangles meeting at the vertex a ray aims at) can sit in a box whose computed entry is a
/// few ulps beyond it; the slack (2^-12, far above those rounding errors) keeps such triangles
/// visible, so traversal returns exactly the brute-force answer. Triangles themselves are still
/// accepted only for `t ≤ best` (then the lower id wins ties).
pub const CULL_SLACK: f32 = 1.0 + 1.0 / 4096.0;

/// `t` pushed away from zero by the relative slack: `t + |t|·2^-12` (+inf stays +inf).
#[inline(always)]
fn slack(t: f32) -> f32 {
    t + t.abs() * (CULL_SLACK - 1.0)
}

/// Work counters of a traversal (summed over rays).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraceStats {
    /// Rays traced.
    pub rays: u64,
    /// Wide nodes tested (each tests `WIDTH` child boxes at once).
    pub node_tests: u64,
    /// Ray–triangle tests.
    pub tri_tests: u64,
}

impl TraceStats {
    /// Sum of two counters.
    pub fn add(&self, o: &TraceStats) -> TraceStats {
        TraceStats {
            rays: self.rays + o.rays,
            node_tests: self.node_tests + o.node_tests,
            tri_tests: self.tri_tests + o.tri_tests,
        }
    }
}

/// Which node test a traversal uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeTest {
    /// Four scalar [`slab_test`]s (the reference).
    Scalar,
    /// One SSE slab test of all four lanes (x86-64; elsewhere it falls back to `Scalar`).
    Simd,
}

/// Result of testing one node: a bit per entered lane and each lane's entry distance.
pub type LaneHits = (u32, [f32; WIDTH]);

/// The scalar node test: lane `i` entered iff `slab_test` of child `i` passes (its distance
/// is then the entry distance; a missed lane's distance is unspecified).
#[inline(always)]
pub fn node_test_scalar(node: &WideNode, r: &PreRay, tfar: f32) -> LaneHits {
    let mut mask = 0;
    let mut dist = [0.0; WIDTH];
    for (lane, d) in dist.iter_mut().enumerate() {
        let p = &node.planes;
        let min = [p[0][lane], p[2][lane], p[4][lane]];
        let max = [p[1][lane], p[3][lane], p[5][lane]];
        match slab_test(r, min, max, tfar) {
            Some(t) => {
                mask |= 1 << lane;
                *d = t;
            }
            None => *d = f32::INFINITY,
        }
    }
    (mask, dist)
}

/// The SIMD node test (SSE on x86-64, else the scalar one); same mask, and the same entry
/// distances on entered lanes, as [`node_test_scalar`].
pub fn node_test_simd(node: &WideNode, r: &PreRay, tfar: f32) -> LaneHits {
    Tester::new(NodeTest::Simd, r).test(node, r, tfar)
}

#[cfg(target_arch = "x86_64")]
mod sse {
    use core::arch::x86_64::*;

    use super::LaneHits;
    use crate::trace::intersect::{PreRay, FAR_WIDEN};
    use crate::trace::wide::WideNode;

    /// Ray constants broadcast to all lanes.
    #[derive(Clone, Copy, Debug)]
    pub struct SseRay {
        org: [__m128; 3],
        inv: [__m128; 3],
        /// Plane row of the near plane per axis (`2a` or `2a + 1`).
        near: [usize; 3],
        tnear: __m128,
        widen: __m128,
    }

    impl SseRay {
        #[inline(always)]
        pub fn new(r: &PreRay) -> SseRay {
            let near = [0, 1, 2].map(|a| 2 * a + r.near_is_max[a] as usize);
            // SAFETY: SSE is part of the x86-64 baseline; these intrinsics only move values.
            unsafe {
                SseRay {
                    org: r.org.map(|o| _mm_set1_ps(o)),
                    inv: r.inv.map(|i| _mm_set1_ps(i)),
                    near,
                    tnear: _mm_set1_ps(r.tnear),
                    widen: _mm_set1_ps(FAR_WIDEN),
                }
            }
        }

        /// The four slab tests of `node` in one go, operation for operation the same as
        /// `slab_test` (sub, mul, widen-mul, then `max(tn, t0)` / `min(tf, t1)` whose operand
        /// order discards NaN exactly as `max_sse`/`min_sse` do).
        #[inline(always)]
        pub fn test(&self, node: &WideNode, tfar: f32) -> LaneHits {
            // SAFETY: SSE is part of the x86-64 baseline. The aligned loads read
            // `planes[n]` / `planes[f]`, `[f32; 4]` rows at 16-byte multiples inside a 64-byte
            // aligned node; the unaligned store writes the 4 floats of `dist`.
            unsafe {
                let mut t0 = self.tnear;
                let mut t1 = _mm_set1_ps(tfar);
                for a in 0..3 {
                    let n = self.near[a];
                    let f = n ^ 1;
                    let np = _mm_load_ps(node.planes[n].as_ptr());
                    let fp = _mm_load_ps(node.planes[f].as_ptr());
                    let tn = _mm_mul_ps(_mm_sub_ps(np, self.org[a]), self.inv[a]);
                    let tf = _mm_mul_ps(
                        _mm_mul_ps(_mm_sub_ps(fp, self.org[a]), self.inv[a]),
                        self.widen,
                    );
                    t0 = _mm_max_ps(tn, t0);
                    t1 = _mm_min_ps(tf, t1);
                }
                let mask = _mm_movemask_ps(_mm_cmple_ps(t0, t1)) as u32;
                let mut dist = [0.0f32; 4];
                _mm_storeu_ps(dist.as_mut_ptr(), t0);
                (mask, dist)
            }
        }
    }
}

/// The node test of one ray, chosen once per ray.
#[derive(Clone, Copy, Debug)]
enum Tester {
    Scalar,
    #[cfg(target_arch = "x86_64")]
    Sse(sse::SseRay),
}

impl Tester {
    #[inline(always)]
    fn new(kind: NodeTest, r: &PreRay) -> Tester {
        match kind {
            NodeTest::Scalar => Tester::Scalar,
            #[cfg(target_arch = "x86_64")]
            NodeTest::Simd => Tester::Sse(sse::SseRay::new(r)),
            #[cfg(not(target_arch = "x86_64"))]
            NodeTest::Simd => Tester::Scalar,
        }
    }

    #[inline(always)]
    fn test(&self, node: &WideNode, r: &PreRay, tfar: f32) -> LaneHits {
        match self {
            Tester::Scalar => node_test_scalar(node, r, tfar),
            #[cfg(target_arch = "x86_64")]
            Tester::Sse(s) => s.test(node, tfar),
        }
    }
}

/// A fixed-capacity stack of `(child code, entry distance)`; its capacity is the bound
/// [`WideBvh::from_bvh2`] proved for the tree.
struct Stack {
    items: [MaybeUninit<(u32, f32)>; STACK_CAPACITY],
    len: usize,
}

impl Stack {
    #[inline(always)]
    fn new() -> Stack {
        Stack {
            items: [MaybeUninit::uninit(); STACK_CAPACITY],
            len: 0,
        }
    }

    #[inline(always)]
    fn push(&mut self, e: (u32, f32)) {
        // Never fails on a tree from `from_bvh2` (depth ≤ MAX_DEPTH); `items[len]` is
        // bounds-checked regardless, so a broken invariant panics instead of corrupting.
        self.items[self.len] = MaybeUninit::new(e);
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<(u32, f32)> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        // SAFETY: every slot below the old `len` was written by `push` before being counted.
        Some(unsafe { self.items[self.len].assume_init() })
    }
}

/// Push the entered lanes of `hits`, farthest first, so the nearest is popped next.
#[inline(always)]
fn push_ordered(stack: &mut Stack, node: &WideNode, (mask, dist): LaneHits) {
    let mut e = [(0u32, 0.0f32); WIDTH];
    let mut n = 0;
    let mut m = mask;
    while m != 0 {
        let lane = m.trailing_zeros() as usize;
        m &= m - 1;
        let code = node.child[lane];
        if code == EMPTY {
            continue;
        }
        // Insertion sort by descending distance (at most four entries).
        let mut j = n;
        while j > 0 && e[j - 1].1 < dist[lane] {
            e[j] = e[j - 1];
            j -= 1;
        }
        e[j] = (code, dist[lane]);
        n += 1;
    }
    for &x in &e[..n] {
        stack.push(x);
    }
}

/// Closest hit of `ray` in `bvh` (`None` when nothing is hit in `[tnear, tfar]` or the ray is
/// invalid), counting work into `stats` when `STATS` is set.
#[inline]
pub fn closest<const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    kind: NodeTest,
    stats: &mut TraceStats,
) -> Option<Hit> {
    if STATS {
        stats.rays += 1;
    }
    if !ray.is_valid() || bvh.nodes.is_empty() {
        return None;
    }
    let r = PreRay::new(ray);
    let tester = Tester::new(kind, &r);
    let mut best = Hit {
        t: r.tfar,
        prim: u32::MAX,
        u: 0.0,
        v: 0.0,
    };
    let mut found = false;
    let mut cull = slack(r.tfar);
    let mut stack = Stack::new();
    stack.push((0, r.tnear));
    while let Some((code, d)) = stack.pop() {
        if d > cull {
            continue;
        }
        if code & LEAF != 0 {
            let mut slot = (code & !LEAF) as usize;
            loop {
                if STATS {
                    stats.tri_tests += 1;
                }
                let id = bvh.ids[slot];
                let prim = id & !LAST;
                if let Some((t, u, v)) = triangle_test(&r, &bvh.tris[slot], best.t) {
                    if !found || better(t, prim, best.t, best.prim) {
                        best = Hit { t, prim, u, v };
                        cull = slack(t);
                        found = true;
                    }
                }
                if id & LAST != 0 {
                    break;
                }
                slot += 1;
            }
        } else {
            let node = &bvh.nodes[code as usize];
            if STATS {
                stats.node_tests += 1;
            }
            let hits = tester.test(node, &r, cull);
            push_ordered(&mut stack, node, hits);
        }
    }
    found.then_some(best)
}

/// True when `ray` hits any triangle in `[tnear, tfar]` (false for an invalid ray).
#[inline]
pub fn occluded<const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    kind: NodeTest,
    stats: &mut TraceStats,
) -> bool {
    if STATS {
        stats.rays += 1;
    }
    if !ray.is_valid() || bvh.nodes.is_empty() {
        return false;
    }
    let r = PreRay::new(ray);
    let tester = Tester::new(kind, &r);
    let cull = slack(r.tfar);
    let mut stack = Stack::new();
    stack.push((0, r.tnear));
    while let Some((code, _)) = stack.pop() {
        if code & LEAF != 0 {
            let mut slot = (code & !LEAF) as usize;
            loop {
                if STATS {
                    stats.tri_tests += 1;
                }
                if triangle_test(&r, &bvh.tris[slot], r.tfar).is_some() {
                    return true;
                }
                if bvh.ids[slot] & LAST != 0 {
                    break;
                }
                slot += 1;
            }
        } else {
            let node = &bvh.nodes[code as usize];
            if STATS {
                stats.node_tests += 1;
            }
            let hits = tester.test(node, &r, cull);
            push_ordered(&mut stack, node, hits);
        }
    }
    false
}
