//! Golden vectors of the EMC definition (emc-algorithms.md §2.6 and §3.6), and the layout
//! schedules of §3.6's worked table: hand-checked values that every backend must reproduce.

use emc_core::{Aabb, Backend, Encoder, Frame, LayoutSpec, Normalization};
use glam::Vec3;

fn b(lo: [f32; 3], hi: [f32; 3]) -> Aabb {
    Aabb::new(Vec3::from(lo), Vec3::from(hi))
}

fn all_encoders(spec: LayoutSpec, frame: &Frame) -> Vec<Encoder> {
    let layout = spec.resolve(frame.extent());
    let mut v: Vec<Encoder> = Backend::ALL
        .into_iter()
        .filter_map(|be| Encoder::with_backend(layout, frame, be).ok())
        .collect();
    v.push(Encoder::new(&spec, frame));
    v
}

#[test]
fn morton_vectors_2_6() {
    let unit = b([0.0; 3], [1.0; 3]);
    let p1 = [0.5f32, 0.25, 0.75];
    let p2 = [0.1f32, 0.7, 0.3];
    let boxes = [unit, b(p1, p1), b(p2, p2)];
    let frame = Frame::with_normalization(&boxes, Normalization::PrimitiveBox).unwrap();
    for e in all_encoders(LayoutSpec::Morton30, &frame) {
        assert_eq!(e.quantizer().quantize(&boxes[1])[..3], [512, 256, 768]);
        assert_eq!(e.encode(&boxes[1]), 0x2B00_0000, "{}", e.backend());
        assert_eq!(e.quantizer().quantize(&boxes[2])[..3], [102, 716, 307]);
        assert_eq!(e.encode(&boxes[2]), 0x115A_95A9, "{}", e.backend());
    }
    for e in all_encoders(LayoutSpec::Morton63, &frame) {
        assert_eq!(
            e.quantizer().quantize(&boxes[1])[..3],
            [1048576, 524288, 1572864]
        );
        assert_eq!(
            e.encode(&boxes[1]),
            0x5600_0000_0000_0000,
            "{}",
            e.backend()
        );
        assert_eq!(
            e.quantizer().quantize(&boxes[2])[..3],
            [209715, 1468006, 629145]
        );
        assert_eq!(
            e.encode(&boxes[2]),
            0x22B5_2B52_B52B_52B5,
            "{}",
            e.backend()
        );
    }
}

#[test]
fn emc_vectors_3_6() {
    // Mesh box [0,0,0]-[4,4,1] for positions and size (D = sqrt 33).
    let scene = b([0.0; 3], [4.0, 4.0, 1.0]);
    let prims = [
        b([1.0, 1.0, 0.2], [1.2, 1.1, 0.3]),
        b([0.0, 0.0, 0.0], [4.0, 4.0, 0.5]),
        b([2.5, 0.5, 0.5], [3.5, 1.5, 0.9]),
    ];
    let mut boxes = vec![scene];
    boxes.extend_from_slice(&prims);
    let frame = Frame::with_normalization(&boxes, Normalization::PrimitiveBox).unwrap();
    assert!((frame.diagonal() - 33f64.sqrt()).abs() < 1e-12);
    let want64: [(u64, [u64; 4]); 3] = [
        (0x3021_3914_C453_2132, [288358, 275251, 65536, 13]),
        (0xC224_0810_2040_0000, [524288, 524288, 65536, 63]),
        (0xB302_4009_0024_0240, [786432, 262144, 183500, 32]),
    ];
    let want32 = [0x3021_3914u64, 0xC224_0810, 0xB302_4009];
    let want30 = [0x0C11_3213u64, 0x3010_0000, 0x2C82_4024];
    let l64 = LayoutSpec::Emc64Var.resolve(frame.extent());
    assert_eq!(l64.counts_line().to_string(), "20/20/18/6");
    for e in all_encoders(LayoutSpec::Emc64Var, &frame) {
        for (p, (code, q)) in prims.iter().zip(want64) {
            assert_eq!(e.quantizer().quantize(p), q);
            assert_eq!(e.encode(p), code, "{} {}", e.backend(), e.layout());
            assert_eq!(e.decode(code), q);
        }
    }
    for e in all_encoders(LayoutSpec::Emc32Var, &frame) {
        for (p, code) in prims.iter().zip(want32) {
            assert_eq!(e.encode(p), code, "{} {}", e.backend(), e.layout());
        }
    }
    // EMC-30 without size: 30 spatial bits by halving.
    let mut sched = [emc_core::Channel::X; 30];
    emc_core::layout::halving_schedule(frame.extent(), 30, &mut sched);
    let l30 = emc_core::Layout::from_channels(&sched, emc_core::SizeTransform::Sqrt).unwrap();
    assert_eq!(l30.counts_line().to_string(), "11/11/8/0");
    for be in Backend::ALL {
        let Ok(e) = Encoder::with_backend(l30, &frame, be) else {
            continue;
        };
        for (p, code) in prims.iter().zip(want30) {
            assert_eq!(e.encode(p), code, "{} {}", e.backend(), e.layout());
        }
    }
}

#[test]
fn worked_schedules_3_6() {
    let cases: [([f64; 3], LayoutSpec, &str); 5] = [
        ([1.0; 3], LayoutSpec::Emc64Var, "20/19/19/6"),
        ([1.0; 3], LayoutSpec::Emc32Var, "10/9/9/4"),
        ([4.0, 4.0, 1.0], LayoutSpec::Emc64Var, "20/20/18/6"),
        ([16.0, 1.0, 1.0], LayoutSpec::Emc64Var, "22/18/18/6"),
        ([100.0, 10.0, 1.0], LayoutSpec::Emc64Var, "23/19/16/6"),
    ];
    for (e, spec, counts) in cases {
        assert_eq!(spec.resolve(e).counts_line().to_string(), counts, "{e:?}");
    }
    let cube = LayoutSpec::Emc64Var.resolve([1.0; 3]);
    assert_eq!(
        cube.pattern_str().to_string(),
        "xyzxyzsxyzxyzsxyzxyzsxyzxyzsxyzxyzsxyzxyzsxyzxyzxyzxyzxyzxyzxyzx"
    );
    let p = LayoutSpec::Emc64Var
        .resolve([16.0, 1.0, 1.0])
        .pattern_str()
        .to_string();
    assert!(p.starts_with("xxxxxyszxyzxys"), "{p}");
    let p = LayoutSpec::Emc64Var
        .resolve([100.0, 10.0, 1.0])
        .pattern_str()
        .to_string();
    assert!(p.starts_with("xxxxyxsyxyxyzsxyzxyzs"), "{p}");
    let p = LayoutSpec::Emc64Var
        .resolve([4.0, 4.0, 1.0])
        .pattern_str()
        .to_string();
    assert!(p.starts_with("xyxyxyszxyzxyszxyzxys"), "{p}");
    // A cube without size bits is the standard Morton code.
    let m = LayoutSpec::Emc64VarNoSize.resolve([1.0; 3]);
    assert_eq!(m.pattern_str().to_string()[..63], "xyz".repeat(21));
    assert_eq!(
        LayoutSpec::Emc64Sort
            .resolve([1.0, 3.0, 2.0])
            .pattern_str()
            .to_string(),
        "yzxs".repeat(16)
    );
    assert_eq!(
        LayoutSpec::Morton30.resolve([1.0; 3]).to_string(),
        format!("10/10/10/0 {}", "xyz".repeat(10))
    );
}
