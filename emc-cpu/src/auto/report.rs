//! `emc layout --auto-report`: how good and how cheap `--layout auto` is on each scene. Every
//! candidate is built in full (plain Karras LBVH, headline SAH: `Ct = Ci = 1`, one triangle
//! per leaf) to find the best one, and the choice is timed against fast-preset builds in the
//! same rounds. The presets' traced SAH with and without auto is measured too.
#![forbid(unsafe_code)]

use std::fmt::Write as _;
use std::time::Instant;

use emc_core::{Frame, Normalization};

use super::{choose, AutoChoice, LayoutChoice, AUTO};
use crate::build::{build_aabbs, scene_bounds, Builder, PipelineOptions};
use crate::bvh::refit::CollapseParams;
use crate::cputime::median;
use crate::scene::Mesh;
use crate::trace::api::{Accel, BuildOptions as AccelOptions, Preset};

/// The targets of issue 15: auto's full-build SAH within this many percent of the best
/// candidate's.
pub const TARGET_GAP_PCT: f64 = 1.0;
/// The choice's cost at most this share (percent) of one fast-preset build.
pub const TARGET_COST_PCT: f64 = 15.0;

/// A preset built twice, with its own layout and with auto.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PresetPair {
    /// Traced SAH ([`crate::trace::WideBvh::sah`]) with the preset's own layout.
    pub own_sah: f64,
    /// The same with the auto layout.
    pub auto_sah: f64,
    /// Median wall ms of a fresh build with the preset's own layout.
    pub own_ms: f64,
    /// The same with auto (the choice included).
    pub auto_ms: f64,
}

impl PresetPair {
    /// SAH change of auto against the preset's own layout, in percent.
    pub fn sah_change_pct(&self) -> f64 {
        pct(self.auto_sah, self.own_sah)
    }

    /// Build-time change of auto against the preset's own layout, in percent.
    pub fn time_change_pct(&self) -> f64 {
        pct(self.auto_ms, self.own_ms)
    }
}

/// The report of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneReport {
    /// Mesh name.
    pub name: String,
    /// Triangles.
    pub prims: usize,
    /// What auto chose, with every candidate's estimate.
    pub choice: AutoChoice,
    /// Full-build headline SAH of every candidate, in the order of `choice.scored`.
    pub full: Vec<f64>,
    /// Median wall ms of the choice (sample and estimates).
    pub choice_ms: f64,
    /// Median wall ms of a fresh fast-preset build (`Accel::build`), timed in the same rounds.
    pub fast_ms: f64,
    /// The fast preset (`emc32-var`) against `auto:32`.
    pub fast: Option<PresetPair>,
    /// The balanced preset (`emc64-var`) against `auto`.
    pub balanced: Option<PresetPair>,
    /// Threads of the pool every figure was measured on.
    pub threads: usize,
}

fn pct(a: f64, b: f64) -> f64 {
    if b > 0.0 && b.is_finite() {
        (a / b - 1.0) * 100.0
    } else {
        0.0
    }
}

impl SceneReport {
    /// Index of the candidate with the least full-build SAH (the first on ties).
    pub fn best(&self) -> usize {
        (0..self.full.len())
            .min_by(|&a, &b| self.full[a].total_cmp(&self.full[b]).then(a.cmp(&b)))
            .unwrap_or(0)
    }

    /// Auto's full-build SAH above the best candidate's, in percent (≥ 0).
    pub fn gap_pct(&self) -> f64 {
        pct(self.full[self.choice.chosen], self.full[self.best()])
    }

    /// Auto's full-build SAH against `emc64-var`'s, in percent.
    pub fn vs_var_pct(&self) -> f64 {
        pct(
            self.full[self.choice.chosen],
            self.full[self.choice.reference],
        )
    }

    /// The choice's cost as a share of one fast-preset build, in percent.
    pub fn cost_pct(&self) -> f64 {
        if self.fast_ms > 0.0 {
            self.choice_ms / self.fast_ms * 100.0
        } else {
            0.0
        }
    }
}

/// What [`measure`] does besides the full candidate builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReportOptions {
    /// Timing rounds (choice and fast build alternately; medians).
    pub rounds: usize,
    /// Also build the fast and balanced presets with and without auto.
    pub presets: bool,
}

fn accel_opts(preset: Preset, layout: Option<LayoutChoice>) -> AccelOptions {
    AccelOptions {
        layout,
        ..AccelOptions::preset(preset)
    }
}

fn timed_accel(scene: &Mesh, opts: &AccelOptions) -> anyhow::Result<(f64, Accel)> {
    let t = Instant::now();
    let a = Accel::build(&scene.vertices, &scene.indices, opts)?;
    Ok((t.elapsed().as_secs_f64() * 1e3, a))
}

/// A preset with its own layout and with `auto` (`bits` code bits), `rounds` alternating
/// fresh builds each.
fn preset_pair(
    scene: &Mesh,
    preset: Preset,
    auto: LayoutChoice,
    rounds: usize,
) -> anyhow::Result<PresetPair> {
    let (own, with) = (accel_opts(preset, None), accel_opts(preset, Some(auto)));
    let (mut t_own, mut t_auto) = (Vec::new(), Vec::new());
    let (mut own_sah, mut auto_sah) = (0.0, 0.0);
    for r in 0..rounds {
        // Alternate which goes first, so drift in the machine's load falls on both.
        let order = if r % 2 == 0 {
            [false, true]
        } else {
            [true, false]
        };
        for a in order {
            let (ms, acc) = timed_accel(scene, if a { &with } else { &own })?;
            if a {
                t_auto.push(ms);
                auto_sah = acc.wide_bvh().sah();
            } else {
                t_own.push(ms);
                own_sah = acc.wide_bvh().sah();
            }
        }
    }
    Ok(PresetPair {
        own_sah,
        auto_sah,
        own_ms: median(&t_own),
        auto_ms: median(&t_auto),
    })
}

/// Measure one scene on the current rayon pool.
pub fn measure(scene: &Mesh, opts: &ReportOptions) -> anyhow::Result<SceneReport> {
    let rounds = opts.rounds.max(1);
    let threads = rayon::current_num_threads();
    let boxes = scene.aabbs();
    let frame = Frame::from_bounds(scene_bounds(&boxes)?, Normalization::CentroidBox)?;
    let fast = accel_opts(Preset::Fast, None);
    // One untimed warm-up of each, then alternating timed rounds.
    let choice = choose(&boxes, &frame, super::AUTO_BITS)?;
    timed_accel(scene, &fast)?;
    let (mut t_choice, mut t_fast) = (Vec::new(), Vec::new());
    for _ in 0..rounds {
        let t = Instant::now();
        let again = choose(&boxes, &frame, super::AUTO_BITS)?;
        t_choice.push(t.elapsed().as_secs_f64() * 1e3);
        anyhow::ensure!(again.chosen == choice.chosen, "auto changed its choice");
        t_fast.push(timed_accel(scene, &fast)?.0);
    }
    let mut full = Vec::with_capacity(choice.scored.len());
    for s in &choice.scored {
        let out = build_aabbs(
            boxes.clone(),
            &PipelineOptions {
                layout: LayoutChoice::Fixed(s.candidate.spec),
                builder: Builder::Lbvh,
                threads,
                collapse: CollapseParams::NONE,
            },
        )?;
        full.push(out.report.sah_headline);
    }
    let (fast_pair, balanced) = if opts.presets {
        (
            Some(preset_pair(
                scene,
                Preset::Fast,
                LayoutChoice::Auto { bits: 32 },
                rounds,
            )?),
            Some(preset_pair(scene, Preset::Balanced, AUTO, rounds.min(3))?),
        )
    } else {
        (None, None)
    };
    Ok(SceneReport {
        name: scene.name.clone(),
        prims: scene.triangle_count(),
        choice,
        full,
        choice_ms: median(&t_choice),
        fast_ms: median(&t_fast),
        fast: fast_pair,
        balanced,
        threads,
    })
}

/// The machine's 1-minute load average, if the system tells it.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Mean of the values (0 for none).
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n > 0 {
        s / n as f64
    } else {
        0.0
    }
}

/// The report as a Markdown table with the verdict on both targets and the mean SAH change
/// against `emc64-var`.
pub fn table(rows: &[SceneReport]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| scene | tris | auto picks | auto SAH | best candidate | best SAH | gap | vs emc64-var | choice ms | fast build ms | cost |"
    );
    let _ = writeln!(s, "|---|---:|---|---:|---|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let (c, b) = (r.choice.chosen, r.best());
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {} | {:.3} | {:+.2}% | {:+.2}% | {:.2} | {:.2} | {:.1}% |",
            r.name,
            r.prims,
            r.choice.scored[c].candidate.label,
            r.full[c],
            r.choice.scored[b].candidate.label,
            r.full[b],
            r.gap_pct(),
            r.vs_var_pct(),
            r.choice_ms,
            r.fast_ms,
            r.cost_pct()
        );
    }
    let worst_gap = rows.iter().map(|r| r.gap_pct()).fold(0.0, f64::max);
    let worst_cost = rows.iter().map(|r| r.cost_pct()).fold(0.0, f64::max);
    let _ = writeln!(
        s,
        "\nmean headline SAH change of auto against emc64-var: {:+.2}% over {} scenes",
        mean(rows.iter().map(|r| r.vs_var_pct())),
        rows.len()
    );
    let verdict = |ok: bool| if ok { "met" } else { "MISSED" };
    let _ = writeln!(
        s,
        "targets: gap to the best candidate <= {TARGET_GAP_PCT}% ({}, worst {worst_gap:.2}%); \
         choice <= {TARGET_COST_PCT}% of a fast build ({}, worst {worst_cost:.1}%)",
        verdict(worst_gap <= TARGET_GAP_PCT),
        verdict(worst_cost <= TARGET_COST_PCT)
    );
    let presets: Vec<&SceneReport> = rows.iter().filter(|r| r.fast.is_some()).collect();
    if !presets.is_empty() {
        let _ = writeln!(
            s,
            "\n| scene | fast SAH emc32-var | fast SAH auto:32 | SAH | fast ms | fast ms auto:32 | time | balanced SAH emc64-var | balanced SAH auto | SAH | time |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        for r in &presets {
            if let (Some(f), Some(b)) = (r.fast, r.balanced) {
                let _ = writeln!(
                    s,
                    "| {} | {:.3} | {:.3} | {:+.2}% | {:.2} | {:.2} | {:+.1}% | {:.3} | {:.3} | {:+.2}% | {:+.1}% |",
                    r.name,
                    f.own_sah,
                    f.auto_sah,
                    f.sah_change_pct(),
                    f.own_ms,
                    f.auto_ms,
                    f.time_change_pct(),
                    b.own_sah,
                    b.auto_sah,
                    b.sah_change_pct(),
                    b.time_change_pct()
                );
            }
        }
        let m = |f: &dyn Fn(&SceneReport) -> Option<f64>| mean(presets.iter().filter_map(|r| f(r)));
        let _ = writeln!(
            s,
            "\nmean traced-SAH change with auto: fast (auto:32) {:+.2}% at {:+.1}% build time; \
             balanced (auto) {:+.2}% at {:+.1}% build time",
            m(&|r| r.fast.map(|p| p.sah_change_pct())),
            m(&|r| r.fast.map(|p| p.time_change_pct())),
            m(&|r| r.balanced.map(|p| p.sah_change_pct())),
            m(&|r| r.balanced.map(|p| p.time_change_pct())),
        );
    }
    s
}

/// The scenes of the report when none are given: every built-in scene, then every shared
/// scene that is present.
pub fn default_scenes() -> Vec<String> {
    let mut v: Vec<String> = crate::scene::builtin::NAMES
        .iter()
        .map(|n| format!("builtin:{n}"))
        .collect();
    for (name, _) in crate::scene::SHARED_SCENES {
        if crate::scene::shared_scene_path(name).is_some() {
            v.push(name.to_string());
        }
    }
    v
}
