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
//!
//! Builds, rebuilds and batches run in the caller's rayon pool: an `Accel` owns no threads.
//! For a given pool, call them inside `pool.install(|| ...)`.
#![forbid(unsafe_code)]

use glam::Vec3;
use rayon::prelude::*;

use emc_core::{Aabb, LayoutSpec};

use crate::auto::LayoutChoice;

use crate::build::{build_aabbs_inline, Builder};
use crate::bvh::atrbvh::{restructure_built as restructure_atr, AtrConfig};
use crate::bvh::collapse::collapse_bvh;
use crate::bvh::refit::CollapseParams;
use crate::bvh::Bvh;
use crate::trace::intersect::{Hit, Ray};
use crate::trace::refit::RefitPlan;
use crate::trace::traverse::{closest, occluded, NodeTest, TraceStats};
use crate::trace::wide::{WideBvh, WideNodeN, WIDTH, WIDTH8};
use crate::trace::wide_lbvh::{build_fast, FastScratch, FastTimes};
use crate::trace::TraceError;

/// Speed / quality trade-off of [`Accel::build`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Preset {
    /// Fastest build: the LBVH's radix tree (`lbvh`) over `emc32-var` codes opened straight
    /// into the traced wide tree (see `trace::wide_lbvh`), for scenes rebuilt every frame.
    Fast,
    /// LBVH (`lbvh`, `emc64-var`) improved by agglomerative treelet restructuring (`atrbvh`).
    #[default]
    Balanced,
    /// Best tracing speed: top-down binned SAH, for static scenes traced many times.
    Quality,
}

/// Options of [`Accel::build`]: a preset, and overrides of its choices, set with the
/// `with_` methods (the struct is `#[non_exhaustive]`, so options can be added later without
/// breaking callers).
///
/// ```
/// use emc_cpu::{BuildOptions, Builder, Preset};
/// use emc_core::LayoutSpec;
///
/// let opts = BuildOptions::preset(Preset::Balanced)
///     .with_layout(LayoutSpec::Emc64Sort)
///     .with_width(4);
/// assert_eq!(opts.resolve().0, Builder::Lbvh);
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct BuildOptions {
    /// The preset that fills in everything left `None`.
    pub preset: Preset,
    /// Code layout of the LBVH builders, fixed or [`crate::auto::AUTO`] (chosen per scene,
    /// see [`crate::auto`]); ignored by `binned-sah`.
    pub layout: Option<LayoutChoice>,
    /// Hierarchy builder.
    pub builder: Option<Builder>,
    /// Run treelet restructuring (`atrbvh`) on the binary tree before the leaf collapse.
    pub restructure: Option<bool>,
    /// Largest leaf of the SAH leaf collapse of the BVH2 before the wide collapse (1 keeps one
    /// triangle per leaf; default 4, except after treelet restructuring, where `None` leaves
    /// the leaves to the wide collapse). The wide tree's cover DP merges leaves up to eight
    /// triangles either way; the fast preset's builder chooses its own.
    pub leaf_size: Option<u32>,
    /// Children per node of the traced tree, 4 or 8 (`None`: [`default_width`]).
    pub width: Option<usize>,
}

impl BuildOptions {
    /// Options of a preset, with no override.
    pub fn preset(preset: Preset) -> BuildOptions {
        BuildOptions {
            preset,
            ..BuildOptions::default()
        }
    }

    /// With this code layout (a [`LayoutSpec`] or a [`LayoutChoice`], e.g. [`crate::auto::AUTO`]).
    #[inline]
    pub fn with_layout(mut self, layout: impl Into<LayoutChoice>) -> BuildOptions {
        self.layout = Some(layout.into());
        self
    }

    /// With this hierarchy builder.
    #[inline]
    pub fn with_builder(mut self, builder: Builder) -> BuildOptions {
        self.builder = Some(builder);
        self
    }

    /// With or without treelet restructuring.
    #[inline]
    pub fn with_restructure(mut self, restructure: bool) -> BuildOptions {
        self.restructure = Some(restructure);
        self
    }

    /// With this largest leaf of the SAH leaf collapse ([`BuildOptions::leaf_size`]).
    #[inline]
    pub fn with_leaf_size(mut self, leaf_size: u32) -> BuildOptions {
        self.leaf_size = Some(leaf_size);
        self
    }

    /// With this many children per node of the traced tree (4 or 8).
    #[inline]
    pub fn with_width(mut self, width: usize) -> BuildOptions {
        self.width = Some(width);
        self
    }

    /// The builder, layout and restructuring the preset and overrides resolve to.
    pub fn resolve(&self) -> (Builder, LayoutChoice, bool) {
        let (b, l, r) = match self.preset {
            Preset::Fast => (Builder::Lbvh, LayoutSpec::Emc32Var, false),
            Preset::Balanced => (Builder::Lbvh, LayoutSpec::Emc64Var, true),
            Preset::Quality => (Builder::BinnedSah, LayoutSpec::Emc64Var, false),
        };
        (
            self.builder.unwrap_or(b),
            self.layout.unwrap_or(LayoutChoice::Fixed(l)),
            self.restructure.unwrap_or(r),
        )
    }
}

/// Whether every one of `n` vertices is named by some triangle.
fn every_vertex_referenced(indices: &[[u32; 3]], n: usize) -> bool {
    let mut seen = vec![false; n];
    for t in indices {
        for &i in t {
            seen[i as usize] = true;
        }
    }
    seen.iter().all(|&s| s)
}

/// The largest absolute coordinate of `v`, or `None` when one is not finite.
fn max_abs_of_vertices(v: &[Vec3]) -> Option<f32> {
    let (m, ok) = v
        .par_chunks(16384)
        .map(|c| {
            let (mut m, mut ok) = (0.0f32, true);
            for p in c {
                for x in [p.x, p.y, p.z] {
                    let a = x.abs();
                    ok &= a.is_finite();
                    m = if a > m { a } else { m };
                }
            }
            (m, ok)
        })
        .reduce(|| (0.0, true), |a, b| (a.0.max(b.0), a.1 && b.1));
    ok.then_some(m)
}

/// The largest absolute coordinate of the vertices the triangles name, and the first triangle
/// with a non-finite corner.
fn max_abs_of_triangles(indices: &[[u32; 3]], vertices: &[Vec3]) -> (f32, Option<usize>) {
    let (m, bad) = indices
        .par_iter()
        .enumerate()
        .with_min_len(4096)
        .fold(
            || (0.0f32, usize::MAX),
            |(mut m, mut bad), (i, t)| {
                for &k in t {
                    let v = vertices[k as usize];
                    if !v.is_finite() {
                        bad = bad.min(i);
                    }
                    m = m.max(v.abs().max_element());
                }
                (m, bad)
            },
        )
        .reduce(|| (0.0, usize::MAX), |a, b| (a.0.max(b.0), a.1.min(b.1)));
    (m, (bad != usize::MAX).then_some(bad))
}

/// Default largest leaf of [`BuildOptions::leaf_size`].
pub const DEFAULT_LEAF_SIZE: u32 = 4;

/// The tree width a build makes when [`BuildOptions::width`] is `None`: 8 where the CPU has
/// AVX2 (its node test covers eight children per instruction), else 4 (SSE).
pub fn default_width() -> usize {
    if crate::trace::traverse::avx2_available() {
        WIDTH8
    } else {
        WIDTH
    }
}

/// A triangle mesh ready for ray queries: a copy of the mesh and its wide BVH.
#[derive(Debug, Clone)]
pub struct Accel {
    bvh: WideBvh,
    vertices: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
    opts: BuildOptions,
    test: NodeTest,
    scratch4: FastScratch<WIDTH>,
    scratch8: FastScratch<WIDTH8>,
    phases: FastTimes,
    /// The other builders' triangle list and boxes, kept for the next rebuild.
    bvh2_scratch: (Vec<[Vec3; 3]>, Vec<Aabb>),
    /// The level order of [`Accel::refit`] and whether every vertex is referenced, made at
    /// the first refit after a build.
    refit: Option<(RefitPlan, bool)>,
}

impl Accel {
    /// Build over an indexed mesh. Fails on an out-of-range index, a non-finite vertex, an
    /// empty mesh, an unknown builder or layout, a width other than 4 or 8, or a tree too deep
    /// to trace.
    pub fn build(
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        opts: &BuildOptions,
    ) -> Result<Accel, TraceError> {
        let width = opts.width.unwrap_or_else(default_width);
        if width != WIDTH && width != WIDTH8 {
            return Err(TraceError::Width(width));
        }
        let mut a = Accel {
            bvh: WideBvh::empty(),
            vertices: Vec::new(),
            indices: Vec::new(),
            opts: *opts,
            test: NodeTest::for_width(width),
            scratch4: FastScratch::default(),
            scratch8: FastScratch::default(),
            phases: FastTimes::default(),
            bvh2_scratch: (Vec::new(), Vec::new()),
            refit: None,
        };
        a.build_over(vertices, indices)?;
        a.vertices = vertices.to_vec();
        a.indices = indices.to_vec();
        a.debug_validate();
        Ok(a)
    }

    /// Build over a triangle list (triangle id = position in `tris`; the mesh's vertices are
    /// the corners in order, three per triangle).
    pub fn from_triangles(tris: Vec<[Vec3; 3]>, opts: &BuildOptions) -> Result<Accel, TraceError> {
        let vertices: Vec<Vec3> = tris.iter().flatten().copied().collect();
        let n = tris.len() as u32;
        if tris.len() > crate::trace::wide::MAX_TRIANGLES {
            return Err(TraceError::TooManyTriangles(tris.len()));
        }
        let indices: Vec<[u32; 3]> = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        Accel::build(&vertices, &indices, opts)
    }

    /// Rebuild over new positions of the same mesh: `vertices` replaces the vertices of the
    /// build (same count, same indices; for [`Accel::from_triangles`] the triangles' corners in
    /// order), with the same options, reusing the previous build's buffers (the fast preset
    /// all of them; the other presets the triangle list, the boxes and the wide tree's nodes
    /// and packets, while their BVH2 builders still allocate their own). Fails, leaving the
    /// structure as it was, on a vertex count that differs from the build's or on a non-finite
    /// vertex; a tree too deep to trace is an error that leaves the structure empty.
    pub fn rebuild(&mut self, vertices: &[Vec3]) -> Result<(), TraceError> {
        if vertices.len() != self.vertices.len() {
            return Err(TraceError::VertexCount {
                given: vertices.len(),
                expected: self.vertices.len(),
            });
        }
        let indices = std::mem::take(&mut self.indices);
        let r = self.build_over(vertices, &indices);
        self.indices = indices;
        self.refit = None;
        r?;
        self.vertices.copy_from_slice(vertices);
        self.debug_validate();
        Ok(())
    }

    /// Refit the tree to new positions of the same mesh: `vertices` replaces the vertices (same
    /// count, same indices), the tree keeps its topology and only its boxes move (see
    /// [`WideBvh::refit`]), level by level in the caller's rayon pool. Much cheaper than
    /// [`Accel::rebuild`], but the tree is the old one: for a deformation that moves
    /// triangles far from their neighbours it traces slower than a rebuild (`emc compare
    /// --frames` shows when). Fails, leaving the structure as it was, on a vertex count that
    /// differs from the build's or on a non-finite vertex.
    pub fn refit(&mut self, vertices: &[Vec3]) -> Result<(), TraceError> {
        if vertices.len() != self.vertices.len() {
            return Err(TraceError::VertexCount {
                given: vertices.len(),
                expected: self.vertices.len(),
            });
        }
        let (bvh, indices, nv) = (&self.bvh, &self.indices, vertices.len());
        let (plan, all_referenced) = &mut *self
            .refit
            .get_or_insert_with(|| (RefitPlan::new(bvh), every_vertex_referenced(indices, nv)));
        // The largest coordinate of the referenced vertices (as a build measures it): over
        // the vertex list when every vertex is referenced, else through the indices (which
        // also names the first triangle with a non-finite corner).
        let scanned = if *all_referenced {
            max_abs_of_vertices(vertices)
        } else {
            None
        };
        let max_abs = match scanned {
            Some(m) => m,
            None => {
                let (m, bad) = max_abs_of_triangles(indices, vertices);
                if let Some(i) = bad {
                    return Err(TraceError::NonFinite(i));
                }
                m
            }
        };
        self.vertices.copy_from_slice(vertices);
        let (verts, idx) = (&self.vertices, &self.indices);
        self.bvh.refit(
            plan,
            |id| {
                let [a, b, c] = idx[id as usize];
                [verts[a as usize], verts[b as usize], verts[c as usize]]
            },
            max_abs,
        );
        self.debug_validate();
        Ok(())
    }

    /// Debug builds check every tree they build (see [`WideBvh::validate`]).
    fn debug_validate(&self) {
        if cfg!(debug_assertions) {
            if let Err(e) = self.bvh.validate(self.indices.len(), |i| self.triangle(i)) {
                panic!("the builder made an invalid tree: {e}");
            }
        }
    }

    /// Build `self.bvh` over the mesh with `self.opts`, reusing the buffers held.
    fn build_over(&mut self, vertices: &[Vec3], indices: &[[u32; 3]]) -> Result<(), TraceError> {
        let width = self.test.width();
        let (builder, layout, restructure) = self.opts.resolve();
        // The radix tree (Karras = Apetrei) without restructuring goes straight to the wide
        // tree; the other builders make a BVH2 that is then collapsed.
        let fast = matches!(builder, Builder::Lbvh | Builder::LbvhApetrei)
            && !restructure
            && self.opts.leaf_size.is_none_or(|l| l == DEFAULT_LEAF_SIZE);
        let opts = self.opts;
        let bvh = &mut self.bvh;
        let (scratch4, scratch8) = (&mut self.scratch4, &mut self.scratch8);
        let phases = &mut self.phases;
        let (tris, aabbs) = &mut self.bvh2_scratch;
        *phases = FastTimes::default();
        let run = || -> Result<(), TraceError> {
            if fast {
                let times = phases;
                return if width == WIDTH8 {
                    let mut nodes = std::mem::take(&mut bvh.nodes8);
                    let mut packets = std::mem::take(&mut bvh.packets);
                    let r = build_fast::<WIDTH8>(
                        vertices,
                        indices,
                        &layout,
                        scratch8,
                        &mut nodes,
                        &mut packets,
                        times,
                    );
                    bvh.nodes.clear();
                    bvh.nodes8 = nodes;
                    bvh.packets = packets;
                    r.map(|t| bvh.set_fast(indices.len(), t, WIDTH8))
                } else {
                    let mut nodes = std::mem::take(&mut bvh.nodes);
                    let mut packets = std::mem::take(&mut bvh.packets);
                    let r = build_fast::<WIDTH>(
                        vertices,
                        indices,
                        &layout,
                        scratch4,
                        &mut nodes,
                        &mut packets,
                        times,
                    );
                    bvh.nodes8.clear();
                    bvh.nodes = nodes;
                    bvh.packets = packets;
                    r.map(|t| bvh.set_fast(indices.len(), t, WIDTH))
                };
            }
            gather_triangles(vertices, indices, tris)?;
            let bvh2 = build_bvh2_in(tris, &opts, aabbs)?;
            bvh.rebuild_from_own_bvh2(&bvh2, tris, width)
        };
        run()
    }

    /// Wrap a BVH2 from any builder (validated against `tris`, then collapsed to the default
    /// width). A later [`Accel::rebuild`] builds with the default options.
    pub fn from_bvh2(bvh2: &Bvh, tris: Vec<[Vec3; 3]>) -> Result<Accel, TraceError> {
        let width = default_width();
        let bvh = WideBvh::from_bvh2_width(bvh2, &tris, width)?;
        let n = tris.len() as u32;
        Ok(Accel {
            bvh,
            vertices: tris.iter().flatten().copied().collect(),
            indices: (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(),
            opts: BuildOptions::default(),
            test: NodeTest::for_width(width),
            scratch4: FastScratch::default(),
            scratch8: FastScratch::default(),
            phases: FastTimes::default(),
            bvh2_scratch: (Vec::new(), Vec::new()),
            refit: None,
        })
    }

    /// The closest hit of `ray` in `[tnear, tfar]` (`None` for a miss or an invalid ray:
    /// non-finite or zero direction, NaN interval).
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        closest::<false>(&self.bvh, ray, self.test, &mut TraceStats::default())
    }

    /// True when `ray` hits anything in `[tnear, tfar]`.
    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        occluded::<false>(&self.bvh, ray, self.test, &mut TraceStats::default())
    }

    /// Closest hits of many rays, in parallel; one answer per ray, in order.
    pub fn intersect_batch(&self, rays: &[Ray]) -> Vec<Option<Hit>> {
        rays.par_iter().map(|r| self.intersect(r)).collect()
    }

    /// Occlusion of many rays, in parallel; one answer per ray, in order.
    pub fn occluded_batch(&self, rays: &[Ray]) -> Vec<bool> {
        rays.par_iter().map(|r| self.occluded(r)).collect()
    }

    /// Triangle `id`'s corners.
    #[inline]
    pub fn triangle(&self, id: u32) -> [Vec3; 3] {
        self.indices[id as usize].map(|i| self.vertices[i as usize])
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// Number of vertices (the copy of the mesh's vertex list the structure keeps).
    pub fn vertex_count(&self) -> usize {
        self.vertices.len()
    }

    /// All triangles in id order (a new list).
    pub fn triangles(&self) -> Vec<[Vec3; 3]> {
        self.indices
            .iter()
            .map(|t| t.map(|i| self.vertices[i as usize]))
            .collect()
    }

    /// A box around every triangle: the union of the root's children's boxes (which the
    /// builders pad a little for rounding).
    pub fn bounds(&self) -> Aabb {
        fn root<const W: usize>(n: &WideNodeN<W>) -> Aabb {
            (0..W)
                .map(|lane| n.child_box(lane))
                .filter(Aabb::is_valid)
                .fold(Aabb::EMPTY, |a, b| a.union(&b))
        }
        match (self.bvh.nodes8.first(), self.bvh.nodes.first()) {
            (Some(n), _) => root(n),
            (None, Some(n)) => root(n),
            (None, None) => Aabb::EMPTY,
        }
    }

    /// The wide BVH being traced.
    pub fn wide_bvh(&self) -> &WideBvh {
        &self.bvh
    }

    /// Wall milliseconds of the last build's phases when it took the fast path (the fast
    /// preset's LBVH straight to the wide tree), else all zero.
    pub fn build_phases(&self) -> FastTimes {
        self.phases
    }

    /// The node test (and so the tree width) queries use.
    pub fn node_test(&self) -> NodeTest {
        self.test
    }
}

/// The triangles of an indexed mesh (an index naming no vertex is an error).
fn gather_triangles(
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    tris: &mut Vec<[Vec3; 3]>,
) -> Result<(), TraceError> {
    tris.clear();
    tris.reserve(indices.len());
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
    Ok(())
}

/// The BVH2 a preset and its overrides ask for, built by the LBVH / binned-SAH pipeline.
pub fn build_bvh2(tris: &[[Vec3; 3]], opts: &BuildOptions) -> Result<Bvh, TraceError> {
    build_bvh2_in(tris, opts, &mut Vec::new())
}

/// [`build_bvh2`] with the triangles' boxes in `aabbs` (reused, left holding them).
fn build_bvh2_in(
    tris: &[[Vec3; 3]],
    opts: &BuildOptions,
    aabbs: &mut Vec<Aabb>,
) -> Result<Bvh, TraceError> {
    if tris.is_empty() {
        return Err(TraceError::NoTriangles);
    }
    // Checked on the corners: a box's min/max can drop a NaN.
    if let Some(i) = tris.iter().position(|t| !t.iter().all(|v| v.is_finite())) {
        return Err(TraceError::NonFinite(i));
    }
    aabbs.clear();
    aabbs.par_extend(
        tris.par_iter()
            .map(|t| Aabb::from_triangle(t[0], t[1], t[2])),
    );
    let (builder, layout, restructure) = opts.resolve();
    let max_leaf = opts.leaf_size.unwrap_or(DEFAULT_LEAF_SIZE);
    if max_leaf == 0 {
        return Err(TraceError::ZeroLeafSize);
    }
    let collapse = CollapseParams {
        max_leaf,
        ..CollapseParams::default()
    };
    let threads = rayon::current_num_threads();
    let bopts = crate::build::PipelineOptions {
        layout,
        builder,
        threads,
        collapse: if restructure {
            CollapseParams::NONE
        } else {
            collapse
        },
    };
    let out = build_aabbs_inline(std::mem::take(aabbs), &bopts).map_err(TraceError::Build)?;
    *aabbs = out.aabbs;
    if !restructure {
        return Ok(out.bvh);
    }
    let mut bvh = out.bvh;
    restructure_atr(&mut bvh, aabbs, &AtrConfig::default()).map_err(TraceError::Restructure)?;
    // Without a leaf size of its own, the restructured tree keeps one triangle per leaf: the
    // wide collapse's cover DP chooses the leaves itself (up to eight triangles). An SAH leaf
    // collapse before it was measured to change nothing the DP chooses (same wide SAH and work
    // per ray on san-francisco, bathroom and dragon) and costs more than it saves here (1.39 vs
    // 1.24 G instructions for a san-francisco build); after binned SAH it saves more than it
    // costs, so that path keeps it.
    if opts.leaf_size.is_none() {
        return Ok(bvh);
    }
    Ok(collapse_bvh(&bvh, &collapse))
}
