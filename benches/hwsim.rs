//! Host speed of the EMC unit model: the fast mode (codes through the datapath plus exact
//! timing) in codes per host-second, the timing recurrence alone, and the cycle-stepped mode in
//! simulated cycles per host-second; emc-core's encoder on the same boxes is the baseline of
//! the same run. `cargo bench -p emc-benches --bench hwsim`.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use emc_core::{Encoder, Frame, LayoutSpec};
use emc_cpu::scene::{load_with, SceneOptions};
use emc_hwsim::{MemoryConfig, Mode, Unit, UnitOptions};

fn boxes(prims: usize) -> Vec<emc_core::Aabb> {
    load_with(
        "builtin:uniform",
        &SceneOptions::default().with_prims(prims),
    )
    .expect("built-in scene")
    .aabbs()
}

fn bench(c: &mut Criterion) {
    let big = boxes(2_000_000);
    let frame = Frame::new(&big).expect("frame");
    let mem = MemoryConfig::default();
    let mut g = c.benchmark_group("hwsim-fast");
    g.sample_size(10);
    g.throughput(Throughput::Elements(big.len() as u64));
    for spec in [
        LayoutSpec::Morton63,
        LayoutSpec::Emc64Var,
        LayoutSpec::Emc64Sort,
    ] {
        let unit = Unit::for_spec(&spec, &frame, &UnitOptions::default()).expect("unit");
        g.bench_function(format!("{spec}/fast-run"), |b| {
            b.iter(|| black_box(unit.run(&big, &mem, Mode::Fast).expect("run").stats.cycles))
        });
        g.bench_function(format!("{spec}/timing-only"), |b| {
            b.iter(|| black_box(unit.timing(big.len() as u64, &mem).expect("timing").cycles))
        });
        let enc = Encoder::new(&spec, &frame);
        let mut out = vec![0u64; big.len()];
        g.bench_function(format!("{spec}/emc-core-baseline"), |b| {
            b.iter(|| {
                enc.encode_batch(&big, &mut out).expect("encode");
                black_box(out[0])
            })
        });
    }
    g.finish();

    let small = &big[..200_000];
    let mut g = c.benchmark_group("hwsim-stepped");
    g.sample_size(10);
    for spec in [LayoutSpec::Morton63, LayoutSpec::Emc64Var] {
        let unit = Unit::for_spec(&spec, &frame, &UnitOptions::default()).expect("unit");
        let cycles = unit
            .timing(small.len() as u64, &mem)
            .expect("timing")
            .cycles;
        // Throughput in simulated cycles: criterion's elements/s are cycles per host-second.
        g.throughput(Throughput::Elements(cycles));
        g.bench_function(format!("{spec}/stepped-cycles"), |b| {
            b.iter(|| {
                black_box(
                    unit.run(small, &mem, Mode::Stepped)
                        .expect("run")
                        .stats
                        .cycles,
                )
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
