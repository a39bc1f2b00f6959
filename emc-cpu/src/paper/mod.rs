//! `emc paper`, the project's main report: the seed's two LBVH/ATRBVH tables reproduced, what
//! code accuracy costs in build and trace time (with its Pareto front), the seed's example
//! layout table, all written as Markdown, CSV, SVG plots and one PNG image per scene.
#![forbid(unsafe_code)]

pub mod csv;
pub mod measure;
pub mod pareto;
pub mod plots;
pub mod sweep;
pub mod tables;

use std::path::{Path, PathBuf};

use emc_core::LayoutSpec;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::scene::{load_with, Mesh, SceneOptions};
use crate::trace::image::{shade, Shading};
use measure::{all_variants, build, trace, MeasureError, PaperBuilder, Variant, Workload};

/// The scenes `emc paper` runs when none are given.
pub const DEFAULT_SCENES: [&str; 5] = [
    "builtin:uniform",
    "builtin:stadium",
    "builtin:city",
    "builtin:hair",
    "builtin:mixed",
];

/// Primitives of a built-in scene under `--quick`.
pub const QUICK_PRIMS: usize = 100_000;

/// Primary rays of the fixed ray budget (`res²`) without and with `--quick`.
pub const DEFAULT_RAYS: usize = 1024 * 1024;
/// Primary rays of the fixed ray budget under `--quick`.
pub const QUICK_RAYS: usize = 256 * 256;

/// What `emc paper` runs.
#[derive(Clone, Debug, PartialEq)]
pub struct PaperConfig {
    /// Mesh specs (`builtin:NAME`, OBJ paths, shared scene names).
    pub scenes: Vec<String>,
    /// Output folder.
    pub out: PathBuf,
    /// Threads of every build and trace.
    pub threads: usize,
    /// Seed of the built-in scenes.
    pub seed: u64,
    /// Primitives of the built-in scenes (`None`: their default size).
    pub prims: Option<usize>,
    /// Primary rays of the fixed budget (rounded up to a square image).
    pub rays: usize,
    /// Timed repeats of each trace (median reported).
    pub repeats: usize,
    /// Show progress bars (they stay hidden anyway when stderr is not a terminal).
    pub progress: bool,
}

impl PaperConfig {
    /// The configuration of `--quick` (or the full run) with defaults for everything else.
    pub fn new(quick: bool) -> PaperConfig {
        PaperConfig {
            scenes: DEFAULT_SCENES.iter().map(|s| s.to_string()).collect(),
            out: PathBuf::from("out/paper"),
            threads: 1,
            seed: crate::scene::builtin::DEFAULT_SEED,
            prims: quick.then_some(QUICK_PRIMS),
            rays: if quick { QUICK_RAYS } else { DEFAULT_RAYS },
            repeats: 3,
            progress: true,
        }
    }

    /// Side of the square image holding at least `rays` primary rays (at least 8).
    pub fn resolution(&self) -> u32 {
        let mut r = (self.rays as f64).sqrt().ceil() as u32;
        while (r as usize) * (r as usize) < self.rays {
            r += 1;
        }
        r.max(8)
    }
}

/// Everything that stops `emc paper`.
#[derive(Debug, thiserror::Error)]
pub enum PaperError {
    /// No scene to run.
    #[error("no scenes given")]
    NoScenes,
    /// A thread count of 0.
    #[error("the thread count must be at least 1")]
    ZeroThreads,
    /// A ray budget of 0.
    #[error("the ray budget must be at least 1")]
    ZeroRays,
    /// Two scenes with the same name.
    #[error("scene `{0}` is given twice")]
    Duplicate(String),
    /// A scene failed to load.
    #[error("loading {spec}: {source}")]
    Mesh {
        /// The spec given.
        spec: String,
        /// Why.
        source: crate::scene::SceneError,
    },
    /// A build or trace failed.
    #[error("{scene}, {builder} {layout}: {source}")]
    Measure {
        /// Mesh name.
        scene: String,
        /// Builder name.
        builder: &'static str,
        /// Layout name.
        layout: String,
        /// Why.
        source: MeasureError,
    },
    /// The thread pool could not be created.
    #[error("cannot create a pool of {0} threads: {1}")]
    Pool(usize, String),
    /// An output file could not be written.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A plot could not be drawn.
    #[error("drawing {path}: {msg}")]
    Plot {
        /// The file.
        path: PathBuf,
        /// Why.
        msg: String,
    },
    /// The bit-budget sweep failed.
    #[error("{scene}, bit-budget sweep: {source}")]
    Sweep {
        /// Mesh name.
        scene: String,
        /// Why.
        source: sweep::SweepError,
    },
    /// An image could not be encoded.
    #[error("writing {path}: {source}")]
    Image {
        /// The file.
        path: PathBuf,
        /// Why.
        source: crate::trace::image::ImageError,
    },
}

/// One measured configuration: builder × layout variant on one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Run {
    /// Builder.
    pub builder: PaperBuilder,
    /// Layout variant (`None` for binned SAH).
    pub variant: Option<Variant>,
    /// The resolved layout as the seed prints it (`None` for binned SAH).
    pub layout: Option<String>,
    /// Thread-CPU milliseconds, triangles to collapsed BVH.
    pub build_ms: f64,
    /// Wall milliseconds of the same.
    pub build_wall_ms: f64,
    /// SAH, `Ct = Ci = 1`, one primitive per leaf.
    pub sah_headline: f64,
    /// SAH of the traced (collapsed) BVH.
    pub sah_collapsed: f64,
    /// Trace figures.
    pub traced: measure::Traced,
    /// On the front of (build ms, collapsed SAH).
    pub pareto_sah: bool,
    /// On the front of (build ms, trace ms): the configurations a time-to-image choice can
    /// pick for some number of images.
    pub pareto_time: bool,
}

impl Run {
    /// The layout column: a shared layout name, `morton63-cube`, or `none`.
    pub fn layout_name(&self) -> String {
        self.variant
            .map(|v| v.name())
            .unwrap_or_else(|| measure::NO_LAYOUT.to_string())
    }

    /// Build plus trace thread-CPU milliseconds.
    pub fn time_to_image_ms(&self) -> f64 {
        self.build_ms + self.traced.trace_ms()
    }

    /// True for the run of `builder` over the plain `spec`.
    pub fn is(&self, builder: PaperBuilder, spec: LayoutSpec) -> bool {
        self.builder == builder && self.variant == Some(Variant::plain(spec))
    }
}

/// All runs of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneResult {
    /// Mesh name.
    pub name: String,
    /// File-name stem of its outputs.
    pub stem: String,
    /// Triangles.
    pub prims: usize,
    /// Image side of the ray budget.
    pub res: u32,
    /// Runs: every variant × (lbvh, atrbvh), then binned SAH.
    pub runs: Vec<Run>,
    /// The primary rays shaded by facing normal (`atrbvh`, `emc64-var` BVH).
    pub image: Option<crate::trace::image::Image>,
    /// The bit-budget sweep (plain LBVH, `auto:N` per length).
    pub sweep: Vec<sweep::SweepRow>,
}

impl SceneResult {
    /// The run of `builder` over plain `spec`.
    pub fn find(&self, builder: PaperBuilder, spec: LayoutSpec) -> Option<&Run> {
        self.runs.iter().find(|r| r.is(builder, spec))
    }
}

/// What a whole `emc paper` run produced.
#[derive(Clone, Debug, PartialEq)]
pub struct PaperResults {
    /// Per scene.
    pub scenes: Vec<SceneResult>,
    /// Threads used.
    pub threads: usize,
    /// Primary rays per trace.
    pub rays: usize,
    /// Files written, in order.
    pub files: Vec<PathBuf>,
}

/// A file-name stem for a scene name: `builtin:city` → `city`, paths to their file stem, every
/// character outside `[A-Za-z0-9._-]` replaced by `-`.
pub fn stem_of(name: &str) -> String {
    let base = name.strip_prefix("builtin:").unwrap_or(name);
    let base = Path::new(base)
        .file_name()
        .and_then(|f| f.to_str())
        .unwrap_or(base);
    let base = base
        .strip_suffix(".zst")
        .unwrap_or(base)
        .trim_end_matches(".obj");
    base.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '-'
            }
        })
        .collect()
}

fn load_scenes(cfg: &PaperConfig) -> Result<Vec<Mesh>, PaperError> {
    let opts = SceneOptions::default()
        .with_prims(cfg.prims)
        .with_seed(cfg.seed);
    let mut out: Vec<Mesh> = Vec::new();
    for spec in &cfg.scenes {
        let s = load_with(spec, &opts).map_err(|source| PaperError::Mesh {
            spec: spec.clone(),
            source,
        })?;
        if out.iter().any(|o| stem_of(&o.name) == stem_of(&s.name)) {
            return Err(PaperError::Duplicate(s.name));
        }
        out.push(s);
    }
    Ok(out)
}

/// Measure every configuration of every scene (no file written).
pub fn measure_all(cfg: &PaperConfig) -> Result<PaperResults, PaperError> {
    if cfg.scenes.is_empty() {
        return Err(PaperError::NoScenes);
    }
    if cfg.threads == 0 {
        return Err(PaperError::ZeroThreads);
    }
    if cfg.rays == 0 {
        return Err(PaperError::ZeroRays);
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .build()
        .map_err(|e| PaperError::Pool(cfg.threads, e.to_string()))?;
    // Untimed work (loading, ray generation, the sweep's choices) may use every core, and
    // runs only between timed runs: nothing here overlaps a timed build or trace.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let untimed = rayon::ThreadPoolBuilder::new()
        .num_threads(cores)
        .build()
        .map_err(|e| PaperError::Pool(cores, e.to_string()))?;
    let scenes = untimed.install(|| load_scenes(cfg))?;
    let variants = all_variants();
    let per_scene = variants.len() * 2 + 1 + sweep::SWEEP_BITS.len();
    let bar = if cfg.progress {
        ProgressBar::with_draw_target(
            Some((scenes.len() * per_scene) as u64),
            ProgressDrawTarget::stderr(),
        )
    } else {
        ProgressBar::hidden()
    };
    if let Ok(style) = ProgressStyle::with_template(
        "{elapsed_precise} [{bar:30}] {pos}/{len} ETA {eta_precise} {msg}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    let res = cfg.resolution();
    let mut results = Vec::with_capacity(scenes.len());
    for scene in &scenes {
        bar.set_message(format!("{}: rays", scene.name));
        let work = untimed.install(|| Workload::new(scene, res));
        let mut configs: Vec<(PaperBuilder, Option<Variant>)> = Vec::new();
        for v in &variants {
            configs.push((PaperBuilder::Lbvh, Some(*v)));
            configs.push((PaperBuilder::Atrbvh, Some(*v)));
        }
        configs.push((PaperBuilder::BinnedSah, None));
        let mut runs = Vec::with_capacity(configs.len());
        let mut image = None;
        for (b, v) in configs {
            let vname = v.map(|v| v.name()).unwrap_or_else(|| "-".into());
            bar.set_message(format!(
                "{} ({} tris): {} over {}, {} thread{}",
                scene.name,
                scene.triangle_count(),
                b.name(),
                vname,
                cfg.threads,
                if cfg.threads == 1 { "" } else { "s" }
            ));
            let wrap = |source| PaperError::Measure {
                scene: scene.name.clone(),
                builder: b.name(),
                layout: vname.clone(),
                source,
            };
            let variant = v.unwrap_or(Variant::plain(LayoutSpec::Morton63));
            let built = build(scene, b, &variant, &pool).map_err(wrap)?;
            let (traced, wide, hits) =
                trace(&built.bvh, &work, cfg.repeats, &pool).map_err(wrap)?;
            if b == PaperBuilder::Atrbvh && v == Some(Variant::plain(LayoutSpec::Emc64Var)) {
                image = Some(pool.install(|| {
                    shade(
                        &wide,
                        &work.tris,
                        &work.primary,
                        &hits,
                        (res, res),
                        work.frame.diag,
                        Shading::Normal,
                    )
                }));
            }
            runs.push(Run {
                builder: b,
                variant: v,
                layout: built.layout,
                build_ms: built.build_ms,
                build_wall_ms: built.build_wall_ms,
                sah_headline: built.sah_headline,
                sah_collapsed: built.sah_collapsed,
                traced,
                pareto_sah: false,
                pareto_time: false,
            });
            bar.inc(1);
        }
        mark_pareto(&mut runs);
        bar.set_message(format!(
            "{}: bit-budget sweep, choosing layouts",
            scene.name
        ));
        let step = |bits: u32, label: &str| {
            bar.set_message(format!(
                "{}: bit-budget sweep, lbvh over {bits}-bit {label}",
                scene.name
            ));
            bar.inc(1);
        };
        let sw = sweep::measure_sweep(scene, &work, cfg.repeats, &pool, &untimed, &step).map_err(
            |source| PaperError::Sweep {
                scene: scene.name.clone(),
                source,
            },
        )?;
        results.push(SceneResult {
            stem: stem_of(&scene.name),
            name: scene.name.clone(),
            prims: scene.triangle_count(),
            res,
            runs,
            image,
            sweep: sw,
        });
    }
    bar.finish_and_clear();
    Ok(PaperResults {
        scenes: results,
        threads: cfg.threads,
        rays: (res as usize) * (res as usize),
        files: Vec::new(),
    })
}

/// Set the two Pareto flags of a scene's runs.
pub fn mark_pareto(runs: &mut [Run]) {
    let sah: Vec<(f64, f64)> = runs.iter().map(|r| (r.build_ms, r.sah_collapsed)).collect();
    let time: Vec<(f64, f64)> = runs
        .iter()
        .map(|r| (r.build_ms, r.traced.trace_ms()))
        .collect();
    for ((r, a), b) in runs
        .iter_mut()
        .zip(pareto::pareto_front(&sah))
        .zip(pareto::pareto_front(&time))
    {
        r.pareto_sah = a;
        r.pareto_time = b;
    }
}

fn write(path: PathBuf, text: &str, files: &mut Vec<PathBuf>) -> Result<(), PaperError> {
    std::fs::write(&path, text).map_err(|source| PaperError::Io {
        path: path.clone(),
        source,
    })?;
    files.push(path);
    Ok(())
}

/// Run everything and write the report into `cfg.out`: `paper.md`, `runs.csv`,
/// `seed-tables.csv`, two SVG plots and one PNG per scene.
pub fn run(cfg: &PaperConfig) -> Result<PaperResults, PaperError> {
    let mut res = measure_all(cfg)?;
    let out = &cfg.out;
    std::fs::create_dir_all(out).map_err(|source| PaperError::Io {
        path: out.clone(),
        source,
    })?;
    let mut files = Vec::new();
    let mut md = tables::markdown(&res);
    md.push_str("\n## What every bit buys\n\nPlain LBVH per code length, the layout `auto:N` picks; thread-CPU ms per phase; the radix sort orders only the key bytes in which codes differ.\n");
    for s in &res.scenes {
        md.push_str(&sweep::sweep_markdown(&s.name, &s.sweep));
    }
    write(out.join("paper.md"), &md, &mut files)?;
    write(out.join("runs.csv"), &csv::runs_csv(&res), &mut files)?;
    write(
        out.join("seed-tables.csv"),
        &csv::seed_tables_csv(&res),
        &mut files,
    )?;
    for s in &res.scenes {
        let p = out.join(format!("{}-build-vs-sah.svg", s.stem));
        plots::plot_scene(s, plots::Axis::Sah, &p)?;
        files.push(p);
        let p = out.join(format!("{}-build-vs-time-to-image.svg", s.stem));
        plots::plot_scene(s, plots::Axis::TimeToImage, &p)?;
        files.push(p);
        let p = out.join(format!("{}-bits.svg", s.stem));
        plots::plot_sweep(s, &p)?;
        files.push(p);
    }
    for s in &res.scenes {
        if let Some(img) = &s.image {
            let path = out.join(format!("{}.png", s.stem));
            let f = std::fs::File::create(&path).map_err(|source| PaperError::Io {
                path: path.clone(),
                source,
            })?;
            img.write_png(f).map_err(|source| PaperError::Image {
                path: path.clone(),
                source,
            })?;
            files.push(path);
        }
    }
    res.files = files;
    Ok(res)
}
