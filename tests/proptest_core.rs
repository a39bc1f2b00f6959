//! Property tests of emc-core (`[[test]] proptest_core`): random valid patterns and random
//! scenes with the hard cases mixed in; all backends agree, decode inverts encode, quantisation
//! is monotone per axis, and the size threshold table equals the size formula.
//!
//! Cases per property default to a CI-friendly count; more with `PROPTEST_CASES=10000 cargo test
//! --release -p emc-tests --test proptest_core`. Failures are persisted in
//! `proptest-regressions/` next to this file and replayed first; commit them.

// Axis and channel loops index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

use emc_core::{Aabb, Backend, Channel, Encoder, Expander, LayoutSpec, Quantizer};
use emc_tests::{
    aabb, fast_expanders, finite_f32, frame_of, layout_of, pattern, pattern_letters, reference,
    scene,
};
use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;

fn config(default_cases: u32) -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default_cases);
    ProptestConfig {
        cases,
        // Next to this file: `proptest_core.proptest-regressions` (the test package has no
        // lib.rs or main.rs for the default lookup to anchor on).
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource(
            "proptest-regressions",
        ))),
        ..ProptestConfig::default()
    }
}

/// A layout name for a scene: a standard one or a custom pattern (and its size transform).
fn spec() -> impl Strategy<Value = LayoutSpec> {
    prop_oneof![
        prop::sample::select(LayoutSpec::STANDARD.to_vec()),
        (pattern(), any::<bool>()).prop_map(|(p, linear)| {
            let name = format!(
                "custom:{}{}",
                pattern_letters(&p),
                if linear { ":linear" } else { "" }
            );
            name.parse().expect("generated patterns are valid")
        }),
    ]
}

/// Every encoder for a spec in a frame: each backend that exists here, forced, and dispatch.
fn encoders(spec: &LayoutSpec, boxes: &[Aabb]) -> Vec<Encoder> {
    let frame = frame_of(boxes);
    let layout = spec.resolve(frame.extent());
    let mut v: Vec<Encoder> = Backend::ALL
        .into_iter()
        .filter_map(|b| Encoder::with_backend(layout, &frame, b).ok())
        .collect();
    v.push(Encoder::new(spec, &frame));
    v
}

proptest! {
    #![proptest_config(config(2048))]

    /// Random patterns: every backend expands like the reference, ignores bits above each
    /// channel's width, and compacts back; the pattern survives its `custom:` name.
    #[test]
    fn backends_agree_on_random_patterns(
        p in pattern(),
        linear in any::<bool>(),
        raw in any::<[u64; 4]>(),
    ) {
        let layout = layout_of(&p, linear);
        let name = format!("custom:{}{}", pattern_letters(&p), if linear { ":linear" } else { "" });
        let spec: LayoutSpec = name.parse().unwrap();
        prop_assert_eq!(spec.to_string(), name);
        let resolved = spec.resolve([1.0, 2.0, 3.0]);
        prop_assert_eq!(resolved.channels(), layout.channels());
        prop_assert_eq!(resolved.transform(), layout.transform());

        let bits = layout.bit_counts();
        let q = [0, 1, 2, 3].map(|c| raw[c] & emc_tests::ones(bits[c]));
        let oracle = reference(&layout);
        let code = oracle.expand(raw);
        prop_assert_eq!(code, oracle.expand(q));
        prop_assert_eq!(oracle.compact(code), q);
        let fast: Vec<Expander> = fast_expanders(&layout);
        prop_assert!(fast.iter().any(|e| e.backend() == Backend::Table));
        for e in &fast {
            prop_assert_eq!(e.expand(raw), code, "{}", e.backend());
            prop_assert_eq!(e.compact(code), q, "{}", e.backend());
            // Bits above the layout width are ignored by decoders.
            if layout.len() < 64 {
                prop_assert_eq!(e.compact(code | (u64::MAX << layout.len())), q);
            }
        }
    }

    /// Random scenes (hard cases mixed in) and layouts: every backend and the batch path give
    /// the same codes, decode gives the quantised values, and the quantiser equals the
    /// reference formulas.
    #[test]
    fn encoders_agree_on_random_scenes(boxes in scene(12), spec in spec()) {
        let encs = encoders(&spec, &boxes);
        let mut want = vec![0u64; boxes.len()];
        for b in &boxes {
            let q = encs[0].quantizer().quantize(b);
            prop_assert_eq!(q, encs[0].quantizer().quantize_reference(b));
        }
        for (i, b) in boxes.iter().enumerate() {
            want[i] = encs[0].encode(b);
        }
        for e in &encs {
            let mut got = vec![0u64; boxes.len()];
            e.encode_batch(&boxes, &mut got).unwrap();
            prop_assert_eq!(&got, &want, "{} {}", e.backend(), e.layout());
            for (b, &code) in boxes.iter().zip(&got) {
                prop_assert_eq!(e.encode(b), code);
                prop_assert_eq!(e.decode(code), e.quantizer().quantize(b), "{}", e.backend());
            }
            if e.layout().fits_u32() {
                let mut narrow = vec![0u32; boxes.len()];
                e.encode_batch_u32(&boxes, &mut narrow).unwrap();
                prop_assert!(narrow.iter().zip(&want).all(|(&n, &w)| u64::from(n) == w));
            }
        }
    }

    /// For every standard layout: moving a box's centre up along one axis never lowers that
    /// axis' value, and growing its diagonal never lowers the size value.
    #[test]
    fn monotone_per_axis_every_standard_layout(
        boxes in scene(8),
        probe in aabb(),
        axis in 0usize..3,
        v in [finite_f32(), finite_f32()],
        grow in 0.0f32..4.0,
    ) {
        let frame = frame_of(&boxes);
        let (lo, hi) = if v[0] <= v[1] { (v[0], v[1]) } else { (v[1], v[0]) };
        let mut a = probe;
        a.min[axis] = lo;
        a.max[axis] = lo;
        let mut b = probe;
        b.min[axis] = hi;
        b.max[axis] = hi;
        let mut big = probe;
        big.max = (probe.max + (probe.max - probe.min) * grow).min(glam::Vec3::splat(f32::MAX));
        for spec in LayoutSpec::STANDARD {
            let layout = spec.resolve(frame.extent());
            let q = Quantizer::new(&layout, &frame);
            prop_assert!(q.quantize(&a)[axis] <= q.quantize(&b)[axis], "{} {}", spec, layout);
            prop_assert!(
                probe.diagonal_sq_f64() <= big.diagonal_sq_f64()
                    && q.quantize(&probe)[3] <= q.quantize(&big)[3],
                "{} size", spec
            );
        }
    }

    /// The threshold table equals the size formula: on random boxes, on every threshold `T_k`
    /// and on both of its f64 neighbours, and each `T_k` is the first `d2` reaching `k`.
    #[test]
    fn size_thresholds_equal_formula(
        boxes in scene(8),
        size_bits in 1usize..=8,
        linear in any::<bool>(),
        probes in prop::collection::vec(aabb(), 1..16),
        d2s in prop::collection::vec(0.0f64..1e6, 1..16),
    ) {
        let frame = frame_of(&boxes);
        // A pattern with `size_bits` size positions among spatial ones.
        let mut p: Vec<Channel> = Vec::new();
        for _ in 0..size_bits {
            p.extend([Channel::X, Channel::Y, Channel::Z, Channel::S]);
        }
        let layout = layout_of(&p, linear);
        let q = Quantizer::new(&layout, &frame);
        let t = q.thresholds().expect("S <= 8 has a table");
        prop_assert_eq!(t.len(), 1 << size_bits);
        for w in t.windows(2) {
            prop_assert!(w[0] <= w[1]);
        }
        for (k, &tk) in t.iter().enumerate().skip(1) {
            let k = k as u64;
            for d2 in [tk, tk.next_down(), tk.next_up()] {
                if d2 >= 0.0 {
                    prop_assert_eq!(q.size_by_thresholds(d2), q.size_from_d2(d2), "k {} d2 {:e}", k, d2);
                }
            }
            if tk.is_finite() {
                prop_assert!(q.size_from_d2(tk) >= k);
                if tk > 0.0 {
                    prop_assert!(q.size_from_d2(tk.next_down()) < k);
                }
            }
        }
        for b in &probes {
            let d2 = b.diagonal_sq_f64();
            prop_assert_eq!(q.size_by_thresholds(d2), q.size_from_d2(d2));
            prop_assert_eq!(q.quantize(b), q.quantize_reference(b));
        }
        let d = frame.diagonal();
        for &x in &d2s {
            // Scaled to the frame so that every size value is hit.
            let d2 = x * 1e-6 * d * d;
            prop_assert_eq!(q.size_by_thresholds(d2), q.size_from_d2(d2), "{:e}", d2);
        }
    }

    /// emc-algorithms.md §3.6: the `emc32-var` code is the top 32 bits of the `emc64-var` code
    /// (their schedules share 32 positions, and power-of-two scales nest the floors and clamps
    /// exactly while no channel is wider than 52 bits).
    #[test]
    fn emc32_is_the_top_of_emc64(boxes in scene(12), probes in prop::collection::vec(aabb(), 1..16)) {
        let frame = frame_of(&boxes);
        let e64 = Encoder::new(&LayoutSpec::Emc64Var, &frame);
        let e32 = Encoder::new(&LayoutSpec::Emc32Var, &frame);
        prop_assume!(e64.layout().bit_counts().iter().all(|&b| b <= 52));
        let all: Vec<Aabb> = boxes.iter().chain(&probes).copied().collect();
        let mut c64 = vec![0u64; all.len()];
        let mut c32 = vec![0u32; all.len()];
        e64.encode_batch(&all, &mut c64).unwrap();
        e32.encode_batch_u32(&all, &mut c32).unwrap();
        for ((b, &w), &n) in all.iter().zip(&c64).zip(&c32) {
            prop_assert_eq!(u64::from(n), w >> 32, "{:?}", b);
            prop_assert_eq!(e32.encode(b), e64.encode(b) >> 32);
        }
    }
}
