//! The min-plus step of the wide-tree cover DP (Ylitie, Karras and Laine 2017) that `wide.rs`
//! and `wide_lbvh.rs` run once per binary node: from the cover costs of the two children by
//! 1..W slots, the cheapest split of `j` slots between them. AVX2 for eight slots (all `j` in
//! the lanes of one register), plain loops otherwise; both give the same bits.
//!
//! ```text
//!   dist(j)  = min over k in 1..j of  cl[k − 1] + cr[j − k − 1]      j = 2..=W
//!   split(j) = the smallest k reaching it, 1 when none is below +inf
//!                                                       (lane j − 1; lane 0 unused: +inf, 0)
//! ```

/// `(dist, split)` of the DP step for children cost rows `cl`, `cr` (see the module docs).
#[inline(always)]
pub fn dist<const W: usize>(cl: &[f32; W], cr: &[f32; W]) -> ([f32; W], [u8; W]) {
    #[cfg(target_arch = "x86_64")]
    if W == 8 && crate::trace::traverse::avx2_available() {
        let (l, r): (&[f32; 8], &[f32; 8]) = (
            cl.as_slice().try_into().expect("W = 8"),
            cr.as_slice().try_into().expect("W = 8"),
        );
        // SAFETY: the CPU has AVX2 (checked just above).
        let (d, s) = unsafe { avx2::dist8(l, r) };
        return (
            d.as_slice().try_into().expect("W = 8"),
            s.as_slice().try_into().expect("W = 8"),
        );
    }
    dist_scalar(cl, cr)
}

/// The plain loops of [`dist`] (the reference).
#[inline(always)]
pub fn dist_scalar<const W: usize>(cl: &[f32; W], cr: &[f32; W]) -> ([f32; W], [u8; W]) {
    let mut dist = [f32::INFINITY; W];
    // k = 1 until a candidate is strictly lower: a valid split even when every candidate is
    // +inf or NaN (boxes of overflowing areas), never the 0 slots that would leave a side
    // empty.
    let mut split = [1u8; W];
    split[0] = 0;
    for j in 2..=W {
        for k in 1..j {
            let c = cl[k - 1] + cr[j - k - 1];
            if c < dist[j - 1] {
                dist[j - 1] = c;
                split[j - 1] = k as u8;
            }
        }
    }
    (dist, split)
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use core::arch::x86_64::*;

    /// [`super::dist_scalar`] for eight slots: for each `k`, lane `d` (= `j − 1`) gets
    /// `cl[k − 1] + cr[d − k]` for `d ≥ k` (+inf below), kept where strictly lower than the
    /// best so far, so the smallest `k` wins ties as in the loops.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn dist8(cl: &[f32; 8], cr: &[f32; 8]) -> ([f32; 8], [u8; 8]) {
        // SAFETY: AVX2 is enabled; the loads and stores touch the eight floats of `cl`, `cr`
        // and the outputs.
        unsafe {
            let inf = _mm256_set1_ps(f32::INFINITY);
            let r = _mm256_loadu_ps(cr.as_ptr());
            let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let mut dist = inf;
            // k = 1 until a candidate is strictly lower (as the loops).
            let mut split = _mm256_setr_epi32(0, 1, 1, 1, 1, 1, 1, 1);
            for k in 1..8i32 {
                let kk = _mm256_set1_epi32(k);
                // Lane d takes cr[d − k]: indices wrap for d < k and are masked to +inf.
                let idx = _mm256_sub_epi32(lane, kk);
                let shifted = _mm256_permutevar8x32_ps(r, idx);
                let below = _mm256_castsi256_ps(_mm256_cmpgt_epi32(kk, lane));
                let shifted = _mm256_blendv_ps(shifted, inf, below);
                let cand = _mm256_add_ps(_mm256_set1_ps(cl[k as usize - 1]), shifted);
                let better = _mm256_cmp_ps::<_CMP_LT_OQ>(cand, dist);
                dist = _mm256_blendv_ps(dist, cand, better);
                split = _mm256_blendv_epi8(split, kk, _mm256_castps_si256(better));
            }
            let mut d = [0.0f32; 8];
            _mm256_storeu_ps(d.as_mut_ptr(), dist);
            let mut s = [0i32; 8];
            _mm256_storeu_si256(s.as_mut_ptr().cast(), split);
            (d, s.map(|x| x as u8))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simd_equals_the_loops() {
        // Rows as the DP makes them (non-decreasing costs, some +inf, many ties).
        let mut x = 0x9e37_79b9u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        for _ in 0..20_000 {
            let mut row = || {
                let mut r = [0.0f32; 8];
                let mut v = (next() % 64) as f32 * 0.25;
                let all_inf = next() % 17 == 0;
                for e in r.iter_mut() {
                    *e = if all_inf || next() % 11 == 0 {
                        f32::INFINITY
                    } else {
                        v
                    };
                    v += [0.0, 0.5, 1.0, 0.125][(next() % 4) as usize];
                }
                r
            };
            let (l, r) = (row(), row());
            let (a, sa) = dist(&l, &r);
            let (b, sb) = dist_scalar(&l, &r);
            assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "{l:?} {r:?}");
            assert_eq!(sa, sb, "{l:?} {r:?}");
        }
    }
}
