//! Tracer benchmarks: single-ray primary and AO throughput of the 8-wide (AVX2) and 4-wide
//! (SSE) trees on one thread (the per-thread figure the protocol compares), each against its
//! scalar node test in the same run, on a built-in scene and (when present) the shared
//! `sionna-san-francisco`.
//! Run: `cargo bench -p emc-benches --bench trace` (set `EMC_TRACE_RES` for another image size).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use emc_cpu::scene::{self, SceneOptions};
use emc_cpu::trace::traverse::{closest, occluded};
use emc_cpu::trace::workload::{
    all_ao_rays, primary_rays, trace_closest, Camera, CameraMode, SceneFrame,
};
use emc_cpu::trace::{Accel, BuildOptions, NodeTest, Preset, Ray, TraceStats};

/// Image edge of the benchmark rays (the protocol uses 1024; smaller keeps runs short).
fn res() -> u32 {
    std::env::var("EMC_TRACE_RES")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&r| r > 0)
        .unwrap_or(256)
}

struct Workload {
    name: String,
    accel: Accel,
    primary: Vec<Ray>,
    ao: Vec<Ray>,
}

fn workload(spec: &str, prims: Option<usize>) -> Option<Workload> {
    let s = scene::load_with(spec, &SceneOptions::default().with_prims(prims)).ok()?;
    let tris: Vec<_> = (0..s.triangle_count()).map(|i| s.triangle(i)).collect();
    let accel = Accel::build(
        &s.vertices,
        &s.indices,
        &BuildOptions::preset(Preset::Quality),
    )
    .ok()?;
    let frame = SceneFrame::of(&tris);
    let cam = Camera::protocol(&frame, CameraMode::for_scene(&s.name));
    let primary = primary_rays(&cam, res(), res());
    let (hits, _) = trace_closest(accel.wide_bvh(), &primary, NodeTest::Simd, false);
    let (ao, _) = all_ao_rays(&primary, &hits, &tris, frame.diag);
    Some(Workload {
        name: s.name.clone(),
        accel,
        primary,
        ao,
    })
}

fn bench_trace(c: &mut Criterion) {
    let mut loads = vec![workload("builtin:city", Some(200_000))];
    if scene::shared_scene_path("sionna-san-francisco").is_some() {
        loads.push(workload("sionna-san-francisco", None));
    } else {
        eprintln!("shared scenes absent: benchmarking built-in scenes only");
    }
    for w in loads.into_iter().flatten() {
        let mut g = c.benchmark_group(format!("trace/{}", w.name));
        g.sample_size(10);
        let bvh = w.accel.wide_bvh();
        for kind in [
            NodeTest::Avx512,
            NodeTest::Avx2,
            NodeTest::Simd,
            NodeTest::Scalar8,
            NodeTest::Scalar,
        ] {
            g.throughput(Throughput::Elements(w.primary.len() as u64));
            g.bench_function(BenchmarkId::new("primary", format!("{kind:?}")), |b| {
                b.iter(|| {
                    let mut s = TraceStats::default();
                    w.primary
                        .iter()
                        .filter(|r| closest::<false>(bvh, r, kind, &mut s).is_some())
                        .count()
                })
            });
            g.throughput(Throughput::Elements(w.ao.len() as u64));
            g.bench_function(BenchmarkId::new("ao", format!("{kind:?}")), |b| {
                b.iter(|| {
                    let mut s = TraceStats::default();
                    w.ao.iter()
                        .filter(|r| occluded::<false>(bvh, r, kind, &mut s))
                        .count()
                })
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench_trace);
criterion_main!(benches);
