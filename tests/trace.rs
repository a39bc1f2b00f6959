//! Tests of the tracer (`emc_cpu::trace`): BVH traversal against brute force on built-in and
//! shared scenes for every builder, SIMD node tests against the scalar reference, watertight
//! closed meshes, axis-parallel rays, a reference image, and the benchmark protocol's counts.

use std::path::PathBuf;
use std::sync::OnceLock;

use emc_core::Aabb;
use emc_core::LayoutSpec;
use emc_cpu::build::Builder;
use emc_cpu::bvh::{Bvh, Node};
use emc_cpu::scene::{self, Mesh, SceneOptions};
use emc_cpu::trace::image::{shade, Image, Shading};
use emc_cpu::trace::intersect::{brute_force_closest, brute_force_occluded, slab_test, PreRay};
use emc_cpu::trace::traverse::{
    avx2_available, avx512_available, closest, node_test_avx2, node_test_avx2_octant,
    node_test_avx512, node_test_scalar, node_test_simd, occluded,
};
use emc_cpu::trace::wide::{WideNodeN, MAX_DEPTH};
use emc_cpu::trace::workload::{
    cosine_dir, primary_rays, protocol_counts, trace_closest, trace_occluded, Camera, CameraMode,
    SceneFrame,
};
use emc_cpu::trace::{
    Accel, BuildOptions, Hit, NodeTest, Preset, Ray, TraceError, TraceStats, WideBvh,
};
use glam::Vec3;

// ---------------------------------------------------------------------------------------------
// Helpers: a deterministic generator, triangle lists, a local median-split builder.

/// SplitMix64: a small deterministic generator for test rays.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn dir(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            let l = v.length_squared();
            if l > 1e-4 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }
}

fn triangles(s: &Mesh) -> Vec<[Vec3; 3]> {
    (0..s.triangle_count()).map(|i| s.triangle(i)).collect()
}

fn tri_box(t: &[Vec3; 3]) -> Aabb {
    Aabb::from_triangle(t[0], t[1], t[2])
}

/// A top-down median-split BVH2 (object median on the longest centroid axis), test-only.
fn median_split(tris: &[[Vec3; 3]], leaf: usize) -> Bvh {
    let mut ids: Vec<u32> = (0..tris.len() as u32).collect();
    let mut nodes = vec![Node::default()];
    let mut work = vec![(0usize, 0usize, tris.len())];
    while let Some((slot, lo, hi)) = work.pop() {
        let mut b = Aabb::EMPTY;
        let mut cb = Aabb::EMPTY;
        for &i in &ids[lo..hi] {
            let tb = tri_box(&tris[i as usize]);
            b = b.union(&tb);
            cb.grow((tb.min + tb.max) * 0.5);
        }
        if hi - lo <= leaf {
            nodes[slot] = Node::leaf(b, lo as u32, (hi - lo) as u32);
            continue;
        }
        let e = cb.max - cb.min;
        let axis = if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        };
        let key = |i: &u32| {
            let tb = tri_box(&tris[*i as usize]);
            (tb.min + tb.max)[axis]
        };
        ids[lo..hi].sort_by(|a, b| key(a).total_cmp(&key(b)).then(a.cmp(b)));
        let mid = (lo + hi) / 2;
        let l = nodes.len();
        nodes.push(Node::default());
        nodes.push(Node::default());
        nodes[slot] = Node::inner(b, l as u32, l as u32 + 1);
        work.push((l, lo, mid));
        work.push((l + 1, mid, hi));
    }
    Bvh {
        nodes,
        prim_indices: ids,
        root: 0,
    }
}

/// The named code layouts of the LBVH builders.
const LAYOUTS: [&str; 6] = [
    "morton30",
    "morton63",
    "emc64-sort",
    "emc64-var",
    "emc32-var",
    "emc64-var-nosize",
];

/// Every (builder name, wide BVH) this suite can make for `tris`: the test-local median
/// split, binned SAH, and both LBVH builders over every layout (with and without treelet
/// restructuring), at several leaf sizes.
fn all_bvhs(tris: &[[Vec3; 3]]) -> Vec<(String, WideBvh)> {
    let mut out = Vec::new();
    for leaf in [1, 4] {
        let b = median_split(tris, leaf);
        out.push((
            format!("median-split/leaf{leaf}"),
            WideBvh::from_bvh2(&b, tris).expect("median split converts"),
        ));
    }
    let mut configs: Vec<(Builder, Option<LayoutSpec>, bool, u32)> = vec![
        (Builder::BinnedSah, None, false, 1),
        (Builder::BinnedSah, None, false, 4),
        (Builder::BinnedSah, None, true, 8),
    ];
    for l in LAYOUTS {
        let l: LayoutSpec = l.parse().unwrap();
        // Leaf sizes 4 and 1 build on the fast path; 2 goes through a BVH2 and the collapse.
        configs.push((Builder::Lbvh, Some(l), false, 4));
        configs.push((Builder::Lbvh, Some(l), false, 1));
        configs.push((Builder::LbvhApetrei, Some(l), false, 2));
        configs.push((Builder::Lbvh, Some(l), true, 8));
    }
    for (builder, layout, restructure, leaf) in configs {
        let mut opts = BuildOptions::preset(Preset::Quality)
            .with_builder(builder)
            .with_restructure(restructure)
            .with_leaf_size(leaf);
        opts.layout = layout.map(Into::into);
        let name = format!(
            "{builder}/{}/atr={restructure}/leaf{leaf}",
            layout.map_or("-".to_string(), |l| l.to_string())
        );
        let a = Accel::from_triangles(tris.to_vec(), &opts)
            .unwrap_or_else(|e| panic!("{name} builds: {e}"));
        out.push((name, a.wide_bvh().clone()));
    }
    out
}

/// Rays of every kind the tests use: random origins and directions around the scene, rays
/// aimed exactly at vertices and at points on edges, axis-parallel rays through vertex
/// coordinates (origins on box planes), and random finite intervals.
fn test_rays(tris: &[[Vec3; 3]], n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng(seed);
    let f = SceneFrame::of(tris);
    let pad = (f.max - f.min) * 0.1 + Vec3::splat(1e-3);
    let (lo, hi) = (f.min - pad, f.max + pad);
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let o = Vec3::new(
            rng.range(lo.x, hi.x),
            rng.range(lo.y, hi.y),
            rng.range(lo.z, hi.z),
        );
        let t = &tris[rng.below(tris.len())];
        let mut ray = match k % 5 {
            0 => Ray::new(o, rng.dir()),
            1 => Ray::new(o, t[rng.below(3)] - o),
            2 => {
                let (a, b) = (t[rng.below(3)], t[rng.below(3)]);
                let s = rng.unit();
                Ray::new(o, a + (b - a) * s - o)
            }
            3 => {
                // Axis-parallel through a vertex's other two coordinates.
                let v = t[rng.below(3)];
                let axis = rng.below(3);
                let mut o2 = v;
                o2[axis] = o[axis];
                let mut d = Vec3::ZERO;
                d[axis] = if rng.unit() < 0.5 { 1.0 } else { -1.0 };
                Ray::new(o2, d)
            }
            _ => {
                // A direction with one exact zero and a signed zero on another.
                let mut d = rng.dir();
                d[rng.below(3)] = 0.0;
                if d == Vec3::ZERO {
                    d = Vec3::X;
                }
                Ray::new(o, d)
            }
        };
        if k % 3 == 1 {
            ray.tfar = rng.range(0.0, 2.0) * (hi - lo).length();
        }
        out.push(ray);
    }
    out
}

/// The brute-force answers (closest hit, any hit) of `rays`.
fn brute_force(tris: &[[Vec3; 3]], rays: &[Ray]) -> Vec<(Option<Hit>, bool)> {
    use rayon::prelude::*;
    rays.par_iter()
        .map(|r| (brute_force_closest(r, tris), brute_force_occluded(r, tris)))
        .collect()
}

/// Check closest hit (t bits and id) and any hit against brute force.
fn check_against_brute_force(name: &str, tris: &[[Vec3; 3]], bvh: &WideBvh, rays: &[Ray]) {
    check_against(name, bvh, rays, &brute_force(tris, rays));
}

/// The SIMD kernels this CPU runs: SSE (4-wide tree), AVX2 and, where the CPU has it,
/// AVX-512 (8-wide tree); a kernel the CPU lacks is skipped with a message (once).
fn simd_kernels() -> Vec<NodeTest> {
    static SAID: OnceLock<()> = OnceLock::new();
    let mut k = vec![NodeTest::Simd, NodeTest::Avx2];
    if avx512_available() {
        k.push(NodeTest::Avx512);
    } else {
        SAID.get_or_init(|| {
            println!("no AVX-512 F/VL/DQ on this CPU: the Avx512 kernel is skipped")
        });
    }
    k
}

/// Check closest hit (t bits and id) and any hit against precomputed brute-force answers, on
/// the 4-wide (SSE) and the 8-wide (AVX2, AVX-512) tree.
fn check_against(name: &str, bvh: &WideBvh, rays: &[Ray], want: &[(Option<Hit>, bool)]) {
    for kind in simd_kernels() {
        check_against_with(&format!("{name} {kind:?}"), bvh, rays, want, kind);
    }
}

fn check_against_with(
    name: &str,
    bvh: &WideBvh,
    rays: &[Ray],
    want: &[(Option<Hit>, bool)],
    kind: NodeTest,
) {
    use rayon::prelude::*;
    let bad: Vec<String> = rays
        .par_iter()
        .zip(want)
        .enumerate()
        .filter_map(|(i, (r, &(want, want_occ)))| {
            let got = closest::<false>(bvh, r, kind, &mut TraceStats::default());
            let same = match (want, got) {
                (None, None) => true,
                (Some(a), Some(b)) => a.t.to_bits() == b.t.to_bits() && a.prim == b.prim,
                _ => false,
            };
            let occ = occluded::<false>(bvh, r, kind, &mut TraceStats::default());
            (!same || occ != want.is_some() || occ != want_occ)
                .then(|| format!("ray {i} {r:?}: want {want:?} got {got:?} occluded {occ}"))
        })
        .collect();
    assert!(
        bad.is_empty(),
        "{name}: {} of {} rays disagree with brute force, first: {}",
        bad.len(),
        rays.len(),
        bad[0]
    );
}

fn builtin(name: &str, prims: usize) -> Mesh {
    scene::load_with(
        &format!("builtin:{name}"),
        &SceneOptions::default().with_prims(prims),
    )
    .expect("built-in scene")
}

// ---------------------------------------------------------------------------------------------
// Geometry and node tests.

#[test]
fn simd_node_test_equals_scalar_bit_for_bit() {
    check_node_test::<4>(node_test_simd);
}

#[test]
fn avx2_node_test_equals_scalar_bit_for_bit() {
    if !avx2_available() {
        println!("no AVX2 on this CPU: node_test_avx2 is the scalar test itself");
    }
    check_node_test::<8>(node_test_avx2);
}

#[test]
fn avx2_octant_node_tests_equal_scalar_bit_for_bit() {
    if !avx2_available() {
        println!("no AVX2 on this CPU: node_test_avx2_octant is the scalar test itself");
    }
    check_node_test::<8>(node_test_avx2_octant);
}

#[test]
fn avx512_node_test_equals_scalar_bit_for_bit() {
    if !avx512_available() {
        println!("no AVX-512 F/VL/DQ on this CPU: node_test_avx512 falls back to the AVX2 test");
    }
    check_node_test::<8>(node_test_avx512);
}

/// Random and adversarial nodes and rays (±0 components, origins on planes, unused lanes):
/// `test` gives the scalar test's mask and entry distances, bit for bit.
fn check_node_test<const W: usize>(test: fn(&WideNodeN<W>, &PreRay, f32) -> (u32, [f32; W])) {
    let mut rng = Rng(7);
    let coords = [-2.0f32, -1.0, -0.0, 0.0, 0.5, 1.0, 3.0];
    for k in 0..200_000 {
        let mut node = WideNodeN::<W>::empty();
        for lane in 0..W {
            for a in 0..3 {
                let (x, y) = if k % 2 == 0 {
                    (coords[rng.below(7)], coords[rng.below(7)])
                } else {
                    (rng.range(-2.0, 2.0), rng.range(-2.0, 2.0))
                };
                node.planes[2 * a][lane] = x.min(y);
                node.planes[2 * a + 1][lane] = x.max(y);
            }
        }
        if k % 7 == 0 {
            // An unused lane.
            for a in 0..3 {
                node.planes[2 * a][W - 1] = f32::INFINITY;
                node.planes[2 * a + 1][W - 1] = f32::NEG_INFINITY;
            }
        }
        let o = if k % 3 == 0 {
            Vec3::new(
                coords[rng.below(7)],
                coords[rng.below(7)],
                coords[rng.below(7)],
            )
        } else {
            Vec3::new(
                rng.range(-3.0, 3.0),
                rng.range(-3.0, 3.0),
                rng.range(-3.0, 3.0),
            )
        };
        let mut d = rng.dir();
        if k % 4 == 0 {
            d[rng.below(3)] = if rng.unit() < 0.5 { 0.0 } else { -0.0 };
        }
        if k % 8 == 0 {
            d[rng.below(3)] = 0.0;
        }
        if d.abs().max_element() == 0.0 {
            d = Vec3::Y;
        }
        let r = PreRay::new(&Ray::new(o, d));
        let tfar = if k % 5 == 0 {
            rng.range(0.0, 4.0)
        } else {
            f32::INFINITY
        };
        let (m_ref, d_ref) = node_test_scalar(&node, &r, tfar);
        let (m_simd, d_simd) = test(&node, &r, tfar);
        assert_eq!(
            m_ref, m_simd,
            "mask differs for ray {o:?} {d:?} node {node:?}"
        );
        for lane in 0..W {
            if m_ref & (1 << lane) != 0 {
                assert_eq!(d_ref[lane].to_bits(), d_simd[lane].to_bits());
                assert!(!d_ref[lane].is_nan());
            }
            // The scalar reference agrees with the box-wise slab test.
            let b = node.child_box(lane);
            let s = slab_test(&r, b.min.to_array(), b.max.to_array(), tfar);
            assert_eq!(s.is_some(), m_ref & (1 << lane) != 0);
        }
    }
}

#[test]
fn axis_parallel_and_zero_component_rays_give_no_nan() {
    // An axis-aligned grid of unit quads in z = 0 (shared edges and vertices everywhere).
    let mut tris = Vec::new();
    for y in 0..8 {
        for x in 0..8 {
            let p = |dx: i32, dy: i32| Vec3::new((x + dx) as f32, (y + dy) as f32, 0.0);
            tris.push([p(0, 0), p(1, 0), p(1, 1)]);
            tris.push([p(0, 0), p(1, 1), p(0, 1)]);
        }
    }
    let bvh = WideBvh::from_bvh2(&median_split(&tris, 1), &tris).unwrap();
    // Straight down through every grid point, cell centre and edge midpoint: all must hit at t = 1.
    for yi in 0..=16 {
        for xi in 0..=16 {
            let o = Vec3::new(xi as f32 * 0.5, yi as f32 * 0.5, 1.0);
            for d in [Vec3::new(0.0, 0.0, -1.0), Vec3::new(-0.0, -0.0, -1.0)] {
                let h = closest::<false>(
                    &bvh,
                    &Ray::new(o, d),
                    NodeTest::Simd,
                    &mut TraceStats::default(),
                )
                .unwrap_or_else(|| panic!("ray down at {o:?} leaked"));
                assert_eq!(h.t, 1.0);
                assert!(!h.u.is_nan() && !h.v.is_nan());
                let b = brute_force_closest(&Ray::new(o, d), &tris).unwrap();
                assert_eq!((h.t, h.prim), (b.t, b.prim), "tie rule at {o:?}");
            }
            // In the plane of the grid, along x: a ray in the triangle plane never hits.
            let r = Ray::new(Vec3::new(-1.0, yi as f32 * 0.5, 0.0), Vec3::X);
            assert_eq!(
                closest::<false>(&bvh, &r, NodeTest::Simd, &mut TraceStats::default()),
                brute_force_closest(&r, &tris)
            );
        }
    }
}

#[test]
fn invalid_rays_are_misses() {
    let tris = vec![[Vec3::ZERO, Vec3::X, Vec3::Y]];
    let a = Accel::from_triangles(tris, &BuildOptions::default()).unwrap();
    let o = Vec3::new(0.2, 0.2, 1.0);
    for r in [
        Ray::new(o, Vec3::ZERO),
        Ray::new(o, Vec3::new(f32::NAN, 0.0, -1.0)),
        Ray::new(Vec3::splat(f32::INFINITY), Vec3::Z),
        Ray::segment(o, -Vec3::Z, f32::NAN, 1.0),
        Ray::segment(o, -Vec3::Z, 2.0, 1.0),
    ] {
        assert_eq!(a.intersect(&r), None);
        assert!(!a.occluded(&r));
    }
    assert!(a.occluded(&Ray::new(o, -Vec3::Z)));
}

// ---------------------------------------------------------------------------------------------
// Conversion.

#[test]
fn conversion_refuses_bad_trees_and_too_deep_trees() {
    let tris: Vec<[Vec3; 3]> = (0..400)
        .map(|i| {
            let x = i as f32;
            [
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 0.5, 0.0, 0.0),
                Vec3::new(x, 1.0, 0.0),
            ]
        })
        .collect();
    // A caterpillar: every inner node has a leaf and the rest of the chain.
    let caterpillar = |n: usize| {
        let mut nodes = Vec::new();
        let mut prim = Vec::new();
        for i in 0..n - 1 {
            let b = tris[i..n]
                .iter()
                .fold(Aabb::EMPTY, |b, t| b.union(&tri_box(t)));
            let me = nodes.len() as u32;
            nodes.push(Node::inner(b, me + 1, me + 2));
            nodes.push(Node::leaf(tri_box(&tris[i]), i as u32, 1));
            prim.push(i as u32);
        }
        nodes.push(Node::leaf(tri_box(&tris[n - 1]), (n - 1) as u32, 1));
        prim.push((n - 1) as u32);
        Bvh {
            nodes,
            prim_indices: prim,
            root: 0,
        }
    };
    // Each wide level swallows three chain levels: 200 fits, 400 does not.
    let ok = caterpillar(200);
    let w = WideBvh::from_bvh2(&ok, &tris[..200]).expect("a 200-chain fits");
    assert!(w.depth <= MAX_DEPTH);
    check_against_brute_force(
        "caterpillar",
        &tris[..200],
        &w,
        &test_rays(&tris[..200], 2000, 3),
    );
    match WideBvh::from_bvh2(&caterpillar(400), &tris) {
        Err(TraceError::TooDeep { depth, max }) => assert!(depth > max),
        other => panic!("a 400-chain must be refused, got {other:?}"),
    }
    // A tree that misses a triangle, and one with a bad child index.
    let mut missing = median_split(&tris, 1);
    missing.prim_indices.pop();
    assert!(matches!(
        WideBvh::from_bvh2(&missing, &tris),
        Err(TraceError::InvalidBvh(_))
    ));
    let mut bad = median_split(&tris, 1);
    bad.nodes[0] = Node::inner(bad.nodes[0].bounds, 1, 999_999);
    assert!(matches!(
        WideBvh::from_bvh2(&bad, &tris),
        Err(TraceError::InvalidBvh(_))
    ));
    assert!(matches!(
        WideBvh::from_bvh2(&Bvh::default(), &[]),
        Err(TraceError::NoTriangles)
    ));
    // A root leaf holding everything.
    let all = Bvh {
        nodes: vec![Node::leaf(
            tris.iter().fold(Aabb::EMPTY, |b, t| b.union(&tri_box(t))),
            0,
            tris.len() as u32,
        )],
        prim_indices: (0..tris.len() as u32).collect(),
        root: 0,
    };
    let w = WideBvh::from_bvh2(&all, &tris).unwrap();
    check_against_brute_force("root leaf", &tris, &w, &test_rays(&tris, 500, 4));
}

#[test]
fn api_rejects_bad_meshes() {
    let v = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let o = BuildOptions::default();
    assert!(matches!(
        Accel::build(&v, &[[0, 1, 3]], &o),
        Err(TraceError::BadIndex {
            tri: 0,
            index: 3,
            ..
        })
    ));
    assert!(matches!(
        Accel::build(&v, &[], &o),
        Err(TraceError::NoTriangles)
    ));
    let nan = [Vec3::ZERO, Vec3::X, Vec3::new(f32::NAN, 0.0, 0.0)];
    assert!(matches!(
        Accel::build(&nan, &[[0, 1, 2]], &o),
        Err(TraceError::NonFinite(0))
    ));
    for bad in [o.with_leaf_size(0), o.with_width(3)] {
        assert!(Accel::build(&v, &[[0, 1, 2]], &bad).is_err(), "{bad:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// Traversal against brute force.

#[test]
fn closest_and_any_hit_equal_brute_force_on_builtin_scenes() {
    for (name, prims) in [
        ("uniform", 3000),
        ("stadium", 3000),
        ("city", 3000),
        ("hair", 3000),
        ("mixed", 3000),
        ("sphere", 1280),
    ] {
        let s = builtin(name, prims);
        let tris = triangles(&s);
        let rays = test_rays(&tris, 3000, 11);
        let want = brute_force(&tris, &rays);
        for (b, bvh) in all_bvhs(&tris) {
            check_against(&format!("builtin:{name} {b}"), &bvh, &rays, &want);
        }
    }
}

#[test]
fn scalar_and_simd_traversals_agree_including_work_counters() {
    let s = builtin("mixed", 20_000);
    let tris = triangles(&s);
    let rays = test_rays(&tris, 20_000, 5);
    for (b, bvh) in all_bvhs(&tris) {
        let eight = simd_kernels().into_iter().filter(|k| k.width() == 8);
        let pairs = [(NodeTest::Scalar, NodeTest::Simd)]
            .into_iter()
            .chain(eight.map(|k| (NodeTest::Scalar8, k)));
        for (scalar, simd) in pairs {
            let mut s1 = TraceStats::default();
            let mut s2 = TraceStats::default();
            for r in &rays {
                let a = closest::<true>(&bvh, r, scalar, &mut s1);
                let c = closest::<true>(&bvh, r, simd, &mut s2);
                let four = closest::<false>(&bvh, r, NodeTest::Scalar, &mut TraceStats::default());
                assert_eq!(
                    a.map(|h| (h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits())),
                    c.map(|h| (h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits()))
                );
                // Both trees give the same closest hit.
                assert_eq!(
                    a.map(|h| (h.t.to_bits(), h.prim)),
                    four.map(|h| (h.t.to_bits(), h.prim))
                );
                assert_eq!(
                    occluded::<true>(&bvh, r, scalar, &mut s1),
                    occluded::<true>(&bvh, r, simd, &mut s2)
                );
            }
            assert_eq!(s1, s2, "{b} {simd:?}");
        }
    }
}

#[test]
fn batch_api_equals_single_rays() {
    let s = builtin("city", 5000);
    let tris = triangles(&s);
    let rays = test_rays(&tris, 4000, 9);
    for preset in [Preset::Fast, Preset::Balanced, Preset::Quality] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let a = pool
            .install(|| Accel::build(&s.vertices, &s.indices, &BuildOptions::preset(preset)))
            .unwrap();
        let (hits, occ) = pool.install(|| (a.intersect_batch(&rays), a.occluded_batch(&rays)));
        for (i, r) in rays.iter().enumerate() {
            assert_eq!(hits[i], a.intersect(r));
            assert_eq!(occ[i], a.occluded(r));
            assert_eq!(
                hits[i].map(|h| (h.t, h.prim)),
                brute_force_closest(r, &tris).map(|h| (h.t, h.prim))
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Watertightness.

#[test]
fn closed_icosphere_is_watertight() {
    // Level 5: 20,480 triangles, 10,242 vertices, 30,720 edges.
    let s = builtin("sphere", 20_480);
    assert_eq!(s.triangle_count(), 20_480);
    let tris = triangles(&s);
    let a = Accel::from_triangles(tris.clone(), &BuildOptions::preset(Preset::Quality)).unwrap();
    let mut edges: Vec<(u32, u32)> = s
        .indices
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .map(|(x, y)| (x.min(y), x.max(y)))
        .collect();
    edges.sort_unstable();
    edges.dedup();
    assert_eq!(edges.len(), 30_720);
    // Targets: every vertex, and 24 points along every edge (exact end points included).
    let mut targets: Vec<Vec3> = s.vertices.clone();
    for &(x, y) in &edges {
        let (p, q) = (s.vertices[x as usize], s.vertices[y as usize]);
        for k in 1..24 {
            let f = k as f32 / 24.0;
            targets.push(p + (q - p) * f);
        }
    }
    // Origins: the centre and points inside, some on coordinate planes.
    let origins = [
        Vec3::ZERO,
        Vec3::new(0.3, -0.2, 0.1),
        Vec3::new(0.0, 0.5, 0.0),
        Vec3::new(-0.61, 0.0, 0.37),
        Vec3::new(0.1, 0.1, -0.8),
    ];
    let rays: Vec<Ray> = origins
        .iter()
        .flat_map(|&o| targets.iter().map(move |&t| Ray::new(o, t - o)))
        .collect();
    assert!(rays.len() > 3_000_000, "{} rays", rays.len());
    let hits = a.intersect_batch(&rays);
    let occ = a.occluded_batch(&rays);
    let escaped: Vec<usize> = (0..rays.len()).filter(|&i| hits[i].is_none()).collect();
    assert!(
        escaped.is_empty(),
        "{} of {} rays escaped the closed sphere, first {:?}",
        escaped.len(),
        rays.len(),
        rays[escaped[0]]
    );
    assert!(occ.iter().all(|&o| o), "an occlusion ray escaped");
    // The API traces the fastest tree; the other tree must be just as closed.
    let other = if NodeTest::fastest() == NodeTest::Avx2 {
        NodeTest::Simd
    } else {
        NodeTest::Avx2
    };
    let (hits, _) = trace_closest(a.wide_bvh(), &rays, other, false);
    let (occ, _) = trace_occluded(a.wide_bvh(), &rays, other, false);
    assert!(
        hits.iter().all(|h| h.is_some()),
        "a ray escaped ({other:?})"
    );
    assert!(
        occ.iter().all(|&o| o),
        "an occlusion ray escaped ({other:?})"
    );
}

// ---------------------------------------------------------------------------------------------
// Reference image.

fn reference_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/trace-mixed-normal-128.png")
}

/// Tolerance: every channel within ±1 of the reference, except at most 16 of the 16,384
/// pixels (silhouette pixels whose ray may pick another triangle on another platform).
#[test]
fn rendered_image_matches_reference() {
    let s = builtin("mixed", 20_000);
    let tris = triangles(&s);
    let a = Accel::from_triangles(tris.clone(), &BuildOptions::preset(Preset::Quality)).unwrap();
    let frame = SceneFrame::of(&tris);
    let cam = Camera::protocol(&frame, CameraMode::Outside);
    let rays = primary_rays(&cam, 128, 128);
    let (hits, _) = trace_closest(a.wide_bvh(), &rays, NodeTest::Simd, false);
    let img = shade(
        a.wide_bvh(),
        &tris,
        &rays,
        &hits,
        (128, 128),
        frame.diag,
        Shading::Normal,
    );
    let path = reference_path();
    if std::env::var_os("EMC_REGEN_TRACE_REF").is_some() {
        img.write_png(std::fs::File::create(&path).unwrap())
            .unwrap();
        eprintln!("wrote {}", path.display());
        return;
    }
    let reference = Image::read_png(std::fs::File::open(&path).expect(
        "reference image missing; create it with EMC_REGEN_TRACE_REF=1 cargo test --release \
         -p emc-tests --test trace rendered_image",
    ))
    .unwrap();
    assert_eq!((reference.width, reference.height), (128, 128));
    let background = img
        .rgb
        .chunks(3)
        .filter(|p| p == &emc_cpu::trace::image::BACKGROUND)
        .count();
    assert!(
        background > 100 && background < 128 * 128 - 100,
        "the scene fills part of the frame"
    );
    let off = img
        .rgb
        .chunks(3)
        .zip(reference.rgb.chunks(3))
        .filter(|(p, q)| p.iter().zip(q.iter()).any(|(a, b)| a.abs_diff(*b) > 1))
        .count();
    assert!(
        off <= 16,
        "{off} pixels differ from the reference by more than 1"
    );
}

// ---------------------------------------------------------------------------------------------
// Shared scenes: brute force and the benchmark protocol's counts.

/// Embree 3.13.5's counts from the benchmark protocol (scene, camera, primary hits, AO rays,
/// AO occluded); scenes of at most 1M triangles.
const PROTOCOL: [(&str, usize, u64, u64, u64); 8] = [
    ("spot", 5856, 206_481, 825_924, 23_736),
    ("sionna-etoile", 13_098, 402_695, 1_610_780, 273_388),
    ("sionna-munich", 38_936, 403_746, 1_614_984, 307_215),
    ("torcs-spring", 62_875, 107_534, 430_136, 27_222),
    ("stanford-bunny", 69_451, 254_905, 1_019_620, 53_729),
    ("sionna-san-francisco", 268_041, 399_370, 1_597_480, 439_685),
    ("pbrt-bathroom", 447_123, 1_048_576, 4_194_304, 696_003),
    ("stanford-dragon", 871_414, 237_361, 949_444, 137_129),
];

/// A loaded shared scene: its triangles and their acceleration structure.
type Loaded = (Vec<[Vec3; 3]>, Accel);

/// Load (once per test binary) a shared scene with the `quality` preset.
fn shared_scene(name: &str) -> Option<&'static Loaded> {
    static CACHE: OnceLock<std::sync::Mutex<Vec<(String, &'static Loaded)>>> = OnceLock::new();
    scene::shared_scene_path(name)?;
    let cache = CACHE.get_or_init(Default::default);
    let mut c = cache.lock().unwrap();
    if let Some((_, v)) = c.iter().find(|(n, _)| n == name) {
        return Some(v);
    }
    let s = scene::load(name).expect("shared scene loads");
    let tris = triangles(&s);
    let a = Accel::from_triangles(tris.clone(), &BuildOptions::preset(Preset::Quality)).unwrap();
    let v: &'static Loaded = Box::leak(Box::new((tris, a)));
    c.push((name.to_string(), v));
    Some(v)
}

/// The protocol's bound on every count.
const PROTOCOL_TOLERANCE: f64 = 5e-4;

/// Check the protocol counts of the named scenes of `table`; returns how many were present.
fn check_protocol_counts(table: &[(&str, usize, u64, u64, u64)], names: &[&str]) -> usize {
    let mut tested = 0;
    let mut failures = Vec::new();
    for &(name, tris_n, hits, ao, occ) in table {
        if !names.contains(&name) {
            continue;
        }
        let Some((tris, a)) = shared_scene(name) else {
            eprintln!("skipping {name}: not present");
            continue;
        };
        assert_eq!(tris.len(), tris_n, "{name} triangle count");
        let c = protocol_counts(a.wide_bvh(), tris, CameraMode::for_scene(name), 1024);
        let rel = |got: u64, want: u64| (got as f64 - want as f64).abs() / want as f64;
        eprintln!("{name}: {c:?} vs Embree {hits}/{ao}/{occ}");
        for (what, got, want) in [
            ("primary hits", c.primary_hits, hits),
            ("AO rays", c.ao_rays, ao),
            ("AO occluded", c.ao_occluded, occ),
        ] {
            if rel(got, want) > PROTOCOL_TOLERANCE {
                failures.push(format!(
                    "{name}: {what} {got} vs Embree {want} ({:+.4}%, tolerance {:.3}%)",
                    (got as f64 / want as f64 - 1.0) * 100.0,
                    PROTOCOL_TOLERANCE * 100.0
                ));
            }
        }
        tested += 1;
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    tested
}

#[test]
fn protocol_counts_agree_with_embree() {
    if scene::shared_scenes_dir().is_none() {
        eprintln!("skipping: no shared scenes directory");
        return;
    }
    let names: Vec<&str> = PROTOCOL.iter().map(|p| p.0).collect();
    let tested = check_protocol_counts(&PROTOCOL, &names);
    eprintln!("{tested} shared scenes checked");
}

/// Embree 3.13.5's counts of the two scenes above 1M triangles (opt-in: loading and building
/// them takes minutes).
const PROTOCOL_LARGE: [(&str, usize, u64, u64, u64); 2] = [
    ("pbrt-crown", 3_540_214, 142_186, 568_744, 49_328),
    ("san-miguel-pbrtv3", 9_384_746, 253_877, 1_015_508, 121_741),
];

/// Opt-in: `cargo test --release -p emc-tests --test trace -- --ignored large_scenes`.
#[test]
#[ignore = "pbrt-crown and san-miguel-pbrtv3: minutes to load and build"]
fn protocol_counts_agree_with_embree_large_scenes() {
    if scene::shared_scenes_dir().is_none() {
        eprintln!("skipping: no shared scenes directory");
        return;
    }
    let names: Vec<&str> = PROTOCOL_LARGE.iter().map(|p| p.0).collect();
    let tested = check_protocol_counts(&PROTOCOL_LARGE, &names);
    eprintln!("{tested} large shared scenes checked");
}

/// The AO basis does not depend on the sign of a zero `n.z`: normals of axis-aligned faces
/// often carry `-0.0` after the facing flip, and the protocol's counts (Embree's harness) take
/// them as `+0.0`. With the sign bit instead, half of such normals get a different basis.
#[test]
fn ao_basis_ignores_the_sign_of_zero() {
    let normals = [
        (Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 0.0, -0.0)),
        (Vec3::new(0.0, -1.0, 0.0), Vec3::new(-0.0, -1.0, -0.0)),
        (Vec3::new(0.6, 0.8, 0.0), Vec3::new(0.6, 0.8, -0.0)),
    ];
    let mut rng = Rng(7);
    for (pos, neg) in normals {
        for _ in 0..64 {
            let (u1, u2) = (rng.unit(), rng.unit());
            let (a, b) = (cosine_dir(pos, u1, u2), cosine_dir(neg, u1, u2));
            assert_eq!(
                a.to_array().map(f32::to_bits),
                b.to_array().map(f32::to_bits)
            );
            // Cosine-weighted around n: unit length and in n's hemisphere.
            assert!((a.length() - 1.0).abs() < 1e-5 && a.dot(pos) >= 0.0);
        }
    }
    // A negative n.z that is not zero still takes the other branch of the basis.
    let n = Vec3::new(0.0, 0.6, -0.8);
    let d = cosine_dir(n, 0.3, 0.7);
    assert!((d.length() - 1.0).abs() < 1e-5 && d.dot(n) > 0.0);
}

#[test]
fn shared_scenes_equal_brute_force() {
    if scene::shared_scenes_dir().is_none() {
        eprintln!("skipping: no shared scenes directory");
        return;
    }
    for (name, ..) in PROTOCOL {
        let Some((tris, a)) = shared_scene(name) else {
            eprintln!("skipping {name}: not present");
            continue;
        };
        let mut rays = test_rays(tris, 60, 21);
        // Protocol rays too: a slice of the primary rays.
        let f = SceneFrame::of(tris);
        let cam = Camera::protocol(&f, CameraMode::for_scene(name));
        rays.extend(primary_rays(&cam, 256, 256).into_iter().step_by(1093));
        let want = brute_force(tris, &rays);
        check_against(&format!("{name} binned-sah"), a.wide_bvh(), &rays, &want);
        // The LBVH builders: two layouts, both hierarchy builders, with and without atrbvh.
        for (builder, layout, restructure) in [
            (Builder::Lbvh, "morton63", false),
            (Builder::LbvhApetrei, "emc64-var", false),
            (Builder::Lbvh, "emc64-var", true),
        ] {
            let opts = BuildOptions::default()
                .with_builder(builder)
                .with_layout(layout.parse::<emc_cpu::LayoutChoice>().unwrap())
                .with_restructure(restructure);
            let b = Accel::from_triangles(tris.clone(), &opts).unwrap();
            let label = format!("{name} {builder}/{layout}/atr={restructure}");
            check_against(&label, b.wide_bvh(), &rays, &want);
        }
    }
}

#[test]
fn hard_builtin_scenes_equal_brute_force() {
    // The builders' hard cases (points, planes, far/huge/tiny/subnormal coordinates, needles,
    // duplicates...): every tree converts and traces exactly like brute force.
    for name in scene::builtin::HARD_NAMES {
        let Ok(s) = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(2000),
        ) else {
            eprintln!("builtin:{name} does not load at 2000 triangles; skipped");
            continue;
        };
        let tris = triangles(&s);
        let rays = test_rays(&tris, 2000, 31);
        let want = brute_force(&tris, &rays);
        for (builder, layout) in [
            (Builder::BinnedSah, "emc64-var"),
            (Builder::Lbvh, "emc64-var"),
            (Builder::LbvhApetrei, "morton30"),
        ] {
            let opts = BuildOptions::default()
                .with_builder(builder)
                .with_layout(layout.parse::<emc_cpu::LayoutChoice>().unwrap());
            match Accel::from_triangles(tris.clone(), &opts) {
                Ok(a) => check_against(
                    &format!("builtin:{name} {builder}/{layout}"),
                    a.wide_bvh(),
                    &rays,
                    &want,
                ),
                Err(e) => panic!("builtin:{name} {builder}/{layout}: {e}"),
            }
        }
    }
}
