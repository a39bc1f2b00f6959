//! The batch pipeline's lane handling against the scalar encoder: boxes the frame never saw
//! (NaN of either sign, infinities, far outside the frame, inverted, diagonals past `D`) in
//! every lane of every step, on every batch length 1..=48 (so lone last groups of four, odd
//! step counts and scalar tails all occur), for every layout of the suite and every encoder
//! variant this CPU runs. The size fix-up of the dispatched AVX-512 pipeline compares `f64`
//! bit patterns as integers; NaN of either sign and `+inf` are where that could go wrong.

use emc_core::{Aabb, Backend, Encoder, Frame, Layout, SizePath};
use emc_tests::{all_layouts, bx, frame_of};
use glam::Vec3;

/// A box with its corners exactly as given (no reordering).
fn raw(min: [f32; 3], max: [f32; 3]) -> Aabb {
    Aabb {
        min: Vec3::from(min),
        max: Vec3::from(max),
    }
}

/// Boxes no frame is built from, plus two ordinary ones.
fn odd_boxes() -> Vec<Aabb> {
    let nan = f32::NAN;
    let neg_nan = f32::from_bits(0xFFC0_0000);
    let inf = f32::INFINITY;
    vec![
        raw([nan, 0.0, 0.0], [1.0, 1.0, 1.0]),
        raw([0.2, 0.2, 0.2], [neg_nan, 0.5, 0.5]),
        raw([neg_nan; 3], [neg_nan; 3]),
        raw([nan; 3], [nan; 3]),
        raw([-inf, 0.0, 0.0], [inf, 0.0, 0.0]),
        raw([0.0; 3], [inf, 1.0, 1.0]),
        raw([-3e38; 3], [3e38; 3]),
        raw([-1e30, 5.0, 5.0], [-1e30, 5.0, 5.0]),
        raw([1e30; 3], [1e30; 3]),
        raw([2.0, 3.0, 1.0], [1.0, 2.0, 0.5]),
        raw([-0.0; 3], [0.0; 3]),
        bx([0.1, 0.2, 0.3], [0.4, 0.5, 0.9]),
        bx([0.0; 3], [1.0; 3]),
    ]
}

/// The dispatched encoder and every forced backend, each with every size path it accepts.
fn variants(layout: &Layout, frame: &Frame) -> Vec<Encoder> {
    let mut base = vec![Encoder::for_layout(*layout, frame)];
    for b in Backend::ALL {
        if let Ok(e) = Encoder::with_backend(*layout, frame, b) {
            base.push(e);
        }
    }
    let mut out = Vec::new();
    for e in base {
        for s in [
            SizePath::Thresholds,
            SizePath::Formula,
            SizePath::Avx512Lookup,
        ] {
            if let Ok(es) = e.clone().with_size_path(s) {
                out.push(es);
            }
        }
        out.push(e);
    }
    out
}

#[test]
fn odd_boxes_in_every_lane_and_batch_length() {
    let frame = frame_of(&[
        bx([0.0; 3], [1.0, 0.5, 0.25]),
        bx([0.5; 3], [2.0, 1.0, 1.5]),
    ]);
    let odd = odd_boxes();
    for (label, layout) in all_layouts() {
        let layout = layout.spec().resolve(frame.extent());
        for enc in variants(&layout, &frame) {
            for len in 1..=48usize {
                // A different rotation per length puts every odd box in every lane.
                let boxes: Vec<Aabb> = (0..len).map(|i| odd[(i + 5 * len) % odd.len()]).collect();
                let mut got = vec![0u64; len];
                enc.encode_batch(&boxes, &mut got).unwrap();
                let mut got32 = vec![0u32; len];
                let fits = enc.encode_batch_u32(&boxes, &mut got32).is_ok();
                for (i, b) in boxes.iter().enumerate() {
                    let want = enc.encode(b);
                    assert_eq!(
                        got[i],
                        want,
                        "{label} [{}]: length {len}, box {i} {b:?}",
                        enc.pipeline()
                    );
                    if fits {
                        assert_eq!(got32[i] as u64, want, "{label}: u32, length {len}, box {i}");
                    }
                }
            }
        }
    }
}
