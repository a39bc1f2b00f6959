//! Quantisation hard cases (`[[test]] quantize`), for every standard layout: flat scenes, the
//! max face, 1e±30 and subnormal magnitudes, signed zeros, identical primitives, monotonicity,
//! and the errors for non-finite, inverted and empty input and for mismatched output buffers.

// Axis and channel loops index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

use emc_core::{
    Aabb, Backend, Channel, Encoder, Error, Frame, Layout, LayoutSpec, Normalization, SceneBounds,
};
use emc_tests::{bx, hard_scenes, ones, pt};

/// Every standard layout plus two customs (linear and sqrt size), resolved in `frame`.
fn layouts_in(frame: &Frame) -> Vec<Layout> {
    let mut v: Vec<Layout> = LayoutSpec::STANDARD
        .iter()
        .map(|s| s.resolve(frame.extent()))
        .collect();
    for name in ["custom:xyzs", "custom:sszzyyxxsxyz:linear"] {
        v.push(name.parse::<LayoutSpec>().unwrap().resolve(frame.extent()));
    }
    v
}

/// Every encoder that can serve `layout` here, forced, plus the dispatched one.
fn encoders(layout: Layout, frame: &Frame) -> Vec<Encoder> {
    let mut v: Vec<Encoder> = Backend::ALL
        .into_iter()
        .filter_map(|b| Encoder::with_backend(layout, frame, b).ok())
        .collect();
    v.push(Encoder::for_layout(layout, frame));
    v
}

/// The checks every box of every hard scene must pass in every layout: the fast quantiser
/// equals the reference formulas, values are in range, all backends and the batch path agree,
/// and decode gives the quantised values back.
fn check_scene(name: &str, boxes: &[Aabb], frame: &Frame) {
    for layout in layouts_in(frame) {
        let encs = encoders(layout, frame);
        let bits = layout.bit_counts();
        let q0 = encs[0].quantizer();
        let mut batch = vec![0u64; boxes.len()];
        for e in &encs {
            e.encode_batch(boxes, &mut batch).unwrap();
            for (b, &code) in boxes.iter().zip(&batch) {
                let q = q0.quantize(b);
                assert_eq!(q, q0.quantize_reference(b), "{name} {layout}: {b:?}");
                for c in 0..4 {
                    assert!(q[c] <= ones(bits[c]), "{name} {layout}: channel {c} {q:?}");
                }
                assert_eq!(e.encode(b), code, "{name} {layout} {}: batch", e.backend());
                assert_eq!(
                    code,
                    encs[0].encode(b),
                    "{name} {layout}: {} vs {}",
                    e.backend(),
                    encs[0].backend()
                );
                assert_eq!(e.decode(code), q, "{name} {layout} {}", e.backend());
            }
        }
    }
}

#[test]
fn hard_scenes_all_layouts_all_backends() {
    for (name, boxes) in hard_scenes() {
        for n in [
            Normalization::CentroidBox,
            Normalization::PrimitiveBox,
            Normalization::Cube,
        ] {
            let frame = Frame::with_normalization(&boxes, n)
                .unwrap_or_else(|e| panic!("{name}: frame refused: {e}"));
            check_scene(name, &boxes, &frame);
        }
    }
}

/// A zero-extent axis gets no bits in the adaptive layouts and the value 0 in the fixed ones.
#[test]
fn flat_axis_gives_zero_and_no_bits() {
    for a in 0..3 {
        let mut boxes = vec![
            bx([0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
            bx([5.0, 7.0, 9.0], [6.0, 8.0, 9.5]),
            pt([3.0, 1.0, 4.0]),
        ];
        for b in &mut boxes {
            b.min[a] = 2.5;
            b.max[a] = 2.5;
        }
        let frame = Frame::new(&boxes).unwrap();
        assert_eq!(frame.extent()[a], 0.0);
        for spec in LayoutSpec::STANDARD {
            let layout = spec.resolve(frame.extent());
            if matches!(
                spec,
                LayoutSpec::Emc32Var | LayoutSpec::Emc64Var | LayoutSpec::Emc64VarNoSize
            ) {
                assert_eq!(layout.bit_counts()[a], 0, "{spec} {layout}");
            }
            for e in encoders(layout, &frame) {
                for b in &boxes {
                    assert_eq!(e.decode(e.encode(b))[a], 0, "{spec} axis {a}");
                }
                // A point off the plane of a flat axis still gives 0 there (scale 0, no NaN).
                let mut off = boxes[0];
                off.min[a] = 1e30;
                off.max[a] = 1e30;
                assert_eq!(e.quantizer().quantize(&off)[a], 0);
            }
        }
    }
}

/// The primitive whose centre is on the max face of an axis gets `2^n − 1` there (never 0 and
/// never a wrap), and the one on the min face 0, for every layout, every hard scene and every
/// normalisation — including channels wider than the 53-bit f64 mantissa (a line scene gives
/// one axis all 64 bits of `emc64-var-nosize`).
#[test]
fn max_face_gives_all_ones() {
    let mut scenes = hard_scenes();
    scenes.push((
        "line 0..1",
        vec![
            pt([0.0, 0.0, 0.0]),
            pt([1.0, 0.0, 0.0]),
            pt([0.3, 0.0, 0.0]),
        ],
    ));
    scenes.push((
        "line 3..1e7",
        vec![pt([3.0, -2.0, 1.0]), pt([1e7, -2.0, 1.0])],
    ));
    scenes.push((
        "line 0.1..0.7",
        vec![pt([0.0, 0.1, 0.0]), pt([0.0, 0.7, 0.0])],
    ));
    for (name, boxes) in scenes {
        for n in [Normalization::CentroidBox, Normalization::PrimitiveBox] {
            let frame = Frame::with_normalization(&boxes, n).unwrap();
            for layout in layouts_in(&frame) {
                let enc = Encoder::for_layout(layout, &frame);
                let q = enc.quantizer();
                let bits = layout.bit_counts();
                for a in 0..3 {
                    if frame.extent()[a] <= 0.0 || bits[a] == 0 {
                        continue;
                    }
                    let lo = frame.origin()[a];
                    let hi = lo + frame.extent()[a];
                    for b in &boxes {
                        let c = b.center_f64()[a];
                        if c >= hi {
                            assert_eq!(
                                q.quantize(b)[a],
                                ones(bits[a]),
                                "{name} {n} {layout}: axis {a} max face"
                            );
                        }
                        if c <= lo {
                            assert_eq!(q.quantize(b)[a], 0, "{name} {n} {layout}: min face");
                        }
                    }
                }
            }
        }
    }
}

/// -0.0 and +0.0 coordinates give the same code, whether zero is inside the frame or its
/// min face.
#[test]
fn signed_zeros_give_equal_codes() {
    for scene in [
        vec![pt([-1.0, -1.0, -1.0]), pt([1.0, 1.0, 1.0])],
        vec![pt([0.0, 0.0, 0.0]), pt([1.0, 2.0, 3.0])],
        vec![pt([-0.0, -0.0, -0.0]), pt([1.0, 2.0, 3.0])],
    ] {
        let frame = Frame::new(&scene).unwrap();
        let plus = bx([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let minus = bx([-0.0, -0.0, -0.0], [-0.0, -0.0, -0.0]);
        let mixed = bx([-0.0, 0.0, -0.0], [0.0, -0.0, 0.0]);
        for layout in layouts_in(&frame) {
            for e in encoders(layout, &frame) {
                assert_eq!(
                    e.encode(&plus),
                    e.encode(&minus),
                    "{layout} {}",
                    e.backend()
                );
                assert_eq!(
                    e.encode(&plus),
                    e.encode(&mixed),
                    "{layout} {}",
                    e.backend()
                );
            }
        }
    }
    // A frame built from -0.0 alone equals the one from +0.0 where it matters.
    let a = Frame::new(&[pt([-0.0; 3])]).unwrap();
    let b = Frame::new(&[pt([0.0; 3])]).unwrap();
    assert_eq!(a.extent(), b.extent());
    assert_eq!(a.diagonal(), b.diagonal());
}

/// All primitives identical: the frame is accepted, every axis is flat, and every layout
/// gives every primitive the same code (position 0, size the maximum since d = D).
#[test]
fn identical_primitives() {
    for prim in [
        bx([1.0, 2.0, 3.0], [1.5, 2.5, 3.5]),
        pt([7.0, -7.0, 0.0]),
        bx([1e30, -1e30, 1e-30], [2e30, -1e29, 2e-30]),
    ] {
        let boxes = vec![prim; 5];
        let frame = Frame::new(&boxes).unwrap();
        assert_eq!(frame.extent(), [0.0; 3]);
        for layout in layouts_in(&frame) {
            for e in encoders(layout, &frame) {
                let codes: Vec<u64> = boxes.iter().map(|b| e.encode(b)).collect();
                assert!(codes.iter().all(|&c| c == codes[0]), "{layout}");
                let q = e.decode(codes[0]);
                assert_eq!(q[..3], [0, 0, 0], "{layout}");
                let s = layout.bits(Channel::S);
                let want = if prim.min == prim.max { 0 } else { ones(s) };
                assert_eq!(q[3], want, "{layout} {}: size", e.backend());
            }
        }
    }
}

/// Along each axis, a ≤ b ⇒ q(a) ≤ q(b); along the diagonal length, d ≤ d' ⇒ s(d) ≤ s(d'), on
/// dense sweeps through every hard scene's frame and beyond it on both sides.
#[test]
fn monotone_per_axis_and_size() {
    for (name, boxes) in hard_scenes() {
        let frame = Frame::new(&boxes).unwrap();
        for layout in layouts_in(&frame) {
            let enc = Encoder::for_layout(layout, &frame);
            let q = enc.quantizer();
            for a in 0..3 {
                let lo = frame.origin()[a];
                let e = frame.extent()[a].max(1e-30);
                let mut prev = 0;
                for i in -2000..=22000i64 {
                    let v = (lo + e * i as f64 / 20000.0) as f32;
                    let mut p = [0.0f32; 3];
                    p[a] = v;
                    let got = q.quantize(&pt(p))[a];
                    assert!(got >= prev, "{name} {layout}: axis {a} at {v:e}");
                    prev = got;
                }
            }
            let d = frame.diagonal().max(1e-30);
            let mut prev = 0;
            for i in 0..=30000i64 {
                let w = (d * i as f64 / 20000.0) as f32;
                let got = q.quantize(&bx([0.0; 3], [w, 0.0, 0.0]))[3];
                assert!(got >= prev, "{name} {layout}: size at {w:e}");
                prev = got;
            }
        }
    }
}

#[test]
fn non_finite_and_inverted_boxes_are_refused_with_their_index() {
    let good = bx([0.0; 3], [1.0; 3]);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        for axis in 0..3 {
            for corner in 0..2 {
                let mut b = good;
                if corner == 0 {
                    b.min[axis] = bad;
                } else {
                    b.max[axis] = bad;
                }
                for idx in [0usize, 3, 6] {
                    let mut boxes = vec![good; 7];
                    boxes[idx] = b;
                    let err = Frame::new(&boxes).unwrap_err();
                    assert_eq!(err, Error::NonFinite(idx), "{bad} axis {axis}");
                    assert!(err.to_string().contains(&format!("primitive {idx} ")));
                    // The index stays global when bounds are gathered in parts.
                    if idx >= 3 {
                        assert_eq!(SceneBounds::of(&boxes[3..], 3), Err(Error::NonFinite(idx)));
                    }
                }
            }
        }
    }
    for axis in 0..3 {
        let mut inv = good;
        inv.min[axis] = 2.0;
        let boxes = [good, good, inv, good];
        let err = Frame::new(&boxes).unwrap_err();
        assert_eq!(err, Error::InvertedBox(2));
        assert!(err.to_string().contains("primitive 2 "), "{err}");
    }
    // The first bad box is reported.
    let mut nan = good;
    nan.max.y = f32::NAN;
    let mut inv = good;
    inv.min.z = 5.0;
    assert_eq!(Frame::new(&[good, inv, nan]), Err(Error::InvertedBox(1)));
    assert_eq!(Frame::new(&[good, nan, inv]), Err(Error::NonFinite(1)));
}

#[test]
fn empty_scene_is_refused() {
    assert_eq!(Frame::new(&[]), Err(Error::EmptyScene));
    for n in [
        Normalization::CentroidBox,
        Normalization::PrimitiveBox,
        Normalization::Cube,
    ] {
        assert_eq!(
            Frame::from_bounds(SceneBounds::EMPTY, n),
            Err(Error::EmptyScene)
        );
    }
    assert_eq!(Error::EmptyScene.to_string(), "the scene has no primitives");
    // Merged partial bounds equal the bounds of the whole slice.
    let (_, boxes) = hard_scenes().remove(0);
    let a = SceneBounds::of(&boxes[..1], 0).unwrap();
    let b = SceneBounds::of(&boxes[1..], 1).unwrap();
    assert_eq!(a.merge(&b), SceneBounds::of(&boxes, 0).unwrap());
    assert_eq!(
        Frame::from_bounds(a.merge(&b), Normalization::CentroidBox).unwrap(),
        Frame::new(&boxes).unwrap()
    );
}

#[test]
fn batch_buffer_errors() {
    let boxes = [bx([0.0; 3], [1.0; 3]), pt([0.5; 3]), pt([2.0; 3])];
    let frame = Frame::new(&boxes).unwrap();
    for spec in LayoutSpec::STANDARD {
        for e in encoders(spec.resolve(frame.extent()), &frame) {
            let mut short = [0u64; 2];
            assert_eq!(
                e.encode_batch(&boxes, &mut short),
                Err(Error::LengthMismatch(3, 2))
            );
            let mut long = [0u64; 4];
            assert_eq!(
                e.encode_batch(&boxes, &mut long),
                Err(Error::LengthMismatch(3, 4))
            );
            let mut empty: [u64; 0] = [];
            assert_eq!(e.encode_batch(&[], &mut empty), Ok(()));
            let mut u = [0u32; 3];
            if e.layout().len() > 32 {
                let err = e.encode_batch_u32(&boxes, &mut u).unwrap_err();
                assert_eq!(err, Error::CodeTooWide(e.layout().len()));
                assert!(err.to_string().contains(&e.layout().len().to_string()));
                // Width is checked before length.
                assert_eq!(
                    e.encode_batch_u32(&boxes, &mut [0u32; 1]),
                    Err(Error::CodeTooWide(e.layout().len()))
                );
            } else {
                e.encode_batch_u32(&boxes, &mut u).unwrap();
                let mut w = [0u64; 3];
                e.encode_batch(&boxes, &mut w).unwrap();
                assert_eq!(u.map(u64::from), w, "{spec}");
                assert_eq!(
                    e.encode_batch_u32(&boxes, &mut [0u32; 5]),
                    Err(Error::LengthMismatch(3, 5))
                );
            }
        }
    }
    assert_eq!(
        Error::LengthMismatch(3, 2).to_string(),
        "output buffer holds 2 codes but 3 primitives were given"
    );
}
