//! AVX-512 size step of the batch pipeline (x86_64 only): the size channel of eight boxes at a
//! time without a square root or a divide, bit for bit [`Quantizer::size_by_thresholds`]. The
//! positions still come from the AVX2 step ([`super::avx2`]); entered only after
//! [`crate::cpu::has_avx512`] said yes.
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
//! [`Quantizer::size_by_thresholds`]: crate::Quantizer::size_by_thresholds

use core::arch::x86_64::*;

use super::avx2::{positions4, quantize4, Kernel, SIZE_LOOKUP512};

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
    let r = _mm512_mul_pd(d2, c.inv_d2);
    let r = _mm512_max_pd(r, _mm512_set1_pd(f64::from_bits((1023 - 600) << 52)));
    let r = _mm512_min_pd(r, _mm512_set1_pd(1.0));
    let y = _mm512_rsqrt14_pd(r);
    let g = if c.linear {
        _mm512_rcp14_pd(y)
    } else {
        _mm512_rsqrt14_pd(y)
    };
    let x = _mm512_add_pd(_mm512_mul_pd(g, c.scale), _mm512_set1_pd(0.5));
    let k = _mm512_min_epi64(_mm512_cvttpd_epi64(x), c.top);
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

/// The dispatched `pdep` pipeline with the AVX-512 size step: eight boxes per step (a lone
/// last group of four is quantised twice and written once). Returns `4·n4`.
///
/// # Safety
/// AVX2, BMI2 and AVX-512 F/DQ/VL; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes
/// (`u32` when `W32`).
#[target_feature(enable = "avx2,bmi2,avx512f,avx512dq,avx512vl")]
#[allow(clippy::needless_range_loop)] // `l` picks the same lane from each channel's row
pub(super) unsafe fn run_pdep<const W32: bool>(
    k: &Kernel,
    m: [u64; 4],
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let c = Consts::new(k);
    // The size channel (at most `LOOKUP_BITS` bits here) is deposited by a table load instead
    // of a fourth `pdep`: `st[v] = pdep(v, m[3])` for every 6-bit `v`, built once per batch.
    // Loads run on the address units while the `pdep`s compete for the integer ALUs.
    let st: [u64; 64] = core::array::from_fn(|v| _pdep_u64(v as u64, m[3]));
    // Software-pipelined: step g quantises its pair into `next` while the pdeps of the
    // previous pair (in `q`) run, so the two dependency chains overlap.
    let mut q = [[0u32; 8]; 4];
    let mut prev: Option<(usize, usize)> = None; // (first code, codes) held in `q`
    let mut g = 0;
    loop {
        let mut next = [[0u32; 8]; 4];
        let cur = if g < n4 {
            let pa = src.wrapping_add(24 * g);
            let pairs = n4 - g >= 2;
            let pb = if pairs { pa.wrapping_add(24) } else { pa };
            // SAFETY: groups g (and g + 1 when `pairs`) lie inside `src`.
            let ((qa, da), (qb, db)) =
                unsafe { (positions4(k, pa, true), positions4(k, pb, true)) };
            let s = size8(&c, _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(da), db));
            // Already in `0 ..= 2^S − 1` (see `size8`); the mask makes the table index
            // obviously in bounds for the unchecked read below.
            let s = _mm256_and_si256(s, _mm256_set1_epi32(63));
            for ch in 0..3 {
                let row = next[ch].as_mut_ptr() as *mut __m128i;
                // SAFETY: each row holds eight u32: two stores of four.
                unsafe {
                    _mm_storeu_si128(row, qa[ch]);
                    _mm_storeu_si128(row.add(1), qb[ch]);
                }
            }
            // SAFETY: the size row holds eight u32.
            unsafe { _mm256_storeu_si256(next[3].as_mut_ptr() as *mut __m256i, s) };
            let lanes = if pairs { 8 } else { 4 };
            g += lanes / 4;
            Some((4 * g - lanes, lanes))
        } else {
            None
        };
        if let Some((first, lanes)) = prev {
            for l in 0..lanes {
                let code = _pdep_u64(q[0][l] as u64, m[0])
                    | _pdep_u64(q[1][l] as u64, m[1])
                    | _pdep_u64(q[2][l] as u64, m[2])
                    // SAFETY: `q[3][l] < 64` (masked above) and `st` has 64 entries.
                    | unsafe { *st.get_unchecked(q[3][l] as usize) };
                let i = first + l;
                // SAFETY: `i < 4·n4` by the contract above.
                unsafe {
                    if W32 {
                        (out as *mut u32).add(i).write_unaligned(code as u32);
                    } else {
                        (out as *mut u64).add(i).write_unaligned(code);
                    }
                }
            }
        }
        if cur.is_none() {
            break;
        }
        q = next;
        prev = cur;
    }
    4 * n4
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
