//! Exhaustive tests of emc-core (`[[test]] exhaustive`): every backend against the bit-loop
//! reference over every value of every channel, every code of the ≤ 32-bit layouts through
//! decode → encode, and every `f32` on one axis of three frames (monotone, clamped, batch = scalar).
//!
//! Opt-in full `f32` sweep (all 2^32 patterns × 2 boxes × 3 frames; about 30 CPU-minutes,
//! 15 minutes on 2 idle cores):
//!     cargo test --release -p emc-tests --test exhaustive -- --ignored f32_sweep_full

// Axis and channel loops index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

use emc_core::{Aabb, Backend, Channel, Encoder, Expander, Frame, Layout, LayoutSpec};
use emc_tests::{all_layouts, bx, f32_of_rank, fast_expanders, ones, pt, reference};
use rayon::prelude::*;

/// Channels up to this width are swept over all their values for the table/magic backends;
/// wider ones by sliding 8-bit windows.
const FULL_BITS: u32 = 24;
/// The same limit for pdep, which is microcoded (~100 ns per call) on the CI machine (Zen 1):
/// channels up to 21 bits are swept fully, wider ones by sliding 8-bit windows.
const FULL_BITS_PDEP: u32 = 21;

/// Run `f` on every value of `0..n`, on all cores, in chunks of `chunk` consecutive values.
fn par_for(n: u64, chunk: u64, f: impl Fn(u64) + Sync) {
    (0..n.div_ceil(chunk)).into_par_iter().for_each(|c| {
        for v in c * chunk..((c + 1) * chunk).min(n) {
            f(v);
        }
    });
}

/// Check one channel value against every expander: `expand` equals the reference, bits above
/// the channel's width are ignored, and `compact` inverts it.
fn check_value(layout: &Layout, oracle: &Expander, fast: &[Expander], q: [u64; 4]) {
    let want = oracle.expand(q);
    let n = layout.len();
    assert!(
        n == 64 || want >> n == 0,
        "{layout}: code {want:#x} above width"
    );
    assert_eq!(oracle.compact(want), q, "{layout}: reference round trip");
    let bits = layout.bit_counts();
    let mut garbage = q;
    for c in 0..4 {
        garbage[c] |= !ones(bits[c]);
    }
    for e in fast {
        let got = e.expand(q);
        assert_eq!(
            got,
            want,
            "{layout}: {} expand {q:x?}: {got:#x} vs reference {want:#x}",
            e.backend()
        );
        assert_eq!(
            e.expand(garbage),
            want,
            "{layout}: {} expand with bits above widths {garbage:x?}",
            e.backend()
        );
        assert_eq!(
            e.compact(want),
            q,
            "{layout}: {} compact {want:#x}",
            e.backend()
        );
    }
}

/// Sweep channel `c`: every value when it has at most `full` bits, else every 8-bit window
/// `w << shift`; the other channels are 0 and then all ones.
fn sweep_channel(layout: &Layout, oracle: &Expander, fast: &[Expander], c: Channel, full: u32) {
    let bits = layout.bit_counts();
    let b = bits[c.index()];
    if b == 0 {
        return;
    }
    let others_ones = [ones(bits[0]), ones(bits[1]), ones(bits[2]), ones(bits[3])];
    for base in [[0u64; 4], others_ones] {
        let with = |v: u64| {
            let mut q = base;
            q[c.index()] = v;
            q
        };
        if b <= full {
            par_for(1u64 << b, 1 << 12, |v| {
                check_value(layout, oracle, fast, with(v))
            });
        } else {
            (0..=b - 8).into_par_iter().for_each(|shift| {
                for w in 0..256u64 {
                    check_value(layout, oracle, fast, with(w << shift));
                }
            });
        }
    }
}

fn sweep_layouts(pick: impl Fn(&Expander) -> bool, full: u32) -> usize {
    let mut checked = 0;
    for (label, layout) in all_layouts() {
        let oracle = reference(&layout);
        let fast: Vec<Expander> = fast_expanders(&layout).into_iter().filter(&pick).collect();
        if fast.is_empty() {
            continue;
        }
        for c in Channel::ALL {
            sweep_channel(&layout, &oracle, &fast, c, full);
        }
        checked += fast.len();
        eprintln!(
            "checked {} on {label}",
            fast.iter()
                .map(|e| e.backend().name())
                .collect::<Vec<_>>()
                .join("+")
        );
    }
    checked
}

/// Magic (where the pattern is regular) and table against the reference on every channel of
/// every standard layout on every test extent and every custom pattern.
#[test]
fn channels_magic_table_vs_reference() {
    let n = sweep_layouts(
        |e| matches!(e.backend(), Backend::Magic | Backend::Table),
        FULL_BITS,
    );
    // Table serves every layout; magic at least morton30, morton63 and emc64-sort.
    assert!(n >= emc_tests::all_layouts().len() + 3, "only {n} sweeps");
}

/// pdep against the reference (skipped with a message when the CPU lacks BMI2).
#[test]
fn channels_pdep_vs_reference() {
    if !emc_core::cpu::has_bmi2() {
        eprintln!("skipped: no BMI2 on this CPU, the pdep backend does not exist here");
        return;
    }
    let n = sweep_layouts(|e| e.backend() == Backend::Pdep, FULL_BITS_PDEP);
    assert_eq!(n, emc_tests::all_layouts().len());
}

/// The frame whose extents resolve an adaptive layout to the wanted shape: two point boxes.
fn frame_with_extent(e: [f32; 3]) -> Frame {
    Frame::new(&[pt([0.0; 3]), pt(e)]).unwrap()
}

/// Every code of a ≤ 32-bit layout survives decode → expand with the dispatched backend (its
/// batch calls).
fn all_codes_round_trip(spec: LayoutSpec, frame: &Frame) {
    let enc = Encoder::new(&spec, frame);
    let n = enc.layout().len();
    assert!(n <= 32);
    eprintln!(
        "{spec} {} via {}: all 2^{n} codes",
        enc.layout(),
        enc.backend()
    );
    let bits = enc.layout().bit_counts();
    let above = [0, 1, 2, 3].map(|c| !ones(bits[c]));
    const CHUNK: u64 = 1 << 20;
    /// Codes decoded and expanded per batch call.
    const BATCH: usize = 4096;
    (0..(1u64 << n) / CHUNK).into_par_iter().for_each(|ci| {
        // Branch-free inner loop over batches (`decode_batch`, `expand_batch`: the backend's
        // own loop; `layouts.rs` holds them equal to `decode` and `expand` code by code):
        // accumulate, then check once per chunk (and rescan code by code only on failure, to
        // name the first bad code).
        let (mut wide, mut diff) = (0u64, 0u64);
        let mut codes = vec![0u64; BATCH];
        let mut q = vec![[0u64; 4]; BATCH];
        let mut back = vec![0u64; BATCH];
        let mut start = ci * CHUNK;
        while start < (ci + 1) * CHUNK {
            for (k, c) in codes.iter_mut().enumerate() {
                *c = start + k as u64;
            }
            enc.decode_batch(&codes, &mut q).unwrap();
            enc.expand_batch(&q, &mut back).unwrap();
            for ((v, &b), &c) in q.iter().zip(&back).zip(&codes) {
                wide |=
                    (v[0] & above[0]) | (v[1] & above[1]) | (v[2] & above[2]) | (v[3] & above[3]);
                diff |= b ^ c;
            }
            start += BATCH as u64;
        }
        if wide != 0 || diff != 0 {
            for code in ci * CHUNK..(ci + 1) * CHUNK {
                let q = enc.decode(code);
                for c in 0..4 {
                    assert!(q[c] <= ones(bits[c]), "{code:#x}: channel {c} too wide");
                }
                assert_eq!(enc.expand(q), code, "{spec}: decode→encode of {code:#x}");
            }
            panic!("{spec}: a batch of chunk {ci} failed where no single code does");
        }
    });
}

#[test]
fn all_codes_morton30() {
    all_codes_round_trip(LayoutSpec::Morton30, &frame_with_extent([1.0; 3]));
}

#[test]
fn all_codes_emc32_var_cube() {
    let f = frame_with_extent([1.0; 3]);
    assert_eq!(
        LayoutSpec::Emc32Var
            .resolve(f.extent())
            .counts_line()
            .to_string(),
        "10/9/9/4"
    );
    all_codes_round_trip(LayoutSpec::Emc32Var, &f);
}

#[test]
fn all_codes_emc32_var_flat() {
    let f = frame_with_extent([3.0, 1.0, 0.0]);
    let l = LayoutSpec::Emc32Var.resolve(f.extent());
    assert_eq!(l.bits(Channel::Z), 0, "{l}");
    all_codes_round_trip(LayoutSpec::Emc32Var, &f);
}

/// One frame of the `f32` sweep: its boxes, the layout, the swept axis and the fixed point the
/// other two axes sit at.
struct SweepFrame {
    name: &'static str,
    boxes: Vec<Aabb>,
    spec: LayoutSpec,
    axis: usize,
}

fn sweep_frames() -> Vec<SweepFrame> {
    let sub = |b: u32| f32::from_bits(b);
    vec![
        SweepFrame {
            name: "unit cube",
            boxes: vec![bx([0.0; 3], [0.0; 3]), bx([1.0; 3], [1.0; 3])],
            spec: LayoutSpec::Emc64Var,
            axis: 0,
        },
        SweepFrame {
            name: "huge 1e30",
            boxes: vec![
                bx([-1e30, -3e30, 0.0], [1e30, -1e30, 1e29]),
                bx([2e30, 5e30, 1e28], [3e30, 7e30, 2e29]),
            ],
            spec: LayoutSpec::Emc64VarNoSize,
            axis: 1,
        },
        SweepFrame {
            // Centres span subnormals and the smallest normals; z is flat, so x and y share
            // 58 bits (> 24: the low bits are only meaningful because the arithmetic is f64).
            name: "tiny subnormal",
            boxes: vec![
                bx([sub(1), 0.0, 1e-30], [sub(3), sub(5), 1e-30]),
                bx(
                    [sub(0x0090_0000), sub(0x0040_0000), 1e-30],
                    [2e-38, 3e-38, 1e-30],
                ),
            ],
            spec: LayoutSpec::Emc64Var,
            axis: 0,
        },
    ]
}

/// First and last value of a run that must be non-decreasing.
#[derive(Clone, Copy, Default)]
struct Run(Option<(u64, u64)>);

impl Run {
    fn push(&mut self, v: u64, what: impl FnOnce() -> String) {
        self.0 = match self.0 {
            None => Some((v, v)),
            Some((first, last)) => {
                assert!(last <= v, "not monotone: {}", what());
                Some((first, v))
            }
        };
    }
}

/// Check that consecutive chunk runs join monotonically; returns the last value.
fn join(runs: impl Iterator<Item = Run>, name: &str) -> u64 {
    let mut prev = 0;
    for (first, last) in runs.filter_map(|r| r.0) {
        assert!(prev <= first, "{name}: not monotone across chunks");
        prev = last;
    }
    prev
}

/// Walk `f32` ranks `0, stride, 2·stride, …` (value order) on one axis of each sweep frame,
/// with two boxes per value `v`: the point at `v` and the box from 0 to `v` on that axis.
/// Checks: the position value is monotone in `v`, 0 below the frame and for NaN, `2^n − 1` on
/// and above the max face; the size value is monotone in `v ≥ 0` and all ones once `v ≥ D`;
/// the fast quantiser equals the reference formulas; `encode_batch` (the dispatched SIMD
/// pipeline) equals per-box `encode` (scalar); decode gives the quantised values back.
fn f32_sweep(stride: u64) {
    for f in sweep_frames() {
        let frame = Frame::new(&f.boxes).unwrap();
        let enc = Encoder::new(&f.spec, &frame);
        let quant = enc.quantizer();
        let a = f.axis;
        let n = enc.layout().bit_counts()[a];
        let max = ones(n);
        let smax = ones(enc.layout().bits(Channel::S));
        let (lo, hi) = (frame.origin()[a], frame.origin()[a] + frame.extent()[a]);
        let centre = [0, 1, 2].map(|i| (frame.origin()[i] + frame.extent()[i] * 0.5) as f32);
        eprintln!(
            "{}: {} via {} [{}], axis {a} has {n} bits, stride {stride}",
            f.name,
            enc.layout(),
            enc.backend(),
            enc.pipeline()
        );
        assert!(n > 0);
        const CHUNK: u64 = 1 << 16;
        let total = (1u64 << 32).div_ceil(stride);
        let runs: Vec<(Run, Run)> = (0..total.div_ceil(CHUNK))
            .into_par_iter()
            .map(|ci| {
                let ranks: Vec<u32> = (ci * CHUNK..((ci + 1) * CHUNK).min(total))
                    .map(|k| (k * stride) as u32)
                    .collect();
                let mut boxes: Vec<Aabb> = Vec::with_capacity(2 * ranks.len());
                for &r in &ranks {
                    let v = f32_of_rank(r);
                    let mut p = centre;
                    p[a] = v;
                    boxes.push(pt(p));
                    let mut q = centre;
                    q[a] = 0.0;
                    let mut sized = pt(q);
                    if !v.is_nan() {
                        sized.min[a] = v.min(0.0);
                        sized.max[a] = v.max(0.0);
                    }
                    boxes.push(sized);
                }
                let mut batch = vec![0u64; boxes.len()];
                enc.encode_batch(&boxes, &mut batch).unwrap();
                let (mut pos, mut size) = (Run::default(), Run::default());
                for (b, &code) in boxes.iter().zip(&batch) {
                    let q = quant.quantize(b);
                    assert_eq!(q, quant.quantize_reference(b), "{}: {b:?}", f.name);
                    assert_eq!(code, enc.encode(b), "{}: batch != scalar, {b:?}", f.name);
                    assert_eq!(enc.decode(code), q, "{}: decode, {b:?}", f.name);
                    assert!(q[a] <= max && q[3] <= smax, "{}: {q:?} too wide", f.name);
                }
                for (pair, &r) in boxes.chunks(2).zip(&ranks) {
                    let v = f32_of_rank(r);
                    let (qp, qs) = (quant.quantize(&pair[0]), quant.quantize(&pair[1]));
                    if v.is_nan() {
                        assert_eq!(qp[a], 0, "{}: NaN must give 0", f.name);
                        continue;
                    }
                    if (v as f64) <= lo {
                        assert_eq!(qp[a], 0, "{}: {v:e} below the frame", f.name);
                    }
                    if (v as f64) >= hi {
                        assert_eq!(qp[a], max, "{}: {v:e} on/above the max face", f.name);
                    }
                    pos.push(qp[a], || format!("{} position at {v:e}", f.name));
                    if v >= 0.0 {
                        size.push(qs[3], || format!("{} size at {v:e}", f.name));
                        if v as f64 >= frame.diagonal() {
                            assert_eq!(qs[3], smax, "{}: size {v:e} >= D", f.name);
                        }
                    }
                }
                (pos, size)
            })
            .collect();
        let last = join(runs.iter().map(|r| r.0), f.name);
        assert_eq!(last, max, "{}: +inf must reach the max", f.name);
        let last = join(runs.iter().map(|r| r.1), f.name);
        assert_eq!(
            last, smax,
            "{}: the largest size must reach the max",
            f.name
        );
    }
}

/// Every 251st `f32` pattern (a prime stride, so every exponent and many mantissa residues are
/// visited) on each of the three frames. The full sweep is `f32_sweep_full`.
#[test]
fn f32_sweep_strided() {
    f32_sweep(251);
}

/// All 2^32 `f32` patterns on each of the three frames (opt-in, see the file header).
#[test]
#[ignore = "about 15 minutes on 2 cores; run with --ignored f32_sweep_full"]
fn f32_sweep_full() {
    f32_sweep(1);
}
