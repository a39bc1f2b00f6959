//! `--layout auto`: the code layout chosen per scene. A [`LayoutChoice`] is what builds take
//! (a fixed [`LayoutSpec`] or `auto`); `auto` resolves, once the scene's boxes and frame are
//! known, to the candidate ([`candidates`]) whose LBVH over a size-stratified sample of the
//! primitives has the least inner-node area ([`estimate`](mod@estimate); candidates it ties
//! are told apart by the deep levels of dense windows), with the reason printed by the CLI.
//! emc-core's `LayoutSpec` stays a name over extents only; everything here needs the boxes.
//! (Only [`scan`], the pass's SIMD kernel, has `unsafe`.)
#![deny(unsafe_code)]

pub mod candidates;
pub mod estimate;
#[cfg(feature = "cli")]
pub mod report;
#[allow(unsafe_code)]
pub mod scan;

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use emc_core::{Aabb, Frame, LayoutSpec};
use rayon::prelude::*;

use candidates::{Candidate, Rule};
use estimate::{estimate, estimate_backend, estimate_windows, Estimate, Sample, Scratch};

/// Candidates whose estimated SAH is within this many percent of the best estimate count as
/// tied with it, and the tie goes to the reference, then to the named layouts: smaller
/// differences between sampled trees are not evidence (on the validation scenes they went
/// either way in the full builds, by up to 1%).
pub const KEEP_MARGIN_PCT: f64 = 0.5;

/// Code bits of plain `auto`.
pub const AUTO_BITS: u32 = 64;

/// The layout a build uses: a fixed one, or the one `auto` picks for the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LayoutChoice {
    /// This layout (`morton63`, `emc64-var`, `custom:…`).
    Fixed(LayoutSpec),
    /// The best of the candidates of `bits` code bits by the sampled estimate: `auto` (64 bits:
    /// `morton63`, `emc64-sort`, `emc64-var`, `emc64-var-nosize` and the generated patterns)
    /// or `auto:N` (`N` in 8..=64: the generated patterns of that length, plus `morton30` and
    /// `emc32-var` for 32).
    Auto {
        /// Code length of the candidates.
        bits: u32,
    },
}

/// `auto`: the 64-bit candidates.
pub const AUTO: LayoutChoice = LayoutChoice::Auto { bits: AUTO_BITS };

impl From<LayoutSpec> for LayoutChoice {
    fn from(s: LayoutSpec) -> LayoutChoice {
        LayoutChoice::Fixed(s)
    }
}

impl Default for LayoutChoice {
    /// `emc64-var`.
    fn default() -> LayoutChoice {
        LayoutChoice::Fixed(LayoutSpec::Emc64Var)
    }
}

impl fmt::Display for LayoutChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LayoutChoice::Fixed(s) => write!(f, "{s}"),
            LayoutChoice::Auto { bits: AUTO_BITS } => f.write_str("auto"),
            LayoutChoice::Auto { bits } => write!(f, "auto:{bits}"),
        }
    }
}

/// Why a layout option or an automatic choice failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AutoError {
    /// `auto:N` with `N` outside 8..=64 or not a number.
    #[error(
        "`{0}`: auto takes a code length of {min} to 64 bits (auto:N)",
        min = candidates::MIN_BITS
    )]
    BadBits(String),
    /// Neither `auto` nor a layout name.
    #[error("`{name}`: {msg} (or auto, auto:N)")]
    BadLayout {
        /// The text given.
        name: String,
        /// emc-core's message.
        msg: String,
    },
    /// No primitives to choose for.
    #[error("no primitives to choose a layout for")]
    Empty,
    /// The sample's sort refused its input.
    #[error(transparent)]
    Sort(#[from] crate::sort::SortError),
}

impl FromStr for LayoutChoice {
    type Err = AutoError;
    /// `auto`, `auto:N`, or any layout name emc-core parses.
    fn from_str(s: &str) -> Result<Self, AutoError> {
        if s == "auto" {
            return Ok(AUTO);
        }
        if let Some(b) = s.strip_prefix("auto:") {
            return match b.parse::<u32>() {
                Ok(bits) if (candidates::MIN_BITS..=64).contains(&bits) => {
                    Ok(LayoutChoice::Auto { bits })
                }
                _ => Err(AutoError::BadBits(s.to_string())),
            };
        }
        s.parse::<LayoutSpec>()
            .map(LayoutChoice::Fixed)
            .map_err(|e| AutoError::BadLayout {
                name: s.to_string(),
                msg: e.to_string(),
            })
    }
}

impl LayoutChoice {
    /// The fixed layout, if this is one.
    pub fn fixed(&self) -> Option<LayoutSpec> {
        match self {
            LayoutChoice::Fixed(s) => Some(*s),
            LayoutChoice::Auto { .. } => None,
        }
    }

    /// True for `auto` and `auto:N`.
    pub fn is_auto(&self) -> bool {
        matches!(self, LayoutChoice::Auto { .. })
    }

    /// The layout for these boxes in this frame: the fixed one, or [`choose`]'s pick (with the
    /// choice). Runs on the current rayon pool.
    pub fn resolve(
        &self,
        boxes: &[Aabb],
        frame: &Frame,
    ) -> Result<(LayoutSpec, Option<AutoChoice>), AutoError> {
        match *self {
            LayoutChoice::Fixed(s) => Ok((s, None)),
            LayoutChoice::Auto { bits } => {
                let c = choose(boxes, frame, bits)?;
                Ok((c.spec(), Some(c)))
            }
        }
    }
}

/// One candidate with its estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scored {
    /// The candidate.
    pub candidate: Candidate,
    /// Its estimate over the sample.
    pub estimate: Estimate,
}

/// What `auto` chose for a scene, and from what.
#[derive(Clone, Debug, PartialEq)]
pub struct AutoChoice {
    /// Code length of the candidates.
    pub bits: u32,
    /// Every candidate in order (named first), with its estimate.
    pub scored: Vec<Scored>,
    /// Index of the pick in `scored`.
    pub chosen: usize,
    /// Index of the reference the changes are given against (`emc64-var`, `emc32-var`, or the
    /// first generated pattern at other lengths).
    pub reference: usize,
    /// Triangles of the scene.
    pub prims: usize,
    /// Sample triangles from the uniform strata.
    pub uniform: usize,
    /// Sample triangles taken for being among the largest.
    pub large: usize,
    /// Boxes in the dense windows (0 when the sample tree alone decided).
    pub window_boxes: usize,
    /// Wall milliseconds of the choice (sample pass and every candidate's estimate).
    pub wall_ms: f64,
}

impl AutoChoice {
    /// The chosen layout.
    pub fn spec(&self) -> LayoutSpec {
        self.scored[self.chosen].candidate.spec
    }

    /// The chosen candidate.
    pub fn candidate(&self) -> &Candidate {
        &self.scored[self.chosen].candidate
    }

    /// Estimated headline SAH change of candidate `i` against the reference, in percent.
    pub fn change_pct(&self, i: usize) -> f64 {
        let r = self.scored[self.reference].estimate.sah();
        let c = self.scored[i].estimate.sah();
        if r > 0.0 && r.is_finite() {
            (c / r - 1.0) * 100.0
        } else {
            0.0
        }
    }

    /// Name of candidate `i` as the tables print it: the label, and for a generated pattern
    /// also the pattern.
    pub fn name(&self, i: usize) -> String {
        let c = &self.scored[i].candidate;
        match c.rule {
            Rule::Named => c.label.to_string(),
            _ => format!("{} ({})", c.label, c.spec),
        }
    }

    /// The candidates the dense windows were measured for (those the sample tree tied).
    pub fn tied(&self) -> Vec<usize> {
        (0..self.scored.len())
            .filter(|&i| self.scored[i].estimate.dense_sah().is_some())
            .collect()
    }

    /// Estimated SAH change with the deep levels of candidate `i` against the best tied
    /// candidate's (the least estimate with the deep levels), in percent; `None` for a
    /// candidate the windows were not measured for.
    pub fn dense_change_pct(&self, i: usize) -> Option<f64> {
        let c = self.scored[i].estimate.dense_sah()?;
        let best = self
            .tied()
            .iter()
            .filter_map(|&j| self.scored[j].estimate.dense_sah())
            .fold(f64::INFINITY, f64::min);
        Some(if best > 0.0 && best.is_finite() {
            (c / best - 1.0) * 100.0
        } else {
            0.0
        })
    }

    /// The decision in one line: the pick, its estimated change against the reference, the
    /// runners-up, and the sample it rests on.
    pub fn reason(&self) -> String {
        let pick = &self.scored[self.chosen].candidate;
        let mut order: Vec<usize> = (0..self.scored.len()).collect();
        order.sort_by(|&a, &b| {
            self.scored[a]
                .estimate
                .sah()
                .total_cmp(&self.scored[b].estimate.sah())
                .then(a.cmp(&b))
        });
        let next: Vec<String> = order
            .iter()
            .filter(|&&i| i != self.chosen)
            .take(3)
            .map(|&i| {
                format!(
                    "{} {:+.2}%",
                    self.scored[i].candidate.label,
                    self.change_pct(i)
                )
            })
            .collect();
        let vs = if self.chosen == self.reference {
            format!("the reference (no candidate {KEEP_MARGIN_PCT}% or more below it)")
        } else {
            format!(
                "{:+.2}% against {}",
                self.change_pct(self.chosen),
                self.scored[self.reference].candidate.label
            )
        };
        let sample = if self.uniform >= self.prims {
            format!("all {} triangles (exact)", self.prims)
        } else {
            format!(
                "{} uniform + {} largest of {} triangles",
                self.uniform, self.large, self.prims
            )
        };
        let tied = self.tied();
        let dense = if tied.is_empty() {
            String::new()
        } else {
            let mut t = tied.clone();
            t.sort_by(|&a, &b| {
                let (x, y) = (
                    self.dense_change_pct(a).unwrap_or(0.0),
                    self.dense_change_pct(b).unwrap_or(0.0),
                );
                x.total_cmp(&y).then(a.cmp(&b))
            });
            let list: Vec<String> = t
                .iter()
                .map(|&i| {
                    format!(
                        "{} {:+.2}%",
                        self.scored[i].candidate.label,
                        self.dense_change_pct(i).unwrap_or(0.0)
                    )
                })
                .collect();
            format!(
                "; {} tied within {KEEP_MARGIN_PCT}%, decided with the deep levels of {} \
                 dense-window boxes: {}",
                tied.len(),
                self.window_boxes,
                list.join(", ")
            )
        };
        format!(
            "{} [{}]: by the estimated SAH of the sampled LBVHs, {vs}; next {}{dense}; {} \
             candidates over {sample}, {:.2} ms",
            pick.label,
            pick.rule,
            next.join(", "),
            self.scored.len(),
            self.wall_ms
        )
    }
}

/// Choose the layout of `bits` code bits for `boxes` (the frame's boxes), in two stages.
/// First the sample tree: every candidate's estimate over the sample (in parallel on the
/// current rayon pool, each candidate's sum on one thread in a fixed order); the candidates
/// within [`KEEP_MARGIN_PCT`] of the least estimate are tied. One of them alone is the pick.
/// Several: the sample could not tell them apart, so the dense windows are drawn and each tied
/// candidate's estimate gains the deep levels ([`Estimate::dense_sah`]); the least of those
/// wins, and again within the margin the tie goes to the reference, then the named layouts,
/// then the earliest generated one. Deterministic: any thread count gives the same choice.
pub fn choose(boxes: &[Aabb], frame: &Frame, bits: u32) -> Result<AutoChoice, AutoError> {
    if boxes.is_empty() {
        return Err(AutoError::Empty);
    }
    if !(candidates::MIN_BITS..=64).contains(&bits) {
        return Err(AutoError::BadBits(format!("auto:{bits}")));
    }
    let t0 = Instant::now();
    let sample = Sample::draw(boxes, frame);
    let cands = candidates::candidates(frame, &sample.size_stats, bits);
    let backend = estimate_backend();
    let e = frame.extent();
    let est: Vec<Result<Estimate, crate::sort::SortError>> = cands
        .par_iter()
        .map_init(Scratch::default, |s, c| {
            estimate(&sample, &c.spec.resolve(e), frame, backend, s)
        })
        .collect();
    let mut scored = Vec::with_capacity(cands.len());
    for (c, a) in cands.iter().zip(est) {
        scored.push(Scored {
            candidate: *c,
            estimate: a?,
        });
    }
    let reference = scored
        .iter()
        .position(|s| {
            matches!(
                s.candidate.spec,
                LayoutSpec::Emc64Var | LayoutSpec::Emc32Var
            )
        })
        .or_else(|| scored.iter().position(|s| s.candidate.rule != Rule::Named))
        .unwrap_or(0);
    let sah1: Vec<f64> = scored.iter().map(|s| s.estimate.sah()).collect();
    let tied = within_margin(&sah1, &(0..scored.len()).collect::<Vec<_>>());
    let mut window_boxes = 0;
    let chosen = if tied.len() > 1 && !sample.is_whole() {
        window_boxes = sample.windows.iter().map(|w| w.len()).sum();
        let win: Vec<Result<estimate::TreeAreas, crate::sort::SortError>> = tied
            .par_iter()
            .map_init(Scratch::default, |s, &i| {
                estimate_windows(&sample, &cands[i].spec.resolve(e), frame, backend, s)
            })
            .collect();
        for (&i, w) in tied.iter().zip(win) {
            scored[i].estimate.windows = w?;
        }
        let sah2: Vec<f64> = scored
            .iter()
            .map(|s| s.estimate.dense_sah().unwrap_or(f64::INFINITY))
            .collect();
        pick(&within_margin(&sah2, &tied), &scored, reference)
    } else {
        pick(&tied, &scored, reference)
    };
    let mut c = AutoChoice {
        bits,
        scored,
        chosen,
        reference,
        prims: boxes.len(),
        uniform: sample.uniform,
        large: sample.large,
        window_boxes,
        wall_ms: 0.0,
    };
    c.wall_ms = t0.elapsed().as_secs_f64() * 1e3;
    Ok(c)
}

/// Of the candidates `among`, those whose score is within [`KEEP_MARGIN_PCT`] of the least
/// (ascending indices).
fn within_margin(score: &[f64], among: &[usize]) -> Vec<usize> {
    let best = among
        .iter()
        .map(|&i| score[i])
        .fold(f64::INFINITY, f64::min);
    among
        .iter()
        .copied()
        .filter(|&i| score[i] <= best * (1.0 + KEEP_MARGIN_PCT / 100.0))
        .collect()
}

/// The pick among tied candidates: the reference, else the first named one, else the first.
fn pick(tied: &[usize], scored: &[Scored], reference: usize) -> usize {
    if tied.contains(&reference) {
        return reference;
    }
    tied.iter()
        .copied()
        .find(|&i| scored[i].candidate.rule == Rule::Named)
        .or_else(|| tied.first().copied())
        .unwrap_or(reference)
}
