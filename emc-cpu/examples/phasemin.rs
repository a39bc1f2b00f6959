use emc_cpu::trace::{Accel, BuildOptions, Preset};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = emc_cpu::scene::load_with(&args[1], &Default::default()).unwrap();
    let reps: usize = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(20);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(|| {
        let mut a = Accel::build(&scene.vertices, &scene.indices, &BuildOptions::preset(Preset::Fast)).unwrap();
        let mut best = [f64::INFINITY; 5];
        for _ in 0..reps {
            let t = std::time::Instant::now();
            a.rebuild(&scene.vertices).unwrap();
            let w = t.elapsed().as_secs_f64() * 1e3;
            let p = a.build_phases();
            for (b, x) in best.iter_mut().zip([p.aabb, p.encode, p.sort, p.tree, w]) { *b = b.min(x); }
        }
        let n = scene.indices.len() as f64;
        println!("min over {reps} warm rebuilds, ns/tri: aabb {:.1} encode {:.1} sort {:.1} tree {:.1} total {:.1}", best[0]*1e6/n, best[1]*1e6/n, best[2]*1e6/n, best[3]*1e6/n, best[4]*1e6/n);
    });
}
