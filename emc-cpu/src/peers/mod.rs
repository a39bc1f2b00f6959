//! The other ray tracers measured beside emc in one process by `emc compare`, and the ray loop
//! every tracer (emc's presets and each peer) is timed with, as the peer harness in
//! `../shared/peers/embree/embree_bench.c` times Embree.
//!
//! The loop ([`trace_closest`], [`trace_occluded`]): one single-ray call per ray in protocol
//! order; one thread is a plain loop on the calling thread, `N` threads are the caller plus
//! `N − 1` scoped threads taking chunks of [`CHUNK`] rays in order, each with flush-to-zero and
//! denormals-are-zero set while it traces ([`FtzGuard`]), as the harness sets them. The peers
//! themselves (`embree`: Embree 3 through a hand-written binding; `obvhs`: the obvhs crate)
//! exist only with the `peers` cargo feature, so a plain build needs neither.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glam::Vec3;

use crate::cputime::thread_cpu_time;
use crate::trace::workload::{pcg_hash, primary_rays, AoCounts, Camera, CameraMode, SceneFrame};
use crate::trace::{Accel, Hit, Ray, Scene};

#[cfg(feature = "peers")]
pub mod embree;
#[cfg(feature = "peers")]
pub mod obvhs;

/// Rays a thread takes at a time when several trace (the harness's `CHUNK`).
pub const CHUNK: usize = 4096;

/// MXCSR bit 15: flush-to-zero.
#[cfg(target_arch = "x86_64")]
const MXCSR_FTZ: u32 = 1 << 15;
/// MXCSR bit 6: denormals-are-zero.
#[cfg(target_arch = "x86_64")]
const MXCSR_DAZ: u32 = 1 << 6;

/// Sets flush-to-zero and denormals-are-zero on the current thread (x86-64 SSE control
/// register; nothing elsewhere) and restores the previous mode when dropped.
#[derive(Debug)]
pub struct FtzGuard {
    /// MXCSR before the guard set it.
    #[cfg(target_arch = "x86_64")]
    previous: u32,
}

impl FtzGuard {
    /// Turn FTZ and DAZ on for this thread until the guard is dropped.
    pub fn new() -> FtzGuard {
        #[cfg(target_arch = "x86_64")]
        {
            let previous = read_mxcsr();
            write_mxcsr(previous | MXCSR_FTZ | MXCSR_DAZ);
            FtzGuard { previous }
        }
        #[cfg(not(target_arch = "x86_64"))]
        FtzGuard {}
    }

    /// True when this thread's floating-point mode flushes denormals (always false off x86-64).
    pub fn active() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            read_mxcsr() & (MXCSR_FTZ | MXCSR_DAZ) == MXCSR_FTZ | MXCSR_DAZ
        }
        #[cfg(not(target_arch = "x86_64"))]
        false
    }
}

impl Default for FtzGuard {
    fn default() -> Self {
        FtzGuard::new()
    }
}

impl Drop for FtzGuard {
    fn drop(&mut self) {
        #[cfg(target_arch = "x86_64")]
        write_mxcsr(self.previous);
    }
}

#[cfg(target_arch = "x86_64")]
fn read_mxcsr() -> u32 {
    let mut v = 0u32;
    // SAFETY: `stmxcsr` stores the 4-byte SSE control register to the address given, which is
    // `v`, a live, writable, aligned u32; it touches nothing else (no stack, no flags).
    unsafe {
        core::arch::asm!(
            "stmxcsr [{p}]",
            p = in(reg) &mut v as *mut u32,
            options(nostack, preserves_flags)
        );
    }
    v
}

#[cfg(target_arch = "x86_64")]
fn write_mxcsr(v: u32) {
    // SAFETY: `ldmxcsr` loads the SSE control register from `v`, a live aligned u32; callers
    // only pass a value read by `stmxcsr` with at most the FTZ and DAZ bits added, so no
    // reserved bit is set (which would fault) and no exception is unmasked. The mode change
    // alters only how denormal floats round, never memory safety.
    unsafe {
        core::arch::asm!(
            "ldmxcsr [{p}]",
            p = in(reg) &v as *const u32,
            options(nostack, readonly, preserves_flags)
        );
    }
}

/// Wall time and the CPU time of the threads that did the work.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Timing {
    /// Wall time.
    pub wall: Duration,
    /// Summed CPU time of the working threads (zero where the platform has no thread clock).
    pub cpu: Duration,
}

/// Run `work` on the calling thread and `threads − 1` scoped threads, each under an
/// [`FtzGuard`]; returns the wall time from before the first spawn to after the last join and
/// the threads' summed CPU time inside `work`.
fn on_threads(threads: usize, work: &(dyn Fn() + Sync)) -> Timing {
    let cpu_ns = AtomicU64::new(0);
    let timed = || {
        let _ftz = FtzGuard::new();
        let c0 = thread_cpu_time();
        work();
        let c = thread_cpu_time().saturating_sub(c0);
        cpu_ns.fetch_add(c.as_nanos() as u64, Ordering::Relaxed);
    };
    let t0 = Instant::now();
    std::thread::scope(|s| {
        for _ in 1..threads.max(1) {
            s.spawn(timed);
        }
        timed();
    });
    Timing {
        wall: t0.elapsed(),
        cpu: Duration::from_nanos(cpu_ns.into_inner()),
    }
}

/// Closest hits of `rays`, one `hit(state, ray)` call per ray in order, on `threads` threads
/// (chunks of [`CHUNK`]); `state` makes each thread's private state (an intersect context).
/// Returns one answer per ray and the times.
pub fn trace_closest<S>(
    rays: &[Ray],
    threads: usize,
    state: impl Fn() -> S + Sync,
    hit: impl Fn(&mut S, &Ray) -> Option<Hit> + Sync,
) -> (Vec<Option<Hit>>, Timing) {
    let mut out: Vec<Option<Hit>> = vec![None; rays.len()];
    let elapsed = {
        let work = Mutex::new(out.chunks_mut(CHUNK).zip(rays.chunks(CHUNK)));
        on_threads(threads, &|| {
            let mut s = state();
            loop {
                let next = work.lock().unwrap_or_else(|e| e.into_inner()).next();
                let Some((o, r)) = next else { break };
                for (h, ray) in o.iter_mut().zip(r) {
                    *h = hit(&mut s, ray);
                }
            }
        })
    };
    (out, elapsed)
}

/// How many of `rays` are occluded, one `occluded(state, ray)` call per ray in order, on
/// `threads` threads (chunks of [`CHUNK`]); returns the count and the times.
pub fn trace_occluded<S>(
    rays: &[Ray],
    threads: usize,
    state: impl Fn() -> S + Sync,
    occluded: impl Fn(&mut S, &Ray) -> bool + Sync,
) -> (u64, Timing) {
    let next = AtomicUsize::new(0);
    let count = AtomicU64::new(0);
    let elapsed = on_threads(threads, &|| {
        let mut s = state();
        let mut local = 0u64;
        loop {
            let b = next.fetch_add(CHUNK, Ordering::Relaxed);
            if b >= rays.len() {
                break;
            }
            for ray in &rays[b..(b + CHUNK).min(rays.len())] {
                local += occluded(&mut s, ray) as u64;
            }
        }
        count.fetch_add(local, Ordering::Relaxed);
    });
    (count.into_inner(), elapsed)
}

/// A structure the protocol's rays can be traced through with the loop above.
pub trait Tracer: Sync {
    /// Closest hits of `rays` (tnear..tfar of each ray) on `threads` threads, with the times.
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing);
    /// Occluded count of `rays` on `threads` threads, with the times.
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing);
}

impl Tracer for Scene {
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || (), |_, r| self.intersect(r))
    }
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(rays, threads, || (), |_, r| Scene::occluded(self, r))
    }
}

impl Tracer for Accel {
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || (), |_, r| self.intersect(r))
    }
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(rays, threads, || (), |_, r| Accel::occluded(self, r))
    }
}

/// The protocol's rays of one scene: the primary rays and what the AO rays need.
#[derive(Debug, Clone)]
pub struct Protocol {
    /// The scene's triangles in id order (normals of the AO rays' origins).
    pub tris: Vec<[Vec3; 3]>,
    /// Bounds and diagonal of the referenced vertices.
    pub frame: SceneFrame,
    /// The primary rays, `res × res` in 8×8-tile order.
    pub primary: Vec<Ray>,
}

impl Protocol {
    /// The protocol for `tris` seen from `mode` at `res × res` (rays made on the current rayon
    /// pool).
    pub fn new(tris: Vec<[Vec3; 3]>, mode: CameraMode, res: u32) -> Protocol {
        let frame = SceneFrame::of(&tris);
        let cam = Camera::protocol(&frame, mode);
        let primary = primary_rays(&cam, res, res);
        Protocol {
            tris,
            frame,
            primary,
        }
    }

    /// The AO rays of a tracer's own primary hits (4 per hit, primary order), as the harness
    /// computes them ([`harness_ao_rays`]).
    pub fn ao_rays(&self, hits: &[Option<Hit>]) -> Vec<Ray> {
        harness_ao_rays(&self.primary, hits, &self.tris, self.frame.diag)
    }

    /// Trace the whole protocol once through `t` on `threads` threads: its counts, its AO rays,
    /// and the primary and AO times.
    pub fn run(&self, t: &dyn Tracer, threads: usize) -> ProtocolRun {
        let (hits, primary_time) = t.closest(&self.primary, threads);
        let ao = self.ao_rays(&hits);
        let (ao_occluded, ao_time) = t.occluded(&ao, threads);
        ProtocolRun {
            counts: AoCounts {
                primary_hits: hits.iter().filter(|h| h.is_some()).count() as u64,
                ao_rays: ao.len() as u64,
                ao_occluded,
            },
            ao,
            primary_time,
            ao_time,
        }
    }
}

/// The protocol's AO rays of every primary hit (4 per hit, in primary order), with the peer
/// harness' arithmetic, so that its rays and counts are reproduced bit for bit: the normal
/// divided by its length (`(0, 1, 0)` for a zero-area triangle), the angle `φ = 2π·u2` and its
/// cosine and sine in `f64` rounded to `f32`, the direction divided by its length; under
/// FTZ/DAZ, as the harness runs. (`workload::ao_rays` takes φ, cos and sin in `f32` and
/// normalizes by a reciprocal: its directions differ from these in the low bits of most rays,
/// which moves AO counts by a ray or so.)
pub fn harness_ao_rays(
    primary: &[Ray],
    hits: &[Option<Hit>],
    tris: &[[Vec3; 3]],
    diag: f64,
) -> Vec<Ray> {
    harness_ao_rays_by(primary, hits, |h| tris[h.prim as usize], diag)
}

/// [`harness_ao_rays`] with the hit triangle's corners given by `tri_of` (for a scene of
/// instances: the instance's transform applied to the mesh's triangle).
pub fn harness_ao_rays_by(
    primary: &[Ray],
    hits: &[Option<Hit>],
    tri_of: impl Fn(&Hit) -> [Vec3; 3],
    diag: f64,
) -> Vec<Ray> {
    let _ftz = FtzGuard::new();
    let eps = (1e-4 * diag) as f32;
    let tfar = (0.1 * diag) as f32;
    let mut out = Vec::with_capacity(4 * hits.iter().filter(|h| h.is_some()).count());
    for (i, (ray, hit)) in primary.iter().zip(hits).enumerate() {
        let Some(hit) = hit else { continue };
        let p = ray.origin + hit.t * ray.dir;
        let t = tri_of(hit);
        let c = (t[1] - t[0]).cross(t[2] - t[0]);
        let l = c.dot(c).sqrt();
        let mut n = if l > 0.0 { c / l } else { Vec3::Y };
        if n.dot(ray.dir) > 0.0 {
            n = -n;
        }
        let o = p + n * eps;
        // Duff et al. 2017 orthonormal basis around n.
        let sign = if n.z >= 0.0 { 1.0f32 } else { -1.0 };
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let b1 = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let b2 = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        for k in 0..4u32 {
            let h1 = pcg_hash((i as u32).wrapping_mul(4).wrapping_add(k));
            let h2 = pcg_hash(h1);
            let u1 = (h1 >> 8) as f32 * (1.0 / 16_777_216.0);
            let u2 = (h2 >> 8) as f32 * (1.0 / 16_777_216.0);
            let r = u1.sqrt();
            let phi = 2.0 * std::f64::consts::PI * u2 as f64;
            let (lx, ly) = (r * phi.cos() as f32, r * phi.sin() as f32);
            let lz = (1.0 - u1).max(0.0).sqrt();
            let d = b1 * lx + b2 * ly + n * lz;
            out.push(Ray::segment(o, d / d.dot(d).sqrt(), 0.0, tfar));
        }
    }
    out
}

/// One pass of the protocol through one tracer.
#[derive(Debug, Clone)]
pub struct ProtocolRun {
    /// Primary hits, AO rays, AO occluded.
    pub counts: AoCounts,
    /// The AO rays generated from this tracer's primary hits.
    pub ao: Vec<Ray>,
    /// Times of the primary rays.
    pub primary_time: Timing,
    /// Times of the AO rays.
    pub ao_time: Timing,
}
