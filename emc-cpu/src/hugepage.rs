//! Transparent huge pages for the large buffers a build writes once (its output): one
//! `madvise(MADV_HUGEPAGE)` over a fresh allocation turns some thousand 4 KiB page faults per
//! 4 MiB into two 2 MiB ones. Linux only; elsewhere (or when the kernel refuses) a no-op.

/// Ask for huge pages over the unused capacity of `v` (call before writing to it).
pub fn advise<T>(v: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = v.capacity() * core::mem::size_of::<T>();
        if bytes < 2 * HUGE {
            return;
        }
        let start = v.as_ptr() as usize;
        let lo = start.next_multiple_of(HUGE);
        let hi = (start + bytes) & !(HUGE - 1);
        if hi > lo {
            // SAFETY: madvise only changes how the kernel backs the pages of this range, which
            // lies inside the allocation of `v` (rounded inwards to whole huge pages); it
            // neither reads nor writes the memory, and a refusal leaves it as it was.
            unsafe {
                libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}
