//! Build and trace a mesh with the library alone (works with `default-features = false`): a
//! built-in scene, an `Accel` of each preset, a fan of rays from outside, the hits counted and
//! the first one printed. Runs in CI:
//! `cargo run --release -p emc-cpu --no-default-features --example trace_mesh`.

use emc_cpu::scene::{builtin, SceneOptions};
use emc_cpu::trace::{Accel, BuildOptions, Preset, Ray};
use glam::Vec3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let opts = SceneOptions::default().with_prims(50_000);
    let scene = builtin::generate("sphere", &opts)?;
    let (lo, hi) = scene.vertices.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &v| (lo.min(v), hi.max(v)),
    );
    let center = 0.5 * (lo + hi);
    let eye = center + Vec3::new(0.0, 0.0, 3.0 * (hi - lo).max_element());
    // A 64 × 64 fan of rays from `eye` towards the box of the scene.
    let rays: Vec<Ray> = (0..64 * 64)
        .map(|i| {
            let (x, y) = ((i % 64) as f32 / 63.0, (i / 64) as f32 / 63.0);
            let target = Vec3::new(lo.x + x * (hi.x - lo.x), lo.y + y * (hi.y - lo.y), center.z);
            Ray::new(eye, target - eye)
        })
        .collect();
    for preset in [Preset::Fast, Preset::Balanced, Preset::Quality] {
        let accel = Accel::build(
            &scene.vertices,
            &scene.indices,
            &BuildOptions::preset(preset),
        )?;
        let hits = accel.intersect_batch(&rays);
        let n = hits.iter().flatten().count();
        let first = hits.iter().flatten().next();
        println!(
            "{preset:?}: {} triangles, {n} of {} rays hit; first hit {first:?}",
            scene.indices.len(),
            rays.len()
        );
        // Any-hit agrees with closest-hit.
        let occluded = accel.occluded_batch(&rays);
        assert!(occluded.iter().zip(&hits).all(|(o, h)| *o == h.is_some()));
    }
    Ok(())
}
