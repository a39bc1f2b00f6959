//! AVX2 kernels of the batch pipeline (x86_64 only): four boxes per step in `f64` lanes, bit for
//! bit the scalar arithmetic of [`crate::quantize`], then byte tables, `u64x4` magic spreads,
//! `pdep` or the reference loop. Entered only after [`crate::cpu::detect`] reported AVX2.
//!
//! One step, four boxes `b0..b3` (24 `f32` each, `#[repr(C)]`: min xyz, max xyz):
//!
//! ```text
//!   a_i = load f32x4 at b_i + 0  = [mnx mny mnz mxx]      b_i = load f32x4 at b_i + 8 bytes
//!                                                            = [mnz mxx mxy mxz]
//!   transpose a_0..a_3 → MNX MNY MNZ (f32x4),  b_0..b_3 → MXX MXY MXZ  (no lane crossing)
//!   f64x4: c2 = MN + MX,  d = MX − MN,  d2 = (dx·dx + dy·dy) + dz·dz        (no FMA)
//!   q_a   = cvtt(min(max((c2 − 2o)·(2^n/E/2), 0), 2^n − 1))   max(v, 0) maps NaN to 0
//! ```

use core::arch::x86_64::*;

use crate::aabb::Aabb;
use crate::expand::table::Table;
use crate::expand::Expander;
use crate::layout::SizeTransform;
use crate::quantize::{Quantizer, MAX_THRESHOLD_BITS};
use crate::simd::SizePath;

/// No size channel.
pub(super) const SIZE_NONE: u8 = 0;
/// Size by an `f32` estimate fixed up with two threshold comparisons (`S <= 8`).
const SIZE_THRESH: u8 = 1;
/// Size by the normative `f64` formula, sqrt transform.
const SIZE_EXACT_SQRT: u8 = 2;
/// Size by the normative `f64` formula, linear transform.
const SIZE_EXACT_LINEAR: u8 = 3;
/// Size by the AVX-512 estimate and one threshold comparison (`S <= 6`, see
/// [`super::avx512`]); only set when [`crate::cpu::has_avx512`] said yes.
pub(super) const SIZE_LOOKUP512: u8 = 4;

/// Per-encoder constants of the AVX2 quantise step.
#[derive(Clone, Debug)]
pub(crate) struct Kernel {
    /// `2·origin` per axis.
    pub(super) o2: [f64; 3],
    /// `2^n / E / 2` per axis.
    pub(super) hs: [f64; 3],
    /// `2^n − 1` per channel (x, y, z, s) as `f64` (exact: at most 31 bits).
    pub(super) maxf: [f64; 4],
    /// One of the `SIZE_*` modes.
    pub(super) size_mode: u8,
    /// `1 / D²` (only an estimate is derived from it).
    pub(super) inv_d2: f64,
    /// `2^S` as `f32` and `2^S − 1` as `i32`.
    pub(super) s_scale_f32: f32,
    pub(super) s_top: i32,
    /// All ones when the transform is linear (selects `rcp` over the second `rsqrt`).
    pub(super) linear: bool,
    /// Frame diagonal `D` and `2^S` for the exact modes.
    pub(super) diag: f64,
    pub(super) s_scale: f64,
    /// The quantiser's thresholds `T(0..2^S)` (`T(0) = 0`), padded with +inf (never read).
    pub(super) thr: [f64; 256],
    /// The CPU has AVX-512 F/DQ/VL ([`crate::cpu::has_avx512`]): without a size channel the
    /// pdep expansion runs the AVX-512 pipeline too.
    avx512: bool,
    /// The layout's channel masks when the batch expands by AVX-512 bit shuffles instead of
    /// the expander (only set after [`crate::cpu::has_avx512_bit_shuffle`] said yes).
    shuffle: Option<[u64; 4]>,
}

impl Kernel {
    /// Constants for a quantiser, or `None` when a channel has more than 31 bits (the
    /// `f64x4 → i32x4` truncation covers `[0, 2^31)`; such layouts stay scalar) or when
    /// `size` is [`SizePath::Avx512Lookup`] and this CPU lacks AVX-512.
    /// `size` picks how an `S <= 8` size channel is computed (larger `S` always uses the
    /// formula, and so does the AVX-512 lookup for `S > 6`; `None` without a size channel).
    pub(crate) fn new(q: &Quantizer, size: SizePath) -> Option<Kernel> {
        let max = q.max();
        if max.iter().any(|&m| m > i32::MAX as u64) {
            return None;
        }
        if size == SizePath::Avx512Lookup && !crate::cpu::has_avx512() {
            return None;
        }
        let s = q.size_bits();
        let mut k = Kernel {
            o2: q.origin2(),
            hs: q.half_scale(),
            maxf: max.map(|m| m as f64),
            size_mode: SIZE_NONE,
            inv_d2: 1.0 / (q.diagonal() * q.diagonal()),
            s_scale_f32: (1u32 << s.min(31)) as f32,
            s_top: (1i32 << s.min(30)) - 1,
            linear: q.transform() == SizeTransform::Linear,
            diag: q.diagonal(),
            s_scale: crate::quantize::pow2(s),
            thr: [f64::INFINITY; 256],
            avx512: crate::cpu::has_avx512(),
            shuffle: None,
        };
        if s == 0 {
            return Some(k);
        }
        match q.thresholds() {
            Some(t) if s <= MAX_THRESHOLD_BITS && size == SizePath::Thresholds => {
                k.thr[..t.len()].copy_from_slice(t);
                k.size_mode = SIZE_THRESH;
            }
            Some(t) if s <= super::avx512::LOOKUP_BITS && size == SizePath::Avx512Lookup => {
                k.thr[..t.len()].copy_from_slice(t);
                k.size_mode = SIZE_LOOKUP512;
            }
            _ => {
                k.size_mode = match q.transform() {
                    SizeTransform::Sqrt => SIZE_EXACT_SQRT,
                    SizeTransform::Linear => SIZE_EXACT_LINEAR,
                };
            }
        }
        Some(k)
    }

    /// Expand by AVX-512 bit shuffles with these channel masks (`Some`), or by the expander
    /// (`None`); false (and no change) when the CPU lacks AVX-512 VBMI/BITALG.
    pub(crate) fn set_bit_shuffle(&mut self, masks: Option<[u64; 4]>) -> bool {
        if masks.is_some() && !crate::cpu::has_avx512_bit_shuffle() {
            return false;
        }
        self.shuffle = masks;
        true
    }

    /// Whether the batch expands by AVX-512 bit shuffles.
    pub(crate) fn bit_shuffle(&self) -> bool {
        self.shuffle.is_some()
    }

    /// Whether a pdep expansion runs the eight-lane AVX-512 pipeline
    /// ([`super::avx512::run_pdep`]), as [`Kernel::encode`] dispatches it.
    pub(crate) fn wide_pdep(&self) -> bool {
        self.shuffle.is_none()
            && (self.size_mode == SIZE_LOOKUP512 || (self.size_mode == SIZE_NONE && self.avx512))
    }

    /// How the size channel is computed (`None` without one).
    pub(crate) fn size_path(&self) -> Option<SizePath> {
        match self.size_mode {
            SIZE_NONE => None,
            SIZE_THRESH => Some(SizePath::Thresholds),
            SIZE_LOOKUP512 => Some(SizePath::Avx512Lookup),
            _ => Some(SizePath::Formula),
        }
    }

    /// Encode the first `4·⌊n/4⌋` boxes into `out` (codes as `u64`, or as `u32` when `W32`),
    /// returning how many were encoded; the caller encodes the rest with the scalar path.
    ///
    /// # Safety
    /// The CPU must support AVX2 (and BMI2 when `exp` is the pdep expander); `out` must be
    /// valid for `boxes.len()` writes of `u64` (or `u32` when `W32`).
    pub(crate) unsafe fn encode<const W32: bool>(
        &self,
        exp: &Expander,
        boxes: &[Aabb],
        out: *mut u8,
    ) -> usize {
        let n4 = boxes.len() / 4;
        let src = boxes.as_ptr() as *const f32;
        macro_rules! by_size {
            ($mode:expr, $s:ident => $e:expr) => {
                match $mode {
                    SIZE_NONE => {
                        const $s: u8 = SIZE_NONE;
                        $e
                    }
                    SIZE_THRESH => {
                        const $s: u8 = SIZE_THRESH;
                        $e
                    }
                    SIZE_EXACT_SQRT => {
                        const $s: u8 = SIZE_EXACT_SQRT;
                        $e
                    }
                    SIZE_LOOKUP512 => {
                        const $s: u8 = SIZE_LOOKUP512;
                        $e
                    }
                    _ => {
                        const $s: u8 = SIZE_EXACT_LINEAR;
                        $e
                    }
                }
            };
        }
        macro_rules! tables {
            ($t:expr, $($nt:literal)*) => {
                match $t.slots().len() {
                    $($nt => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                        table_nt::<S, $nt, W32>(self, $t, src, n4, out)
                    }),)*
                    _ => 0,
                }
            };
        }
        if let Some(m) = self.shuffle {
            return by_size!(self.size_mode, S =>
                // SAFETY: `shuffle` is only set after `has_avx512_bit_shuffle()` said yes (which
                // includes everything the lookup mode needs); `out` by the caller; `n4` groups
                // lie in `boxes`.
                unsafe { super::avx512::run_bit_shuffle::<S, W32>(self, m, src, n4, out) });
        }
        match exp {
            Expander::Table(t) => tables!(t, 1 2 3 4 5 6 7 8 9 10 11 12),
            Expander::Magic(m) => {
                let cnt = m.shifts().map(|s| s.unwrap_or(0) as i64);
                match m.period() {
                    1 => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                        run_magic::<S, 1, W32>(self, cnt, src, n4, out)
                    }),
                    2 => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                        run_magic::<S, 2, W32>(self, cnt, src, n4, out)
                    }),
                    3 => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                        run_magic::<S, 3, W32>(self, cnt, src, n4, out)
                    }),
                    4 => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                        run_magic::<S, 4, W32>(self, cnt, src, n4, out)
                    }),
                    _ => 0,
                }
            }
            Expander::Pdep(p)
                if self.size_mode == SIZE_LOOKUP512
                    || (self.size_mode == SIZE_NONE && self.avx512) =>
            {
                // SAFETY: the lookup mode is only set after `has_avx512()` said yes (see
                // `Kernel::new`), `avx512` is that answer; BMI2 and `out` by the caller; `n4`
                // groups lie in `boxes`.
                unsafe { super::avx512::run_pdep::<W32>(self, p.masks(), src, n4, out) }
            }
            Expander::Pdep(_) => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                run_pdep::<S, W32>(self, exp, src, n4, out)
            }),
            Expander::Reference(_) => by_size!(self.size_mode, S =>
                        // SAFETY: AVX2 (+ BMI2 for pdep) and `out` by the caller; `n4` groups lie in `boxes`.
                        unsafe {
                run_lanes::<S, W32>(self, exp, src, n4, out)
            }),
        }
    }
}

/// Write one code.
///
/// # Safety
/// `out` valid for index `i` of `u64` (or `u32` when `W32`).
#[inline(always)]
unsafe fn put<const W32: bool>(out: *mut u8, i: usize, code: u64) {
    if W32 {
        // SAFETY: by the contract above.
        unsafe { (out as *mut u32).add(i).write_unaligned(code as u32) }
    } else {
        // SAFETY: by the contract above.
        unsafe { (out as *mut u64).add(i).write_unaligned(code) }
    }
}

/// One position channel: `cvtt(min(max((c2 − o2)·hs, 0), max))`.
///
/// `max_pd(v, 0)` returns its second operand when `v` is NaN, so NaN → 0 like the scalar
/// saturating cast; on `[0, 2^n − 1]` truncation equals the scalar `trunc_sat(v).min(max)`
/// (values above the maximum truncate to at least the maximum there, so both give it).
#[target_feature(enable = "avx2")]
#[inline]
fn position(c2: __m256d, o2: f64, hs: f64, max: f64) -> __m128i {
    let v = _mm256_mul_pd(_mm256_sub_pd(c2, _mm256_set1_pd(o2)), _mm256_set1_pd(hs));
    let v = _mm256_max_pd(v, _mm256_setzero_pd());
    let v = _mm256_min_pd(v, _mm256_set1_pd(max));
    _mm256_cvttpd_epi32(v)
}

/// The low 32 bits of each `i64` lane of `v`, as `i32x4`.
#[target_feature(enable = "avx2")]
#[inline]
fn low_dwords(v: __m256i) -> __m128i {
    let lo = _mm_castsi128_ps(_mm256_castsi256_si128(v));
    let hi = _mm_castsi128_ps(_mm256_extracti128_si256::<1>(v));
    _mm_castps_si128(_mm_shuffle_ps::<0b10_00_10_00>(lo, hi))
}

/// The position channels of four boxes (`[qx, qy, qz]`, each `i32x4`) and, when `D2`, their
/// squared diagonals `d2 = (dx·dx + dy·dy) + dz·dz` when `with_d2` (else zero).
///
/// # Safety
/// `p` must point at four consecutive `Aabb` (24 readable `f32`).
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn positions4(
    k: &Kernel,
    p: *const f32,
    with_d2: bool,
) -> ([__m128i; 3], __m256d) {
    // SAFETY: offsets 0..=22 + 4 lanes stay inside the 24 floats of the four boxes.
    let (a0, b0, a1, b1, a2, b2, a3, b3) = unsafe {
        (
            _mm_loadu_ps(p),
            _mm_loadu_ps(p.add(2)),
            _mm_loadu_ps(p.add(6)),
            _mm_loadu_ps(p.add(8)),
            _mm_loadu_ps(p.add(12)),
            _mm_loadu_ps(p.add(14)),
            _mm_loadu_ps(p.add(18)),
            _mm_loadu_ps(p.add(20)),
        )
    };
    // a_i = [mnx mny mnz mxx]: columns 0, 1, 2.
    let t0 = _mm_unpacklo_ps(a0, a1); // a0.0 a1.0 a0.1 a1.1
    let t1 = _mm_unpacklo_ps(a2, a3); // a2.0 a3.0 a2.1 a3.1
    let t2 = _mm_unpackhi_ps(a0, a1); // a0.2 a1.2 a0.3 a1.3
    let t3 = _mm_unpackhi_ps(a2, a3); // a2.2 a3.2 a2.3 a3.3
    let mnx = _mm_movelh_ps(t0, t1);
    let mny = _mm_movehl_ps(t1, t0);
    let mnz = _mm_movelh_ps(t2, t3);
    // b_i = [mnz mxx mxy mxz]: columns 1, 2, 3.
    let u0 = _mm_unpacklo_ps(b0, b1); // b0.0 b1.0 b0.1 b1.1
    let u1 = _mm_unpacklo_ps(b2, b3); // b2.0 b3.0 b2.1 b3.1
    let u2 = _mm_unpackhi_ps(b0, b1); // b0.2 b1.2 b0.3 b1.3
    let u3 = _mm_unpackhi_ps(b2, b3); // b2.2 b3.2 b2.3 b3.3
    let mxx = _mm_movehl_ps(u1, u0);
    let mxy = _mm_movelh_ps(u2, u3);
    let mxz = _mm_movehl_ps(u3, u2);

    let (lx, ly, lz) = (
        _mm256_cvtps_pd(mnx),
        _mm256_cvtps_pd(mny),
        _mm256_cvtps_pd(mnz),
    );
    let (hx, hy, hz) = (
        _mm256_cvtps_pd(mxx),
        _mm256_cvtps_pd(mxy),
        _mm256_cvtps_pd(mxz),
    );
    let qx = position(_mm256_add_pd(lx, hx), k.o2[0], k.hs[0], k.maxf[0]);
    let qy = position(_mm256_add_pd(ly, hy), k.o2[1], k.hs[1], k.maxf[1]);
    let qz = position(_mm256_add_pd(lz, hz), k.o2[2], k.hs[2], k.maxf[2]);
    if !with_d2 {
        return ([qx, qy, qz], _mm256_setzero_pd());
    }
    let dx = _mm256_sub_pd(hx, lx);
    let dy = _mm256_sub_pd(hy, ly);
    let dz = _mm256_sub_pd(hz, lz);
    let d2 = _mm256_add_pd(
        _mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)),
        _mm256_mul_pd(dz, dz),
    );
    ([qx, qy, qz], d2)
}

/// Quantise four boxes: `[qx, qy, qz, qs]`, each `i32x4` (`qs` is 0 when `SIZE` is none).
///
/// # Safety
/// `p` must point at four consecutive `Aabb` (24 readable `f32`); the lookup mode also needs
/// AVX-512 (which [`Kernel::new`] checked before setting it).
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn quantize4<const SIZE: u8>(k: &Kernel, p: *const f32) -> [__m128i; 4] {
    // SAFETY: `p` by the contract above.
    let ([qx, qy, qz], d2) = unsafe { positions4(k, p, SIZE != SIZE_NONE) };
    if SIZE == SIZE_NONE {
        return [qx, qy, qz, _mm_setzero_si128()];
    }
    let qs = match SIZE {
        // SAFETY: the lookup mode is only set after `has_avx512()` said yes.
        SIZE_LOOKUP512 => unsafe { super::avx512::size4(k, d2) },
        // SAFETY: AVX2 by the target feature; `size_thresholds` keeps its gather in bounds.
        SIZE_THRESH => unsafe { size_thresholds(k, d2) },
        SIZE_EXACT_SQRT => {
            let v = _mm256_mul_pd(
                _mm256_sqrt_pd(_mm256_div_pd(_mm256_sqrt_pd(d2), _mm256_set1_pd(k.diag))),
                _mm256_set1_pd(k.s_scale),
            );
            clamp_trunc(v, k.maxf[3])
        }
        _ => {
            let v = _mm256_div_pd(
                _mm256_mul_pd(_mm256_sqrt_pd(d2), _mm256_set1_pd(k.s_scale)),
                _mm256_set1_pd(k.diag),
            );
            clamp_trunc(v, k.maxf[3])
        }
    };
    [qx, qy, qz, qs]
}

/// `cvtt(min(max(v, 0), max))`, the scalar `trunc_sat(v).min(max)` (see [`position`]).
#[target_feature(enable = "avx2")]
#[inline]
fn clamp_trunc(v: __m256d, max: f64) -> __m128i {
    let v = _mm256_max_pd(v, _mm256_setzero_pd());
    _mm256_cvttpd_epi32(_mm256_min_pd(v, _mm256_set1_pd(max)))
}

/// The size channel for `S <= 8`, exactly [`Quantizer::size_by_thresholds`].
///
/// The exact value `q` is the number of thresholds `T(1..2^S)` with `T(j) <= d2`, i.e.
/// `min(⌊x_n⌋, M)` with `x_n` the normative `f64` value and `M = 2^S − 1`. An estimate comes
/// from `f32`: `ρ = clamp(d2 · (1/D²), 0, 1)`, `g = rsqrt(rsqrt(ρ))` (sqrt transform, `≈ ρ^¼`)
/// or `rcp(rsqrt(ρ))` (linear, `≈ ρ^½`), `x_a = g · 2^S`, `k = min(trunc(x_a + ½), M)`.
///
/// Claim: `q ∈ {k − 1, k}`, so `q = k − 1 + [T(k) <= d2]` (one table read per lane).
/// Let `x = 2^S·ρ^e` (`e` = ¼ or ½) be the exact real value for the clamped `ρ`. `x_n` is within
/// a few ulps of `x` (`< 2^-40` for `x <= 2^8`). `ρ` in `f32` carries a relative error below
/// `2^-23` (two `f64` roundings, one `f32` rounding) or, if subnormal or flushed, an absolute
/// error below `2^-126`; `rsqrtps` and `rcpps` have relative error at most `1.5·2^-12` each
/// (both vendors' manuals), so `g` is within a relative `1.5·2^-12·(1 + ½) < 2^-10.4` of
/// `ρ^e` (the first error enters halved or negated), plus `2^S·2^-31` from the absolute case;
/// scaling by `2^S` is exact. With `S <= 8`, `|x_a − x| < 0.2`, and `+ ½` rounds by at most
/// `2^-15`. So `x_a + ½ ∈ [k, k + 1)` puts `x_n` in `(k − 1, k + 1)`: `⌊x_n⌋ ∈ {k − 1, k}`.
/// Clamping keeps it: `x_a <= 2^S·(1 + 2^-10.4)` gives `trunc(x_a + ½) <= 2^S = M + 1`, and when
/// it is `M + 1`, `⌊x_n⌋ >= M` so `q = M` (for `ρ >= 1`, `x_n >= 2^S` and again `q = M`). For
/// `k = 0` the formula reads `−1 + [0 <= d2] = 0`. The comparison is `!(T(k) > d2)`, true for
/// a NaN `d2` too: NaN gives `ρ = 0` (`max` returns its second operand), `k = 0` and `q = 0`,
/// as the scalar search does.
///
/// # Safety
/// Needs AVX2 (the caller's target feature).
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn size_thresholds(k: &Kernel, d2: __m256d) -> __m128i {
    let r = _mm256_mul_pd(d2, _mm256_set1_pd(k.inv_d2));
    let r = _mm256_min_pd(_mm256_max_pd(r, _mm256_setzero_pd()), _mm256_set1_pd(1.0));
    let rf = _mm256_cvtpd_ps(r);
    let y = _mm_rsqrt_ps(rf);
    let lin = _mm_castsi128_ps(_mm_set1_epi32(-(k.linear as i32)));
    let g = _mm_blendv_ps(_mm_rsqrt_ps(y), _mm_rcp_ps(y), lin);
    let x = _mm_add_ps(_mm_mul_ps(g, _mm_set1_ps(k.s_scale_f32)), _mm_set1_ps(0.5));
    let est = _mm_min_epi32(_mm_cvttps_epi32(x), _mm_set1_epi32(k.s_top));
    // Four scalar loads beat `vgatherdpd` here (measured); `& 255` keeps them in bounds
    // (`est` is already in 0..=2^S − 1 <= 255: clamped above, truncation of a non-negative).
    let th = |i: i32| k.thr[i as usize & 255];
    let t = _mm256_set_pd(
        th(_mm_extract_epi32::<3>(est)),
        th(_mm_extract_epi32::<2>(est)),
        th(_mm_extract_epi32::<1>(est)),
        th(_mm_cvtsi128_si32(est)),
    );
    // All-ones where !(T(k) > d2): subtracting the mask adds one.
    let m = _mm256_castpd_si256(_mm256_cmp_pd::<_CMP_NGT_UQ>(t, d2));
    _mm_sub_epi32(_mm_add_epi32(est, _mm_set1_epi32(-1)), low_dwords(m))
}

/// Groups of four boxes the table kernel quantises before it expands them: splitting the two
/// phases helps the load-heavy table loop (measured 5.6 against 6.3 ns/code for `emc64-var`),
/// while the pdep kernel runs one group at a time, software-pipelined (3.4 against 4.2 ns/code
/// for quantise-all-then-expand, measured before the pipelining), and the lane kernel fused.
/// The block (`64 × 64 B`) stays in L1.
const TABLE_BLOCK: usize = 64;

/// Quantise groups `g0 .. g0 + lanes.len()` into `lanes[j][channel][lane]`.
///
/// # Safety
/// AVX2; those groups of four boxes lie inside `src`.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn quantize_block<const SIZE: u8>(
    k: &Kernel,
    src: *const f32,
    g0: usize,
    lanes: &mut [[[u32; 4]; 4]],
) {
    for (j, l) in lanes.iter_mut().enumerate() {
        // SAFETY: group g0 + j lies inside `src` by the contract above.
        let q = unsafe { quantize4::<SIZE>(k, src.add(24 * (g0 + j))) };
        for (row, v) in l.iter_mut().zip(q) {
            // SAFETY: each row holds four u32.
            unsafe { _mm_storeu_si128(row.as_mut_ptr() as *mut __m128i, v) };
        }
    }
}

/// Byte-table expansion of `n4` groups with exactly `NT` tables.
///
/// # Safety
/// AVX2; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes.
#[target_feature(enable = "avx2")]
unsafe fn table_nt<const SIZE: u8, const NT: usize, const W32: bool>(
    k: &Kernel,
    t: &Table,
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let Ok(tabs) = <&[[u64; 256]; NT]>::try_from(t.entries()) else {
        return 0;
    };
    // Lanes are stored as four i32x4 (x, y, z, s): byte j of channel c, lane l is at
    // 16c + 4l + j. Each slot's offset for lane 0:
    let mut offs = [0usize; NT];
    for (o, &(c, j)) in offs.iter_mut().zip(t.slots()) {
        *o = 16 * (c as usize & 3) + (j as usize & 3);
    }
    let mut lanes = [[[0u32; 4]; 4]; TABLE_BLOCK];
    let mut g0 = 0;
    while g0 < n4 {
        let m = (n4 - g0).min(TABLE_BLOCK);
        // SAFETY: groups g0..g0 + m are inside `src`.
        unsafe { quantize_block::<SIZE>(k, src, g0, &mut lanes[..m]) };
        for (j, q) in lanes[..m].iter().enumerate() {
            let bytes = q.as_ptr() as *const u8;
            for l in 0..4 {
                let mut code = 0u64;
                for i in 0..NT {
                    // SAFETY: offs[i] <= 51 and 4l <= 12, inside the 64 bytes of `q`.
                    let byte = unsafe { *bytes.add(offs[i] + 4 * l) };
                    code |= tabs[i][byte as usize];
                }
                // SAFETY: index 4(g0 + j) + l < 4·n4.
                unsafe { put::<W32>(out, 4 * (g0 + j) + l, code) };
            }
        }
        g0 += m;
    }
    4 * n4
}

/// `(x | x << S) & m` on four `u64` lanes.
#[target_feature(enable = "avx2")]
#[inline]
fn stage<const S: i32>(x: __m256i, m: u64) -> __m256i {
    _mm256_and_si256(
        _mm256_or_si256(x, _mm256_slli_epi64::<S>(x)),
        _mm256_set1_epi64x(m as i64),
    )
}

/// The spreads of [`crate::expand::magic`] on four `u64` lanes (values already within width).
#[target_feature(enable = "avx2")]
#[inline]
fn spread<const K: u32>(x: __m256i) -> __m256i {
    match K {
        1 => x,
        2 => {
            let x = stage::<16>(x, 0x0000_FFFF_0000_FFFF);
            let x = stage::<8>(x, 0x00FF_00FF_00FF_00FF);
            let x = stage::<4>(x, 0x0F0F_0F0F_0F0F_0F0F);
            let x = stage::<2>(x, 0x3333_3333_3333_3333);
            stage::<1>(x, 0x5555_5555_5555_5555)
        }
        3 => {
            let x = stage::<32>(x, 0x001F_0000_0000_FFFF);
            let x = stage::<16>(x, 0x001F_0000_FF00_00FF);
            let x = stage::<8>(x, 0x100F_00F0_0F00_F00F);
            let x = stage::<4>(x, 0x10C3_0C30_C30C_30C3);
            stage::<2>(x, 0x1249_2492_4924_9249)
        }
        _ => {
            let x = stage::<24>(x, 0x0000_00FF_0000_00FF);
            let x = stage::<12>(x, 0x000F_000F_000F_000F);
            let x = stage::<6>(x, 0x0303_0303_0303_0303);
            stage::<3>(x, 0x1111_1111_1111_1111)
        }
    }
}

/// Magic-bits expansion of `n4` groups for a regular pattern of period `K`.
///
/// # Safety
/// AVX2; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes.
#[target_feature(enable = "avx2")]
unsafe fn run_magic<const SIZE: u8, const K: u32, const W32: bool>(
    k: &Kernel,
    shifts: [i64; 4],
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let cnt = shifts.map(|s| _mm_cvtsi64_si128(s & 63));
    for g in 0..n4 {
        // SAFETY: group g is boxes 4g..4g+4 of `src`.
        let q = unsafe { quantize4::<SIZE>(k, src.add(24 * g)) };
        // Unused channels quantise to 0 (maximum 0) and add nothing.
        let mut code = _mm256_sll_epi64(spread::<K>(_mm256_cvtepu32_epi64(q[0])), cnt[0]);
        code = _mm256_or_si256(
            code,
            _mm256_sll_epi64(spread::<K>(_mm256_cvtepu32_epi64(q[1])), cnt[1]),
        );
        code = _mm256_or_si256(
            code,
            _mm256_sll_epi64(spread::<K>(_mm256_cvtepu32_epi64(q[2])), cnt[2]),
        );
        if SIZE != SIZE_NONE {
            code = _mm256_or_si256(
                code,
                _mm256_sll_epi64(spread::<K>(_mm256_cvtepu32_epi64(q[3])), cnt[3]),
            );
        }
        if W32 {
            // SAFETY: four u32 codes at 4g..4g+4 are inside `out`.
            unsafe {
                _mm_storeu_si128(
                    (out as *mut u32).add(4 * g) as *mut __m128i,
                    low_dwords(code),
                )
            };
        } else {
            // SAFETY: four u64 codes at 4g..4g+4 are inside `out`.
            unsafe { _mm256_storeu_si256((out as *mut u64).add(4 * g) as *mut __m256i, code) };
        }
    }
    4 * n4
}

/// `pdep` expansion of each lane.
///
/// # Safety
/// AVX2 and BMI2; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes.
#[target_feature(enable = "avx2,bmi2")]
#[allow(clippy::needless_range_loop)] // `l` picks the same lane from each channel's row
unsafe fn run_pdep<const SIZE: u8, const W32: bool>(
    k: &Kernel,
    exp: &Expander,
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let Expander::Pdep(p) = exp else {
        return 0;
    };
    let m = p.masks();
    // Software-pipelined: step g quantises group g into `next` while the pdeps of group g − 1
    // (in `q`) run, so the two dependency chains overlap. Zen 4, 16K boxes in cache, times the
    // streaming baseline: morton63 2.2 against 2.4 fused; emc64-var with the f64 size formula
    // 3.8 against 4.0.
    // Two buffers, used alternately: group g goes to buf[g % 2].
    let mut buf = [[[0u32; 4]; 4]; 2];
    for g in 0..=n4 {
        let (lo, hi) = buf.split_at_mut(1);
        let (next, q) = if g % 2 == 0 {
            (&mut lo[0], &hi[0])
        } else {
            (&mut hi[0], &lo[0])
        };
        if g < n4 {
            // SAFETY: group g lies inside `src`.
            let v = unsafe { quantize4::<SIZE>(k, src.add(24 * g)) };
            for (row, x) in next.iter_mut().zip(v) {
                // SAFETY: each row holds four u32.
                unsafe { _mm_storeu_si128(row.as_mut_ptr() as *mut __m128i, x) };
            }
        }
        if g > 0 {
            for l in 0..4 {
                let mut code = _pdep_u64(q[0][l] as u64, m[0])
                    | _pdep_u64(q[1][l] as u64, m[1])
                    | _pdep_u64(q[2][l] as u64, m[2]);
                if SIZE != SIZE_NONE {
                    code |= _pdep_u64(q[3][l] as u64, m[3]);
                }
                // SAFETY: index 4(g − 1) + l < 4·n4.
                unsafe { put::<W32>(out, 4 * (g - 1) + l, code) };
            }
        }
    }
    4 * n4
}

/// Any other expander, called once per lane (the forced reference backend).
///
/// # Safety
/// AVX2; `src` holds `4·n4` boxes; `out` valid for `4·n4` codes.
#[target_feature(enable = "avx2")]
#[allow(clippy::needless_range_loop)] // `l` picks the same lane from each channel's row
unsafe fn run_lanes<const SIZE: u8, const W32: bool>(
    k: &Kernel,
    exp: &Expander,
    src: *const f32,
    n4: usize,
    out: *mut u8,
) -> usize {
    let mut lanes = [[[0u32; 4]; 4]; 1];
    let mut g0 = 0;
    while g0 < n4 {
        let m = (n4 - g0).min(1);
        // SAFETY: groups g0..g0 + m are inside `src`.
        unsafe { quantize_block::<SIZE>(k, src, g0, &mut lanes[..m]) };
        for (j, q) in lanes[..m].iter().enumerate() {
            for l in 0..4 {
                let code = exp.expand([
                    q[0][l] as u64,
                    q[1][l] as u64,
                    q[2][l] as u64,
                    q[3][l] as u64,
                ]);
                // SAFETY: index 4(g0 + j) + l < 4·n4.
                unsafe { put::<W32>(out, 4 * (g0 + j) + l, code) };
            }
        }
        g0 += m;
    }
    4 * n4
}
