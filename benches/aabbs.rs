//! Pipeline step 1 (triangle boxes): the AVX2 path against the scalar reference, one thread
//! (`chunk_aabbs`) and the rayon-parallel entry point, on a real mesh (pbrt-bathroom when the
//! shared scenes are present), the watertight `builtin:sphere` and the same sphere with its
//! triangles shuffled (random vertex gathers): `cargo bench -p emc-benches --bench aabbs`.

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_core::Aabb;
use emc_cpu::aabbs::{chunk_aabbs, triangle_aabbs_with, AabbPath};
use emc_cpu::scene::{self, builtin::Pcg32, Mesh};

fn inputs() -> Vec<(String, Mesh)> {
    let mut v = Vec::new();
    if scene::shared_scene_path("pbrt-bathroom").is_some() {
        v.push((
            "pbrt-bathroom".to_string(),
            scene::load("pbrt-bathroom").expect("scene loads"),
        ));
    } else {
        eprintln!("pbrt-bathroom not found; benchmarking built-in scenes only");
    }
    let sphere = scene::load("builtin:sphere").expect("builtin loads");
    let mut shuffled = sphere.clone();
    let mut rng = Pcg32::new(1, 1);
    for i in (1..shuffled.indices.len()).rev() {
        let j = (rng.next_u32() as usize) % (i + 1);
        shuffled.indices.swap(i, j);
    }
    v.push(("sphere".to_string(), sphere));
    v.push(("sphere-shuffled".to_string(), shuffled));
    v
}

fn bench(c: &mut Criterion) {
    eprintln!("detected path: {}", AabbPath::detect().describe());
    let mut paths = vec![AabbPath::Scalar];
    if AabbPath::Avx2.available() {
        paths.push(AabbPath::Avx2);
    }
    for (name, s) in inputs() {
        let n = s.triangle_count();
        let mut out = vec![Aabb::EMPTY; n];
        let mut g = c.benchmark_group(format!("aabbs/{name}"));
        g.throughput(Throughput::Elements(n as u64));
        for &p in &paths {
            g.bench_function(BenchmarkId::new("1-thread", p), |b| {
                b.iter(|| chunk_aabbs(p, &s.vertices, &s.indices, &mut out))
            });
            g.bench_function(BenchmarkId::new("rayon", p), |b| {
                b.iter(|| triangle_aabbs_with(p, &s.vertices, &s.indices, &mut out))
            });
        }
        g.finish();
    }
}

fn main() {
    let mut c = Criterion::default()
        .sample_size(30)
        .warm_up_time(std::time::Duration::from_millis(500))
        .measurement_time(std::time::Duration::from_secs(2))
        .configure_from_args();
    bench(&mut c);
    c.final_summary();
}
