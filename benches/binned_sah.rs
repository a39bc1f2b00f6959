//! Speed of the `binned-sah` reference builder (boxes in, one-primitive-per-leaf BVH out) on
//! pbrt-bathroom, or `builtin:mixed` when the shared scenes are absent, with 1 and 2 threads.
//! Before criterion's wall-clock medians it prints a thread-CPU-time report (Linux):
//! `cargo bench -p emc-benches --bench binned_sah`.

use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_core::Aabb;
use emc_cpu::bvh::binned_sah::{build_binned_sah, DEFAULT_BINS};

/// The boxes to build over and the scene's name.
fn input() -> (String, Vec<Aabb>) {
    emc_benches::bathroom_or_mixed()
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

/// Median wall time and mean CPU time of `runs` builds per thread count, and the throughput in
/// primitives per thread-CPU-second.
fn cpu_report(name: &str, boxes: &[Aabb]) {
    const RUNS: usize = 7;
    let n = boxes.len() as f64;
    let mut base_cpu = None;
    for threads in [1, 2] {
        let p = pool(threads);
        p.install(|| build_binned_sah(boxes, DEFAULT_BINS).expect("valid boxes"));
        let mut walls = Vec::with_capacity(RUNS);
        let cpu0 = emc_cpu::cputime::process_cpu_time();
        for _ in 0..RUNS {
            let t = Instant::now();
            let bvh = p.install(|| build_binned_sah(boxes, DEFAULT_BINS).expect("valid boxes"));
            walls.push(t.elapsed());
            drop(bvh);
        }
        let cpu = emc_cpu::cputime::process_cpu_time()
            .zip(cpu0)
            .map(|(b, a)| (b - a) / RUNS as u32);
        walls.sort();
        let wall = walls[RUNS / 2];
        match cpu {
            Some(cpu) => {
                let ratio = base_cpu.map_or(1.0, |b: Duration| cpu.as_secs_f64() / b.as_secs_f64());
                base_cpu.get_or_insert(cpu);
                println!(
                    "binned-sah {name}, {threads} thread(s): wall median {:.1} ms ({:.2} Mprims/s), \
                     CPU {:.1} ms ({:.2} Mprims per thread-CPU-second, CPU {ratio:.2}x the 1-thread run)",
                    wall.as_secs_f64() * 1e3,
                    n / wall.as_secs_f64() / 1e6,
                    cpu.as_secs_f64() * 1e3,
                    n / cpu.as_secs_f64() / 1e6,
                );
            }
            None => println!(
                "binned-sah {name}, {threads} thread(s): wall median {:.1} ms ({:.2} Mprims/s); \
                 no per-thread CPU clock on this system",
                wall.as_secs_f64() * 1e3,
                n / wall.as_secs_f64() / 1e6,
            ),
        }
    }
}

fn bench(c: &mut Criterion, name: &str, boxes: &[Aabb]) {
    let mut g = c.benchmark_group("binned_sah");
    g.sample_size(10);
    g.throughput(Throughput::Elements(boxes.len() as u64));
    for threads in [1, 2] {
        let p = pool(threads);
        g.bench_with_input(
            BenchmarkId::new(name, format!("{threads} thread(s)")),
            &boxes,
            |b, boxes| {
                b.iter(|| p.install(|| build_binned_sah(boxes, DEFAULT_BINS).expect("valid")))
            },
        );
    }
    g.finish();
}

fn main() {
    let (name, boxes) = input();
    cpu_report(&name, &boxes);
    let mut c = Criterion::default().configure_from_args();
    bench(&mut c, &name, &boxes);
    c.final_summary();
}
