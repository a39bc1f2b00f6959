//! Tests of the library face of the tracer, `Accel`, for every preset and both tree widths:
//! closest and any hit equal brute force on every built-in scene (the hard cases included)
//! and on the shared scenes of at most a million triangles, every tree passes the wide-tree
//! validator, `rebuild` after moving the vertices equals a fresh build of the moved mesh, a
//! shared `BuildContext` changes no tree whatever it built before, and bad input is refused
//! with an error.

use emc_cpu::scene::{self, builtin, Mesh, SceneOptions};
use emc_cpu::trace::intersect::{brute_force_closest, brute_force_occluded};
use emc_cpu::trace::traverse::brute_force_packets_many;
use emc_cpu::trace::wide::TriPacket;
use emc_cpu::trace::{Accel, BuildContext, BuildOptions, Hit, Preset, Ray, TraceError};
use emc_tests::adversarial_rays;
use glam::Vec3;
use rayon::prelude::*;

const PRESETS: [Preset; 3] = [Preset::Fast, Preset::Balanced, Preset::Quality];

fn triangles(s: &Mesh) -> Vec<[Vec3; 3]> {
    (0..s.triangle_count()).map(|i| s.triangle(i)).collect()
}

/// `n` rays: half aimed from random origins at random points inside random triangles, half
/// the adversarial set of `emc_tests` (edges, vertices, axis-parallel, grazing, zero
/// components, origins on triangles).
fn rays_for(tris: &[[Vec3; 3]], n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = builtin::Pcg32::new(seed, 3);
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for t in tris {
        for v in t {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
    }
    let pad = (hi - lo) * 0.2 + Vec3::splat(1e-3);
    let mut out = Vec::with_capacity(n);
    for _ in 0..n / 2 {
        let o = Vec3::new(
            rng.range(lo.x - pad.x, hi.x + pad.x),
            rng.range(lo.y - pad.y, hi.y + pad.y),
            rng.range(lo.z - pad.z, hi.z + pad.z),
        );
        let t = tris[rng.next_u32() as usize % tris.len()];
        let (u, v) = (rng.f32(), rng.f32());
        let (u, v) = if u + v > 1.0 {
            (1.0 - u, 1.0 - v)
        } else {
            (u, v)
        };
        let p = t[0] + (t[1] - t[0]) * u + (t[2] - t[0]) * v;
        let d = p - o;
        out.push(Ray::new(o, if d == Vec3::ZERO { Vec3::Z } else { d }));
    }
    out.extend(adversarial_rays(tris, n - n / 2, seed ^ 0x5eed));
    out
}

/// Brute-force answers: closest hit and any hit, by the scalar test per triangle; over
/// 100,000 triangles by the packet test over every triangle, the packets read in cache-sized
/// tiles for groups of rays (`brute_force_packets_many`: equal and far faster; compared with
/// the scalar test on every 97th ray).
fn brute_force(tris: &[[Vec3; 3]], rays: &[Ray]) -> Vec<(Option<Hit>, bool)> {
    if tris.len() < 100_000 {
        return rays
            .par_iter()
            .map(|r| (brute_force_closest(r, tris), brute_force_occluded(r, tris)))
            .collect();
    }
    let packets = TriPacket::of_triangles(tris);
    let hits: Vec<Option<Hit>> = rays
        .par_chunks(256)
        .flat_map_iter(|c| brute_force_packets_many(c, &packets))
        .collect();
    rays.par_iter().zip(&hits).step_by(97).for_each(|(r, b)| {
        let a = brute_force_closest(r, tris);
        assert_eq!(
            a.map(|h| (h.t.to_bits(), h.prim)),
            b.map(|h| (h.t.to_bits(), h.prim)),
            "{r:?}"
        );
    });
    hits.into_iter().map(|h| (h, h.is_some())).collect()
}

/// The tiled brute force equals one ray's pass at a time, ray by ray: over several tiles of
/// packets and a last partial one, a last partial group of rays, and rays it must refuse
/// (non-finite, zero direction, `tnear > tfar`), which hit nothing.
#[test]
fn tiled_brute_force_equals_one_ray_at_a_time() {
    let s = scene::load_with("builtin:mixed", &SceneOptions::default().with_prims(5000)).unwrap();
    let tris = triangles(&s);
    let packets = TriPacket::of_triangles(&tris);
    assert!(
        packets.len() > 2 * 512,
        "{} packets: several tiles",
        packets.len()
    );
    assert!(!packets.len().is_multiple_of(512), "a last partial tile");
    let mut rays = rays_for(&tris, 1000, 29);
    // Segments: rays that hit, cut to end before their hit or to start after it.
    let mut cut = 0;
    for i in 0..400 {
        let r = rays[i];
        if let Some(h) = emc_cpu::trace::traverse::brute_force_packets(&r, &packets) {
            let mut short = r;
            (short.tnear, short.tfar) = (h.t * 0.25, h.t * 0.5);
            let mut beyond = r;
            beyond.tnear = h.t * 1.001;
            rays.extend([short, beyond]);
            cut += 1;
        }
    }
    assert!(cut > 50, "{cut} segments");
    rays.push(Ray::new(Vec3::ZERO, Vec3::ZERO));
    rays.push(Ray::new(Vec3::NAN, Vec3::X));
    let mut back = rays[0];
    back.tnear = 2.0;
    back.tfar = 1.0;
    rays.push(back);
    rays.push(rays[1]);
    let many = brute_force_packets_many(&rays, &packets);
    assert_eq!(many.len(), rays.len());
    let mut hits = 0;
    for (i, (r, m)) in rays.iter().zip(&many).enumerate() {
        let one = emc_cpu::trace::traverse::brute_force_packets(r, &packets);
        let key =
            |h: &Option<Hit>| h.map(|h| (h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits()));
        assert_eq!(key(m), key(&one), "ray {i} {r:?}");
        hits += m.is_some() as usize;
    }
    assert!(hits > 300, "{hits} of {} rays hit", rays.len());
    // Some segments miss what their whole ray hits (the interval is honoured).
    let n = rays.len();
    let segment_misses = many[1000..n - 4].iter().filter(|h| h.is_none()).count();
    assert!(segment_misses > 20, "{segment_misses} segments miss");
    assert!(many[rays.len() - 4..rays.len() - 1]
        .iter()
        .all(Option::is_none));
}

/// `a` answers every ray as brute force does: closest `t` bits and triangle id, any hit.
fn check(name: &str, a: &Accel, rays: &[Ray], want: &[(Option<Hit>, bool)]) {
    let bad: Vec<String> = rays
        .par_iter()
        .zip(want)
        .enumerate()
        .filter_map(|(i, (r, &(w, wo)))| {
            let got = a.intersect(r);
            let same = match (w, got) {
                (None, None) => true,
                (Some(x), Some(y)) => x.t.to_bits() == y.t.to_bits() && x.prim == y.prim,
                _ => false,
            };
            let occ = a.occluded(r);
            (!same || occ != wo)
                .then(|| format!("ray {i} {r:?}: want {w:?}/{wo}, got {got:?}/{occ}"))
        })
        .collect();
    assert!(
        bad.is_empty(),
        "{name}: {} of {} rays differ from brute force; first: {}",
        bad.len(),
        rays.len(),
        bad[0]
    );
}

fn build(s: &Mesh, preset: Preset, width: usize) -> Accel {
    let opts = BuildOptions::preset(preset).with_width(width);
    let a = Accel::build(&s.vertices, &s.indices, &opts)
        .unwrap_or_else(|e| panic!("{preset:?}/{width} builds: {e}"));
    a.wide_bvh()
        .validate(a.triangle_count(), |i| a.triangle(i))
        .unwrap_or_else(|e| panic!("{preset:?}/{width}: invalid tree: {e}"));
    a
}

fn check_scene(label: &str, s: &Mesh, rays: usize) {
    let tris = triangles(s);
    let rays = rays_for(&tris, rays, 17);
    let want = brute_force(&tris, &rays);
    for preset in PRESETS {
        for width in [4, 8] {
            let a = build(s, preset, width);
            assert_eq!(a.wide_bvh().width(), width);
            check(
                &format!("{label} {preset:?}/{width}-wide"),
                &a,
                &rays,
                &want,
            );
        }
    }
}

#[test]
fn every_preset_equals_brute_force_on_builtin_scenes() {
    for name in builtin::NAMES {
        let s = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(4000),
        )
        .unwrap();
        check_scene(&format!("builtin:{name}"), &s, 10_000);
    }
}

/// The fast preset with a leaf size of 1 (a scene's top-level tree) gives every triangle a
/// leaf of its own, at both widths, and traces like brute force.
#[test]
fn fast_builds_of_one_triangle_per_leaf() {
    for name in ["city", "sphere"] {
        let s = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(3000),
        )
        .unwrap();
        let tris = triangles(&s);
        let rays = rays_for(&tris, 4000, 23);
        let want = brute_force(&tris, &rays);
        for width in [4, 8] {
            let opts = BuildOptions::preset(Preset::Fast)
                .with_width(width)
                .with_leaf_size(1);
            let a = Accel::build(&s.vertices, &s.indices, &opts).unwrap();
            let w = a.wide_bvh();
            w.validate(a.triangle_count(), |i| a.triangle(i)).unwrap();
            assert_eq!(
                w.leaves,
                tris.len(),
                "{name}/{width}: one leaf per triangle"
            );
            assert!(w.packets.iter().all(|p| p.count == 1 && p.last == 1));
            check(&format!("{name} fast/leaf1/{width}-wide"), &a, &rays, &want);
            // The default keeps leaves of several triangles.
            let d =
                Accel::build(&s.vertices, &s.indices, &BuildOptions::preset(Preset::Fast)).unwrap();
            assert!(
                d.wide_bvh().leaves < tris.len() / 2,
                "{name}: default leaves"
            );
        }
    }
}

#[test]
fn every_preset_equals_brute_force_on_hard_scenes() {
    let mut tested = 0;
    for name in builtin::HARD_NAMES {
        let Ok(s) = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(2000),
        ) else {
            // builtin:hard-nonfinite is refused at load time (its own test covers it).
            continue;
        };
        check_scene(&format!("builtin:{name}"), &s, 10_000);
        tested += 1;
    }
    assert!(
        tested >= builtin::HARD_NAMES.len() - 1,
        "{tested} hard scenes loaded"
    );
}

#[test]
fn every_preset_equals_brute_force_on_shared_scenes() {
    if scene::shared_scenes_dir().is_none() {
        eprintln!("skipping: no shared scenes directory (../shared/scenes or $EMC_SHARED_DIR)");
        return;
    }
    for name in ["sionna-san-francisco", "pbrt-bathroom", "stanford-dragon"] {
        if scene::shared_scene_path(name).is_none() {
            eprintln!("skipping {name}: not present");
            continue;
        }
        let s = scene::load(name).unwrap();
        assert!(s.triangle_count() <= 1_000_000);
        let t0 = std::time::Instant::now();
        check_scene(name, &s, 10_000);
        eprintln!("{name}: {:.1} s", t0.elapsed().as_secs_f64());
    }
}

/// A deterministic deformation of every vertex (a travelling wave along each axis).
fn moved(v: &[Vec3], phase: f32) -> Vec<Vec3> {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for p in v {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let e = (hi - lo).max_element().max(1e-6);
    v.iter()
        .map(|p| {
            let q = (*p - lo) / e;
            *p + Vec3::new(
                (q.y * 7.0 + phase).sin(),
                (q.z * 5.0 + phase).cos(),
                (q.x * 3.0 - phase).sin(),
            ) * (0.05 * e)
        })
        .collect()
}

#[test]
fn rebuild_equals_a_fresh_build_of_the_moved_mesh() {
    for name in ["mixed", "city"] {
        let s = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(5000),
        )
        .unwrap();
        for (preset, width) in PRESETS.into_iter().flat_map(|p| [(p, 8), (p, 4)]) {
            let mut a = build(&s, preset, width);
            // Over the same vertices first: the fast preset's sort then takes the previous
            // order whole (its hint serves), and the tree must still be the fresh build's.
            let first = a.wide_bvh().clone();
            a.rebuild(&s.vertices).unwrap();
            let x = a.wide_bvh();
            assert!(
                x.nodes8 == first.nodes8 && x.nodes == first.nodes && x.packets == first.packets,
                "{name} {preset:?} width {width}: a rebuild over the same vertices differs"
            );
            // A few vertices pulled towards the middle (the others keep the bounds, so most codes
            // stay and the fast preset's sort merges the changed ones into the previous order).
            let mid = s.vertices.iter().fold(Vec3::ZERO, |a, &v| a + v) / s.vertices.len() as f32;
            let mut v = s.vertices.clone();
            for p in v.iter_mut().step_by(97) {
                *p = p.lerp(mid, 0.3);
            }
            a.rebuild(&v).unwrap();
            let fresh = build(
                &Mesh {
                    vertices: v,
                    ..s.clone()
                },
                preset,
                width,
            );
            let (x, y) = (a.wide_bvh(), fresh.wide_bvh());
            assert!(
                x.nodes8 == y.nodes8 && x.nodes == y.nodes && x.packets == y.packets,
                "{name} {preset:?} width {width}: a rebuild with a few vertices moved differs"
            );
            for frame in 1..=3 {
                let v = moved(&s.vertices, frame as f32);
                a.rebuild(&v).unwrap();
                let fresh_scene = Mesh {
                    vertices: v.clone(),
                    ..s.clone()
                };
                let fresh = build(&fresh_scene, preset, width);
                let (x, y) = (a.wide_bvh(), fresh.wide_bvh());
                assert!(
                    x.nodes8 == y.nodes8 && x.nodes == y.nodes && x.packets == y.packets,
                    "{name} {preset:?} width {width} frame {frame}: rebuild differs from a \
                     fresh build"
                );
                a.wide_bvh()
                    .validate(a.triangle_count(), |i| a.triangle(i))
                    .unwrap();
                let tris = triangles(&fresh_scene);
                let rays = rays_for(&tris, 2000, frame);
                check(
                    &format!("{name} {preset:?} width {width} frame {frame}"),
                    &a,
                    &rays,
                    &brute_force(&tris, &rays),
                );
            }
        }
    }
}

#[test]
fn rebuild_refuses_bad_vertices_and_keeps_the_tree() {
    let s = scene::load_with("builtin:sphere", &SceneOptions::default().with_prims(500)).unwrap();
    for preset in PRESETS {
        let mut a = build(&s, preset, 8);
        let before = a.wide_bvh().clone();
        match a.rebuild(&s.vertices[1..]) {
            Err(TraceError::VertexCount { given, expected }) => {
                assert_eq!((given, expected), (s.vertices.len() - 1, s.vertices.len()))
            }
            other => panic!("{preset:?}: a short vertex list gave {other:?}"),
        }
        let mut nan = s.vertices.clone();
        nan[3].y = f32::NAN;
        let r = a.rebuild(&nan);
        assert!(
            matches!(r, Err(TraceError::NonFinite(_))),
            "{preset:?}: {r:?}"
        );
        assert!(a.wide_bvh().nodes8 == before.nodes8 && a.wide_bvh().packets == before.packets);
        let tris = triangles(&s);
        let rays = rays_for(&tris, 500, 5);
        check(
            &format!("{preset:?} after refusals"),
            &a,
            &rays,
            &brute_force(&tris, &rays),
        );
    }
}

/// Refit: to the unmoved mesh it gives the build's tree bit for bit (every box is the union of
/// its triangles' boxes, padded alike); to moved meshes, frame after frame, a valid tree that
/// answers every ray as brute force does, on both widths and every preset, on one and three
/// threads alike.
#[test]
fn refit_keeps_the_topology_and_follows_the_moved_mesh() {
    for name in ["mixed", "city"] {
        let s = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(5000),
        )
        .unwrap();
        for preset in PRESETS {
            for width in [4, 8] {
                let label = format!("{name} {preset:?} width {width}");
                let mut a = build(&s, preset, width);
                let before = a.wide_bvh().clone();
                a.refit(&s.vertices).unwrap();
                let x = a.wide_bvh();
                assert!(
                    x.nodes == before.nodes
                        && x.nodes8 == before.nodes8
                        && x.packets == before.packets
                        && x.max_abs == before.max_abs,
                    "{label}: refit to the same vertices changed the tree"
                );
                for frame in 1..=3 {
                    let v = moved(&s.vertices, frame as f32);
                    a.refit(&v).unwrap();
                    let three = rayon::ThreadPoolBuilder::new()
                        .num_threads(3)
                        .build()
                        .unwrap();
                    let mut b = build(&s, preset, width);
                    three.install(|| b.refit(&v)).unwrap();
                    assert!(
                        a.wide_bvh().nodes == b.wide_bvh().nodes
                            && a.wide_bvh().nodes8 == b.wide_bvh().nodes8,
                        "{label} frame {frame}: the refit depends on the thread count"
                    );
                    // Same topology: the child codes never change.
                    let codes = |w: &emc_cpu::trace::WideBvh| {
                        (
                            w.nodes.iter().map(|n| n.child).collect::<Vec<_>>(),
                            w.nodes8.iter().map(|n| n.child).collect::<Vec<_>>(),
                        )
                    };
                    assert_eq!(codes(a.wide_bvh()), codes(&before), "{label}");
                    a.wide_bvh()
                        .validate(a.triangle_count(), |i| a.triangle(i))
                        .unwrap_or_else(|e| panic!("{label} frame {frame}: {e}"));
                    let moved_scene = Mesh {
                        vertices: v.clone(),
                        ..s.clone()
                    };
                    let tris = triangles(&moved_scene);
                    let rays = rays_for(&tris, 2000, 40 + frame);
                    check(
                        &format!("{label} refit frame {frame}"),
                        &a,
                        &rays,
                        &brute_force(&tris, &rays),
                    );
                }
            }
        }
    }
}

#[test]
fn refit_refuses_bad_vertices_and_keeps_the_tree() {
    let s = scene::load_with("builtin:sphere", &SceneOptions::default().with_prims(500)).unwrap();
    for preset in PRESETS {
        let mut a = build(&s, preset, 8);
        let before = a.wide_bvh().clone();
        assert!(matches!(
            a.refit(&s.vertices[1..]),
            Err(TraceError::VertexCount { .. })
        ));
        let mut inf = s.vertices.clone();
        inf[7].z = f32::INFINITY;
        let r = a.refit(&inf);
        assert!(
            matches!(r, Err(TraceError::NonFinite(_))),
            "{preset:?}: {r:?}"
        );
        assert!(a.wide_bvh().nodes8 == before.nodes8 && a.wide_bvh().packets == before.packets);
    }
}

#[test]
fn bad_meshes_and_options_are_refused() {
    let v = [Vec3::ZERO, Vec3::X, Vec3::Y];
    for preset in PRESETS {
        let o = BuildOptions::preset(preset);
        assert!(matches!(
            Accel::build(&v, &[[0, 1, 3]], &o),
            Err(TraceError::BadIndex {
                tri: 0,
                index: 3,
                vertices: 3
            })
        ));
        assert!(matches!(
            Accel::build(&v, &[], &o),
            Err(TraceError::NoTriangles)
        ));
        let inf = [Vec3::ZERO, Vec3::X, Vec3::new(0.0, f32::INFINITY, 0.0)];
        assert!(matches!(
            Accel::build(&inf, &[[0, 1, 2]], &o),
            Err(TraceError::NonFinite(0))
        ));
        // Every non-finite kind, on any axis, in the second triangle; one not used is fine.
        for bad in [f32::NAN, f32::NEG_INFINITY, -f32::NAN] {
            for axis in 0..3 {
                let mut p = Vec3::new(0.5, 0.5, 0.5);
                p[axis] = bad;
                let m = [Vec3::ZERO, Vec3::X, Vec3::Y, p, Vec3::splat(f32::MAX)];
                assert!(matches!(
                    Accel::build(&m, &[[0, 1, 2], [0, 3, 1]], &o),
                    Err(TraceError::NonFinite(1))
                ));
                assert!(Accel::build(&m, &[[0, 1, 2], [0, 4, 1]], &o).is_ok());
            }
        }
        assert!(matches!(
            Accel::build(&v, &[[0, 1, 2], [u32::MAX, 1, 2]], &o),
            Err(TraceError::BadIndex {
                tri: 1,
                index: u32::MAX,
                vertices: 3
            })
        ));
        let w = o.with_width(6);
        assert!(matches!(
            Accel::build(&v, &[[0, 1, 2]], &w),
            Err(TraceError::Width(6))
        ));
    }
    // Every preset: a leaf size of 0 is refused (the fast preset builds on its own path only
    // at leaf sizes 1 and 4).
    for preset in [Preset::Fast, Preset::Balanced, Preset::Quality] {
        let l = BuildOptions::preset(preset).with_leaf_size(0);
        assert!(matches!(
            Accel::build(&v, &[[0, 1, 2]], &l),
            Err(TraceError::ZeroLeafSize)
        ));
    }
}

/// The same nodes and packets.
fn same_tree(x: &Accel, y: &Accel) -> bool {
    let (x, y) = (x.wide_bvh(), y.wide_bvh());
    x.nodes == y.nodes && x.nodes8 == y.nodes8 && x.packets == y.packets
}

#[test]
fn a_shared_context_changes_no_tree() {
    // Meshes of different sizes in turn (a smaller after a larger, every preset after every
    // other), structures dropped and kept, so the context's scratch and the buffers it takes
    // back from dropped structures hold another build's leftovers each time.
    let meshes: Vec<Mesh> = [
        ("mixed", 20_000),
        ("city", 3000),
        ("hair", 9000),
        ("sphere", 500),
    ]
    .iter()
    .map(|&(name, prims)| {
        scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(prims),
        )
        .unwrap()
    })
    .collect();
    let mut ctx = BuildContext::new();
    let mut kept = Vec::new();
    for round in 0..2 {
        for (m, s) in meshes.iter().enumerate() {
            for preset in PRESETS {
                for width in [8, 4] {
                    let opts = BuildOptions::preset(preset).with_width(width);
                    let a = Accel::build_in(&mut ctx, &s.vertices, &s.indices, &opts).unwrap();
                    let fresh = build(s, preset, width);
                    assert!(
                        same_tree(&a, &fresh),
                        "round {round}, mesh {m}, {preset:?}/{width}: the context changed the tree"
                    );
                    assert_eq!(a.triangle(0), fresh.triangle(0));
                    // Every other structure is kept for a while, the rest dropped at once.
                    if (m + width) % 3 == 0 {
                        kept.push(a);
                    }
                }
            }
            if kept.len() > 4 {
                kept.drain(..2);
            }
        }
    }
    // A rebuild in the shared context equals a fresh build of the moved mesh.
    let s = &meshes[1];
    for preset in PRESETS {
        let opts = BuildOptions::preset(preset);
        let mut a = Accel::build_in(&mut ctx, &s.vertices, &s.indices, &opts).unwrap();
        let v = moved(&s.vertices, 2.0);
        a.rebuild_in(&mut ctx, &v).unwrap();
        let fresh_scene = Mesh {
            vertices: v,
            ..s.clone()
        };
        assert!(
            same_tree(&a, &build(&fresh_scene, preset, 8)),
            "{preset:?}: rebuild_in differs from a fresh build"
        );
        // A plain rebuild of a structure built in a context works from its own buffers.
        a.rebuild(&s.vertices).unwrap();
        assert!(
            same_tree(&a, &build(s, preset, 8)),
            "{preset:?}: plain rebuild"
        );
    }
}

/// `opts`' build of `s` at each of `threads` equals its one-thread build, node for node and
/// packet for packet (`what` names the case in a failure).
fn assert_same_at_thread_counts(s: &Mesh, opts: &BuildOptions, threads: &[usize], what: &str) {
    let at = |threads| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| Accel::build(&s.vertices, &s.indices, opts))
            .unwrap()
    };
    let one = at(1);
    for &threads in threads {
        let other = at(threads);
        let (x, y) = (one.wide_bvh(), other.wide_bvh());
        assert!(
            x.nodes == y.nodes && x.nodes8 == y.nodes8 && x.packets == y.packets,
            "{what}: {threads} threads build another tree than one"
        );
    }
}

#[test]
fn builds_are_identical_at_any_thread_count() {
    // Large enough for many blocks (the parallel block phase) on every preset.
    let s = scene::load_with(
        "builtin:mixed",
        &SceneOptions::default().with_prims(120_000),
    )
    .unwrap();
    for preset in PRESETS {
        for width in [4, 8] {
            let opts = BuildOptions::preset(preset).with_width(width);
            assert_same_at_thread_counts(&s, &opts, &[2, 3], &format!("{preset:?}/{width}"));
        }
    }
}

#[test]
fn large_fast_builds_are_identical_at_any_thread_count() {
    // Past the size where the top partition splits its halves as parallel tasks (2^17
    // primitives) at several levels, and with many block groups for the workers to claim.
    let s = scene::load_with(
        "builtin:mixed",
        &SceneOptions::default().with_prims(600_000),
    )
    .unwrap();
    let opts = BuildOptions::preset(Preset::Fast);
    assert_same_at_thread_counts(&s, &opts, &[2, 3, 5], "fast, 600k triangles");
}

#[test]
fn both_copies_of_the_fast_block_builders_build_the_same_tree() {
    use emc_cpu::trace::wide_lbvh::{force_baseline_tree, tree_isa};
    let (isa, why) = tree_isa();
    if isa == "baseline" {
        eprintln!("skipped: the fast build has no second copy to compare on this CPU ({why})");
        return;
    }
    let mut meshes: Vec<(String, Mesh)> = Vec::new();
    for name in builtin::NAMES.iter().chain(builtin::HARD_NAMES.iter()) {
        let spec = format!("builtin:{name}");
        if let Ok(s) = scene::load_with(&spec, &SceneOptions::default().with_prims(20_000)) {
            meshes.push((spec, s));
        }
    }
    assert!(meshes.len() >= builtin::NAMES.len() + builtin::HARD_NAMES.len() - 1);
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    for (spec, s) in &meshes {
        for width in [8, 4] {
            for threads in [1, 2] {
                let run = || build(s, Preset::Fast, width);
                let (v3, base) = if threads == 1 {
                    let v3 = run();
                    force_baseline_tree(true);
                    let base = run();
                    force_baseline_tree(false);
                    (v3, base)
                } else {
                    let v3 = two.install(run);
                    force_baseline_tree(true);
                    let base = two.install(run);
                    force_baseline_tree(false);
                    (v3, base)
                };
                assert!(
                    same_tree(&v3, &base),
                    "{spec} width {width}, {threads} thread(s): the {isa} copy built another tree"
                );
            }
        }
    }
}

#[test]
fn every_preset_builds_large_hard_scenes() {
    // At 20,000 triangles the huge-coordinate scenes overflow box areas to +inf in the wide
    // cover DP of the fast build's top (a split of zero slots once made it panic).
    for name in builtin::HARD_NAMES {
        let spec = format!("builtin:{name}");
        let Ok(s) = scene::load_with(&spec, &SceneOptions::default().with_prims(20_000)) else {
            continue;
        };
        // Few rays: where the boxes all overlap (a point, one cell, 1 mm at 10^7, subnormal
        // coordinates) a ray tests all 20,000 triangles, milliseconds a ray; the
        // 2,000-triangle scenes above take 10,000 rays each.
        check_scene(&format!("{spec} (20k)"), &s, 250);
    }
}

/// The building blocks under `Accel` refuse inputs that do not fit with errors: the fast
/// builder a leaf size it does not make, a refit plan a mesh without the tree's triangles, a
/// refit too few vertices or a plan made for another tree.
#[test]
fn fast_build_and_refit_refuse_mismatched_inputs() {
    use emc_cpu::trace::refit::RefitPlan;
    use emc_cpu::trace::wide_lbvh::{build_fast, FastScratch, FastTimes};
    let s = scene::load_with("builtin:sphere", &SceneOptions::default().with_prims(500)).unwrap();
    let layout: emc_cpu::auto::LayoutChoice =
        "emc32-var".parse::<emc_core::LayoutSpec>().unwrap().into();
    for leaf in [0, 9] {
        let r = build_fast::<8>(
            &s.vertices,
            &s.indices,
            &layout,
            leaf,
            0,
            &mut FastScratch::default(),
            &mut Vec::new(),
            &mut Vec::new(),
            &mut FastTimes::default(),
        );
        assert!(
            matches!(r, Err(TraceError::FastLeafSize { given, max: 8 }) if given == leaf),
            "leaf size {leaf}: {r:?}"
        );
    }
    let a = Accel::build(&s.vertices, &s.indices, &BuildOptions::preset(Preset::Fast)).unwrap();
    let mut bvh = a.wide_bvh().clone();
    let n = s.indices.len();
    assert!(matches!(
        RefitPlan::new(&bvh, &s.indices[..n / 2]),
        Err(TraceError::MissingTriangle { triangles, .. }) if triangles == n / 2
    ));
    let mut plan = RefitPlan::new(&bvh, &s.indices).unwrap();
    let few = &s.vertices[..s.vertices.len() / 2];
    assert!(matches!(
        bvh.refit(&mut plan, few, 1.0),
        Err(TraceError::BadIndex { vertices, .. }) if vertices == few.len()
    ));
    let other = Accel::build(
        &s.vertices,
        &s.indices,
        &BuildOptions::preset(Preset::Quality),
    )
    .unwrap();
    let mut other_plan = RefitPlan::new(other.wide_bvh(), &s.indices).unwrap();
    assert!(matches!(
        bvh.refit(&mut other_plan, &s.vertices, 1.0),
        Err(TraceError::RefitPlanMismatch)
    ));
    // The matching plan and vertices refit the tree to itself.
    let max_abs = s
        .vertices
        .iter()
        .map(|v| v.abs().max_element())
        .fold(0.0f32, f32::max);
    bvh.refit(&mut plan, &s.vertices, max_abs).unwrap();
    assert!(bvh.nodes8 == a.wide_bvh().nodes8 && bvh.packets == a.wide_bvh().packets);
}

#[test]
fn the_balanced_collapse_planned_during_restructuring_equals_one_planned_after() {
    // The balanced build plans the wide collapse inside the treelet restructuring's last
    // pass, node by node; planning the finished BVH2 afterwards (the library's collapse of
    // any BVH2) must give the same wide tree, node for node, at both widths and any thread
    // count.
    use emc_cpu::trace::api::build_bvh2;
    use emc_cpu::trace::WideBvh;
    for (spec, prims) in [
        ("builtin:mixed", 60_000),
        ("builtin:hard-needles", 5_000),
        ("builtin:hard-huge", 5_000),
        ("builtin:hard-duplicates", 5_000),
    ] {
        let s = scene::load_with(spec, &SceneOptions::default().with_prims(prims)).unwrap();
        let tris = triangles(&s);
        for width in [4, 8] {
            let opts = BuildOptions::preset(Preset::Balanced).with_width(width);
            let bvh2 = build_bvh2(&tris, &opts).unwrap();
            let after = WideBvh::from_bvh2_width(&bvh2, &tris, width).unwrap();
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let a = pool
                    .install(|| Accel::from_triangles(tris.clone(), &opts))
                    .unwrap();
                let during = a.wide_bvh();
                assert!(
                    during.nodes == after.nodes
                        && during.nodes8 == after.nodes8
                        && during.packets == after.packets,
                    "{spec} {width}-wide, {threads} threads: another tree"
                );
            }
        }
    }
}
