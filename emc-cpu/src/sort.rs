//! Parallel LSD radix sort of (code, primitive index) pairs: step 3 of the LBVH pipeline.
//! Stable, 8-bit digits, passes whose digit is the same in every key are skipped (found from the
//! per-chunk histograms of one up-front counting pass); the result is the unique stable order, so
//! it is bit-identical for any thread count.

use rayon::prelude::*;

/// Number of buckets per pass (8-bit digits).
const RADIX: usize = 256;

/// Below this many pairs a single chunk (no task spawning) is used.
const SERIAL_BELOW: usize = 1 << 14;

/// A key the radix sort can order: an unsigned integer read as `BYTES` 8-bit digits.
pub trait RadixKey: Copy + Send + Sync + Ord + Default + 'static {
    /// Number of 8-bit digits (passes at most).
    const BYTES: usize;
    /// Digit `pass` (0 = least significant byte).
    fn digit(self, pass: usize) -> usize;
    /// The key widened to 64 bits (for prefix comparisons in the hierarchy builders).
    fn widen(self) -> u64;
}

impl RadixKey for u64 {
    const BYTES: usize = 8;
    #[inline(always)]
    fn digit(self, pass: usize) -> usize {
        ((self >> (8 * pass)) & 0xff) as usize
    }
    #[inline(always)]
    fn widen(self) -> u64 {
        self
    }
}

impl RadixKey for u32 {
    const BYTES: usize = 4;
    #[inline(always)]
    fn digit(self, pass: usize) -> usize {
        ((self >> (8 * pass)) & 0xff) as usize
    }
    #[inline(always)]
    fn widen(self) -> u64 {
        self as u64
    }
}

/// Errors of the radix sort.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SortError {
    /// Keys and values of different lengths.
    #[error("{keys} keys but {values} values")]
    LengthMismatch {
        /// Number of keys.
        keys: usize,
        /// Number of values.
        values: usize,
    },
    /// More pairs than a `u32` index can name.
    #[error("{0} pairs exceed the 2^32 - 1 the sort supports")]
    TooMany(usize),
}

/// What a sort did.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct SortReport {
    /// Scatter passes performed.
    pub passes: u32,
    /// Passes skipped because their digit was constant across all keys.
    pub skipped: u32,
}

/// Histogram of one chunk for every digit position.
type Hist = [[u32; RADIX]; 8];

/// Count every digit of every key of one chunk.
fn count_all<K: RadixKey>(keys: &[K]) -> Box<Hist> {
    let mut h: Box<Hist> = Box::new([[0u32; RADIX]; 8]);
    for &k in keys {
        for (p, row) in h.iter_mut().enumerate().take(K::BYTES) {
            row[k.digit(p)] += 1;
        }
    }
    h
}

/// Count one digit of one chunk.
fn count_one<K: RadixKey>(keys: &[K], pass: usize) -> [u32; RADIX] {
    let mut h = [0u32; RADIX];
    for &k in keys {
        h[k.digit(pass)] += 1;
    }
    h
}

/// Scatter one chunk to its destination slots: `dst` holds, in chunk order, disjoint mutable
/// sub-slices per bucket (only the chunk's own slots of each bucket).
fn scatter_chunk<K: RadixKey>(
    keys: &[K],
    vals: &[u32],
    pass: usize,
    kdst: [&mut [K]; RADIX],
    vdst: [&mut [u32]; RADIX],
) {
    // Per-bucket write cursors. The caller sized bucket `d`'s sub-slices to exactly this chunk's
    // count of digit `d` in this pass, so each cursor ends exactly at its slice's end.
    let mut kp: [*mut K; RADIX] = kdst.map(|s| s.as_mut_ptr_range().start);
    let mut vp: [*mut u32; RADIX] = vdst.map(|s| s.as_mut_ptr_range().start);
    for (&k, &v) in keys.iter().zip(vals) {
        let d = k.digit(pass);
        // SAFETY: `kp[d]`/`vp[d]` point into the chunk's own, exclusively borrowed sub-slices
        // of bucket `d`, which hold one slot per key of this chunk with digit `d` (histogram of
        // the same chunk and pass); each key advances its cursor once, so no write leaves them.
        unsafe {
            kp[d].write(k);
            vp[d].write(v);
            kp[d] = kp[d].add(1);
            vp[d] = vp[d].add(1);
        }
    }
}

/// Sort `keys` ascending and apply the same permutation to `vals`, stably (equal keys keep the
/// order of their values' positions). Runs on the current rayon pool; the result does not
/// depend on the number of threads.
pub fn sort_pairs<K: RadixKey>(
    keys: &mut Vec<K>,
    vals: &mut Vec<u32>,
) -> Result<SortReport, SortError> {
    sort_pairs_with(keys, vals, &mut Vec::new(), &mut Vec::new())
}

/// [`sort_pairs`] with caller-owned scratch buffers (their contents are overwritten; a build
/// arena passes the same ones again so that their pages are already mapped). On return the
/// scratch holds the other ping-pong buffers, of the input's length.
pub fn sort_pairs_with<K: RadixKey>(
    keys: &mut Vec<K>,
    vals: &mut Vec<u32>,
    kscratch: &mut Vec<K>,
    vscratch: &mut Vec<u32>,
) -> Result<SortReport, SortError> {
    let n = keys.len();
    if vals.len() != n {
        return Err(SortError::LengthMismatch {
            keys: n,
            values: vals.len(),
        });
    }
    if n > u32::MAX as usize {
        return Err(SortError::TooMany(n));
    }
    let mut report = SortReport::default();
    if n < 2 {
        report.skipped = K::BYTES as u32;
        return Ok(report);
    }
    let chunks = if n < SERIAL_BELOW {
        1
    } else {
        rayon::current_num_threads().clamp(1, n / 4096)
    };
    let chunk_len = n.div_ceil(chunks);

    // One counting pass for all digits: per-chunk histograms of the first executed pass, and the
    // (permutation-invariant) totals that tell which passes are constant.
    let first_hists: Vec<Box<Hist>> = keys.par_chunks(chunk_len).map(count_all).collect();
    let mut totals = [[0usize; RADIX]; 8];
    for h in &first_hists {
        for p in 0..K::BYTES {
            for b in 0..RADIX {
                totals[p][b] += h[p][b] as usize;
            }
        }
    }

    let kbuf: &mut Vec<K> = kscratch;
    let vbuf: &mut Vec<u32> = vscratch;
    crate::buffers::refill(kbuf, n, K::default());
    crate::buffers::refill(vbuf, n, 0);
    let mut first_done = false;
    for pass in 0..K::BYTES {
        if totals[pass].contains(&n) {
            report.skipped += 1;
            continue;
        }
        let hists: Vec<[u32; RADIX]> = if chunks == 1 {
            // One chunk: its histogram is the (permutation-invariant) total.
            vec![core::array::from_fn(|b| totals[pass][b] as u32)]
        } else if !first_done {
            first_hists.iter().map(|h| h[pass]).collect()
        } else {
            keys.par_chunks(chunk_len)
                .map(|c| count_one(c, pass))
                .collect()
        };
        first_done = true;

        // Carve the destination into per-(bucket, chunk) sub-slices, bucket-major, so that each
        // chunk owns exactly the slots its elements go to: no unsafe and no shared writes.
        let mut per_chunk_k: Vec<Vec<&mut [K]>> = (0..hists.len()).map(|_| Vec::new()).collect();
        let mut per_chunk_v: Vec<Vec<&mut [u32]>> = (0..hists.len()).map(|_| Vec::new()).collect();
        {
            let mut krest: &mut [K] = kbuf;
            let mut vrest: &mut [u32] = vbuf;
            for b in 0..RADIX {
                for (c, h) in hists.iter().enumerate() {
                    let len = h[b] as usize;
                    let (kh, kt) = std::mem::take(&mut krest).split_at_mut(len);
                    let (vh, vt) = std::mem::take(&mut vrest).split_at_mut(len);
                    per_chunk_k[c].push(kh);
                    per_chunk_v[c].push(vh);
                    krest = kt;
                    vrest = vt;
                }
            }
        }
        keys.par_chunks(chunk_len)
            .zip(vals.par_chunks(chunk_len))
            .zip(per_chunk_k.into_par_iter().zip(per_chunk_v.into_par_iter()))
            .for_each(|((kc, vc), (kd, vd))| {
                let kd: [&mut [K]; RADIX] = match kd.try_into() {
                    Ok(a) => a,
                    Err(_) => unreachable!("one sub-slice per bucket"),
                };
                let vd: [&mut [u32]; RADIX] = match vd.try_into() {
                    Ok(a) => a,
                    Err(_) => unreachable!("one sub-slice per bucket"),
                };
                scatter_chunk(kc, vc, pass, kd, vd);
            });
        std::mem::swap(keys, kbuf);
        std::mem::swap(vals, vbuf);
        report.passes += 1;
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(s: &mut u64) -> u64 {
        *s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *s >> 11
    }

    #[test]
    fn matches_std_stable_sort() {
        let mut s = 7u64;
        for &n in &[0usize, 1, 2, 100, 5000, 40_000] {
            let keys: Vec<u64> = (0..n)
                .map(|_| lcg(&mut s) & 0x00ff_00f0_0000_ffff)
                .collect();
            let mut want: Vec<(u64, u32)> = keys.iter().copied().zip(0..).collect();
            want.sort_by_key(|p| p.0);
            let (mut k, mut v) = (keys.clone(), (0..n as u32).collect::<Vec<_>>());
            let r = sort_pairs(&mut k, &mut v).unwrap();
            let got: Vec<(u64, u32)> = k.into_iter().zip(v).collect();
            assert_eq!(got, want);
            if n > 2 {
                assert_eq!(r.passes, 4, "only bytes 0, 1, 4 and 6 vary");
                assert_eq!(r.skipped, 4);
            }
        }
    }

    #[test]
    fn u32_keys_and_errors() {
        let mut k: Vec<u32> = vec![5, 3, 5, 1];
        let mut v = vec![0, 1, 2, 3];
        sort_pairs(&mut k, &mut v).unwrap();
        assert_eq!((k, v), (vec![1, 3, 5, 5], vec![3, 1, 0, 2]));
        let mut k: Vec<u32> = vec![1];
        let mut v: Vec<u32> = vec![];
        assert!(sort_pairs(&mut k, &mut v).is_err());
    }
}
