//! The radix sort of (code, index) pairs against rayon's `par_sort_unstable` on the same pairs,
//! 1M to 16M keys of EMC-like codes (`emc64-var` and `emc32-var` codes of a clustered box set
//! with sizes over six decades), on 1 and 2 threads:
//! `cargo bench -p emc-benches --bench sort` (`EMC_BENCH_N` caps the largest size).

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_core::{Aabb, Encoder, Frame, LayoutSpec};
use emc_cpu::sort::sort_pairs;
use glam::Vec3;
use rayon::prelude::*;

/// Boxes in a few dense clusters plus a sparse background, sizes log-uniform over 1e-6..1.
fn boxes(n: usize) -> Vec<Aabb> {
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32) / (1u64 << 24) as f32
    };
    (0..n)
        .map(|i| {
            let c = if i % 4 == 0 {
                Vec3::new(next() * 100.0, next() * 10.0, next())
            } else {
                let k = (i % 7) as f32;
                Vec3::new(10.0 * k, 2.0 + k * 0.5, 0.5) + Vec3::new(next(), next(), next()) * 0.3
            };
            let r = 1e-6f32 * 10f32.powf(6.0 * next());
            Aabb::new(c - Vec3::splat(r), c + Vec3::splat(r))
        })
        .collect()
}

fn codes64(b: &[Aabb]) -> Vec<u64> {
    let enc = Encoder::new(&LayoutSpec::Emc64Var, &Frame::new(b).expect("finite boxes"));
    let mut out = vec![0u64; b.len()];
    out.par_chunks_mut(1 << 14)
        .zip(b.par_chunks(1 << 14))
        .for_each(|(o, c)| enc.encode_batch(c, o).expect("same length"));
    out
}

fn codes32(b: &[Aabb]) -> Vec<u32> {
    let enc = Encoder::new(&LayoutSpec::Emc32Var, &Frame::new(b).expect("finite boxes"));
    let mut out = vec![0u32; b.len()];
    out.par_chunks_mut(1 << 14)
        .zip(b.par_chunks(1 << 14))
        .for_each(|(o, c)| enc.encode_batch_u32(c, o).expect("32-bit layout"));
    out
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

fn main() {
    let max = emc_benches::bench_n();
    let sizes: Vec<usize> = [1usize << 20, 1 << 22, 1 << 24]
        .into_iter()
        .filter(|&n| n <= max.max(1 << 20))
        .collect();
    let mut c = Criterion::default()
        .sample_size(10)
        .measurement_time(std::time::Duration::from_secs(3))
        .configure_from_args();
    for &n in &sizes {
        let b = boxes(n);
        let k64 = codes64(&b);
        let k32 = codes32(&b);
        drop(b);
        let mut g = c.benchmark_group(format!("sort/{n}"));
        g.throughput(Throughput::Elements(n as u64));
        for threads in [1usize, 2] {
            let p = pool(threads);
            g.bench_function(BenchmarkId::new("radix-u64", threads), |bch| {
                bch.iter(|| {
                    p.install(|| {
                        let (mut k, mut v) = (k64.clone(), (0..n as u32).collect::<Vec<_>>());
                        sort_pairs(&mut k, &mut v).expect("same length");
                        (k, v)
                    })
                })
            });
            g.bench_function(BenchmarkId::new("par_sort_unstable-u64", threads), |bch| {
                bch.iter(|| {
                    p.install(|| {
                        let mut pairs: Vec<(u64, u32)> = k64.iter().copied().zip(0u32..).collect();
                        pairs.par_sort_unstable();
                        pairs
                    })
                })
            });
            g.bench_function(BenchmarkId::new("radix-u32", threads), |bch| {
                bch.iter(|| {
                    p.install(|| {
                        let (mut k, mut v) = (k32.clone(), (0..n as u32).collect::<Vec<_>>());
                        sort_pairs(&mut k, &mut v).expect("same length");
                        (k, v)
                    })
                })
            });
            g.bench_function(BenchmarkId::new("par_sort_unstable-u32", threads), |bch| {
                bch.iter(|| {
                    p.install(|| {
                        let mut pairs: Vec<(u32, u32)> = k32.iter().copied().zip(0u32..).collect();
                        pairs.par_sort_unstable();
                        pairs
                    })
                })
            });
        }
        g.finish();
    }
    c.final_summary();
}
