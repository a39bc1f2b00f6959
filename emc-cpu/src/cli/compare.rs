//! `emc compare`: emc's presets beside the peers (Embree 3 LOW and MEDIUM, obvhs; feature
//! `peers`) in one process, on the benchmark protocol's rays: build ms (cold and warm), primary
//! and AO Mrays/s, the protocol counts, BVH memory, and each emc figure's ratio to the best peer
//! measured in the same run. A ratio to a figure from another run or machine is never printed.
//!
//! Builds, as the peer harness times Embree: one warm-up build, then **cold** = median of
//! [`BUILDS`] builds of fresh objects (the previous one dropped first), **warm** = median of
//! [`BUILDS`] rebuilds of the kept one over the same vertices (`Accel::rebuild_in`, whose fast
//! preset then sorts in one pass: no code changed; Embree: `rtcUpdateGeometryBuffer` and a
//! commit of the same scene; obvhs: its PLOC builder and tree reused; moving meshes:
//! `--frames`). Wall time; the
//! thread pools exist before the clock starts (one rayon pool for emc and obvhs, one Embree
//! device), and emc builds in one [`BuildContext`] per configuration, its device: scratch
//! memory kept from build to build (the warm-up build fills it), every `Accel` fresh.
//! Traces: one warm-up pass per configuration (its counts and its own AO rays, made with the
//! harness's arithmetic: [`crate::peers::harness_ao_rays`], so emc's AO counts here can differ
//! by a ray from `emc render`'s), then `--runs` passes that alternate the configurations run by
//! run; medians; single-ray calls through [`crate::peers`]' loop (FTZ/DAZ on every tracing
//! thread, emc's included; builds run in the default floating-point mode on every side). Beside
//! each wall figure, its CPU time (process CPU of a build, thread CPU of the tracing threads),
//! for runs on a shared machine.

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use glam::Vec3;

use crate::cputime::process_cpu_time;
use crate::peers::{Protocol, Timing, Tracer};
use crate::scene::{load_with, SceneOptions};
use crate::trace::wide_lbvh::FastTimes;
use crate::trace::workload::{AoCounts, CameraMode};
use crate::trace::{Accel, BuildContext, BuildOptions, Preset};

/// Builds per cold and per warm median (the harness's `--reps 5`).
pub const BUILDS: usize = 5;

/// Arguments of `emc compare`.
#[derive(clap::Args, Debug, Clone)]
pub struct CompareArgs {
    /// Scenes: `.obj` / `.obj.zst` files, shared scene names, or `builtin:NAME`.
    #[arg(required = true)]
    pub scenes: Vec<String>,
    /// Threads for building and tracing, on every side (at least 1).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Also write one CSV row per scene and configuration to this file.
    #[arg(long)]
    pub csv: Option<String>,
    /// Timed trace passes per configuration (after one warm-up), alternating configurations.
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// emc presets to measure, comma-separated: fast, balanced, quality.
    #[arg(long, default_value = "fast,balanced,quality")]
    pub presets: String,
    /// Image width and height of the primary rays (the protocol uses 1024).
    #[arg(long, default_value_t = 1024)]
    pub res: u32,
    /// Camera: outside or center (default: center for pbrt-bathroom, else outside).
    #[arg(long)]
    pub camera: Option<String>,
    /// Approximate triangle count of built-in scenes.
    #[arg(long)]
    pub prims: Option<usize>,
    /// Animate instead (`builtin:wave`): per frame refit and rebuild against Embree's REFIT
    /// and LOW commits of the same vertices, and the frame's primary rays through each.
    #[arg(long)]
    pub frames: Option<u32>,
    /// Instance each scene's mesh this many times instead: a two-level `Scene` (quality
    /// preset mesh, LBVH top level) against the same instances in Embree, top level built,
    /// moved and traced.
    #[arg(long, conflicts_with = "frames")]
    pub instances: Option<usize>,
}

/// A configuration measured: an emc preset or a peer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Config {
    /// `Accel` with this preset.
    Emc(Preset),
    /// Embree 3 at this build quality.
    #[cfg(feature = "peers")]
    Embree(crate::peers::embree::Quality),
    /// obvhs' fastest build (PLOC → BVH2).
    #[cfg(feature = "peers")]
    Obvhs,
}

impl Config {
    /// The row label.
    pub fn name(self) -> &'static str {
        match self {
            Config::Emc(Preset::Fast) => "emc fast",
            Config::Emc(Preset::Balanced) => "emc balanced",
            Config::Emc(Preset::Quality) => "emc quality",
            #[cfg(feature = "peers")]
            Config::Embree(crate::peers::embree::Quality::Low) => "embree LOW",
            #[cfg(feature = "peers")]
            Config::Embree(crate::peers::embree::Quality::Medium) => "embree MEDIUM",
            #[cfg(feature = "peers")]
            Config::Obvhs => "obvhs fastest",
        }
    }

    /// True for the peers (the denominators of the ratios).
    pub fn is_peer(self) -> bool {
        !matches!(self, Config::Emc(_))
    }
}

/// Parse `--presets`: a non-empty comma-separated list of fast, balanced, quality.
pub fn parse_presets(s: &str) -> anyhow::Result<Vec<Preset>> {
    let mut out = Vec::new();
    for p in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let preset = match p {
            "fast" => Preset::Fast,
            "balanced" => Preset::Balanced,
            "quality" => Preset::Quality,
            _ => bail!("--presets: unknown preset `{p}` (fast, balanced, quality)"),
        };
        if !out.contains(&preset) {
            out.push(preset);
        }
    }
    if out.is_empty() {
        bail!("--presets names no preset (fast, balanced, quality)");
    }
    Ok(out)
}

/// Median of durations in milliseconds (mean of the middle two for an even count).
fn median_ms(v: &[Duration]) -> f64 {
    median(v.iter().map(|d| d.as_secs_f64() * 1e3).collect()).unwrap_or(f64::NAN)
}

/// The median of `x` (the mean of the middle two for an even count); `None` when empty.
fn median(mut x: Vec<f64>) -> Option<f64> {
    x.sort_by(f64::total_cmp);
    let n = x.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(x[n / 2]),
        _ => Some(0.5 * (x[n / 2 - 1] + x[n / 2])),
    }
}

/// The 1-minute load average, if the system tells it.
fn loadavg() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

fn fmt_load(l: Option<f64>) -> String {
    l.map_or_else(|| "?".into(), |l| format!("{l:.2}"))
}

/// A built structure of one configuration (an Embree scene borrows the device and the mesh;
/// the marker keeps the lifetime when the peers are compiled out).
enum Built<'a> {
    Emc(Box<Accel>, std::marker::PhantomData<&'a ()>),
    #[cfg(feature = "peers")]
    Embree(crate::peers::embree::Scene<'a>),
    #[cfg(feature = "peers")]
    Obvhs(Box<crate::peers::obvhs::Bvh>),
}

impl Built<'_> {
    fn tracer(&self) -> &dyn Tracer {
        match self {
            Built::Emc(a, _) => &**a,
            #[cfg(feature = "peers")]
            Built::Embree(s) => s,
            #[cfg(feature = "peers")]
            Built::Obvhs(b) => &**b,
        }
    }

    fn memory_bytes(&self) -> u64 {
        match self {
            Built::Emc(a, _) => a.wide_bvh().memory_bytes() as u64,
            #[cfg(feature = "peers")]
            Built::Embree(s) => s.memory_bytes().max(0) as u64,
            #[cfg(feature = "peers")]
            Built::Obvhs(b) => b.memory_bytes() as u64,
        }
    }
}

/// Everything measured of one configuration on one scene.
#[derive(Clone, Debug)]
pub struct Row {
    /// The configuration.
    pub config: Config,
    /// Median cold build, wall ms.
    pub cold_ms: f64,
    /// Median warm build, wall ms.
    pub warm_ms: f64,
    /// Median cold build, process CPU ms.
    pub cold_cpu_ms: f64,
    /// Median warm build, process CPU ms.
    pub warm_cpu_ms: f64,
    /// Median primary Mrays/s (wall).
    pub primary_mrays: f64,
    /// Median AO Mrays/s (wall).
    pub ao_mrays: f64,
    /// Median primary M rays per CPU-second of the tracing threads.
    pub primary_mrays_cpu: f64,
    /// Median AO M rays per CPU-second of the tracing threads.
    pub ao_mrays_cpu: f64,
    /// The protocol counts of this configuration's own rays.
    pub counts: AoCounts,
    /// Bytes of the traced structure.
    pub memory_bytes: u64,
    /// emc's fast path: per-phase wall ms (medians of the cold and of the warm builds) and
    /// what the structure came to, for the per-phase budget.
    pub phases: Option<FastPhases>,
}

/// Per-phase medians of the fast path's builds, and the sizes the memory traffic follows from.
#[derive(Clone, Copy, Debug)]
pub struct FastPhases {
    /// Median of the cold builds' phases.
    pub cold: FastTimes,
    /// Median of the warm builds' phases.
    pub warm: FastTimes,
    /// Triangle packets, wide nodes, node bytes, vertices, code bytes and sort passes.
    pub packets: usize,
    /// Wide nodes.
    pub nodes: usize,
    /// Bytes per wide node.
    pub node_bytes: usize,
    /// Vertices of the mesh.
    pub vertices: usize,
    /// On a pool of several threads: the same preset's cold builds there and on one thread,
    /// alternating.
    pub scaling: Option<Scaling>,
}

/// The fast path's cold builds on the run's pool and on a pool of one thread, alternating
/// build by build in the same run: for each row of [`SCALING_ROWS`], the median wall ms on one
/// thread and on the pool (rows derived from several timings, such as the blocks or the rest,
/// are computed per build, then their median taken).
#[derive(Clone, Copy, Debug)]
pub struct Scaling {
    /// Threads of the run's pool.
    pub threads: usize,
    /// Triangles of the mesh (which steps of the tree phase run in parallel depends on it).
    pub triangles: usize,
    /// Per row: median ms on one thread, then on the pool.
    pub ms: [[f64; 2]; SCALING_ROWS.len()],
}

/// The rows of [`Scaling`].
pub const SCALING_ROWS: [&str; 8] = [
    "aabb (checks, boxes, bounds)",
    "encode",
    "sort",
    "tree: partition",
    "tree: blocks",
    "tree: top (serial)",
    "rest (mesh copies, allocation)",
    "whole build (Accel)",
];

/// The rows of [`SCALING_ROWS`] of one build: its phases and its whole wall ms.
fn scaling_row(t: &FastTimes, wall: f64) -> [f64; SCALING_ROWS.len()] {
    [
        t.aabb,
        t.encode,
        t.sort,
        t.partition,
        t.tree - t.partition - t.top,
        t.top,
        wall - (t.aabb + t.encode + t.sort + t.tree),
        wall,
    ]
}

/// A parallel phase should run at least this many times its one-thread speed on two threads
/// (issue 11's target for the fast preset).
const PARALLEL_SPEEDUP_TARGET: f64 = 1.8;
/// The serial steps of the fast build should take at most this share of its one-thread time.
const SERIAL_SHARE_TARGET: f64 = 0.10;

/// [`BUILDS`] rounds (after one warm-up round) of a cold build of preset `p` on `ctx`'s pool,
/// then one on a pool of one thread: each pool with its own [`BuildContext`], every `Accel`
/// fresh and dropped before the next build of its pool, as in [`time_builds`].
fn scaling(
    p: Preset,
    ctx: &Session,
    vertices: &[Vec3],
    indices: &[[u32; 3]],
) -> anyhow::Result<Scaling> {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .context("making a one-thread pool")?;
    let opts = BuildOptions::preset(p);
    let pools = [&one, &ctx.pool];
    let mut bctx = [BuildContext::new(), BuildContext::new()];
    // rows[k][build][row]
    let mut rows: [Vec<[f64; SCALING_ROWS.len()]>; 2] = Default::default();
    for round in 0..=BUILDS {
        for k in [1, 0] {
            let c = &mut bctx[k];
            let t0 = Instant::now();
            let a = pools[k].install(|| Accel::build_in(c, vertices, indices, &opts))?;
            let ms = t0.elapsed().as_secs_f64() * 1e3;
            if round > 0 {
                rows[k].push(scaling_row(&a.build_phases(), ms));
            }
        }
    }
    Ok(Scaling {
        threads: ctx.threads,
        triangles: indices.len(),
        ms: core::array::from_fn(|r| {
            rows.each_ref()
                .map(|b| median(b.iter().map(|row| row[r]).collect()).unwrap_or(f64::NAN))
        }),
    })
}

/// Per-field medians of phase timings.
fn median_phases(v: &[FastTimes]) -> FastTimes {
    let m = |f: fn(&FastTimes) -> f64| median(v.iter().map(f).collect()).unwrap_or(0.0);
    FastTimes {
        aabb: m(|t| t.aabb),
        choose: m(|t| t.choose),
        layout: v.first().and_then(|t| t.layout),
        encode: m(|t| t.encode),
        sort: m(|t| t.sort),
        tree: m(|t| t.tree),
        partition: m(|t| t.partition),
        top: m(|t| t.top),
    }
}

/// The best peer figure of each column: lowest build ms, highest Mrays/s.
#[derive(Clone, Copy, Debug)]
pub struct Best {
    /// Lowest cold build ms of a peer.
    pub cold_ms: f64,
    /// Lowest warm build ms of a peer.
    pub warm_ms: f64,
    /// Highest primary Mrays/s of a peer.
    pub primary_mrays: f64,
    /// Highest AO Mrays/s of a peer.
    pub ao_mrays: f64,
}

/// The best peer figures among `rows`, `None` when no peer was measured.
pub fn best_peer(rows: &[Row]) -> Option<Best> {
    let peers: Vec<&Row> = rows.iter().filter(|r| r.config.is_peer()).collect();
    if peers.is_empty() {
        return None;
    }
    let min = |f: fn(&Row) -> f64| peers.iter().map(|r| f(r)).fold(f64::INFINITY, f64::min);
    let max = |f: fn(&Row) -> f64| peers.iter().map(|r| f(r)).fold(0.0, f64::max);
    Some(Best {
        cold_ms: min(|r| r.cold_ms),
        warm_ms: min(|r| r.warm_ms),
        primary_mrays: max(|r| r.primary_mrays),
        ao_mrays: max(|r| r.ao_mrays),
    })
}

/// An emc row's four ratios to the best peer: cold, warm (emc ms / peer ms: below 1 is
/// faster), primary, AO (emc Mrays/s / peer Mrays/s: above 1 is faster).
pub fn ratios(r: &Row, b: &Best) -> [f64; 4] {
    [
        r.cold_ms / b.cold_ms,
        r.warm_ms / b.warm_ms,
        r.primary_mrays / b.primary_mrays,
        r.ao_mrays / b.ao_mrays,
    ]
}

/// Median wall and CPU ms of one kind of build.
#[derive(Clone, Copy, Debug, Default)]
struct BuildMs {
    wall: f64,
    cpu: f64,
}

fn medians(t: &[Timing]) -> BuildMs {
    let wall: Vec<Duration> = t.iter().map(|t| t.wall).collect();
    let cpu: Vec<Duration> = t.iter().map(|t| t.cpu).collect();
    BuildMs {
        wall: median_ms(&wall),
        cpu: median_ms(&cpu),
    }
}

/// Process CPU time (every thread: rayon workers, Embree's) spent in `f`, with its result.
fn with_cpu<R>(f: impl FnOnce() -> R) -> (R, Duration) {
    let c0 = process_cpu_time().unwrap_or_default();
    let r = f();
    let c = process_cpu_time().unwrap_or_default().saturating_sub(c0);
    (r, c)
}

/// Cold and warm build times (wall as each build reports it, process CPU around it) of one
/// configuration; returns the kept structure.
fn time_builds<B>(
    mut cold: impl FnMut() -> anyhow::Result<(B, Duration)>,
    mut warm: impl FnMut(&mut B) -> anyhow::Result<Duration>,
) -> anyhow::Result<(B, BuildMs, BuildMs)> {
    drop(cold()?.0); // warm-up
    let mut colds = Vec::with_capacity(BUILDS);
    let mut kept: Option<B> = None;
    for _ in 0..BUILDS {
        drop(kept.take());
        let (r, cpu) = with_cpu(&mut cold);
        let (b, wall) = r?;
        colds.push(Timing { wall, cpu });
        kept = Some(b);
    }
    let Some(mut b) = kept else {
        bail!("no build was kept")
    };
    let mut warms = Vec::with_capacity(BUILDS);
    for _ in 0..BUILDS {
        let (r, cpu) = with_cpu(|| warm(&mut b));
        warms.push(Timing { wall: r?, cpu });
    }
    Ok((b, medians(&colds), medians(&warms)))
}

/// What the process holds across scenes: the emc/obvhs pool and the Embree device.
pub(crate) struct Session {
    pub(crate) threads: usize,
    pub(crate) pool: rayon::ThreadPool,
    #[cfg(feature = "peers")]
    pub(crate) device: crate::peers::embree::Device,
}

/// The configurations of a run: the presets asked for, then the peers compiled in.
fn configs(presets: &[Preset]) -> Vec<Config> {
    #[allow(unused_mut)]
    let mut c: Vec<Config> = presets.iter().map(|&p| Config::Emc(p)).collect();
    #[cfg(feature = "peers")]
    {
        use crate::peers::embree::Quality;
        c.extend([
            Config::Embree(Quality::Low),
            Config::Embree(Quality::Medium),
            Config::Obvhs,
        ]);
    }
    c
}

/// One line per configuration saying what it builds and traces.
#[cfg_attr(not(feature = "peers"), allow(unused_variables))]
fn describe(configs: &[Config], ctx: &Session) -> Vec<String> {
    configs
        .iter()
        .map(|&c| {
            let what = match c {
                Config::Emc(p) => {
                    let (b, l, r) = BuildOptions::preset(p).resolve();
                    format!(
                        "Accel::build, builder {b}, layout {l}{}, traced {}-wide",
                        if r { " + atrbvh" } else { "" },
                        crate::trace::api::default_width()
                    )
                }
                #[cfg(feature = "peers")]
                Config::Embree(q) => format!(
                    "Embree {} {} (shared buffers, RTC_SCENE_FLAG_NONE), BVH8, 4-triangle leaves",
                    ctx.device.version(),
                    match q {
                        crate::peers::embree::Quality::Low => "RTC_BUILD_QUALITY_LOW: Morton",
                        crate::peers::embree::Quality::Medium =>
                            "RTC_BUILD_QUALITY_MEDIUM: binned SAH",
                    }
                ),
                #[cfg(feature = "peers")]
                Config::Obvhs => crate::peers::obvhs::DESCRIPTION.to_string(),
            };
            format!("  {:<14} {what}", c.name())
        })
        .collect()
}

/// Build one configuration (warm-up, cold, warm).
fn build<'a>(
    c: Config,
    ctx: &'a Session,
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    #[cfg(feature = "peers")] mesh: &'a crate::peers::embree::Mesh,
) -> anyhow::Result<(Built<'a>, BuildMs, BuildMs, Option<FastPhases>)> {
    let pool = &ctx.pool;
    match c {
        Config::Emc(p) => {
            let opts = BuildOptions::preset(p);
            let (mut pc, mut pw) = (Vec::new(), Vec::new());
            // The build context is emc's device: scratch memory kept between the builds (the
            // warm-up build fills it), every structure fresh.
            let bctx = std::cell::RefCell::new(BuildContext::new());
            let bctx = &bctx;
            let (a, cold, warm) = time_builds(
                || {
                    let t0 = Instant::now();
                    let c: &mut BuildContext = &mut bctx.borrow_mut();
                    let a = pool.install(|| Accel::build_in(c, vertices, indices, &opts))?;
                    let t = t0.elapsed();
                    pc.push(a.build_phases());
                    Ok((a, t))
                },
                |a: &mut Accel| {
                    let t0 = Instant::now();
                    let c: &mut BuildContext = &mut bctx.borrow_mut();
                    pool.install(|| a.rebuild_in(c, vertices))?;
                    let t = t0.elapsed();
                    pw.push(a.build_phases());
                    Ok(t)
                },
            )?;
            // Only the fast path times a tree phase.
            let fast = a.build_phases().tree > 0.0;
            let scaling = if fast && ctx.threads > 1 {
                Some(scaling(p, ctx, vertices, indices)?)
            } else {
                None
            };
            let phases = fast.then(|| {
                let w = a.wide_bvh();
                FastPhases {
                    cold: median_phases(&pc[1..]),
                    warm: median_phases(&pw),
                    packets: w.packets.len(),
                    nodes: w.nodes.len() + w.nodes8.len(),
                    node_bytes: if w.nodes8.is_empty() { 128 } else { 256 },
                    vertices: vertices.len(),
                    scaling,
                }
            });
            Ok((
                Built::Emc(Box::new(a), std::marker::PhantomData),
                cold,
                warm,
                phases,
            ))
        }
        #[cfg(feature = "peers")]
        Config::Embree(q) => {
            use crate::peers::embree::Scene;
            let (s, cold, warm) = time_builds(
                || Ok(Scene::build(&ctx.device, mesh, q)?),
                |s: &mut Scene| Ok(s.rebuild()?),
            )?;
            Ok((Built::Embree(s), cold, warm, None))
        }
        #[cfg(feature = "peers")]
        Config::Obvhs => {
            use crate::peers::obvhs::Bvh;
            let (b, cold, warm) = time_builds(
                || Ok(pool.install(|| Bvh::build(vertices, indices))?),
                |b: &mut Bvh| Ok(pool.install(|| b.rebuild(vertices))?),
            )?;
            Ok((Built::Obvhs(Box::new(b)), cold, warm, None))
        }
    }
}

/// One scene's measurements.
struct SceneResult {
    name: String,
    ntris: usize,
    mode: CameraMode,
    rows: Vec<Row>,
    /// Load average before the builds and after the traces.
    load: [Option<f64>; 2],
}

/// Measure every configuration on one scene; prints progress on stderr, returns the rows and
/// the load averages before and after.
fn measure_scene(
    spec: &str,
    args: &CompareArgs,
    ctx: &Session,
    configs: &[Config],
) -> anyhow::Result<SceneResult> {
    let scene = load_with(
        spec,
        &SceneOptions {
            prims: args.prims,
            ..SceneOptions::default()
        },
    )
    .with_context(|| format!("loading {spec}"))?;
    let mode = match args.camera.as_deref() {
        Some(c) => c.parse::<CameraMode>().map_err(anyhow::Error::msg)?,
        None => CameraMode::for_scene(&scene.name),
    };
    let tris: Vec<[Vec3; 3]> = (0..scene.triangle_count())
        .map(|i| scene.triangle(i))
        .collect();
    let ntris = tris.len();
    let protocol = ctx.pool.install(|| Protocol::new(tris, mode, args.res));
    let load0 = loadavg();
    eprintln!(
        "# {}: {ntris} triangles, camera {mode:?}, load average {}",
        scene.name,
        fmt_load(load0)
    );
    #[cfg(feature = "peers")]
    let mesh = crate::peers::embree::Mesh::new(&scene.vertices, &scene.indices)?;
    let mut built: Vec<(Config, Built, BuildMs, BuildMs)> = Vec::with_capacity(configs.len());
    let mut phases = Vec::with_capacity(configs.len());
    for &c in configs {
        let (b, cold, warm, ph) = build(
            c,
            ctx,
            &scene.vertices,
            &scene.indices,
            #[cfg(feature = "peers")]
            &mesh,
        )
        .with_context(|| format!("{}: building {}", scene.name, c.name()))?;
        eprintln!(
            "#   {:<14} cold {:.2} ms, warm {:.2} ms",
            c.name(),
            cold.wall,
            warm.wall
        );
        built.push((c, b, cold, warm));
        phases.push(ph);
    }
    // Warm-up pass: each configuration's counts and its own AO rays.
    let threads = ctx.threads;
    let first: Vec<_> = built
        .iter()
        .map(|(_, b, _, _)| protocol.run(b.tracer(), threads))
        .collect();
    let mut prim_t = vec![Vec::with_capacity(args.runs); built.len()];
    let mut ao_t = vec![Vec::with_capacity(args.runs); built.len()];
    for _ in 0..args.runs {
        for (k, (c, b, _, _)) in built.iter().enumerate() {
            let t = b.tracer();
            let (hits, tp) = t.closest(&protocol.primary, threads);
            let n_hits = hits.iter().filter(|h| h.is_some()).count() as u64;
            drop(hits);
            let (occ, ta) = t.occluded(&first[k].ao, threads);
            if n_hits != first[k].counts.primary_hits || occ != first[k].counts.ao_occluded {
                bail!(
                    "{}: {} counted {n_hits} hits / {occ} occluded, {} / {} before",
                    scene.name,
                    c.name(),
                    first[k].counts.primary_hits,
                    first[k].counts.ao_occluded
                );
            }
            prim_t[k].push(tp);
            ao_t[k].push(ta);
        }
    }
    let load1 = loadavg();
    let mrays = |n: usize, ms: f64| n as f64 / (ms * 1e-3) * 1e-6;
    let rows = built
        .iter()
        .enumerate()
        .map(|(k, (c, b, cold, warm))| {
            let (p, a) = (medians(&prim_t[k]), medians(&ao_t[k]));
            let (np, na) = (protocol.primary.len(), first[k].ao.len());
            Row {
                config: *c,
                cold_ms: cold.wall,
                warm_ms: warm.wall,
                cold_cpu_ms: cold.cpu,
                warm_cpu_ms: warm.cpu,
                primary_mrays: mrays(np, p.wall),
                ao_mrays: mrays(na, a.wall),
                primary_mrays_cpu: mrays(np, p.cpu),
                ao_mrays_cpu: mrays(na, a.cpu),
                counts: first[k].counts,
                memory_bytes: b.memory_bytes(),
                phases: phases[k],
            }
        })
        .collect();
    Ok(SceneResult {
        name: scene.name.clone(),
        ntris,
        mode,
        rows,
        load: [load0, load1],
    })
}

fn ratio_cell(x: Option<f64>) -> String {
    x.map_or_else(|| "—".into(), |x| format!("{x:.2}×"))
}

/// Print one scene's table.
fn print_table(name: &str, ntris: usize, mode: CameraMode, rows: &[Row], args: &CompareArgs) {
    let best = best_peer(rows);
    println!();
    println!(
        "{name}: {ntris} triangles, camera {mode:?}, {}×{} primary rays, {} thread{}, medians of {BUILDS} builds and {} trace runs",
        args.res,
        args.res,
        args.threads,
        if args.threads == 1 { "" } else { "s" },
        args.runs
    );
    println!(
        "{:<14} {:>9} {:>7} {:>9} {:>7} {:>9} {:>7} {:>9} {:>7} {:>9} {:>9} {:>9} {:>8}",
        "config",
        "cold ms",
        "/best",
        "warm ms",
        "/best",
        "prim Mr/s",
        "/best",
        "AO Mr/s",
        "/best",
        "prim hits",
        "AO rays",
        "AO occl",
        "mem MiB"
    );
    for r in rows {
        let q = match (&best, r.config.is_peer()) {
            (Some(b), false) => ratios(r, b).map(Some),
            _ => [None; 4],
        };
        println!(
            "{:<14} {:>9.2} {:>7} {:>9.2} {:>7} {:>9.2} {:>7} {:>9.2} {:>7} {:>9} {:>9} {:>9} {:>8.1}",
            r.config.name(),
            r.cold_ms,
            ratio_cell(q[0]),
            r.warm_ms,
            ratio_cell(q[1]),
            r.primary_mrays,
            ratio_cell(q[2]),
            r.ao_mrays,
            ratio_cell(q[3]),
            r.counts.primary_hits,
            r.counts.ao_rays,
            r.counts.ao_occluded,
            r.memory_bytes as f64 / (1u64 << 20) as f64
        );
    }
    println!("the same per CPU time (which other tenants of a shared machine cannot take):");
    println!(
        "{:<14} {:>11} {:>11} {:>13} {:>13}",
        "config", "cold cpu ms", "warm cpu ms", "prim Mr/cpu-s", "AO Mr/cpu-s"
    );
    for r in rows {
        println!(
            "{:<14} {:>11.2} {:>11.2} {:>13.2} {:>13.2}",
            r.config.name(),
            r.cold_cpu_ms,
            r.warm_cpu_ms,
            r.primary_mrays_cpu,
            r.ao_mrays_cpu
        );
    }
    print_targets(rows, ntris);
    match best {
        Some(_) => println!(
            "/best: emc's figure over the best peer's of this run (build: lowest ms, below 1 is faster; Mrays/s: highest, above 1 is faster)"
        ),
        None => println!(
            "no peer measured: the peers (Embree 3 LOW/MEDIUM, obvhs) need `--features peers` \
             (cargo run --release -p emc-cpu --features peers -- compare ...)"
        ),
    }
}

/// The targets against the Embree row they name (same run): the fast preset against
/// Embree LOW (cold ≤ 0.5×, warm ≤ 0.25×), quality and balanced against Embree MEDIUM (cold
/// ≤ 1.0×); then the fast path's per-phase budget in ns per triangle beside the bytes per
/// triangle each phase must at least move, and on several threads its phases against one
/// thread ([`Scaling`]).
fn print_targets(rows: &[Row], ntris: usize) {
    let find = |name: &str| rows.iter().find(|r| r.config.name() == name);
    let (low, medium) = (find("embree LOW"), find("embree MEDIUM"));
    for r in rows.iter().filter(|r| !r.config.is_peer()) {
        let (peer, cold_t, warm_t) = if r.config.name() == "emc fast" {
            (low, 0.5, Some(0.25))
        } else {
            (medium, 1.0, None)
        };
        let Some(p) = peer else { continue };
        let warm = warm_t.map_or(String::new(), |t| {
            format!(", warm {:.2}× (target ≤ {t}×)", r.warm_ms / p.cold_ms)
        });
        println!(
            "target {}: cold {:.2}× {} (target ≤ {cold_t}×){warm}",
            r.config.name(),
            r.cold_ms / p.cold_ms,
            p.config.name(),
        );
    }
    let Some((r, ph)) = rows.iter().find_map(|r| r.phases.map(|p| (r, p))) else {
        return;
    };
    let n = ntris.max(1) as f64;
    let ns = |ms: f64| ms * 1e6 / n;
    let per = |x: usize| x as f64 / n;
    // Bytes per triangle each phase reads and writes at least (first touch of fresh memory
    // not counted): indices 12 and the gathered corners, boxes 24, codes 4 (emc32-var), the
    // sort's (code, id) pairs read and written per pass, the packets and nodes written.
    let corners = 12.0 * per(ph.vertices).min(3.0);
    let traffic = [
        (
            "aabb (checks, boxes, bounds)",
            12.0 + corners + 24.0 + 12.0 * per(ph.vertices),
        ),
        ("encode", 24.0 + 4.0),
        ("sort (cold ≈ 4 passes)", 4.0 * 2.0 * 8.0),
        (
            "tree (blocks, packets, top)",
            4.0 + 4.0
                + 12.0
                + 36.0
                + per(ph.packets) * 176.0
                + per(ph.nodes) * ph.node_bytes as f64,
        ),
    ];
    let cold = [ph.cold.aabb, ph.cold.encode, ph.cold.sort, ph.cold.tree];
    let warm = [ph.warm.aabb, ph.warm.encode, ph.warm.sort, ph.warm.tree];
    let (isa, why) = crate::trace::wide_lbvh::tree_isa();
    println!(
        "{} per phase, ns per triangle (medians; the rest of the build, copies of the mesh and allocation, is the difference to the total; block builders: {isa}, {why}):",
        r.config.name()
    );
    println!(
        "{:<30} {:>9} {:>9} {:>12}",
        "phase", "cold", "warm", "bytes/tri"
    );
    for (i, (name, b)) in traffic.iter().enumerate() {
        println!(
            "{name:<30} {:>9.1} {:>9.1} {b:>12.0}",
            ns(cold[i]),
            ns(warm[i])
        );
    }
    let sum = |v: &[f64; 4]| v.iter().sum::<f64>();
    println!(
        "{:<30} {:>9.1} {:>9.1}",
        "phases",
        ns(sum(&cold)),
        ns(sum(&warm))
    );
    println!(
        "{:<30} {:>9.1} {:>9.1}",
        "whole build (Accel)",
        ns(r.cold_ms),
        ns(r.warm_ms)
    );
    if let Some(p) = low {
        println!(
            "{:<30} {:>9.1} {:>9.1}   (0.5× and 0.25× of embree LOW's cold build)",
            "budget",
            ns(0.5 * p.cold_ms),
            ns(0.25 * p.cold_ms)
        );
    }
    println!(
        "(warm = rebuilds over the same vertices: the fast preset's sort keeps the last order and \
         sorts only changed codes, here none; a moving mesh changes them: see --frames)"
    );
    if let Some(sc) = ph.scaling {
        print_scaling(r.config.name(), &sc);
    }
}

/// The fast path's phases on the run's pool against one thread (same run, alternating builds),
/// and how they stand against the two-thread targets.
fn print_scaling(name: &str, sc: &Scaling) {
    for line in scaling_lines(name, sc) {
        println!("{line}");
    }
}

/// The lines of [`print_scaling`]. Which rows run in parallel: the boxes, codes and sort
/// always; the partition when the mesh has more than
/// [`crate::trace::wide_lbvh::PARTITION_PAR_MIN`] triangles (its top halves), the blocks when
/// there are several; the top never (rows not in parallel count as serial). The rest
/// (copies, allocation) is shown, not judged.
fn scaling_lines(name: &str, sc: &Scaling) -> Vec<String> {
    use crate::trace::wide_lbvh::{BLOCK, PARTITION_PAR_MIN};
    let n = sc.triangles;
    let parallel = [
        Some(true),
        Some(true),
        Some(true),
        Some(n > PARTITION_PAR_MIN as usize),
        Some(n > BLOCK as usize),
        Some(false),
        None,
        None,
    ];
    let threads = sc.threads;
    // One-thread ms over the pool's; undefined when either is not positive.
    let speedup = |[a, b]: [f64; 2]| (a > 0.0 && b > 0.0).then(|| a / b);
    let mut out = vec![
        format!(
            "{name} on {threads} threads against 1 thread (the same run, cold builds \
             alternating between the two pools, medians of {BUILDS}; speedup = one-thread ms \
             / {threads}-thread ms):"
        ),
        format!(
            "{:<30} {:>11} {:>11} {:>8}  runs",
            "phase",
            "1 thread ms",
            format!("{threads} thr. ms"),
            "speedup"
        ),
    ];
    for (r, &label) in SCALING_ROWS.iter().enumerate() {
        let [a, b] = sc.ms[r];
        let how = match parallel[r] {
            Some(true) => "in parallel",
            Some(false) => "serially",
            None => "",
        };
        out.push(format!(
            "{label:<30} {a:>11.2} {b:>11.2} {:>8}  {how}",
            speedup(sc.ms[r]).map_or("—".to_string(), |x| format!("{x:.2}×"))
        ));
    }
    let slow: Vec<String> = (0..SCALING_ROWS.len())
        .filter(|&r| parallel[r] == Some(true))
        .filter_map(|r| {
            let x = speedup(sc.ms[r])?;
            (x < PARALLEL_SPEEDUP_TARGET).then(|| format!("{} {x:.3}×", SCALING_ROWS[r]))
        })
        .collect();
    let one_ms = sc.ms[SCALING_ROWS.len() - 1][0];
    let serial: f64 = (0..SCALING_ROWS.len())
        .filter(|&r| parallel[r] == Some(false))
        .map(|r| sc.ms[r][0])
        .sum();
    let share = |x: f64| 100.0 * x / one_ms;
    out.push(format!(
        "parallel phases under {PARALLEL_SPEEDUP_TARGET}× ({}): {}; the serial steps {:.1}% of \
         the one-thread build (target ≤ {:.0}%), the rest {:.1}%",
        if threads == 2 {
            "target: none"
        } else {
            "the target is set for 2 threads"
        },
        if slow.is_empty() {
            "none".to_string()
        } else {
            slow.join(", ")
        },
        share(serial),
        100.0 * SERIAL_SHARE_TARGET,
        share(sc.ms[SCALING_ROWS.len() - 2][0]),
    ));
    out
}

/// CSV header of `--csv`.
pub const CSV_HEADER: &str = "scene,tris,camera,config,peer,threads,res,runs,build_cold_ms,build_warm_ms,build_cold_cpu_ms,build_warm_cpu_ms,primary_mrays,ao_mrays,primary_mrays_cpu,ao_mrays_cpu,primary_hits,ao_rays,ao_occluded,mem_bytes,cold_vs_best_peer,warm_vs_best_peer,primary_vs_best_peer,ao_vs_best_peer,loadavg_start,loadavg_end";

/// Run `emc compare`.
pub fn run(args: &CompareArgs) -> anyhow::Result<()> {
    if args.threads == 0 || args.threads > 1024 {
        bail!("--threads must be in 1..=1024");
    }
    if args.runs == 0 || args.runs > 1000 {
        bail!("--runs must be in 1..=1000");
    }
    if args.res == 0 || args.res > 16384 {
        bail!("--res must be in 1..=16384");
    }
    let presets = parse_presets(&args.presets)?;
    if let Some(c) = args.camera.as_deref() {
        c.parse::<CameraMode>().map_err(anyhow::Error::msg)?;
    }
    let ctx = Session {
        threads: args.threads,
        pool: rayon::ThreadPoolBuilder::new()
            .num_threads(args.threads)
            .build()
            .context("creating the thread pool")?,
        #[cfg(feature = "peers")]
        device: crate::peers::embree::Device::new(args.threads)?,
    };
    if let Some(n) = args.frames {
        println!(
            "emc compare --frames: {} thread{}, load average {}",
            args.threads,
            if args.threads == 1 { "" } else { "s" },
            fmt_load(loadavg())
        );
        crate::cli::frames::run(args, &ctx, n)?;
        println!("load average {} after", fmt_load(loadavg()));
        return Ok(());
    }
    if let Some(n) = args.instances {
        println!(
            "emc compare --instances: {} thread{}, load average {}",
            args.threads,
            if args.threads == 1 { "" } else { "s" },
            fmt_load(loadavg())
        );
        crate::cli::instances::run(args, &ctx, n)?;
        println!("load average {} after", fmt_load(loadavg()));
        return Ok(());
    }
    let mut csv = match &args.csv {
        Some(p) => {
            let mut f = std::io::BufWriter::new(
                std::fs::File::create(p).with_context(|| format!("creating {p}"))?,
            );
            writeln!(f, "{CSV_HEADER}").with_context(|| format!("writing {p}"))?;
            Some((p, f))
        }
        None => None,
    };
    let configs = configs(&presets);
    println!(
        "emc compare: {} thread{}, load average {}; configurations:",
        args.threads,
        if args.threads == 1 { "" } else { "s" },
        fmt_load(loadavg())
    );
    for l in describe(&configs, &ctx) {
        println!("{l}");
    }
    if !configs.iter().any(|c| c.is_peer()) {
        println!(
            "peers: not built in; Embree 3 and obvhs need `--features peers` \
             (cargo run --release -p emc-cpu --features peers -- compare ...)"
        );
    }
    for spec in &args.scenes {
        let SceneResult {
            name,
            ntris,
            mode,
            rows,
            load: [l0, l1],
        } = measure_scene(spec, args, &ctx, &configs)?;
        print_table(&name, ntris, mode, &rows, args);
        println!(
            "load average {} before, {} after the traces",
            fmt_load(l0),
            fmt_load(l1)
        );
        if let Some((p, f)) = &mut csv {
            let best = best_peer(&rows);
            for r in &rows {
                let q = match (&best, r.config.is_peer()) {
                    (Some(b), false) => ratios(r, b).map(|x| format!("{x:.4}")),
                    _ => Default::default(),
                };
                writeln!(
                    f,
                    "{name},{ntris},{},{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{},{},{}",
                    match mode {
                        CameraMode::Outside => "outside",
                        CameraMode::Center => "center",
                    },
                    r.config.name(),
                    r.config.is_peer() as u8,
                    args.threads,
                    args.res,
                    args.runs,
                    r.cold_ms,
                    r.warm_ms,
                    r.cold_cpu_ms,
                    r.warm_cpu_ms,
                    r.primary_mrays,
                    r.ao_mrays,
                    r.primary_mrays_cpu,
                    r.ao_mrays_cpu,
                    r.counts.primary_hits,
                    r.counts.ao_rays,
                    r.counts.ao_occluded,
                    r.memory_bytes,
                    q[0],
                    q[1],
                    q[2],
                    q[3],
                    l0.map_or(String::new(), |l| format!("{l:.2}")),
                    l1.map_or(String::new(), |l| format!("{l:.2}")),
                )
                .with_context(|| format!("writing {p}"))?;
            }
            f.flush().with_context(|| format!("writing {p}"))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scaling report divides the one-thread figure by the pool's, derives the blocks and
    /// the rest per build, names exactly the parallel phases below the target, counts the top
    /// (and a partition without parallel halves) as serial, and shows an undefined speed-up
    /// as a dash.
    #[test]
    fn scaling_lines_report_speedups_and_shares() {
        let t = |aabb, encode, sort, tree, partition, top| FastTimes {
            aabb,
            encode,
            sort,
            tree,
            partition,
            top,
            ..FastTimes::default()
        };
        let one = scaling_row(&t(4.0, 4.0, 10.0, 20.0, 2.0, 1.0), 40.0);
        let many = scaling_row(&t(2.0, 2.5, 5.0, 10.5, 1.0, 1.0), 21.0);
        let report = |triangles: usize| {
            let sc = Scaling {
                threads: 2,
                triangles,
                ms: core::array::from_fn(|r| [one[r], many[r]]),
            };
            scaling_lines("emc fast", &sc)
        };
        let lines = report(1 << 20);
        let row = |lines: &[String], name: &str| {
            lines
                .iter()
                .find(|l| l.starts_with(name))
                .unwrap_or_else(|| panic!("no row {name}: {lines:#?}"))
                .clone()
        };
        let r = |name: &str| row(&lines, name);
        assert!(r("aabb").contains(" 4.00 ") && r("aabb").contains(" 2.00 "));
        assert!(r("aabb").contains("2.00×"), "{lines:#?}");
        assert!(r("encode").contains("1.60×"), "{lines:#?}");
        // Blocks: 20 − 2 − 1 = 17 ms on one thread, 10.5 − 1 − 1 = 8.5 on two.
        assert!(r("tree: blocks").contains(" 17.00 ") && r("tree: blocks").contains("2.00×"));
        // The rest: 40 − 38 = 2 ms against 21 − 20 = 1 ms.
        assert!(r("rest").contains(" 2.00 ") && r("rest").contains(" 1.00 "));
        assert!(r("whole build").contains("1.90×"));
        let last = lines.last().expect("lines");
        assert!(last.contains("target: none"), "{last}");
        assert!(last.contains("encode 1.600×"), "{last}");
        for fast_or_serial in ["aabb", "sort ", "blocks", "partition", "top"] {
            assert!(!last.contains(fast_or_serial), "{fast_or_serial}: {last}");
        }
        assert!(
            last.contains("serial steps 2.5%") && last.contains("rest 5.0%"),
            "{last}"
        );
        // A mesh of one block: its partition and its block run serially (2 + 17 + 1 of 40 ms
        // with the top), and a top of 0 ms has no speed-up.
        let small = report(1000);
        assert!(
            small.last().unwrap().contains("serial steps 50.0%"),
            "{small:#?}"
        );
        assert!(row(&small, "tree: partition").ends_with("serially"));
        assert!(row(&small, "tree: blocks").ends_with("serially"));
        // Over one block but too small for parallel halves: only the partition is serial.
        let mid = report(100_000);
        assert!(
            mid.last().unwrap().contains("serial steps 7.5%"),
            "{mid:#?}"
        );
        let mut zero = many;
        zero[5] = 0.0;
        let sc = Scaling {
            threads: 4,
            triangles: 1000,
            ms: core::array::from_fn(|r| [one[r], zero[r]]),
        };
        let lines = scaling_lines("emc fast", &sc);
        assert!(row(&lines, "tree: top").contains("—"), "{lines:#?}");
        assert!(lines.last().unwrap().contains("set for 2 threads"));
    }
}
