//! `emc paper`: the project's main report. Runs every builder × layout on the given scenes (the
//! built-in ones by default), writes Markdown, CSV, SVG plots and PNG images to a folder, and
//! prints a summary with the thread-CPU time the run took.
#![forbid(unsafe_code)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use emc_core::LayoutSpec;

use crate::paper::measure::PaperBuilder;
use crate::paper::tables::{mean, scene_change, Metric};
use crate::paper::{run as run_paper, PaperConfig, DEFAULT_SCENES};

/// Arguments of `emc paper`.
#[derive(clap::Args, Debug, Clone)]
pub struct PaperArgs {
    /// Scenes: `builtin:NAME`, OBJ files (`.obj`, `.obj.zst`) or shared scene names. Default:
    /// the built-in uniform, stadium, city, hair and mixed scenes.
    pub scenes: Vec<String>,
    /// Output folder.
    #[arg(long, default_value = "out/paper")]
    pub out: PathBuf,
    /// Small and fast: built-in scenes of 100k triangles, 256×256 primary rays per configuration.
    #[arg(long)]
    pub quick: bool,
    /// Threads of every build and trace (at least 1).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Seed of the built-in scenes.
    #[arg(long, default_value_t = crate::scene::builtin::DEFAULT_SEED)]
    pub seed: u64,
    /// Primary rays of the fixed ray budget per configuration (rounded up to a square image).
    #[arg(long)]
    pub rays: Option<usize>,
    /// Triangles of the built-in scenes (default: 100k with --quick, else their own default).
    #[arg(long)]
    pub prims: Option<usize>,
    /// Timed repeats of each trace, median reported.
    #[arg(long)]
    pub repeat: Option<usize>,
}

/// Run `emc paper`.
pub fn run(a: &PaperArgs) -> anyhow::Result<()> {
    let mut cfg = PaperConfig::new(a.quick);
    if !a.scenes.is_empty() {
        cfg.scenes = a.scenes.clone();
    } else {
        cfg.scenes = DEFAULT_SCENES.iter().map(|s| s.to_string()).collect();
    }
    cfg.out = a.out.clone();
    cfg.threads = a.threads;
    cfg.seed = a.seed;
    if let Some(r) = a.rays {
        cfg.rays = r;
    }
    if a.prims.is_some() {
        cfg.prims = a.prims;
    }
    if let Some(r) = a.repeat {
        cfg.repeats = r;
    }
    let cpu0 = crate::cputime::process_cpu_time().map(|d| d.as_secs_f64());
    let t0 = Instant::now();
    let res = run_paper(&cfg).context("emc paper")?;
    let wall = t0.elapsed().as_secs_f64();
    let cpu = crate::cputime::process_cpu_time()
        .map(|d| d.as_secs_f64())
        .zip(cpu0)
        .map(|(b, a)| b - a);
    println!(
        "emc paper: {} scenes, {} threads, {} primary rays per configuration",
        res.scenes.len(),
        res.threads,
        res.rays
    );
    for s in &res.scenes {
        let l = |b, spec, m| scene_change(s, b, spec, m);
        let var = s
            .find(PaperBuilder::Lbvh, LayoutSpec::Emc64Var)
            .and_then(|r| r.layout.clone())
            .unwrap_or_default();
        println!(
            "  {:<22} {:>8} tris  emc64-var {:<40}  SAH vs morton63: lbvh sort {:+.1}% var {:+.1}%, atrbvh sort {:+.1}% var {:+.1}%",
            s.name,
            s.prims,
            var,
            l(PaperBuilder::Lbvh, LayoutSpec::Emc64Sort, Metric::SahHeadline),
            l(PaperBuilder::Lbvh, LayoutSpec::Emc64Var, Metric::SahHeadline),
            l(PaperBuilder::Atrbvh, LayoutSpec::Emc64Sort, Metric::SahHeadline),
            l(PaperBuilder::Atrbvh, LayoutSpec::Emc64Var, Metric::SahHeadline),
        );
        if let Some(best) = s
            .runs
            .iter()
            .min_by(|a, b| a.time_to_image_ms().total_cmp(&b.time_to_image_ms()))
        {
            println!(
                "  {:<22} fastest time-to-image: {} {} ({:.1} CPU ms); Pareto (build, SAH): {}",
                "",
                best.builder.name(),
                best.layout_name(),
                best.time_to_image_ms(),
                s.runs
                    .iter()
                    .filter(|r| r.pareto_sah)
                    .map(|r| format!("{} {}", r.builder.name(), r.layout_name()))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    for b in [PaperBuilder::Lbvh, PaperBuilder::Atrbvh] {
        for spec in [LayoutSpec::Emc64Sort, LayoutSpec::Emc64Var] {
            let avg = |m| {
                mean(
                    &res.scenes
                        .iter()
                        .map(|s| scene_change(s, b, spec, m))
                        .filter(|v| v.is_finite())
                        .collect::<Vec<_>>(),
                )
            };
            println!(
                "  AVG {:<7} {:<10} vs morton63: SAH {:+.1}%, SAH collapsed {:+.1}%, primary Mrays/CPU-s {:+.1}%, AO {:+.1}%",
                b.name(),
                spec.to_string(),
                avg(Metric::SahHeadline),
                avg(Metric::SahCollapsed),
                avg(Metric::PrimaryMrays),
                avg(Metric::AoMrays)
            );
        }
    }
    println!("wrote {} files to {}", res.files.len(), cfg.out.display());
    match cpu {
        Some(c) => println!("time: {wall:.1} s wall, {c:.1} thread-CPU s (all threads of the process, scene generation included)"),
        None => println!("time: {wall:.1} s wall"),
    }
    Ok(())
}
