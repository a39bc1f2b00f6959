//! Speed of the `atrbvh` treelet restructuring post-pass on the morton63 LBVH of pbrt-bathroom
//! (or `builtin:mixed` when the shared scenes are absent), with 1 and 2 threads. Before
//! criterion's wall-clock medians it prints thread-CPU time per million primitives:
//! `cargo bench -p emc-benches --bench atrbvh`.

use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_core::{Aabb, LayoutSpec};
use emc_cpu::build::{build_aabbs, Builder, PipelineOptions};
use emc_cpu::bvh::atrbvh::{restructure, AtrConfig};
use emc_cpu::bvh::refit::CollapseParams;
use emc_cpu::bvh::{sah_cost, Bvh, SahConstants};
use emc_cpu::cputime::thread_cpu_time;

/// The scene's name, its boxes and its morton63 LBVH with one primitive per leaf.
fn input() -> (String, Vec<Aabb>, Bvh) {
    let (spec, aabbs) = emc_benches::bathroom_or_mixed();
    let opts = PipelineOptions::default()
        .with_layout(LayoutSpec::Morton63)
        .with_builder(Builder::Lbvh)
        .with_threads(2)
        .with_collapse(CollapseParams::NONE);
    let bvh = build_aabbs(aabbs.clone(), &opts).expect("LBVH builds").bvh;
    (spec, aabbs, bvh)
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

/// Median wall and median pool CPU time of `RUNS` restructurings per thread count, as ms per
/// million primitives; also the share spent in the input check and the two SAH sums.
fn cpu_report(name: &str, aabbs: &[Aabb], bvh: &Bvh) {
    const RUNS: usize = 5;
    let mp = aabbs.len() as f64 / 1e6;
    let cfg = AtrConfig::default();
    let mut base = None;
    for threads in [1, 2] {
        let p = pool(threads);
        let (mut walls, mut cpus) = (Vec::new(), Vec::new());
        let mut stats = None;
        for _ in 0..RUNS + 1 {
            let mut t = bvh.clone();
            let c0 = emc_cpu::cputime::pool_cpu_time(&p);
            let w0 = Instant::now();
            let s = p.install(|| restructure(&mut t, aabbs, &cfg).expect("valid input"));
            walls.push(w0.elapsed().as_secs_f64() * 1e3);
            cpus.push((emc_cpu::cputime::pool_cpu_time(&p) - c0).as_secs_f64() * 1e3);
            stats = Some(s);
        }
        // The first run warms the pool and the allocator.
        walls.remove(0);
        cpus.remove(0);
        walls.sort_by(f64::total_cmp);
        cpus.sort_by(f64::total_cmp);
        let (wall, cpu) = (walls[RUNS / 2], cpus[RUNS / 2]);
        let ratio = cpu / *base.get_or_insert(cpu);
        let s = stats.expect("ran");
        println!(
            "atrbvh {name} ({} prims), {threads} thread(s): wall median {wall:.1} ms \
             ({:.1} ms/Mprims), thread-CPU median {cpu:.1} ms ({:.1} ms/Mprims, {ratio:.2}x the \
             1-thread CPU); SAH {:.2} -> {:.2}, {} of {} treelets improved",
            aabbs.len(),
            wall / mp,
            cpu / mp,
            s.sah_before,
            s.sah_after,
            s.treelets_improved,
            s.treelets_formed
        );
    }
    // The serial parts inside `restructure`: the input check and the two SAH sums.
    let t0 = thread_cpu_time();
    bvh.validate(aabbs).expect("valid");
    let t1 = thread_cpu_time();
    let _ = sah_cost(bvh, SahConstants::COLLAPSE);
    let t2 = thread_cpu_time();
    println!(
        "  of which serial: validate {:.1} ms, one SAH sum {:.1} ms (twice per call)",
        (t1 - t0).as_secs_f64() * 1e3,
        (t2 - t1).as_secs_f64() * 1e3
    );
}

fn main() {
    let (name, aabbs, bvh) = input();
    cpu_report(&name, &aabbs, &bvh);
    let mut c = Criterion::default()
        .configure_from_args()
        .sample_size(10)
        .measurement_time(Duration::from_secs(10));
    let mut g = c.benchmark_group("atrbvh");
    g.throughput(Throughput::Elements(aabbs.len() as u64));
    for threads in [1, 2] {
        let p = pool(threads);
        g.bench_with_input(BenchmarkId::new(&name, threads), &threads, |b, _| {
            b.iter_batched(
                || bvh.clone(),
                |mut t| {
                    p.install(|| restructure(&mut t, &aabbs, &AtrConfig::default()))
                        .expect("valid input")
                },
                criterion::BatchSize::LargeInput,
            )
        });
    }
    g.finish();
    c.final_summary();
}
