//! The hard-case catalogue (`builtin:hard-*`) through the whole pipeline: for every standard
//! layout and every builder, codes are monotone per axis, the BVH validates, bounds contain
//! their triangles exactly, both SAH figures are finite, and tracing equals brute force.

use emc_core::{Aabb, LayoutSpec};
use emc_cpu::build::{build_scene, encoder_for, BuildOutput, Builder, PipelineOptions};
use emc_cpu::scene::{self, builtin::HARD_NAMES, Mesh, SceneOptions};
use emc_cpu::trace::intersect::{brute_force_closest, brute_force_occluded, Ray};
use emc_cpu::trace::Accel;
use emc_tests::adversarial_rays;
use glam::Vec3;
use rayon::prelude::*;

fn load(name: &str, prims: Option<usize>) -> Mesh {
    scene::load_with(
        &format!("builtin:{name}"),
        &SceneOptions::default().with_prims(prims),
    )
    .unwrap_or_else(|e| panic!("builtin:{name}: {e}"))
}

fn triangles(s: &Mesh) -> Vec<[Vec3; 3]> {
    (0..s.triangle_count()).map(|i| s.triangle(i)).collect()
}

fn contains(b: &Aabb, v: Vec3) -> bool {
    b.min.cmple(v).all() && v.cmple(b.max).all()
}

/// Quantised x, y, z never decrease along the boxes sorted by centre on that axis (ties in the
/// centre key may take any order, so a whole group of equal keys is compared at once).
fn check_monotone(label: &str, aabbs: &[Aabb], layout: &LayoutSpec) {
    let enc = encoder_for(aabbs, layout).unwrap_or_else(|e| panic!("{label}: encoder: {e}"));
    let q: Vec<[u64; 4]> = aabbs
        .par_iter()
        .map(|b| enc.decode(enc.encode(b)))
        .collect();
    for axis in [0usize, 1, 2] {
        let key = |i: usize| aabbs[i].min[axis] as f64 + aabbs[i].max[axis] as f64;
        let mut order: Vec<usize> = (0..aabbs.len()).collect();
        order.par_sort_unstable_by(|&a, &b| key(a).total_cmp(&key(b)));
        let (mut before, mut group, mut group_key) = (0u64, 0u64, f64::NEG_INFINITY);
        for &i in &order {
            if key(i) != group_key {
                before = before.max(group);
                group_key = key(i);
            }
            assert!(
                q[i][axis] >= before,
                "{label}: axis {axis} not monotone at box {i} {:?}: {} after {}",
                aabbs[i],
                q[i][axis],
                before
            );
            group = group.max(q[i][axis]);
        }
    }
}

/// Validation, exact containment of every triangle vertex in its box and its leaf, finite SAH.
fn check_tree(label: &str, s: &Mesh, out: &BuildOutput) {
    out.bvh
        .validate(&out.aabbs)
        .unwrap_or_else(|e| panic!("{label}: invalid BVH: {e}"));
    for (i, b) in out.aabbs.iter().enumerate() {
        for v in s.triangle(i) {
            assert!(contains(b, v), "{label}: box {i} {b:?} misses vertex {v:?}");
        }
    }
    for n in out.bvh.nodes.iter().filter(|n| n.is_leaf()) {
        let ids = &out.bvh.prim_indices[n.first() as usize..(n.first() + n.count()) as usize];
        for &p in ids {
            for v in s.triangle(p as usize) {
                assert!(
                    contains(&n.bounds, v),
                    "{label}: leaf {:?} misses vertex {v:?} of triangle {p}",
                    n.bounds
                );
            }
        }
    }
    let r = &out.report;
    assert!(
        r.sah_headline.is_finite() && r.sah_collapsed.is_finite(),
        "{label}: SAH {} / {}",
        r.sah_headline,
        r.sah_collapsed
    );
}

/// Closest hit (t bits and id) and any hit equal brute force on every ray.
fn check_trace(
    label: &str,
    out: &BuildOutput,
    tris: &[[Vec3; 3]],
    rays: &[Ray],
    want: &[(Option<emc_cpu::trace::Hit>, bool)],
) {
    let accel = Accel::from_bvh2(&out.bvh, tris.to_vec())
        .unwrap_or_else(|e| panic!("{label}: conversion: {e}"));
    let bad: Vec<String> = rays
        .par_iter()
        .zip(want)
        .enumerate()
        .filter_map(|(i, (r, (want, want_occ)))| {
            let got = accel.intersect(r);
            let same = match (want, got) {
                (None, None) => true,
                (Some(a), Some(b)) => a.t.to_bits() == b.t.to_bits() && a.prim == b.prim,
                _ => false,
            };
            let occ = accel.occluded(r);
            (!same || occ != *want_occ)
                .then(|| format!("ray {i} {r:?}: want {want:?} got {got:?} occluded {occ}"))
        })
        .collect();
    assert!(
        bad.is_empty(),
        "{label}: {} of {} rays disagree with brute force, first: {}",
        bad.len(),
        rays.len(),
        bad[0]
    );
}

fn opts(builder: Builder, layout: LayoutSpec) -> PipelineOptions {
    PipelineOptions::default()
        .with_builder(builder)
        .with_layout(layout)
        .with_threads(2)
}

/// Every (builder, layout) pair: the three LBVH builders on each standard layout, binned SAH
/// once (it reads no codes).
fn configurations() -> Vec<(Builder, LayoutSpec)> {
    let mut v = vec![(Builder::BinnedSah, LayoutSpec::Emc64Var)];
    for l in LayoutSpec::STANDARD {
        for b in [Builder::Lbvh, Builder::LbvhApetrei, Builder::Atrbvh] {
            v.push((b, l));
        }
    }
    v
}

/// The whole check on one scene: monotone codes per layout, then every configuration's tree
/// and traversal against brute force on `nrays` rays.
fn check_scene(name: &str, prims: Option<usize>, configs: &[(Builder, LayoutSpec)], nrays: usize) {
    let s = load(name, prims);
    let tris = triangles(&s);
    let aabbs = s.aabbs();
    for l in LayoutSpec::STANDARD {
        check_monotone(&format!("builtin:{name} {l}"), &aabbs, &l);
    }
    let rays = adversarial_rays(&tris, nrays, 0x5eed ^ name.len() as u64);
    let want: Vec<_> = rays
        .par_iter()
        .map(|r| {
            (
                brute_force_closest(r, &tris),
                brute_force_occluded(r, &tris),
            )
        })
        .collect();
    let hits = want.iter().filter(|w| w.0.is_some()).count();
    for &(b, l) in configs {
        let label = format!("builtin:{name} ({} triangles) {b}/{l}", tris.len());
        let out = build_scene(&s, &opts(b, l)).unwrap_or_else(|e| panic!("{label}: {e}"));
        check_tree(&label, &s, &out);
        check_trace(&label, &out, &tris, &rays, &want);
    }
    eprintln!(
        "builtin:{name}: {} triangles, {} configurations, {hits} of {} rays hit",
        tris.len(),
        configs.len(),
        rays.len()
    );
}

#[test]
fn every_hard_case_small_through_every_layout_and_builder() {
    for name in HARD_NAMES {
        check_scene(name, Some(3000), &configurations(), 600);
    }
}

/// The configurations of the full-size scenes (millions of triangles): the one-pass LBVH on
/// a 64-bit and a 30-bit layout, and binned SAH; codes are still checked on every layout.
fn big_configurations() -> Vec<(Builder, LayoutSpec)> {
    vec![
        (Builder::LbvhApetrei, LayoutSpec::Emc64Var),
        (Builder::LbvhApetrei, LayoutSpec::Morton30),
        (Builder::BinnedSah, LayoutSpec::Emc64Var),
    ]
}

#[test]
fn one_big_among_a_million_tiny() {
    // The catalogue's full size: 10^6 tiny triangles + 1 covering everything.
    check_scene("hard-one-big", None, &big_configurations(), 32);
}

#[test]
fn two_to_the_21_plus_one_in_one_cell() {
    // The catalogue's full size: 2^21 + 1 triangles inside one cell finer than any code.
    check_scene("hard-same-cell", None, &big_configurations(), 32);
}
