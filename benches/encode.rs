//! Encoder benchmarks (figures, not tests): per backend × layout, encode-only (pre-quantised
//! channel values, 32 B in + 8 B out) and the full pipeline (AABB → code, real size channel,
//! 24 B in + 8 B out) with the dispatched AVX2 quantise and forced scalar, plus the streaming
//! baseline that moves exactly the pipeline's bytes (the memory ceiling).
//!
//! `cargo bench -p emc-benches --bench encode` (16M primitives; `EMC_BENCH_N=1000000` for a
//! quick run). Criterion reports wall-clock throughput; the thread-CPU-time ratios to the
//! baseline come from `emc layout --ratios` (see the README).

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_benches::{bench_n, uniform_boxes};
use emc_core::{Backend, Encoder, Frame, LayoutSpec};
use emc_cpu::encode::{expand_slice, stream_baseline};

const LAYOUTS: [&str; 4] = ["morton63", "emc64-var", "emc64-sort", "emc32-var"];

fn bench(c: &mut Criterion) {
    let n = bench_n();
    let boxes = uniform_boxes(n);
    let frame = Frame::new(&boxes).expect("the uniform scene has a valid frame");
    let mut out = vec![0u64; n];

    let mut g = c.benchmark_group("encode/baseline");
    g.throughput(Throughput::Elements(n as u64));
    g.sample_size(10);
    g.bench_function("stream-24B-in-8B-out", |b| {
        b.iter(|| stream_baseline(&boxes, &mut out).expect("lengths match"))
    });
    g.finish();

    for name in LAYOUTS {
        let spec: LayoutSpec = name.parse().expect("standard layout name");
        let layout = spec.resolve(frame.extent());
        let dispatched = Encoder::for_layout(layout, &frame);
        eprintln!(
            "{name} {layout}: dispatch {} ({}); {}",
            dispatched.backend(),
            dispatched.reason(),
            dispatched.pipeline()
        );
        let q: Vec<[u64; 4]> = boxes
            .iter()
            .map(|b| dispatched.quantizer().quantize(b))
            .collect();
        let mut g = c.benchmark_group(format!("encode/{name}"));
        g.throughput(Throughput::Elements(n as u64));
        g.sample_size(10);
        g.bench_function("pipeline/dispatched", |b| {
            b.iter(|| {
                dispatched
                    .encode_batch(&boxes, &mut out)
                    .expect("lengths match")
            })
        });
        for backend in Backend::ALL {
            let Ok(enc) = Encoder::with_backend(layout, &frame, backend) else {
                eprintln!("{name}: backend {backend} cannot serve this layout here");
                continue;
            };
            g.bench_function(BenchmarkId::new("encode-only", backend), |b| {
                b.iter(|| expand_slice(enc.expander(), &q, &mut out).expect("lengths match"))
            });
            g.bench_function(BenchmarkId::new("pipeline", backend), |b| {
                b.iter(|| enc.encode_batch(&boxes, &mut out).expect("lengths match"))
            });
            g.bench_function(BenchmarkId::new("pipeline-scalar", backend), |b| {
                b.iter(|| {
                    enc.encode_batch_scalar(&boxes, &mut out)
                        .expect("lengths match")
                })
            });
        }
        g.finish();
    }
}

criterion::criterion_group!(benches, bench);
criterion::criterion_main!(benches);
