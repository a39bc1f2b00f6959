//! Large build buffers, optionally backed by transparent huge pages: the pipeline allocates
//! ~100 bytes per primitive of fresh memory and 4 KiB page faults cost about a phase. Opt-in
//! (`EMC_HUGEPAGE=1`): on a busy machine THP compaction stalls made builds slower and erratic.

use rayon::prelude::*;

/// Buffers smaller than this are left alone (a huge page is 2 MiB).
const MIN_BYTES: usize = 4 << 20;

/// With `EMC_HUGEPAGE=1`, ask the kernel to back the 2 MiB-aligned interior of `v`'s (not yet
/// touched) capacity with huge pages. Harmless if THP is off or the call fails.
fn advise<T>(v: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = v.capacity() * std::mem::size_of::<T>();
        if bytes < MIN_BYTES || !enabled() {
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

/// True when `EMC_HUGEPAGE=1` (read once).
pub fn enabled() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("EMC_HUGEPAGE").is_some_and(|v| v == "1"))
}

/// A vector of `n` copies of `x`: with huge pages, filled in parallel after the hint; else
/// `vec![x; n]` (zeroed allocator pages, no writing pass, when `x` is a zero integer).
pub fn filled<T: Copy + Send + Sync>(n: usize, x: T) -> Vec<T> {
    if !enabled() {
        return vec![x; n];
    }
    let mut v: Vec<T> = Vec::with_capacity(n);
    advise(&v);
    v.par_extend((0..n).into_par_iter().with_min_len(1 << 14).map(|_| x));
    v
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
