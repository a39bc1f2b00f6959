//! Mesh loading speed on the shared scenes: the whole `scene::load` (read, zstd, line check,
//! `tobj`, assembly), the parse of already decompressed bytes, and the line check alone (its
//! cost relative to the parse is the overhead of naming malformed lines). Scenes up to 1M
//! triangles by default; `EMC_BENCH_LARGE=1` adds crown and San Miguel:
//! `cargo bench -p emc-benches --bench scene_load`.

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput};
use emc_cpu::scene::{self, obj};

fn bench(c: &mut Criterion) {
    let large = std::env::var_os("EMC_BENCH_LARGE").is_some();
    for (name, tris) in scene::SHARED_SCENES {
        if tris > 1_000_000 && !large {
            continue;
        }
        let Some(path) = scene::shared_scene_path(name) else {
            eprintln!("skipped {name}: not in the shared scenes directory");
            continue;
        };
        let bytes = obj::read_file(&path).expect("scene reads");
        let mut g = c.benchmark_group(format!("scene_load/{name}"));
        g.throughput(Throughput::Elements(tris as u64));
        g.sample_size(10);
        g.warm_up_time(Duration::from_millis(100));
        g.measurement_time(Duration::from_secs(if tris > 1_000_000 { 30 } else { 5 }));
        g.bench_function(BenchmarkId::new("load", name), |b| {
            b.iter(|| scene::load(name).expect("scene loads"))
        });
        g.bench_function(BenchmarkId::new("parse", name), |b| {
            b.iter(|| obj::parse_obj_bytes(&bytes, &path, name.to_string()).expect("parses"))
        });
        g.bench_function(BenchmarkId::new("check", name), |b| {
            b.iter(|| obj::check_obj_bytes(&bytes, &path).expect("checks"))
        });
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("pool");
        g.bench_function(BenchmarkId::new("check-1-thread", name), |b| {
            b.iter(|| pool.install(|| obj::check_obj_bytes(&bytes, &path).expect("checks")))
        });
        g.finish();
    }
}

fn main() {
    let mut c = Criterion::default().configure_from_args();
    bench(&mut c);
    c.final_summary();
}
