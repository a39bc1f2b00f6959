//! Tests of emc-hwsim: the unit's codes against emc-core's encoder (built-in scenes, shared
//! scenes up to 1M triangles, random layouts and hard-case boxes), and the fast timing mode
//! against the cycle-stepped one on small and bandwidth-starved configurations.

use emc_core::glam::Vec3;
use emc_core::{Aabb, Encoder, Frame, LayoutSpec, Quantizer};
use emc_hwsim::{MemoryConfig, Mode, RoutingChoice, SizeSearch, SizeUnit, Unit, UnitOptions};
use proptest::prelude::*;

/// Count codes of the unit (fast datapath) that differ from emc-core's encoder.
fn mismatches(unit: &Unit, enc: &Encoder, boxes: &[Aabb]) -> usize {
    let mut codes = Vec::new();
    unit.codes(boxes, &mut codes);
    codes
        .iter()
        .zip(boxes)
        .filter(|(c, b)| **c != enc.encode(b))
        .count()
}

fn all_specs() -> Vec<LayoutSpec> {
    let mut v = LayoutSpec::STANDARD.to_vec();
    for s in [
        "custom:xyzs",
        "custom:sxyz",
        "custom:xxyszzxxyz",
        "custom:xyzsxyzsxyzs:linear",
        "custom:ssssssssssxyz",
        "custom:sssssssssssssssssxyzxyz:linear",
        "custom:zzzzzzzzzzzzzzzzzzzzzzzzzzzzzzzz",
    ] {
        v.push(s.parse().unwrap());
    }
    v
}

fn option_sets() -> Vec<UnitOptions> {
    let d = UnitOptions::default();
    vec![
        d,
        UnitOptions {
            routing: RoutingChoice::Crossbar,
            size_search: SizeSearch::Bank,
            ..d
        },
        UnitOptions {
            routing: RoutingChoice::Benes,
            iterative_formula: true,
            lanes: 3,
            ..d
        },
    ]
}

fn small_scene(seed: u64, n: usize) -> Vec<Aabb> {
    let mut s = seed | 1;
    let mut r = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    (0..n)
        .map(|_| {
            let p = Vec3::new(r() * 100.0, r() * 30.0, r() * 7.0);
            let e = Vec3::new(r(), r(), r()) * (r() * r() * 20.0);
            Aabb::new(p, p + e)
        })
        .collect()
}

#[test]
fn registers_match_the_quantizer() {
    let boxes = small_scene(7, 500);
    let frame = Frame::new(&boxes).unwrap();
    for spec in all_specs() {
        let layout = spec.resolve(frame.extent());
        let q = Quantizer::new(&layout, &frame);
        let unit = Unit::new(&layout, &frame, &UnitOptions::default()).unwrap();
        let r = unit.registers();
        for a in 0..3 {
            if layout.bit_counts()[a] > 0 {
                assert_eq!(r.origin2[a].to_bits(), q.origin2()[a].to_bits());
                assert_eq!(r.half_scale[a].to_bits(), q.half_scale()[a].to_bits());
            }
        }
    }
}

#[test]
fn every_stage_path_agrees_with_emc_core_on_small_scenes() {
    for seed in 1..4 {
        let boxes = small_scene(seed, 2000);
        let frame = Frame::new(&boxes).unwrap();
        for spec in all_specs() {
            let layout = spec.resolve(frame.extent());
            let enc = Encoder::for_layout(layout, &frame);
            for opts in option_sets() {
                let unit = Unit::new(&layout, &frame, &opts).unwrap();
                assert_eq!(mismatches(&unit, &enc, &boxes), 0, "{spec} {opts:?}");
                // The generic per-stage composition equals the specialised loops.
                for b in &boxes[..200] {
                    assert_eq!(unit.code(b), enc.encode(b), "{spec} {opts:?}");
                }
            }
        }
    }
}

#[test]
fn fixed_layouts_use_wires_and_programmable_ones_a_network() {
    let boxes = small_scene(3, 100);
    let frame = Frame::new(&boxes).unwrap();
    let d = UnitOptions::default();
    let m = Unit::for_spec(&LayoutSpec::Morton63, &frame, &d).unwrap();
    assert!(matches!(
        m.registers().net,
        emc_hwsim::Network::Fixed { per_axis: 21 }
    ));
    assert!(matches!(m.registers().size, SizeUnit::None));
    assert!(m
        .stages()
        .iter()
        .all(|s| !s.name.starts_with("route") && !s.name.starts_with("size")));
    let v = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &d).unwrap();
    assert!(matches!(v.registers().net, emc_hwsim::Network::Benes(_)));
    assert!(matches!(
        v.registers().size,
        SizeUnit::Thresholds { bits: 6, .. }
    ));
    assert!(v.depth() > m.depth());
    let s = Unit::for_spec(&LayoutSpec::Emc64Sort, &frame, &d).unwrap();
    assert!(matches!(
        s.registers().size,
        SizeUnit::Formula { bits: 16, .. }
    ));
    // A flat scene: the z lane is not instantiated by the adaptive layout.
    let flat: Vec<Aabb> = boxes
        .iter()
        .map(|b| Aabb::new(b.min.with_z(1.0), b.max.with_z(1.0)))
        .collect();
    let ff = Frame::new(&flat).unwrap();
    let u = Unit::for_spec(&LayoutSpec::Emc64Var, &ff, &d).unwrap();
    assert!(!u.registers().axis_on[2]);
    assert!(format!("{u}").contains("z position lane (0 bits)"));
    assert!(Unit::for_spec(
        &LayoutSpec::Emc64Var,
        &frame,
        &UnitOptions {
            routing: RoutingChoice::Fixed,
            ..d
        }
    )
    .is_err());
}

fn mem(bw: f64, lat: f64) -> MemoryConfig {
    MemoryConfig {
        bandwidth_gbps: bw,
        clock_ghz: 1.0,
        latency_ns: lat,
    }
}

#[test]
fn fast_mode_equals_cycle_stepped_mode() {
    let boxes = small_scene(11, 700);
    let frame = Frame::new(&boxes).unwrap();
    let mems = [
        mem(1000.0, 0.0),
        mem(51.2, 100.0),
        mem(25.6, 100.0),
        mem(12.8, 80.0),
        mem(3.3, 7.0),
        mem(0.7, 250.0),
    ];
    let d = UnitOptions::default();
    let opts = [
        d,
        UnitOptions { lanes: 4, ..d },
        UnitOptions {
            lanes: 2,
            input_capacity: 8,
            output_capacity: 8,
            read_burst: 8,
            write_burst_bytes: 32,
            ..d
        },
        UnitOptions {
            lanes: 3,
            input_capacity: 13,
            output_capacity: 5,
            read_burst: 5,
            write_burst_bytes: 20,
            iterative_formula: true,
            ..d
        },
        UnitOptions {
            input_capacity: 1,
            output_capacity: 1,
            read_burst: 1,
            write_burst_bytes: 1,
            ..d
        },
    ];
    for spec in [
        LayoutSpec::Morton63,
        LayoutSpec::Emc64Var,
        LayoutSpec::Emc64Sort,
        LayoutSpec::Emc32Var,
    ] {
        for o in &opts {
            let unit = Unit::for_spec(&spec, &frame, o).unwrap();
            let enc = Encoder::new(&spec, &frame);
            for m in &mems {
                for n in [0usize, 1, 2, 7, 64, 700] {
                    let b = &boxes[..n];
                    let f = unit.run(b, m, Mode::Fast).unwrap();
                    let s = unit.run(b, m, Mode::Stepped).unwrap();
                    assert_eq!(f.stats, s.stats, "{spec} {o:?} {m:?} n={n}");
                    assert_eq!(f.codes, s.codes);
                    let want: Vec<u64> = b.iter().map(|x| enc.encode(x)).collect();
                    assert_eq!(s.codes, want);
                    let occ = s.occupancy.unwrap();
                    assert_eq!(
                        occ.weighted_sums(),
                        (s.stats.in_fifo_sum, s.stats.out_fifo_sum)
                    );
                    assert_eq!(occ.input.iter().sum::<u64>(), s.stats.cycles);
                }
            }
        }
    }
}
