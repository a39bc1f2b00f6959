//! CPU-time clocks and the median: what every figure of emc-cpu (builds, encoders, traces,
//! reports, benches) is measured with. CPU time, unlike wall time, does not count the time other
//! tenants of a shared machine hold the core.

use std::time::Duration;

/// CPU time consumed by the calling thread (`CLOCK_THREAD_CPUTIME_ID`). Zero on a platform
/// without a per-thread clock (then every CPU figure reads as unavailable, never as wall time).
pub fn thread_cpu_time() -> Duration {
    clock(sys::CLOCK_THREAD_CPUTIME_ID).unwrap_or(Duration::ZERO)
}

/// The clocks of Linux's `clock_gettime`, declared here (the C library is linked by `std`
/// anyway, so the lean library needs no `libc` crate). `timespec` is two `long`s on the 64-bit
/// Linux targets; elsewhere there is no CPU clock and every CPU figure reads as unavailable.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
mod sys {
    use core::ffi::{c_int, c_long};

    /// `struct timespec` of 64-bit Linux.
    #[repr(C)]
    pub struct Timespec {
        pub tv_sec: c_long,
        pub tv_nsec: c_long,
    }

    pub const CLOCK_PROCESS_CPUTIME_ID: c_int = 2;
    pub const CLOCK_THREAD_CPUTIME_ID: c_int = 3;

    unsafe extern "C" {
        pub fn clock_gettime(clock: c_int, ts: *mut Timespec) -> c_int;
    }
}

#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
mod sys {
    pub const CLOCK_PROCESS_CPUTIME_ID: i32 = 2;
    pub const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
}

/// The time of `clock`; `None` where unavailable.
fn clock(id: i32) -> Option<Duration> {
    #[cfg(all(target_os = "linux", target_pointer_width = "64"))]
    {
        let mut ts = sys::Timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `ts` is a valid, writable timespec of the target's layout and the clock ids
        // are constants Linux has always supported; the call only writes `ts`.
        let rc = unsafe { sys::clock_gettime(id, &mut ts) };
        if rc == 0 && ts.tv_sec >= 0 && (0..1_000_000_000).contains(&ts.tv_nsec) {
            return Some(Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32));
        }
        None
    }
    #[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
    {
        let _ = id;
        None
    }
}

/// CPU time consumed so far by every worker of a rayon pool (the caller waits in `install`
/// and is idle, so it is not counted).
pub fn pool_cpu_time(pool: &rayon::ThreadPool) -> Duration {
    pool.broadcast(|_| thread_cpu_time()).into_iter().sum()
}

/// Time the calling thread has spent runnable but waiting for a core (the scheduler's run
/// queue, second field of Linux's `/proc/thread-self/schedstat`): time other tenants of the
/// machine held the core it wanted. Zero where unavailable.
pub fn thread_run_queue_wait() -> Duration {
    #[cfg(target_os = "linux")]
    {
        if let Ok(s) = std::fs::read_to_string("/proc/thread-self/schedstat") {
            if let Some(ns) = s
                .split_whitespace()
                .nth(1)
                .and_then(|f| f.parse::<u64>().ok())
            {
                return Duration::from_nanos(ns);
            }
        }
    }
    Duration::ZERO
}

/// `(CPU time, run-queue wait)` of each worker of a rayon pool so far, by thread index.
pub fn pool_thread_times(pool: &rayon::ThreadPool) -> Vec<(Duration, Duration)> {
    pool.broadcast(|_| (thread_cpu_time(), thread_run_queue_wait()))
}

/// CPU time (user + system) of this whole process, finished threads included
/// (`CLOCK_PROCESS_CPUTIME_ID`); `None` where unavailable.
pub fn process_cpu_time() -> Option<Duration> {
    clock(sys::CLOCK_PROCESS_CPUTIME_ID)
}

/// Median of a list (the mean of the middle two for an even count); NaN when empty.
pub fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}
