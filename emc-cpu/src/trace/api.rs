//! The library face of the tracer: build an [`Accel`] from a triangle mesh with a [`Preset`]
//! and [`BuildOptions`], then ask `intersect` / `occluded` for single rays or slices of rays.
//!
//! ```
//! use emc_cpu::trace::{Accel, BuildOptions, Preset, Ray};
//! use glam::Vec3;
//!
//! // A unit square in the z = 0 plane, as two triangles.
//! let vertices = [
//!     Vec3::new(0.0, 0.0, 0.0),
//!     Vec3::new(1.0, 0.0, 0.0),
//!     Vec3::new(1.0, 1.0, 0.0),
//!     Vec3::new(0.0, 1.0, 0.0),
//! ];
//! let indices = [[0, 1, 2], [0, 2, 3]];
//! let accel = Accel::build(&vertices, &indices, &BuildOptions::preset(Preset::Fast))?;
//!
//! let ray = Ray::new(Vec3::new(0.25, 0.5, 2.0), Vec3::new(0.0, 0.0, -1.0));
//! let hit = accel.intersect(&ray).expect("the ray hits the square");
//! assert_eq!((hit.t, hit.prim), (2.0, 1));
//! assert!(accel.occluded(&ray));
//!
//! // Batches run in parallel and return one answer per ray, in order.
//! let rays = [ray, Ray::new(Vec3::new(5.0, 5.0, 2.0), Vec3::new(0.0, 0.0, -1.0))];
//! let hits = accel.intersect_batch(&rays);
//! assert!(hits[0].is_some() && hits[1].is_none());
//! # Ok::<(), emc_cpu::trace::TraceError>(())
//! ```
#![forbid(unsafe_code)]

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;

use emc_core::{Aabb, LayoutSpec};

use crate::build::{build_aabbs, Builder};
use crate::bvh::atrbvh::{restructure as restructure_atr, AtrConfig};
use crate::bvh::collapse::collapse_bvh;
use crate::bvh::refit::CollapseParams;
use crate::bvh::Bvh;
use crate::trace::intersect::{Hit, Ray};
use crate::trace::traverse::{closest, occluded, NodeTest, TraceStats};
use crate::trace::wide::WideBvh;
use crate::trace::TraceError;

/// Speed / quality trade-off of [`Accel::build`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Preset {
    /// Fastest build: one-pass LBVH (`lbvh-apetrei`) over `emc64-var` codes, for dynamic
    /// scenes.
    Fast,
    /// LBVH (`lbvh`, `emc64-var`) improved by agglomerative treelet restructuring (`atrbvh`).
    #[default]
    Balanced,
    /// Best tracing speed: top-down binned SAH, for static scenes traced many times.
    Quality,
}

/// Options of [`Accel::build`]: a preset, and overrides of its choices.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BuildOptions {
    /// The preset that fills in everything left `None`.
    pub preset: Preset,
    /// Code layout of the LBVH builders (ignored by `binned-sah`).
    pub layout: Option<LayoutSpec>,
    /// Hierarchy builder.
    pub builder: Option<Builder>,
    /// Run treelet restructuring (`atrbvh`) on the binary tree before the leaf collapse.
    pub restructure: Option<bool>,
    /// Threads for building and batch tracing (`None`: as many as rayon's current pool).
    pub threads: Option<usize>,
    /// Largest leaf of the SAH leaf collapse (1 keeps one triangle per leaf; default 4).
    pub leaf_size: Option<u32>,
}

impl BuildOptions {
    /// Options of a preset, with no override.
    pub fn preset(preset: Preset) -> BuildOptions {
        BuildOptions {
            preset,
            ..BuildOptions::default()
        }
    }

    /// The builder, layout and restructuring the preset and overrides resolve to.
    pub fn resolve(&self) -> (Builder, LayoutSpec, bool) {
        let (b, l, r) = match self.preset {
            Preset::Fast => (Builder::LbvhApetrei, LayoutSpec::Emc64Var, false),
            Preset::Balanced => (Builder::Lbvh, LayoutSpec::Emc64Var, true),
            Preset::Quality => (Builder::BinnedSah, LayoutSpec::Emc64Var, false),
        };
        (
            self.builder.unwrap_or(b),
            self.layout.unwrap_or(l),
            self.restructure.unwrap_or(r),
        )
    }
}

/// Default largest leaf of [`BuildOptions::leaf_size`].
pub const DEFAULT_LEAF_SIZE: u32 = 4;

/// A triangle mesh ready for ray queries: the triangles and their wide BVH.
#[derive(Debug, Clone)]
pub struct Accel {
    bvh: WideBvh,
    tris: Vec<[Vec3; 3]>,
    /// The mesh's triangles as vertex indices (for [`Accel::rebuild`]).
    indices: Vec<[u32; 3]>,
    /// Vertices the indices address.
    vertex_count: usize,
    opts: BuildOptions,
    pool: Option<Arc<rayon::ThreadPool>>,
}

impl Accel {
    /// Build over an indexed mesh. Fails on an out-of-range index, a non-finite vertex, an
    /// empty mesh, an unknown builder or layout, or a tree too deep to trace.
    pub fn build(
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        opts: &BuildOptions,
    ) -> Result<Accel, TraceError> {
        let mut tris = Vec::with_capacity(indices.len());
        for (i, t) in indices.iter().enumerate() {
            let mut v = [Vec3::ZERO; 3];
            for (k, &ix) in t.iter().enumerate() {
                v[k] = *vertices.get(ix as usize).ok_or(TraceError::BadIndex {
                    tri: i,
                    index: ix,
                    vertices: vertices.len(),
                })?;
            }
            tris.push(v);
        }
        let mut a = Accel::from_triangles(tris, opts)?;
        a.indices = indices.to_vec();
        a.vertex_count = vertices.len();
        Ok(a)
    }

    /// Rebuild over new positions of the same mesh: `vertices` replaces the vertices of the
    /// [`Accel::build`] call (same count, same indices; for [`Accel::from_triangles`] the
    /// vertices are the triangles' corners in order, three per triangle), with the same
    /// options. Fails, leaving the structure as it was, on a vertex count that differs from
    /// the build's or on a non-finite vertex.
    pub fn rebuild(&mut self, vertices: &[Vec3]) -> Result<(), TraceError> {
        if vertices.len() != self.vertex_count {
            return Err(TraceError::VertexCount {
                given: vertices.len(),
                expected: self.vertex_count,
            });
        }
        let tris: Vec<[Vec3; 3]> = self
            .indices
            .iter()
            .map(|t| t.map(|i| vertices[i as usize]))
            .collect();
        let bvh2 = self.run(|| build_bvh2(&tris, &self.opts))?;
        self.bvh = WideBvh::from_bvh2(&bvh2, &tris)?;
        self.tris = tris;
        Ok(())
    }

    /// Build over a triangle list (triangle id = position in `tris`).
    pub fn from_triangles(tris: Vec<[Vec3; 3]>, opts: &BuildOptions) -> Result<Accel, TraceError> {
        if opts.threads == Some(0) {
            return Err(TraceError::Build(
                "the thread count must be at least 1".into(),
            ));
        }
        let pool = match opts.threads {
            Some(n) => Some(Arc::new(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .map_err(|e| TraceError::ThreadPool(e.to_string()))?,
            )),
            None => None,
        };
        let bvh2 = match &pool {
            Some(p) => p.install(|| build_bvh2(&tris, opts))?,
            None => build_bvh2(&tris, opts)?,
        };
        let bvh = WideBvh::from_bvh2(&bvh2, &tris)?;
        Ok(Accel::assemble(bvh, tris, *opts, pool))
    }

    fn assemble(
        bvh: WideBvh,
        tris: Vec<[Vec3; 3]>,
        opts: BuildOptions,
        pool: Option<Arc<rayon::ThreadPool>>,
    ) -> Accel {
        let n = tris.len() as u32;
        Accel {
            bvh,
            indices: (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(),
            vertex_count: tris.len() * 3,
            tris,
            opts,
            pool,
        }
    }

    /// Wrap a BVH2 from any builder (validated against `tris`, then collapsed to 4- and 8-wide).
    /// A later [`Accel::rebuild`] builds with the default options.
    pub fn from_bvh2(bvh2: &Bvh, tris: Vec<[Vec3; 3]>) -> Result<Accel, TraceError> {
        let bvh = WideBvh::from_bvh2(bvh2, &tris)?;
        Ok(Accel::assemble(bvh, tris, BuildOptions::default(), None))
    }

    /// The closest hit of `ray` in `[tnear, tfar]` (`None` for a miss or an invalid ray:
    /// non-finite or zero direction, NaN interval).
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        closest::<false>(
            &self.bvh,
            ray,
            NodeTest::fastest(),
            &mut TraceStats::default(),
        )
    }

    /// True when `ray` hits anything in `[tnear, tfar]`.
    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        occluded::<false>(
            &self.bvh,
            ray,
            NodeTest::fastest(),
            &mut TraceStats::default(),
        )
    }

    /// Closest hits of many rays, in parallel; one answer per ray, in order.
    pub fn intersect_batch(&self, rays: &[Ray]) -> Vec<Option<Hit>> {
        self.run(|| rays.par_iter().map(|r| self.intersect(r)).collect())
    }

    /// Occlusion of many rays, in parallel; one answer per ray, in order.
    pub fn occluded_batch(&self, rays: &[Ray]) -> Vec<bool> {
        self.run(|| rays.par_iter().map(|r| self.occluded(r)).collect())
    }

    /// The triangles, in id order.
    pub fn triangles(&self) -> &[[Vec3; 3]] {
        &self.tris
    }

    /// The wide BVH being traced.
    pub fn wide_bvh(&self) -> &WideBvh {
        &self.bvh
    }

    fn run<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        match &self.pool {
            Some(p) => p.install(f),
            None => f(),
        }
    }
}

/// The BVH2 a preset and its overrides ask for, built by the LBVH / binned-SAH pipeline.
pub fn build_bvh2(tris: &[[Vec3; 3]], opts: &BuildOptions) -> Result<Bvh, TraceError> {
    if tris.is_empty() {
        return Err(TraceError::NoTriangles);
    }
    let aabbs: Vec<Aabb> = tris
        .par_iter()
        .map(|t| Aabb::from_triangle(t[0], t[1], t[2]))
        .collect();
    if let Some(i) = aabbs.iter().position(|b| !b.is_finite()) {
        return Err(TraceError::NonFinite(i));
    }
    let (builder, layout, restructure) = opts.resolve();
    let max_leaf = opts.leaf_size.unwrap_or(DEFAULT_LEAF_SIZE);
    if max_leaf == 0 {
        return Err(TraceError::Build(
            "the maximum leaf size must be at least 1".into(),
        ));
    }
    if opts.threads == Some(0) {
        return Err(TraceError::Build(
            "the thread count must be at least 1".into(),
        ));
    }
    let collapse = CollapseParams {
        max_leaf,
        ..CollapseParams::default()
    };
    let threads = opts.threads.unwrap_or_else(rayon::current_num_threads);
    let bopts = crate::build::BuildOptions {
        layout,
        builder,
        threads,
        collapse: if restructure {
            CollapseParams::NONE
        } else {
            collapse
        },
    };
    let out = build_aabbs(aabbs, &bopts).map_err(|e| TraceError::Build(e.to_string()))?;
    if !restructure {
        return Ok(out.bvh);
    }
    let mut bvh = out.bvh;
    restructure_atr(&mut bvh, &out.aabbs, &AtrConfig::default())
        .map_err(|e| TraceError::Build(e.to_string()))?;
    Ok(collapse_bvh(&bvh, &collapse))
}
