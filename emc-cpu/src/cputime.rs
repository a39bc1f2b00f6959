//! CPU-time clocks and the median: what every figure of emc-cpu (builds, encoders, traces,
//! reports, benches) is measured with. CPU time, unlike wall time, does not count the time other
//! tenants of a shared machine hold the core.

use std::time::Duration;

/// CPU time consumed by the calling thread (`CLOCK_THREAD_CPUTIME_ID`). Zero on a platform
/// without a per-thread clock (then every CPU figure reads as unavailable, never as wall time).
pub fn thread_cpu_time() -> Duration {
    #[cfg(unix)]
    {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `ts` is a valid, writable timespec and the clock id is a constant every unix
        // target supports; the call only writes `ts`.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
        if rc == 0 {
            return Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32);
        }
    }
    Duration::ZERO
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

/// CPU time (user + system) of this whole process, finished threads included (`getrusage`);
/// `None` where unavailable.
pub fn process_cpu_time() -> Option<Duration> {
    #[cfg(unix)]
    {
        // SAFETY: `rusage` is plain old data; the all-zero value is valid.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: `ru` is a valid, writable rusage and RUSAGE_SELF is always supported.
        let rc = unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) };
        if rc == 0 {
            let tv = |t: libc::timeval| {
                Duration::new(t.tv_sec as u64, 0) + Duration::from_micros(t.tv_usec as u64)
            };
            return Some(tv(ru.ru_utime) + tv(ru.ru_stime));
        }
    }
    None
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
