//! One measured configuration of `emc paper`: a builder (`lbvh`, `atrbvh`, `binned-sah`) over
//! one layout variant (a [`LayoutSpec`], optionally with cube normalisation), timed, costed by
//! SAH and traced with the benchmark protocol's primary and AO rays.
#![forbid(unsafe_code)]

use std::time::Instant;

use emc_core::{Aabb, Frame, LayoutSpec, Normalization};
use glam::Vec3;

use crate::build::{build_scene, encode_codes, scene_bounds, sort_codes, Builder, PipelineOptions};
use crate::bvh::atrbvh::{restructure, AtrConfig};
use crate::bvh::collapse::collapse_bvh;
use crate::bvh::refit::CollapseParams;
use crate::bvh::sweep::sweep_tree;
use crate::bvh::{sah_cost, sah_headline, Bvh, SahConstants};
use crate::cputime::median;
use crate::scene::Mesh;
use crate::trace::workload::{all_ao_rays, trace_closest, trace_occluded, Camera, SceneFrame};
use crate::trace::{Hit, NodeTest, Ray, TraceStats, WideBvh};

/// The hierarchy builders `emc paper` compares.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PaperBuilder {
    /// Karras LBVH with SAH leaf collapse (`lbvh`).
    Lbvh,
    /// The LBVH restructured by agglomerative treelets, then collapsed (`atrbvh`).
    Atrbvh,
    /// Top-down binned SAH, the quality reference (`binned-sah`).
    BinnedSah,
}

impl PaperBuilder {
    /// The shared builder name.
    pub fn name(self) -> &'static str {
        match self {
            PaperBuilder::Lbvh => "lbvh",
            PaperBuilder::Atrbvh => "atrbvh",
            PaperBuilder::BinnedSah => "binned-sah",
        }
    }
}

/// A code layout plus the position normalisation of its frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Variant {
    /// The layout.
    pub spec: LayoutSpec,
    /// Normalise positions to the cube of the largest extent instead of the centroid box.
    pub cube: bool,
    /// `--layout auto`: the layout chosen for the scene inside the timed build (`spec` is
    /// then unused).
    pub auto: bool,
}

impl Variant {
    /// A layout with the default (centroid-box) normalisation.
    pub const fn plain(spec: LayoutSpec) -> Variant {
        Variant {
            spec,
            cube: false,
            auto: false,
        }
    }

    /// `auto`: the scene's layout chosen by [`crate::auto::choose`], the choice timed as part
    /// of the build.
    pub const fn auto() -> Variant {
        Variant {
            spec: LayoutSpec::Emc64Var,
            cube: false,
            auto: true,
        }
    }

    /// The name tables and CSV files use: the shared layout name, `-cube` appended for the
    /// cube-normalised ablation, `auto` for the automatic choice.
    pub fn name(&self) -> String {
        if self.auto {
            "auto".to_string()
        } else if self.cube {
            format!("{}-cube", self.spec)
        } else {
            self.spec.to_string()
        }
    }
}

/// Name in the `layout` column of the binned-SAH row (it uses no codes).
pub const NO_LAYOUT: &str = "none";

/// Every layout variant of the accuracy-versus-time table, in report order.
pub fn all_variants() -> Vec<Variant> {
    let mut v: Vec<Variant> = LayoutSpec::STANDARD
        .into_iter()
        .map(Variant::plain)
        .collect();
    v.push(Variant {
        spec: LayoutSpec::Morton63,
        cube: true,
        auto: false,
    });
    v.push(Variant::auto());
    v
}

/// A built hierarchy with its build figures.
#[derive(Clone, Debug)]
pub struct Built {
    /// The collapsed BVH that is traced.
    pub bvh: Bvh,
    /// Thread-CPU milliseconds (summed over the pool) from triangles to the collapsed BVH.
    pub build_ms: f64,
    /// Wall milliseconds of the same.
    pub build_wall_ms: f64,
    /// The resolved layout as the seed prints it (`None` for binned SAH).
    pub layout: Option<String>,
    /// SAH with `Ct = Ci = 1`, one primitive per leaf.
    pub sah_headline: f64,
    /// SAH of the collapsed BVH with the collapse constants.
    pub sah_collapsed: f64,
}

/// Errors of one measured configuration.
#[derive(Debug, thiserror::Error)]
pub enum MeasureError {
    /// The build pipeline failed.
    #[error(transparent)]
    Build(#[from] crate::build::BuildError),
    /// Treelet restructuring failed.
    #[error(transparent)]
    Atr(#[from] crate::bvh::atrbvh::AtrError),
    /// The BVH could not be made traceable.
    #[error(transparent)]
    Trace(#[from] crate::trace::TraceError),
    /// A layout or frame problem.
    #[error(transparent)]
    Core(#[from] emc_core::Error),
}

/// Build `builder` over `scene` with `variant` on a pool of `pool`'s threads.
pub fn build(
    scene: &Mesh,
    builder: PaperBuilder,
    variant: &Variant,
    pool: &rayon::ThreadPool,
) -> Result<Built, MeasureError> {
    let threads = pool.current_num_threads();
    let collapse = CollapseParams::default();
    if variant.cube && !variant.auto {
        return build_cube(scene, builder, variant.spec, pool);
    }
    let b = match builder {
        PaperBuilder::Lbvh => Builder::Lbvh,
        PaperBuilder::Atrbvh => Builder::Atrbvh,
        PaperBuilder::BinnedSah => Builder::BinnedSah,
    };
    let out = build_scene(
        scene,
        &PipelineOptions {
            layout: if variant.auto {
                crate::auto::AUTO
            } else {
                variant.spec.into()
            },
            builder: b,
            threads,
            collapse,
        },
    )?;
    Ok(Built {
        bvh: out.bvh,
        build_ms: out.report.total().cpu_ms,
        build_wall_ms: out.report.total().wall_ms,
        layout: out.report.layout,
        sah_headline: out.report.sah_headline,
        sah_collapsed: out.report.sah_collapsed,
    })
}

/// The LBVH (or ATRBVH) of a cube-normalised frame, by the pipeline's own phases: boxes,
/// frame, codes, radix sort, the Karras tree by the split sweep, emission (and for `atrbvh`
/// treelet restructuring and the SAH collapse). The sweep's headline SAH is taken inside the
/// timed section, as the pipeline does for `lbvh`.
fn build_cube(
    scene: &Mesh,
    builder: PaperBuilder,
    spec: LayoutSpec,
    pool: &rayon::ThreadPool,
) -> Result<Built, MeasureError> {
    let collapse = CollapseParams::default();
    let k = SahConstants {
        ct: collapse.ct,
        ci: collapse.ci,
    };
    let atr = match builder {
        PaperBuilder::Lbvh => false,
        PaperBuilder::Atrbvh => true,
        // Binned SAH uses no codes: the cube frame changes nothing.
        PaperBuilder::BinnedSah => return build(scene, builder, &Variant::plain(spec), pool),
    };
    let tree_k = if atr { CollapseParams::NONE } else { collapse };
    let c0 = pool_cpu_ms(pool);
    let t0 = Instant::now();
    let r = pool.install(
        || -> Result<(Bvh, Option<Bvh>, String, Option<_>), MeasureError> {
            let mut aabbs = crate::buffers::filled(scene.indices.len(), Aabb::EMPTY);
            crate::aabbs::triangle_aabbs(&scene.vertices, &scene.indices, &mut aabbs);
            let frame = Frame::from_bounds(scene_bounds(&aabbs)?, Normalization::Cube)?;
            let enc = emc_core::Encoder::new(&spec, &frame);
            let layout = enc.layout().to_string();
            let codes = encode_codes(&enc, &aabbs)?;
            let (keys, order, _) = sort_codes(codes)?;
            let swept = sweep_tree(&keys, order, &aabbs, &tree_k);
            drop(keys);
            if atr {
                let mut bvh = swept.emit();
                restructure(&mut bvh, &aabbs, &AtrConfig::default())?;
                let c = collapse_bvh(&bvh, &collapse);
                Ok((c, Some(bvh), layout, None))
            } else {
                let headline = swept.sah_headline(&aabbs);
                Ok((swept.emit(), None, layout, Some(headline)))
            }
        },
    )?;
    let build_wall_ms = t0.elapsed().as_secs_f64() * 1e3;
    let build_ms = pool_cpu_ms(pool) - c0;
    let (bvh, plain, layout, tree) = r;
    let headline = match (plain, tree) {
        (Some(p), _) => pool.install(|| sah_headline(&p)),
        (None, Some(h)) => h,
        (None, None) => f64::NAN,
    };
    Ok(Built {
        sah_collapsed: sah_cost(&bvh, k),
        bvh,
        build_ms,
        build_wall_ms,
        layout: Some(layout),
        sah_headline: headline,
    })
}

/// The traced figures of one BVH on the protocol workload.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Traced {
    /// Primary rays cast.
    pub primary_rays: u64,
    /// AO rays cast.
    pub ao_rays: u64,
    /// Primary hits (a correctness check: every builder must agree).
    pub primary_hits: u64,
    /// Occluded AO rays (the same check).
    pub ao_occluded: u64,
    /// Thread-CPU milliseconds of the primary rays (summed over the pool, median of the
    /// repeats): unlike wall time, not inflated when other processes take the cores.
    pub primary_ms: f64,
    /// Thread-CPU milliseconds of the AO rays (median of the repeats).
    pub ao_ms: f64,
    /// Wall milliseconds of the primary rays (median of the repeats).
    pub primary_wall_ms: f64,
    /// Wall milliseconds of the AO rays (median of the repeats).
    pub ao_wall_ms: f64,
    /// Wide-node tests per ray over both kinds.
    pub node_tests_per_ray: f64,
    /// Triangle tests per ray over both kinds.
    pub tri_tests_per_ray: f64,
}

impl Traced {
    /// Thread-CPU milliseconds of the whole ray budget.
    pub fn trace_ms(&self) -> f64 {
        self.primary_ms + self.ao_ms
    }

    /// Wall milliseconds of the whole ray budget.
    pub fn trace_wall_ms(&self) -> f64 {
        self.primary_wall_ms + self.ao_wall_ms
    }

    /// Million primary rays per thread-CPU second.
    pub fn primary_mrays(&self) -> f64 {
        mrays(self.primary_rays, self.primary_ms)
    }

    /// Million AO rays per thread-CPU second.
    pub fn ao_mrays(&self) -> f64 {
        mrays(self.ao_rays, self.ao_ms)
    }
}

fn mrays(rays: u64, ms: f64) -> f64 {
    if ms > 0.0 {
        rays as f64 / ms / 1e3
    } else {
        0.0
    }
}

/// The protocol rays of one scene: primary rays in tile order at `res × res`.
#[derive(Clone, Debug)]
pub struct Workload {
    /// The triangles, id order.
    pub tris: Vec<[Vec3; 3]>,
    /// Mesh frame (bounds, diagonal).
    pub frame: SceneFrame,
    /// Primary rays, tile order.
    pub primary: Vec<Ray>,
    /// Image side in pixels.
    pub res: u32,
}

impl Workload {
    /// The protocol workload of `scene` at `res × res`.
    pub fn new(scene: &Mesh, res: u32) -> Workload {
        let tris: Vec<[Vec3; 3]> = (0..scene.triangle_count())
            .map(|i| scene.triangle(i))
            .collect();
        let frame = SceneFrame::of(&tris);
        let mode = crate::trace::workload::CameraMode::for_scene(&scene.name);
        let cam = Camera::protocol(&frame, mode);
        let primary = crate::trace::workload::primary_rays(&cam, res, res);
        Workload {
            tris,
            frame,
            primary,
            res,
        }
    }
}

/// Trace the workload on `bvh`: primary rays, then the AO rays of their hits, each timed
/// `repeats` times (median), then once more with counters. Returns the figures, the wide BVH
/// and the primary hits (for the image).
pub fn trace(
    bvh: &Bvh,
    w: &Workload,
    repeats: usize,
    pool: &rayon::ThreadPool,
) -> Result<(Traced, WideBvh, Vec<Option<Hit>>), MeasureError> {
    let wide = pool.install(|| WideBvh::from_bvh2(bvh, &w.tris))?;
    let repeats = repeats.max(1);
    let (mut tp, mut wp) = (Vec::with_capacity(repeats), Vec::with_capacity(repeats));
    let mut hits = Vec::new();
    for _ in 0..repeats {
        let c0 = pool_cpu_ms(pool);
        let t0 = Instant::now();
        let (h, _) = pool.install(|| trace_closest(&wide, &w.primary, NodeTest::Simd, false));
        wp.push(t0.elapsed().as_secs_f64() * 1e3);
        tp.push(pool_cpu_ms(pool) - c0);
        hits = h;
    }
    let (ao, _) = pool.install(|| all_ao_rays(&w.primary, &hits, &w.tris, w.frame.diag));
    let (mut ta, mut wa) = (Vec::with_capacity(repeats), Vec::with_capacity(repeats));
    let mut occ = Vec::new();
    for _ in 0..repeats {
        let c0 = pool_cpu_ms(pool);
        let t0 = Instant::now();
        let (o, _) = pool.install(|| trace_occluded(&wide, &ao, NodeTest::Simd, false));
        wa.push(t0.elapsed().as_secs_f64() * 1e3);
        ta.push(pool_cpu_ms(pool) - c0);
        occ = o;
    }
    let (_, sp) = pool.install(|| trace_closest(&wide, &w.primary, NodeTest::Simd, true));
    let (_, sa) = pool.install(|| trace_occluded(&wide, &ao, NodeTest::Simd, true));
    let s: TraceStats = sp.add(&sa);
    let rays = s.rays.max(1) as f64;
    let t = Traced {
        primary_rays: w.primary.len() as u64,
        ao_rays: ao.len() as u64,
        primary_hits: hits.iter().filter(|h| h.is_some()).count() as u64,
        ao_occluded: occ.iter().filter(|&&o| o).count() as u64,
        primary_ms: median(&tp),
        ao_ms: median(&ta),
        primary_wall_ms: median(&wp),
        ao_wall_ms: median(&wa),
        node_tests_per_ray: s.node_tests as f64 / rays,
        tri_tests_per_ray: s.tri_tests as f64 / rays,
    };
    Ok((t, wide, hits))
}

/// CPU milliseconds of all threads of `pool` so far.
pub fn pool_cpu_ms(pool: &rayon::ThreadPool) -> f64 {
    crate::cputime::pool_cpu_time(pool).as_secs_f64() * 1e3
}
