//! Tests of `trace::Scene`, the multi-geometry face of the tracer: two-level traversal through
//! instances (mirrored, non-uniformly scaled, rotated) against brute force over the flattened
//! world-space triangles, ray masks, custom primitives (spheres through a callback) against an
//! analytic brute force with the callback counted, refit of a mesh in a scene, tracing from
//! many threads, and the errors of bad edits.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use emc_core::Aabb;
use emc_cpu::scene::{builtin, SceneOptions};
use emc_cpu::trace::traverse::brute_force_packets_many;
use emc_cpu::trace::wide::TriPacket;
use emc_cpu::trace::{BuildOptions, CustomHit, Hit, Preset, Ray, Scene, TraceError};
use glam::{Affine3A, Quat, Vec3};

/// A point or direction in f64.
#[derive(Clone, Copy)]
struct D3([f64; 3]);

impl D3 {
    fn sub(self, o: D3) -> D3 {
        D3([0, 1, 2].map(|a| self.0[a] - o.0[a]))
    }
    fn dot(self, o: D3) -> f64 {
        self.0[0] * o.0[0] + self.0[1] * o.0[1] + self.0[2] * o.0[2]
    }
    fn cross(self, o: D3) -> D3 {
        let (a, b) = (self.0, o.0);
        D3([
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ])
    }
}

/// `v` in f64.
fn d3(v: Vec3) -> D3 {
    D3([v.x as f64, v.y as f64, v.z as f64])
}
use rayon::prelude::*;

/// Vertices and triangles of a mesh.
type MeshData = (Vec<Vec3>, Vec<[u32; 3]>);

/// A mesh of a built-in scene, `prims` triangles.
fn mesh(name: &str, prims: usize, seed: u64) -> MeshData {
    let s = builtin::generate(
        name,
        &SceneOptions::default().with_prims(prims).with_seed(seed),
    )
    .unwrap();
    (s.vertices, s.indices)
}

/// `m` scaled into the unit cube around the origin (so transforms place it).
fn normalise(mut m: MeshData) -> MeshData {
    let (lo, hi) = m.0.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), v| (lo.min(*v), hi.max(*v)),
    );
    let (c, s) = (0.5 * (lo + hi), 1.0 / (hi - lo).max_element());
    for v in &mut m.0 {
        *v = (*v - c) * s;
    }
    m
}

/// A random transform: rotation, non-uniform scale in [0.3, 3] per axis, a mirror on one axis
/// for every other transform (`k` odd), and a translation in [-12, 12]^3.
fn transform(rng: &mut builtin::Pcg32, k: usize) -> Affine3A {
    let axis = Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    )
    .try_normalize()
    .unwrap_or(Vec3::Z);
    let q = Quat::from_axis_angle(axis, rng.range(0.0, std::f32::consts::TAU));
    let mut s = Vec3::new(
        rng.range(0.3, 3.0),
        rng.range(0.3, 3.0),
        rng.range(0.3, 3.0),
    );
    if k % 2 == 1 {
        s[k % 3] = -s[k % 3];
    }
    let t = Vec3::new(
        rng.range(-12.0, 12.0),
        rng.range(-12.0, 12.0),
        rng.range(-12.0, 12.0),
    );
    Affine3A::from_scale_rotation_translation(s, q, t)
}

/// One world-space triangle of the flattened scene, with the ids a hit on it reports and the
/// masks that must both pass.
#[derive(Clone, Copy)]
struct Flat {
    tri: [Vec3; 3],
    instance: u32,
    geom: u32,
    prim: u32,
    masks: (u32, u32),
}

/// The f64 distance along `r` to the plane of `t` and how far outside the triangle the ray
/// meets the plane (0 inside: the most negative barycentric weight times the longest edge, an
/// estimate of the distance to the triangle); `None` when the ray is parallel to the plane.
fn f64_hit(r: &Ray, t: &[Vec3; 3]) -> Option<(f64, f64)> {
    let [a, b, c] = t.map(d3);
    let (o, d) = (d3(r.origin), d3(r.dir));
    let (e1, e2) = (b.sub(a), c.sub(a));
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-300 {
        return None;
    }
    let s = o.sub(a);
    let u = s.dot(p) / det;
    let q = s.cross(e1);
    let v = d.dot(q) / det;
    let tt = e2.dot(q) / det;
    let w = u.min(v).min(1.0 - u - v);
    let edge = [e1, e2, c.sub(b)]
        .iter()
        .map(|e| e.dot(*e).sqrt())
        .fold(0.0, f64::max);
    Some((tt, (-w).max(0.0) * edge))
}

/// The spatial tolerance of a hit of `r` at distance `t`: 1e-5 of the coordinates' magnitude
/// there. The world-space triangles carry the rounding of their transform (a few ulps of
/// their coordinates), which is that far off the object-space triangles the scene traces.
fn space_tol(r: &Ray, t: f64) -> f64 {
    let p = (r.origin + r.dir * t as f32).abs().max_element() as f64;
    1e-5 * p.max(r.origin.abs().max_element() as f64).max(1.0)
}

/// Two distances along `r` within 1e-5 relative, of themselves or of the coordinates'
/// magnitude ([`space_tol`]) over the direction's length.
fn close(r: &Ray, a: f64, b: f64) -> bool {
    let coords = space_tol(r, a) / r.dir.length() as f64;
    (a - b).abs() <= (1e-5 * a.abs().max(b.abs())).max(coords).max(1e-30)
}

/// The cosine of the angle between `r` and the normal of `tri` (small: a grazing ray, which
/// sees a shift of the plane by the transform's rounding magnified by its inverse).
fn cos_to(r: &Ray, tri: &[Vec3; 3]) -> f64 {
    let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]).normalize_or_zero();
    (n.dot(r.dir.normalize_or_zero()).abs() as f64).max(1e-30)
}

/// Two distances along `r` to triangle `tri` within [`close`], or within the distance that a
/// shift of the triangle's plane by [`space_tol`] makes at the ray's angle to it.
fn close_on(r: &Ray, tri: &[Vec3; 3], a: f64, b: f64) -> bool {
    let along = space_tol(r, a) / cos_to(r, tri) / r.dir.length() as f64;
    close(r, a, b) || (a - b).abs() <= along
}

/// True when `r` hits `tri` at about distance `t` or meets its plane within [`space_tol`] of
/// it (over the cosine: where the ray meets the plane moves that much).
fn nearly_hits(r: &Ray, tri: &[Vec3; 3], t: f32) -> bool {
    f64_hit(r, tri).is_some_and(|(tt, out)| {
        close_on(r, tri, tt, t as f64) && out <= space_tol(r, tt) / cos_to(r, tri)
    })
}

/// True when `r` passes within [`space_tol`] of an edge of `tri` (hit or not).
fn grazes(r: &Ray, tri: &[Vec3; 3]) -> bool {
    let shrunk = |k: usize| {
        // The triangle pulled in by the tolerance toward its centroid: a ray that hits the
        // triangle but not the pulled-in one passes near an edge.
        let c = (tri[0] + tri[1] + tri[2]) / 3.0;
        let d = tri[k] - c;
        let tol = (space_tol(r, f64_hit(r, tri).map_or(0.0, |h| h.0)) / cos_to(r, tri)) as f32;
        c + d * (1.0 - (4.0 * tol / d.length().max(1e-30)).min(1.0))
    };
    let inner = [shrunk(0), shrunk(1), shrunk(2)];
    match (f64_hit(r, tri), f64_hit(r, &inner)) {
        (Some((t, out)), Some((_, out_in))) => {
            out <= space_tol(r, t) / cos_to(r, tri) && out_in > 0.0
        }
        _ => true,
    }
}

/// Compare the scene's closest hits and occlusion with brute force over `flat`; returns how
/// many rays were judged grazing or distorted (answers that differ where the ray passes
/// within the tolerance of an edge, or a near tie).
fn check(scene: &Scene, flat: &[Flat], rays: &[Ray], label: &str) -> usize {
    let hits = scene.intersect_batch(rays);
    let occ = scene.occluded_batch(rays);
    let index: HashMap<(u32, u32, u32), usize> = flat
        .iter()
        .enumerate()
        .map(|(k, f)| ((f.instance, f.geom, f.prim), k))
        .collect();
    // Brute force over the triangles each ray's mask sees, by the packet test: per mask, its
    // triangles and their packets, and the rays that carry it traced together.
    let mut by_mask: HashMap<u32, Vec<usize>> = HashMap::new();
    for (i, r) in rays.iter().enumerate() {
        by_mask.entry(r.mask).or_default().push(i);
    }
    let mut seen_of: HashMap<u32, Vec<&Flat>> = HashMap::new();
    let mut bfs: Vec<Option<Hit>> = vec![None; rays.len()];
    for (&mask, which) in &by_mask {
        let seen: Vec<&Flat> = flat
            .iter()
            .filter(|f| f.masks.0 & mask != 0 && f.masks.1 & mask != 0)
            .collect();
        let tris: Vec<[Vec3; 3]> = seen.iter().map(|f| f.tri).collect();
        let packets = TriPacket::of_triangles(&tris);
        let mine: Vec<Ray> = which.iter().map(|&i| rays[i]).collect();
        let got: Vec<Option<Hit>> = mine
            .par_chunks(256)
            .flat_map_iter(|c| brute_force_packets_many(c, &packets))
            .collect();
        for (&i, h) in which.iter().zip(got) {
            bfs[i] = h;
        }
        seen_of.insert(mask, seen);
    }
    let grazing = AtomicU64::new(0);
    rays.par_iter().enumerate().for_each(|(i, r)| {
        let seen = &seen_of[&r.mask];
        let bf = bfs[i];
        let got = hits[i];
        let mine = got.map(|h| {
            let k = *index
                .get(&(h.instance, h.geom, h.prim))
                .unwrap_or_else(|| panic!("{label} ray {i}: hit names no primitive: {h:?}"));
            let f = &flat[k];
            // Masks filter exactly: the reported geometry is one the ray sees.
            assert!(
                f.masks.0 & r.mask != 0 && f.masks.1 & r.mask != 0,
                "{label} ray {i}: hit on a masked-out geometry {h:?}"
            );
            // What the scene reports is (nearly) there.
            assert!(
                nearly_hits(r, &f.tri, h.t),
                "{label} ray {i}: {h:?} is not on its triangle ({:?})",
                f64_hit(r, &f.tri)
            );
            f
        });
        let want = bf.map(|b| seen[b.prim as usize]);
        let same = |f: &Flat, h: &Hit| (f.instance, f.geom, f.prim) == (h.instance, h.geom, h.prim);
        match (bf, got) {
            (Some(b), Some(h)) if same(want.unwrap(), &h) => {
                let tri = &want.unwrap().tri;
                assert!(
                    close_on(r, tri, b.t as f64, h.t as f64),
                    "{label} ray {i}: t {} vs {}",
                    h.t,
                    b.t
                );
            }
            (None, None) => {}
            (b, h) => {
                // Brute force and the scene disagree: either a near tie (same distance), or
                // the nearer of the two answers grazes an edge (so the farther side may pass
                // by it).
                let tie = matches!((b, h), (Some(b), Some(h)) if close(r, b.t as f64, h.t as f64));
                let near_first = match (b, h) {
                    (Some(b), Some(h)) if b.t < h.t => want.unwrap(),
                    (Some(_), None) => want.unwrap(),
                    _ => mine.unwrap(),
                };
                assert!(
                    tie || grazes(r, &near_first.tri),
                    "{label} ray {i}: scene {h:?} vs brute force {b:?} on {:?}",
                    f64_hit(r, &near_first.tri)
                );
                grazing.fetch_add(1, Ordering::Relaxed);
            }
        }
        // Any hit agrees with closest hit.
        assert_eq!(
            occ[i],
            got.is_some(),
            "{label} ray {i}: occluded vs closest"
        );
    });
    grazing.into_inner() as usize
}

/// `n` rays over the flattened scene, masks drawn from `masks`: half aimed at inner points of
/// random triangles from random origins, half from random origins in random directions.
fn rays_for(flat: &[Flat], n: usize, seed: u64, masks: &[u32]) -> Vec<Ray> {
    let mut rng = builtin::Pcg32::new(seed, 11);
    let (lo, hi) = flat.iter().flat_map(|f| f.tri).fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), v| (lo.min(v), hi.max(v)),
    );
    let pad = (hi - lo) * 0.2;
    (0..n)
        .map(|i| {
            let o = Vec3::new(
                rng.range(lo.x - pad.x, hi.x + pad.x),
                rng.range(lo.y - pad.y, hi.y + pad.y),
                rng.range(lo.z - pad.z, hi.z + pad.z),
            );
            let d = if i % 2 == 0 {
                let t = flat[rng.next_u32() as usize % flat.len()].tri;
                let (u, v) = (rng.range(0.1, 0.45), rng.range(0.1, 0.45));
                t[0] + (t[1] - t[0]) * u + (t[2] - t[0]) * v - o
            } else {
                Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                )
            };
            let d = if d == Vec3::ZERO { Vec3::Z } else { d };
            Ray::new(o, d).with_mask(masks[rng.next_u32() as usize % masks.len()])
        })
        .collect()
}

/// Two scenes to instance (one with two meshes of different masks), a top level of random
/// instances of both plus one mesh of its own; the flattened triangles of it all.
fn instanced(count: usize, seed: u64, preset: Preset) -> (Scene, Vec<Flat>) {
    let opts = BuildOptions::preset(preset);
    let parts = [
        normalise(mesh("sphere", 1200, seed)),
        normalise(mesh("city", 900, seed + 1)),
        normalise(mesh("uniform", 700, seed + 2)),
    ];
    // Scene A: sphere (mask 0b01) and city (mask 0b10); scene B: uniform (all).
    let mut a = Scene::new();
    let ga0 = a.add_mesh(&parts[0].0, &parts[0].1, &opts).unwrap();
    let ga1 = a.add_mesh(&parts[1].0, &parts[1].1, &opts).unwrap();
    a.set_mask(ga0, 0b01).unwrap();
    a.set_mask(ga1, 0b10).unwrap();
    a.commit().unwrap();
    let mut b = Scene::new();
    b.add_mesh(&parts[2].0, &parts[2].1, &opts).unwrap();
    b.commit().unwrap();
    let (a, b) = (Arc::new(a), Arc::new(b));
    let a_masks = [0b01, 0b10];

    let mut rng = builtin::Pcg32::new(seed, 5);
    let mut top = Scene::new();
    let mut flat = Vec::new();
    for k in 0..count {
        let m = transform(&mut rng, k);
        let use_a = k % 3 != 2;
        let id = top
            .add_instance(if use_a { a.clone() } else { b.clone() }, m)
            .unwrap();
        let imask = [Ray::ALL, 0b100, 0b011][k % 3];
        top.set_mask(id, imask).unwrap();
        let geoms: Vec<(u32, &MeshData, u32)> = if use_a {
            vec![(0, &parts[0], a_masks[0]), (1, &parts[1], a_masks[1])]
        } else {
            vec![(0, &parts[2], Ray::ALL)]
        };
        for (g, (v, ix), gmask) in geoms {
            for (p, t) in ix.iter().enumerate() {
                flat.push(Flat {
                    tri: t.map(|i| m.transform_point3(v[i as usize])),
                    instance: id,
                    geom: g,
                    prim: p as u32,
                    masks: (imask, gmask),
                });
            }
        }
    }
    // A mesh straight in the top level (no instance).
    let (v, ix) = mesh("stadium", 800, seed + 3);
    let v: Vec<Vec3> = v.iter().map(|p| *p * 0.05).collect();
    let g = top.add_mesh(&v, &ix, &opts).unwrap();
    for (p, t) in ix.iter().enumerate() {
        flat.push(Flat {
            tri: t.map(|i| v[i as usize]),
            instance: Hit::NO_INSTANCE,
            geom: g,
            prim: p as u32,
            masks: (Ray::ALL, Ray::ALL),
        });
    }
    (top, flat)
}

#[test]
fn two_level_traversal_equals_brute_force_over_the_flattened_triangles() {
    for (seed, preset, count) in [
        (1, Preset::Quality, 40),
        (2, Preset::Fast, 60),
        (3, Preset::Balanced, 25),
    ] {
        let (mut scene, flat) = instanced(count, seed, preset);
        let masks = [Ray::ALL, 0b001, 0b010, 0b100, 0b110];
        let rays = rays_for(&flat, 10_000, seed, &masks);
        // Uncommitted (each geometry's box tested in turn), then through the top-level tree:
        // the same answers.
        let before = scene.intersect_batch(&rays);
        scene.commit().unwrap();
        assert_eq!(
            before,
            scene.intersect_batch(&rays),
            "seed {seed}: commit changed hits"
        );
        let grazing = check(&scene, &flat, &rays, &format!("{preset:?} seed {seed}"));
        assert!(
            grazing <= 50,
            "seed {seed}: {grazing} grazing rays of 10,000"
        );
        eprintln!(
            "{preset:?} seed {seed}: {count} instances, {} triangles, {} rays hit, {grazing} grazing",
            flat.len(),
            scene.intersect_batch(&rays).iter().flatten().count()
        );
    }
}

#[test]
fn moving_instances_and_recommitting_follows_the_transforms() {
    let (mut scene, flat) = instanced(30, 9, Preset::Fast);
    scene.commit().unwrap();
    // Move every instance by a fixed offset and recommit (the top tree is rebuilt in place).
    let shift = Affine3A::from_translation(Vec3::new(3.0, -2.0, 1.5));
    for id in 0..30 {
        let m = scene.transform(id).unwrap();
        scene.set_transform(id, shift * m).unwrap();
    }
    scene.commit().unwrap();
    let moved: Vec<Flat> = flat
        .iter()
        .map(|f| Flat {
            tri: if f.instance == Hit::NO_INSTANCE {
                f.tri
            } else {
                f.tri.map(|v| shift.transform_point3(v))
            },
            ..*f
        })
        .collect();
    let rays = rays_for(&moved, 6_000, 9, &[Ray::ALL, 0b011]);
    let grazing = check(&scene, &moved, &rays, "moved");
    assert!(grazing <= 30, "{grazing} grazing rays");
}

/// The first hit of a sphere (centre `c`, radius `r`) in `[tnear, tfar]`, in f64.
fn sphere_hit(ray: &Ray, c: Vec3, r: f32) -> Option<f32> {
    let (o, d) = (d3(ray.origin).sub(d3(c)), d3(ray.dir));
    let (a, b, cc) = (d.dot(d), o.dot(d), o.dot(o) - (r as f64) * (r as f64));
    let disc = b * b - a * cc;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    [(-b - s) / a, (-b + s) / a]
        .into_iter()
        .map(|t| t as f32)
        .find(|&t| t >= ray.tnear && t <= ray.tfar)
}

/// `n` random spheres in a cube of side 100, radii 0.2 to 1.5.
fn spheres(n: usize, seed: u64) -> Vec<(Vec3, f32)> {
    let mut rng = builtin::Pcg32::new(seed, 7);
    (0..n)
        .map(|_| {
            let c = Vec3::new(
                rng.range(0.0, 100.0),
                rng.range(0.0, 100.0),
                rng.range(0.0, 100.0),
            );
            (c, rng.range(0.2, 1.5))
        })
        .collect()
}

#[test]
fn custom_spheres_equal_an_analytic_brute_force_and_the_tree_culls() {
    let balls = spheres(5_000, 4);
    let boxes: Vec<Aabb> = balls
        .iter()
        .map(|&(c, r)| Aabb::new(c - Vec3::splat(r), c + Vec3::splat(r)))
        .collect();
    let calls = Arc::new(AtomicU64::new(0));
    let mut scene = Scene::new();
    let (b2, c2) = (balls.clone(), calls.clone());
    let g = scene
        .add_custom(&boxes, move |ray, prim| {
            c2.fetch_add(1, Ordering::Relaxed);
            let (c, r) = b2[prim as usize];
            sphere_hit(ray, c, r).map(|t| CustomHit { t, u: 0.0, v: 0.0 })
        })
        .unwrap();
    scene.commit().unwrap();
    let mut rng = builtin::Pcg32::new(4, 9);
    let rays: Vec<Ray> = (0..10_000)
        .map(|i| {
            let o = Vec3::new(
                rng.range(-20.0, 120.0),
                rng.range(-20.0, 120.0),
                rng.range(-20.0, 120.0),
            );
            let d = if i % 2 == 0 {
                balls[rng.next_u32() as usize % balls.len()].0 - o
            } else {
                Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                )
            };
            Ray::new(o, d)
        })
        .collect();
    calls.store(0, Ordering::Relaxed);
    let hits = scene.intersect_batch(&rays);
    let closest_calls = calls.load(Ordering::Relaxed);
    let occ = scene.occluded_batch(&rays);
    let mut n_hit = 0;
    for (i, r) in rays.iter().enumerate() {
        // Analytic brute force: every sphere, nearest t, ties to the lower index.
        let bf = balls
            .iter()
            .enumerate()
            .filter_map(|(k, &(c, rad))| sphere_hit(r, c, rad).map(|t| (t, k as u32)))
            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let got = hits[i].map(|h| (h.t, h.prim));
        assert_eq!(got, bf, "ray {i}");
        if let Some(h) = hits[i] {
            assert_eq!((h.geom, h.instance), (g, Hit::NO_INSTANCE));
            n_hit += 1;
        }
        assert_eq!(occ[i], bf.is_some(), "ray {i}: occluded");
    }
    let brute_calls = (rays.len() * balls.len()) as u64;
    eprintln!(
        "{n_hit} of {} rays hit; callback calls {closest_calls} for closest hits, brute force {brute_calls}",
        rays.len()
    );
    assert!(n_hit > 3_000, "only {n_hit} rays hit");
    assert!(
        closest_calls * 100 < brute_calls,
        "the tree culls too little: {closest_calls} callback calls of {brute_calls}"
    );
}

#[test]
fn instanced_custom_spheres_follow_their_transforms() {
    // Spheres instanced under uniform scales and translations stay spheres: the brute force is
    // the analytic one over the world-space spheres.
    let balls = spheres(400, 6);
    let boxes: Vec<Aabb> = balls
        .iter()
        .map(|&(c, r)| Aabb::new(c - Vec3::splat(r), c + Vec3::splat(r)))
        .collect();
    let mut inner = Scene::new();
    let b2 = balls.clone();
    inner
        .add_custom(&boxes, move |ray, prim| {
            let (c, r) = b2[prim as usize];
            sphere_hit(ray, c, r).map(|t| CustomHit { t, u: 1.0, v: 2.0 })
        })
        .unwrap();
    inner.commit().unwrap();
    let inner = Arc::new(inner);
    let mut top = Scene::new();
    let mut world = Vec::new();
    let mut rng = builtin::Pcg32::new(6, 1);
    for k in 0..8u32 {
        let s = rng.range(0.5, 2.0);
        let t = Vec3::new(rng.range(-150.0, 150.0), rng.range(-150.0, 150.0), 0.0);
        let m = Affine3A::from_scale_rotation_translation(Vec3::splat(s), Quat::IDENTITY, t);
        let id = top.add_instance(inner.clone(), m).unwrap();
        assert_eq!(id, k);
        for (p, &(c, r)) in balls.iter().enumerate() {
            world.push((m.transform_point3(c), r * s, k, p as u32));
        }
    }
    top.commit().unwrap();
    let rays: Vec<Ray> = (0..4_000)
        .map(|i| {
            let o = Vec3::new(rng.range(-300.0, 300.0), rng.range(-300.0, 300.0), -50.0);
            let target = world[(i * 7919) % world.len()].0;
            Ray::new(o, target - o)
        })
        .collect();
    for (i, r) in rays.iter().enumerate() {
        let bf = world
            .iter()
            .filter_map(|&(c, rad, inst, p)| sphere_hit(r, c, rad).map(|t| (t, inst, p)))
            .min_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
        let got = top.intersect(r);
        match (bf, got) {
            (Some((t, inst, p)), Some(h)) => {
                assert!(close(r, t as f64, h.t as f64), "ray {i}: t {} vs {t}", h.t);
                if (h.instance, h.prim) != (inst, p) {
                    let (c, rad, _, _) =
                        world[(h.instance as usize) * balls.len() + h.prim as usize];
                    let t2 = sphere_hit(r, c, rad).expect("the reported sphere is hit");
                    assert!(close(r, t2 as f64, t as f64), "ray {i}: no near tie");
                }
                assert_eq!((h.u, h.v), (1.0, 2.0), "the callback's u, v come back");
            }
            (None, None) => {}
            (b, h) => panic!("ray {i}: scene {h:?} vs brute force {b:?}"),
        }
    }
}

#[test]
fn refit_of_a_mesh_in_a_scene_keeps_every_triangle_and_equals_brute_force() {
    let (v, ix) = normalise(mesh("sphere", 3000, 12));
    // Small spheres far from the mesh: a second geometry the rays below do not reach.
    let far = |c: Vec3| c * 0.02 + Vec3::splat(1000.0);
    let balls = spheres(50, 12);
    let boxes: Vec<Aabb> = balls
        .iter()
        .map(|&(c, r)| {
            Aabb::new(
                far(c) - Vec3::splat(r * 0.02),
                far(c) + Vec3::splat(r * 0.02),
            )
        })
        .collect();
    let mut scene = Scene::new();
    let g = scene
        .add_mesh(&v, &ix, &BuildOptions::preset(Preset::Quality))
        .unwrap();
    let b2 = balls.clone();
    scene
        .add_custom(&boxes, move |ray, prim| {
            let (c, r) = b2[prim as usize];
            sphere_hit(ray, far(c), r * 0.02).map(|t| CustomHit { t, u: 0.0, v: 0.0 })
        })
        .unwrap();
    scene.commit().unwrap();
    for frame in 1..4 {
        // A wave that moves every vertex (and the mesh's box).
        let moved: Vec<Vec3> = v
            .iter()
            .map(|p| {
                *p + Vec3::new(
                    0.3 * frame as f32,
                    0.2 * (p.x * 9.0 + frame as f32).sin(),
                    0.0,
                )
            })
            .collect();
        if frame == 2 {
            scene.rebuild_mesh(g, &moved).unwrap();
        } else {
            scene.refit_mesh(g, &moved).unwrap();
        }
        scene.commit().unwrap();
        let tris: Vec<[Vec3; 3]> = ix.iter().map(|t| t.map(|i| moved[i as usize])).collect();
        let mesh = scene.mesh(g).unwrap();
        mesh.wide_bvh()
            .validate(tris.len(), |i| tris[i as usize])
            .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
        let flat: Vec<Flat> = tris
            .iter()
            .enumerate()
            .map(|(p, t)| Flat {
                tri: *t,
                instance: Hit::NO_INSTANCE,
                geom: g,
                prim: p as u32,
                masks: (Ray::ALL, Ray::ALL),
            })
            .collect();
        let rays = rays_for(&flat, 4_000, frame, &[Ray::ALL]);
        let grazing = check(&scene, &flat, &rays, &format!("frame {frame}"));
        assert!(grazing <= 20, "frame {frame}: {grazing} grazing");
    }
}

#[test]
fn many_threads_tracing_one_scene_give_the_hits_of_one_thread() {
    fn send_sync<T: Send + Sync>() {}
    send_sync::<Scene>();
    send_sync::<emc_cpu::trace::Accel>();
    let (mut scene, flat) = instanced(20, 21, Preset::Quality);
    scene.commit().unwrap();
    let rays = rays_for(&flat, 20_000, 21, &[Ray::ALL, 0b010]);
    let one: Vec<Option<Hit>> = rays.iter().map(|r| scene.intersect(r)).collect();
    let scene = Arc::new(scene);
    let handles: Vec<_> = (0..4)
        .map(|k| {
            let (s, rays) = (scene.clone(), rays.clone());
            std::thread::spawn(move || {
                // Each thread walks the rays from a different start.
                let n = rays.len();
                (0..n)
                    .map(|i| (i + k * n / 4) % n)
                    .map(|i| (i, s.intersect(&rays[i])))
                    .collect::<Vec<_>>()
            })
        })
        .collect();
    for h in handles {
        for (i, hit) in h.join().unwrap() {
            assert_eq!(hit, one[i], "ray {i}");
        }
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    assert_eq!(pool.install(|| scene.intersect_batch(&rays)), one);
}

#[test]
fn bad_edits_are_refused_with_errors() {
    let (v, ix) = normalise(mesh("sphere", 200, 1));
    let opts = BuildOptions::preset(Preset::Fast);
    let mut inner = Scene::new();
    let g = inner.add_mesh(&v, &ix, &opts).unwrap();
    inner.commit().unwrap();
    let inner = Arc::new(inner);
    let mut top = Scene::new();
    let singular = Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0));
    assert!(matches!(
        top.add_instance(inner.clone(), singular),
        Err(TraceError::NotInvertible)
    ));
    let nan = Affine3A::from_translation(Vec3::new(f32::NAN, 0.0, 0.0));
    assert!(matches!(
        top.add_instance(inner.clone(), nan),
        Err(TraceError::NotInvertible)
    ));
    let huge = Affine3A::from_scale(Vec3::splat(1e38)) * Affine3A::from_scale(Vec3::splat(1e3));
    assert!(top.add_instance(inner.clone(), huge).is_err());
    assert!(matches!(
        top.add_instance(Arc::new(Scene::new()), Affine3A::IDENTITY),
        Err(TraceError::EmptyScene)
    ));
    let i = top.add_instance(inner.clone(), Affine3A::IDENTITY).unwrap();
    assert!(matches!(
        top.set_transform(i, singular),
        Err(TraceError::NotInvertible)
    ));
    assert_eq!(
        top.transform(i).unwrap(),
        Affine3A::IDENTITY,
        "a refused edit changes nothing"
    );
    top.commit().unwrap();
    let nested = Arc::new(top.clone());
    assert!(matches!(
        top.add_instance(nested, Affine3A::IDENTITY),
        Err(TraceError::NestedInstance)
    ));
    assert!(matches!(
        top.set_mask(99, 1),
        Err(TraceError::NoGeometry(99))
    ));
    assert!(matches!(
        top.refit_mesh(i, &v),
        Err(TraceError::WrongGeometry { .. })
    ));
    let mut own = Scene::new();
    let m = own.add_mesh(&v, &ix, &opts).unwrap();
    assert!(matches!(
        own.set_transform(m, Affine3A::IDENTITY),
        Err(TraceError::WrongGeometry { .. })
    ));
    assert!(matches!(
        own.refit_mesh(m, &v[..3]),
        Err(TraceError::VertexCount { .. })
    ));
    assert!(matches!(
        own.add_mesh(&v, &[], &opts),
        Err(TraceError::NoTriangles)
    ));
    let f = |_: &Ray, _: u32| None;
    assert!(matches!(
        own.add_custom(&[], f),
        Err(TraceError::NoTriangles)
    ));
    let bad = Aabb::new(Vec3::ONE, Vec3::ZERO);
    assert!(matches!(
        own.add_custom(&[Aabb::new(Vec3::ZERO, Vec3::ONE), bad], f),
        Err(TraceError::BadBox(1))
    ));
    let nanbox = Aabb::new(Vec3::ZERO, Vec3::new(f32::NAN, 1.0, 1.0));
    assert!(matches!(
        own.add_custom(&[nanbox], f),
        Err(TraceError::BadBox(0))
    ));
    let c = own
        .add_custom(&[Aabb::new(Vec3::ZERO, Vec3::ONE)], f)
        .unwrap();
    assert!(matches!(
        own.set_custom_boxes(c, &[]),
        Err(TraceError::BoxCount { .. })
    ));
    own.set_custom_boxes(c, &[Aabb::new(Vec3::ONE, Vec3::splat(2.0))])
        .unwrap();
    own.commit().unwrap();
    // Invalid rays miss, whatever the scene.
    let bad_ray = Ray::new(Vec3::ZERO, Vec3::ZERO);
    assert!(top.intersect(&bad_ray).is_none() && !top.occluded(&bad_ray));
    assert_eq!(inner.mask(g).unwrap(), Ray::ALL);
}

#[test]
fn instance_boxes_hold_their_geometry_and_are_tighter_than_the_turned_mesh_box() {
    // An instance's box is the union of the instanced scene's root child boxes transformed:
    // it must hold every transformed vertex (a mesh, a scene of two meshes, a small mesh far
    // from the origin), and for the mesh near the origin, whose root splits it, it is smaller
    // under rotations than the transformed box of the whole mesh in nine cases of ten (the
    // two-mesh scene's root children are the two overlapping meshes' boxes, and the far mesh
    // is tiny beside its rounding margin, so those are only checked to hold their vertices).
    let (v, ix) = normalise(mesh("mixed", 4000, 21));
    let (v2, ix2) = normalise(mesh("sphere", 800, 22));
    let mut one = Scene::new();
    one.add_mesh(&v, &ix, &BuildOptions::preset(Preset::Quality))
        .unwrap();
    one.commit().unwrap();
    let mut two = Scene::new();
    for (vv, ii) in [(&v, &ix), (&v2, &ix2)] {
        two.add_mesh(vv, ii, &BuildOptions::preset(Preset::Fast))
            .unwrap();
    }
    two.commit().unwrap();
    // A fast-preset mesh far from the origin (where the rounding margin, not the trees' own
    // padding, decides), alone in its scene.
    let far: Vec<Vec3> = v2
        .iter()
        .map(|p| *p * 0.01 + Vec3::new(3.0e5, -7.0e5, 1.1e6))
        .collect();
    let mut three = Scene::new();
    three
        .add_mesh(&far, &ix2, &BuildOptions::preset(Preset::Fast))
        .unwrap();
    three.commit().unwrap();
    let (one, two, three) = (Arc::new(one), Arc::new(two), Arc::new(three));
    let mut rng = builtin::Pcg32::new(23, 5);
    let (mut smaller, mut total) = (0, 0);
    for k in 0..40 {
        let m = transform(&mut rng, k);
        for (blas, verts, split) in [
            (&one, vec![&v], true),
            (&two, vec![&v, &v2], false),
            (&three, vec![&far], false),
        ] {
            let mut top = Scene::new();
            top.add_instance(blas.clone(), m).unwrap();
            top.commit().unwrap();
            let b = top.bounds();
            for p in verts.iter().flat_map(|vs| vs.iter()) {
                let w = m.transform_point3(*p);
                assert!(
                    b.min.cmple(w).all() && w.cmple(b.max).all(),
                    "transform {k}: vertex {w} outside the instance box {b:?}"
                );
            }
            // The mesh's own box, turned: its eight corners.
            let mb = blas.bounds();
            let mut loose = Aabb::EMPTY;
            for c in 0..8 {
                let p = Vec3::new(
                    if c & 1 == 0 { mb.min.x } else { mb.max.x },
                    if c & 2 == 0 { mb.min.y } else { mb.max.y },
                    if c & 4 == 0 { mb.min.z } else { mb.max.z },
                );
                loose.grow(m.transform_point3(p));
            }
            let area = |b: &Aabb| {
                let e = b.max - b.min;
                e.x * e.y + e.y * e.z + e.z * e.x
            };
            if split {
                total += 1;
                smaller += usize::from(area(&b) < area(&loose));
            }
        }
    }
    assert!(
        smaller * 10 >= total * 9,
        "only {smaller} of {total} instance boxes are tighter than the turned mesh box"
    );
}
