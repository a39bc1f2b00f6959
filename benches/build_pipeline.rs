//! The whole build pipeline (boxes → collapsed BVH) per builder on 1 and 2 threads, on
//! pbrt-bathroom (or `builtin:mixed` when the shared scenes are absent). Before criterion's
//! wall-clock medians it prints each builder's per-phase thread-CPU report (median of 5), for
//! cold builds (fresh buffers) and warm ones (a `BuildArena` holding the previous build's):
//! `cargo bench -p emc-benches --bench build`.

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_core::{Aabb, LayoutSpec};
use emc_cpu::build::{
    build_aabbs, build_aabbs_in, BuildArena, BuildReport, Builder, Phase, PipelineOptions,
};

fn input() -> (String, Vec<Aabb>) {
    emc_benches::bathroom_or_mixed()
}

fn opts(builder: Builder, threads: usize) -> PipelineOptions {
    PipelineOptions::default()
        .with_layout(LayoutSpec::Emc64Var)
        .with_builder(builder)
        .with_threads(threads)
}

/// Per-phase thread-CPU milliseconds of the median (by total CPU) of 5 builds, cold and warm.
fn cpu_report(name: &str, boxes: &[Aabb]) {
    for builder in Builder::ALL {
        for warm in [false, true] {
            report_one(name, boxes, builder, warm);
        }
    }
}

fn report_one(name: &str, boxes: &[Aabb], builder: Builder, warm: bool) {
    let label = if warm { "warm" } else { "cold" };
    let mut base = None;
    for threads in [1usize, 2] {
        let mut arena = BuildArena::new();
        if warm {
            let first = build_aabbs_in(boxes.to_vec(), &opts(builder, threads), &mut arena);
            arena.recycle(first.expect("valid boxes"));
        }
        let mut runs: Vec<BuildReport> = (0..5)
            .map(|_| {
                if warm {
                    let out = build_aabbs_in(boxes.to_vec(), &opts(builder, threads), &mut arena)
                        .expect("valid boxes");
                    let r = out.report.clone();
                    arena.recycle(out);
                    r
                } else {
                    build_aabbs(boxes.to_vec(), &opts(builder, threads))
                        .expect("valid boxes")
                        .report
                }
            })
            .collect();
        {
            runs.sort_by(|a, b| a.total().cpu_ms.total_cmp(&b.total().cpu_ms));
            let r = &runs[2];
            let phases: Vec<String> = Phase::ALL
                .iter()
                .map(|&p| format!("{} {:.1}", p.name(), r.phase(p).cpu_ms))
                .collect();
            let cpu = r.total().cpu_ms;
            let ratio = base.map(|b: f64| cpu / b).unwrap_or(1.0);
            base.get_or_insert(cpu);
            println!(
                "{name} {builder} {threads}T {label}: cpu ms [{}] total {cpu:.1} (x{ratio:.2} of 1T), \
                 wall {:.1} ms, {:.2} Mprims/CPU-s",
                phases.join(", "),
                r.total().wall_ms,
                r.mprims_per_cpu_s()
            );
        }
    }
}

fn main() {
    let (name, boxes) = input();
    cpu_report(&name, &boxes);
    let mut c = Criterion::default()
        .sample_size(10)
        .measurement_time(std::time::Duration::from_secs(4))
        .configure_from_args();
    let mut g = c.benchmark_group(format!("build/{name}"));
    g.throughput(Throughput::Elements(boxes.len() as u64));
    for builder in Builder::ALL {
        for threads in [1usize, 2] {
            g.bench_function(BenchmarkId::new(builder.name(), threads), |b| {
                b.iter(|| build_aabbs(boxes.clone(), &opts(builder, threads)).expect("valid boxes"))
            });
        }
    }
    g.finish();
    c.final_summary();
}
