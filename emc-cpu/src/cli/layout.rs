//! `emc layout`: build a scene's frame and print, per layout, the seed-style line, each
//! backend's encode-only and full-pipeline throughput in thread CPU time, the ratio to a
//! streaming baseline measured in the same rounds, and which backend dispatch picked and why.
//!
//! `--ratios` turns it into the ratio measurement tool: only the baseline and the dispatched
//! pipelines, at least 9 interleaved rounds, the median of the per-round ratios.
#![forbid(unsafe_code)]

use std::fmt::Write as _;
use std::time::Instant;

use anyhow::{bail, Context};
use emc_core::{Aabb, Backend, Encoder, Frame, LayoutSpec, Normalization, QuantizePath};

use crate::auto::LayoutChoice;
use crate::cputime::{median, thread_cpu_time};
use crate::encode::{encode_parallel, expand_slice, stream_baseline};
use crate::scene::{load_with, SceneOptions};

/// Triangles of a built-in scene when `--prims` is not given.
pub const DEFAULT_PRIMS: usize = 1 << 20;

/// Arguments of `emc layout`.
#[derive(clap::Args, Debug, Clone)]
pub struct LayoutArgs {
    /// A scene file (`.obj`, `.obj.zst`), a shared scene name, or `builtin:NAME`.
    #[arg(default_value = "builtin:uniform")]
    pub scene: String,
    /// Triangle count of a built-in scene.
    #[arg(long, default_value_t = DEFAULT_PRIMS)]
    pub prims: usize,
    /// Layouts to report (repeatable); default: morton30, morton63, emc64-sort, emc64-var,
    /// emc32-var, emc64-var-nosize. Also `custom:PATTERN[:linear]`, and `auto` (or `auto:N`):
    /// the layout chosen for the scene, printed with its reason and every candidate.
    #[arg(long = "layout")]
    pub layouts: Vec<String>,
    /// Threads for loading the scene and for an extra parallel-encode row (wall clock); the
    /// per-backend figures are always one thread.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Interleaved timing rounds (default 5, or 9 with `--ratios`).
    #[arg(long)]
    pub rounds: Option<usize>,
    /// Measure only the streaming baseline and the dispatched pipelines (forced-scalar
    /// quantise for comparison), and report the median of per-round ratios.
    #[arg(long)]
    pub ratios: bool,
    /// Instead of the encode report: what `--layout auto` picks on each of these scenes (none
    /// given: every built-in and shared scene) against full LBVH builds of every candidate,
    /// and what the choice costs against fast-preset builds timed in the same rounds.
    #[arg(long = "auto-report", num_args = 0.., value_name = "SCENES")]
    pub auto_report: Option<Vec<String>>,
    /// With `--auto-report`: also build the fast and balanced presets with and without auto.
    #[arg(long)]
    pub presets: bool,
}

/// One timed kernel of a layout.
enum Kind<'a> {
    Baseline,
    Expand(&'a Encoder),
    Pipeline(&'a Encoder),
    PipelineScalar(&'a Encoder),
}

struct Timed<'a> {
    kind: Kind<'a>,
    secs: Vec<f64>,
    ratios: Vec<f64>,
}

impl Timed<'_> {
    fn run(&self, boxes: &[Aabb], q: &[[u64; 4]], out: &mut [u64]) -> anyhow::Result<()> {
        match self.kind {
            Kind::Baseline => stream_baseline(boxes, out)?,
            Kind::Expand(e) => expand_slice(e.expander(), q, out)?,
            Kind::Pipeline(e) => e.encode_batch(boxes, out)?,
            Kind::PipelineScalar(e) => e.encode_batch_scalar(boxes, out)?,
        }
        Ok(())
    }

    /// "ns/code  Mcodes/s" from the median time.
    fn rate(&self, n: usize) -> String {
        let s = median(&self.secs);
        format!(
            "{:7.2} ns {:7.1} M/s",
            s * 1e9 / n as f64,
            n as f64 / s / 1e6
        )
    }

    fn ratio(&self) -> f64 {
        median(&self.ratios)
    }
}

/// Run `emc layout`.
pub fn run(args: &LayoutArgs) -> anyhow::Result<()> {
    if args.threads == 0 {
        bail!("--threads must be at least 1");
    }
    if args.prims == 0 {
        bail!("--prims must be at least 1");
    }
    let rounds = args.rounds.unwrap_or(if args.ratios { 9 } else { 5 });
    if rounds == 0 {
        bail!("--rounds must be at least 1");
    }
    let specs: Vec<LayoutChoice> = if args.layouts.is_empty() {
        LayoutSpec::STANDARD.map(LayoutChoice::Fixed).to_vec()
    } else {
        args.layouts
            .iter()
            .map(|l| l.parse().with_context(|| format!("--layout {l}")))
            .collect::<anyhow::Result<_>>()?
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()
        .context("cannot start the thread pool")?;
    if let Some(scenes) = &args.auto_report {
        return pool.install(|| auto_report(args, scenes, rounds));
    }
    pool.install(|| report(args, &specs, rounds))
}

/// `--auto-report`: one scene at a time, a line per scene as it is done, then the table.
fn auto_report(args: &LayoutArgs, scenes: &[String], rounds: usize) -> anyhow::Result<()> {
    use crate::auto::report;
    let scenes = if scenes.is_empty() {
        report::default_scenes()
    } else {
        scenes.to_vec()
    };
    let opts = report::ReportOptions {
        rounds,
        presets: args.presets,
    };
    let load = report::load_average();
    let mut rows = Vec::with_capacity(scenes.len());
    for spec in &scenes {
        let sopts = SceneOptions {
            prims: spec.starts_with("builtin:").then_some(args.prims),
            ..SceneOptions::default()
        };
        let scene = load_with(spec, &sopts).with_context(|| format!("loading {spec}"))?;
        let r = report::measure(&scene, &opts).with_context(|| format!("scene {spec}"))?;
        println!("{}: {}", r.name, r.choice.reason());
        for (i, s) in r.choice.scored.iter().enumerate() {
            println!(
                "  {:<16} est. {:>+7.2}%  full SAH {:>9.4} ({:>+6.2}% vs {}){}{}",
                s.candidate.label,
                r.choice.change_pct(i),
                r.full[i],
                (r.full[i] / r.full[r.choice.reference] - 1.0) * 100.0,
                r.choice.scored[r.choice.reference].candidate.label,
                if i == r.choice.chosen {
                    "  <- auto"
                } else {
                    ""
                },
                if i == r.best() { "  <- best" } else { "" },
            );
        }
        rows.push(r);
    }
    println!();
    println!(
        "auto report: {} threads, {rounds} alternating rounds (medians, wall ms), load average {} at the start, {} at the end",
        rayon::current_num_threads(),
        load.map_or("?".into(), |l| format!("{l:.2}")),
        report::load_average().map_or("?".into(), |l| format!("{l:.2}")),
    );
    print!("{}", report::table(&rows));
    Ok(())
}

fn report(args: &LayoutArgs, choices: &[LayoutChoice], rounds: usize) -> anyhow::Result<()> {
    let opts = SceneOptions {
        prims: Some(args.prims),
        ..SceneOptions::default()
    };
    let scene = load_with(&args.scene, &opts).with_context(|| format!("scene {}", args.scene))?;
    let boxes = scene.aabbs();
    let bounds = scene
        .scene_bounds(&boxes)
        .with_context(|| format!("scene {}", scene.name))?;
    let frame = Frame::from_bounds(bounds, Normalization::CentroidBox)?;
    let n = boxes.len();
    let cpu = emc_core::cpu::detect();
    println!(
        "scene {}: {} primitives; extent {:.4e} x {:.4e} x {:.4e}, D = {:.4e}",
        scene.name,
        n,
        frame.extent()[0],
        frame.extent()[1],
        frame.extent()[2],
        frame.diagonal()
    );
    println!(
        "cpu: {} family {:#x} model {:#x}, bmi2 {}, avx2 {}; {}",
        cpu.vendor_str(),
        cpu.family,
        cpu.model,
        cpu.bmi2,
        cpu.avx2,
        cpu.pdep_reason()
    );
    println!(
        "timing: thread CPU time, median of {rounds} interleaved rounds, one thread; \
         ratio = median of per-round (kernel / baseline); baseline streams 24 B in + 8 B out \
         per primitive"
    );
    let mut specs = Vec::with_capacity(choices.len());
    for c in choices {
        let (spec, auto) = c.resolve(&boxes, &frame)?;
        if let Some(a) = auto {
            println!();
            println!("{c}: {}", a.reason());
            for (i, sc) in a.scored.iter().enumerate() {
                println!(
                    "  {:<16} est. SAH {:>+8.2}%  {}  {}{}",
                    sc.candidate.label,
                    a.change_pct(i),
                    sc.candidate.spec.resolve(frame.extent()).counts_line(),
                    sc.candidate.spec,
                    if i == a.chosen { "  <- chosen" } else { "" }
                );
            }
        }
        specs.push(spec);
    }
    let mut out = vec![0u64; n];
    for spec in &specs {
        let layout = spec.resolve(frame.extent());
        let dispatched = Encoder::for_layout(layout, &frame);
        println!();
        println!("{spec}  {layout}");
        println!(
            "  dispatch: {} ({}); {}",
            dispatched.backend(),
            dispatched.reason(),
            dispatched.pipeline()
        );
        let mut reference = vec![0u64; n];
        dispatched.encode_batch_scalar(&boxes, &mut reference)?;
        let q: Vec<[u64; 4]> = if args.ratios {
            Vec::new()
        } else {
            boxes
                .iter()
                .map(|b| dispatched.quantizer().quantize(b))
                .collect()
        };
        // Every backend that can serve the layout here, and why the others cannot.
        let mut encoders: Vec<(Backend, Encoder)> = Vec::new();
        let mut unavailable: Vec<String> = Vec::new();
        if !args.ratios {
            for b in Backend::ALL {
                match Encoder::with_backend(layout, &frame, b) {
                    Ok(e) => encoders.push((b, e)),
                    Err(_) if b == Backend::Magic => {
                        unavailable.push(format!("{b}: n/a (the pattern is not regular)"))
                    }
                    Err(e) => unavailable.push(format!("{b}: n/a ({e})")),
                }
            }
        }
        let mut timed = vec![Timed {
            kind: Kind::Baseline,
            secs: Vec::new(),
            ratios: Vec::new(),
        }];
        let mut add = |kind| {
            timed.push(Timed {
                kind,
                secs: Vec::new(),
                ratios: Vec::new(),
            })
        };
        add(Kind::Pipeline(&dispatched));
        add(Kind::PipelineScalar(&dispatched));
        for (_, e) in &encoders {
            add(Kind::Expand(e));
            add(Kind::Pipeline(e));
            add(Kind::PipelineScalar(e));
        }
        // Warm-up doubles as the correctness check: every pipeline equals the scalar path.
        for t in &timed {
            t.run(&boxes, &q, &mut out)?;
            if matches!(t.kind, Kind::Pipeline(_) | Kind::PipelineScalar(_)) && out != reference {
                bail!("{spec}: a batch pipeline disagrees with the scalar encoder");
            }
        }
        for _ in 0..rounds {
            let mut base = f64::NAN;
            for t in timed.iter_mut() {
                let t0 = thread_cpu_time();
                t.run(&boxes, &q, &mut out)?;
                let s = (thread_cpu_time() - t0).as_secs_f64().max(1e-9);
                if matches!(t.kind, Kind::Baseline) {
                    base = s;
                }
                t.secs.push(s);
                t.ratios.push(s / base);
            }
        }
        println!("  baseline stream:              {}", timed[0].rate(n));
        println!(
            "  dispatched pipeline:          {}  {:5.2}x baseline",
            timed[1].rate(n),
            timed[1].ratio()
        );
        println!(
            "  same, scalar quantize:        {}  {:5.2}x baseline",
            timed[2].rate(n),
            timed[2].ratio()
        );
        if args.ratios {
            let r = &timed[1].ratios;
            let lo = r.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = r.iter().copied().fold(0.0, f64::max);
            println!(
                "  per-round ratios of the dispatched pipeline: min {lo:.2} median {:.2} max \
                 {hi:.2} over {} rounds",
                timed[1].ratio(),
                r.len()
            );
        } else {
            println!(
                "  {:<10} {:>22} {:>22} {:>8} {:>22} {:>8}",
                "backend", "encode only", "pipeline", "ratio", "pipeline, scalar q", "ratio"
            );
            for (i, (b, e)) in encoders.iter().enumerate() {
                let k = 3 + 3 * i;
                let mut line = String::new();
                write!(
                    line,
                    "  {:<10} {:>22} {:>22} {:>7.2}x {:>22} {:>7.2}x",
                    b.name(),
                    timed[k].rate(n),
                    timed[k + 1].rate(n),
                    timed[k + 1].ratio(),
                    timed[k + 2].rate(n),
                    timed[k + 2].ratio()
                )?;
                if e.pipeline().quantize == QuantizePath::Avx2 {
                    write!(line, "  [{}]", e.pipeline().expand)?;
                }
                println!("{line}");
            }
            for u in &unavailable {
                println!("  {u}");
            }
        }
        if args.threads > 1 {
            let mut secs = Vec::new();
            for _ in 0..rounds {
                let t0 = Instant::now();
                encode_parallel(&dispatched, &boxes, &mut out)?;
                secs.push(t0.elapsed().as_secs_f64());
            }
            if out != reference {
                bail!("{spec}: the parallel encoder disagrees with the scalar encoder");
            }
            let s = median(&secs);
            println!(
                "  parallel pipeline, {} threads (wall clock): {:.2} ns/code {:.1} M/s",
                args.threads,
                s * 1e9 / n as f64,
                n as f64 / s / 1e6
            );
        }
    }
    Ok(())
}
