//! A forest of instances with the library alone: one mesh built once as a scene of its own,
//! then placed 10,000 times under rotations, scales and mirrors in a two-level `Scene`, with
//! a mask that hides every other row; rays traced in parallel, then every instance moved and
//! the top level committed again. Runs in CI:
//! `cargo run --release -p emc-cpu --no-default-features --example instances`.

use std::sync::Arc;
use std::time::Instant;

use emc_cpu::scene::{builtin, SceneOptions};
use emc_cpu::trace::{BuildOptions, Preset, Ray, Scene};
use glam::{Affine3A, Quat, Vec3};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The instanced mesh: a built-in sphere of 20,000 triangles, radius about 1.
    let mesh = builtin::generate("sphere", &SceneOptions::default().with_prims(20_000))?;
    let mut tree = Scene::new();
    tree.add_mesh(
        &mesh.vertices,
        &mesh.indices,
        &BuildOptions::preset(Preset::Quality),
    )?;
    tree.commit()?;
    let size = tree.bounds().max - tree.bounds().min;
    let tree = Arc::new(tree);

    // 100 × 100 instances on a plane, each turned, scaled, every third one mirrored.
    let side = 100;
    let place = |k: usize, lift: f32| {
        let (i, j) = ((k % side) as f32, (k / side) as f32);
        let s = 0.4 + 0.1 * ((k * 7) % 5) as f32;
        let mirror = if k.is_multiple_of(3) { -1.0 } else { 1.0 };
        Affine3A::from_scale_rotation_translation(
            Vec3::new(mirror * s, s, s),
            Quat::from_rotation_y(k as f32),
            Vec3::new(i * size.x, lift, j * size.z),
        )
    };
    let mut forest = Scene::new();
    for k in 0..side * side {
        let id = forest.add_instance(tree.clone(), place(k, 0.0))?;
        // Odd rows carry mask bit 1 only, even rows bit 0.
        forest.set_mask(id, if (k / side) % 2 == 1 { 0b10 } else { 0b01 })?;
    }
    let t = Instant::now();
    forest.commit()?;
    println!(
        "{} instances of {} triangles: top level built in {:.1} ms, {:.1} MiB",
        forest.geometry_count(),
        mesh.triangle_count(),
        t.elapsed().as_secs_f64() * 1e3,
        forest.memory_bytes() as f64 / 1048576.0
    );

    // Rays straight down onto every instance's centre, seeing all rows or the even ones only.
    let rays: Vec<Ray> = (0..side * side)
        .map(|k| {
            let c = place(k, 0.0).transform_point3(Vec3::ZERO);
            Ray::new(c + Vec3::new(0.0, 10.0, 0.0), Vec3::new(0.0, -1.0, 0.0))
        })
        .collect();
    let all = forest.intersect_batch(&rays);
    let even: Vec<Ray> = rays.iter().map(|r| r.with_mask(0b01)).collect();
    let seen = forest.intersect_batch(&even);
    let hits = all.iter().flatten().count();
    let even_hits = seen.iter().flatten().count();
    println!(
        "{hits} of {} rays hit; with mask 0b01, {even_hits}",
        rays.len()
    );
    assert_eq!(hits, rays.len(), "every ray aims at an instance");
    assert_eq!(even_hits, rays.len() / 2, "the mask hides the odd rows");
    for (k, h) in all.iter().enumerate() {
        assert_eq!(
            h.map(|h| h.instance),
            Some(k as u32),
            "ray {k} hits its own instance"
        );
    }

    // Lift every instance by one unit and commit again: the hits follow.
    let t = Instant::now();
    for k in 0..side * side {
        forest.set_transform(k as u32, place(k, 1.0))?;
    }
    forest.commit()?;
    println!(
        "moved every instance and committed again in {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let moved = forest.intersect_batch(&rays);
    for (a, b) in all.iter().zip(&moved) {
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(
            (a.t - b.t - 1.0).abs() < 1e-3,
            "lifted by one: {} then {}",
            a.t,
            b.t
        );
    }
    println!("first hit {:?}", moved[0]);
    Ok(())
}
