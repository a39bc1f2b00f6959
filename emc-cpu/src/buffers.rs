//! Large build buffers: the pipeline allocates ~100 bytes per primitive, and the page faults of
//! fresh memory cost about a phase, so big buffers are reused when they are large enough (kept
//! as they are when the caller overwrites every element), filled in parallel (first touch on
//! every core) when they are not, and fresh big ones are hinted to transparent huge pages
//! (San Miguel, first build, 2 threads, thread-CPU: AABB phase 121 -> 45 ms, sort 227 -> 187 ms).

use rayon::prelude::*;

/// A vector of `n` copies of `x` (`vec![x; n]`: zeroed allocator pages, no writing pass, when
/// `x` is a zero integer).
pub fn filled<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    vec![x; n]
}

/// Make `v` hold `n` copies of `x`, reusing its allocation when it is large enough (its pages
/// are then already mapped: a memset instead of page faults); else as [`filled`].
pub fn refill<T: Copy + Send + Sync>(v: &mut Vec<T>, n: usize, x: T) {
    if v.capacity() >= n {
        v.clear();
        v.resize(n, x);
    } else {
        *v = filled(n, x);
    }
}

/// Make `v` hold `n` elements whose values do not matter (the caller overwrites every one):
/// a reused allocation keeps its old elements, so a warm build neither clears nor refills it
/// (only a longer tail is written with `x`); a new one is [`filled`] (for a zero integer: fresh
/// zero pages, faulted in by the caller's own parallel writes).
pub fn resized<T: Copy + Send + Sync>(v: &mut Vec<T>, n: usize, x: T) {
    if v.len() >= n {
        v.truncate(n);
    } else if v.capacity() >= n {
        v.resize(n, x);
    } else {
        *v = fresh(n, x);
    }
}

/// [`resized`] for a type whose fill is not zero pages: a new allocation is filled with `x` in
/// parallel (first touch, and its page faults, on every core of the current pool).
pub fn resized_par<T: Copy + Send + Sync>(v: &mut Vec<T>, n: usize, x: T) {
    if v.len() >= n {
        v.truncate(n);
    } else if v.capacity() >= n {
        v.resize(n, x);
    } else {
        *v = fresh_par(n, x);
    }
}

/// `n` copies of `x` in a new allocation: zero pages for a zero integer (faulted in by the
/// first writes), the huge-page hint given before anything is touched.
fn fresh<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    let v = filled(n, x);
    hint_huge_pages(&v);
    v
}

/// `n` copies of `x` in a new allocation, written in parallel after the huge-page hint.
fn fresh_par<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    hint_huge_pages(&v);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(|_| x));
    v
}

/// Bytes of a transparent huge page (x86-64).
const HUGE_PAGE: usize = 2 << 20;

/// Ask the kernel to back the whole 2 MiB pages inside `v`'s allocation with transparent huge
/// pages (`madvise(MADV_HUGEPAGE)`; systems in THP `madvise` mode only do so when asked): one
/// fault and one 2 MiB clear instead of 512 faults per 2 MiB. Only for allocations of at least
/// 8 MiB; a no-op where unsupported or refused (the hint changes no contents).
fn hint_huge_pages<T>(v: &Vec<T>) {
    let bytes = v.capacity() * std::mem::size_of::<T>();
    if bytes < 4 * HUGE_PAGE {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        let start = v.as_ptr() as usize;
        let first = start.next_multiple_of(HUGE_PAGE);
        let end = (start + bytes) / HUGE_PAGE * HUGE_PAGE;
        if end > first {
            // SAFETY: `first..end` lies inside `v`'s live allocation (rounded inwards to whole
            // huge pages) and MADV_HUGEPAGE only changes how the kernel backs those pages, never
            // their contents or the mapping; the result is ignored (the hint is optional).
            unsafe {
                libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
            }
        }
    }
}

/// A vector of `n` values made by `f`, filled in parallel.
pub fn from_fn<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(f));
    v
}

/// Collect an indexed parallel iterator into a vector allocated once.
pub fn collect<T: Send>(it: impl IndexedParallelIterator<Item = T>) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(it.len());
    v.par_extend(it);
    v
}
