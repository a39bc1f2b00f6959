//! Parallel radix sort of (code, primitive index) pairs: step 3 of the LBVH pipeline.
//! Hybrid, on the bits that vary only: one parallel most-significant-digit split of the whole
//! array by its top varying bits into cache-sized buckets, then every bucket is an independent
//! task sorted least-significant-digit first in the core's cache.
//!
//! ```text
//!   key bits:  63 ......... hi | hi-1 .... hi-w | hi-w-1 ............ lo | lo-1 ..... 0
//!              same in all keys| split digit    | bucket's LSD digits     | same in all keys
//!   split:     w ≤ 11 bits (about 4096 pairs per bucket), every thread counts and scatters its
//!              own contiguous chunk into its own slots of every bucket
//!   bucket:    its own varying bits (bucket mask), 8-bit digits from its lowest varying bit,
//!              all histograms from one counting pass, digits constant in the bucket skipped,
//!              ping-pong between the two buffers in cache; ≤ 32 pairs: insertion sort
//! ```
//!
//! A rebuild whose codes barely changed sorts with `sort_with_ids_hinted` (crate-private)
//! instead: the pairs whose code did not change keep the last sort's order, the others are
//! sorted and merged in.
//!
//! Buckets of 64Ki pairs or more are split again the same way. Every step is stable and a range
//! whose keys are all equal is left as it is, so the result is the unique stable order:
//! bit-identical for any thread count. Which step a range gets depends on its size only, so one
//! thread does the same work as many.

use rayon::prelude::*;

/// Ranges of at most this many pairs are insertion-sorted.
const INSERTION_MAX: usize = 32;

/// Below this many pairs a range is split on one thread (no tasks, no chunk histograms).
const PARALLEL_MIN: usize = 1 << 16;

/// Widest digit of the parallel first split (2048 buckets).
const TOP_BITS_MAX: u32 = 11;

/// Buckets of an in-cache LSD pass (8-bit digits: the histograms live on the stack).
const LSD_RADIX: usize = 256;

/// The first (parallel) split aims at buckets of about this many pairs, so that each bucket's
/// task runs in the core's own cache.
const TOP_BUCKET_TARGET: usize = 1 << 12;

/// The first split's buckets should average at least this many pairs.
const BUCKET_MIN: usize = 1 << 9;

/// A key the radix sort can order: an unsigned integer of `BITS` bits.
pub trait RadixKey: Copy + Send + Sync + Ord + Default + 'static {
    /// Bits of the key.
    const BITS: u32;
    /// Number of 8-bit digits (the byte positions [`SortReport`] counts).
    const BYTES: usize;
    /// The key widened to 64 bits (digits, masks, and prefix comparisons in the hierarchy
    /// builders).
    fn widen(self) -> u64;
}

impl RadixKey for u64 {
    const BITS: u32 = 64;
    const BYTES: usize = 8;
    #[inline(always)]
    fn widen(self) -> u64 {
        self
    }
}

impl RadixKey for u32 {
    const BITS: u32 = 32;
    const BYTES: usize = 4;
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

/// What a sort found and did.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct SortReport {
    /// Byte positions of the key (bits `8i..8i+8`) in which some keys differ: the bytes the sort
    /// orders by.
    pub passes: u32,
    /// Byte positions in which all keys agree: never looked at after the first read.
    pub skipped: u32,
    /// Bits from the lowest to the highest bit in which some keys differ (0 when all are equal).
    pub varying_bits: u32,
    /// Width of the first (parallel) split's digit in bits (0 when there was none).
    pub top_digit_bits: u32,
    /// Most times any pair was moved: parallel splits plus in-cache LSD passes on its way
    /// (insertion sorts and copies not counted).
    pub depth: u32,
}

/// `(bits set in some key, bits set in every key)` of a slice.
fn or_and<K: RadixKey>(keys: &[K]) -> (u64, u64) {
    let mut o = 0u64;
    let mut a = !0u64;
    for &k in keys {
        let w = k.widen();
        o |= w;
        a &= w;
    }
    (o, a)
}

/// Bits in which some keys of the slice differ (in parallel when `par`).
fn varying_mask<K: RadixKey>(keys: &[K], par: bool) -> u64 {
    let (o, a) = if par {
        keys.par_chunks(PARALLEL_MIN)
            .map(or_and)
            .reduce(|| (0, !0), |x, y| (x.0 | y.0, x.1 & y.1))
    } else {
        or_and(keys)
    };
    o & !a
}

/// Digit of `k` at `shift`, `mask` = buckets − 1.
#[inline(always)]
fn digit<K: RadixKey>(k: K, shift: u32, mask: usize) -> usize {
    (k.widen() >> shift) as usize & mask
}

/// Stable insertion sort of a short range.
fn insertion_sort<K: RadixKey>(k: &mut [K], v: &mut [u32]) {
    for i in 1..k.len() {
        let (key, val) = (k[i], v[i]);
        let mut j = i;
        while j > 0 && k[j - 1] > key {
            k[j] = k[j - 1];
            v[j] = v[j - 1];
            j -= 1;
        }
        k[j] = key;
        v[j] = val;
    }
}

/// Width of the split of a range of `m ≥ PARALLEL_MIN` pairs whose varying bits are `lo..hi`.
/// Buckets should average at most [`TOP_BUCKET_TARGET`] pairs (in cache) and at least
/// [`BUCKET_MIN`] (worth their histograms); within that, the narrowest digit that leaves the
/// buckets the fewest 8-bit LSD passes (e.g. 64 varying bits: 8 bits, 7 passes left, rather than
/// 7 bits and 8 passes), at most [`TOP_BITS_MAX`] bits.
fn split_width(m: usize, hi: u32, lo: u32) -> u32 {
    let span = hi - lo;
    let log2 = |x: usize| usize::BITS - 1 - x.max(1).leading_zeros();
    let narrow = (log2(m / TOP_BUCKET_TARGET) + 1).clamp(1, TOP_BITS_MAX);
    let wide = log2(m / BUCKET_MIN).clamp(narrow, TOP_BITS_MAX);
    let passes = |w: u32| (span - w).div_ceil(8);
    (narrow..=wide)
        .min_by_key(|&w| (passes(w.min(span)), w))
        .unwrap_or(narrow)
        .min(span)
}

/// Sorts `(dk, dv)`, using `(ok, ov)` (same length) as the other buffer; the result ends in the
/// data buffer when `want_in_data`, else in the other one. `mask` is the range's varying bits
/// when known; with `ids` the values are not read but taken to be the positions `0, 1, …` (and
/// written so). Ranges of at least [`PARALLEL_MIN`] pairs are split by the pool and their buckets
/// sorted as tasks; smaller ones by [`lsd`] (or an insertion sort) on the calling thread. That
/// choice depends on the size only, so one thread does the same work as many. Returns the depth
/// (splits and passes on the longest way).
fn sort_range<K: RadixKey>(
    dk: &mut [K],
    dv: &mut [u32],
    ok: &mut [K],
    ov: &mut [u32],
    want_in_data: bool,
    mask: Option<u64>,
    ids: bool,
) -> u32 {
    let m = dk.len();
    if ids && m < PARALLEL_MIN {
        // Small: the values are the positions, written before any step reads them.
        fill_positions(dv);
    }
    if m <= INSERTION_MAX {
        insertion_sort(dk, dv);
        if !want_in_data {
            ok.copy_from_slice(dk);
            ov.copy_from_slice(dv);
        }
        return 0;
    }
    let par = m >= PARALLEL_MIN;
    let mask = mask.unwrap_or_else(|| varying_mask(dk, par && rayon::current_num_threads() > 1));
    if mask == 0 {
        // All keys equal: already in stable order.
        if ids && par {
            fill_positions(dv);
        }
        if !want_in_data {
            ok.copy_from_slice(dk);
            ov.copy_from_slice(dv);
        }
        return 0;
    }
    if !par {
        return lsd(dk, dv, ok, ov, want_in_data, mask);
    }
    let hi = 64 - mask.leading_zeros();
    let lo = mask.trailing_zeros();
    let w = split_width(m, hi, lo);
    let shift = hi - w;
    // The split moves the pairs into the other buffer; the buckets sort from there.
    let starts = split_parallel(dk, dv, ok, ov, shift, w, ids);
    // After a split on the lowest varying bits every bucket holds equal keys.
    let last = shift <= lo;
    let mut buckets = Vec::with_capacity(1 << w);
    {
        let (mut kd, mut vd, mut ks, mut vs) = (dk, dv, ok, ov);
        for b in 0..1usize << w {
            let len = starts[b + 1] - starts[b];
            let (kd0, kd1) = std::mem::take(&mut kd).split_at_mut(len);
            let (vd0, vd1) = std::mem::take(&mut vd).split_at_mut(len);
            let (ks0, ks1) = std::mem::take(&mut ks).split_at_mut(len);
            let (vs0, vs1) = std::mem::take(&mut vs).split_at_mut(len);
            (kd, vd, ks, vs) = (kd1, vd1, ks1, vs1);
            if len > 0 {
                buckets.push((ks0, vs0, kd0, vd0));
            }
        }
    }
    let depth = buckets
        .into_par_iter()
        .with_max_len(1)
        .map(|(ks, vs, kd, vd)| {
            if last || ks.len() < 2 {
                if want_in_data {
                    kd.copy_from_slice(ks);
                    vd.copy_from_slice(vs);
                }
                0
            } else {
                sort_range(ks, vs, kd, vd, !want_in_data, None, false)
            }
        })
        .max();
    depth.unwrap_or(0) + 1
}

/// Least significant digit first over the varying bits `mask` of a cache-sized range: 8-bit
/// digits from the lowest varying bit up, the histograms of all digits from one counting pass,
/// digits that are the same in every key skipped. Same contract as [`sort_range`]; returns the
/// passes done.
fn lsd<K: RadixKey>(
    dk: &mut [K],
    dv: &mut [u32],
    ok: &mut [K],
    ov: &mut [u32],
    want_in_data: bool,
    mask: u64,
) -> u32 {
    let m = dk.len();
    let hi = 64 - mask.leading_zeros();
    let lo = mask.trailing_zeros();
    let digits = (hi - lo).div_ceil(8) as usize;
    let mut counts = [[0u32; LSD_RADIX]; 8];
    for &k in dk.iter() {
        let w = k.widen() >> lo;
        for (i, c) in counts.iter_mut().enumerate().take(digits) {
            c[(w >> (8 * i)) as usize & 0xff] += 1;
        }
    }
    let mut in_data = true;
    let mut passes = 0;
    for (i, c) in counts.iter().enumerate().take(digits) {
        if c.contains(&(m as u32)) {
            continue;
        }
        let shift = lo + 8 * i as u32;
        let mut cursor = [0u32; LSD_RADIX];
        let mut sum = 0u32;
        for (cur, &n) in cursor.iter_mut().zip(c) {
            *cur = sum;
            sum += n;
        }
        let (sk, sv, tk, tv): (&[K], &[u32], &mut [K], &mut [u32]) = if in_data {
            (dk, dv, ok, ov)
        } else {
            (ok, ov, dk, dv)
        };
        let (tkp, tvp) = (tk.as_mut_ptr(), tv.as_mut_ptr());
        for (&k, &v) in sk.iter().zip(sv) {
            let d = digit(k, shift, 0xff);
            let p = cursor[d] as usize;
            // SAFETY: `cursor` holds the exclusive prefix sums of this pass's histogram of the
            // same keys (`tk`, `tv` have `m` slots), so digit `d`'s cursor runs through
            // `start(d) .. start(d) + count(d) ≤ m`, each slot written once.
            unsafe {
                tkp.add(p).write(k);
                tvp.add(p).write(v);
            }
            cursor[d] += 1;
        }
        in_data = !in_data;
        passes += 1;
    }
    if in_data != want_in_data {
        if want_in_data {
            dk.copy_from_slice(ok);
            dv.copy_from_slice(ov);
        } else {
            ok.copy_from_slice(dk);
            ov.copy_from_slice(dv);
        }
    }
    passes
}

/// Sort `keys` ascending and apply the same permutation to `vals`, stably (equal keys keep the
/// order of their values' positions). Runs on the current rayon pool; the result does not
/// depend on the number of threads.
pub fn sort_pairs<K: RadixKey>(keys: &mut [K], vals: &mut [u32]) -> Result<SortReport, SortError> {
    sort_pairs_with(keys, vals, &mut Vec::new(), &mut Vec::new())
}

/// Give the scratch buffer `v` the length `n`, reusing its allocation and contents (its pages
/// are then already mapped and nothing is cleared) when it is large enough.
fn scratch<T: Copy + Default + Send + Sync>(v: &mut Vec<T>, n: usize) {
    crate::buffers::resized(v, n, T::default());
}

/// [`sort_pairs`] with caller-owned scratch buffers (their contents are overwritten; a build
/// arena passes the same ones again so that their pages are already mapped). On return the
/// scratch buffers have the input's length.
pub fn sort_pairs_with<K: RadixKey>(
    keys: &mut [K],
    vals: &mut [u32],
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
    scratch(kscratch, n);
    scratch(vscratch, n);
    let (mask, mut report) = survey(keys);
    if mask == 0 {
        return Ok(report);
    }
    report.depth = sort_range(keys, vals, kscratch, vscratch, true, Some(mask), false);
    Ok(report)
}

/// Sort `keys` ascending (stably) and make `ids[p]` the original position of the key now at
/// `p`: [`sort_pairs_with`] on the values `0, 1, …, n − 1`, which the first split writes itself
/// instead of reading them (`ids` is resized to `keys.len()`; its old contents do not matter).
pub fn sort_with_ids<K: RadixKey>(
    keys: &mut [K],
    ids: &mut Vec<u32>,
    kscratch: &mut Vec<K>,
    vscratch: &mut Vec<u32>,
) -> Result<SortReport, SortError> {
    let n = keys.len();
    if n > u32::MAX as usize {
        return Err(SortError::TooMany(n));
    }
    crate::buffers::resized(ids, n, 0);
    scratch(kscratch, n);
    scratch(vscratch, n);
    let (mask, mut report) = survey(keys);
    report.depth = if mask == 0 {
        fill_positions(ids);
        0
    } else {
        sort_range(keys, ids, kscratch, vscratch, true, Some(mask), true)
    };
    Ok(report)
}

/// A hinted sort sets aside at most one pair in this many before it sorts from scratch
/// (measured, one thread, stanford-dragon with the vertices in a ball around its centre swaying:
/// 0.4% of them moved, sort 7 ns per triangle against the radix sort's 25-33; 6.8%, 15-18 with
/// this limit, the radix sort's time at a limit of one in 16; 23.8%, too many: the radix sort's
/// time, the pass given up early).
const HINT_ASIDE_DIV: usize = 6;

/// How far ahead of its gather the hinted sort fetches a key, in pairs (measured, one thread,
/// stanford-dragon rebuilt over the same vertices, two runs each: 5.2 and 5.2 ns per triangle,
/// without the fetch 7.8 and 6.5).
const HINT_FETCH_AHEAD: usize = 64;

/// [`sort_with_ids`] of the keys of a rebuild, `fresh` (in position order), given the previous
/// sort's result: `sorted` its keys in order and `ids` their positions. A pair whose key did
/// not change keeps its place relative to the others that did not; only the changed ones are
/// set aside, sorted, and merged in from the back:
///
/// ```text
///   i = 0, 1, …:  id = ids[i], k = fresh[id]
///   kept:         k == sorted[i] and (k, id) ≥ the last kept  -> sorted[kept], ids[kept]
///                 (in place: kept ≤ i)
///   set aside:    the rest                                    -> a short list, then sorted
///   merge:        the largest set-aside pair first: the kept pairs above it move up by the
///                 number of set-aside pairs not yet placed (one memmove), it goes below them
/// ```
///
/// Pairs compare by (key, position), the order [`sort_with_ids`] produces (it is stable), so
/// the result is identical to it whatever `sorted` and `ids` hold (the kept pairs are checked
/// to ascend). More than `n / 6` pairs set aside stop the pass and the keys are sorted from
/// scratch instead, as they are when the lengths differ. On return `sorted` holds the sorted
/// keys, `ids` their positions and `fresh` nothing of use (it served as scratch). Returns
/// whether the previous order served. `ids` must be a permutation of `0..n` when the lengths
/// agree (a sort's result is); the caller keeps track of that. `rest` is the set-aside list's
/// buffer (its contents do not matter; a caller keeps it so that rebuilds allocate nothing).
pub(crate) fn sort_with_ids_hinted<K: RadixKey>(
    sorted: &mut Vec<K>,
    fresh: &mut Vec<K>,
    ids: &mut Vec<u32>,
    vscratch: &mut Vec<u32>,
    rest: &mut Vec<(K, u32)>,
) -> Result<bool, SortError> {
    let n = fresh.len();
    if ids.len() != n || sorted.len() != n || n < 2 {
        std::mem::swap(sorted, fresh);
        sort_with_ids(sorted, ids, fresh, vscratch)?;
        return Ok(false);
    }
    let limit = n / HINT_ASIDE_DIV;
    rest.clear();
    let mut kept = 0usize;
    let mut last = (0u64, 0u32);
    for i in 0..n {
        if let Some(&ahead) = ids.get(i + HINT_FETCH_AHEAD) {
            crate::trace::traverse::prefetch(&fresh[ahead as usize], 1);
        }
        let id = ids[i];
        let k = fresh[id as usize];
        let c = (k.widen(), id);
        if k == sorted[i] && c >= last {
            sorted[kept] = k;
            ids[kept] = id;
            kept += 1;
            last = c;
        } else {
            if rest.len() == limit {
                std::mem::swap(sorted, fresh);
                sort_with_ids(sorted, ids, fresh, vscratch)?;
                return Ok(false);
            }
            rest.push((k, id));
        }
    }
    rest.sort_unstable();
    let mut hi = kept;
    for (r, &(k, v)) in rest.iter().enumerate().rev() {
        // Kept pairs below (k, v): those of smaller keys, then those of key k and a lower
        // position.
        let lo = sorted[..hi].partition_point(|&x| x < k);
        let eq = lo + sorted[lo..hi].partition_point(|&x| x == k);
        let p = lo + ids[lo..eq].partition_point(|&x| x < v);
        sorted.copy_within(p..hi, p + r + 1);
        ids.copy_within(p..hi, p + r + 1);
        sorted[p + r] = k;
        ids[p + r] = v;
        hi = p;
    }
    Ok(true)
}

/// Write `0, 1, …` into `v` (in parallel when long).
fn fill_positions(v: &mut [u32]) {
    v.par_chunks_mut(PARALLEL_MIN)
        .enumerate()
        .for_each(|(c, s)| {
            for (i, x) in s.iter_mut().enumerate() {
                *x = (c * PARALLEL_MIN + i) as u32;
            }
        });
}

/// The keys' varying bits and the report fields that follow from them.
fn survey<K: RadixKey>(keys: &[K]) -> (u64, SortReport) {
    let n = keys.len();
    let mut report = SortReport {
        skipped: K::BYTES as u32,
        ..SortReport::default()
    };
    if n < 2 {
        return (0, report);
    }
    let mask = varying_mask(keys, n >= PARALLEL_MIN && rayon::current_num_threads() > 1);
    let varying_bytes = (0..K::BYTES)
        .filter(|&i| (mask >> (8 * i)) & 0xff != 0)
        .count() as u32;
    report.passes = varying_bytes;
    report.skipped = K::BYTES as u32 - varying_bytes;
    if mask != 0 {
        let hi = 64 - mask.leading_zeros();
        let lo = mask.trailing_zeros();
        report.varying_bits = hi - lo;
        if n >= PARALLEL_MIN {
            report.top_digit_bits = split_width(n, hi, lo);
        }
    }
    (mask, report)
}

/// One chunk's destination slots of every bucket, keys and values.
type ChunkSlots<'a, K> = (Vec<&'a mut [K]>, Vec<&'a mut [u32]>);

/// The first split, in parallel: every thread counts the digit in its own contiguous chunk,
/// then scatters the chunk into its own slots of every bucket. Returns the bucket starts (and
/// `n` after the last bucket).
fn split_parallel<K: RadixKey>(
    keys: &[K],
    vals: &[u32],
    kout: &mut [K],
    vout: &mut [u32],
    shift: u32,
    w: u32,
    ids: bool,
) -> Vec<usize> {
    let n = keys.len();
    let threads = rayon::current_num_threads();
    let radix = 1usize << w;
    let mask = radix - 1;
    let chunks = threads.clamp(1, n.div_ceil(PARALLEL_MIN / 4).max(1));
    let chunk_len = n.div_ceil(chunks);
    let hists: Vec<Vec<u32>> = keys
        .par_chunks(chunk_len)
        .map(|c| {
            let mut h = vec![0u32; radix];
            for &k in c {
                h[digit(k, shift, mask)] += 1;
            }
            h
        })
        .collect();
    let mut starts = Vec::with_capacity(radix + 1);
    let mut sum = 0usize;
    for b in 0..radix {
        starts.push(sum);
        sum += hists.iter().map(|h| h[b] as usize).sum::<usize>();
    }
    starts.push(sum);
    // Carve the destination into per-(bucket, chunk) sub-slices, bucket-major, so that each
    // chunk owns exactly the slots its pairs go to.
    let mut per_chunk: Vec<ChunkSlots<'_, K>> = (0..hists.len())
        .map(|_| (Vec::with_capacity(radix), Vec::with_capacity(radix)))
        .collect();
    {
        let (mut krest, mut vrest): (&mut [K], &mut [u32]) = (kout, vout);
        for b in 0..radix {
            for (c, h) in hists.iter().enumerate() {
                let len = h[b] as usize;
                let (kh, kt) = std::mem::take(&mut krest).split_at_mut(len);
                let (vh, vt) = std::mem::take(&mut vrest).split_at_mut(len);
                per_chunk[c].0.push(kh);
                per_chunk[c].1.push(vh);
                (krest, vrest) = (kt, vt);
            }
        }
    }
    keys.par_chunks(chunk_len)
        .zip(vals.par_chunks(chunk_len))
        .zip(per_chunk.into_par_iter())
        .enumerate()
        .for_each(|(c, ((kc, vc), (kd, vd)))| {
            if ids {
                let first = (c * chunk_len) as u32;
                scatter_chunk(kc, (first..).take(kc.len()), kd, vd, shift, w)
            } else {
                scatter_chunk(kc, vc.iter().copied(), kd, vd, shift, w)
            }
        });
    starts
}

/// Scatter one chunk (keys `kc`, values `vc`) into its own slots of every bucket: `kd[d]`,
/// `vd[d]` hold exactly the chunk's count of digit `d`, in bucket order.
fn scatter_chunk<K: RadixKey>(
    kc: &[K],
    vc: impl Iterator<Item = u32>,
    kd: Vec<&mut [K]>,
    vd: Vec<&mut [u32]>,
    shift: u32,
    w: u32,
) {
    let mask = (1usize << w) - 1;
    // Write cursors into the chunk's own sub-slice of every bucket.
    let mut kp: Vec<*mut K> = kd.into_iter().map(|s| s.as_mut_ptr()).collect();
    let mut vp: Vec<*mut u32> = vd.into_iter().map(|s| s.as_mut_ptr()).collect();
    for (&k, v) in kc.iter().zip(vc) {
        let d = digit(k, shift, mask);
        // SAFETY: `d < radix` (masked), the cursor vectors have `radix` entries.
        // `kp[d]`/`vp[d]` start at this chunk's own, exclusively borrowed sub-slices of
        // bucket `d`, sized to this chunk's count of digit `d` (its histogram above);
        // each key advances its cursor once, so every write stays inside them.
        unsafe {
            let (pk, pv) = (kp.get_unchecked_mut(d), vp.get_unchecked_mut(d));
            pk.write(k);
            pv.write(v);
            *pk = pk.add(1);
            *pv = pv.add(1);
        }
    }
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

    fn check<K: RadixKey + std::fmt::Debug>(keys: Vec<K>, threads: usize) -> SortReport {
        let mut want: Vec<(K, u32)> = keys.iter().copied().zip(0..).collect();
        want.sort_by_key(|p| p.0);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let n = keys.len();
        let (mut k, mut v) = (keys, (0..n as u32).collect::<Vec<_>>());
        let r = pool.install(|| sort_pairs(&mut k, &mut v)).unwrap();
        let got: Vec<(K, u32)> = k.into_iter().zip(v).collect();
        assert_eq!(got, want, "n = {n}, threads = {threads}");
        r
    }

    #[test]
    fn matches_std_stable_sort() {
        let mut s = 7u64;
        for &n in &[0usize, 1, 2, 100, 5000, 40_000, 200_000] {
            let keys: Vec<u64> = (0..n)
                .map(|_| lcg(&mut s) & 0x00ff_00f0_0000_ffff)
                .collect();
            for threads in [1, 2, 3] {
                let r = check(keys.clone(), threads);
                if n > 2 {
                    assert_eq!((r.passes, r.skipped), (4, 4), "bytes 0, 1, 4 and 6 vary");
                    assert_eq!(
                        r.varying_bits, 53,
                        "bits 0 to 52 (the generator gives 53 bits)"
                    );
                }
            }
        }
    }

    #[test]
    fn edge_cases_all_thread_counts() {
        for threads in [1, 2, 3] {
            // Empty, one, all equal (small and large, parallel path), two values.
            assert_eq!(check(Vec::<u64>::new(), threads).passes, 0);
            assert_eq!(check(vec![9u64], threads).passes, 0);
            for n in [2usize, 33, 1000, 300_000] {
                let r = check(vec![0xdead_beef_u64; n], threads);
                assert_eq!((r.passes, r.skipped, r.varying_bits), (0, 8, 0));
                check((0..n as u64).map(|i| (i * 7919) % 2).collect(), threads);
                check(
                    (0..n as u32).map(|i| ((i % 3) << 31) >> 1).collect(),
                    threads,
                );
            }
            // Only the lowest bits used; only the highest bit; descending; many duplicates.
            let n = 250_000;
            let r = check(
                (0..n as u64).map(|i| (i * 2_654_435_761) & 0x3f).collect(),
                threads,
            );
            assert_eq!((r.varying_bits, r.passes), (6, 1));
            let r = check((0..n as u64).map(|i| (i & 1) << 63).collect(), threads);
            assert_eq!((r.varying_bits, r.top_digit_bits, r.depth), (1, 1, 1));
            check((0..n as u64).rev().collect(), threads);
            check((0..n as u64).map(|i| (i * 31) % 977).collect(), threads);
            let mut s = 5u64;
            check((0..n).map(|_| lcg(&mut s) as u32).collect(), threads);
            check(
                (0..n)
                    .map(|_| lcg(&mut s) << 11 | lcg(&mut s) & 0x7ff)
                    .collect::<Vec<u64>>(),
                threads,
            );
            // One huge bucket (90% of the keys share their top 20 bits) next to a sparse rest.
            check(
                (0..n)
                    .map(|i| {
                        let x = lcg(&mut s);
                        if i % 10 == 0 {
                            x << 11
                        } else {
                            0xabcde << 44 | x & 0xfff_ffff
                        }
                    })
                    .collect::<Vec<u64>>(),
                threads,
            );
        }
    }

    #[test]
    fn sort_with_ids_equals_sort_pairs_on_positions() {
        let mut s = 13u64;
        let sets: Vec<Vec<u64>> = vec![
            vec![],
            vec![4],
            vec![3; 70_000],
            (0..100).map(|i| (i * 37) % 11).collect(),
            (0..70_000).map(|_| lcg(&mut s) & 0x3ff).collect(),
            (0..300_000).map(|_| lcg(&mut s) << 11).collect(),
            (0..300_000)
                .map(|i| if i % 9 == 0 { lcg(&mut s) } else { 5 << 60 })
                .collect(),
        ];
        for keys in sets {
            let n = keys.len();
            let (mut want_k, mut want_v) = (keys.clone(), (0..n as u32).collect::<Vec<_>>());
            let want_r = sort_pairs(&mut want_k, &mut want_v).unwrap();
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                // Stale contents in every buffer must not matter.
                let (mut k, mut ids) = (keys.clone(), vec![7u32; n / 2]);
                let (mut ks, mut vs) = (vec![1u64; n], vec![9u32; n + 5]);
                let r = pool
                    .install(|| sort_with_ids(&mut k, &mut ids, &mut ks, &mut vs))
                    .unwrap();
                assert_eq!(
                    (&k, &ids, r),
                    (&want_k, &want_v, want_r),
                    "n {n}, {threads} threads"
                );
            }
        }
    }

    /// The hinted sort equals the plain one: keys unchanged since the previous sort, a few
    /// changed (far and near, ties), too many changed (the fallback), and hints that are not a
    /// previous sort's result at all (unsorted keys, a random permutation, other lengths).
    #[test]
    fn hinted_sort_equals_sort_with_ids() {
        let mut s = 29u64;
        for &n in &[0usize, 1, 2, 3, 17, 1000, 70_000] {
            for ties in [false, true] {
                let mask = if ties { 0xf } else { !0 };
                let before: Vec<u64> = (0..n).map(|_| lcg(&mut s) & mask).collect();
                let (mut prev_k, mut prev_v) = (before.clone(), Vec::new());
                sort_with_ids(&mut prev_k, &mut prev_v, &mut Vec::new(), &mut Vec::new()).unwrap();
                let mut perm: Vec<u32> = (0..n as u32).collect();
                for i in (1..n).rev() {
                    perm.swap(i, lcg(&mut s) as usize % (i + 1));
                }
                // (new keys, previous sorted keys, previous ids, whether the hint must serve)
                type Case = (Vec<u64>, Vec<u64>, Vec<u32>, Option<bool>);
                let mut cases: Vec<Case> =
                    vec![(before.clone(), prev_k.clone(), prev_v.clone(), Some(n >= 2))];
                for changes in [1usize, 3, n / 40, n / 4, n] {
                    let mut k = before.clone();
                    for _ in 0..changes.min(n) {
                        let i = lcg(&mut s) as usize % n;
                        k[i] = if lcg(&mut s) & 1 == 0 {
                            lcg(&mut s) & mask
                        } else {
                            k[i].wrapping_add(1) & mask
                        };
                    }
                    let serves = (changes <= 3 && n >= 1000).then_some(true);
                    cases.push((k, prev_k.clone(), prev_v.clone(), serves));
                }
                let unsorted: Vec<u64> = (0..n).map(|_| lcg(&mut s) & mask).collect();
                cases.push((before.clone(), unsorted, prev_v.clone(), None));
                cases.push((before.clone(), prev_k.clone(), perm, None));
                cases.push((before.clone(), vec![0; n + 1], prev_v.clone(), Some(false)));
                cases.push((before.clone(), prev_k.clone(), vec![0; n / 2], Some(false)));
                for (c, (fresh, sorted, ids, serves)) in cases.into_iter().enumerate() {
                    let (mut want_k, mut want_v) = (fresh.clone(), Vec::new());
                    sort_with_ids(&mut want_k, &mut want_v, &mut Vec::new(), &mut Vec::new())
                        .unwrap();
                    let (mut k, mut f, mut v) = (sorted, fresh, ids);
                    let mut rest = vec![(5u64, 5u32); 2];
                    let served =
                        sort_with_ids_hinted(&mut k, &mut f, &mut v, &mut vec![1u32; 3], &mut rest)
                            .unwrap();
                    assert_eq!((&k, &v), (&want_k, &want_v), "n {n}, ties {ties}, case {c}");
                    if let Some(want) = serves {
                        assert_eq!(served, want, "n {n}, ties {ties}, case {c}");
                    }
                }
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
