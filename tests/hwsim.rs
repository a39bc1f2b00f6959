//! Tests of emc-hwsim: the unit's codes against emc-core's encoder (built-in scenes, shared
//! scenes up to 1M triangles, random layouts and hard-case boxes), and the fast timing mode
//! against the cycle-stepped one on small and bandwidth-starved configurations.

use emc_core::glam::Vec3;
use emc_core::{Aabb, Encoder, Frame, LayoutSpec, Quantizer};
use emc_cpu::scene::{load_with, shared_scenes_dir, SceneOptions, SHARED_SCENES};
use emc_hwsim::cost::cost;
use emc_hwsim::{MemoryConfig, Mode, RoutingChoice, SizeSearch, SizeUnit, Unit, UnitOptions};
use emc_tests::{aabb, frame_of, hard_scenes, layout_of, pattern, scene};
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
        emc_hwsim::Network::Fixed {
            morton: Some(21),
            ..
        }
    ));
    // A custom pattern equal to a regular one is wired too; an irregular one is routed.
    for (name, wired) in [
        ("custom:xyzs", true),
        ("custom:zyxzyxzyx", true),
        ("custom:xxyszzxxyz", false),
    ] {
        let spec: LayoutSpec = name.parse().unwrap();
        let u = Unit::for_spec(&spec, &frame, &d).unwrap();
        assert_eq!(
            matches!(u.registers().net, emc_hwsim::Network::Fixed { .. }),
            wired,
            "{name}"
        );
    }
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
        UnitOptions {
            lanes: 4,
            // Credits must cover the codes in flight (Little's law: depth × rate + a burst).
            output_capacity: 128,
            ..d
        },
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

#[test]
fn hard_scenes_are_bit_exact_in_both_modes() {
    for (name, boxes) in hard_scenes() {
        let frame = frame_of(&boxes);
        for spec in all_specs() {
            let layout = spec.resolve(frame.extent());
            let enc = Encoder::for_layout(layout, &frame);
            for opts in option_sets() {
                let unit = Unit::new(&layout, &frame, &opts).unwrap();
                let want: Vec<u64> = boxes.iter().map(|b| enc.encode(b)).collect();
                let f = unit.run(&boxes, &mem(12.8, 100.0), Mode::Fast).unwrap();
                let s = unit.run(&boxes, &mem(12.8, 100.0), Mode::Stepped).unwrap();
                assert_eq!(f.codes, want, "{name} {spec} {opts:?}");
                assert_eq!(s.codes, want, "{name} {spec} {opts:?}");
                assert_eq!(f.stats, s.stats, "{name} {spec} {opts:?}");
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Random custom layouts (channels up to 32 bits, either size transform) on random scenes
    /// of hard-case boxes, probed with boxes inside and outside the frame.
    #[test]
    fn random_layouts_and_boxes_are_bit_exact(
        chans in pattern(),
        linear in any::<bool>(),
        boxes in scene(24),
        probes in prop::collection::vec(aabb(), 0..24),
        lanes in 1u32..4,
        xbar in any::<bool>(),
    ) {
        let frame = frame_of(&boxes);
        let layout = layout_of(&chans, linear);
        let enc = Encoder::for_layout(layout, &frame);
        let opts = UnitOptions {
            lanes,
            routing: if xbar { RoutingChoice::Crossbar } else { RoutingChoice::Benes },
            ..UnitOptions::default()
        };
        let unit = Unit::new(&layout, &frame, &opts).unwrap();
        let all: Vec<Aabb> = boxes.iter().chain(probes.iter()).copied().collect();
        for b in &all {
            prop_assert_eq!(unit.code(b), enc.encode(b));
        }
        let f = unit.run(&all, &mem(6.4, 30.0), Mode::Fast).unwrap();
        let s = unit.run(&all, &mem(6.4, 30.0), Mode::Stepped).unwrap();
        let want: Vec<u64> = all.iter().map(|b| enc.encode(b)).collect();
        prop_assert_eq!(&f.codes, &want);
        prop_assert_eq!(&s.codes, &want);
        prop_assert_eq!(f.stats, s.stats);
    }

    /// Timing only: random buffer sizes, bursts, lanes, II and bandwidths (down to starved).
    #[test]
    fn fast_timing_equals_stepped_on_random_configurations(
        n in 0usize..400,
        lanes in 1u32..5,
        read_burst in 1u32..12,
        extra_in in 0u32..40,
        write_burst_bytes in 8u32..96,
        extra_out in 0u32..20,
        bw in 0.2f64..80.0,
        lat in 0.0f64..300.0,
        iterative in any::<bool>(),
        spec_i in 0usize..4,
    ) {
        let boxes = small_scene(n as u64 + 5, n.max(1));
        let boxes = &boxes[..n];
        let frame = Frame::new(&small_scene(5, 50)).unwrap();
        let spec = [LayoutSpec::Morton63, LayoutSpec::Emc64Var, LayoutSpec::Emc64Sort, LayoutSpec::Emc32Var][spec_i];
        let cb = if spec == LayoutSpec::Emc32Var { 4 } else { 8 };
        let wb = (write_burst_bytes / cb).max(1);
        let opts = UnitOptions {
            lanes,
            read_burst,
            input_capacity: read_burst + extra_in,
            write_burst_bytes,
            output_capacity: wb + extra_out,
            iterative_formula: iterative,
            ..UnitOptions::default()
        };
        let unit = Unit::for_spec(&spec, &frame, &opts).unwrap();
        let m = MemoryConfig { bandwidth_gbps: (bw * 10.0).round() / 10.0, clock_ghz: 1.0, latency_ns: lat.round() };
        let f = unit.run(boxes, &m, Mode::Fast).unwrap();
        let s = unit.run(boxes, &m, Mode::Stepped).unwrap();
        prop_assert_eq!(f.stats, s.stats);
        prop_assert_eq!(f.codes, s.codes);
    }
}

#[test]
fn bad_configurations_are_refused() {
    let boxes = small_scene(3, 10);
    let frame = Frame::new(&boxes).unwrap();
    let d = UnitOptions::default();
    let spec = LayoutSpec::Emc64Var;
    assert!(Unit::for_spec(&spec, &frame, &UnitOptions { lanes: 0, ..d }).is_err());
    let u = Unit::for_spec(
        &spec,
        &frame,
        &UnitOptions {
            input_capacity: 4,
            read_burst: 8,
            ..d
        },
    )
    .unwrap();
    assert!(u.run(&boxes, &MemoryConfig::default(), Mode::Fast).is_err());
    assert!(u
        .run(&boxes, &MemoryConfig::default(), Mode::Stepped)
        .is_err());
    let u = Unit::for_spec(
        &spec,
        &frame,
        &UnitOptions {
            output_capacity: 2,
            ..d
        },
    )
    .unwrap();
    assert!(u.timing(10, &MemoryConfig::default()).is_err());
    let u = Unit::for_spec(&spec, &frame, &d).unwrap();
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(u
            .timing(
                10,
                &MemoryConfig {
                    bandwidth_gbps: bad,
                    ..MemoryConfig::default()
                }
            )
            .is_err());
        assert!(u
            .timing(
                10,
                &MemoryConfig {
                    clock_ghz: bad,
                    ..MemoryConfig::default()
                }
            )
            .is_err());
    }
    assert!(u
        .timing(
            10,
            &MemoryConfig {
                latency_ns: -1.0,
                ..MemoryConfig::default()
            }
        )
        .is_err());
}

#[test]
fn timing_follows_bandwidth_and_lanes() {
    // Compute-bound with ample memory: one code per cycle per lane after the pipeline fills.
    let frame = Frame::new(&small_scene(2, 100)).unwrap();
    let d = UnitOptions::default();
    let unit = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &d).unwrap();
    let n = 20_000u64;
    let fast_mem = MemoryConfig {
        bandwidth_gbps: 10_000.0,
        clock_ghz: 1.0,
        latency_ns: 0.0,
    };
    let s = unit.timing(n, &fast_mem).unwrap();
    assert!(
        s.codes_per_cycle() > 0.99 && s.codes_per_cycle() <= 1.0,
        "{s}"
    );
    // Memory-bound: codes/cycle approaches bandwidth / (24 + 8) bytes per cycle.
    for bw in [12.8, 25.6] {
        let s = unit
            .timing(
                n,
                &MemoryConfig {
                    bandwidth_gbps: bw,
                    ..fast_mem
                },
            )
            .unwrap();
        let bound = bw / 32.0;
        assert!(s.codes_per_cycle() <= bound + 1e-9, "{bw}: {s}");
        assert!(s.codes_per_cycle() > 0.97 * bound, "{bw}: {s}");
        assert!(s.memory_utilisation() > 0.97, "{bw}: {s}");
    }
    // Four lanes at 51.2 GB/s: 1.6 codes/cycle, memory-bound above one lane's 1.0.
    let four = Unit::for_spec(
        &LayoutSpec::Emc64Var,
        &frame,
        &UnitOptions {
            lanes: 4,
            // Credits must cover the codes in flight (Little's law: depth × rate + a burst).
            output_capacity: 128,
            ..d
        },
    )
    .unwrap();
    let s = four
        .timing(
            n,
            &MemoryConfig {
                bandwidth_gbps: 51.2,
                ..fast_mem
            },
        )
        .unwrap();
    assert!(
        s.codes_per_cycle() > 1.5 && s.codes_per_cycle() <= 1.6,
        "{s}"
    );
}

#[test]
fn cost_model_counts_only_instantiated_parts() {
    let frame = Frame::new(&small_scene(2, 100)).unwrap();
    let d = UnitOptions::default();
    let m = cost(&Unit::for_spec(&LayoutSpec::Morton63, &frame, &d).unwrap());
    let v = cost(&Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &d).unwrap());
    let x = cost(
        &Unit::for_spec(
            &LayoutSpec::Emc64Var,
            &frame,
            &UnitOptions {
                routing: RoutingChoice::Crossbar,
                ..d
            },
        )
        .unwrap(),
    );
    let s = cost(&Unit::for_spec(&LayoutSpec::Emc64Sort, &frame, &d).unwrap());
    assert!(m.items.iter().all(|i| !i.name.contains("Beneš")
        && !i.name.contains("size")
        && !i.name.contains("threshold")));
    assert!(v.items.iter().any(|i| i.name.contains("Beneš")));
    assert!(v
        .items
        .iter()
        .any(|i| i.name.contains("threshold registers (63")));
    assert!(m.area_um2() < v.area_um2() && v.area_um2() < x.area_um2());
    assert!(
        v.area_um2() < s.area_um2(),
        "the sqrt/divide path costs more than thresholds"
    );
    assert!(m.latency_cycles < v.latency_cycles && v.latency_cycles < s.latency_cycles);
    assert!(m.energy_pj() < v.energy_pj());
    // Two lanes double the datapath but not the buffers or configuration registers.
    let v2 = cost(
        &Unit::for_spec(
            &LayoutSpec::Emc64Var,
            &frame,
            &UnitOptions { lanes: 2, ..d },
        )
        .unwrap(),
    );
    assert!(v2.area_um2() < 2.0 * v.area_um2() && v2.area_um2() > 1.5 * v.logic_area_um2());
}

/// The built-in scenes at a small size, every standard layout, fast and stepped.
#[test]
fn builtin_scenes_are_bit_exact() {
    for name in emc_cpu::scene::builtin::NAMES {
        let scene = load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(20_000),
        )
        .unwrap();
        let boxes = scene.aabbs();
        let frame = Frame::new(&boxes).unwrap();
        for spec in LayoutSpec::STANDARD {
            let enc = Encoder::new(&spec, &frame);
            for opts in option_sets() {
                let unit = Unit::for_spec(&spec, &frame, &opts).unwrap();
                assert_eq!(
                    mismatches(&unit, &enc, &boxes),
                    0,
                    "builtin:{name} {spec} {opts:?}"
                );
            }
        }
        let unit = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &UnitOptions::default()).unwrap();
        let f = unit
            .run(&boxes[..3000], &mem(12.8, 100.0), Mode::Fast)
            .unwrap();
        let s = unit
            .run(&boxes[..3000], &mem(12.8, 100.0), Mode::Stepped)
            .unwrap();
        assert_eq!(f.stats, s.stats);
        assert_eq!(f.codes, s.codes);
    }
}

/// Every shared scene up to 1M triangles, every standard layout (skips when absent).
#[test]
fn shared_scenes_up_to_1m_are_bit_exact() {
    if shared_scenes_dir().is_none() {
        eprintln!("skipping: the shared scenes directory is absent");
        return;
    }
    for (name, tris) in SHARED_SCENES {
        if tris > 1_000_000 {
            continue;
        }
        let Ok(scene) = load_with(name, &SceneOptions::default()) else {
            eprintln!("skipping shared scene {name}: not present");
            continue;
        };
        let boxes = scene.aabbs();
        let frame = Frame::new(&boxes).unwrap();
        for spec in LayoutSpec::STANDARD {
            let enc = Encoder::new(&spec, &frame);
            let unit = Unit::for_spec(&spec, &frame, &UnitOptions::default()).unwrap();
            assert_eq!(mismatches(&unit, &enc, &boxes), 0, "{name} {spec}");
        }
        eprintln!(
            "{name}: {} triangles bit-exact on every standard layout",
            boxes.len()
        );
    }
}

#[test]
fn stalls_are_attributed_to_their_cause_and_setup_is_costed() {
    let boxes = small_scene(9, 3000);
    let frame = Frame::new(&boxes).unwrap();
    let d = UnitOptions::default();
    // Starved input: low bandwidth, the output FIFO never fills.
    let u = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &d).unwrap();
    let s = u
        .run(&boxes, &mem(6.4, 100.0), Mode::Stepped)
        .unwrap()
        .stats;
    assert!(s.stall_input > 0 && s.stall_output == 0, "{s}");
    // An output FIFO of one burst cannot cover the 22 codes in flight: credit stalls appear.
    let small_out = UnitOptions {
        output_capacity: 8,
        ..d
    };
    let u = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &small_out).unwrap();
    let s = u
        .run(&boxes, &mem(200.0, 10.0), Mode::Stepped)
        .unwrap()
        .stats;
    assert!(s.stall_output > 0, "{s}");
    assert!(s.codes_per_cycle() < 0.5, "{s}");
    // Setup: the bounds pass streams 24 B per AABB at the port's bandwidth.
    let m = mem(12.8, 100.0);
    let c = emc_hwsim::setup::setup_cost(&u, 1_000_000, &m, false).unwrap();
    assert_eq!(c.bounds_cycles, 24_000_000 * 10 / 128 + 100);
    assert_eq!(c.schedule_cycles, 64);
    let c2 = emc_hwsim::setup::setup_cost(&u, 1_000_000, &m, true).unwrap();
    assert_eq!(c2.bounds_cycles, 0);
    let fixed = Unit::for_spec(&LayoutSpec::Morton63, &frame, &d).unwrap();
    let cf = emc_hwsim::setup::setup_cost(&fixed, 10, &m, true).unwrap();
    assert_eq!(
        (
            cf.schedule_cycles,
            cf.host_routing_steps,
            cf.host_threshold_evals
        ),
        (0, 0, 0)
    );
}

/// Boxes spread over the axes in `axes` (the others constant) across `[o, o + len]`, with the
/// two extreme centres present, small boxes and a few boxes outside the frame as probes.
fn swept_scene(axes: [bool; 3], o: f32, len: f32, seed: u64) -> (Vec<Aabb>, Vec<Aabb>) {
    swept_scene_ratio(axes, o, [len; 3], seed)
}

/// [`swept_scene`] with a length per axis.
fn swept_scene_ratio(axes: [bool; 3], o: f32, lens: [f32; 3], seed: u64) -> (Vec<Aabb>, Vec<Aabb>) {
    let len = lens[0].max(lens[1]).max(lens[2]);
    let mut s = seed | 1;
    let mut r = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let at = |t: [f32; 3]| {
        Vec3::new(
            if axes[0] {
                (o + len * t[0]) * (lens[0] / len)
            } else {
                0.25
            },
            if axes[1] {
                (o + len * t[1]) * (lens[1] / len)
            } else {
                -3.0
            },
            if axes[2] {
                (o + len * t[2]) * (lens[2] / len)
            } else {
                7.5
            },
        )
    };
    let mut boxes = vec![Aabb::point(at([0.0; 3])), Aabb::point(at([1.0; 3]))];
    for _ in 0..150 {
        let p = at([r(), r(), r()]);
        let e = Vec3::new(
            if axes[0] {
                lens[0] * r() * r() * 0.01
            } else {
                0.0
            },
            if axes[1] {
                lens[1] * r() * r() * 0.01
            } else {
                0.0
            },
            if axes[2] {
                lens[2] * r() * r() * 0.01
            } else {
                0.0
            },
        );
        boxes.push(Aabb::new(p, p + e));
    }
    let probes = (0..20)
        .map(|_| {
            let p = at([r() * 3.0 - 1.0, r() * 3.0 - 1.0, r() * 3.0 - 1.0]);
            Aabb::new(p, p + Vec3::splat(len * r()))
        })
        .collect();
    (boxes, probes)
}

/// Issue 14 §0: every layout on one-, two- and three-axis scenes whose extents sweep decades
/// (so adaptive layouts give one axis 53–64 bits): schedule, position scales and thresholds
/// come from the unit's firmware, and every code equals emc-core's.
#[test]
fn swept_extents_on_one_two_three_axes_are_bit_exact() {
    let axis_sets = [
        [false, true, false],
        [true, false, false],
        [false, false, true],
        [true, true, false],
        [false, true, true],
        [true, true, true],
    ];
    let mut specs = all_specs();
    specs.push(
        "custom:yyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx"
            .parse()
            .unwrap(),
    );
    let mut widest = [false; 65];
    let mut seed = 1;
    for axes in axis_sets {
        for (exp, ratio) in (-30..=30)
            .step_by(6)
            .flat_map(|e| [(e, 0), (e, 48), (e, 51)])
        {
            for o in [0.1f32, -7.0, 1e3] {
                let len = 10f32.powi(exp) * 0.49;
                // The last active axis shorter by 2^-ratio: two-axis layouts then give the
                // long axis 53 and more bits.
                let mut lens = [len; 3];
                let last = (0..3).rev().find(|&a| axes[a]).unwrap();
                lens[last] = len * 2f32.powi(-ratio);
                seed += 1;
                let (boxes, probes) = swept_scene_ratio(axes, o * 10f32.powi(exp), lens, seed);
                let frame = Frame::new(&boxes).unwrap();
                let all: Vec<Aabb> = boxes.iter().chain(&probes).copied().collect();
                for spec in &specs {
                    let enc = Encoder::new(spec, &frame);
                    let opts = if seed % 2 == 0 {
                        UnitOptions::default()
                    } else {
                        UnitOptions {
                            routing: RoutingChoice::Crossbar,
                            size_search: SizeSearch::Bank,
                            ..UnitOptions::default()
                        }
                    };
                    let unit = Unit::for_spec(spec, &frame, &opts).unwrap();
                    assert_eq!(
                        unit.layout().channels(),
                        enc.layout().channels(),
                        "firmware schedule of {spec} on {:?}",
                        frame.extent()
                    );
                    for b in unit.layout().bit_counts() {
                        widest[b as usize] = true;
                    }
                    let bad = mismatches(&unit, &enc, &all);
                    assert_eq!(bad, 0, "{spec} axes {axes:?} len {len:e} o {o}");
                    for b in all.iter().take(40) {
                        assert_eq!(unit.code(b), enc.encode(b), "{spec} {b:?}");
                    }
                }
            }
        }
    }
    for n in [53, 58, 64] {
        assert!(
            widest[n],
            "the sweep never gave a channel {n} bits: {:?}",
            (0..65).filter(|&i| widest[i]).collect::<Vec<_>>()
        );
    }
}

/// Issue 14 §0, the reported case: two triangles along y from 0.1 to 0.59 give `emc64-var`
/// the layout 0/58/0/6; the unit's max face must reach `2^58 − 1` like emc-core's.
#[test]
fn a_58_bit_channel_reaches_its_maximum() {
    let tri = |y0: f32, y1: f32| {
        Aabb::from_triangle(
            Vec3::new(1.0, y0, 2.0),
            Vec3::new(1.0, y1, 2.0),
            Vec3::new(1.0, y0, 2.0),
        )
    };
    let boxes = [tri(0.1, 0.1), tri(0.59, 0.59), tri(0.2, 0.3)];
    let frame = Frame::new(&boxes).unwrap();
    let unit = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &UnitOptions::default()).unwrap();
    assert_eq!(unit.layout().bit_counts(), [0, 58, 0, 6]);
    let enc = Encoder::new(&LayoutSpec::Emc64Var, &frame);
    for b in &boxes {
        assert_eq!(unit.code(b), enc.encode(b));
    }
    assert_eq!(enc.decode(unit.code(&boxes[1]))[1], (1u64 << 58) - 1);
}

/// Issue 14 §0: the size thresholds are the firmware's own bisection on the unit's formula
/// path; they equal emc-core's table (derived there by emc-core's own formula) bit for bit.
#[test]
fn size_thresholds_are_derived_by_the_unit_and_equal_emc_core() {
    let mut checked = 0;
    for diag_exp in [-35, -12, -3, 0, 1, 7, 20, 36] {
        for axes in [
            [true, true, true],
            [false, true, false],
            [true, false, true],
        ] {
            let len = 10f32.powi(diag_exp);
            let (boxes, _) = swept_scene(axes, 0.3 * len, len, diag_exp as u64 + 99);
            let frame = Frame::new(&boxes).unwrap();
            for spec in all_specs() {
                let layout = spec.resolve(frame.extent());
                let q = Quantizer::new(&layout, &frame);
                let unit = Unit::new(&layout, &frame, &UnitOptions::default()).unwrap();
                match (&unit.registers().size, q.thresholds()) {
                    (SizeUnit::Thresholds { keys, .. }, Some(t)) => {
                        assert_eq!(keys.len(), t.len());
                        for k in 1..t.len() {
                            assert_eq!(
                                keys[k],
                                t[k].to_bits(),
                                "{spec} k={k} D={}",
                                frame.diagonal()
                            );
                        }
                        checked += 1;
                    }
                    (SizeUnit::Thresholds { .. }, None) | (_, Some(_)) => {
                        panic!("{spec}: unit and emc-core disagree on the size path")
                    }
                    _ => {}
                }
            }
        }
    }
    assert!(checked > 50, "{checked}");
}
