//! A deforming mesh traced frame by frame with the library alone: one `Accel` built once, then
//! per frame `Accel::refit` with the moved vertices (same topology, boxes updated) and every
//! fourth frame `Accel::rebuild` (a fresh tree, buffers reused), and a probe ray whose hit
//! follows the surface. Runs in CI:
//! `cargo run --release -p emc-cpu --no-default-features --example animate`.

use emc_cpu::trace::{Accel, BuildOptions, Preset, Ray};
use glam::Vec3;

/// A `n × n` grid in the xy plane, displaced in z by a travelling wave at time `t`.
fn grid(n: usize, t: f32) -> Vec<Vec3> {
    (0..n * n)
        .map(|i| {
            let (x, y) = (
                (i % n) as f32 / (n - 1) as f32,
                (i / n) as f32 / (n - 1) as f32,
            );
            let z = 0.1 * (6.0 * (x + y) + t).sin();
            Vec3::new(x, y, z)
        })
        .collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let n = 200;
    let mut indices = Vec::with_capacity(2 * (n - 1) * (n - 1));
    for y in 0..n - 1 {
        for x in 0..n - 1 {
            let i = (y * n + x) as u32;
            let (r, d) = (i + 1, i + n as u32);
            indices.push([i, r, d]);
            indices.push([r, d + 1, d]);
        }
    }
    let mut accel = Accel::build(&grid(n, 0.0), &indices, &BuildOptions::preset(Preset::Fast))?;
    // Straight down onto the point (0.5, 0.5): the hit's height is the wave's there.
    let probe = Ray::new(Vec3::new(0.5, 0.5, 1.0), Vec3::new(0.0, 0.0, -1.0));
    for frame in 0..8 {
        let t = frame as f32 * 0.5;
        if frame % 4 == 0 {
            accel.rebuild(&grid(n, t))?;
        } else {
            accel.refit(&grid(n, t))?;
        }
        let hit = accel
            .intersect(&probe)
            .ok_or("the probe ray missed the surface")?;
        let z = 1.0 - hit.t;
        let want = 0.1 * (6.0f32 + t).sin();
        println!(
            "frame {frame} ({}): surface at z = {z:+.4} (wave {want:+.4}), triangle {}",
            if frame % 4 == 0 {
                "rebuilt"
            } else {
                "refitted"
            },
            hit.prim
        );
        // The grid is piecewise linear: within a cell's curvature of the exact wave.
        assert!(
            (z - want).abs() < 2e-3,
            "frame {frame}: hit at {z}, wave at {want}"
        );
    }
    Ok(())
}
