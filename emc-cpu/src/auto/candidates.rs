//! The candidate layouts of `--layout auto` and of the paper's bit-budget sweep: the named
//! layouts of that width, and patterns generated from the scene's extents and the sizes of its
//! primitives by one rule (size bits where the cells become as small as their threshold).
//! Pure functions of (code length, frame, size statistics): deterministic, no timing.
#![forbid(unsafe_code)]

use std::fmt;

use emc_core::{Aabb, Channel, Frame, LayoutSpec, Pattern, SizeTransform};

/// Most bits any channel of a generated pattern gets (a custom pattern's limit).
pub const CHANNEL_MAX: u32 = 32;

/// Shortest code length the generator makes patterns for.
pub const MIN_BITS: u32 = 8;

/// How a candidate was made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rule {
    /// A named layout (`morton63`, `emc64-var`, …).
    Named,
    /// Size bits by the threshold rule: size bit `k` (of `bits`) goes in front of the first
    /// spatial bit whose cell diagonal is at most `2^shift · τ_k`, where `τ_k = D / 4^k` (sqrt
    /// size) or `D / 2^k` (linear): the size split sits where the cells are as small as the
    /// primitives it separates, `shift` octree levels higher (> 0) or lower (< 0).
    Threshold {
        /// Size bits asked for (fewer are placed when the code ends first).
        bits: u32,
        /// The size transform.
        transform: SizeTransform,
        /// Octree levels (cell diagonal doublings) the size bits move towards the MSB.
        shift: i32,
    },
    /// Only spatial bits, by longest-extent halving.
    NoSize,
}

impl fmt::Display for Rule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Rule::Named => f.write_str("named"),
            Rule::NoSize => f.write_str("halving, no size"),
            Rule::Threshold {
                bits,
                transform,
                shift,
            } => {
                write!(f, "{bits} {transform} size bits at their cells")?;
                match shift {
                    0 => Ok(()),
                    s if s > 0 => write!(f, ", {s} level{} higher", if s > 1 { "s" } else { "" }),
                    s => write!(f, ", {} level{} lower", -s, if s < -1 { "s" } else { "" }),
                }
            }
        }
    }
}

/// One candidate layout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// The layout (named or `custom:…`).
    pub spec: LayoutSpec,
    /// How it was made.
    pub rule: Rule,
    /// A short label for tables (`emc64-var`, `thr-sqrt`, `thr-sqrt-hi`, …).
    pub label: &'static str,
}

/// What the generator needs to know about the primitives' sizes: quantiles of `d / D`
/// (box diagonal over the scene diagonal) over a sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SizeStats {
    /// 10th percentile of `d / D`: the small primitives.
    pub small: f64,
    /// Median of `d / D`.
    pub median: f64,
    /// 99th percentile of `d / D`: the large primitives.
    pub large: f64,
}

impl SizeStats {
    /// Quantiles of `d / D` over `boxes` (`diag` = the scene diagonal `D`).
    pub fn of(boxes: &[Aabb], diag: f64) -> SizeStats {
        let mut d2: Vec<f64> = boxes.iter().map(Aabb::diagonal_sq_f64).collect();
        d2.sort_by(f64::total_cmp);
        SizeStats::from_sorted_d2(&d2, diag)
    }

    /// Quantiles of `d / D` from squared box diagonals sorted ascending. An empty slice or a
    /// zero diagonal gives all ones (every size bit is then placed at once and is constant).
    pub fn from_sorted_d2(d2: &[f64], diag: f64) -> SizeStats {
        if d2.is_empty() || diag <= 0.0 || !diag.is_finite() {
            return SizeStats {
                small: 1.0,
                median: 1.0,
                large: 1.0,
            };
        }
        let q = |p: f64| d2[((d2.len() - 1) as f64 * p).round() as usize].sqrt() / diag;
        SizeStats {
            small: q(0.10),
            median: q(0.5),
            large: q(0.99),
        }
    }

    /// Size bits that reach down to the small primitives: `ceil(log_b(1 / small))` with `b` 4
    /// for the sqrt transform and 2 for the linear one, in `[1, max]`.
    pub fn bits_for(&self, transform: SizeTransform, max: u32) -> u32 {
        let per_bit = match transform {
            SizeTransform::Sqrt => 2.0,
            SizeTransform::Linear => 1.0,
        };
        let s = self.small.max(f64::MIN_POSITIVE);
        let b = (-s.log2() / per_bit).ceil();
        if b.is_finite() {
            (b.max(1.0) as u32).clamp(1, max.max(1))
        } else {
            max.max(1)
        }
    }
}

/// The longest-extent axis among those with fewer than [`CHANNEL_MAX`] bits (ties x > y > z);
/// when every extent is zero, round robin over the axes that still have room.
fn next_axis(e: &[f64; 3], counts: &[u32; 4], step: usize) -> usize {
    let mut best: Option<usize> = None;
    for a in 0..3 {
        if counts[a] >= CHANNEL_MAX {
            continue;
        }
        match best {
            Some(b) if e[a] <= e[b] => {}
            _ => best = Some(a),
        }
    }
    let a = best.unwrap_or(0);
    if e[a] > 0.0 {
        return a;
    }
    (0..3)
        .map(|k| (step + k) % 3)
        .find(|&k| counts[k] < CHANNEL_MAX)
        .unwrap_or(0)
}

/// The channels of a pattern of `len` positions: longest-extent halving of the centroid box
/// (ties x > y > z, no channel above [`CHANNEL_MAX`] bits) with up to `size_bits` size bits,
/// size bit `k` in front of the first spatial bit whose cell diagonal is at most
/// `2^shift · D · r^k` (`r` = 1/4 sqrt, 1/2 linear). `size_bits = 0` gives pure halving.
pub fn threshold_channels(
    frame: &Frame,
    len: u32,
    size_bits: u32,
    transform: SizeTransform,
    shift: i32,
) -> Vec<Channel> {
    let len = len.min(64) as usize;
    let mut e = frame.extent();
    let ratio = match transform {
        SizeTransform::Sqrt => 0.25,
        SizeTransform::Linear => 0.5,
    };
    let diag = frame.diagonal();
    let mut tau = diag * ratio * 2f64.powi(shift);
    let mut counts = [0u32; 4];
    let mut out = Vec::with_capacity(len);
    let mut spatial = 0usize;
    // A spatial bit is always possible while some axis has room (3 · 32 ≥ 64).
    for _ in 0..len {
        let cell = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
        if counts[3] < size_bits.min(CHANNEL_MAX) && cell <= tau {
            out.push(Channel::S);
            counts[3] += 1;
            tau *= ratio;
        } else {
            let a = next_axis(&e, &counts, spatial);
            out.push(Channel::from_index(a));
            counts[a] += 1;
            e[a] *= 0.5;
            spatial += 1;
        }
    }
    out
}

/// A `custom:` spec of the channels (`None` if a channel exceeds the custom limit, which the
/// generator never produces).
pub fn spec_of(chans: &[Channel], transform: SizeTransform) -> Option<LayoutSpec> {
    let s: String = chans.iter().map(|c| c.letter()).collect();
    Pattern::parse(&s, transform).ok().map(LayoutSpec::Custom)
}

/// The named layouts of exactly `len` bits that auto considers at that length.
pub fn named_of_len(len: u32) -> Vec<LayoutSpec> {
    match len {
        64 => vec![
            LayoutSpec::Morton63,
            LayoutSpec::Emc64Sort,
            LayoutSpec::Emc64Var,
            LayoutSpec::Emc64VarNoSize,
        ],
        32 => vec![LayoutSpec::Morton30, LayoutSpec::Emc32Var],
        _ => Vec::new(),
    }
}

/// The generated patterns of `len` bits for a scene (frame + size statistics), by the rules of
/// [`Rule`]: size bits at their cells with the sqrt transform, one level higher, one level
/// lower, half as many, with the linear transform, and (for the sweep's lengths that have no
/// named layout) pure halving.
pub fn generated(frame: &Frame, sizes: &SizeStats, len: u32) -> Vec<Candidate> {
    let len = len.clamp(MIN_BITS, 64);
    let max_size = len / 4;
    let s_sqrt = sizes.bits_for(SizeTransform::Sqrt, max_size);
    let s_lin = sizes.bits_for(SizeTransform::Linear, max_size);
    let rules: [(&'static str, u32, SizeTransform, i32); 5] = [
        ("thr-sqrt", s_sqrt, SizeTransform::Sqrt, 0),
        ("thr-sqrt-hi", s_sqrt, SizeTransform::Sqrt, 1),
        ("thr-sqrt-lo", s_sqrt, SizeTransform::Sqrt, -1),
        ("thr-sqrt-half", s_sqrt.div_ceil(2), SizeTransform::Sqrt, 0),
        ("thr-linear", s_lin, SizeTransform::Linear, 0),
    ];
    let mut out = Vec::new();
    for (label, bits, transform, shift) in rules {
        let chans = threshold_channels(frame, len, bits, transform, shift);
        let placed = chans.iter().filter(|&&c| c == Channel::S).count() as u32;
        if let Some(spec) = spec_of(&chans, transform) {
            out.push(Candidate {
                spec,
                rule: Rule::Threshold {
                    bits: placed,
                    transform,
                    shift,
                },
                label,
            });
        }
    }
    if named_of_len(len).is_empty() {
        let chans = threshold_channels(frame, len, 0, SizeTransform::Sqrt, 0);
        if let Some(spec) = spec_of(&chans, SizeTransform::Sqrt) {
            out.push(Candidate {
                spec,
                rule: Rule::NoSize,
                label: "halving",
            });
        }
    }
    out
}

/// Label of a named layout.
fn named_label(spec: LayoutSpec) -> &'static str {
    match spec {
        LayoutSpec::Morton30 => "morton30",
        LayoutSpec::Morton63 => "morton63",
        LayoutSpec::Emc64Sort => "emc64-sort",
        LayoutSpec::Emc64Var => "emc64-var",
        LayoutSpec::Emc32Var => "emc32-var",
        LayoutSpec::Emc64VarNoSize => "emc64-var-nosize",
        LayoutSpec::Custom(_) => "custom",
    }
}

/// Every candidate of `len` bits (named first), without duplicates: a generated pattern that
/// resolves to the same channels and transform as an earlier candidate is dropped. `len` 64
/// gives the set of `--layout auto`.
pub fn candidates(frame: &Frame, sizes: &SizeStats, len: u32) -> Vec<Candidate> {
    let mut out: Vec<Candidate> = named_of_len(len)
        .into_iter()
        .map(|spec| Candidate {
            spec,
            rule: Rule::Named,
            label: named_label(spec),
        })
        .collect();
    let e = frame.extent();
    let same = |a: &LayoutSpec, b: &LayoutSpec| {
        let (la, lb) = (a.resolve(e), b.resolve(e));
        la.channels() == lb.channels()
            && (la.bits(Channel::S) == 0 || la.transform() == lb.transform())
    };
    for c in generated(frame, sizes, len) {
        if !out.iter().any(|o| same(&o.spec, &c.spec)) {
            out.push(c);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use emc_core::glam::Vec3;

    fn cube_frame() -> Frame {
        let boxes = [
            Aabb::new(Vec3::ZERO, Vec3::splat(0.0)),
            Aabb::new(Vec3::splat(1.0), Vec3::splat(1.0)),
        ];
        Frame::new(&boxes).unwrap()
    }

    #[test]
    fn threshold_rule_reproduces_the_named_emc_layouts_in_a_cube() {
        let f = cube_frame();
        // sqrt, 6 size bits: the size bits land every 7th position like emc64-var.
        let c = threshold_channels(&f, 64, 6, SizeTransform::Sqrt, 0);
        let var = LayoutSpec::Emc64Var.resolve(f.extent());
        assert_eq!(c.as_slice(), var.channels());
        // linear, 16 size bits: (xyzs)^16 like emc64-sort.
        let c = threshold_channels(&f, 64, 16, SizeTransform::Linear, 0);
        let sort = LayoutSpec::Emc64Sort.resolve(f.extent());
        assert_eq!(c.as_slice(), sort.channels());
        // No size bits: the halving schedule.
        let c = threshold_channels(&f, 64, 0, SizeTransform::Sqrt, 0);
        let nosize = LayoutSpec::Emc64VarNoSize.resolve(f.extent());
        assert_eq!(c.as_slice(), nosize.channels());
    }

    #[test]
    fn shifts_move_size_bits_by_octree_levels() {
        let f = cube_frame();
        let pos = |shift| {
            threshold_channels(&f, 64, 6, SizeTransform::Sqrt, shift)
                .iter()
                .position(|&c| c == Channel::S)
                .unwrap()
        };
        assert_eq!(pos(0), 6);
        assert_eq!(pos(1), 3);
        assert_eq!(pos(-1), 9);
    }

    #[test]
    fn flat_and_degenerate_frames_keep_channels_within_limits() {
        // A line along x: all spatial bits would go to x; the cap sends the rest elsewhere.
        let line = [
            Aabb::new(Vec3::ZERO, Vec3::ZERO),
            Aabb::new(Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0)),
        ];
        let f = Frame::new(&line).unwrap();
        let sizes = SizeStats::of(&line, f.diagonal());
        for len in [24, 32, 48, 64] {
            for c in generated(&f, &sizes, len) {
                let l = c.spec.resolve(f.extent());
                assert_eq!(l.len(), len);
                assert!(
                    l.bit_counts().iter().all(|&b| b <= CHANNEL_MAX),
                    "{}",
                    c.spec
                );
            }
        }
        // A point: every extent zero.
        let point = [Aabb::new(Vec3::ONE, Vec3::ONE)];
        let f = Frame::new(&point).unwrap();
        let sizes = SizeStats::of(&point, f.diagonal());
        assert!(!candidates(&f, &sizes, 64).is_empty());
    }

    #[test]
    fn size_bits_follow_the_small_primitives() {
        let s = SizeStats {
            small: 1.0 / 4096.0,
            median: 0.01,
            large: 0.5,
        };
        assert_eq!(s.bits_for(SizeTransform::Sqrt, 16), 6);
        assert_eq!(s.bits_for(SizeTransform::Linear, 16), 12);
        assert_eq!(s.bits_for(SizeTransform::Linear, 8), 8);
    }
}
