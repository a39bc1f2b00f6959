//! `emc build`: load a scene, run the build pipeline on a local pool and print per-phase wall and
//! thread-CPU milliseconds, throughput, tree shape and both SAH figures.
#![forbid(unsafe_code)]

use anyhow::{bail, Context};

use crate::auto::LayoutChoice;

use crate::build::{
    build_scene_in, BuildArena, BuildOutput, BuildReport, Builder, Phase, PhaseTime,
    PipelineOptions,
};
use crate::bvh::refit::CollapseParams;
use crate::scene::{load_with, SceneOptions};

/// Arguments of `emc build`.
#[derive(clap::Args, Debug, Clone)]
pub struct BuildArgs {
    /// A scene file (`.obj`, `.obj.zst`), a shared scene name, or `builtin:NAME`.
    pub scene: String,
    /// Code layout: morton30, morton63, emc64-sort, emc64-var, emc32-var, emc64-var-nosize,
    /// custom:PATTERN (optionally followed by :linear), or auto (chosen for the scene among
    /// the 64-bit candidates; auto:N among those of N bits).
    #[arg(long, default_value = "emc64-var")]
    pub layout: String,
    /// Hierarchy builder: lbvh, lbvh-apetrei, binned-sah or atrbvh.
    #[arg(long, default_value = "lbvh")]
    pub builder: String,
    /// Threads of the build pool (at least 1).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Approximate triangle count of a built-in scene.
    #[arg(long)]
    pub prims: Option<usize>,
    /// Largest leaf the SAH collapse may create (1 keeps one primitive per leaf).
    #[arg(long, default_value_t = 8)]
    pub leaf_size: u32,
    /// Build this many times and report the run with the median thread-CPU total. Builds after
    /// the first reuse the previous build's buffers (warm) unless `--cold` is given.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Give every repeated build fresh buffers (as a first build in a process has).
    #[arg(long)]
    pub cold: bool,
    /// Skip the structural check of the finished BVH.
    #[arg(long)]
    pub no_validate: bool,
    /// Also run the same builds on a pool of this many threads first (same repeat count, warm
    /// or cold alike) and print each phase's CPU time relative to it, e.g. `--vs-threads 1`
    /// with `--threads 2` for the parallel CPU overhead.
    #[arg(long)]
    pub vs_threads: Option<usize>,
}

/// The builds of one thread count: the first build's report, the median report (by total CPU
/// over the warm builds, or over all when cold or single) and the last build's output.
struct Series {
    first: BuildReport,
    median: BuildReport,
    count: usize,
    last: BuildOutput,
}

/// Run `repeat` builds with `opts` (fresh buffers each when `cold`, else the previous build's).
fn series(
    scene: &crate::scene::Mesh,
    opts: &PipelineOptions,
    repeat: usize,
    cold: bool,
) -> anyhow::Result<Series> {
    let mut reports: Vec<BuildReport> = Vec::with_capacity(repeat);
    let mut arena = BuildArena::new();
    let mut last: Option<BuildOutput> = None;
    for _ in 0..repeat {
        if cold {
            drop(last.take());
            arena = BuildArena::new();
        } else if let Some(prev) = last.take() {
            arena.recycle(prev);
        }
        let out = build_scene_in(scene, opts, &mut arena)?;
        reports.push(out.report.clone());
        last = Some(out);
    }
    let Some(last) = last else {
        bail!("no build ran");
    };
    let first = reports[0].clone();
    // Warm runs are those after the first (unless cold); the median is taken over them.
    let mut pool: Vec<BuildReport> = if cold || reports.len() == 1 {
        reports
    } else {
        reports.split_off(1)
    };
    let count = pool.len();
    pool.sort_by(|a, b| a.total().cpu_ms.total_cmp(&b.total().cpu_ms));
    let median = pool.swap_remove(count / 2);
    Ok(Series {
        first,
        median,
        count,
        last,
    })
}

/// A share as a percentage, or `-` on a one-thread pool (where it is 100% by definition).
fn share(t: &PhaseTime, threads: usize) -> String {
    if threads < 2 {
        "-".to_string()
    } else if t.cpu_ms > 0.0 {
        format!("{:.1}%", 100.0 * t.serial_share())
    } else {
        String::new()
    }
}

/// Run `emc build`.
pub fn run(args: &BuildArgs) -> anyhow::Result<()> {
    if args.threads == 0 {
        bail!("--threads must be at least 1");
    }
    if args.leaf_size == 0 {
        bail!("--leaf-size must be at least 1");
    }
    if args.repeat == 0 {
        bail!("--repeat must be at least 1");
    }
    if args.vs_threads == Some(0) {
        bail!("--vs-threads must be at least 1");
    }
    let layout: LayoutChoice = args
        .layout
        .parse()
        .with_context(|| format!("--layout {}", args.layout))?;
    let builder: Builder = args.builder.parse()?;
    let opts = PipelineOptions {
        layout,
        builder,
        threads: args.threads,
        collapse: CollapseParams {
            max_leaf: args.leaf_size,
            ..CollapseParams::default()
        },
    };
    let scene = load_with(
        &args.scene,
        &SceneOptions {
            prims: args.prims,
            ..SceneOptions::default()
        },
    )
    .with_context(|| format!("loading {}", args.scene))?;
    if scene.dropped_nonfinite > 0 {
        println!(
            "note: {} triangles with a non-finite vertex were dropped",
            scene.dropped_nonfinite
        );
    }
    let base = match args.vs_threads {
        Some(t) => Some(series(
            &scene,
            &PipelineOptions { threads: t, ..opts },
            args.repeat,
            args.cold,
        )?),
        None => None,
    };
    // Every build gives the same BVH (builds are deterministic); the last one is validated.
    let Series {
        first,
        median,
        count,
        last: out,
    } = series(&scene, &opts, args.repeat, args.cold)?;
    let r = &median;
    let what = match (args.repeat, args.cold) {
        (1, _) => String::from(", one cold build (fresh buffers)"),
        (_, true) => format!(", median of {count} cold builds (fresh buffers each) by CPU time"),
        _ => format!(
            ", median of {count} warm builds (buffers reused from the previous build) by CPU time"
        ),
    };
    println!(
        "scene {}: {} triangles; builder {}, layout {}, threads {}{what}",
        scene.name,
        r.prims,
        r.builder,
        r.layout.as_deref().unwrap_or("(none)"),
        r.threads,
    );
    if let Some(c) = &r.auto {
        println!("layout auto: {}", c.reason());
        println!(
            "  {:<16} {:>12}  pattern (MSB first)",
            "candidate", "est. SAH"
        );
        for (i, sc) in c.scored.iter().enumerate() {
            println!(
                "  {:<16} {:>+11.2}%  {}{}",
                sc.candidate.label,
                c.change_pct(i),
                sc.candidate.spec,
                if i == c.chosen { "  <- chosen" } else { "" }
            );
        }
        println!(
            "  choice cost: {:.2} ms wall, {:.2} ms CPU (in the encode phase below)",
            r.auto_time.wall_ms, r.auto_time.cpu_ms
        );
    }
    let vs_head = match &base {
        Some(b) => format!(" {:>11}", format!("cpu/{}T cpu", b.median.threads)),
        None => String::new(),
    };
    println!(
        "{:<10} {:>10} {:>10} {:>8} {:>8}{vs_head}",
        "phase", "wall ms", "cpu ms", "cpu/wall", "serial"
    );
    let ratio = |a: f64, b: f64| {
        if b > 0.0 {
            format!(" {:>11.3}", a / b)
        } else {
            format!(" {:>11}", "")
        }
    };
    for p in Phase::ALL {
        let t = r.phase(p);
        let par = if t.wall_ms > 0.0 {
            t.cpu_ms / t.wall_ms
        } else {
            0.0
        };
        let vs = match &base {
            Some(b) => ratio(t.cpu_ms, b.median.phase(p).cpu_ms),
            None => String::new(),
        };
        println!(
            "{:<10} {:>10.2} {:>10.2} {:>8.2} {:>8}{vs}",
            p.name(),
            t.wall_ms,
            t.cpu_ms,
            par,
            share(&t, r.threads)
        );
    }
    let t = r.total();
    let vs = match &base {
        Some(b) => ratio(t.cpu_ms, b.median.total().cpu_ms),
        None => String::new(),
    };
    println!(
        "{:<10} {:>10.2} {:>10.2} {:>8.2} {:>8}{vs}",
        "total",
        t.wall_ms,
        t.cpu_ms,
        if t.wall_ms > 0.0 {
            t.cpu_ms / t.wall_ms
        } else {
            0.0
        },
        share(&t, r.threads)
    );
    if r.threads > 1 {
        println!(
            "serial: share of a phase's thread-CPU time the busiest thread spent while the \
             others had none of its work: per-thread CPU c_i and run-queue wait q_i (time kept \
             off the core by other tenants), sum over i != busiest of max(0, c_max - c_i - q_i) \
             / (T-1) / sum c_i (T = 2: the busiest thread's CPU beyond the other's, less the \
             other's run-queue wait); load imbalance counts as serial"
        );
    }
    if let Some(b) = &base {
        println!(
            "baseline: {} threads, {} build(s) in this run; total {:.2} ms CPU, {:.2} ms wall, \
             {:.2} Mprims per thread-CPU-second",
            b.median.threads,
            b.count,
            b.median.total().cpu_ms,
            b.median.total().wall_ms,
            b.median.mprims_per_cpu_s()
        );
    }
    if args.repeat > 1 && !args.cold {
        let cpu: Vec<String> = Phase::ALL
            .iter()
            .map(|&p| format!("{} {:.2}", p.name(), first.phase(p).cpu_ms))
            .collect();
        println!(
            "first (cold) build: cpu ms [{}] total {:.2}, {:.2} Mprims per thread-CPU-second, \
             {:.2} ms wall",
            cpu.join(", "),
            first.total().cpu_ms,
            first.mprims_per_cpu_s(),
            first.total().wall_ms
        );
    }
    println!(
        "throughput: {:.2} Mprims per thread-CPU-second, {:.2} Mprims per wall-second",
        r.mprims_per_cpu_s(),
        r.mprims_per_wall_s()
    );
    if r.sort.passes + r.sort.skipped > 0 {
        println!(
            "sort: {} varying key bits ({} of {} bytes constant, never sorted on), first split \
             {} bits, at most {} moves per pair",
            r.sort.varying_bits,
            r.sort.skipped,
            r.sort.passes + r.sort.skipped,
            r.sort.top_digit_bits,
            r.sort.depth
        );
    }
    println!(
        "tree: {} nodes, {} leaves, depth {}",
        r.nodes, r.leaves, r.depth
    );
    println!(
        "SAH headline (Ct = Ci = 1, one primitive per leaf): {:.4}",
        r.sah_headline
    );
    println!(
        "SAH collapsed (Ct = 1.2, Ci = 1, leaves of at most {}): {:.4}",
        args.leaf_size, r.sah_collapsed
    );
    if !args.no_validate {
        let s = out
            .bvh
            .validate(&out.aabbs)
            .context("the built BVH is malformed")?;
        println!(
            "validate: ok ({} nodes, {} leaves, largest leaf {}, depth {})",
            s.nodes, s.leaves, s.max_leaf_size, s.depth
        );
    }
    Ok(())
}
