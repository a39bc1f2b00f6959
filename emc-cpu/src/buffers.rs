//! Large build buffers: the pipeline allocates ~100 bytes per primitive, and the page faults of
//! fresh memory cost about a phase, so big buffers are reused when they are large enough (kept
//! as they are when the caller overwrites every element) and filled in parallel (first touch on
//! every core) when they are not. Fresh buffers of 4 MiB or more ask for transparent huge pages
//! before their first touch (`hugepage::advise`): a first bathroom build with the fast preset
//! went from about 62 to 40 ms of thread-CPU. (An earlier attempt on every buffer of the BVH2
//! pipeline saw San Miguel's sort phase double once; watch for compaction stalls.)
#![forbid(unsafe_code)]

use rayon::prelude::*;

/// A vector of `n` copies of `x`, its pages asked to be huge before they are written.
pub fn filled<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    // Advised before the first touch (`vec![x; n]` writes its copies at once as 4 KiB page
    // faults unless `x` is a zero integer): one-thread stanford-dragon quality builds 3-5%
    // faster, San Miguel's fast build 8%, bathroom and San Francisco within noise
    // (alternating builds in one process).
    let mut v = Vec::with_capacity(n);
    crate::hugepage::advise(&v);
    v.resize(n, x);
    v
}

/// Make `v` hold `n` elements whose values do not matter (the caller overwrites every one):
/// a reused allocation keeps its old elements, so a warm build neither clears nor refills it
/// (only a longer tail is written with `x`); a new one is [`filled`] (for a zero integer: fresh
/// zero pages, faulted in by the caller's own parallel writes).
pub fn resized<T: Copy + Send + Sync>(v: &mut Vec<T>, n: usize, x: T) {
    resize_keeping(v, n, x, filled);
}

/// [`resized`] for a type whose fill is not zero pages: a new allocation is filled with `x` in
/// parallel (first touch, and its page faults, on every core of the current pool).
pub fn resized_par<T: Copy + Send + Sync>(v: &mut Vec<T>, n: usize, x: T) {
    resize_keeping(v, n, x, |n, x| from_fn(n, |_| x));
}

/// `v` to length `n`: truncated or extended with `x` in its own allocation, or replaced by
/// `fresh(n, x)` when that is too small.
fn resize_keeping<T: Copy>(v: &mut Vec<T>, n: usize, x: T, fresh: impl FnOnce(usize, T) -> Vec<T>) {
    if v.len() >= n {
        v.truncate(n);
    } else if v.capacity() >= n {
        v.resize(n, x);
    } else {
        *v = fresh(n, x);
    }
}

/// Empty `v` and make room for `n` elements: its allocation kept when large enough, else a
/// fresh one asked for huge pages before its first write (an output buffer built by pushes).
pub fn cleared_with_room<T>(v: &mut Vec<T>, n: usize) {
    v.clear();
    if v.capacity() < n {
        *v = Vec::with_capacity(n);
        crate::hugepage::advise(v);
    }
}

/// Make `v` a copy of `src`, written once, in parallel on the current pool (into its own
/// allocation when that is large enough, else a fresh one, as [`cleared_with_room`]).
pub fn copied_par<T: Copy + Send + Sync>(v: &mut Vec<T>, src: &[T]) {
    cleared_with_room(v, src.len());
    v.par_extend(src.par_iter().copied());
}

/// `dst.copy_from_slice(src)` in parallel pieces on the current pool (equal lengths).
pub fn copy_par<T: Copy + Send + Sync>(dst: &mut [T], src: &[T]) {
    const CHUNK: usize = 1 << 15;
    assert_eq!(dst.len(), src.len(), "copy_par: lengths differ");
    dst.par_chunks_mut(CHUNK)
        .zip(src.par_chunks(CHUNK))
        .for_each(|(d, s)| d.copy_from_slice(s));
}

/// A vector of `n` values made by `f`, filled in parallel.
pub fn from_fn<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    crate::hugepage::advise(&v);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(f));
    v
}

/// Collect an indexed parallel iterator into a vector allocated once.
pub fn collect<T: Send>(it: impl IndexedParallelIterator<Item = T>) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(it.len());
    v.par_extend(it);
    v
}
