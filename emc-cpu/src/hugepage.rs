//! Large build buffers backed by transparent huge pages where the OS allows it: the pipeline
//! allocates ~100 bytes per primitive of fresh memory, and with 4 KiB pages the page faults
//! alone cost as much as a whole phase. Only a hint: without THP the buffers are ordinary.

use rayon::prelude::*;

/// Buffers smaller than this are left alone (a huge page is 2 MiB).
const MIN_BYTES: usize = 4 << 20;

/// Ask the kernel to back the 2 MiB-aligned interior of `v`'s (not yet touched) capacity with
/// huge pages. Harmless if THP is off or the call fails.
fn advise<T>(v: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = v.capacity() * std::mem::size_of::<T>();
        if bytes < MIN_BYTES || std::env::var_os("EMC_NO_HUGEPAGE").is_some() {
            return;
        }
        let start = v.as_ptr() as usize;
        let lo = start.next_multiple_of(HUGE);
        let hi = (start + bytes) & !(HUGE - 1);
        if hi > lo {
            // SAFETY: [lo, hi) lies inside the vector's own allocation (page aligned, since
            // both ends are 2 MiB multiples within it); MADV_HUGEPAGE changes only how the kernel
            // backs those pages, never their contents or validity.
            unsafe {
                libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

/// A vector of `n` copies of `x`, filled in parallel after the huge-page hint.
pub fn filled<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    advise(&v);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(|_| x));
    v
}

/// A vector of `n` values made by `f`, filled in parallel after the huge-page hint.
pub fn from_fn<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    advise(&v);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(f));
    v
}

/// Collect an indexed parallel iterator into a vector after the huge-page hint.
pub fn collect<T: Send>(it: impl IndexedParallelIterator<Item = T>) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(it.len());
    advise(&v);
    v.par_extend(it);
    v
}
