//! The vectorised batch pipeline against the scalar path: every layout of the suite, every
//! backend and both quantise paths, on the hard-case scenes, random scenes (proptest) and boxes
//! whose squared diagonal sits on and around every size threshold. Also the parallel encoder.

use emc_core::{Aabb, Backend, Encoder, Frame, Layout, QuantizePath, SizePath};
use emc_tests::{all_layouts, bx, frame_of, hard_scenes, layout_of, scene};
use glam::Vec3;
use proptest::prelude::*;

/// Every encoder variant of a layout that this CPU can run: each available backend with each
/// available quantise path.
fn variants(layout: &Layout, frame: &Frame) -> Vec<Encoder> {
    let mut out = Vec::new();
    for b in Backend::ALL {
        let Ok(enc) = Encoder::with_backend(*layout, frame, b) else {
            continue;
        };
        for q in [QuantizePath::Scalar, QuantizePath::Avx2] {
            if let Ok(e) = enc.clone().with_quantize(q) {
                // Every size path of the AVX2 step (each is exact; dispatch picks one per CPU;
                // the AVX-512 lookup only where the CPU has AVX-512).
                for s in [
                    SizePath::Thresholds,
                    SizePath::Formula,
                    SizePath::Avx512Lookup,
                ] {
                    if let Ok(es) = e.clone().with_size_path(s) {
                        // The AVX-512 bit-shuffle expansion too, where the CPU has it.
                        if let Ok(eb) = es.clone().with_bit_shuffle(true) {
                            out.push(eb);
                        }
                        out.push(es);
                    }
                }
                out.push(e);
            }
        }
    }
    out.push(Encoder::for_layout(*layout, frame));
    out
}

/// `encode_batch` (and the `u32` variant) equals `encode` on every box, for every variant.
/// Lengths that are not multiples of four exercise the scalar tail.
fn check(layout: &Layout, frame: &Frame, boxes: &[Aabb], label: &str) -> Result<(), String> {
    for enc in variants(layout, frame) {
        let want: Vec<u64> = boxes.iter().map(|b| enc.encode(b)).collect();
        let mut got = vec![0u64; boxes.len()];
        enc.encode_batch(boxes, &mut got)
            .map_err(|e| e.to_string())?;
        let mut scalar = vec![0u64; boxes.len()];
        enc.encode_batch_scalar(boxes, &mut scalar)
            .map_err(|e| e.to_string())?;
        for i in 0..boxes.len() {
            if got[i] != want[i] || scalar[i] != want[i] {
                return Err(format!(
                    "{label}: {} [{}]: box {i} {:?}: batch {:#x} scalar {:#x} encode {:#x} \
                     (q {:?})",
                    enc.layout(),
                    enc.pipeline(),
                    boxes[i],
                    got[i],
                    scalar[i],
                    want[i],
                    enc.quantizer().quantize(&boxes[i])
                ));
            }
        }
        if layout.fits_u32() {
            let mut got32 = vec![0u32; boxes.len()];
            enc.encode_batch_u32(boxes, &mut got32)
                .map_err(|e| e.to_string())?;
            for i in 0..boxes.len() {
                if got32[i] as u64 != want[i] {
                    return Err(format!("{label}: u32 batch differs at {i}"));
                }
            }
        }
    }
    Ok(())
}

#[test]
fn avx2_path_is_reported_where_available() {
    let frame = Frame::new(&[bx([0.0; 3], [1.0; 3]), bx([2.0; 3], [3.0; 3])]).unwrap();
    let enc = Encoder::new(&"emc64-var".parse().unwrap(), &frame);
    let p = enc.pipeline();
    eprintln!("{p}; expand reason: {}", enc.reason());
    if emc_core::cpu::detect().avx2 {
        assert_eq!(p.quantize, QuantizePath::Avx2);
        let t = enc.clone().with_size_path(SizePath::Thresholds).unwrap();
        assert_eq!(t.pipeline().size, Some(SizePath::Thresholds));
        let f = enc.clone().with_size_path(SizePath::Formula).unwrap();
        assert_eq!(f.pipeline().size, Some(SizePath::Formula));
        // The AVX-512 lookup serves S <= 6 (emc64-var has 6) and is what dispatch picks when
        // the CPU has AVX-512; without it, asking for it is an error.
        let l = enc.clone().with_size_path(SizePath::Avx512Lookup);
        if emc_core::cpu::has_avx512() {
            assert_eq!(l.unwrap().pipeline().size, Some(SizePath::Avx512Lookup));
            assert_eq!(p.size, Some(SizePath::Avx512Lookup));
            // emc64-sort has 16 size bits: the lookup falls back to the formula.
            let sort = Encoder::new(&"emc64-sort".parse().unwrap(), &frame);
            assert_eq!(sort.pipeline().size, Some(SizePath::Formula));
            // Dispatch keeps pdep for the expansion; the bit shuffle is opt-in.
            assert_eq!(p.expand, emc_core::ExpandPath::PdepLanes);
        } else {
            assert!(l.is_err());
        }
        let shuffled = enc.clone().with_bit_shuffle(true);
        if emc_core::cpu::has_avx512_bit_shuffle() {
            let s = shuffled.unwrap();
            assert_eq!(s.pipeline().expand, emc_core::ExpandPath::BitShuffle512);
            let off = s.with_bit_shuffle(false).unwrap();
            assert_eq!(off.pipeline().expand, emc_core::ExpandPath::PdepLanes);
        } else {
            assert!(shuffled.is_err());
        }
    } else {
        eprintln!("no AVX2 here: the SIMD comparisons below only cover the scalar path");
        assert_eq!(p.quantize, QuantizePath::Scalar);
        assert!(enc.clone().with_quantize(QuantizePath::Avx2).is_err());
    }
    // 32-bit channels stay scalar (the i32 truncation covers 31 bits) and say so.
    let wide: Layout = "custom:xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx"
        .parse::<emc_core::LayoutSpec>()
        .unwrap()
        .resolve(frame.extent());
    let enc = Encoder::for_layout(wide, &frame);
    assert_eq!(enc.pipeline().quantize, QuantizePath::Scalar);
    assert!(enc.with_quantize(QuantizePath::Avx2).is_err());
}

#[test]
fn hard_scenes_every_layout_every_path() {
    for (name, boxes) in hard_scenes() {
        let frame = frame_of(&boxes);
        // Probe boxes: the scene's own, its frame corners, points outside, and copies so that
        // every box also lands in a four-lane group; 4k + 3 boxes leave a tail.
        let o = frame.origin();
        let e = frame.extent();
        let mut probe = boxes.clone();
        for t in [-0.5, 0.0, 0.25, 0.5, 1.0, 1.5] {
            let p = Vec3::new(
                (o[0] + e[0] * t) as f32,
                (o[1] + e[1] * t) as f32,
                (o[2] + e[2] * t) as f32,
            );
            probe.push(Aabb::point(p));
            probe.push(Aabb::new(
                p,
                p + Vec3::splat(frame.diagonal() as f32 * 0.01),
            ));
        }
        probe.extend(boxes.iter().copied());
        while probe.len() % 4 != 3 {
            probe.push(boxes[probe.len() % boxes.len()]);
        }
        for (label, layout) in all_layouts() {
            let layout = layout.spec().resolve(frame.extent());
            check(&layout, &frame, &probe, &format!("{name} / {label}")).unwrap();
        }
    }
}

/// Boxes whose squared diagonal is each size threshold and its `f32` neighbours: the fix-up of
/// the size estimate must land on the exact count at every step of every layout with size bits.
#[test]
fn size_thresholds_and_neighbours() {
    let scene = vec![
        bx([0.0; 3], [1.0, 0.5, 0.25]),
        bx([3.0, 1.0, 2.0], [7.0, 2.0, 2.5]),
    ];
    let frame = frame_of(&scene);
    for (label, layout) in all_layouts() {
        let layout = layout.spec().resolve(frame.extent());
        let enc = Encoder::for_layout(layout, &frame);
        let Some(t) = enc.quantizer().thresholds() else {
            continue;
        };
        let mut probe = Vec::new();
        for &tk in &t[1..] {
            // A box along x with dx = sqrt(T) (f32), plus 3 ulps either way, and a box whose
            // diagonal spreads over three axes.
            let base = (tk.sqrt() as f32).to_bits() as i64;
            for d in -3i64..=3 {
                let dx = f32::from_bits((base + d).max(0) as u32);
                probe.push(bx([0.0; 3], [dx, 0.0, 0.0]));
                let s = dx / 3f32.sqrt();
                probe.push(bx([1.0, 1.0, 1.0], [1.0 + s, 1.0 + s, 1.0 + s]));
            }
        }
        probe.push(bx([0.0; 3], [1e30, 1e30, 1e30])); // beyond D: saturates
        probe.push(bx([0.0; 3], [0.0; 3])); // zero size
        check(&layout, &frame, &probe, &label).unwrap();
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Random scenes (hard values included) on every standard layout and random patterns.
    #[test]
    fn random_scenes_batch_equals_scalar(
        boxes in scene(67),
        chans in emc_tests::pattern(),
        linear in any::<bool>(),
    ) {
        let frame = frame_of(&boxes);
        for spec in emc_core::LayoutSpec::STANDARD {
            let layout = spec.resolve(frame.extent());
            check(&layout, &frame, &boxes, &spec.to_string()).map_err(TestCaseError::fail)?;
        }
        let layout = layout_of(&chans, linear);
        check(&layout, &frame, &boxes, "random pattern").map_err(TestCaseError::fail)?;
    }
}

/// The parallel encoder equals the single-thread batch on a scene large enough to split.
#[test]
fn parallel_equals_single_thread() {
    let mut boxes = Vec::new();
    let mut s = 0x9E37_79B9u32;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        s as f32 / u32::MAX as f32
    };
    for _ in 0..200_003 {
        let p = Vec3::new(next(), next(), next()) * 100.0;
        let h = Vec3::new(next(), next(), next()) * 0.5;
        boxes.push(Aabb::new(p - h, p + h));
    }
    let frame = Frame::new(&boxes).unwrap();
    for spec in emc_core::LayoutSpec::STANDARD {
        let enc = Encoder::new(&spec, &frame);
        let mut one = vec![0u64; boxes.len()];
        enc.encode_batch_scalar(&boxes, &mut one).unwrap();
        let mut par = vec![0u64; boxes.len()];
        emc_cpu::encode::encode_parallel(&enc, &boxes, &mut par).unwrap();
        assert!(one == par, "{spec}: parallel differs from single thread");
        if enc.layout().fits_u32() {
            let mut par32 = vec![0u32; boxes.len()];
            emc_cpu::encode::encode_parallel_u32(&enc, &boxes, &mut par32).unwrap();
            assert!(
                one.iter().zip(&par32).all(|(&a, &b)| a == b as u64),
                "{spec}: u32"
            );
        }
        let mut short = vec![0u64; 3];
        assert!(emc_cpu::encode::encode_parallel(&enc, &boxes, &mut short).is_err());
    }
}
