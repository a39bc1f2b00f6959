//! A custom primitive with the library alone: 100,000 spheres given to a `Scene` as boxes and
//! an intersection callback, traced in parallel; the callback counts its calls, which the
//! scene's tree keeps to a few per ray instead of one per sphere. Runs in CI:
//! `cargo run --release -p emc-cpu --no-default-features --example spheres`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use emc_core::Aabb;
use emc_cpu::trace::{CustomHit, Ray, Scene};
use glam::Vec3;

/// The nearest hit of the sphere (`c`, `r`) in the ray's interval.
fn hit_sphere(ray: &Ray, c: Vec3, r: f32) -> Option<CustomHit> {
    let o = ray.origin - c;
    let (a, b, cc) = (ray.dir.dot(ray.dir), o.dot(ray.dir), o.dot(o) - r * r);
    let disc = b * b - a * cc;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    [(-b - s) / a, (-b + s) / a]
        .into_iter()
        .find(|t| (ray.tnear..=ray.tfar).contains(t))
        .map(|t| {
            // u, v: the hit point's direction from the centre, as longitude and height.
            let n = (o + ray.dir * t) / r;
            CustomHit {
                t,
                u: n.z.atan2(n.x),
                v: n.y,
            }
        })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Spheres on a jittered 3-D lattice (a small deterministic generator, no dependency).
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut unit = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let balls: Vec<(Vec3, f32)> = (0..100_000)
        .map(|i| {
            let cell = Vec3::new((i % 50) as f32, ((i / 50) % 50) as f32, (i / 2500) as f32);
            let jitter = Vec3::new(unit(), unit(), unit()) * 0.5;
            (cell * 2.0 + jitter, 0.2 + 0.5 * unit())
        })
        .collect();
    let boxes: Vec<Aabb> = balls
        .iter()
        .map(|&(c, r)| Aabb::new(c - Vec3::splat(r), c + Vec3::splat(r)))
        .collect();
    let calls = Arc::new(AtomicU64::new(0));
    let mut scene = Scene::new();
    let (b, n) = (balls.clone(), calls.clone());
    let id = scene.add_custom(&boxes, move |ray, prim| {
        n.fetch_add(1, Ordering::Relaxed);
        let (c, r) = b[prim as usize];
        hit_sphere(ray, c, r)
    })?;
    scene.commit()?;

    // A 256 × 256 fan of rays from outside the lattice towards its far face.
    let eye = Vec3::new(-20.0, 60.0, -30.0);
    let rays: Vec<Ray> = (0..256 * 256)
        .map(|i| {
            let (x, y) = ((i % 256) as f32 / 255.0, (i / 256) as f32 / 255.0);
            Ray::new(eye, Vec3::new(100.0 * x, 100.0 * y, 80.0) - eye)
        })
        .collect();
    let hits = scene.intersect_batch(&rays);
    let n_hit = hits.iter().flatten().count();
    let per_ray = calls.load(Ordering::Relaxed) as f64 / rays.len() as f64;
    println!(
        "{} spheres: {n_hit} of {} rays hit, {per_ray:.1} callback calls per ray (brute force: {})",
        balls.len(),
        rays.len(),
        balls.len()
    );
    // Every hit is on the sphere it names, and nearer than any other sphere along the ray
    // (checked by brute force for a sample of the rays).
    for (r, h) in rays.iter().zip(&hits).step_by(997) {
        let nearest = balls
            .iter()
            .enumerate()
            .filter_map(|(k, &(c, rad))| hit_sphere(r, c, rad).map(|h| (h.t, k as u32)))
            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        assert_eq!(h.map(|h| (h.t, h.prim)), nearest);
        if let Some(h) = h {
            assert_eq!(h.geom, id);
        }
    }
    assert!(per_ray < 100.0, "the tree culls: {per_ray} calls per ray");
    println!("first hit {:?}", hits.iter().flatten().next());
    Ok(())
}
