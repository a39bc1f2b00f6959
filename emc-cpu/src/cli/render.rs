//! `emc render`: build a BVH over a scene, collapse it to the tracer's wide BVH, trace the
//! benchmark protocol (primary, AO and diffuse bounce rays) on a local pool, print throughput
//! and work per ray, and write a shaded PNG.
#![forbid(unsafe_code)]

use std::time::Instant;

use anyhow::{bail, Context};

use crate::build::Builder;
use crate::scene::{load_with, SceneOptions};
use crate::trace::image::{shade, Shading};
use crate::trace::workload::{
    all_ao_rays, all_bounce_rays, primary_rays, trace_closest, trace_occluded, Camera, CameraMode,
    SceneFrame,
};
use crate::trace::{Accel, BuildOptions, NodeTest, Preset, TraceStats};

/// Arguments of `emc render`.
#[derive(clap::Args, Debug, Clone)]
pub struct RenderArgs {
    /// A scene file (`.obj`, `.obj.zst`), a shared scene name, or `builtin:NAME`.
    pub scene: String,
    /// Build preset: fast, balanced or quality (the options below override it).
    #[arg(long, default_value = "quality")]
    pub preset: String,
    /// Code layout of the LBVH builders (morton30, morton63, emc64-sort, emc64-var, ..., or
    /// auto: chosen per scene).
    #[arg(long)]
    pub layout: Option<String>,
    /// Hierarchy builder: lbvh, lbvh-apetrei or binned-sah.
    #[arg(long)]
    pub builder: Option<String>,
    /// Treelet restructuring (atrbvh) before the leaf collapse: on or off.
    #[arg(long)]
    pub restructure: Option<String>,
    /// Largest leaf of the SAH collapse.
    #[arg(long)]
    pub leaf_size: Option<u32>,
    /// Threads for building and tracing (at least 1).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Image width and height in pixels (the protocol uses 1024).
    #[arg(long, default_value_t = 1024)]
    pub res: u32,
    /// Camera: outside or center (default: center for pbrt-bathroom, else outside).
    #[arg(long)]
    pub camera: Option<String>,
    /// Approximate triangle count of a built-in scene.
    #[arg(long)]
    pub prims: Option<usize>,
    /// Where to write the PNG (none: no image).
    #[arg(long)]
    pub out: Option<String>,
    /// Pixel shading: normal or ao.
    #[arg(long, default_value = "normal")]
    pub shading: String,
    /// Tree width to trace: 4 (SSE) or 8 (AVX2, scalar without it); default: 8 when the CPU
    /// has AVX2, else 4.
    #[arg(long)]
    pub width: Option<usize>,
    /// Trace each ray set this many times and report the run with the median CPU time.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Also compare these node tests on the traced tree (comma-separated: scalar, sse for
    /// width 4; scalar8, avx2, avx512 for width 8), on one thread, interleaved per block of
    /// 2048 rays (the order rotating from block to block, `--repeat` passes, at least 3), so
    /// that the machine's drift falls on all alike; prints Mrays/s and the ratio to the first.
    #[arg(long, value_delimiter = ',')]
    pub kernels: Vec<String>,
}

/// Rays per block of the `--kernels` comparison.
const KERNEL_BLOCK: usize = 2048;

/// The `--kernels` comparison: per kernel, the wall seconds of all its blocks and its counts
/// (primary hits, AO occluded).
fn compare_kernels(
    w: &crate::trace::WideBvh,
    kinds: &[NodeTest],
    primary: &[crate::trace::Ray],
    ao: &[crate::trace::Ray],
    passes: usize,
) -> Vec<(f64, f64, usize, usize)> {
    use crate::trace::traverse::{closest, occluded};
    let s = &mut TraceStats::default();
    let p = interleaved(kinds.len(), primary, passes, |k, r| {
        r.iter()
            .filter(|r| closest::<false>(w, r, kinds[k], s).is_some())
            .count()
    });
    let a = interleaved(kinds.len(), ao, passes, |k, r| {
        r.iter()
            .filter(|r| occluded::<false>(w, r, kinds[k], s))
            .count()
    });
    p.iter()
        .zip(&a)
        .map(|(&(tp, cp), &(ta, ca))| (tp, ta, cp, ca))
        .collect()
}

/// Seconds and result count of each of `n` tracers (`trace(k, block)` traces `block` with
/// tracer `k` and counts its hits) over `rays`, `passes` times, interleaved per
/// [`KERNEL_BLOCK`] rays with the order rotating from block to block and pass to pass.
fn interleaved(
    n: usize,
    rays: &[crate::trace::Ray],
    passes: usize,
    mut trace: impl FnMut(usize, &[crate::trace::Ray]) -> usize,
) -> Vec<(f64, usize)> {
    let mut out = vec![(0.0, 0usize); n];
    for turn in 0..passes {
        for (bi, b) in rays.chunks(KERNEL_BLOCK).enumerate() {
            for j in 0..n {
                let k = (bi + j + turn) % n;
                let t = Instant::now();
                let c = trace(k, b);
                out[k].0 += t.elapsed().as_secs_f64();
                out[k].1 += c;
            }
        }
    }
    out
}

/// One timed phase: wall and pool CPU seconds.
#[derive(Clone, Copy, Debug)]
struct Timing {
    wall: f64,
    cpu: f64,
}

fn timed<R: Send>(pool: &rayon::ThreadPool, f: impl FnOnce() -> R + Send) -> (R, Timing) {
    let cpu = || crate::cputime::pool_cpu_time(pool).as_secs_f64();
    let c0 = cpu();
    let t0 = Instant::now();
    let r = pool.install(f);
    let wall = t0.elapsed().as_secs_f64();
    (
        r,
        Timing {
            wall,
            cpu: cpu() - c0,
        },
    )
}

fn median_run<R: Send>(
    pool: &rayon::ThreadPool,
    repeat: usize,
    mut f: impl FnMut() -> R + Send,
) -> (R, Timing) {
    let mut runs: Vec<(R, Timing)> = (0..repeat).map(|_| timed(pool, &mut f)).collect();
    runs.sort_by(|a, b| a.1.cpu.total_cmp(&b.1.cpu));
    runs.swap_remove(runs.len() / 2)
}

fn report(kind: &str, rays: usize, t: Timing, s: &TraceStats, threads: usize) {
    let n = rays as f64;
    let per_ray = |x: u64| if rays > 0 { x as f64 / n } else { 0.0 };
    println!(
        "{kind:<8} {rays:>9} rays  {:>8.2} Mrays/s  {:>6.2} Mrays/s/thread  {:>6.2} M rays per thread-CPU-s  {:>6.2} node tests/ray  {:>6.2} triangle tests/ray",
        n / t.wall * 1e-6,
        n / t.wall * 1e-6 / threads as f64,
        n / t.cpu * 1e-6,
        per_ray(s.node_tests),
        per_ray(s.tri_tests),
    );
}

/// Run `emc render`.
pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    if args.threads == 0 {
        bail!("--threads must be at least 1");
    }
    if args.res == 0 || args.res > 16384 {
        bail!("--res must be in 1..=16384");
    }
    if args.repeat == 0 {
        bail!("--repeat must be at least 1");
    }
    let preset = match args.preset.as_str() {
        "fast" => Preset::Fast,
        "balanced" => Preset::Balanced,
        "quality" => Preset::Quality,
        p => bail!("unknown preset `{p}` (fast, balanced, quality)"),
    };
    let layout: Option<crate::auto::LayoutChoice> = args
        .layout
        .as_deref()
        .map(|l| l.parse().with_context(|| format!("--layout {l}")))
        .transpose()?;
    let builder: Option<Builder> = args.builder.as_deref().map(str::parse).transpose()?;
    let restructure = match args.restructure.as_deref() {
        None => None,
        Some("on") => Some(true),
        Some("off") => Some(false),
        Some(x) => bail!("--restructure takes on or off, not `{x}`"),
    };
    let shading: Shading = args.shading.parse().map_err(anyhow::Error::msg)?;
    let kernels: Vec<NodeTest> = args
        .kernels
        .iter()
        .map(|k| k.parse::<NodeTest>().map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<_>>()?;
    let scene = load_with(
        &args.scene,
        &SceneOptions {
            prims: args.prims,
            ..SceneOptions::default()
        },
    )
    .with_context(|| format!("loading {}", args.scene))?;
    let mode = match args.camera.as_deref() {
        Some(c) => c.parse::<CameraMode>().map_err(anyhow::Error::msg)?,
        None => CameraMode::for_scene(&scene.name),
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()
        .context("creating the thread pool")?;
    let opts = BuildOptions {
        preset,
        layout,
        builder,
        restructure,
        leaf_size: args.leaf_size,
        width: args.width,
    };
    let (b, l, r) = opts.resolve();
    if let Some(n) = args.width {
        if n != 4 && n != 8 {
            bail!("--width {n}: the tracer has 4- and 8-wide trees");
        }
    }
    let t0 = Instant::now();
    let accel = pool.install(|| Accel::build(&scene.vertices, &scene.indices, &opts))?;
    let build_ms = t0.elapsed().as_secs_f64() * 1e3;
    let w = accel.wide_bvh();
    let tris = &accel.triangles()[..];
    println!(
        "scene {}: {} triangles; builder {b}, layout {l}, restructure {}, leaf size {}, threads {}",
        scene.name,
        tris.len(),
        if r { "on" } else { "off" },
        args.leaf_size
            .unwrap_or(crate::trace::api::DEFAULT_LEAF_SIZE),
        args.threads
    );
    if l.is_auto() && b != Builder::BinnedSah {
        // The choice is a function of the boxes: made again here, untimed, to print it.
        let boxes = scene.aabbs();
        let frame = emc_core::Frame::from_bounds(
            scene.scene_bounds(&boxes)?,
            emc_core::Normalization::CentroidBox,
        )?;
        if let (_, Some(c)) = pool.install(|| l.resolve(&boxes, &frame))? {
            println!("layout auto: {}", c.reason());
        }
    }
    let kind = accel.node_test();
    if let Some(k) = kernels.iter().find(|k| k.width() != kind.width()) {
        bail!(
            "--kernels {}: a {}-wide test, but the traced tree is {}-wide (--width)",
            k.name(),
            k.width(),
            kind.width()
        );
    }
    println!(
        "build (triangles to a traceable {}-wide BVH, first build in this process, thread pool included): {build_ms:.1} ms wall; {} wide nodes, {} leaves, depth {}, {:.1} MiB, SAH {:.2}",
        kind.width(),
        w.nodes.len() + w.nodes8.len(),
        w.leaves,
        w.depth.max(w.depth8),
        w.memory_bytes() as f64 / (1 << 20) as f64,
        w.sah()
    );
    let (runs, why) = kind.resolved();
    println!(
        "traversal: {}-wide, {} node test ({why})",
        kind.width(),
        runs.name()
    );
    let frame = SceneFrame::of(tris);
    let cam = Camera::protocol(&frame, mode);
    let primary = pool.install(|| primary_rays(&cam, args.res, args.res));
    let ((hits, _), tp) = median_run(&pool, args.repeat, || {
        trace_closest(w, &primary, kind, false)
    });
    let (_, sp) = pool.install(|| trace_closest(w, &primary, kind, true));
    let (ao, _) = pool.install(|| all_ao_rays(&primary, &hits, tris, frame.diag));
    let ((occ, _), ta) = median_run(&pool, args.repeat, || trace_occluded(w, &ao, kind, false));
    let (_, sa) = pool.install(|| trace_occluded(w, &ao, kind, true));
    let bounce = pool.install(|| all_bounce_rays(&primary, &hits, tris, frame.diag));
    let (_, tb) = median_run(&pool, args.repeat, || {
        trace_closest(w, &bounce, kind, false)
    });
    let (_, sb) = pool.install(|| trace_closest(w, &bounce, kind, true));
    let n_hits = hits.iter().filter(|h| h.is_some()).count();
    let n_occ = occ.iter().filter(|&&o| o).count();
    println!(
        "camera {mode:?}, {}x{}: primary hits {n_hits}, AO rays {}, AO occluded {n_occ}",
        args.res,
        args.res,
        ao.len()
    );
    report("primary", primary.len(), tp, &sp, args.threads);
    report("ao", ao.len(), ta, &sa, args.threads);
    report("bounce", bounce.len(), tb, &sb, args.threads);
    if !kernels.is_empty() {
        let passes = args.repeat.max(3);
        let single = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .context("creating the thread pool")?;
        let got = single.install(|| compare_kernels(w, &kernels, &primary, &ao, passes));
        println!(
            "node tests, one thread, interleaved per {KERNEL_BLOCK}-ray block, {passes} passes:"
        );
        let mr = |n: usize, s: f64| (n * passes) as f64 / s * 1e-6;
        for (k, g) in kernels.iter().zip(&got) {
            let (runs, why) = k.resolved();
            println!(
                "  {:<8} primary {:>7.3} Mrays/s ({:.3}x)  AO {:>7.3} Mrays/s ({:.3}x)  hits {} occluded {}  runs {} ({why})",
                k.name(),
                mr(primary.len(), g.0),
                got[0].0 / g.0,
                mr(ao.len(), g.1),
                got[0].1 / g.1,
                g.2 / passes,
                g.3 / passes,
                runs.name(),
            );
        }
        if got.iter().any(|g| (g.2, g.3) != (got[0].2, got[0].3)) {
            bail!("the node tests disagree on the counts");
        }
    }
    if let Some(path) = &args.out {
        let img = pool.install(|| {
            shade(
                w,
                tris,
                &primary,
                &hits,
                (args.res, args.res),
                frame.diag,
                shading,
            )
        });
        let f = std::fs::File::create(path).with_context(|| format!("creating {path}"))?;
        img.write_png(f)
            .with_context(|| format!("writing {path}"))?;
        println!("wrote {path} ({shading:?} shading)");
    }
    Ok(())
}
