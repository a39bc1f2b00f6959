//! AVX-512 parts of the batch pipeline (x86_64 only), entered only after
//! [`crate::cpu::has_avx512`] said yes: the size channel of eight boxes at a time without a
//! square root or a divide, bit for bit [`Quantizer::size_by_thresholds`], and the dispatched
//! pdep pipeline ([`run_pdep`]) that quantises eight boxes per step in `f64x8` lanes.
//!
//! ```text
//!   d2 (f64x8) ─► ρ = clamp(d2·(1/D²), 2^-600, 1) ─► g = rsqrt14(rsqrt14(ρ)) ≈ ρ^¼
//!                                                       (linear: rcp14(rsqrt14(ρ)) ≈ ρ^½)
//!   k = min(cvtt(g·2^S + ½), 2^S − 1)                   estimate, q ∈ {k − 1, k}
//!   T(k): k bits 0-3 → vpermt2pd over 16 thresholds (4 register pairs hold T(0..64))
//!         k bit 4    → blend pairs 0/1 and 2/3,  k bit 5 → blend those two
//!   q = k − [T(k) > d2]
//! ```
//!
//! [`run_pdep`] keeps only the estimate in vector registers and makes the comparison on the
//! integer side, on bit patterns, beside the `pdep`s; it runs as a four-stage software
//! pipeline over steps of eight boxes (see there):
//!
//! ```text
//!   step j:  A  load 3×64 B, vpermt2ps transpose, cvtps2pd  (boxes of step j)   → registers
//!            B  positions, d2                                (step j − 1)       → ring slot
//!            C  size estimate k                              (step j − 2)       → ring slot
//!            D  per lane: 3 pdep | st[k − [d2 < T(k)]]       (step j − 3)       ← ring slot
//! ```
//!
//! [`Quantizer::size_by_thresholds`]: crate::Quantizer::size_by_thresholds

use core::arch::x86_64::*;

use super::avx2::{positions4, quantize4, Kernel, SIZE_LOOKUP512, SIZE_NONE};

/// Largest size-bit count the in-register lookup serves (`2^6 = 64` thresholds, eight `zmm`).
pub(crate) const LOOKUP_BITS: u32 = 6;

/// The per-encoder constants of [`size8`], loaded into registers once per batch.
#[derive(Clone, Copy)]
struct Consts {
    /// `T(8i .. 8i + 8)`, +inf past `2^S − 1` (never selected).
    t: [__m512d; 8],
    /// `1 / D²`.
    inv_d2: __m512d,
    /// `2^S` as `f64`.
    scale: __m512d,
    /// `2^S − 1` as `i64`.
    top: __m512i,
    /// Linear transform (`ρ^½`) instead of sqrt (`ρ^¼`).
    linear: bool,
    /// More than 16 thresholds (`S > 4`): the two blend levels are needed.
    wide: bool,
}

impl Consts {
    /// Load the kernel's thresholds and constants.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn new(k: &Kernel) -> Consts {
        let mut t = [_mm512_setzero_pd(); 8];
        for (i, r) in t.iter_mut().enumerate() {
            let mut row = [0.0; 8];
            row.copy_from_slice(&k.thr[8 * i..8 * i + 8]);
            // SAFETY: `row` holds eight f64.
            *r = unsafe { _mm512_loadu_pd(row.as_ptr()) };
        }
        Consts {
            t,
            inv_d2: _mm512_set1_pd(k.inv_d2),
            scale: _mm512_set1_pd(k.s_scale),
            top: _mm512_set1_epi64(k.s_top as i64),
            linear: k.linear,
            wide: k.s_top >= 16,
        }
    }
}

/// The estimate `k` of [`size8`] (`q ∈ {k − 1, k}`, see there) as `i64x8`, in `0 ..= 2^S − 1`.
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
#[inline]
fn estimate8<const LINEAR: bool>(c: &Consts, d2: __m512d) -> __m512i {
    let r = _mm512_mul_pd(d2, c.inv_d2);
    let r = _mm512_max_pd(r, _mm512_set1_pd(f64::from_bits((1023 - 600) << 52)));
    let r = _mm512_min_pd(r, _mm512_set1_pd(1.0));
    let y = _mm512_rsqrt14_pd(r);
    let g = if LINEAR {
        _mm512_rcp14_pd(y)
    } else {
        _mm512_rsqrt14_pd(y)
    };
    let x = _mm512_add_pd(_mm512_mul_pd(g, c.scale), _mm512_set1_pd(0.5));
    _mm512_min_epi64(_mm512_cvttpd_epi64(x), c.top)
}

/// The size channel of eight boxes from their squared diagonals, as `i32x8`.
///
/// Exactness (the argument of `avx2::size_thresholds`, with tighter estimates): let `x` be the
/// exact real `2^S·ρ^e` (`e` = ¼ or ½) and `x_n` the normative `f64` value, a few ulps from `x`.
/// `ρ` carries a relative error of a few `f64` ulps (`1/D²` and the product), and the clamp to
/// `[2^-600, 1]` keeps every operand normal (below `2^-600`, `x < 2^-142` and both the estimate
/// and `q` are 0). `vrsqrt14pd` and `vrcp14pd` have relative error below `2^-14`, so `g` is
/// within `1.5·2^-14` (sqrt) or `2·2^-14` (linear) of `ρ^e`, and with `S <= 6`,
/// `|g·2^S − x| < 2^-7`. Then `g·2^S + ½ ∈ [k, k + 1)` puts `x_n` in `(k − 1, k + 1)`:
/// `⌊x_n⌋ ∈ {k − 1, k}`, and `q = k − 1 + [T(k) <= d2] = k − [T(k) > d2]`. When `k` is clamped
/// to `M = 2^S − 1`, `g·2^S + ½ >= M + 1` gives `x_n > M`, so `T(M) <= d2` and `q = M = k`. NaN: `max` returns its second operand, so `ρ = 2^-600`, `k = 0`,
/// and `T(0) = 0 > NaN` is false: `q = 0`, as the scalar search gives. `d2 = +inf`: `ρ = 1`,
/// `k = M`, `T(M) <= inf`: `q = M`, as the formula gives.
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
#[inline]
fn size8(c: &Consts, d2: __m512d) -> __m256i {
    let k = if c.linear {
        estimate8::<true>(c, d2)
    } else {
        estimate8::<false>(c, d2)
    };
    let t01 = _mm512_permutex2var_pd(c.t[0], k, c.t[1]);
    let t = if c.wide {
        let t23 = _mm512_permutex2var_pd(c.t[2], k, c.t[3]);
        let t45 = _mm512_permutex2var_pd(c.t[4], k, c.t[5]);
        let t67 = _mm512_permutex2var_pd(c.t[6], k, c.t[7]);
        let b4 = _mm512_test_epi64_mask(k, _mm512_set1_epi64(16));
        let b5 = _mm512_test_epi64_mask(k, _mm512_set1_epi64(32));
        let lo = _mm512_mask_blend_pd(b4, t01, t23);
        let hi = _mm512_mask_blend_pd(b4, t45, t67);
        _mm512_mask_blend_pd(b5, lo, hi)
    } else {
        t01
    };
    let above = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(t, d2);
    let q = _mm512_mask_sub_epi64(k, above, k, _mm512_set1_epi64(1));
    _mm512_cvtepi64_epi32(q)
}

/// [`size8`] for the four-lane paths (table, magic and reference expanders): the upper half
/// repeats the lower. Builds its constants on every call; the dispatched pdep path
/// ([`run_pdep`]) runs eight lanes with the constants in registers instead.
///
/// # Safety
/// The CPU must support AVX-512 F, DQ and VL.
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
pub(super) unsafe fn size4(k: &Kernel, d2: __m256d) -> __m128i {
    let c = Consts::new(k);
    let wide = _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(d2), d2);
    _mm256_castsi256_si128(size8(&c, wide))
}

/// `v` unchanged, through an empty `asm!` that names it as one general-purpose register: the
/// integer side of the pdep pipeline stays scalar (without it LLVM's SLP vectoriser turns the
/// per-lane table reads and compares into `vpgather`s and moves the `pdep` results back into
/// vector registers: 3.1 against 1.9 ns/code for `emc64-var` in cache on Zen 4).
#[inline(always)]
fn gpr(mut v: u64) -> u64 {
    // SAFETY: the template is empty: no instruction runs, no memory or flag is touched.
    unsafe {
        core::arch::asm!("/* {0} */", inout(reg) v, options(pure, nomem, nostack, preserves_flags))
    };
    v
}

/// The dispatched `pdep` pipeline on an AVX-512 CPU, for layouts without a size channel or
/// with the AVX-512 size step (`k.size_mode` none or lookup): eight boxes per step (a lone
/// last group of four is quantised twice and written once). Returns `4·n4`.
///
/// # Safety
/// AVX2, BMI2 and AVX-512 F/DQ/VL; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes
/// (`u32` when `W32`).
#[target_feature(enable = "avx2,bmi2,avx512f,avx512dq,avx512vl")]
pub(super) unsafe fn run_pdep<const W32: bool>(
    k: &Kernel,
    m: [u64; 4],
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    // SAFETY: the caller's contract, passed on unchanged.
    unsafe {
        if k.size_mode == SIZE_NONE {
            run_pdep_t::<false, false, W32>(k, m, src, n4, out)
        } else if k.linear {
            run_pdep_t::<true, true, W32>(k, m, src, n4, out)
        } else {
            run_pdep_t::<true, false, W32>(k, m, src, n4, out)
        }
    }
}

/// [`run_pdep`] with a size channel (`SIZED`, by the AVX-512 lookup mode) of one transform
/// (`LINEAR`), or without one.
///
/// The vector step computes only the estimate `k` of [`size8`]; its fix-up runs on the
/// integer side, beside the `pdep`s, on the bit patterns of `d2` and `T(k)`: both are `+0`,
/// positive or `+inf` (or `d2` is NaN), and such `f64` order like their bits as unsigned
/// integers, so `T(k) > d2` is `bits(d2) < bits(T(k))` (false for a NaN of either sign, as the
/// ordered vector compare). Then `q = k − [bits(d2) < bits(T(k))]` and the code takes the
/// size deposit `st[q] = pdep(q, m_s)` from a 64-entry table.
///
/// # Safety
/// As [`run_pdep`].
#[target_feature(enable = "avx2,bmi2,avx512f,avx512dq,avx512vl")]
#[allow(clippy::needless_range_loop)] // `l` picks the same lane from each channel's row
unsafe fn run_pdep_t<const SIZED: bool, const LINEAR: bool, const W32: bool>(
    k: &Kernel,
    m: [u64; 4],
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let c = Consts::new(k);
    let t = Transpose8::new();
    // The size channel (at most `LOOKUP_BITS` bits here) is deposited by a table load instead
    // of a fourth `pdep`: `st[v] = pdep(v, m[3])` for every 6-bit `v`, built once per batch.
    // Both tables stay zero (unread) without a size channel.
    let st: [u64; 64] = core::array::from_fn(|v| if SIZED { _pdep_u64(v as u64, m[3]) } else { 0 });
    // `tb[v] = bits(T(v))`; +inf past `2^S − 1` (never selected: `k <= 2^S − 1`).
    let tb: [u64; 64] = core::array::from_fn(|v| if SIZED { k.thr[v].to_bits() } else { 0 });
    // Software-pipelined in four stages over steps of eight boxes (groups 2e and 2e + 1),
    // so that no iteration holds one long dependency chain (a step's chain from its loads to
    // the size estimate is some 70 cycles long, more than the out-of-order window covers):
    //   A(j)     load and transpose step j                 → `fields` (registers)
    //   B(j − 1) positions and `d2` of step j − 1          → ring slot, `d2` (registers)
    //   C(j − 2) size estimate of step j − 2               → ring slot
    //   D(j − 3) integer side: pdeps, size fix-up, codes   ← ring slot
    // The integer side reads its lanes with scalar loads from the ring: moving them out of
    // vector registers lane by lane (`vpextrd`, what LLVM made of a copied buffer) was the
    // bottleneck before. Zen 4, `emc64-var`, 16K boxes in cache: 2.91 ns/code with
    // extraction and the in-register lookup of `size8`, 2.48 with the ring, 2.39 with the
    // estimate split off, 1.87 with all four stages. Without a size channel stage C and the
    // fix-up drop out (`morton63`: 1.87 ns/code on the AVX2 pipeline, 1.27 here).
    const LAG: usize = 3;
    let mut ring = [Lanes::default(); 4];
    let ring = ring.as_mut_ptr();
    let steps = n4.div_ceil(2);
    let mut fields = [_mm512_setzero_pd(); 6];
    let mut d2 = _mm512_setzero_pd();
    for j in 0..steps + LAG {
        if SIZED && j >= 2 && j - 2 < steps {
            let est = _mm512_cvtepi64_epi32(estimate8::<LINEAR>(&c, d2));
            // SAFETY: slot `(j − 2) % 4` of the ring; its size row holds eight u32.
            unsafe {
                let slot = &mut *ring.add((j - 2) % 4);
                _mm256_storeu_si256(slot.q[3].as_mut_ptr() as *mut __m256i, est);
            }
        }
        if j >= 1 && j - 1 < steps {
            let (q, d) = quantize8(k, fields);
            // SAFETY: slot `(j − 1) % 4` of the ring; each row holds eight u32, `d2` eight
            // u64.
            unsafe {
                let slot = &mut *ring.add((j - 1) % 4);
                for ch in 0..3 {
                    _mm256_storeu_si256(slot.q[ch].as_mut_ptr() as *mut __m256i, q[ch]);
                }
                if SIZED {
                    _mm512_storeu_pd(slot.d2.as_mut_ptr() as *mut f64, d);
                }
            }
            d2 = d;
        }
        if j < steps {
            let pa = src.wrapping_add(48 * j);
            fields = if 2 * j + 1 < n4 {
                // SAFETY: groups 2j and 2j + 1 (eight boxes) lie inside `src`.
                unsafe { fields8(&t, pa) }
            } else {
                // A lone last group: its four boxes twice, from a copy.
                let mut two = [0f32; 48];
                // SAFETY: group 2j (24 floats) lies inside `src`.
                unsafe {
                    core::ptr::copy_nonoverlapping(pa, two.as_mut_ptr(), 24);
                    core::ptr::copy_nonoverlapping(pa, two.as_mut_ptr().add(24), 24);
                }
                // SAFETY: `two` holds 48 floats.
                unsafe { fields8(&t, two.as_ptr()) }
            };
        }
        if j >= LAG {
            let e = j - LAG;
            let lanes = if 2 * e + 1 < n4 { 8 } else { 4 };
            // SAFETY: slot `e % 4` was written at step e and not since (steps e + 1 ..= j
            // write the other slots).
            let slot = unsafe { &*ring.add(e % 4) };
            for l in 0..lanes {
                // `est` is in 0 ..= 2^S − 1 <= 63 (`estimate8`); the masks make the unchecked
                // reads obviously in bounds. For `est = 0`, `bits(T(0)) = 0` and nothing is
                // below it: `s` never wraps.
                let mut code = _pdep_u64(slot.q[0][l] as u64, m[0])
                    | _pdep_u64(slot.q[1][l] as u64, m[1])
                    | _pdep_u64(slot.q[2][l] as u64, m[2]);
                if SIZED {
                    let est = gpr(slot.q[3][l] as u64) as usize & 63;
                    // SAFETY: `est < 64` and `tb` has 64 entries.
                    let below = gpr(slot.d2[l]) < unsafe { *tb.get_unchecked(est) };
                    let s = est.wrapping_sub(below as usize) & 63;
                    // SAFETY: `s < 64` and `st` has 64 entries.
                    code |= unsafe { *st.get_unchecked(s) };
                }
                let i = 8 * e + l;
                // SAFETY: `i < 4·n4`: step e holds codes 8e .. 8e + lanes.
                unsafe {
                    if W32 {
                        (out as *mut u32).add(i).write_unaligned(code as u32);
                    } else {
                        (out as *mut u64).add(i).write_unaligned(code);
                    }
                }
            }
        }
    }
    4 * n4
}

/// The lane permutations of [`fields8`]: for each pair of box fields, the `vpermt2ps`
/// indices and the lanes whose field lies in the third 64-byte block.
#[derive(Clone, Copy)]
struct Transpose8 {
    idx: [__m512i; 3],
    hi: [__mmask16; 3],
}

impl Transpose8 {
    /// Field `f` of box `i` is float `6i + f` of the 48 (eight boxes, `#[repr(C)]`: min xyz,
    /// max xyz). Output pair `p` holds field `2p` of boxes 0..8 in lanes 0..8 and field
    /// `2p + 1` in lanes 8..16; lane `s` takes float `g = 6(s mod 8) + 2p + s / 8`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn new() -> Transpose8 {
        let mut idx = [_mm512_setzero_si512(); 3];
        let mut hi = [0; 3];
        for p in 0..3 {
            let mut v = [0i32; 16];
            for (s, x) in v.iter_mut().enumerate() {
                let g = 6 * (s % 8) + 2 * p + s / 8;
                *x = g as i32;
                if g >= 32 {
                    hi[p] |= 1 << s;
                }
            }
            // SAFETY: `v` holds sixteen i32.
            idx[p] = unsafe { _mm512_loadu_si512(v.as_ptr() as *const __m512i) };
        }
        Transpose8 { idx, hi }
    }
}

/// The six fields of eight boxes as `f64x8` (`[lx, ly, lz, hx, hy, hz]`: min and max per
/// axis), transposed by `vpermt2ps` from three 64-byte loads: the loading half of the AVX2
/// step's [`positions4`], on eight lanes.
///
/// ```text
///   L0 = floats 0..16, L1 = 16..32, L2 = 32..48        (box i, field f at float 6i + f)
///   pair p, lane s: g = 6(s mod 8) + 2p + s/8
///     P = vpermt2ps(L0, g mod 32, L1)   right where g < 32
///     Q = vpermt2ps(L2, g mod 32, L1)   right where g >= 32 (L2 float g − 32)
///     F_p = blend(g >= 32 ? Q : P)      = [field 2p of boxes 0..8 | field 2p + 1 of 0..8]
///   F_0 = [mnx | mny], F_1 = [mnz | mxx], F_2 = [mxy | mxz]  → cvtps2pd per half
/// ```
///
/// # Safety
/// `p` must point at eight consecutive `Aabb` (48 readable `f32`).
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
#[inline]
unsafe fn fields8(t: &Transpose8, p: *const f32) -> [__m512d; 6] {
    // SAFETY: 48 floats from `p` by the contract above.
    let (l0, l1, l2) = unsafe {
        (
            _mm512_loadu_ps(p),
            _mm512_loadu_ps(p.add(16)),
            _mm512_loadu_ps(p.add(32)),
        )
    };
    let f: [__m512; 3] = core::array::from_fn(|i| {
        let lo = _mm512_permutex2var_ps(l0, t.idx[i], l1);
        let hi = _mm512_permutex2var_ps(l2, t.idx[i], l1);
        _mm512_mask_blend_ps(t.hi[i], lo, hi)
    });
    let lo = |v: __m512| _mm512_cvtps_pd(_mm512_castps512_ps256(v));
    let hi = |v: __m512| _mm512_cvtps_pd(_mm512_extractf32x8_ps::<1>(v));
    [lo(f[0]), hi(f[0]), lo(f[1]), hi(f[1]), lo(f[2]), hi(f[2])]
}

/// The position channels (`i32x8` each) and squared diagonals (`f64x8`) of eight boxes from
/// their [`fields8`]: the arithmetic of the AVX2 step's [`positions4`], bit for bit.
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
#[inline]
fn quantize8(k: &Kernel, f: [__m512d; 6]) -> ([__m256i; 3], __m512d) {
    let [lx, ly, lz, hx, hy, hz] = f;
    let pos = |lo: __m512d, hi: __m512d, a: usize| {
        let v = _mm512_mul_pd(
            _mm512_sub_pd(_mm512_add_pd(lo, hi), _mm512_set1_pd(k.o2[a])),
            _mm512_set1_pd(k.hs[a]),
        );
        // As `avx2::position`: `max` maps NaN to 0, then clamp, then truncate.
        let v = _mm512_max_pd(v, _mm512_setzero_pd());
        _mm512_cvttpd_epi32(_mm512_min_pd(v, _mm512_set1_pd(k.maxf[a])))
    };
    let q = [pos(lx, hx, 0), pos(ly, hy, 1), pos(lz, hz, 2)];
    let dx = _mm512_sub_pd(hx, lx);
    let dy = _mm512_sub_pd(hy, ly);
    let dz = _mm512_sub_pd(hz, lz);
    let d2 = _mm512_add_pd(
        _mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
        _mm512_mul_pd(dz, dz),
    );
    (q, d2)
}

/// One step's lanes of the pdep pipeline: `q[channel][lane]` (the size row holds the
/// estimate `k`) and the squared diagonals `d2` as bit patterns.
#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Lanes {
    q: [[u32; 8]; 4],
    d2: [u64; 8],
}

/// The byte indices of the bit shuffle for one output byte `j` of every code, as an
/// `i64x8` broadcast: byte `i` = the bit of the concatenated value `c` that code bit `8j + i`
/// takes (63, a zero bit of `c`, where no channel owns the code bit).
///
/// ```text
///   c    = x | y << nx | z << (nx + ny) | s << (nx + ny + nz)      (nx = bits of x, …)
///   code bit i = c bit perm[i],  perm[i] = offset(ch) + rank of i among ch's mask bits
/// ```
fn shuffle_indices(masks: [u64; 4]) -> [u64; 8] {
    let mut perm = [63u8; 64];
    let mut off = 0u32;
    for m in masks {
        let mut r = 0u32;
        for (i, p) in perm.iter_mut().enumerate() {
            if (m >> i) & 1 == 1 {
                *p = (off + r).min(63) as u8;
                r += 1;
            }
        }
        off += m.count_ones();
    }
    let mut out = [0u64; 8];
    for (j, o) in out.iter_mut().enumerate() {
        let mut b = [0u8; 8];
        b.copy_from_slice(&perm[8 * j..8 * j + 8]);
        *o = u64::from_le_bytes(b);
    }
    out
}

/// Expand eight quantised boxes (`q[channel]` as `i32x8`) into eight codes by bit shuffles:
/// concatenate the channels into one `u64` per lane, then `vpshufbitqmb` gathers output byte
/// `j` of all eight codes into mask `k_j` (bit `8l + i` = code `l` bit `8j + i`), and one
/// `vpermb` transposes the 8×8 bytes of `[k_0 … k_7]` into the codes.
///
/// ```text
///   M = [k_0 k_1 … k_7] (qword j = k_j):  byte 8j + l = code l byte j
///   code l byte j = M byte 8j + l   → vpermb index at byte 8l + j is 8j + l
/// ```
#[target_feature(enable = "avx512f,avx512bw,avx512bitalg,avx512vbmi")]
#[inline]
fn bit_shuffle8(q: [__m256i; 4], shifts: [__m128i; 4], idx: &[__m512i; 8]) -> __m512i {
    let mut c = _mm512_setzero_si512();
    for ch in 0..4 {
        c = _mm512_or_si512(
            c,
            _mm512_sll_epi64(_mm512_cvtepu32_epi64(q[ch]), shifts[ch]),
        );
    }
    let k: [u64; 8] = core::array::from_fn(|j| _mm512_bitshuffle_epi64_mask(c, idx[j]));
    let m = _mm512_set_epi64(
        k[7] as i64,
        k[6] as i64,
        k[5] as i64,
        k[4] as i64,
        k[3] as i64,
        k[2] as i64,
        k[1] as i64,
        k[0] as i64,
    );
    let t: [u8; 64] = core::array::from_fn(|b| (8 * (b % 8) + b / 8) as u8);
    // SAFETY: `t` holds 64 bytes.
    let tv = unsafe { _mm512_loadu_si512(t.as_ptr() as *const __m512i) };
    _mm512_permutexvar_epi8(tv, m)
}

/// The batch pipeline with AVX-512 bit-shuffle expansion (any pattern, `masks` = the
/// layout's channel masks): eight boxes per step, the size channel by `SIZE` (the AVX-512
/// lookup in eight lanes, or the AVX2 step's four-lane paths twice). A lone last group of
/// four is quantised twice and written once. Returns `4·n4`.
///
/// # Safety
/// AVX2 and AVX-512 F/DQ/VL/BW/BITALG/VBMI; `src` holds `4·n4` boxes; `out` valid for `4·n4`
/// codes (`u32` when `W32`).
#[target_feature(enable = "avx2,avx512f,avx512dq,avx512vl,avx512bw,avx512bitalg,avx512vbmi")]
pub(super) unsafe fn run_bit_shuffle<const SIZE: u8, const W32: bool>(
    k: &Kernel,
    masks: [u64; 4],
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let c = Consts::new(k);
    let idx = shuffle_indices(masks).map(|v| _mm512_set1_epi64(v as i64));
    let mut off = 0i64;
    let shifts = masks.map(|m| {
        let s = _mm_cvtsi64_si128(off);
        off += m.count_ones() as i64;
        s
    });
    let join = |a: __m128i, b: __m128i| _mm256_inserti128_si256::<1>(_mm256_castsi128_si256(a), b);
    let mut g = 0;
    while g < n4 {
        let pa = src.wrapping_add(24 * g);
        let pairs = n4 - g >= 2;
        let pb = if pairs { pa.wrapping_add(24) } else { pa };
        let q = if SIZE == SIZE_LOOKUP512 {
            // SAFETY: groups g (and g + 1 when `pairs`) lie inside `src`.
            let ((qa, da), (qb, db)) =
                unsafe { (positions4(k, pa, true), positions4(k, pb, true)) };
            let s = size8(&c, _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(da), db));
            [
                join(qa[0], qb[0]),
                join(qa[1], qb[1]),
                join(qa[2], qb[2]),
                s,
            ]
        } else {
            // SAFETY: as above; the four-lane size paths need only AVX2.
            let (qa, qb) = unsafe { (quantize4::<SIZE>(k, pa), quantize4::<SIZE>(k, pb)) };
            [
                join(qa[0], qb[0]),
                join(qa[1], qb[1]),
                join(qa[2], qb[2]),
                join(qa[3], qb[3]),
            ]
        };
        let codes = bit_shuffle8(q, shifts, &idx);
        // SAFETY: codes 4g .. 4g + 8 (or + 4 without `pairs`) are inside `out`.
        unsafe {
            if W32 {
                let c32 = _mm512_cvtepi64_epi32(codes);
                let o = (out as *mut u32).add(4 * g);
                if pairs {
                    _mm256_storeu_si256(o as *mut __m256i, c32);
                } else {
                    _mm_storeu_si128(o as *mut __m128i, _mm256_castsi256_si128(c32));
                }
            } else {
                let o = (out as *mut u64).add(4 * g);
                if pairs {
                    _mm512_storeu_si512(o as *mut __m512i, codes);
                } else {
                    _mm256_storeu_si256(o as *mut __m256i, _mm512_castsi512_si256(codes));
                }
            }
        }
        g += if pairs { 2 } else { 1 };
    }
    4 * n4
}
