//! The per-box tests of the sample's one pass over all boxes ([`mod@super::estimate`]): which of
//! eight boxes pass the size prefilter and which have their centre inside one of the dense
//! windows' boxes. Three implementations with one signature, as bit masks: the plain one,
//! SSE2 (every x86-64 CPU has it) and AVX (eight boxes per instruction, where the CPU has it,
//! decided once at run time); all give the same bits (`tests` below).

use emc_core::Aabb;

/// Most window boxes a test takes.
pub const MAX_WINDOWS: usize = 4;

/// A window box `[lo, hi]` per axis, for `min + max` of a box.
pub type Window = ([f32; 3], [f32; 3]);

/// The boxes of a block (at most 8) as two masks, bit `l` for `blk[l]`: the squared diagonal
/// (in `f32`) at least `pre`, and `min + max` (in `f32`) inside `[lo, hi]` on every axis for
/// one of `wins` (at most [`MAX_WINDOWS`]; the rest are ignored).
/// The size test is a conservative prefilter (the caller compares the exact `f64` value of
/// every box that passes), so its `f32` summation order is free; the centre test is exact.
#[inline]
pub fn block_masks(blk: &[Aabb], pre: f32, wins: &[Window]) -> (u32, u32) {
    #[cfg(target_arch = "x86_64")]
    {
        sse2::block_masks(blk, pre, wins)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        plain::block_masks(blk, pre, wins)
    }
}

/// The masks of every block of 8 of `chunk` (the last may be shorter), in order:
/// `f(first index, size mask, window mask)`, by the fastest implementation the CPU has.
#[inline]
pub fn for_each_block(
    chunk: &[Aabb],
    pre: f32,
    wins: &[Window],
    mut f: impl FnMut(usize, u32, u32),
) {
    #[cfg(target_arch = "x86_64")]
    if avx::available() {
        // SAFETY: the CPU has AVX (checked just above).
        unsafe { avx::for_each_block(chunk, pre, wins, &mut f) };
        return;
    }
    for (j, blk) in chunk.chunks(8).enumerate() {
        let (size, inside) = block_masks(blk, pre, wins);
        f(8 * j, size, inside);
    }
}

/// The reference: one box at a time in scalar `f32`.
pub mod plain {
    use super::{Window, MAX_WINDOWS};
    use emc_core::Aabb;

    /// See [`super::block_masks`].
    #[inline]
    pub fn block_masks(blk: &[Aabb], pre: f32, wins: &[Window]) -> (u32, u32) {
        let wins = &wins[..wins.len().min(MAX_WINDOWS)];
        let (mut size, mut inside) = (0u32, 0u32);
        for (l, b) in blk.iter().enumerate().take(8) {
            let d = b.max - b.min;
            size |= ((d.x * d.x + d.y * d.y + d.z * d.z >= pre) as u32) << l;
            let c = [b.min.x + b.max.x, b.min.y + b.max.y, b.min.z + b.max.z];
            let ok = wins
                .iter()
                .any(|(lo, hi)| (0..3).all(|a| c[a] >= lo[a] && c[a] <= hi[a]));
            inside |= (ok as u32) << l;
        }
        (size, inside)
    }
}

/// SSE2, four boxes per step: each box's six floats in two overlapping 16-byte loads, its
/// extent and doubled centre in one subtraction and one addition, then two 4×4 transposes so
/// that the size sums and the window tests run on four boxes per instruction.
#[cfg(target_arch = "x86_64")]
pub mod sse2 {
    use super::{Window, MAX_WINDOWS};
    use core::arch::x86_64::*;
    use emc_core::Aabb;

    /// Rows `r[0..3]` to columns 0, 1, 2 (the fourth lanes are dropped).
    #[inline(always)]
    fn columns(r: [__m128; 4]) -> [__m128; 3] {
        // SAFETY: SSE2 is part of the x86-64 baseline; register shuffles only.
        unsafe {
            let t0 = _mm_unpacklo_ps(r[0], r[1]); // r0.x r1.x r0.y r1.y
            let t1 = _mm_unpacklo_ps(r[2], r[3]); // r2.x r3.x r2.y r3.y
            let t2 = _mm_unpackhi_ps(r[0], r[1]); // r0.z r1.z r0.w r1.w
            let t3 = _mm_unpackhi_ps(r[2], r[3]); // r2.z r3.z r2.w r3.w
            [
                _mm_movelh_ps(t0, t1),
                _mm_movehl_ps(t1, t0),
                _mm_movelh_ps(t2, t3),
            ]
        }
    }

    /// See [`super::block_masks`].
    #[inline]
    pub fn block_masks(blk: &[Aabb], pre: f32, wins: &[Window]) -> (u32, u32) {
        let k = wins.len().min(MAX_WINDOWS);
        let n = blk.len().min(8);
        // SAFETY: SSE2 is part of the x86-64 baseline. `Aabb` is `repr(C)` of six `f32`
        // (min.xyz, max.xyz, 24 bytes): for box `i < n` the loads read floats 0..4 and 2..6
        // of `blk[i]` only, inside the slice.
        unsafe {
            let pre4 = _mm_set1_ps(pre);
            let mut wl = [[_mm_setzero_ps(); 3]; MAX_WINDOWS];
            let mut wh = [[_mm_setzero_ps(); 3]; MAX_WINDOWS];
            for (w, (lo, hi)) in wins[..k].iter().enumerate() {
                for a in 0..3 {
                    wl[w][a] = _mm_set1_ps(lo[a]);
                    wh[w][a] = _mm_set1_ps(hi[a]);
                }
            }
            let (mut size, mut inside) = (0u32, 0u32);
            let mut base = 0;
            while base < n {
                // Four boxes; past the end of a short block the last one again (masked off).
                let m = (n - base).min(4);
                let mut d = [_mm_setzero_ps(); 4];
                let mut c = [_mm_setzero_ps(); 4];
                for j in 0..4 {
                    let p = (&blk[base + j.min(m - 1)] as *const Aabb).cast::<f32>();
                    // a = [min.x, min.y, min.z, max.x], t = [min.z, max.x, max.y, max.z]
                    let a = _mm_loadu_ps(p);
                    let t = _mm_loadu_ps(p.add(2));
                    // hi = [max.x, max.y, max.z, max.z]
                    let hi = _mm_shuffle_ps::<0b11_11_10_01>(t, t);
                    d[j] = _mm_sub_ps(hi, a);
                    c[j] = _mm_add_ps(a, hi);
                }
                let keep = (1u32 << m) - 1;
                let [dx, dy, dz] = columns(d);
                // (dx² + dy²) + dz², the plain implementation's order.
                let d2 = _mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(dx, dx), _mm_mul_ps(dy, dy)),
                    _mm_mul_ps(dz, dz),
                );
                size |= (_mm_movemask_ps(_mm_cmpge_ps(d2, pre4)) as u32 & keep) << base;
                let cc = columns(c);
                let mut any = _mm_setzero_ps();
                for w in 0..k {
                    let mut ok = _mm_castsi128_ps(_mm_set1_epi32(-1));
                    for a in 0..3 {
                        let lo_ok = _mm_cmpge_ps(cc[a], wl[w][a]);
                        let hi_ok = _mm_cmple_ps(cc[a], wh[w][a]);
                        ok = _mm_and_ps(ok, _mm_and_ps(lo_ok, hi_ok));
                    }
                    any = _mm_or_ps(any, ok);
                }
                inside |= (_mm_movemask_ps(any) as u32 & keep) << base;
                base += 4;
            }
            (size, inside)
        }
    }
}

/// AVX, eight boxes per step: the SSE2 steps on both 128-bit halves at once (boxes `j` and
/// `j + 4` share a register), so the transposes stay within the halves.
#[cfg(target_arch = "x86_64")]
pub mod avx {
    use super::{Window, MAX_WINDOWS};
    use core::arch::x86_64::*;
    use emc_core::Aabb;

    /// Whether the CPU has AVX (std caches the answer).
    #[inline]
    pub fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx")
    }

    /// Rows to columns 0, 1, 2 within each 128-bit half.
    #[inline]
    #[target_feature(enable = "avx")]
    fn columns(r: [__m256; 4]) -> [__m256; 3] {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpacklo_ps(r[2], r[3]);
        let t2 = _mm256_unpackhi_ps(r[0], r[1]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        [
            _mm256_shuffle_ps::<0b01_00_01_00>(t0, t1),
            _mm256_shuffle_ps::<0b11_10_11_10>(t0, t1),
            _mm256_shuffle_ps::<0b01_00_01_00>(t2, t3),
        ]
    }

    /// [`super::for_each_block`] with AVX.
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[target_feature(enable = "avx")]
    pub unsafe fn for_each_block(
        chunk: &[Aabb],
        pre: f32,
        wins: &[Window],
        f: &mut impl FnMut(usize, u32, u32),
    ) {
        let k = wins.len().min(MAX_WINDOWS);
        let pre8 = _mm256_set1_ps(pre);
        let mut wl = [[_mm256_setzero_ps(); 3]; MAX_WINDOWS];
        let mut wh = [[_mm256_setzero_ps(); 3]; MAX_WINDOWS];
        for (w, (lo, hi)) in wins[..k].iter().enumerate() {
            for a in 0..3 {
                wl[w][a] = _mm256_set1_ps(lo[a]);
                wh[w][a] = _mm256_set1_ps(hi[a]);
            }
        }
        let mut blocks = chunk.chunks_exact(8);
        let mut first = 0;
        for blk in blocks.by_ref() {
            let mut d = [_mm256_setzero_ps(); 4];
            let mut c = [_mm256_setzero_ps(); 4];
            for j in 0..4 {
                let p0 = (&blk[j] as *const Aabb).cast::<f32>();
                let p1 = (&blk[j + 4] as *const Aabb).cast::<f32>();
                // SAFETY: `Aabb` is `repr(C)` of six `f32`; each load reads floats 0..4 or
                // 2..6 of one box of the block.
                let (a, t) = unsafe {
                    (
                        _mm256_loadu2_m128(p1, p0),
                        _mm256_loadu2_m128(p1.add(2), p0.add(2)),
                    )
                };
                let hi = _mm256_permute_ps::<0b11_11_10_01>(t);
                d[j] = _mm256_sub_ps(hi, a);
                c[j] = _mm256_add_ps(a, hi);
            }
            let [dx, dy, dz] = columns(d);
            let d2 = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)),
                _mm256_mul_ps(dz, dz),
            );
            let size = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(d2, pre8)) as u32;
            let cc = columns(c);
            let mut any = _mm256_setzero_ps();
            for w in 0..k {
                let mut ok = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
                for a in 0..3 {
                    let lo_ok = _mm256_cmp_ps::<_CMP_GE_OQ>(cc[a], wl[w][a]);
                    let hi_ok = _mm256_cmp_ps::<_CMP_LE_OQ>(cc[a], wh[w][a]);
                    ok = _mm256_and_ps(ok, _mm256_and_ps(lo_ok, hi_ok));
                }
                any = _mm256_or_ps(any, ok);
            }
            // Lanes: boxes 0..3 in the low half, 4..7 in the high half: bit l is box l.
            let inside = _mm256_movemask_ps(any) as u32;
            f(first, size, inside);
            first += 8;
        }
        let rest = blocks.remainder();
        if !rest.is_empty() {
            let (size, inside) = super::sse2::block_masks(rest, pre, wins);
            f(first, size, inside);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use emc_core::glam::Vec3;

    /// Both implementations agree on random boxes, boxes on the bounds and the threshold,
    /// zero-size boxes, huge and subnormal ones, and partial blocks.
    #[test]
    fn the_implementations_agree() {
        let mut s = 0x1234_5678_9abc_def1u64;
        let mut r = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut f = move || {
            let v = r();
            match v % 6 {
                0 => 0.0,
                1 => f32::from_bits((v >> 32) as u32 & 0x007f_ffff),
                2 => ((v >> 16) as u32 as f32) * 1e30 / u32::MAX as f32,
                _ => ((v >> 8) as u32 as f32 / u32::MAX as f32) * 4.0 - 2.0,
            }
        };
        let mut boxes = Vec::new();
        for _ in 0..20_000 {
            let (a, b) = (Vec3::new(f(), f(), f()), Vec3::new(f(), f(), f()));
            boxes.push(Aabb::new(a.min(b), a.max(b)));
        }
        // Centres exactly on the window bounds.
        boxes.push(Aabb::new(Vec3::splat(-0.5), Vec3::splat(-0.5)));
        boxes.push(Aabb::new(Vec3::splat(0.25), Vec3::splat(0.25)));
        let wins: [Window; 5] = [
            ([-1.0, -0.5, -2.0], [0.5, 1.0, 0.5]),
            ([0.25, 0.25, 0.25], [0.25, 0.25, 0.25]),
            ([-3.0, 1.0, -3.0], [3.0, 1.5, 3.0]),
            ([1e29, -4.0, -4.0], [2e30, 4.0, 4.0]),
            ([-4.0; 3], [4.0; 3]),
        ];
        for pre in [0.0, 1e-30, 0.5, 3.0, 1e20, f32::INFINITY] {
            for w in 0..=5 {
                let mut i = 0;
                for_each_block(&boxes[..boxes.len() - 3], pre, &wins[..w], |first, a, b| {
                    assert_eq!(first, 8 * i);
                    let blk = &boxes[first..(first + 8).min(boxes.len() - 3)];
                    assert_eq!((a, b), plain::block_masks(blk, pre, &wins[..w]), "{blk:?}");
                    i += 1;
                });
                assert_eq!(i, (boxes.len() - 3).div_ceil(8));
                for (n, blk) in boxes.chunks(8).enumerate() {
                    let blk = &blk[..(n % 9).min(blk.len())];
                    assert_eq!(
                        block_masks(blk, pre, &wins[..w]),
                        plain::block_masks(blk, pre, &wins[..w]),
                        "{blk:?} pre {pre}"
                    );
                }
            }
        }
    }
}
