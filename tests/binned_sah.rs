//! The `binned-sah` builder: node for node equal to a plain single-threaded binned SAH written
//! here, valid on random and degenerate inputs, bit-identical across thread counts, clear
//! errors on bad input, and its SAH within 1% of the reference table on the shared scenes.
//!
//! The two largest scenes run on request:
//! `cargo test --release -p emc-tests --test binned_sah -- --ignored`.

use emc_core::Aabb;
use emc_cpu::bvh::binned_sah::{
    build_binned_sah, build_binned_sah_detailed, build_binned_sah_leaves, BinnedSahError, LeafRule,
    DEFAULT_BINS, MAX_BINS,
};
use emc_cpu::bvh::{sah_headline, Bvh, Node};
use emc_tests::{bx, hard_scenes, pt, scene};
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------------
// The plain reference: recursive, index vectors, every split position evaluated by filtering the
// primitives directly (no bins kept), stable partition by `Vec` filtering.

fn centroid(b: &Aabb) -> [f64; 3] {
    [
        (b.min.x as f64 + b.max.x as f64) * 0.5,
        (b.min.y as f64 + b.max.y as f64) * 0.5,
        (b.min.z as f64 + b.max.z as f64) * 0.5,
    ]
}

fn union_of(aabbs: &[Aabb], ids: &[u32]) -> Aabb {
    ids.iter()
        .fold(Aabb::EMPTY, |u, &i| u.union(&aabbs[i as usize]))
}

/// Bin of centroid coordinate `c` in a node whose centroids span `lo..lo + extent`.
fn plain_bin(c: f64, lo: f64, extent: f64, nb: usize) -> usize {
    (((c - lo) * (nb as f64 / extent)).floor() as usize).min(nb - 1)
}

/// Splits `ids` as the definition says: lowest `A_L·N_L + A_R·N_R` over axes with centroid
/// extent and split positions 1..nb (ties: lowest axis, lowest position); no extent on any
/// axis: halve the range; two primitives: one each, in range order.
fn plain_split(aabbs: &[Aabb], ids: &[u32], nb: usize) -> (Vec<u32>, Vec<u32>) {
    if ids.len() == 2 {
        return (vec![ids[0]], vec![ids[1]]);
    }
    let cs: Vec<[f64; 3]> = ids.iter().map(|&i| centroid(&aabbs[i as usize])).collect();
    let mut best: Option<(f64, usize, usize, f64, f64)> = None;
    for axis in 0..3 {
        let lo = cs.iter().map(|c| c[axis]).fold(f64::INFINITY, f64::min);
        let hi = cs.iter().map(|c| c[axis]).fold(f64::NEG_INFINITY, f64::max);
        let extent = hi - lo;
        if extent <= 0.0 {
            continue;
        }
        for k in 1..nb {
            let (mut l, mut r) = (Vec::new(), Vec::new());
            for (&i, c) in ids.iter().zip(&cs) {
                if plain_bin(c[axis], lo, extent, nb) < k {
                    l.push(i);
                } else {
                    r.push(i);
                }
            }
            if l.is_empty() || r.is_empty() {
                continue;
            }
            let cost = union_of(aabbs, &l).area_f64() * l.len() as f64
                + union_of(aabbs, &r).area_f64() * r.len() as f64;
            if best.is_none_or(|b| cost < b.0) {
                best = Some((cost, axis, k, lo, extent));
            }
        }
    }
    match best {
        Some((_, axis, k, lo, extent)) => ids
            .iter()
            .partition(|&&i| plain_bin(centroid(&aabbs[i as usize])[axis], lo, extent, nb) < k),
        None => {
            let half = ids.len() / 2;
            (ids[..half].to_vec(), ids[half..].to_vec())
        }
    }
}

fn plain_node(aabbs: &[Aabb], ids: Vec<u32>, nb: usize, bvh: &mut Bvh) -> u32 {
    let me = bvh.nodes.len();
    bvh.nodes.push(Node::default());
    let bounds = union_of(aabbs, &ids);
    if ids.len() == 1 {
        bvh.nodes[me] = Node::leaf(bounds, bvh.prim_indices.len() as u32, 1);
        bvh.prim_indices.push(ids[0]);
    } else {
        let (l, r) = plain_split(aabbs, &ids, nb);
        let li = plain_node(aabbs, l, nb, bvh);
        let ri = plain_node(aabbs, r, nb, bvh);
        bvh.nodes[me] = Node::inner(bounds, li, ri);
    }
    me as u32
}

/// The plain reference tree, nodes in depth-first order (left first), as the builder writes.
fn plain_binned_sah(aabbs: &[Aabb], nb: usize) -> Bvh {
    let mut bvh = Bvh::default();
    plain_node(aabbs, (0..aabbs.len() as u32).collect(), nb, &mut bvh);
    bvh
}

// ---------------------------------------------------------------------------------------------
// Helpers.

/// Node for node equality (bounds compared as values: a zero bound may differ in sign).
fn assert_same_tree(got: &Bvh, want: &Bvh, what: &str) {
    assert_eq!(got.root, want.root, "{what}: root");
    assert_eq!(got.nodes.len(), want.nodes.len(), "{what}: node count");
    assert_eq!(
        got.prim_indices, want.prim_indices,
        "{what}: primitive order"
    );
    for (i, (g, w)) in got.nodes.iter().zip(&want.nodes).enumerate() {
        assert_eq!(g.is_leaf(), w.is_leaf(), "{what}: node {i} kind");
        if g.is_leaf() {
            assert_eq!(
                (g.first(), g.count()),
                (w.first(), w.count()),
                "{what}: leaf {i}"
            );
        } else {
            assert_eq!(
                (g.left(), g.right()),
                (w.left(), w.right()),
                "{what}: node {i}"
            );
        }
        assert_eq!(g.bounds, w.bounds, "{what}: node {i} bounds");
    }
}

/// Every bit of a tree, for the thread-count comparison (bounds by their bit patterns).
fn fingerprint(bvh: &Bvh) -> Vec<u32> {
    let mut v = vec![bvh.root];
    v.extend_from_slice(&bvh.prim_indices);
    for n in &bvh.nodes {
        let b = n.bounds;
        v.extend(
            b.min
                .to_array()
                .iter()
                .chain(&b.max.to_array())
                .map(|f| f.to_bits()),
        );
        if n.is_leaf() {
            v.extend([1, n.first(), n.count()]);
        } else {
            v.extend([0, n.left(), n.right()]);
        }
    }
    v
}

/// Builds, validates with the shared checker, checks the one-primitive leaves and the reported
/// depth; returns the tree and its depth.
fn build_checked(aabbs: &[Aabb], nb: usize, what: &str) -> (Bvh, u32) {
    let b = build_binned_sah_detailed(aabbs, nb).unwrap_or_else(|e| panic!("{what}: {e}"));
    let stats = b
        .bvh
        .validate(aabbs)
        .unwrap_or_else(|e| panic!("{what}: invalid tree: {e}"));
    assert_eq!(stats.max_leaf_size, 1, "{what}: one primitive per leaf");
    assert_eq!(stats.nodes, 2 * aabbs.len() - 1, "{what}: node count");
    assert_eq!(stats.depth, b.depth as usize, "{what}: reported depth");
    (b.bvh, b.depth)
}

/// A small deterministic generator (splitmix64) for the large inputs.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    fn point(&mut self, scale: f32) -> [f32; 3] {
        [
            self.unit() * scale,
            self.unit() * scale,
            self.unit() * scale,
        ]
    }
}

/// `n` random boxes of random sizes in a 100-unit cube.
fn random_boxes(n: usize, seed: u64) -> Vec<Aabb> {
    let mut r = Rng(seed);
    (0..n)
        .map(|_| {
            let p = r.point(100.0);
            let s = r.unit() * r.unit() * 5.0;
            let e = [r.unit() * s, r.unit() * s, r.unit() * s];
            bx(p, [p[0] + e[0], p[1] + e[1], p[2] + e[2]])
        })
        .collect()
}

/// Random boxes whose corners snap to a coarse grid, so that many centroids coincide and
/// subtrees fall back to halving their range.
fn clustered_boxes(n: usize, seed: u64) -> Vec<Aabb> {
    let mut r = Rng(seed);
    (0..n)
        .map(|_| {
            let p = r.point(6.0).map(f32::floor);
            let s = (r.next() % 3) as f32;
            bx(p, [p[0] + s, p[1], p[2] + 1.0])
        })
        .collect()
}

/// Nine kinds of identical boxes, shuffled: clusters of thousands whose halving runs on the
/// parallel path.
fn nine_clusters(n: usize, seed: u64) -> Vec<Aabb> {
    let mut r = Rng(seed);
    (0..n)
        .map(|_| {
            let x = (r.next() % 3) as f32 * 10.0;
            let s = (r.next() % 3) as f32;
            bx([x, 0.0, 0.0], [x + 1.0 + s, 1.0, 1.0])
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Agreement with the plain reference.

proptest! {
    #![proptest_config(ProptestConfig::with_cases(192))]

    #[test]
    fn matches_plain_reference_on_random_scenes(
        boxes in scene(200),
        nb in prop::sample::select(vec![2usize, 3, 7, DEFAULT_BINS]),
    ) {
        let (got, _) = build_checked(&boxes, nb, "random scene");
        assert_same_tree(&got, &plain_binned_sah(&boxes, nb), "random scene");
    }
}

#[test]
fn matches_plain_reference_on_large_inputs() {
    // Large enough for the parallel binning, partition and subtree paths.
    for (what, boxes) in [
        ("random 70k", random_boxes(70_000, 1)),
        ("clustered 70k", clustered_boxes(70_000, 2)),
        ("nine big clusters", nine_clusters(40_000, 9)),
    ] {
        let (got, _) = build_checked(&boxes, DEFAULT_BINS, what);
        assert_same_tree(&got, &plain_binned_sah(&boxes, DEFAULT_BINS), what);
    }
}

#[test]
fn scalar_loops_match_the_plain_reference_too() {
    // The SIMD binning and partition are the default where the CPU has AVX2; the scalar loops
    // must give the same trees (both paths are identical, so flipping the switch while other
    // tests build cannot change their results).
    emc_cpu::bvh::binned_sah::force_scalar(true);
    for (name, boxes) in hard_scenes() {
        let got = build_binned_sah(&boxes, DEFAULT_BINS).unwrap();
        assert_same_tree(&got, &plain_binned_sah(&boxes, DEFAULT_BINS), name);
    }
    let boxes = clustered_boxes(40_000, 3);
    let got = build_binned_sah(&boxes, DEFAULT_BINS).unwrap();
    emc_cpu::bvh::binned_sah::force_scalar(false);
    assert_same_tree(
        &got,
        &plain_binned_sah(&boxes, DEFAULT_BINS),
        "clustered, scalar",
    );
}

#[test]
fn matches_plain_reference_on_hard_scenes() {
    for (name, boxes) in hard_scenes() {
        for nb in [2, DEFAULT_BINS, MAX_BINS] {
            let (got, _) = build_checked(&boxes, nb, name);
            assert_same_tree(&got, &plain_binned_sah(&boxes, nb), name);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Degenerate inputs: valid trees of bounded depth.

#[test]
fn a_million_identical_boxes_halve_to_log_depth() {
    let n = 1 << 20;
    let boxes = vec![bx([1.0, 2.0, 3.0], [1.5, 2.0, 4.0]); n];
    let (bvh, depth) = build_checked(&boxes, DEFAULT_BINS, "identical");
    assert_eq!(depth, 20);
    // Every node has the primitive's box: 2n − 1 nodes of equal area.
    assert_eq!(sah_headline(&bvh), (2 * n - 1) as f64);
    // Halving keeps the input order.
    assert!(bvh
        .prim_indices
        .iter()
        .enumerate()
        .all(|(i, &p)| p as usize == i));
}

#[test]
fn identical_points_and_coincident_clusters() {
    let points = vec![pt([-0.0, 0.0, 7.0]); 100_000];
    let (_, depth) = build_checked(&points, DEFAULT_BINS, "identical points");
    assert_eq!(depth, 17);
    // Two clusters of identical boxes: one SAH split, then halving in each.
    let mut two = vec![bx([0.0; 3], [1.0; 3]); 65_536];
    two.extend(vec![bx([5.0; 3], [6.0; 3]); 65_536]);
    let (bvh, depth) = build_checked(&two, DEFAULT_BINS, "two clusters");
    assert_eq!(depth, 17);
    let root = bvh.nodes[bvh.root as usize];
    let left = bvh.nodes[root.left() as usize];
    assert_eq!(left.bounds, bx([0.0; 3], [1.0; 3]));
}

#[test]
fn coplanar_and_collinear_boxes() {
    let mut r = Rng(3);
    let plane: Vec<Aabb> = (0..300_000)
        .map(|_| {
            let p = r.point(10.0);
            bx([p[0], p[1], 2.5], [p[0] + 0.01, p[1] + 0.02, 2.5])
        })
        .collect();
    let (bvh, depth) = build_checked(&plane, DEFAULT_BINS, "coplanar");
    assert!(depth < 64, "coplanar depth {depth}");
    assert!(sah_headline(&bvh).is_finite());

    // Points on a line have zero area: every split costs 0, the tie goes to the first bin and
    // each split peels off 1/32 of the range, a chain of a few hundred levels that the
    // explicit work stack carries.
    let line: Vec<Aabb> = (0..1_000_000).map(|i| pt([1.0, i as f32, -3.0])).collect();
    let (bvh, depth) = build_checked(&line, DEFAULT_BINS, "collinear");
    assert!(
        depth > 64,
        "collinear depth {depth}: zero-cost ties go to the first bin"
    );
    assert_eq!(sah_headline(&bvh), (2 * line.len() - 1) as f64);
}

#[test]
fn one_huge_box_among_many_tiny_ones() {
    let mut r = Rng(4);
    let mut boxes: Vec<Aabb> = (0..400_000)
        .map(|_| {
            let p = r.point(1.0);
            bx(p, [p[0] + 1e-4, p[1] + 1e-4, p[2] + 1e-4])
        })
        .collect();
    boxes.insert(123_456, bx([-1e6; 3], [1e6; 3]));
    let (bvh, _) = build_checked(&boxes, DEFAULT_BINS, "huge among tiny");
    let root = bvh.nodes[bvh.root as usize];
    assert_eq!(root.bounds, bx([-1e6; 3], [1e6; 3]));
}

#[test]
fn centroids_spread_over_the_whole_f32_range() {
    // Geometric spacing over every exponent: the worst case for top-down binning, where each
    // split peels off little; the explicit work stack must carry it.
    let mut r = Rng(5);
    let boxes: Vec<Aabb> = (0..200_000)
        .map(|_| {
            let p = [0, 1, 2].map(|_| {
                let v = f32::from_bits((r.next() as u32) & 0x7F7F_FFFF);
                if r.next() & 1 == 0 {
                    v
                } else {
                    -v
                }
            });
            pt(p)
        })
        .collect();
    build_checked(&boxes, DEFAULT_BINS, "f32 range");
    let chain: Vec<Aabb> = (0..250)
        .map(|i| pt([2f32.powi(i - 125), 0.0, 0.0]))
        .collect();
    let (got, _) = build_checked(&chain, DEFAULT_BINS, "geometric chain");
    assert_same_tree(
        &got,
        &plain_binned_sah(&chain, DEFAULT_BINS),
        "geometric chain",
    );
}

// ---------------------------------------------------------------------------------------------
// The build cut at SAH leaves.

/// Surface area in `f64`, written out here.
fn area64(b: &Aabb) -> f64 {
    let d = [0, 1, 2].map(|a| (b.max[a] as f64 - b.min[a] as f64).max(0.0));
    2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
}

/// Primitives below node `i` of `bvh`.
fn subtree_prims(bvh: &Bvh, i: u32) -> Vec<u32> {
    let n = &bvh.nodes[i as usize];
    if n.is_leaf() {
        let f = n.first() as usize;
        return bvh.prim_indices[f..f + n.count() as usize].to_vec();
    }
    let mut v = subtree_prims(bvh, n.left());
    v.extend(subtree_prims(bvh, n.right()));
    v
}

/// Walks the cut tree beside the full one-primitive-per-leaf tree: every inner node of the cut
/// tree is the full tree's node (same box, children in the same places); every leaf holds the
/// primitives of the full tree's subtree there. The leaf decision is checked against the rule
/// priced on the full tree's children: a leaf where `Ci·A·n < Ct·A + Ci·Σ A_c·n_c`, an inner
/// node elsewhere (for nodes of at most `max_leaf`). Returns the number of leaves.
fn check_cut(cut: &Bvh, c: u32, full: &Bvh, f: u32, rule: &LeafRule, what: &str) -> usize {
    let (cn, fnode) = (&cut.nodes[c as usize], &full.nodes[f as usize]);
    assert_eq!(cn.bounds, fnode.bounds, "{what}: node box");
    let n = subtree_prims(full, f).len();
    let rule_says_leaf = !fnode.is_leaf() && n <= rule.max_leaf as usize && {
        let (l, r) = (
            &full.nodes[fnode.left() as usize],
            &full.nodes[fnode.right() as usize],
        );
        let nl = subtree_prims(full, fnode.left()).len();
        let split = rule.ct * area64(&fnode.bounds)
            + rule.ci * (area64(&l.bounds) * nl as f64 + area64(&r.bounds) * (n - nl) as f64);
        rule.ci * area64(&fnode.bounds) * (n as f64) < split
    };
    if cn.is_leaf() {
        assert!(
            fnode.is_leaf() || rule_says_leaf,
            "{what}: leaf the rule rejects"
        );
        let mut got = subtree_prims(cut, c);
        let mut want = subtree_prims(full, f);
        got.sort_unstable();
        want.sort_unstable();
        assert_eq!(got, want, "{what}: leaf primitives");
        return 1;
    }
    assert!(
        !fnode.is_leaf() && !rule_says_leaf,
        "{what}: split the rule rejects"
    );
    check_cut(cut, cn.left(), full, fnode.left(), rule, what)
        + check_cut(cut, cn.right(), full, fnode.right(), rule, what)
}

#[test]
fn the_cut_build_is_the_full_build_above_its_sah_leaves() {
    let rule = LeafRule {
        max_leaf: 4,
        ct: 1.2,
        ci: 1.0,
    };
    let mut inputs = vec![
        ("random 20k", random_boxes(20_000, 11)),
        ("clustered 30k", clustered_boxes(30_000, 12)),
        ("nine clusters 5k", nine_clusters(5_000, 13)),
    ];
    for (name, boxes) in hard_scenes() {
        inputs.push((name, boxes));
    }
    for (what, boxes) in &inputs {
        let full = build_binned_sah(boxes, DEFAULT_BINS).expect("valid input");
        let cut = build_binned_sah_leaves(boxes, DEFAULT_BINS, rule)
            .expect("valid input")
            .bvh;
        let stats = cut
            .validate(boxes)
            .unwrap_or_else(|e| panic!("{what}: invalid cut tree: {e}"));
        assert!(stats.max_leaf_size <= 4, "{what}: leaf above max_leaf");
        let leaves = check_cut(&cut, 0, &full, 0, &rule, what);
        assert_eq!(stats.nodes, 2 * leaves - 1, "{what}: compact nodes");
        if boxes.len() > 1000 {
            assert!(leaves < boxes.len(), "{what}: the rule made no leaf");
        }
        // max_leaf = 1 is the full build.
        let one = build_binned_sah_leaves(
            boxes,
            DEFAULT_BINS,
            LeafRule {
                max_leaf: 1,
                ..rule
            },
        )
        .expect("valid input");
        assert_same_tree(&one.bvh, &full, what);
    }
    // Any thread count, the same tree.
    let boxes = clustered_boxes(120_000, 14);
    let prints: Vec<Vec<u32>> = [1, 3]
        .into_iter()
        .map(|t| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("thread pool");
            let b = pool.install(|| build_binned_sah_leaves(&boxes, DEFAULT_BINS, rule));
            fingerprint(&b.expect("valid input").bvh)
        })
        .collect();
    assert!(prints[0] == prints[1], "1 and 3 threads differ");
    let bad = LeafRule {
        max_leaf: 0,
        ..rule
    };
    assert_eq!(
        build_binned_sah_leaves(&boxes, DEFAULT_BINS, bad).err(),
        Some(BinnedSahError::LeafRule)
    );
}

// ---------------------------------------------------------------------------------------------
// Determinism and errors.

#[test]
fn identical_output_on_1_2_and_4_threads() {
    let mut inputs = vec![
        ("random 200k", random_boxes(200_000, 6)),
        ("clustered 100k", clustered_boxes(100_000, 7)),
    ];
    // Zeros of both signs in the bounds: the reductions must fold in a fixed order.
    let mut r = Rng(8);
    inputs.push((
        "signed zeros",
        (0..80_000)
            .map(|i| {
                let z = if i % 2 == 0 { 0.0 } else { -0.0 };
                let p = r.point(1.0);
                bx([z, p[1], z], [p[0], p[1] + 0.1, -z])
            })
            .collect(),
    ));
    for (what, boxes) in &inputs {
        let prints: Vec<Vec<u32>> = [1, 2, 4]
            .into_iter()
            .map(|t| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .expect("thread pool");
                let bvh = pool
                    .install(|| build_binned_sah(boxes, DEFAULT_BINS))
                    .expect("valid input");
                bvh.validate(boxes).expect("valid tree");
                fingerprint(&bvh)
            })
            .collect();
        assert!(prints[0] == prints[1], "{what}: 1 and 2 threads differ");
        assert!(prints[0] == prints[2], "{what}: 1 and 4 threads differ");
    }
}

#[test]
fn bad_input_is_an_error() {
    let ok = vec![bx([0.0; 3], [1.0; 3]); 3];
    for nb in [0, 1, MAX_BINS + 1] {
        assert_eq!(build_binned_sah(&ok, nb), Err(BinnedSahError::BinCount(nb)));
    }
    assert_eq!(
        build_binned_sah(&[], DEFAULT_BINS),
        Err(BinnedSahError::NoPrimitives)
    );
    let mut bad = ok.clone();
    bad.push(bx([0.0, f32::NAN, 0.0], [1.0; 3]));
    bad.push(bx([0.0; 3], [f32::INFINITY, 1.0, 1.0]));
    assert_eq!(
        build_binned_sah(&bad, DEFAULT_BINS),
        Err(BinnedSahError::InvalidBox { index: 3 })
    );
    let inverted = vec![bx([0.0; 3], [1.0; 3]), bx([0.0, 2.0, 0.0], [1.0, 1.0, 1.0])];
    assert_eq!(
        build_binned_sah(&inverted, DEFAULT_BINS),
        Err(BinnedSahError::InvalidBox { index: 1 })
    );
    assert!(build_binned_sah(&[Aabb::EMPTY], DEFAULT_BINS).is_err());
}

#[test]
fn single_primitive_is_a_root_leaf() {
    let b = bx([1.0; 3], [2.0; 3]);
    let (bvh, depth) = build_checked(&[b], DEFAULT_BINS, "single");
    assert_eq!(depth, 0);
    assert!(bvh.nodes[0].is_leaf());
    assert_eq!(bvh.nodes[0].bounds, b);
}

// ---------------------------------------------------------------------------------------------
// The reference table (`lbvh-reference-costs.md`, column "binned SAH", Ct = Ci = 1).

fn check_scene(name: &str, want: f64) {
    let Some(path) = emc_cpu::scene::shared_scene_path(name) else {
        eprintln!("skipping {name}: shared scene not found (set EMC_SHARED_DIR)");
        return;
    };
    let scene =
        emc_cpu::scene::load(&path.to_string_lossy()).unwrap_or_else(|e| panic!("{name}: {e}"));
    let boxes = scene.aabbs();
    let (bvh, depth) = build_checked(&boxes, DEFAULT_BINS, name);
    let sah = sah_headline(&bvh);
    let rel = (sah - want) / want;
    eprintln!(
        "{name}: {} triangles, binned SAH {sah:.2} (table {want:.2}, {:+.2}%), depth {depth}",
        boxes.len(),
        rel * 100.0
    );
    assert!(rel.abs() <= 0.01, "{name}: SAH {sah:.3} vs table {want:.2}");
}

#[test]
fn sah_matches_table_sionna_etoile() {
    check_scene("sionna-etoile", 21.02);
}

#[test]
fn sah_matches_table_sionna_munich() {
    check_scene("sionna-munich", 25.83);
}

#[test]
fn sah_matches_table_torcs_spring() {
    check_scene("torcs-spring", 19.07);
}

#[test]
fn sah_matches_table_spot() {
    check_scene("spot", 25.31);
}

#[test]
fn sah_matches_table_stanford_bunny() {
    check_scene("stanford-bunny", 32.48);
}

#[test]
fn sah_matches_table_sionna_san_francisco() {
    check_scene("sionna-san-francisco", 38.51);
}

#[test]
fn sah_matches_table_pbrt_bathroom() {
    check_scene("pbrt-bathroom", 37.92);
}

#[test]
fn sah_matches_table_stanford_dragon() {
    check_scene("stanford-dragon", 50.34);
}

#[test]
#[ignore = "3.5M triangles; run with --release -- --ignored"]
fn sah_matches_table_pbrt_crown() {
    check_scene("pbrt-crown", 13.65);
}

#[test]
#[ignore = "9.4M triangles; run with --release -- --ignored"]
fn sah_matches_table_san_miguel() {
    check_scene("san-miguel-pbrtv3", 16.65);
}
