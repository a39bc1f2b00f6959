//! The BVH build pipeline driver: triangles → boxes → frame → codes → radix sort → hierarchy
//! (Karras or Apetrei) → bounds → SAH collapse, optionally with treelet restructuring (`atrbvh`),
//! or the binned-SAH reference, on a local rayon pool, timing every phase in wall and thread-CPU
//! milliseconds.
#![forbid(unsafe_code)]

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use emc_core::{Aabb, Encoder, Frame, LayoutSpec, Normalization, SceneBounds};

use crate::auto::{AutoChoice, AutoError, LayoutChoice};
use rayon::prelude::*;

use crate::bvh::apetrei::build_apetrei;
use crate::bvh::atrbvh::{restructure, AtrConfig, AtrError};
use crate::bvh::binned_sah::{
    build_binned_sah, build_binned_sah_leaves, BinnedSahError, LeafRule, DEFAULT_BINS,
};
use crate::bvh::collapse::{collapse_bvh, emit};
use crate::bvh::karras::build_karras;
use crate::bvh::refit::{gather_sorted, refit, CollapseParams, RadixTree};
use crate::bvh::sweep::{sweep_tree, sweep_tree_in, SweepScratch};
use crate::bvh::{sah_cost, sah_headline, Bvh, Node, SahConstants};
use crate::scene::Mesh;
use crate::sort::{sort_with_ids, RadixKey, SortError, SortReport};

/// Boxes per rayon task in the frame and encode phases.
const CHUNK: usize = 1 << 14;

/// Most primitives a build accepts (leaf ids `n − 1 + p` must fit a `u32` below the flag bit).
pub const MAX_PRIMS: usize = (1 << 31) - 1;

/// A hierarchy builder.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Builder {
    /// The Karras 2012 radix tree (`lbvh`), built with bounds and collapse decisions by the
    /// one-pass split sweep of `bvh::sweep` (the same tree as Karras' top-down construction and
    /// its bottom-up refit, which [`lbvh_tree`] keeps for comparison).
    Lbvh,
    /// Apetrei 2014: the same tree, topology and bounds in one bottom-up pass (`lbvh-apetrei`).
    LbvhApetrei,
    /// Top-down binned SAH, 32 bins, the quality reference (`binned-sah`).
    BinnedSah,
    /// Karras LBVH with one primitive per leaf, agglomerative treelet restructuring (treelets of
    /// 9, 2 iterations), then the SAH collapse (`atrbvh`).
    Atrbvh,
}

impl Builder {
    /// All builders, in the order reports list them.
    pub const ALL: [Builder; 4] = [
        Builder::Lbvh,
        Builder::LbvhApetrei,
        Builder::BinnedSah,
        Builder::Atrbvh,
    ];

    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Builder::Lbvh => "lbvh",
            Builder::LbvhApetrei => "lbvh-apetrei",
            Builder::BinnedSah => "binned-sah",
            Builder::Atrbvh => "atrbvh",
        }
    }
}

impl fmt::Display for Builder {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Builder {
    type Err = BuildError;
    fn from_str(s: &str) -> Result<Self, BuildError> {
        Builder::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or_else(|| BuildError::UnknownBuilder(s.to_string()))
    }
}

/// Everything that can stop a build.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// A builder name that is not `lbvh`, `lbvh-apetrei`, `binned-sah` or `atrbvh`.
    #[error("unknown builder `{0}` (expected lbvh, lbvh-apetrei, binned-sah or atrbvh)")]
    UnknownBuilder(String),
    /// `threads` of 0.
    #[error("the thread count must be at least 1")]
    ZeroThreads,
    /// A maximum leaf size of 0.
    #[error("the maximum leaf size must be at least 1")]
    ZeroLeafSize,
    /// The thread pool could not be created.
    #[error("cannot create a pool of {threads} threads: {msg}")]
    Pool {
        /// Threads asked for.
        threads: usize,
        /// Why.
        msg: String,
    },
    /// No primitives.
    #[error("the scene has no primitives")]
    Empty,
    /// More primitives than the node ids can address.
    #[error("{0} primitives exceed the {MAX_PRIMS} a build supports")]
    TooMany(usize),
    /// Bad primitive boxes or a layout problem.
    #[error(transparent)]
    Core(#[from] emc_core::Error),
    /// The radix sort refused its input.
    #[error(transparent)]
    Sort(#[from] SortError),
    /// The binned-SAH builder refused its input.
    #[error(transparent)]
    Binned(#[from] BinnedSahError),
    /// The treelet restructuring refused its input.
    #[error(transparent)]
    Atr(#[from] AtrError),
    /// The automatic layout choice failed.
    #[error(transparent)]
    Auto(#[from] AutoError),
}

/// Options of the measured BVH2 pipeline ([`build_aabbs`], [`build_scene`]; what `emc build`
/// and `emc paper` time phase by phase). It runs in a pool of its own with `threads` threads,
/// so that it can read each thread's CPU clock, and returns the binary tree with its report.
/// A library user who wants a tree to trace builds an [`Accel`](crate::Accel) with
/// [`BuildOptions`](crate::BuildOptions) instead (the caller's pool, the wide tree).
///
/// ```
/// use emc_cpu::build::{Builder, PipelineOptions};
/// use emc_cpu::bvh::refit::CollapseParams;
///
/// let opts = PipelineOptions::default()
///     .with_builder(Builder::Atrbvh)
///     .with_threads(2)
///     .with_collapse(CollapseParams::NONE);
/// assert_eq!(opts.collapse.max_leaf, 1);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct PipelineOptions {
    /// Code layout, fixed or `auto` (ignored by `binned-sah`).
    pub layout: LayoutChoice,
    /// Hierarchy builder.
    pub builder: Builder,
    /// Threads of the pipeline's own pool (≥ 1).
    pub threads: usize,
    /// Collapse constants and maximum leaf size (`max_leaf = 1` keeps one primitive per leaf).
    pub collapse: CollapseParams,
}

impl Default for PipelineOptions {
    /// `emc64-var`, `lbvh`, 1 thread, `Ct = 1.2`, `Ci = 1`, leaves of at most 8.
    fn default() -> Self {
        PipelineOptions {
            layout: LayoutChoice::Fixed(LayoutSpec::Emc64Var),
            builder: Builder::Lbvh,
            threads: 1,
            collapse: CollapseParams::default(),
        }
    }
}

impl PipelineOptions {
    /// With this code layout (a [`LayoutSpec`] or a [`LayoutChoice`]).
    #[inline]
    pub fn with_layout(mut self, layout: impl Into<LayoutChoice>) -> Self {
        self.layout = layout.into();
        self
    }

    /// With this hierarchy builder.
    #[inline]
    pub fn with_builder(mut self, builder: Builder) -> Self {
        self.builder = builder;
        self
    }

    /// With this many threads in the pipeline's pool.
    #[inline]
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads;
        self
    }

    /// With these collapse constants and leaf limit.
    #[inline]
    pub fn with_collapse(mut self, collapse: CollapseParams) -> Self {
        self.collapse = collapse;
        self
    }
}

/// The pipeline phases, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Phase {
    /// Triangle boxes.
    Aabb,
    /// Mesh frame (parallel reduction) and codes.
    Encode,
    /// Radix sort of (code, index) pairs.
    Sort,
    /// Topology (Apetrei: topology, bounds and collapse decisions in one pass; binned SAH: the
    /// whole top-down build).
    Hierarchy,
    /// Bottom-up bounds with the collapse decisions (Karras only).
    Bounds,
    /// Treelet restructuring of the one-primitive-per-leaf tree (`atrbvh` only).
    Optimize,
    /// Writing the collapsed BVH.
    Collapse,
}

impl Phase {
    /// All phases in pipeline order.
    pub const ALL: [Phase; 7] = [
        Phase::Aabb,
        Phase::Encode,
        Phase::Sort,
        Phase::Hierarchy,
        Phase::Bounds,
        Phase::Optimize,
        Phase::Collapse,
    ];

    /// Short name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Aabb => "aabb",
            Phase::Encode => "encode",
            Phase::Sort => "sort",
            Phase::Hierarchy => "hierarchy",
            Phase::Bounds => "bounds",
            Phase::Optimize => "optimize",
            Phase::Collapse => "collapse",
        }
    }
}

/// Time spent in one phase.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PhaseTime {
    /// Wall-clock milliseconds.
    pub wall_ms: f64,
    /// CPU milliseconds summed over the pool's threads.
    pub cpu_ms: f64,
    /// CPU milliseconds of the phase's serial part, from per-thread accounting: with `T`
    /// threads whose CPU times in the phase are `c_1..c_T` (busiest `c_max`) and whose times
    /// spent runnable but waiting for a core are `q_1..q_T`, `S = Σ_{i ≠ max} max(0, c_max − c_i
    /// − q_i) / (T − 1)`: the CPU time the busiest thread spent while the others had no work of
    /// the phase (for `T = 2` exactly that; for more threads their average). Load imbalance
    /// counts as serial; time a thread was kept off its core by other tenants does not (the
    /// busiest thread took that share of the work); a waiting thread's brief spinning counts as
    /// work, so `S` errs low by that. Summed over the phase's runs; equal to `cpu_ms` on one
    /// thread.
    pub serial_cpu_ms: f64,
}

impl PhaseTime {
    /// The phase's serial share `serial_cpu_ms / cpu_ms` (0 when the phase did not run): the
    /// fraction of its work that ran while the other threads had none (1 on a one-thread pool).
    /// Amdahl's law then bounds its speed-up on `T` threads by `1 / (s + (1 − s)/T)`.
    pub fn serial_share(&self) -> f64 {
        if self.cpu_ms > 0.0 {
            (self.serial_cpu_ms / self.cpu_ms).clamp(0.0, 1.0)
        } else {
            0.0
        }
    }
}

/// What a build measured and produced (besides the BVH).
#[derive(Clone, Debug, PartialEq)]
pub struct BuildReport {
    /// Primitives built over.
    pub prims: usize,
    /// Threads of the pool.
    pub threads: usize,
    /// Builder used.
    pub builder: Builder,
    /// The resolved layout, as the seed prints it (`None` for binned SAH).
    pub layout: Option<String>,
    /// Time per phase, indexed like [`Phase::ALL`].
    pub phases: [PhaseTime; 7],
    /// Radix sort passes done and skipped.
    pub sort: SortReport,
    /// Nodes of the collapsed BVH.
    pub nodes: usize,
    /// Leaves of the collapsed BVH.
    pub leaves: usize,
    /// Depth of the collapsed BVH (edges, root to deepest leaf).
    pub depth: usize,
    /// Headline SAH: `Ct = Ci = 1`, one primitive per leaf (before collapse).
    pub sah_headline: f64,
    /// SAH of the collapsed BVH with the collapse constants.
    pub sah_collapsed: f64,
    /// What `auto` chose and why (`None` for a fixed layout).
    pub auto: Option<AutoChoice>,
    /// Time of the automatic choice (part of the `encode` phase; zero for a fixed layout).
    pub auto_time: PhaseTime,
}

impl BuildReport {
    /// Sum of the phases.
    pub fn total(&self) -> PhaseTime {
        let mut t = PhaseTime::default();
        for p in &self.phases {
            t.wall_ms += p.wall_ms;
            t.cpu_ms += p.cpu_ms;
            t.serial_cpu_ms += p.serial_cpu_ms;
        }
        t
    }

    /// Time of one phase.
    pub fn phase(&self, p: Phase) -> PhaseTime {
        self.phases[p as usize]
    }

    /// Million primitives per thread-CPU-second, boxes to collapsed BVH.
    pub fn mprims_per_cpu_s(&self) -> f64 {
        let cpu = self.total().cpu_ms;
        if cpu > 0.0 {
            self.prims as f64 / cpu / 1e3
        } else {
            0.0
        }
    }

    /// Million primitives per wall-clock second.
    pub fn mprims_per_wall_s(&self) -> f64 {
        let w = self.total().wall_ms;
        if w > 0.0 {
            self.prims as f64 / w / 1e3
        } else {
            0.0
        }
    }
}

/// A finished build.
#[derive(Clone, Debug)]
pub struct BuildOutput {
    /// The collapsed BVH (depth-first order, root 0).
    pub bvh: Bvh,
    /// The primitive boxes it was built over (index = primitive id).
    pub aabbs: Vec<Aabb>,
    /// Timings and figures.
    pub report: BuildReport,
}

/// A local pool plus the phase clock; or, for library builds, no pool of its own (the caller's
/// pool runs everything), wall times only and no SAH figures.
struct Timed {
    pool: Option<rayon::ThreadPool>,
    threads: usize,
    phases: [PhaseTime; 7],
    metrics: bool,
}

impl Timed {
    fn new(threads: usize) -> Result<Timed, BuildError> {
        if threads == 0 {
            return Err(BuildError::ZeroThreads);
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| BuildError::Pool {
                threads,
                msg: e.to_string(),
            })?;
        Ok(Timed {
            pool: Some(pool),
            threads,
            phases: [PhaseTime::default(); 7],
            metrics: true,
        })
    }

    /// Run in the caller's pool, without CPU accounting or SAH figures.
    fn inline() -> Timed {
        Timed {
            pool: None,
            threads: rayon::current_num_threads(),
            phases: [PhaseTime::default(); 7],
            metrics: false,
        }
    }

    /// A figure only reports need (0 when the build takes none).
    fn metric(&self, f: impl FnOnce() -> f64 + Send) -> f64 {
        match (&self.pool, self.metrics) {
            (Some(p), true) => p.install(f),
            _ => 0.0,
        }
    }

    /// CPU and run-queue-wait milliseconds of every pool thread so far (by thread index).
    fn thread_times(&self) -> Vec<(f64, f64)> {
        let Some(pool) = &self.pool else {
            return Vec::new();
        };
        crate::cputime::pool_thread_times(pool)
            .into_iter()
            .map(|(c, w)| (c.as_secs_f64() * 1e3, w.as_secs_f64() * 1e3))
            .collect()
    }

    /// Run `f` in the pool as phase `p` (times add up if a phase runs twice).
    fn run<R: Send>(&mut self, p: Phase, f: impl FnOnce() -> R + Send) -> R {
        let c0 = self.thread_times();
        let t0 = Instant::now();
        let r = match &self.pool {
            Some(pool) => pool.install(f),
            None => f(),
        };
        let wall = t0.elapsed().as_secs_f64() * 1e3;
        let c1 = self.thread_times();
        let used: Vec<(f64, f64)> = c1
            .iter()
            .zip(&c0)
            .map(|(b, a)| (b.0 - a.0, b.1 - a.1))
            .collect();
        let cpu: f64 = used.iter().map(|u| u.0).sum();
        let serial = serial_cpu(&used);
        let slot = &mut self.phases[p as usize];
        slot.wall_ms += wall;
        slot.cpu_ms += cpu;
        slot.serial_cpu_ms += serial;
        r
    }
}

/// Serial CPU milliseconds of a phase from each thread's `(CPU, run-queue wait)` during it (see
/// [`PhaseTime::serial_cpu_ms`]): the busiest thread's CPU time beyond each other thread's, less
/// the time that other thread waited for a core (it wanted to work but another tenant held the
/// core, so the busiest one took its share: not serial work), averaged over the `T − 1` others.
fn serial_cpu(used: &[(f64, f64)]) -> f64 {
    let cpu: f64 = used.iter().map(|u| u.0).sum();
    if used.len() < 2 {
        return cpu;
    }
    let (busiest, top) =
        used.iter().enumerate().fold(
            (0, f64::MIN),
            |b, (i, u)| if u.0 > b.1 { (i, u.0) } else { b },
        );
    let idle: f64 = used
        .iter()
        .enumerate()
        .filter(|&(i, _)| i != busiest)
        .map(|(_, u)| (top - u.0 - u.1).max(0.0))
        .sum();
    (idle / (used.len() - 1) as f64).clamp(0.0, cpu)
}

/// Mesh bounds of the boxes by a parallel reduction in fixed chunks.
pub fn scene_bounds(aabbs: &[Aabb]) -> Result<SceneBounds, emc_core::Error> {
    aabbs
        .par_chunks(CHUNK)
        .enumerate()
        .map(|(k, c)| SceneBounds::of(c, k * CHUNK))
        .try_reduce(|| SceneBounds::EMPTY, |a, b| Ok(a.merge(&b)))
}

/// The encoder of `layout` for the boxes' frame (positions normalised to the centroid box).
pub fn encoder_for(aabbs: &[Aabb], layout: &LayoutSpec) -> Result<Encoder, BuildError> {
    if aabbs.is_empty() {
        return Err(BuildError::Empty);
    }
    let frame = Frame::from_bounds(scene_bounds(aabbs)?, Normalization::CentroidBox)?;
    Ok(Encoder::new(layout, &frame))
}

/// Codes of the boxes in parallel (64-bit words for every layout).
pub fn encode_codes(enc: &Encoder, aabbs: &[Aabb]) -> Result<Vec<u64>, BuildError> {
    let mut codes = crate::buffers::filled(aabbs.len(), 0u64);
    crate::encode::encode_parallel(enc, aabbs, &mut codes)?;
    Ok(codes)
}

/// Sort codes with their primitive ids: returns (sorted codes, ids in sorted order).
pub fn sort_codes<K: RadixKey>(
    mut keys: Vec<K>,
) -> Result<(Vec<K>, Vec<u32>, SortReport), BuildError> {
    let mut ids: Vec<u32> = Vec::new();
    let r = sort_with_ids(&mut keys, &mut ids, &mut Vec::new(), &mut Vec::new())?;
    Ok((keys, ids, r))
}

/// The radix tree of sorted codes by the chosen LBVH builder, finished by the bottom-up pass
/// (bounds, counts, collapse decisions); `sorted[p]` is the box at sorted position `p` (see
/// [`gather_sorted`]). Not for [`Builder::BinnedSah`] or [`Builder::Atrbvh`] (treated as `lbvh`).
pub fn lbvh_tree<K: RadixKey>(
    builder: Builder,
    keys: &[K],
    sorted: &[Aabb],
    k: &CollapseParams,
) -> RadixTree {
    match builder {
        Builder::LbvhApetrei => build_apetrei(keys, sorted, k),
        _ => {
            let t = build_karras(keys);
            refit(&t, sorted, k);
            t
        }
    }
}

/// The large buffers of a build, kept between builds: a build in an arena that held an earlier
/// build of similar size writes into memory that is already mapped instead of faulting in
/// fresh pages (about 140 bytes per primitive). Results do not depend on the arena's history.
/// Hand a finished build's buffers back with [`BuildArena::recycle`].
#[derive(Debug, Default)]
pub struct BuildArena {
    aabbs: Vec<Aabb>,
    codes64: Vec<u64>,
    codes32: Vec<u32>,
    kbuf64: Vec<u64>,
    kbuf32: Vec<u32>,
    ids: Vec<u32>,
    vbuf: Vec<u32>,
    sweep: SweepScratch,
    nodes: Vec<Node>,
}

impl BuildArena {
    /// An empty arena (the first build in it allocates fresh buffers).
    pub fn new() -> BuildArena {
        BuildArena::default()
    }

    /// Take back the nodes and primitive order of a finished tree for the next build.
    pub fn recycle_bvh(&mut self, bvh: crate::bvh::Bvh) {
        self.nodes = bvh.nodes;
        self.ids = bvh.prim_indices;
    }

    /// Take back the boxes, nodes and primitive order of a finished build for the next one.
    pub fn recycle(&mut self, out: BuildOutput) {
        self.aabbs = out.aabbs;
        self.nodes = out.bvh.nodes;
        self.ids = out.bvh.prim_indices;
    }
}

/// Build over a triangle mesh: every phase from triangle boxes on, in fresh buffers.
pub fn build_scene(scene: &Mesh, opts: &PipelineOptions) -> Result<BuildOutput, BuildError> {
    build_scene_in(scene, opts, &mut BuildArena::new())
}

/// [`build_scene`] in the buffers of `arena`.
pub fn build_scene_in(
    scene: &Mesh,
    opts: &PipelineOptions,
    arena: &mut BuildArena,
) -> Result<BuildOutput, BuildError> {
    let mut timed = Timed::new(opts.threads)?;
    let n = scene.indices.len();
    if n == 0 {
        return Err(BuildError::Empty);
    }
    let mut out = std::mem::take(&mut arena.aabbs);
    let aabbs = timed.run(Phase::Aabb, || {
        crate::buffers::resized_par(&mut out, n, Aabb::EMPTY);
        crate::aabbs::triangle_aabbs(&scene.vertices, &scene.indices, &mut out);
        out
    });
    build_timed(timed, aabbs, None, opts, arena)
}

/// Build over primitive boxes (the AABB phase is then 0), in fresh buffers.
pub fn build_aabbs(aabbs: Vec<Aabb>, opts: &PipelineOptions) -> Result<BuildOutput, BuildError> {
    build_aabbs_in(aabbs, opts, &mut BuildArena::new())
}

/// [`build_aabbs`] for library callers: every phase in the caller's rayon pool (no pool of its
/// own), wall times only, and no SAH figures in the report (`sah_*` and `depth` are 0).
pub fn build_aabbs_inline(
    aabbs: Vec<Aabb>,
    opts: &PipelineOptions,
) -> Result<BuildOutput, BuildError> {
    if opts.threads == 0 {
        return Err(BuildError::ZeroThreads);
    }
    build_timed(Timed::inline(), aabbs, None, opts, &mut BuildArena::new())
}

/// [`build_aabbs_inline`] in the buffers of `arena` (the caller's pool, no CPU accounting);
/// `bounds`, when given, must be [`scene_bounds`] of the boxes (as
/// [`crate::aabbs::triangle_aabbs_bounds`] returns them with the boxes), and saves that pass.
/// They are trusted: only debug builds check them, and other bounds give another frame and
/// so other codes and another (valid) tree.
pub fn build_aabbs_inline_in(
    aabbs: Vec<Aabb>,
    bounds: Option<SceneBounds>,
    opts: &PipelineOptions,
    arena: &mut BuildArena,
) -> Result<BuildOutput, BuildError> {
    build_timed(Timed::inline(), aabbs, bounds, opts, arena)
}

/// [`build_aabbs`] in the buffers of `arena`.
pub fn build_aabbs_in(
    aabbs: Vec<Aabb>,
    opts: &PipelineOptions,
    arena: &mut BuildArena,
) -> Result<BuildOutput, BuildError> {
    build_timed(Timed::new(opts.threads)?, aabbs, None, opts, arena)
}

fn build_timed(
    mut timed: Timed,
    aabbs: Vec<Aabb>,
    bounds: Option<SceneBounds>,
    opts: &PipelineOptions,
    arena: &mut BuildArena,
) -> Result<BuildOutput, BuildError> {
    let n = aabbs.len();
    if n == 0 {
        return Err(BuildError::Empty);
    }
    if n > MAX_PRIMS {
        return Err(BuildError::TooMany(n));
    }
    if opts.collapse.max_leaf == 0 {
        return Err(BuildError::ZeroLeafSize);
    }
    let k = opts.collapse;
    if opts.builder == Builder::BinnedSah {
        let ab = &aabbs;
        if timed.metrics {
            timed.run(Phase::Encode, || scene_bounds(ab))?;
        }
        let (bvh, headline) = if !timed.metrics && k.max_leaf > 1 {
            // Library builds report no one-primitive-per-leaf SAH: cut the top-down build at
            // its SAH leaves instead of building every subtree below them and collapsing it
            // again (same splits above the leaves; 7% fewer instructions for a San Francisco
            // quality build).
            let rule = LeafRule {
                max_leaf: k.max_leaf,
                ct: k.ct,
                ci: k.ci,
            };
            let bvh = timed.run(Phase::Hierarchy, || {
                build_binned_sah_leaves(ab, DEFAULT_BINS, rule).map(|b| b.bvh)
            })?;
            (bvh, f64::NAN)
        } else {
            let plain = timed.run(Phase::Hierarchy, || build_binned_sah(ab, DEFAULT_BINS))?;
            let bvh = timed.run(Phase::Collapse, || collapse_bvh(&plain, &k));
            (bvh, timed.metric(|| sah_headline(&plain)))
        };
        return Ok(finish(
            timed,
            bvh,
            aabbs,
            opts,
            None,
            SortReport::default(),
            headline,
        ));
    }
    let ab = &aabbs;
    let frame = timed.run(Phase::Encode, || {
        let b = match bounds {
            Some(b) => {
                debug_assert_eq!(Ok(b), scene_bounds(ab), "bounds given are not the boxes'");
                b
            }
            None => scene_bounds(ab)?,
        };
        Frame::from_bounds(b, Normalization::CentroidBox)
    })?;
    let (spec, auto, auto_time) = match opts.layout.fixed() {
        Some(spec) => (spec, None, PhaseTime::default()),
        None => {
            // Timed as part of the encode phase, and on its own.
            let before = timed.phases[Phase::Encode as usize];
            let (spec, auto) = timed.run(Phase::Encode, || opts.layout.resolve(ab, &frame))?;
            let after = timed.phases[Phase::Encode as usize];
            let t = PhaseTime {
                wall_ms: after.wall_ms - before.wall_ms,
                cpu_ms: after.cpu_ms - before.cpu_ms,
                serial_cpu_ms: after.serial_cpu_ms - before.serial_cpu_ms,
            };
            (spec, auto, t)
        }
    };
    let enc = Encoder::new(&spec, &frame);
    let layout = Some(enc.layout().to_string());
    let n = ab.len();
    let (bvh, sort, headline) = if enc.layout().fits_u32() {
        let mut codes = std::mem::take(&mut arena.codes32);
        timed.run(Phase::Encode, || {
            crate::buffers::resized(&mut codes, n, 0);
            crate::encode::encode_parallel_u32(&enc, ab, &mut codes)
        })?;
        let mut kbuf = std::mem::take(&mut arena.kbuf32);
        let r = lbvh_phases(&mut timed, codes, &mut kbuf, ab, opts, arena)?;
        (arena.codes32, arena.kbuf32) = (r.3, kbuf);
        (r.0, r.1, r.2)
    } else {
        let mut codes = std::mem::take(&mut arena.codes64);
        timed.run(Phase::Encode, || {
            crate::buffers::resized(&mut codes, n, 0);
            crate::encode::encode_parallel(&enc, ab, &mut codes)
        })?;
        let mut kbuf = std::mem::take(&mut arena.kbuf64);
        let r = lbvh_phases(&mut timed, codes, &mut kbuf, ab, opts, arena)?;
        (arena.codes64, arena.kbuf64) = (r.3, kbuf);
        (r.0, r.1, r.2)
    };
    let mut out = finish(timed, bvh, aabbs, opts, layout, sort, headline);
    out.report.auto = auto;
    out.report.auto_time = auto_time;
    Ok(out)
}

/// Sort, hierarchy, bounds and collapse (sort scratch `kbuf` and the other buffers from
/// `arena`); returns the BVH, the sort report, the headline SAH and the (sorted) key buffer.
type LbvhResult<K> = (Bvh, SortReport, f64, Vec<K>);

fn lbvh_phases<K: RadixKey>(
    timed: &mut Timed,
    mut keys: Vec<K>,
    kbuf: &mut Vec<K>,
    aabbs: &[Aabb],
    opts: &PipelineOptions,
    arena: &mut BuildArena,
) -> Result<LbvhResult<K>, BuildError> {
    let k = opts.collapse;
    let mut order = std::mem::take(&mut arena.ids);
    let vbuf = &mut arena.vbuf;
    let sort = timed.run(Phase::Sort, || {
        sort_with_ids(&mut keys, &mut order, kbuf, vbuf)
    })?;
    if opts.builder == Builder::Atrbvh {
        let bvh = atrbvh_phases(timed, &keys, aabbs, order, &k)?;
        return Ok((bvh.0, sort, bvh.1, keys));
    }
    if opts.builder == Builder::Lbvh {
        let scratch = &mut arena.sweep;
        let swept = timed.run(Phase::Hierarchy, || {
            sweep_tree_in(&keys, order, aabbs, &k, scratch)
        });
        let headline = timed.metric(|| swept.sah_headline(aabbs));
        let nodes = std::mem::take(&mut arena.nodes);
        let scratch = &mut arena.sweep;
        let bvh = timed.run(Phase::Collapse, || swept.emit_in(nodes, scratch));
        return Ok((bvh, sort, headline, keys));
    }
    let (tree, sorted) = match opts.builder {
        Builder::LbvhApetrei => timed.run(Phase::Hierarchy, || {
            let sorted = gather_sorted(aabbs, &order);
            (build_apetrei(&keys, &sorted, &k), sorted)
        }),
        _ => {
            let t = timed.run(Phase::Hierarchy, || build_karras(&keys));
            let sorted = timed.run(Phase::Bounds, || {
                let sorted = gather_sorted(aabbs, &order);
                refit(&t, &sorted, &k);
                sorted
            });
            (t, sorted)
        }
    };
    let headline = timed.metric(|| tree.sah_headline(aabbs));
    let (bvh, _depth) = timed.run(Phase::Collapse, || emit(&tree, &sorted, order));
    timed.run(Phase::Collapse, move || drop((tree, sorted)));
    Ok((bvh, sort, headline, keys))
}

/// `atrbvh` after the sort: the Karras tree (by the sweep), the one-primitive-per-leaf BVH, treelet
/// restructuring (phase `optimize`) and the SAH collapse; returns the BVH and the headline SAH
/// of the restructured tree.
fn atrbvh_phases<K: RadixKey>(
    timed: &mut Timed,
    keys: &[K],
    aabbs: &[Aabb],
    order: Vec<u32>,
    k: &CollapseParams,
) -> Result<(Bvh, f64), BuildError> {
    let swept = timed.run(Phase::Hierarchy, || {
        sweep_tree(keys, order, aabbs, &CollapseParams::NONE)
    });
    let mut plain = timed.run(Phase::Collapse, || swept.emit());
    let cfg = AtrConfig::default();
    timed.run(Phase::Optimize, || restructure(&mut plain, aabbs, &cfg))?;
    let headline = timed.metric(|| sah_headline(&plain));
    let bvh = timed.run(Phase::Collapse, || collapse_bvh(&plain, k));
    Ok((bvh, headline))
}

fn finish(
    timed: Timed,
    bvh: Bvh,
    aabbs: Vec<Aabb>,
    opts: &PipelineOptions,
    layout: Option<String>,
    sort: SortReport,
    headline: f64,
) -> BuildOutput {
    let k = SahConstants {
        ct: opts.collapse.ct,
        ci: opts.collapse.ci,
    };
    let (collapsed, depth) = if timed.metrics {
        (sah_cost(&bvh, k), bvh.depth())
    } else {
        (0.0, 0)
    };
    let leaves = bvh.nodes.iter().filter(|n| n.is_leaf()).count();
    let report = BuildReport {
        prims: aabbs.len(),
        threads: timed.threads,
        builder: opts.builder,
        layout,
        phases: timed.phases,
        sort,
        nodes: bvh.nodes.len(),
        leaves,
        depth,
        sah_headline: headline,
        sah_collapsed: collapsed,
        auto: None,
        auto_time: PhaseTime::default(),
    };
    BuildOutput { bvh, aabbs, report }
}
