//! Single-ray traversal of a [`WideBvh`]: closest hit and any hit, on the 4-wide tree with an
//! SSE node test or on the 8-wide tree with an AVX2 node test (one slab test of all children
//! per instruction), each with a scalar node test as its bit-exact reference. Children are
//! visited nearest first; a node is skipped when its entry
//! distance exceeds the best hit so far (with a rounding slack, [`CULL_SLACK`] plus an
//! absolute part; `t ≤ best` is kept, so ties still reach lower ids).

use core::mem::MaybeUninit;

use crate::trace::intersect::{better, slab_test, triangle_test, Hit, PreRay, Ray};
use crate::trace::wide::{
    TriPacket, WideBvh, WideNode, WideNode8, WideNodeN, LEAF, STACK_CAPACITY8, WIDTH, WIDTH8,
};

/// Relative slack of distance culling, 2^-12. A node is skipped only when its entry distance
/// exceeds `slack(best)` (or `slack(tfar)`): box entries and triangle distances are rounded
/// differently, so a triangle whose computed `t` ties or beats the best (two triangles meeting
/// at the vertex a ray aims at, overlapping coplanar triangles) can sit in a box whose
/// computed entry lies beyond it. The slack keeps such triangles visible, so traversal returns
/// exactly the brute-force answer; triangles themselves are still accepted only for
/// `t ≤ best` (then the lower id wins ties).
pub const CULL_SLACK: f32 = 1.0 + 1.0 / 4096.0;

/// Absolute part of the culling slack, per ray: `2^-16 · (M + max|o|) / max|d|` with `M` the
/// largest vertex coordinate. A triangle's `t` carries an absolute error of a few ulps of the
/// coordinates (vertices minus origin), which dwarfs `t` itself when the origin sits close to
/// the geometry; 2^-16 leaves a margin of 2^7 over the 2^-23 of those roundings. `1/max|d|`
/// is read off the reciprocals the ray already has (the smallest `|inv|`, within an ulp of
/// it), so no division is spent per ray.
#[inline(always)]
fn abs_slack(bvh: &WideBvh, r: &PreRay) -> f32 {
    let o = r.org[0].abs().max(r.org[1].abs()).max(r.org[2].abs());
    let inv_d = r.inv[0].abs().min(r.inv[1].abs()).min(r.inv[2].abs());
    (bvh.max_abs + o) * (1.0 / 65536.0) * inv_d
}

/// `t` pushed away by both slacks: `t + |t|·2^-12 + abs` (+inf stays +inf).
#[inline(always)]
fn slack(t: f32, abs: f32) -> f32 {
    t + t.abs() * (CULL_SLACK - 1.0) + abs
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

/// Which tree and node test a traversal uses. All four give the same hits, bit for bit; the
/// two of one tree also do the same work (same node and triangle counts).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeTest {
    /// 4-wide tree, four scalar [`slab_test`]s per node (the reference of `Simd`).
    Scalar,
    /// 4-wide tree, one SSE slab test of all four lanes (x86-64; elsewhere it falls back to
    /// `Scalar`).
    Simd,
    /// 8-wide tree, eight scalar [`slab_test`]s per node (the reference of `Avx2`).
    Scalar8,
    /// 8-wide tree, one AVX2 slab test of all eight lanes; falls back to `Scalar8` when the
    /// CPU lacks AVX2 (detected at run time).
    Avx2,
    /// 8-wide tree, an AVX-512 slab test: both planes of an axis (one 64-byte row pair) in one
    /// 16-lane register, near and far halves combined under masks; falls back to `Avx2` when
    /// the CPU lacks AVX-512 F/VL/DQ (detected at run time).
    Avx512,
}

impl NodeTest {
    /// The fastest test this CPU runs: `Avx2` when it has AVX2, else `Simd`. Also `Avx2` on
    /// CPUs with AVX-512: the `Avx512` test ran 0.62-0.78x its speed on an AVX-512 Xeon
    /// (pbrt-bathroom and stanford-dragon, primary and AO rays, the two interleaved in one
    /// process), so it is chosen only when asked for.
    pub fn fastest() -> NodeTest {
        if avx2_available() {
            NodeTest::Avx2
        } else {
            NodeTest::Simd
        }
    }

    /// The fastest test of a tree of `width` children (4 or 8) on this CPU.
    pub fn for_width(width: usize) -> NodeTest {
        if width == WIDTH8 {
            NodeTest::Avx2
        } else {
            NodeTest::Simd
        }
    }

    /// Children per node of the tree this test traverses (4 or 8).
    pub fn width(self) -> usize {
        match self {
            NodeTest::Scalar | NodeTest::Simd => WIDTH,
            NodeTest::Scalar8 | NodeTest::Avx2 | NodeTest::Avx512 => WIDTH8,
        }
    }

    /// The test a traversal asked for `self` really runs on this CPU, and why.
    pub fn resolved(self) -> (NodeTest, &'static str) {
        match self {
            NodeTest::Avx512 if avx512_available() => {
                (self, "AVX-512 F/VL/DQ detected at run time")
            }
            NodeTest::Avx512 if avx2_available() => {
                (NodeTest::Avx2, "no AVX-512 F/VL/DQ on this CPU: AVX2 test")
            }
            NodeTest::Avx512 | NodeTest::Avx2 if !avx2_available() => {
                (NodeTest::Scalar8, "no AVX2 on this CPU: scalar test")
            }
            NodeTest::Avx2 => (self, "AVX2 detected at run time"),
            NodeTest::Simd if cfg!(target_arch = "x86_64") => (self, "SSE (x86-64 baseline)"),
            NodeTest::Simd => (NodeTest::Scalar, "no SSE off x86-64: scalar test"),
            _ => (self, "scalar reference"),
        }
    }
}

impl NodeTest {
    /// Every test, by its name in [`NodeTest::name`].
    pub const ALL: [NodeTest; 5] = [
        NodeTest::Scalar,
        NodeTest::Simd,
        NodeTest::Scalar8,
        NodeTest::Avx2,
        NodeTest::Avx512,
    ];

    /// The test's name on the command line: `scalar`, `sse`, `scalar8`, `avx2`, `avx512`.
    pub fn name(self) -> &'static str {
        match self {
            NodeTest::Scalar => "scalar",
            NodeTest::Simd => "sse",
            NodeTest::Scalar8 => "scalar8",
            NodeTest::Avx2 => "avx2",
            NodeTest::Avx512 => "avx512",
        }
    }
}

impl core::str::FromStr for NodeTest {
    type Err = String;

    /// A test by its [`NodeTest::name`].
    fn from_str(s: &str) -> Result<NodeTest, String> {
        NodeTest::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| format!("unknown node test `{s}` (scalar, sse, scalar8, avx2, avx512)"))
    }
}

/// True when the CPU runs the AVX-512 node test (F, VL and DQ, plus AVX2 for the rest of the
/// kernel; checked once, then cached by the standard library).
#[inline(always)]
pub fn avx512_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        avx2_available()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512vl")
            && std::arch::is_x86_feature_detected!("avx512dq")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// True when the CPU runs AVX2 (checked once, then cached by the standard library).
#[inline(always)]
pub fn avx2_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Result of testing one 4-wide node: a bit per entered lane and each lane's entry distance.
pub type LaneHits = (u32, [f32; WIDTH]);

/// Result of testing one `W`-wide node.
pub type LaneHitsN<const W: usize> = (u32, [f32; W]);

/// The scalar node test: lane `i` entered iff `slab_test` of child `i` passes (its distance
/// is then the entry distance; a missed lane's distance is unspecified).
#[inline(always)]
pub fn node_test_scalar<const W: usize>(
    node: &WideNodeN<W>,
    r: &PreRay,
    tfar: f32,
) -> LaneHitsN<W> {
    let mut mask = 0;
    let mut dist = [0.0; W];
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
    #[cfg(target_arch = "x86_64")]
    {
        sse::SseRay::new(r).test(node, tfar)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        node_test_scalar(node, r, tfar)
    }
}

/// The AVX2 node test of an 8-wide node (the scalar one without AVX2); same mask, and the same
/// entry distances on entered lanes, as [`node_test_scalar`].
pub fn node_test_avx2(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
    #[cfg(target_arch = "x86_64")]
    if avx2_available() {
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { avx::node_test(node, r, tfar) };
    }
    node_test_scalar(node, r, tfar)
}

/// The AVX2 node test of the closest-hit kernel of `r`'s octant (near and far rows fixed per
/// kernel; the scalar test without AVX2); same mask, and the same entry distances on entered
/// lanes, as [`node_test_scalar`].
pub fn node_test_avx2_octant(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
    #[cfg(target_arch = "x86_64")]
    if avx2_available() {
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { avx::node_test_octant(node, r, tfar) };
    }
    node_test_scalar(node, r, tfar)
}

/// The AVX-512 node test of an 8-wide node (the AVX2 one without AVX-512, the scalar one
/// without AVX2); same mask, and the same entry distances on entered lanes, as
/// [`node_test_scalar`].
pub fn node_test_avx512(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
    #[cfg(target_arch = "x86_64")]
    if avx512_available() {
        // SAFETY: the CPU has AVX-512 F/VL/DQ and AVX2 (checked just above).
        return unsafe { avx512::node_test(node, r, tfar) };
    }
    node_test_avx2(node, r, tfar)
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use core::arch::x86_64::*;

    use super::LaneHitsN;
    use crate::trace::intersect::PreRay;
    use crate::trace::wide::{WideNode8, WIDTH8};

    /// Ray constants of the AVX-512 test.
    ///
    /// An axis's two plane rows are adjacent in a node, so one 16-lane load holds them:
    /// ```text
    ///   lanes 0..8: planes[2a] (child minima)   lanes 8..16: planes[2a + 1] (maxima)
    ///   (p - org) * inv16, inv16 = inv on the near plane's half, inv_far on the far one's,
    ///   then permuted so that lanes 0..8 hold the near plane's distances, 8..16 the far's
    ///   acc: lanes 0..8 = t0 (max over axes), lanes 8..16 = t1 (min over axes)
    /// ```
    #[derive(Clone, Copy, Debug)]
    pub struct Avx512Ray {
        org: [__m512; 3],
        /// Per axis: `inv` in the near plane's half, `inv_far` in the far plane's.
        inv: [__m512; 3],
        /// Per axis: identity when the near plane is the minimum, else the two halves swapped.
        perm: [__m512i; 3],
        tnear: __m512,
    }

    impl Avx512Ray {
        /// The constants of `r`. Only call with AVX-512 F/VL/DQ present (inlined into such a
        /// function).
        #[inline(always)]
        pub fn new(r: &PreRay) -> Avx512Ray {
            // SAFETY: only reached from functions that run with AVX-512 enabled and detected;
            // these intrinsics only move values.
            unsafe {
                let id = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
                let swap = _mm512_setr_epi32(8, 9, 10, 11, 12, 13, 14, 15, 0, 1, 2, 3, 4, 5, 6, 7);
                Avx512Ray {
                    org: r.org.map(|o| _mm512_set1_ps(o)),
                    inv: [0, 1, 2].map(|a| {
                        // Lanes 8..16 hold the maxima: the far plane's unless the near is max.
                        let far_high = if r.near_is_max[a] { 0x00FF } else { 0xFF00 };
                        _mm512_mask_blend_ps(
                            far_high,
                            _mm512_set1_ps(r.inv[a]),
                            _mm512_set1_ps(r.inv_far[a]),
                        )
                    }),
                    perm: r.near_is_max.map(|m| if m { swap } else { id }),
                    tnear: _mm512_set1_ps(r.tnear),
                }
            }
        }

        /// The low four lanes of the origin and of `tnear` (what the SSE tests broadcast).
        #[inline(always)]
        pub fn low_org_tnear(&self) -> ([__m128; 3], __m128) {
            // SAFETY: only reached with AVX-512 enabled; casts only reinterpret registers.
            unsafe {
                (
                    self.org.map(|o| _mm512_castps512_ps128(o)),
                    _mm512_castps512_ps128(self.tnear),
                )
            }
        }

        /// The eight slab tests of `node`, lane for lane the same operations as `slab_test`:
        /// `(p - o) · inv` on the near plane, `(p - o) · inv_far` on the far one, then
        /// `max(tn, t0)` / `min(tf, t1)` in that operand order (`vmaxps`/`vminps` discard NaN
        /// as `max_sse`/`min_sse` do).
        #[inline(always)]
        pub fn test(&self, node: &WideNode8, tfar: f32) -> LaneHitsN<WIDTH8> {
            super::avx::lane_hits(self.test_raw(node, tfar))
        }

        /// [`Avx512Ray::test`] left in registers: the entry distances and the entered lanes
        /// (all ones).
        #[inline(always)]
        pub fn test_raw(&self, node: &WideNode8, tfar: f32) -> (__m256, __m256) {
            // SAFETY: only reached with AVX-512 F/VL/DQ enabled and detected. `planes` is six
            // contiguous rows of eight floats in a 64-byte aligned node, so the aligned load at
            // float `16 a` (`a < 3`) reads rows `2a` and `2a + 1`, 64 bytes at a 64-byte
            // boundary.
            unsafe {
                let rows = node.planes.as_ptr().cast::<f32>();
                let mut acc = _mm512_mask_broadcastss_ps(self.tnear, 0xFF00, _mm_set_ss(tfar));
                for a in 0..3 {
                    let p = _mm512_load_ps(rows.add(16 * a));
                    let t = _mm512_mul_ps(_mm512_sub_ps(p, self.org[a]), self.inv[a]);
                    let t = _mm512_permutexvar_ps(self.perm[a], t);
                    acc = _mm512_mask_max_ps(acc, 0x00FF, t, acc);
                    acc = _mm512_mask_min_ps(acc, 0xFF00, t, acc);
                }
                let t0 = _mm512_castps512_ps256(acc);
                let t1 = _mm512_extractf32x8_ps::<1>(acc);
                (t0, _mm256_cmp_ps::<_CMP_LE_OQ>(t0, t1))
            }
        }
    }

    /// One AVX-512 node test (for the equality tests).
    ///
    /// # Safety
    /// The CPU must have AVX-512 F, VL and DQ.
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2")]
    pub unsafe fn node_test(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
        Avx512Ray::new(r).test(node, tfar)
    }
}

/// `$e` with the const `$o` set to the octant `$oct` (see `octant`): one instance of `$e` per
/// octant, the ray's picked by one `match`.
#[cfg(target_arch = "x86_64")]
macro_rules! by_octant {
    ($oct:expr, $o:ident => $e:expr) => {
        match $oct {
            0 => {
                const $o: usize = 0;
                $e
            }
            1 => {
                const $o: usize = 1;
                $e
            }
            2 => {
                const $o: usize = 2;
                $e
            }
            3 => {
                const $o: usize = 3;
                $e
            }
            4 => {
                const $o: usize = 4;
                $e
            }
            5 => {
                const $o: usize = 5;
                $e
            }
            6 => {
                const $o: usize = 6;
                $e
            }
            _ => {
                const $o: usize = 7;
                $e
            }
        }
    };
}

#[cfg(target_arch = "x86_64")]
mod avx {
    use core::arch::x86_64::*;

    use super::LaneHitsN;
    use crate::trace::intersect::PreRay;
    use crate::trace::wide::{WideNode8, WIDTH8};

    /// Ray constants broadcast to all eight lanes (what both AVX2 node tests share).
    #[derive(Clone, Copy, Debug)]
    struct Broadcast {
        org: [__m256; 3],
        inv: [__m256; 3],
        inv_far: [__m256; 3],
        tnear: __m256,
    }

    impl Broadcast {
        /// Only call with AVX2 present (inlined into an AVX2 function).
        #[inline(always)]
        fn new(r: &PreRay) -> Broadcast {
            // SAFETY: only reached from functions that run with AVX2 enabled and detected;
            // these intrinsics only move values.
            unsafe {
                Broadcast {
                    org: r.org.map(|o| _mm256_set1_ps(o)),
                    inv: r.inv.map(|i| _mm256_set1_ps(i)),
                    inv_far: r.inv_far.map(|i| _mm256_set1_ps(i)),
                    tnear: _mm256_set1_ps(r.tnear),
                }
            }
        }

        /// The low four lanes of the origin and of `tnear` (what the SSE tests broadcast).
        #[inline(always)]
        fn low_org_tnear(&self) -> ([__m128; 3], __m128) {
            // SAFETY: only reached with AVX2 enabled; casts only reinterpret registers.
            unsafe {
                (
                    self.org.map(|o| _mm256_castps256_ps128(o)),
                    _mm256_castps256_ps128(self.tnear),
                )
            }
        }

        /// The eight slab tests of `node`, operation for operation the same as `slab_test`
        /// (`vmaxps`/`vminps` discard NaN exactly as `max_sse`/`min_sse` do), with the near
        /// and far plane rows of axis `a` at float offsets `near[a]` and `far[a]` from the
        /// first row: `8 · (2a + near_is_max[a])` and the other row of the axis.
        #[inline(always)]
        fn slabs(
            &self,
            node: &WideNode8,
            near: [usize; 3],
            far: [usize; 3],
            tfar: f32,
        ) -> LaneHitsN<WIDTH8> {
            lane_hits(self.slabs_raw(node, near, far, tfar))
        }

        /// [`Broadcast::slabs`] left in registers: the entry distances and the entered lanes
        /// (all ones).
        #[inline(always)]
        fn slabs_raw(
            &self,
            node: &WideNode8,
            near: [usize; 3],
            far: [usize; 3],
            tfar: f32,
        ) -> (__m256, __m256) {
            debug_assert!((0..3).all(|a| near[a] / 16 == a && far[a] / 16 == a));
            debug_assert!((0..3).all(|a| near[a].is_multiple_of(8) && far[a] == near[a] ^ 8));
            // SAFETY: only reached with AVX2 enabled and detected. `planes` is six rows of
            // eight floats, contiguous, in a 64-byte aligned node; `near[a]` and `far[a]` are
            // the two rows of axis `a` (multiples of 8 below 48, as the callers make them),
            // so each aligned load reads one whole row.
            unsafe {
                let rows = node.planes.as_ptr().cast::<f32>();
                let mut t0 = self.tnear;
                let mut t1 = _mm256_set1_ps(tfar);
                for a in 0..3 {
                    let np = _mm256_load_ps(rows.add(near[a]));
                    let fp = _mm256_load_ps(rows.add(far[a]));
                    let tn = _mm256_mul_ps(_mm256_sub_ps(np, self.org[a]), self.inv[a]);
                    let tf = _mm256_mul_ps(_mm256_sub_ps(fp, self.org[a]), self.inv_far[a]);
                    t0 = _mm256_max_ps(tn, t0);
                    t1 = _mm256_min_ps(tf, t1);
                }
                (t0, _mm256_cmp_ps::<_CMP_LE_OQ>(t0, t1))
            }
        }
    }

    /// The AVX2 node test of any ray: the near and far rows are per-ray offsets.
    #[derive(Clone, Copy, Debug)]
    pub struct AvxRay {
        b: Broadcast,
        /// Per axis, the float offsets of the near and the far plane's rows (see
        /// `Broadcast::slabs`).
        near: [usize; 3],
        far: [usize; 3],
    }

    impl AvxRay {
        /// The constants of `r`. Only call with AVX2 present (inlined into an AVX2 function).
        #[inline(always)]
        pub fn new(r: &PreRay) -> AvxRay {
            AvxRay {
                b: Broadcast::new(r),
                near: [0, 1, 2].map(|a| 8 * (2 * a + r.near_is_max[a] as usize)),
                far: [0, 1, 2].map(|a| 8 * (2 * a + !r.near_is_max[a] as usize)),
            }
        }

        /// The low four lanes of the origin and of `tnear`.
        #[inline(always)]
        pub fn low_org_tnear(&self) -> ([__m128; 3], __m128) {
            self.b.low_org_tnear()
        }

        /// The eight slab tests of `node` up to `tfar`.
        #[inline(always)]
        pub fn test(&self, node: &WideNode8, tfar: f32) -> LaneHitsN<WIDTH8> {
            self.b.slabs(node, self.near, self.far, tfar)
        }

        /// [`AvxRay::test`] left in registers: entry distances, entered lanes (all ones).
        #[inline(always)]
        pub fn test_raw(&self, node: &WideNode8, tfar: f32) -> (__m256, __m256) {
            self.b.slabs_raw(node, self.near, self.far, tfar)
        }
    }

    /// The AVX2 node test of the rays of one octant `O` (bit `a` set: the direction's sign
    /// bit `a` is set, the near plane of axis `a` is the box's maximum): the near and far
    /// rows are constants of the kernel, folded into its loads, not per-ray offsets.
    #[derive(Clone, Copy, Debug)]
    pub struct OctRay<const O: usize> {
        b: Broadcast,
    }

    impl<const O: usize> OctRay<O> {
        const NEAR: [usize; 3] = [
            8 * (O & 1),
            8 * (2 + ((O >> 1) & 1)),
            8 * (4 + ((O >> 2) & 1)),
        ];
        const FAR: [usize; 3] = [
            8 * (1 - (O & 1)),
            8 * (3 - ((O >> 1) & 1)),
            8 * (5 - ((O >> 2) & 1)),
        ];

        /// The constants of `r`, whose octant must be `O`. Only call with AVX2 present.
        #[inline(always)]
        pub fn new(r: &PreRay) -> OctRay<O> {
            debug_assert_eq!(super::octant(r), O);
            OctRay {
                b: Broadcast::new(r),
            }
        }

        /// The low four lanes of the origin and of `tnear`.
        #[inline(always)]
        pub fn low_org_tnear(&self) -> ([__m128; 3], __m128) {
            self.b.low_org_tnear()
        }

        /// The eight slab tests of `node` up to `tfar` (those of [`AvxRay::test`]).
        #[inline(always)]
        pub fn test(&self, node: &WideNode8, tfar: f32) -> LaneHitsN<WIDTH8> {
            self.b.slabs(node, Self::NEAR, Self::FAR, tfar)
        }

        /// [`OctRay::test`] left in registers: the entry distances and the entered lanes (all
        /// ones), for the closest-hit walk's sorted push.
        #[inline(always)]
        pub fn test_raw(&self, node: &WideNode8, tfar: f32) -> (__m256, __m256) {
            self.b.slabs_raw(node, Self::NEAR, Self::FAR, tfar)
        }
    }

    /// The eight-lane test's answer as a mask and an array, from its entry distances and
    /// entered lanes (all ones) in registers. Only call with AVX2 present.
    #[inline(always)]
    pub fn lane_hits((t0, entered): (__m256, __m256)) -> LaneHitsN<WIDTH8> {
        // SAFETY: only reached with AVX2 enabled; the unaligned store writes the 8 floats of
        // `dist`.
        unsafe {
            let mut dist = [0.0f32; 8];
            _mm256_storeu_ps(dist.as_mut_ptr(), t0);
            (_mm256_movemask_ps(entered) as u32, dist)
        }
    }

    /// The leaf flags (bit 31) of the eight child codes of `node`, in one instruction: the
    /// sign bits of the code row read as floats. Only call with AVX2 present.
    #[inline(always)]
    pub fn leaf_mask(node: &WideNode8) -> u32 {
        // SAFETY: only reached with AVX2 enabled; `child` is eight `u32` at byte 192 of a
        // 64-byte aligned node, so the aligned load reads exactly that row.
        unsafe { _mm256_movemask_ps(_mm256_load_ps(node.child.as_ptr().cast::<f32>())) as u32 }
    }

    /// One layer of [`sort8_desc`]: lane `i` meets lane `partner[i]` and keeps the larger
    /// key where bit `i` of `TAKE_MAX` is set (the lower lane of each pair), else the smaller.
    #[inline(always)]
    fn sort_layer<const TAKE_MAX: i32>(k: __m256i, partner: __m256i) -> __m256i {
        // SAFETY: only reached with AVX2 enabled (inlined into an AVX2 function); these
        // intrinsics only compute on registers.
        unsafe {
            let p = _mm256_permutevar8x32_epi32(k, partner);
            _mm256_blend_epi32::<TAKE_MAX>(_mm256_min_epu32(k, p), _mm256_max_epu32(k, p))
        }
    }

    /// The eight unsigned keys of `k` in descending order, without a branch: a network of 19
    /// comparators in six layers (the fewest of either for eight inputs), each layer one lane
    /// permutation, a minimum, a maximum and a blend:
    ///
    /// ```text
    ///   layer 1: (0,2) (1,3) (4,6) (5,7)     layer 4: (2,4) (3,5)
    ///   layer 2: (0,4) (1,5) (2,6) (3,7)     layer 5: (1,4) (3,6)
    ///   layer 3: (0,1) (2,3) (4,5) (6,7)     layer 6: (1,2) (3,4) (5,6)
    /// ```
    ///
    /// (the larger key goes to the lower lane of each pair). Exhaustively tested on the 256
    /// inputs of zeros and ones, which by the 0-1 principle proves it sorts every input. Only
    /// call with AVX2 present.
    #[inline(always)]
    pub fn sort8_desc(k: __m256i) -> __m256i {
        // SAFETY: only reached with AVX2 enabled; `_mm256_setr_epi32` only builds constants.
        unsafe {
            let k = sort_layer::<0b0011_0011>(k, _mm256_setr_epi32(2, 3, 0, 1, 6, 7, 4, 5));
            let k = sort_layer::<0b0000_1111>(k, _mm256_setr_epi32(4, 5, 6, 7, 0, 1, 2, 3));
            let k = sort_layer::<0b0101_0101>(k, _mm256_setr_epi32(1, 0, 3, 2, 5, 4, 7, 6));
            let k = sort_layer::<0b0000_1100>(k, _mm256_setr_epi32(0, 1, 4, 5, 2, 3, 6, 7));
            let k = sort_layer::<0b0000_1010>(k, _mm256_setr_epi32(0, 4, 2, 6, 1, 5, 3, 7));
            sort_layer::<0b0010_1010>(k, _mm256_setr_epi32(0, 2, 1, 4, 3, 6, 5, 7))
        }
    }

    /// [`sort8_desc`] on an array (for the tests).
    #[cfg(test)]
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn sort8_desc_array(keys: [u32; 8]) -> [u32; 8] {
        let mut out = [0u32; 8];
        // SAFETY: AVX2 is enabled here; the unaligned load and store read and write the 8
        // keys of `keys` and `out`.
        unsafe {
            let k = _mm256_loadu_si256(keys.as_ptr().cast());
            _mm256_storeu_si256(out.as_mut_ptr().cast(), sort8_desc(k));
        }
        out
    }

    /// One AVX2 node test (for the equality tests).
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn node_test(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
        AvxRay::new(r).test(node, tfar)
    }

    /// One AVX2 node test of the kernel of `r`'s octant (for the equality tests).
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn node_test_octant(node: &WideNode8, r: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
        by_octant!(super::octant(r), O => OctRay::<O>::new(r).test(node, tfar))
    }
}

#[cfg(target_arch = "x86_64")]
mod sse {
    use core::arch::x86_64::*;

    use super::{LaneHits, PacketHits};
    use crate::trace::intersect::PreRay;
    use crate::trace::wide::{TriPacket, WideNode};

    /// Ray constants broadcast to all lanes.
    #[derive(Clone, Copy, Debug)]
    pub struct SseRay {
        org: [__m128; 3],
        inv: [__m128; 3],
        inv_far: [__m128; 3],
        /// Plane row of the near plane per axis (`2a` or `2a + 1`).
        near: [usize; 3],
        tnear: __m128,
        /// The permuted axes of the watertight test, a byte each (`kx | ky << 8 | kz << 16`):
        /// read field by field from the ray (copied as an array, a 16-byte load of three
        /// 8-byte stores missed store forwarding in every ray's set-up).
        k: u32,
        shear: [__m128; 3],
    }

    impl SseRay {
        #[inline(always)]
        pub fn new(r: &PreRay) -> SseRay {
            // SAFETY: SSE is part of the x86-64 baseline; these intrinsics only move values.
            let (org, tnear) = unsafe { (r.org.map(|o| _mm_set1_ps(o)), _mm_set1_ps(r.tnear)) };
            SseRay::with(r, org, tnear)
        }

        /// The constants of `r` with the origin and `tnear` already broadcast (by the AVX2
        /// test, whose low lanes they are).
        #[inline(always)]
        pub fn with(r: &PreRay, org: [__m128; 3], tnear: __m128) -> SseRay {
            debug_assert!(
                !r.shear[2].is_nan(),
                "packet test of a ray without its constants"
            );
            let near = [0, 1, 2].map(|a| 2 * a + r.near_is_max[a] as usize);
            // SAFETY: SSE is part of the x86-64 baseline; these intrinsics only move values.
            unsafe {
                SseRay {
                    org,
                    inv: r.inv.map(|i| _mm_set1_ps(i)),
                    inv_far: r.inv_far.map(|i| _mm_set1_ps(i)),
                    near,
                    tnear,
                    k: (r.k[0] | r.k[1] << 8 | r.k[2] << 16) as u32,
                    shear: r.shear.map(|x| _mm_set1_ps(x)),
                }
            }
        }

        /// The four slab tests of `node` in one go, operation for operation the same as
        /// `slab_test` (sub, mul by `inv` or `inv_far`, then `max(tn, t0)` / `min(tf, t1)`
        /// whose operand order discards NaN exactly as `max_sse`/`min_sse` do).
        #[inline(always)]
        pub fn test(&self, node: &WideNode, tfar: f32) -> LaneHits {
            self.slabs(|row| &node.planes[row], tfar)
        }

        /// The slab test over plane rows: `plane(2a)` the four minima on axis `a`,
        /// `plane(2a + 1)` the maxima.
        #[inline(always)]
        fn slabs<'p>(&self, plane: impl Fn(usize) -> &'p [f32; 4], tfar: f32) -> LaneHits {
            // SAFETY: SSE is part of the x86-64 baseline. The loads read `[f32; 4]` rows
            // (unaligned loads: the rows come from nodes or packets); the unaligned store
            // writes the 4 floats of `dist`.
            unsafe {
                let mut t0 = self.tnear;
                let mut t1 = _mm_set1_ps(tfar);
                for a in 0..3 {
                    let n = self.near[a];
                    let f = n ^ 1;
                    let np = _mm_loadu_ps(plane(n).as_ptr());
                    let fp = _mm_loadu_ps(plane(f).as_ptr());
                    let tn = _mm_mul_ps(_mm_sub_ps(np, self.org[a]), self.inv[a]);
                    let tf = _mm_mul_ps(_mm_sub_ps(fp, self.org[a]), self.inv_far[a]);
                    t0 = _mm_max_ps(tn, t0);
                    t1 = _mm_min_ps(tf, t1);
                }
                let mask = _mm_movemask_ps(_mm_cmple_ps(t0, t1)) as u32;
                let mut dist = [0.0f32; 4];
                _mm_storeu_ps(dist.as_mut_ptr(), t0);
                (mask, dist)
            }
        }

        /// The watertight test of four triangles, lane for lane the same operations as
        /// `triangle_test`, left in registers: per lane `t`, the two edge functions of
        /// vertices 1 and 2, `det`, the lanes that hit in `[tnear, tmax]` (all ones) and the
        /// lanes with a zero edge function (to be redone by the scalar test, which falls back
        /// to `f64`). Padding lanes (all corners zero) never hit: their `det` is zero.
        #[inline(always)]
        fn raw(&self, p: &TriPacket, tmax: f32) -> RawHits {
            // Axis indices (`PreRay::k`, each below 3); the `min` lets the compiler see the
            // row indices below stay in bounds, so the loads carry no checks (a branch pair
            // per load before: about 30 instructions per packet).
            let [kx, ky, kz] = [0, 8, 16].map(|s| ((self.k >> s & 0xff) as usize).min(2));
            // SAFETY: SSE is part of the x86-64 baseline. Every load reads one `[f32; 4]` row
            // of a 16-byte aligned packet.
            unsafe {
                let rel = |j: usize, a: usize| {
                    _mm_sub_ps(_mm_load_ps(p.v[3 * j + a].as_ptr()), self.org[a])
                };
                let (a_x, a_y, a_z) = (rel(0, kx), rel(0, ky), rel(0, kz));
                let (b_x, b_y, b_z) = (rel(1, kx), rel(1, ky), rel(1, kz));
                let (c_x, c_y, c_z) = (rel(2, kx), rel(2, ky), rel(2, kz));
                let [sx, sy, sz] = self.shear;
                let ax = _mm_sub_ps(a_x, _mm_mul_ps(sx, a_z));
                let ay = _mm_sub_ps(a_y, _mm_mul_ps(sy, a_z));
                let bx = _mm_sub_ps(b_x, _mm_mul_ps(sx, b_z));
                let by = _mm_sub_ps(b_y, _mm_mul_ps(sy, b_z));
                let cx = _mm_sub_ps(c_x, _mm_mul_ps(sx, c_z));
                let cy = _mm_sub_ps(c_y, _mm_mul_ps(sy, c_z));
                let u = _mm_sub_ps(_mm_mul_ps(cx, by), _mm_mul_ps(cy, bx));
                let v = _mm_sub_ps(_mm_mul_ps(ax, cy), _mm_mul_ps(ay, cx));
                let w = _mm_sub_ps(_mm_mul_ps(bx, ay), _mm_mul_ps(by, ax));
                let zero = _mm_setzero_ps();
                let any_zero = _mm_or_ps(
                    _mm_or_ps(_mm_cmpeq_ps(u, zero), _mm_cmpeq_ps(v, zero)),
                    _mm_cmpeq_ps(w, zero),
                );
                let neg = _mm_or_ps(
                    _mm_or_ps(_mm_cmplt_ps(u, zero), _mm_cmplt_ps(v, zero)),
                    _mm_cmplt_ps(w, zero),
                );
                let pos = _mm_or_ps(
                    _mm_or_ps(_mm_cmpgt_ps(u, zero), _mm_cmpgt_ps(v, zero)),
                    _mm_cmpgt_ps(w, zero),
                );
                let det = _mm_add_ps(_mm_add_ps(u, v), w);
                let az = _mm_mul_ps(sz, a_z);
                let bz = _mm_mul_ps(sz, b_z);
                let cz = _mm_mul_ps(sz, c_z);
                let tt = _mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(u, az), _mm_mul_ps(v, bz)),
                    _mm_mul_ps(w, cz),
                );
                let t = _mm_div_ps(tt, det);
                let in_range = _mm_and_ps(
                    _mm_cmpge_ps(t, self.tnear),
                    _mm_cmple_ps(t, _mm_set1_ps(tmax)),
                );
                let ok = _mm_andnot_ps(
                    _mm_or_ps(any_zero, _mm_and_ps(neg, pos)),
                    _mm_and_ps(in_range, _mm_cmpneq_ps(det, zero)),
                );
                RawHits {
                    t,
                    v,
                    w,
                    det,
                    ok,
                    any_zero,
                }
            }
        }

        /// The watertight test of four triangles (see [`SseRay::raw`]) as lane masks and
        /// per-lane arrays.
        #[inline(always)]
        pub fn packet(&self, p: &TriPacket, tmax: f32) -> PacketHits {
            let h = self.raw(p, tmax);
            // SAFETY: SSE is part of the x86-64 baseline; the unaligned stores write 4-float
            // local arrays.
            unsafe {
                let mut out = PacketHits {
                    hit: _mm_movemask_ps(h.ok) as u32,
                    redo: _mm_movemask_ps(h.any_zero) as u32,
                    t: [0.0; 4],
                    v: [0.0; 4],
                    w: [0.0; 4],
                    det: [0.0; 4],
                };
                _mm_storeu_ps(out.t.as_mut_ptr(), h.t);
                _mm_storeu_ps(out.v.as_mut_ptr(), h.v);
                _mm_storeu_ps(out.w.as_mut_ptr(), h.w);
                _mm_storeu_ps(out.det.as_mut_ptr(), h.det);
                out
            }
        }

        /// The nearest hit of the packet's first `real` lanes in `[tnear, tmax]` without a
        /// branch per lane: the smallest `t` of the hit lanes by two shuffled minima, the
        /// lowest id among the lanes that share it. `Err(())` when a real lane has a zero edge
        /// function (the caller redoes the packet lane by lane).
        #[inline(always)]
        pub fn nearest(
            &self,
            p: &TriPacket,
            tmax: f32,
            real: u32,
        ) -> Result<Option<(f32, f32, f32, u32)>, ()> {
            let h = self.raw(p, tmax);
            // SAFETY: SSE is part of the x86-64 baseline; the unaligned stores write 4-float
            // local arrays.
            unsafe {
                if _mm_movemask_ps(h.any_zero) as u32 & real != 0 {
                    return Err(());
                }
                let hit = _mm_movemask_ps(h.ok) as u32 & real;
                if hit == 0 {
                    return Ok(None);
                }
                // Missed lanes read +inf; hit lanes hold a finite t (≤ tmax).
                let inf = _mm_set1_ps(f32::INFINITY);
                let tm = _mm_or_ps(_mm_and_ps(h.ok, h.t), _mm_andnot_ps(h.ok, inf));
                let m1 = _mm_min_ps(tm, _mm_shuffle_ps::<0b10_11_00_01>(tm, tm));
                let m2 = _mm_min_ps(m1, _mm_shuffle_ps::<0b01_00_11_10>(m1, m1));
                let ties = _mm_movemask_ps(_mm_cmpeq_ps(tm, m2)) as u32 & hit;
                let mut lane = ties.trailing_zeros() as usize;
                let mut rest = ties & (ties - 1);
                while rest != 0 {
                    let l = rest.trailing_zeros() as usize;
                    rest &= rest - 1;
                    if p.id[l] < p.id[lane] {
                        lane = l;
                    }
                }
                // The lane's own `t` (the minimum's bits may be the other zero's).
                let mut t = [0.0f32; 4];
                let mut v = [0.0f32; 4];
                let mut w = [0.0f32; 4];
                let mut det = [0.0f32; 4];
                _mm_storeu_ps(t.as_mut_ptr(), h.t);
                _mm_storeu_ps(v.as_mut_ptr(), h.v);
                _mm_storeu_ps(w.as_mut_ptr(), h.w);
                _mm_storeu_ps(det.as_mut_ptr(), h.det);
                let inv_det = 1.0 / det[lane];
                Ok(Some((
                    t[lane],
                    v[lane] * inv_det,
                    w[lane] * inv_det,
                    p.id[lane],
                )))
            }
        }

        /// True when a real lane of the packet hits in `[tnear, tmax]`; `None` when none
        /// does but a real lane has a zero edge function (to be redone lane by lane).
        #[inline(always)]
        pub fn any(&self, p: &TriPacket, tmax: f32, real: u32) -> Option<bool> {
            let h = self.raw(p, tmax);
            // SAFETY: SSE is part of the x86-64 baseline; only masks are read.
            unsafe {
                if _mm_movemask_ps(h.ok) as u32 & real != 0 {
                    return Some(true);
                }
                if _mm_movemask_ps(h.any_zero) as u32 & real != 0 {
                    return None;
                }
            }
            Some(false)
        }
    }

    /// What [`SseRay::raw`] leaves in registers.
    #[derive(Clone, Copy)]
    struct RawHits {
        t: __m128,
        v: __m128,
        w: __m128,
        det: __m128,
        ok: __m128,
        any_zero: __m128,
    }
}

/// The SIMD triangle test's answer for one packet (see `SseRay::packet`).
#[derive(Clone, Copy, Debug)]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
struct PacketHits {
    hit: u32,
    redo: u32,
    t: [f32; WIDTH],
    v: [f32; WIDTH],
    w: [f32; WIDTH],
    det: [f32; WIDTH],
}

/// The per-ray triangle packet test of one traversal (4-wide, SSE or scalar).
trait PacketTest {
    /// The SSE packet test, or `None` for the scalar one.
    #[cfg(target_arch = "x86_64")]
    fn sse(&self) -> Option<&sse::SseRay>;

    /// Call `f(t, u, v, id)` for every triangle of packet `p` hit in `[tnear, tmax]`, in
    /// lane order; the same hits, bit for bit, for every tester.
    #[inline(always)]
    fn packet(&self, r: &PreRay, p: &TriPacket, tmax: f32, mut f: impl FnMut(f32, f32, f32, u32)) {
        #[cfg(target_arch = "x86_64")]
        if let Some(s) = self.sse() {
            let real = (1u32 << p.count) - 1;
            let h = s.packet(p, tmax);
            let mut m = (h.hit | h.redo) & real;
            while m != 0 {
                let lane = m.trailing_zeros() as usize;
                m &= m - 1;
                if h.redo & (1 << lane) != 0 {
                    if let Some((t, u, v)) = redo_lane(r, p, lane, tmax) {
                        f(t, u, v, p.id[lane]);
                    }
                } else {
                    let inv_det = 1.0 / h.det[lane];
                    f(
                        h.t[lane],
                        h.v[lane] * inv_det,
                        h.w[lane] * inv_det,
                        p.id[lane],
                    );
                }
            }
            return;
        }
        for lane in 0..p.count as usize {
            if let Some((t, u, v)) = triangle_test(r, &p.lane(lane), tmax) {
                f(t, u, v, p.id[lane]);
            }
        }
    }

    /// Make the nearest hit of packet `p` up to `best.t` the best hit when it beats it
    /// (`better`, or the first hit when `found` is unset): the same answer as offering every
    /// hit of [`PacketTest::packet`] in lane order, without a branch per lane on SSE.
    #[inline(always)]
    fn closest_packet(&self, r: &PreRay, p: &TriPacket, best: &mut Best, found: &mut bool) {
        #[cfg(target_arch = "x86_64")]
        if let Some(s) = self.sse() {
            match s.nearest(p, best.t, (1u32 << p.count) - 1) {
                Ok(None) => return,
                Ok(Some((t, u, v, prim))) => return offer(best, found, t, u, v, prim),
                // A zero edge function: lane by lane below (rare).
                Err(()) => {}
            }
        }
        let tmax = best.t;
        self.packet(r, p, tmax, |t, u, v, prim| {
            offer(best, found, t, u, v, prim)
        });
    }

    /// True when a triangle of packet `p` is hit in `[tnear, tmax]` (what
    /// [`PacketTest::packet`] would report at least once).
    #[inline(always)]
    fn any_packet(&self, r: &PreRay, p: &TriPacket, tmax: f32) -> bool {
        #[cfg(target_arch = "x86_64")]
        if let Some(s) = self.sse() {
            if let Some(hit) = s.any(p, tmax, (1u32 << p.count) - 1) {
                return hit;
            }
        }
        let mut hit = false;
        self.packet(r, p, tmax, |_, _, _, _| hit = true);
        hit
    }
}

/// The per-ray node test of one traversal, `W` wide (the triangle packet test is a
/// [`PacketTest`]).
trait Lanes<const W: usize> {
    /// Test the `W` child boxes of `node` against `[tnear, tfar]`.
    fn test(&self, node: &WideNodeN<W>, r: &PreRay, tfar: f32) -> LaneHitsN<W>;

    /// Bit `i` set when child `i` of `node` is a leaf (or unused), as [`leaf_mask`].
    #[inline(always)]
    fn leaves(&self, node: &WideNodeN<W>) -> u32 {
        leaf_mask(node)
    }

    /// The closest-hit walk of this tester over `nodes` (the tree of width `W` in `bvh`):
    /// [`closest_walk`]; the 8-wide testers take [`closest_walk_sorted`].
    #[inline(always)]
    fn closest_walk<const STATS: bool>(
        &self,
        bvh: &WideBvh,
        nodes: &[WideNodeN<W>],
        r: &PreRay,
        stats: &mut TraceStats,
        leaf: &mut impl LeafVisit<f32>,
    ) where
        Self: Sized,
    {
        closest_walk::<W, STATS, Self>(bvh, nodes, r, self, stats, leaf)
    }

    /// The any-hit walk of this tester over `nodes`: [`occluded_walk`]; the 8-wide SIMD
    /// testers take [`occluded_walk_compact`], which visits in the same order.
    #[inline(always)]
    fn occluded_walk<const STATS: bool>(
        &self,
        bvh: &WideBvh,
        nodes: &[WideNodeN<W>],
        r: &PreRay,
        stats: &mut TraceStats,
        leaf: &mut impl LeafVisit<bool>,
    ) -> bool
    where
        Self: Sized,
    {
        occluded_walk::<W, STATS, Self>(bvh, nodes, r, self, stats, leaf)
    }
}

/// What a walk does at a leaf it enters: test the leaf's primitives, and say how the walk
/// goes on (the best distance so far, or whether a hit ends it). A struct rather than a
/// closure so that its body is inlined into the walk (and its target features).
trait LeafVisit<R> {
    /// Visit leaf `code`.
    fn visit(&mut self, code: u32, stats: &mut TraceStats) -> R;

    /// [`LeafVisit::visit`] inlined into the walk where a visitor keeps its body out of line
    /// elsewhere (see `ClosestTris`).
    #[inline(always)]
    fn visit_inlined(&mut self, code: u32, stats: &mut TraceStats) -> R {
        self.visit(code, stats)
    }
}

/// A closure as a leaf visitor (the item trees', whose visits call out anyway).
struct FnLeaf<F>(F);

impl<R, F: FnMut(u32, &mut TraceStats) -> R> LeafVisit<R> for FnLeaf<F> {
    #[inline(always)]
    fn visit(&mut self, code: u32, stats: &mut TraceStats) -> R {
        (self.0)(code, stats)
    }
}

/// The closest-hit visitor of triangle leaves: every packet of the leaf tested up to the best
/// distance so far; returns the new best distance.
struct ClosestTris<'a, P, const STATS: bool> {
    bvh: &'a WideBvh,
    r: &'a PreRay,
    lanes: &'a P,
    best: Best,
    found: bool,
}

impl<'a, P: PacketTest, const STATS: bool> ClosestTris<'a, P, STATS> {
    /// No hit yet: the best distance is the ray's `tfar`.
    #[inline(always)]
    fn new(bvh: &'a WideBvh, r: &'a PreRay, lanes: &'a P) -> Self {
        ClosestTris {
            bvh,
            r,
            lanes,
            best: Best {
                t: r.tfar,
                prim: u32::MAX,
                u: 0.0,
                v: 0.0,
            },
            found: false,
        }
    }

    /// The best hit found.
    #[inline(always)]
    fn hit(&self) -> Option<Hit> {
        let b = self.best;
        self.found.then_some(Hit::triangle(b.t, b.prim, b.u, b.v))
    }
}

impl<P: PacketTest, const STATS: bool> LeafVisit<f32> for ClosestTris<'_, P, STATS> {
    // Out of line in the 4-wide walk: measured, its closest-hit loop with the packet test
    // inlined ran primary rays 3-13% slower (pbrt-bathroom, stanford-dragon; 0.98x again
    // with the sorted 8-wide walk in place), the any-hit walk gains from it.
    #[inline(never)]
    fn visit(&mut self, code: u32, stats: &mut TraceStats) -> f32 {
        self.visit_inlined(code, stats)
    }

    // Inlined in the sorted 8-wide walk (`closest_walk_sorted`): primary 1.025x on
    // pbrt-bathroom, 1.031x on stanford-dragon, 1.021x on sionna-san-francisco (alternating
    // runs), where the call had to reload the ray's eight-lane constants after every leaf.
    #[inline(always)]
    fn visit_inlined(&mut self, code: u32, stats: &mut TraceStats) -> f32 {
        let mut pi = (code & !LEAF) as usize;
        loop {
            let p = &self.bvh.packets[pi];
            if STATS {
                stats.tri_tests += p.count as u64;
            }
            self.lanes
                .closest_packet(self.r, p, &mut self.best, &mut self.found);
            if p.last != 0 {
                break;
            }
            pi += 1;
        }
        self.best.t
    }
}

/// The any-hit visitor of triangle leaves: true when a triangle of the leaf is hit in
/// `[tnear, tfar]`.
struct OccludedTris<'a, P, const STATS: bool> {
    bvh: &'a WideBvh,
    r: &'a PreRay,
    lanes: &'a P,
}

impl<P: PacketTest, const STATS: bool> LeafVisit<bool> for OccludedTris<'_, P, STATS> {
    #[inline(always)]
    fn visit(&mut self, code: u32, stats: &mut TraceStats) -> bool {
        let mut pi = (code & !LEAF) as usize;
        loop {
            let p = &self.bvh.packets[pi];
            if STATS {
                stats.tri_tests += p.count as u64;
            }
            if self.lanes.any_packet(self.r, p, self.r.tfar) {
                return true;
            }
            if p.last != 0 {
                return false;
            }
            pi += 1;
        }
    }
}

/// The scalar test of one packet lane whose SIMD edge function was zero (rare), kept out of
/// line so the hot loops stay small.
#[cfg(target_arch = "x86_64")]
#[cold]
#[inline(never)]
fn redo_lane(r: &PreRay, p: &TriPacket, lane: usize, tmax: f32) -> Option<(f32, f32, f32)> {
    triangle_test(r, &p.lane(lane), tmax)
}

/// The scalar reference tests, for either width.
struct ScalarLanes;

impl<const W: usize> Lanes<W> for ScalarLanes {
    #[inline(always)]
    fn test(&self, node: &WideNodeN<W>, r: &PreRay, tfar: f32) -> LaneHitsN<W> {
        node_test_scalar(node, r, tfar)
    }

    /// On the 8-wide tree the reference of the 8-wide kernels walks as they do.
    #[inline(always)]
    fn closest_walk<const STATS: bool>(
        &self,
        bvh: &WideBvh,
        nodes: &[WideNodeN<W>],
        r: &PreRay,
        stats: &mut TraceStats,
        leaf: &mut impl LeafVisit<f32>,
    ) {
        if W == WIDTH8 {
            closest_walk_sorted::<STATS, _>(bvh, r, self, stats, leaf)
        } else {
            closest_walk::<W, STATS, Self>(bvh, nodes, r, self, stats, leaf)
        }
    }
}

impl PacketTest for ScalarLanes {
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn sse(&self) -> Option<&sse::SseRay> {
        None
    }
}

/// SSE node and packet tests of the 4-wide tree.
#[cfg(target_arch = "x86_64")]
struct SseLanes(sse::SseRay);

#[cfg(target_arch = "x86_64")]
impl Lanes<WIDTH> for SseLanes {
    #[inline(always)]
    fn test(&self, node: &WideNode, _: &PreRay, tfar: f32) -> LaneHits {
        self.0.test(node, tfar)
    }
}

#[cfg(target_arch = "x86_64")]
impl SseLanes {
    /// The packet test of `r` (its triangle constants made) beside the 8-wide node test
    /// `lanes` of the same ray, sharing its broadcast origin and `tnear` registers. Only call
    /// with the wide test's features present (inlined into a function compiled with them).
    #[inline(always)]
    fn of_wide<T: WideRay>(r: &PreRay, lanes: &WideLanes<T>) -> SseLanes {
        let (org, tnear) = lanes.0.low_org_tnear();
        SseLanes(sse::SseRay::with(r, org, tnear))
    }
}

#[cfg(target_arch = "x86_64")]
impl PacketTest for SseLanes {
    #[inline(always)]
    fn sse(&self) -> Option<&sse::SseRay> {
        Some(&self.0)
    }
}

/// The per-ray constants of an 8-wide SIMD node test (AVX2 or AVX-512), as [`WideLanes`]
/// uses them. Only made and used inside functions compiled with the test's features.
#[cfg(target_arch = "x86_64")]
trait WideRay {
    /// The broadcast constants of `r`.
    fn new(r: &PreRay) -> Self;
    /// The low four lanes of the origin and of `tnear` (what the SSE tests broadcast).
    fn low_org_tnear(&self) -> ([core::arch::x86_64::__m128; 3], core::arch::x86_64::__m128);
    /// The eight slab tests of `node` up to `tfar`.
    fn test(&self, node: &WideNode8, tfar: f32) -> LaneHitsN<WIDTH8>;
    /// [`WideRay::test`] left in registers: entry distances, entered lanes (all ones).
    fn test_raw(
        &self,
        node: &WideNode8,
        tfar: f32,
    ) -> (core::arch::x86_64::__m256, core::arch::x86_64::__m256);
}

#[cfg(target_arch = "x86_64")]
macro_rules! wide_ray {
    ([$($gen:tt)*] $t:ty) => {
        impl<$($gen)*> WideRay for $t {
            #[inline(always)]
            fn new(r: &PreRay) -> Self {
                <$t>::new(r)
            }
            #[inline(always)]
            fn low_org_tnear(
                &self,
            ) -> ([core::arch::x86_64::__m128; 3], core::arch::x86_64::__m128) {
                <$t>::low_org_tnear(self)
            }
            #[inline(always)]
            fn test(&self, node: &WideNode8, tfar: f32) -> LaneHitsN<WIDTH8> {
                <$t>::test(self, node, tfar)
            }
            #[inline(always)]
            fn test_raw(
                &self,
                node: &WideNode8,
                tfar: f32,
            ) -> (core::arch::x86_64::__m256, core::arch::x86_64::__m256) {
                <$t>::test_raw(self, node, tfar)
            }
        }
    };
}
#[cfg(target_arch = "x86_64")]
wide_ray!([] avx::AvxRay);
#[cfg(target_arch = "x86_64")]
wide_ray!([const O: usize] avx::OctRay<O>);
#[cfg(target_arch = "x86_64")]
wide_ray!([] avx512::Avx512Ray);

/// The octant of `r`: bit `a` set when the near plane of axis `a` is the box's maximum.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn octant(r: &PreRay) -> usize {
    r.near_is_max[0] as usize | (r.near_is_max[1] as usize) << 1 | (r.near_is_max[2] as usize) << 2
}

/// `(PreRay, tests)`: the constants of `$ray`, and a kernel's tests `$lanes` made from them
/// (as `$r`) before the ray itself is stored anywhere, so they are built from registers. Read
/// back from the stack, ray fields written by narrower stores than the reads (the near planes'
/// flags, the permuted axes) missed store forwarding in every ray's set-up; without that,
/// 8-wide AVX2 tracing ran 1.01-1.05x as fast on pbrt-bathroom's primary rays, 1.02-1.06x on
/// its AO rays, 1.02-1.035x and 1.03x on stanford-dragon's, 1.01x on sionna-san-francisco's
/// (alternating runs; the SSE kernels within noise). A macro, not a function taking a
/// closure or a constructor: that form traced pbrt-bathroom at 0.73x.
#[cfg(target_arch = "x86_64")]
macro_rules! prepare {
    ($ray:expr, $r:ident => $lanes:expr) => {{
        let pre = PreRay::new($ray);
        let l = {
            let $r = &pre;
            $lanes
        };
        (pre, l)
    }};
    // The box constants alone (`PreRay::boxes`), for the 8-wide SIMD kernels.
    (boxes $ray:expr, $r:ident => $lanes:expr) => {{
        let pre = PreRay::boxes($ray);
        let l = {
            let $r = &pre;
            $lanes
        };
        (pre, l)
    }};
}

/// The octant [`PreRay::new`] gives `ray` (see [`octant`]): the direction's sign bits.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn ray_octant(ray: &Ray) -> usize {
    let d = ray.dir;
    d.x.is_sign_negative() as usize
        | (d.y.is_sign_negative() as usize) << 1
        | (d.z.is_sign_negative() as usize) << 2
}

/// [`closest`] for the rays of octant `O` with the AVX2 node test.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline(never)]
unsafe fn closest_oct<const O: usize, const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Option<Hit> {
    // The ray's constants are made here, next to their use (see `prepare!`).
    let (r, l) = prepare!(boxes ray, r => WideLanes::<avx::OctRay<O>>::new(r));
    closest_wide::<STATS, _>(bvh, ray, &r, &l, stats)
}

/// Capacity of a [`Stack`]: the bound [`WideBvh::from_bvh2`] proved for either tree, plus the
/// seven slots past the top that a push of eight lanes writes.
const STACK_ROWS: usize = STACK_CAPACITY8 + WIDTH8 - 1;

/// The traversal stack of every walk: child codes and their entry distances as two rows, so
/// that the 8-wide walks store eight of either by one instruction.
struct Stack {
    codes: [MaybeUninit<u32>; STACK_ROWS],
    dists: [MaybeUninit<f32>; STACK_ROWS],
    len: usize,
}

impl Stack {
    #[inline(always)]
    fn new() -> Stack {
        // SAFETY: arrays of `MaybeUninit` need no initialisation. (Built this way, not as
        // `[MaybeUninit::uninit(); N]`, which the compiler was seen to zero with a memset of
        // the whole stack on every ray.)
        unsafe {
            Stack {
                codes: MaybeUninit::<[MaybeUninit<u32>; STACK_ROWS]>::uninit().assume_init(),
                dists: MaybeUninit::<[MaybeUninit<f32>; STACK_ROWS]>::uninit().assume_init(),
                len: 0,
            }
        }
    }

    /// Push one entry. Never fails on a tree from `from_bvh2` (depth ≤ MAX_DEPTH); the slots
    /// are bounds-checked regardless, so a broken invariant panics instead of corrupting.
    #[inline(always)]
    fn push(&mut self, code: u32, dist: f32) {
        self.codes[self.len] = MaybeUninit::new(code);
        self.dists[self.len] = MaybeUninit::new(dist);
        self.len += 1;
    }

    /// Pop an entry: code and distance.
    #[inline(always)]
    fn pop(&mut self) -> Option<(u32, f32)> {
        let code = self.pop_code()?;
        // SAFETY: the distance slot was written with the code (the walks that pop distances
        // push both rows).
        Some((code, unsafe { self.dists[self.len].assume_init() }))
    }

    /// Pop a code alone (the any-hit walks push no distances).
    #[inline(always)]
    fn pop_code(&mut self) -> Option<u32> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        // SAFETY: every code slot below the old `len` was written by a push before being
        // counted.
        Some(unsafe { self.codes[self.len].assume_init() })
    }
}

/// The sort key of an entered child in [`closest_walk_sorted`] (0 for a child not entered):
///
/// ```text
///   bit 31 ....................................... 4    3    2 1 0
///   [ entry distance (f32 bits, >= 0), low 4 cleared ] [ 1 ] [ lane ]
/// ```
///
/// Non-negative floats order as their bits do; clearing the low bits rounds the distance
/// toward zero, so the distance a key stands for ([`key_dist`]) never exceeds the entry and
/// culling by it never drops a child the exact distance would keep. The lane makes every key
/// of a node distinct (equal distances: lower lane first) and names the child.
#[inline(always)]
fn sort_key(dist: f32, lane: usize) -> u32 {
    (dist.to_bits() & !15) | 8 | lane as u32
}

/// The distance a [`sort_key`] stands for.
#[inline(always)]
fn key_dist(key: u32) -> f32 {
    f32::from_bits(key & !15)
}

/// One node of [`closest_walk_sorted`]: test `node`'s children up to `tfar`; with one entered,
/// return it and its entry distance; with more, push all but the nearest in descending order
/// of [`sort_key`] (the farthest deepest) and return the nearest with its key's distance;
/// `None` when none is entered. Every tester does exactly what the scalar reference does.
trait SortedStep {
    /// The step at `node` (see the trait).
    fn step(
        &self,
        node: &WideNode8,
        r: &PreRay,
        tfar: f32,
        stack: &mut Stack,
    ) -> Option<(u32, f32)>;
}

impl SortedStep for ScalarLanes {
    #[inline(always)]
    fn step(
        &self,
        node: &WideNode8,
        r: &PreRay,
        tfar: f32,
        stack: &mut Stack,
    ) -> Option<(u32, f32)> {
        let (mask, dist) = node_test_scalar::<WIDTH8>(node, r, tfar);
        match mask.count_ones() {
            0 => None,
            1 => {
                let lane = mask.trailing_zeros() as usize;
                Some((node.child[lane], dist[lane]))
            }
            n => {
                let mut keys: [u32; WIDTH8] = core::array::from_fn(|i| {
                    if mask >> i & 1 != 0 {
                        sort_key(dist[i], i)
                    } else {
                        0
                    }
                });
                keys.sort_unstable_by(|a, b| b.cmp(a));
                let n = n as usize;
                for &k in &keys[..n - 1] {
                    stack.push(node.child[(k & 7) as usize], key_dist(k));
                }
                let k = keys[n - 1];
                Some((node.child[(k & 7) as usize], key_dist(k)))
            }
        }
    }
}

/// [`SortedStep`] of the 8-wide SIMD tests, from their distances and entered lanes left in
/// registers. Only call with AVX2 present (inlined into an AVX2 function).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn sorted_step_simd(
    node: &WideNode8,
    (t0, entered): (core::arch::x86_64::__m256, core::arch::x86_64::__m256),
    stack: &mut Stack,
) -> Option<(u32, f32)> {
    use core::arch::x86_64::*;
    // SAFETY: only reached with AVX2 enabled; the intrinsics compute on registers, the
    // aligned load reads the node's 32-byte row of child codes (byte 192 of a 64-byte aligned
    // node), and the two unaligned stores write slots `len..len + 8` of the stack's rows, in
    // bounds by the check before them.
    unsafe {
        let mask = _mm256_movemask_ps(entered) as u32;
        if mask == 0 {
            return None;
        }
        if mask & (mask - 1) == 0 {
            let lane = mask.trailing_zeros() as usize;
            let mut dist = [0.0f32; WIDTH8];
            _mm256_storeu_ps(dist.as_mut_ptr(), t0);
            return Some((node.child[lane], dist[lane]));
        }
        // `sort_key` on every lane, 0 where not entered.
        let entered = _mm256_castps_si256(entered);
        let rounded = _mm256_and_si256(_mm256_castps_si256(t0), _mm256_set1_epi32(!15));
        let lanes = _mm256_setr_epi32(8, 9, 10, 11, 12, 13, 14, 15);
        let keys = _mm256_and_si256(_mm256_or_si256(rounded, lanes), entered);
        // The nearest: the smallest entered key (the others read as all ones here), by a
        // horizontal minimum that runs beside the sort instead of after it.
        let k = _mm256_or_si256(keys, _mm256_xor_si256(entered, _mm256_set1_epi32(-1)));
        let k = _mm256_min_epu32(k, _mm256_shuffle_epi32::<0b10_11_00_01>(k));
        let k = _mm256_min_epu32(k, _mm256_shuffle_epi32::<0b01_00_11_10>(k));
        let k = _mm256_min_epu32(k, _mm256_permute2x128_si256::<1>(k, k));
        let nearest = _mm256_cvtsi256_si32(k) as u32;
        let sorted = avx::sort8_desc(keys);
        let order = _mm256_and_si256(sorted, _mm256_set1_epi32(7));
        let children = _mm256_load_si256(node.child.as_ptr().cast());
        let len = stack.len;
        assert!(len + WIDTH8 <= STACK_ROWS, "traversal stack overflow");
        _mm256_storeu_si256(
            stack.codes.as_mut_ptr().add(len).cast(),
            _mm256_permutevar8x32_epi32(children, order),
        );
        _mm256_storeu_si256(
            stack.dists.as_mut_ptr().add(len).cast(),
            _mm256_and_si256(sorted, _mm256_set1_epi32(!15)),
        );
        stack.len = len + mask.count_ones() as usize - 1;
        Some((node.child[(nearest & 7) as usize], key_dist(nearest)))
    }
}

#[cfg(target_arch = "x86_64")]
impl<T: WideRay> SortedStep for WideLanes<T> {
    #[inline(always)]
    fn step(
        &self,
        node: &WideNode8,
        _: &PreRay,
        tfar: f32,
        stack: &mut Stack,
    ) -> Option<(u32, f32)> {
        sorted_step_simd(node, self.0.test_raw(node, tfar), stack)
    }
}

/// The closest-hit walk of the 8-wide tree, of triangles or of items (AVX2, AVX-512, and
/// their scalar reference; chosen by [`Lanes::closest_walk`]): every entered child, leaf or
/// inner node, goes through one stack in order of entry distance ([`sort_key`]), sorted
/// without a branch by the SIMD kernels ([`avx::sort8_desc`] on the eight keys, the child
/// codes permuted alike, both rows stored whole at the top of the stack, which then grows by
/// the number entered minus one). The nearest child is visited next; one entered child, the
/// common case, is followed without sorting. A popped entry is skipped when its distance
/// exceeds the best hit so far (with the rounding slack); a leaf is tested where it is popped,
/// its test inlined here (see `ClosestTris`).
///
/// Measured against the walk it replaced (leaves tested where entered, nearest first, before
/// the inner children, which were sorted by insertion), alternating runs, 8-wide quality
/// trees: primary rays 1.063x on pbrt-bathroom, 1.047x on sionna-san-francisco, 1.006x on
/// stanford-dragon; bounce rays 1.25x (pbrt-bathroom), 1.06x (stanford-dragon); triangle
/// tests per primary ray 5.78 -> 4.97 on pbrt-bathroom (leaves now wait behind nearer inner
/// nodes), node tests unchanged. Branch-simulated (cachegrind), the old walk mispredicted
/// about 4.6 branches per primary ray, most on how many children and leaves were entered.
/// Every node through the sort (no one-child shortcut): 0.89x. Fetching the second nearest's
/// lines ahead: no gain.
#[inline(always)]
fn closest_walk_sorted<const STATS: bool, S: SortedStep>(
    bvh: &WideBvh,
    r: &PreRay,
    lanes: &S,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<f32>,
) {
    let abs = abs_slack(bvh, r);
    let cull = slack(r.tfar, abs);
    let mut stack = Stack::new();
    closest_walk_sorted_from::<STATS, S>(
        bvh,
        r,
        lanes,
        stats,
        leaf,
        &mut stack,
        (0, r.tnear),
        [cull, abs],
    );
}

/// [`closest_walk_sorted`] from entry `code` at distance `d` with `stack` below it, culling
/// at `cull` (both slacks applied; `abs` is the absolute one).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn closest_walk_sorted_from<const STATS: bool, S: SortedStep>(
    bvh: &WideBvh,
    r: &PreRay,
    lanes: &S,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<f32>,
    stack: &mut Stack,
    (mut code, mut d): (u32, f32),
    [mut cull, abs]: [f32; 2],
) {
    let nodes = &bvh.nodes8[..];
    loop {
        if d <= cull {
            if code & LEAF != 0 {
                cull = slack(leaf.visit_inlined(code, stats), abs);
            } else {
                if STATS {
                    stats.node_tests += 1;
                }
                if let Some(next) = lanes.step(&nodes[code as usize], r, cull, stack) {
                    (code, d) = next;
                    continue;
                }
            }
        }
        match stack.pop() {
            Some(next) => (code, d) = next,
            None => return,
        }
    }
}

/// [`closest`] with the AVX2 node test of the ray's octant: one kernel per octant, whose
/// near and far plane rows are constants (measured against one kernel for all rays, block-
/// interleaved in one process, 1024² protocol rays, quality trees: primary 1.04x on
/// pbrt-bathroom, 1.06x on stanford-dragon, 1.06-1.09x on sionna-san-francisco; fast trees
/// 1.06x; closest hits of the AO rays 0.90-1.06x, median 1.01x). Any-hit keeps one kernel: per
/// octant it ran AO rays 0.97-1.00x (eight walks of random directions crowd the instruction
/// cache).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline(never)]
unsafe fn closest_avx2<const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Option<Hit> {
    // SAFETY: every arm needs AVX2, which the caller of this function guarantees.
    unsafe { by_octant!(ray_octant(ray), O => closest_oct::<O, STATS>(bvh, ray, stats)) }
}

/// An 8-wide SIMD node test of the 8-wide tree (only built where the CPU has the test's
/// features); its leaves take the SSE packet test, made from the wide test's origin and
/// `tnear` registers (after the root test in [`closest_wide`] and [`occluded_entry`], before
/// the walk in [`occluded_wide`]).
#[cfg(target_arch = "x86_64")]
struct WideLanes<T>(T);

/// The AVX2 node test.
#[cfg(target_arch = "x86_64")]
type AvxLanes = WideLanes<avx::AvxRay>;
/// The AVX-512 node test.
#[cfg(target_arch = "x86_64")]
type Avx512Lanes = WideLanes<avx512::Avx512Ray>;

#[cfg(target_arch = "x86_64")]
impl<T: WideRay> WideLanes<T> {
    /// The node test of `r` (its box constants suffice). Only call with the wide test's
    /// features present (inlined into a function compiled with them).
    #[inline(always)]
    fn new(r: &PreRay) -> WideLanes<T> {
        WideLanes(T::new(r))
    }
}

#[cfg(target_arch = "x86_64")]
impl<T: WideRay> Lanes<WIDTH8> for WideLanes<T> {
    #[inline(always)]
    fn test(&self, node: &WideNode8, _: &PreRay, tfar: f32) -> LaneHitsN<WIDTH8> {
        self.0.test(node, tfar)
    }

    #[inline(always)]
    fn leaves(&self, node: &WideNode8) -> u32 {
        avx::leaf_mask(node)
    }

    #[inline(always)]
    fn closest_walk<const STATS: bool>(
        &self,
        bvh: &WideBvh,
        _: &[WideNode8],
        r: &PreRay,
        stats: &mut TraceStats,
        leaf: &mut impl LeafVisit<f32>,
    ) {
        closest_walk_sorted::<STATS, _>(bvh, r, self, stats, leaf)
    }

    #[inline(always)]
    fn occluded_walk<const STATS: bool>(
        &self,
        bvh: &WideBvh,
        _: &[WideNode8],
        r: &PreRay,
        stats: &mut TraceStats,
        leaf: &mut impl LeafVisit<bool>,
    ) -> bool {
        occluded_walk_compact::<STATS, T>(bvh, r, self, stats, leaf)
    }
}

/// Hint the cache to fetch the `bytes` bytes at `x` (a no-op off x86-64).
#[inline(always)]
pub(crate) fn prefetch<T>(x: &T, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        let p = (x as *const T).cast::<i8>();
        let mut off = 0;
        while off < bytes {
            // SAFETY: a prefetch is only a hint: it never faults and reads nothing into the
            // program; `wrapping_add` forms the address without claiming it is in bounds.
            unsafe {
                core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(
                    p.wrapping_add(off),
                )
            };
            off += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (x, bytes);
}

/// Hint the cache to fetch the line holding the start of element `i` of `items`, which may be
/// past its end (then the hint is for some other address: still no fault, no read), without
/// the bounds check that forming a reference to it would need.
#[inline(always)]
pub(crate) fn prefetch_at<T>(items: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: as in `prefetch`; `wrapping_add` forms the address without claiming it is in
    // bounds.
    unsafe {
        core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(
            items.as_ptr().wrapping_add(i).cast::<i8>(),
        )
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (items, i);
}

/// Bit `i` set when child `i` of `node` is a leaf (or unused: never entered), from the flag
/// bits of the child codes, without a branch per lane.
#[inline(always)]
fn leaf_mask<const W: usize>(node: &WideNodeN<W>) -> u32 {
    let mut m = 0;
    for (lane, &c) in node.child.iter().enumerate() {
        m |= (c >> 31) << lane;
    }
    m
}

/// Push the entered lanes of `hits` but the nearest, farthest first, and return the nearest
/// (visited next without a round trip through the stack).
#[inline(always)]
fn push_ordered<const W: usize>(
    stack: &mut Stack,
    node: &WideNodeN<W>,
    (mask, dist): LaneHitsN<W>,
) -> Option<(u32, f32)> {
    if mask == 0 {
        return None;
    }
    let first = mask.trailing_zeros() as usize;
    let rest = mask & (mask - 1);
    if rest == 0 {
        // One child (the common case): no sorting.
        return Some((node.child[first], dist[first]));
    }
    if rest & (rest - 1) == 0 {
        // Two children: one comparison (ties visit the lower lane first, as the sort below).
        let second = rest.trailing_zeros() as usize;
        let (a, b) = (
            (node.child[first], dist[first]),
            (node.child[second], dist[second]),
        );
        let (near, far) = if b.1 < a.1 { (b, a) } else { (a, b) };
        stack.push(far.0, far.1);
        return Some(near);
    }
    let mut e = [(0u32, 0.0f32); W];
    let mut n = 0;
    let mut m = mask;
    while m != 0 {
        let lane = m.trailing_zeros() as usize;
        m &= m - 1;
        let code = node.child[lane];
        // Insertion sort by descending distance (at most `W` entries).
        let mut j = n;
        while j > 0 && e[j - 1].1 < dist[lane] {
            e[j] = e[j - 1];
            j -= 1;
        }
        e[j] = (code, dist[lane]);
        n += 1;
    }
    if n == 0 {
        return None;
    }
    for &(code, dist) in &e[..n - 1] {
        stack.push(code, dist);
    }
    Some(e[n - 1])
}

/// The tree a traversal asked for `kind` walks (true: the 8-wide one) and the test it uses
/// there: the tree of `kind`'s width when `bvh` has it, else the other one with the same kind
/// of test (SIMD or scalar).
#[inline(always)]
fn tree_of(bvh: &WideBvh, kind: NodeTest) -> (bool, NodeTest) {
    let want8 = kind.width() == WIDTH8;
    let eight = if want8 {
        !bvh.nodes8.is_empty()
    } else {
        bvh.nodes.is_empty()
    };
    let simd = matches!(kind, NodeTest::Simd | NodeTest::Avx2 | NodeTest::Avx512);
    let kind = match (eight, simd) {
        (true, true) => NodeTest::Avx2,
        (true, false) => NodeTest::Scalar8,
        (false, true) => NodeTest::Simd,
        (false, false) => NodeTest::Scalar,
    };
    (eight, kind)
}

/// The loop a traversal runs: which tree, which node test (see [`tree_of`]), chosen from the
/// tree and the (cached) CPU features before any per-ray work.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kernel {
    Avx512,
    Avx2,
    Sse,
    Scalar8,
    Scalar4,
}

/// A [`Kernel`] chosen by [`kernel_of`] for a tree on this CPU (the only way to make one, so a
/// SIMD kernel always comes with the CPU's features): per call, or once per structure (an
/// `Accel` keeps its own and chooses again after every build).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct KernelChoice(Kernel);

/// The kernel of a traversal asked for `kind` in `bvh`.
#[inline(always)]
pub(crate) fn kernel_of(bvh: &WideBvh, kind: NodeTest) -> KernelChoice {
    KernelChoice(kernel_for(bvh, kind))
}

/// [`kernel_of`]'s choice.
#[inline(always)]
fn kernel_for(bvh: &WideBvh, kind: NodeTest) -> Kernel {
    match tree_of(bvh, kind) {
        (true, NodeTest::Avx2) if kind == NodeTest::Avx512 && avx512_available() => Kernel::Avx512,
        (true, NodeTest::Avx2) if avx2_available() => Kernel::Avx2,
        (true, _) => Kernel::Scalar8,
        (false, NodeTest::Simd) if cfg!(target_arch = "x86_64") => Kernel::Sse,
        (false, _) => Kernel::Scalar4,
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
    if !ray.is_valid() {
        return None;
    }
    closest_valid::<STATS>(bvh, ray, kernel_of(bvh, kind), stats)
}

/// [`closest`] of a ray known to be valid ([`Ray::is_valid`]; not counted in `stats.rays`)
/// with the kernel [`kernel_of`] gave for this tree: for callers that checked the ray and
/// chose the kernel already, such as a two-level trace entering an instance.
#[inline]
pub(crate) fn closest_valid<const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    kernel: KernelChoice,
    stats: &mut TraceStats,
) -> Option<Hit> {
    debug_assert!(ray.is_valid());
    if bvh.nodes.is_empty() && bvh.nodes8.is_empty() {
        return None;
    }
    // Each kernel is its own function that makes the ray's constants itself: with its target
    // features, and without the other kernels' registers and stack in its frame.
    match kernel.0 {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `kernel_of` picks `Avx512` only when the CPU has AVX-512 F/VL/DQ and AVX2.
        Kernel::Avx512 => unsafe { closest_avx512::<STATS>(bvh, ray, stats) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `kernel_of` picks `Avx2` only when the CPU has AVX2.
        Kernel::Avx2 => unsafe { closest_avx2::<STATS>(bvh, ray, stats) },
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse => closest_sse::<STATS>(bvh, ray, stats),
        Kernel::Scalar8 => closest_scalar::<WIDTH8, STATS>(bvh, &bvh.nodes8, ray, stats),
        _ => closest_scalar::<WIDTH, STATS>(bvh, &bvh.nodes, ray, stats),
    }
}

/// The traversals of one 8-wide SIMD node test (`$lanes`, compiled with `$feat`): any hit
/// over triangles, and closest and any hit over item boxes. Each makes the ray's constants
/// itself, with the test's features and without the other kernels' registers in its frame.
#[cfg(target_arch = "x86_64")]
macro_rules! simd_kernels {
    ($lanes:ty, $feat:literal, $what:literal, $occluded:ident, $citems:ident, $oitems:ident) => {
        #[doc = concat!("[`occluded`] on the 8-wide tree with the ", $what, " node test;")]
        /// with `ENTRY`, for a ray entering an instance ([`occluded_entry`]).
        ///
        /// # Safety
        #[doc = concat!("The CPU must have ", $what, ".")]
        #[target_feature(enable = $feat)]
        #[inline(never)]
        unsafe fn $occluded<const STATS: bool, const ENTRY: bool>(
            bvh: &WideBvh,
            ray: &Ray,
            stats: &mut TraceStats,
        ) -> bool {
            if ENTRY {
                let (r, l) = prepare!(boxes ray, r => <$lanes>::new(r));
                return occluded_entry::<STATS, _>(bvh, ray, &r, &l, stats);
            }
            let (r, (l, sse)) = prepare!(ray, r => {
                let l = <$lanes>::new(r);
                let sse = SseLanes::of_wide(r, &l);
                (l, sse)
            });
            occluded_wide::<STATS, _>(bvh, &r, &l, &sse, stats)
        }

        #[doc = concat!("[`closest_items`] on the 8-wide tree with the ", $what, " node test.")]
        ///
        /// # Safety
        #[doc = concat!("The CPU must have ", $what, ".")]
        #[target_feature(enable = $feat)]
        unsafe fn $citems(bvh: &WideBvh, ray: &Ray, visit: &mut impl FnMut(u32, f32) -> f32) {
            let (r, l) = prepare!(boxes ray, r => <$lanes>::new(r));
            closest_items_in::<WIDTH8, _>(bvh, &bvh.nodes8, &r, &l, visit)
        }

        #[doc = concat!("[`occluded_items`] on the 8-wide tree with the ", $what, " node test.")]
        ///
        /// # Safety
        #[doc = concat!("The CPU must have ", $what, ".")]
        #[target_feature(enable = $feat)]
        unsafe fn $oitems(bvh: &WideBvh, ray: &Ray, visit: &mut impl FnMut(u32) -> bool) -> bool {
            let (r, l) = prepare!(boxes ray, r => <$lanes>::new(r));
            occluded_items_in::<WIDTH8, _>(bvh, &bvh.nodes8, &r, &l, visit)
        }
    };
}

#[cfg(target_arch = "x86_64")]
simd_kernels!(
    AvxLanes,
    "avx2",
    "AVX2",
    occluded_avx2,
    closest_items_avx2,
    occluded_items_avx2
);
#[cfg(target_arch = "x86_64")]
simd_kernels!(
    Avx512Lanes,
    "avx512f,avx512vl,avx512dq,avx2",
    "AVX-512 F, VL and DQ, and AVX2",
    occluded_avx512,
    closest_items_avx512,
    occluded_items_avx512
);

/// [`closest`] on the 8-wide tree with the AVX-512 node test.
///
/// # Safety
/// The CPU must have AVX-512 F, VL and DQ, and AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2")]
#[inline(never)]
unsafe fn closest_avx512<const STATS: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Option<Hit> {
    let (r, l) = prepare!(boxes ray, r => Avx512Lanes::new(r));
    closest_wide::<STATS, _>(bvh, ray, &r, &l, stats)
}

/// [`closest`] on the 4-wide tree with the SSE node test.
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn closest_sse<const STATS: bool>(bvh: &WideBvh, ray: &Ray, stats: &mut TraceStats) -> Option<Hit> {
    let (r, l) = prepare!(ray, r => SseLanes(sse::SseRay::new(r)));
    closest_in::<WIDTH, STATS, _>(bvh, &bvh.nodes, &r, &l, stats)
}

/// [`closest`] on either tree with the scalar node and packet tests.
#[inline(never)]
fn closest_scalar<const W: usize, const STATS: bool>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    ray: &Ray,
    stats: &mut TraceStats,
) -> Option<Hit> {
    let r = PreRay::new(ray);
    closest_in::<W, STATS, _>(bvh, nodes, &r, &ScalarLanes, stats)
}

/// The best hit so far of a closest-hit traversal (the [`Hit`] without the ids a
/// [`crate::trace::Scene`] adds).
#[derive(Clone, Copy)]
struct Best {
    t: f32,
    prim: u32,
    u: f32,
    v: f32,
}

/// Make `(t, u, v, prim)` the best hit when it beats it (`better`), or when none was `found`.
#[inline(always)]
fn offer(best: &mut Best, found: &mut bool, t: f32, u: f32, v: f32, prim: u32) {
    if !*found || better(t, prim, best.t, best.prim) {
        *best = Best { t, prim, u, v };
        *found = true;
    }
}

/// The closest-hit loop over one triangle tree (`nodes`: the tree of width `W` in `bvh`).
#[inline(always)]
fn closest_in<const W: usize, const STATS: bool, L: Lanes<W> + PacketTest>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    stats: &mut TraceStats,
) -> Option<Hit> {
    let mut v = ClosestTris::<L, STATS>::new(bvh, r, lanes);
    lanes.closest_walk::<STATS>(bvh, nodes, r, stats, &mut v);
    v.hit()
}

/// [`closest_in`] of an 8-wide SIMD kernel, whose ray comes with its box constants alone
/// ([`PreRay::boxes`]): the root is tested first, and only a ray that enters one of its
/// children makes the triangle test's constants (from `ray`) and walks on from there, so it
/// visits what one walk would. Primary rays of an object seen from outside mostly enter none
/// of the root's children: of the primary rays that miss the object, 82% on stanford-dragon
/// (77% of its rays miss), 89% on pbrt-crown, 95% on sionna-san-francisco. Measured against
/// every ray making all its constants first (the kernel before), quality trees, the two
/// interleaved pass by pass in one process, medians of 9 passes on an AVX2 Zen 3: primary rays
/// in 0.80x the time on stanford-dragon (the rays that miss it 0.55x, those that hit 1.01x),
/// 0.83x on sionna-san-francisco, 0.57x on pbrt-crown, 0.98-0.99x on pbrt-bathroom (camera
/// inside: every ray hits). Walking on to the first leaf without the constants saved the
/// misses no more and cost the hits 5-15%: the constants' latency then stands between the
/// first leaf and its test.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn closest_wide<const STATS: bool, T: WideRay>(
    bvh: &WideBvh,
    ray: &Ray,
    r: &PreRay,
    lanes: &WideLanes<T>,
    stats: &mut TraceStats,
) -> Option<Hit> {
    let abs = abs_slack(bvh, r);
    let cull = slack(r.tfar, abs);
    // As the walk from the root would: the root (node 0, an inner node) is tested when
    // `tnear` is within the culling distance.
    let mut stack = Stack::new();
    let next = if r.tnear <= cull {
        if STATS {
            stats.node_tests += 1;
        }
        lanes.step(&bvh.nodes8[0], r, cull, &mut stack)
    } else {
        None
    }?;
    // Made from `ray`, not copied from `r`: its fields were written by narrower stores than
    // a copy reads, which missed store forwarding.
    let full = PreRay::new(ray);
    let sse = SseLanes::of_wide(&full, lanes);
    let mut v = ClosestTris::<_, STATS>::new(bvh, &full, &sse);
    closest_walk_sorted_from::<STATS, _>(
        bvh,
        r,
        lanes,
        stats,
        &mut v,
        &mut stack,
        next,
        [cull, abs],
    );
    v.hit()
}

/// The item-tree walk `$walk` (generic over width and node test) of `$ray` in `$bvh` with the
/// kernel `$kind` resolves to (see [`kernel_of`]): the SIMD ones through their target-feature
/// functions `$avx512` and `$avx2`, which make the ray's constants themselves.
macro_rules! items_by_kernel {
    ($bvh:ident, $ray:ident, $kind:ident, $visit:ident, $walk:ident, $avx512:ident, $avx2:ident) => {
        match kernel_for($bvh, $kind) {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `kernel_of` picks `Avx512` only when the CPU has AVX-512 F/VL/DQ and AVX2.
            Kernel::Avx512 => unsafe { $avx512($bvh, $ray, $visit) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `kernel_of` picks `Avx2` only when the CPU has AVX2.
            Kernel::Avx2 => unsafe { $avx2($bvh, $ray, $visit) },
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => {
                let r = PreRay::new($ray);
                let l = SseLanes(sse::SseRay::new(&r));
                $walk::<WIDTH, _>($bvh, &$bvh.nodes, &r, &l, $visit)
            }
            Kernel::Scalar8 => {
                let r = PreRay::new($ray);
                $walk::<WIDTH8, _>($bvh, &$bvh.nodes8, &r, &ScalarLanes, $visit)
            }
            _ => {
                let r = PreRay::new($ray);
                $walk::<WIDTH, _>($bvh, &$bvh.nodes, &r, &ScalarLanes, $visit)
            }
        }
    };
}

/// Panics unless every leaf of `bvh` holds one item (the shape [`closest_items`] and
/// [`occluded_items`] rely on).
#[inline(always)]
fn assert_item_tree(bvh: &WideBvh) {
    assert_eq!(
        bvh.leaves, bvh.triangles,
        "an item tree has one item per leaf"
    );
}

/// The item of leaf `code` of an item tree (one item per leaf).
#[inline(always)]
fn leaf_item(bvh: &WideBvh, code: u32) -> u32 {
    bvh.packets[(code & !LEAF) as usize].id[0]
}

/// The closest-hit walk over a tree of items' boxes (a [`WideBvh`] of the fast builder at leaf
/// size 1 over one degenerate triangle per item whose box is the item's, so one item per leaf:
/// see `trace::scene`), in the same order and with the same culling as a triangle tree: the
/// node test is each item's box test, and `visit(id, best)` tests item `id` against the ray up
/// to the best distance so far and returns the new best distance (`best` when nothing closer).
/// The ray must be valid. Panics on a tree with a leaf of several items.
#[inline]
pub(crate) fn closest_items(
    bvh: &WideBvh,
    ray: &Ray,
    kind: NodeTest,
    mut visit: impl FnMut(u32, f32) -> f32,
) {
    assert_item_tree(bvh);
    if bvh.nodes.is_empty() && bvh.nodes8.is_empty() {
        return;
    }
    let visit = &mut visit;
    items_by_kernel!(
        bvh,
        ray,
        kind,
        visit,
        closest_items_in,
        closest_items_avx512,
        closest_items_avx2
    )
}

/// The closest-hit walk of [`closest_items`] over the tree `nodes` of `bvh` with `lanes`.
#[inline(always)]
fn closest_items_in<const W: usize, L: Lanes<W>>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    visit: &mut impl FnMut(u32, f32) -> f32,
) {
    let mut best = r.tfar;
    // One item per leaf: the node test has tested the item's box, entered it within the
    // slackened best distance and ordered it among its siblings; the item is visited as it
    // is popped (an item is often far costlier than a box: a transformed ray through a whole
    // tree, or a user's callback).
    let mut leaf = FnLeaf(|code: u32, _: &mut TraceStats| {
        best = visit(leaf_item(bvh, code), best);
        best
    });
    lanes.closest_walk::<false>(bvh, nodes, r, &mut TraceStats::default(), &mut leaf);
}

/// The closest-hit walk over one tree: children nearest first, a node skipped when its entry
/// distance exceeds the slackened best distance; `leaf(code, stats)` tests leaf `code` and
/// returns the best distance so far.
#[inline(always)]
fn closest_walk<const W: usize, const STATS: bool, L: Lanes<W>>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<f32>,
) {
    let abs = abs_slack(bvh, r);
    let mut cull = slack(r.tfar, abs);
    let mut stack = Stack::new();
    let mut next = Some((0, r.tnear));
    while let Some((code, d)) = next.take().or_else(|| stack.pop()) {
        if d > cull {
            continue;
        }
        // Only inner nodes travel: node 0 is the root (a leaf root is a child of it) and
        // leaves are visited where they are entered, below.
        debug_assert!(code & LEAF == 0);
        {
            let node = &nodes[code as usize];
            if STATS {
                stats.node_tests += 1;
            }
            let (mask, dist) = lanes.test(node, r, cull);
            // Entered leaves are tested at once, nearest first, each only while its entry
            // distance is within the (shrinking) cull distance; inner children still entered
            // within it are then visited nearest first.
            let lm = lanes.leaves(node);
            let leaves = mask & lm;
            let mut inner = mask & !lm;
            if leaves != 0 {
                // Fetch the entered inner children while the leaves are tested, so their
                // cache misses overlap the triangle tests.
                let mut m = inner;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    prefetch(
                        &nodes[node.child[lane] as usize],
                        core::mem::size_of::<WideNodeN<W>>(),
                    );
                }
                // Nearest first (one leaf, the common case, needs no sorting); one call
                // site, so the leaf test is inlined once.
                let mut order = [(0u32, 0.0f32); W];
                let mut n = 0;
                let mut m = leaves;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let mut j = n;
                    while j > 0 && order[j - 1].1 > dist[lane] {
                        order[j] = order[j - 1];
                        j -= 1;
                    }
                    order[j] = (node.child[lane], dist[lane]);
                    n += 1;
                }
                for &(child, d) in &order[..n] {
                    if d > cull {
                        break;
                    }
                    cull = slack(leaf.visit(child, stats), abs);
                }
                let mut m = inner;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    if dist[lane] > cull {
                        inner &= !(1 << lane);
                    }
                }
            }
            next = push_ordered(&mut stack, node, (inner, dist));
        }
    }
}

/// Brute force over triangle packets (no tree): the closest hit of `ray` among every
/// triangle of `packets` by the leaves' own packet test (SSE on x86-64), ties to the lower
/// id as everywhere. For oracles over millions of triangles: it is four times faster than
/// [`crate::trace::intersect::brute_force_closest`] and equal to it, because the packet test
/// equals the scalar triangle test lane for lane. Packets as [`TriPacket::of_triangles`]
/// makes them (each packet its own leaf).
pub fn brute_force_packets(ray: &Ray, packets: &[TriPacket]) -> Option<Hit> {
    if !ray.is_valid() {
        return None;
    }
    let r = PreRay::new(ray);
    #[cfg(target_arch = "x86_64")]
    return brute_force_in(&r, packets, &SseLanes(sse::SseRay::new(&r)));
    #[cfg(not(target_arch = "x86_64"))]
    brute_force_in(&r, packets, &ScalarLanes)
}

/// [`brute_force_packets`] of every ray in `rays`, equal to it ray by ray (each ray meets the
/// packets in the same order with the same tests), in far less time over large meshes: the
/// packets are read in tiles that stay in the cache while a group of rays is tested against
/// each, so they stream from memory once per group instead of once per ray (over a million
/// triangles the packets are 44 MB, and one ray's pass is bound by memory bandwidth).
pub fn brute_force_packets_many(rays: &[Ray], packets: &[TriPacket]) -> Vec<Option<Hit>> {
    /// Packets per tile: 176 bytes each, 88 KiB in all (within a core's L2).
    const TILE: usize = 512;
    /// Rays tested against a tile before the next tile.
    const GROUP: usize = 64;
    let mut out = Vec::with_capacity(rays.len());
    for group in rays.chunks(GROUP) {
        let pre: Vec<Option<PreRay>> = group
            .iter()
            .map(|r| r.is_valid().then(|| PreRay::new(r)))
            .collect();
        #[cfg(target_arch = "x86_64")]
        let lanes: Vec<Option<SseLanes>> = pre
            .iter()
            .map(|r| r.as_ref().map(|r| SseLanes(sse::SseRay::new(r))))
            .collect();
        #[cfg(not(target_arch = "x86_64"))]
        let lanes: Vec<Option<ScalarLanes>> = pre
            .iter()
            .map(|r| r.as_ref().map(|_| ScalarLanes))
            .collect();
        let mut best: Vec<(Best, bool)> = pre
            .iter()
            .map(|r| {
                let t = r.as_ref().map_or(0.0, |r| r.tfar);
                let b = Best {
                    t,
                    prim: u32::MAX,
                    u: 0.0,
                    v: 0.0,
                };
                (b, false)
            })
            .collect();
        for tile in packets.chunks(TILE) {
            for ((r, l), (b, found)) in pre.iter().zip(&lanes).zip(&mut best) {
                let (Some(r), Some(l)) = (r, l) else {
                    continue;
                };
                for p in tile {
                    let tmax = b.t;
                    l.packet(r, p, tmax, |t, u, v, prim| offer(b, found, t, u, v, prim));
                }
            }
        }
        out.extend(
            best.iter()
                .map(|(b, found)| found.then_some(Hit::triangle(b.t, b.prim, b.u, b.v))),
        );
    }
    out
}

/// [`brute_force_packets`] with one tester.
fn brute_force_in<L: PacketTest>(r: &PreRay, packets: &[TriPacket], lanes: &L) -> Option<Hit> {
    let mut best = Best {
        t: r.tfar,
        prim: u32::MAX,
        u: 0.0,
        v: 0.0,
    };
    let mut found = false;
    for p in packets {
        let tmax = best.t;
        lanes.packet(r, p, tmax, |t, u, v, prim| {
            offer(&mut best, &mut found, t, u, v, prim)
        });
    }
    found.then_some(Hit::triangle(best.t, best.prim, best.u, best.v))
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
    ray.is_valid() && occluded_valid::<STATS, false>(bvh, ray, kernel_of(bvh, kind), stats)
}

/// [`occluded`] of a ray known to be valid ([`Ray::is_valid`]; not counted in `stats.rays`)
/// with the kernel [`kernel_of`] gave for this tree; `ENTRY` for a ray entering an instance
/// (the 8-wide SIMD kernels then test the root before making the triangle constants, see
/// [`occluded_entry`]; the same answer either way).
#[inline]
pub(crate) fn occluded_valid<const STATS: bool, const ENTRY: bool>(
    bvh: &WideBvh,
    ray: &Ray,
    kernel: KernelChoice,
    stats: &mut TraceStats,
) -> bool {
    debug_assert!(ray.is_valid());
    if bvh.nodes.is_empty() && bvh.nodes8.is_empty() {
        return false;
    }
    match kernel.0 {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `kernel_of` picks `Avx512` only when the CPU has AVX-512 F/VL/DQ and AVX2.
        Kernel::Avx512 => unsafe { occluded_avx512::<STATS, ENTRY>(bvh, ray, stats) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `kernel_of` picks `Avx2` only when the CPU has AVX2.
        Kernel::Avx2 => unsafe { occluded_avx2::<STATS, ENTRY>(bvh, ray, stats) },
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse => occluded_sse::<STATS>(bvh, ray, stats),
        Kernel::Scalar8 => occluded_scalar::<WIDTH8, STATS>(bvh, &bvh.nodes8, ray, stats),
        _ => occluded_scalar::<WIDTH, STATS>(bvh, &bvh.nodes, ray, stats),
    }
}

/// [`occluded`] on the 4-wide tree with the SSE node test.
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn occluded_sse<const STATS: bool>(bvh: &WideBvh, ray: &Ray, stats: &mut TraceStats) -> bool {
    let (r, l) = prepare!(ray, r => SseLanes(sse::SseRay::new(r)));
    occluded_in::<WIDTH, STATS, _>(bvh, &bvh.nodes, &r, &l, stats)
}

/// [`occluded`] on either tree with the scalar node and packet tests.
#[inline(never)]
fn occluded_scalar<const W: usize, const STATS: bool>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    ray: &Ray,
    stats: &mut TraceStats,
) -> bool {
    let r = PreRay::new(ray);
    occluded_in::<W, STATS, _>(bvh, nodes, &r, &ScalarLanes, stats)
}

/// The any-hit loop over one triangle tree.
#[inline(always)]
fn occluded_in<const W: usize, const STATS: bool, L: Lanes<W> + PacketTest>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    stats: &mut TraceStats,
) -> bool {
    let mut v = OccludedTris::<L, STATS> { bvh, r, lanes };
    lanes.occluded_walk::<STATS>(bvh, nodes, r, stats, &mut v)
}

/// [`occluded_in`] of an 8-wide SIMD kernel: the walk of [`occluded_walk_compact`], the
/// packets tested by `sse` (any-hit rays start at a surface, inside the root box, so they
/// make every constant at once: made after the root test instead, as [`occluded_entry`]
/// does, they took 1.05-1.09x the time on the AO rays of pbrt-bathroom, stanford-dragon and
/// sionna-san-francisco).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn occluded_wide<const STATS: bool, T: WideRay>(
    bvh: &WideBvh,
    r: &PreRay,
    lanes: &WideLanes<T>,
    sse: &SseLanes,
    stats: &mut TraceStats,
) -> bool {
    let mut v = OccludedTris::<_, STATS> { bvh, r, lanes: sse };
    occluded_walk_compact::<STATS, T>(bvh, r, lanes, stats, &mut v)
}

/// [`occluded_wide`] for a ray entering an instance of a lone mesh, which often enters none of
/// the root's children though it entered the instance's box (a rotated object's box is
/// loose): the ray comes with its box constants alone ([`PreRay::boxes`]), and only one that
/// enters a child of the root makes the triangle test's (from `ray`) and walks on.
/// Stanford-dragon × 1000 (`emc compare --instances 1000`, two runs each way): AO 0.76-0.77x →
/// 0.81x the best peer's speed.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn occluded_entry<const STATS: bool, T: WideRay>(
    bvh: &WideBvh,
    ray: &Ray,
    r: &PreRay,
    lanes: &WideLanes<T>,
    stats: &mut TraceStats,
) -> bool {
    let cull = slack(r.tfar, abs_slack(bvh, r));
    let root = occluded_step::<STATS, T>(&bvh.nodes8[0], r, lanes, stats, cull);
    if root[1] == 0 {
        return false;
    }
    // Made from `ray`, not copied from `r` (see `closest_wide`).
    let full = PreRay::new(ray);
    let sse = SseLanes::of_wide(&full, lanes);
    let mut v = OccludedTris::<_, STATS> {
        bvh,
        r: &full,
        lanes: &sse,
    };
    occluded_walk_compact_from::<STATS, T>(bvh, r, lanes, stats, &mut v, cull, root)
}

/// True when `visit(id)` is true for an item of the box tree `bvh` (one item per leaf) whose
/// box the ray enters (see [`closest_items`]); the ray must be valid.
#[inline]
pub(crate) fn occluded_items(
    bvh: &WideBvh,
    ray: &Ray,
    kind: NodeTest,
    mut visit: impl FnMut(u32) -> bool,
) -> bool {
    assert_item_tree(bvh);
    if bvh.nodes.is_empty() && bvh.nodes8.is_empty() {
        return false;
    }
    let visit = &mut visit;
    items_by_kernel!(
        bvh,
        ray,
        kind,
        visit,
        occluded_items_in,
        occluded_items_avx512,
        occluded_items_avx2
    )
}

/// The any-hit walk of [`occluded_items`] over the tree `nodes` of `bvh` with `lanes`.
#[inline(always)]
fn occluded_items_in<const W: usize, L: Lanes<W>>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    visit: &mut impl FnMut(u32) -> bool,
) -> bool {
    // One item per leaf: its box was the node test's (see `closest_items_in`).
    let mut leaf = FnLeaf(|code: u32, _: &mut TraceStats| visit(leaf_item(bvh, code)));
    lanes.occluded_walk::<false>(bvh, nodes, r, &mut TraceStats::default(), &mut leaf)
}

/// The any-hit walk over one tree: `leaf(code, stats)` is true when leaf `code` holds a hit,
/// which ends the walk.
#[inline(always)]
fn occluded_walk<const W: usize, const STATS: bool, L: Lanes<W>>(
    bvh: &WideBvh,
    nodes: &[WideNodeN<W>],
    r: &PreRay,
    lanes: &L,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<bool>,
) -> bool {
    let abs = abs_slack(bvh, r);
    let cull = slack(r.tfar, abs);
    let mut stack = Stack::new();
    stack.push(0, r.tnear);
    while let Some((code, _)) = stack.pop() {
        if code & LEAF != 0 {
            if leaf.visit(code, stats) {
                return true;
            }
        } else {
            let node = &nodes[code as usize];
            if STATS {
                stats.node_tests += 1;
            }
            // The leaf flags first: their load does not wait for the test.
            let lm = lanes.leaves(node);
            let (mask, _) = lanes.test(node, r, cull);
            let mut m = mask;
            // Any hit ends the search, so the order of visits only matters for speed: entered
            // leaves are tested at once (no round trip through the stack), inner children go
            // on the stack as they come.
            while m != 0 {
                let lane = m.trailing_zeros() as usize;
                m &= m - 1;
                let child = node.child[lane];
                if lm >> lane & 1 != 0 {
                    if leaf.visit(child, stats) {
                        return true;
                    }
                } else {
                    // Fetched as it is pushed, so its cache misses overlap the leaf tests and
                    // pushes after it. (Measured, AO rays, alternating runs: 1.047x on
                    // pbrt-bathroom, 1.033x on stanford-dragon and sionna-san-francisco against
                    // a loop fetching every entered child, leaves too, before any was tested,
                    // whose branches mispredicted about 4 times per ray; no fetch at all:
                    // 1.034x and 1.01x.)
                    prefetch(&nodes[child as usize], core::mem::size_of::<WideNodeN<W>>());
                    stack.push(child, 0.0);
                }
            }
        }
    }
    false
}

/// Lanes of each 8-bit mask in ascending order, one per byte (the rest 0): the index row
/// that packs a node's chosen children to the front of a vector, for
/// [`occluded_walk_compact`]'s push (2 KiB, kept in the first-level cache by use).
#[cfg(target_arch = "x86_64")]
const COMPACT: [u64; 256] = {
    let mut t = [0u64; 256];
    let mut m = 0;
    while m < 256 {
        let (mut row, mut n, mut lane) = (0u64, 0, 0);
        while lane < 8 {
            if m >> lane & 1 != 0 {
                row |= (lane as u64) << (8 * n);
                n += 1;
            }
            lane += 1;
        }
        t[m] = row;
        m += 1;
    }
    t
};

/// [`occluded_walk`] of the 8-wide SIMD testers, in the same order (entered leaves tested at
/// once in lane order, then the entered inner children from the highest lane down), with
/// fewer data-dependent branches: the highest inner child is visited next and fetched while
/// the leaves are tested; the others go on the stack by one eight-lane store of the child row
/// permuted by [`COMPACT`] (lowest lane deepest), the stack growing by their number. The loop
/// over every entered lane it replaces mispredicted about four branches per AO ray
/// (cachegrind's branch model); measured, AO rays, alternating runs: 1.050x on pbrt-bathroom,
/// 1.048x on sionna-san-francisco, 1.060x on stanford-dragon (also fetching each pushed child:
/// 1.00-1.04x).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn occluded_walk_compact<const STATS: bool, T: WideRay>(
    bvh: &WideBvh,
    r: &PreRay,
    lanes: &WideLanes<T>,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<bool>,
) -> bool {
    let cull = slack(r.tfar, abs_slack(bvh, r));
    let root = occluded_step::<STATS, T>(&bvh.nodes8[0], r, lanes, stats, cull);
    occluded_walk_compact_from::<STATS, T>(bvh, r, lanes, stats, leaf, cull, root)
}

/// One node of the any-hit walk: the test counted, then the node's leaf flags and entered
/// lanes, `[leaves, entered]` (the flags are read first: their load does not wait for the
/// test).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn occluded_step<const STATS: bool, T: WideRay>(
    node: &WideNode8,
    r: &PreRay,
    lanes: &WideLanes<T>,
    stats: &mut TraceStats,
    cull: f32,
) -> [u32; 2] {
    if STATS {
        stats.node_tests += 1;
    }
    let lm = lanes.leaves(node);
    let (mask, _) = lanes.test(node, r, cull);
    [lm, mask]
}

/// [`occluded_walk_compact`] after its first step (the root, node 0, an inner node: a leaf
/// root is a child of it), culling at `cull`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn occluded_walk_compact_from<const STATS: bool, T: WideRay>(
    bvh: &WideBvh,
    r: &PreRay,
    lanes: &WideLanes<T>,
    stats: &mut TraceStats,
    leaf: &mut impl LeafVisit<bool>,
    cull: f32,
    [mut lm, mut mask]: [u32; 2],
) -> bool {
    use core::arch::x86_64::*;
    let nodes = &bvh.nodes8[..];
    let mut stack = Stack::new();
    // Only inner nodes travel, leaves are tested where they are entered.
    let mut node = &nodes[0];
    loop {
        let inner = mask & !lm;
        let mut next = None;
        if inner != 0 {
            let top = 31 - inner.leading_zeros();
            let rest = inner & !(1 << top);
            let child = node.child[top as usize];
            prefetch(&nodes[child as usize], core::mem::size_of::<WideNode8>());
            next = Some(child);
            if rest != 0 {
                let len = stack.len;
                assert!(len + WIDTH8 <= STACK_ROWS, "traversal stack overflow");
                // SAFETY: only reached with AVX2 enabled (the 8-wide SIMD kernels); the
                // aligned load reads the node's 32-byte child row (byte 192 of a 64-byte
                // aligned node), the unaligned store writes slots `len..len + 8` of the code
                // row, in bounds by the check above.
                unsafe {
                    let order =
                        _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(COMPACT[rest as usize] as i64));
                    let children = _mm256_load_si256(node.child.as_ptr().cast());
                    _mm256_storeu_si256(
                        stack.codes.as_mut_ptr().add(len).cast(),
                        _mm256_permutevar8x32_epi32(children, order),
                    );
                }
                stack.len = len + rest.count_ones() as usize;
            }
        }
        let mut m = mask & lm;
        while m != 0 {
            let lane = m.trailing_zeros() as usize;
            m &= m - 1;
            if leaf.visit_inlined(node.child[lane], stats) {
                return true;
            }
        }
        let code = match next.or_else(|| stack.pop_code()) {
            Some(child) => child,
            None => return false,
        };
        node = &nodes[code as usize];
        [lm, mask] = occluded_step::<STATS, T>(node, r, lanes, stats, cull);
    }
}

#[cfg(test)]
mod tests {
    /// The sorted push's network orders every input: exhaustively on zeros and ones (the 0-1
    /// principle makes that a proof for all inputs), and on random keys with repeats.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn sort8_desc_sorts() {
        if !super::avx2_available() {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        let check = |keys: [u32; 8]| {
            let mut want = keys;
            want.sort_unstable_by(|a, b| b.cmp(a));
            // SAFETY: AVX2 was detected above.
            let got = unsafe { super::avx::sort8_desc_array(keys) };
            assert_eq!(got, want, "{keys:?}");
        };
        for bits in 0u32..256 {
            check(core::array::from_fn(|i| bits >> i & 1));
        }
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..20_000 {
            check(core::array::from_fn(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                // Few distinct values (repeats) half the time, full range otherwise.
                if x >> 63 == 0 {
                    (x >> 8) as u32 & 7
                } else {
                    (x >> 16) as u32
                }
            }));
        }
    }
}
