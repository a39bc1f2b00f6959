//! Shared helpers of the emc benchmarks: the primitive count (`EMC_BENCH_N`) and the
//! deterministic box sets the encoder benches run on.

use emc_core::Aabb;
use emc_cpu::scene::{load_with, SceneOptions};

/// Primitives per benchmark: `EMC_BENCH_N` when set (quick runs), else 16M (16,777,216).
pub fn bench_n() -> usize {
    std::env::var("EMC_BENCH_N")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&n| n > 0)
        .unwrap_or(1 << 24)
}

/// The boxes of `builtin:uniform` with `n` triangles (deterministic, default seed).
pub fn uniform_boxes(n: usize) -> Vec<Aabb> {
    let opts = SceneOptions::default().with_prims(n);
    load_with("builtin:uniform", &opts)
        .expect("the built-in uniform scene generates")
        .aabbs()
}

/// The scene the builder benches run on and its boxes: `pbrt-bathroom` when the shared scenes
/// are present, else `builtin:mixed` (with a notice).
pub fn bathroom_or_mixed() -> (String, Vec<Aabb>) {
    let spec = if emc_cpu::scene::shared_scene_path("pbrt-bathroom").is_some() {
        "pbrt-bathroom"
    } else {
        eprintln!("pbrt-bathroom not found; benchmarking builtin:mixed instead");
        "builtin:mixed"
    };
    let scene = emc_cpu::scene::load(spec).expect("benchmark scene loads");
    (spec.to_string(), scene.aabbs())
}
