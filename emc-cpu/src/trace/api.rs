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

use std::sync::{Arc, Mutex};

use glam::Vec3;
use rayon::prelude::*;

use emc_core::{Aabb, LayoutSpec};

use crate::auto::LayoutChoice;

use crate::build::{build_aabbs_inline_in, BuildArena, Builder};
use crate::bvh::atrbvh::{restructure_built as restructure_atr, AtrConfig, AtrScratch};
use crate::bvh::binned_sah::{build_binned_sah_leaves_in, BinnedScratch, LeafRule, DEFAULT_BINS};
use crate::bvh::collapse::collapse_bvh;
use crate::bvh::refit::CollapseParams;
use crate::bvh::Bvh;
use crate::trace::intersect::{Hit, Ray};
use crate::trace::refit::RefitPlan;
use crate::trace::traverse::{
    closest_valid, kernel_of, occluded_valid, KernelChoice, NodeTest, TraceStats,
};
use crate::trace::wide::{
    CollapseScratch, Indexed, Prep, TriPacket, WideBvh, WideNode, WideNode8, WIDTH, WIDTH8,
};
use crate::trace::wide_lbvh::{build_fast, mesh_boxes, FastScratch, FastTimes, LEAF_MAX};
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
    /// triangles either way; the fast preset's builder chooses its own, up to eight, or one
    /// triangle per leaf with a leaf size of 1.
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

/// The memory of builds, kept from one build to the next, as Embree's device keeps its own:
/// the scratch (boxes, codes and sort buffers of the fast preset; the boxes, primitive arrays,
/// binary nodes and collapse plans of the others), and the buffers of
/// structures built in it once they are dropped (their nodes, triangle packets and mesh
/// copies, the largest few of each kind), which the next build takes instead of fresh pages.
/// Build many meshes in one context ([`Accel::build_in`], [`Accel::rebuild_in`]) and only the
/// first build faults in fresh memory for what later ones reuse (the structures themselves
/// hold no scratch); a plain [`Accel::build`] keeps a context of its own inside the structure
/// for its [`Accel::rebuild`]s (all of it for the fast preset, only the boxes for the others,
/// whose builders' arrays outweigh the tree). What a build makes never depends on what the
/// context held before.
///
/// ```
/// use emc_cpu::{Accel, BuildContext, BuildOptions, Preset};
/// use glam::Vec3;
///
/// let mut ctx = BuildContext::new();
/// let opts = BuildOptions::preset(Preset::Quality);
/// let square = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y];
/// let a = Accel::build_in(&mut ctx, &square, &[[0, 1, 2], [0, 2, 3]], &opts)?;
/// let b = Accel::build_in(&mut ctx, &square, &[[0, 1, 3]], &opts)?; // the same buffers
/// assert_eq!((a.triangle_count(), b.triangle_count()), (2, 1));
/// # Ok::<(), emc_cpu::TraceError>(())
/// ```
#[derive(Debug, Default)]
pub struct BuildContext {
    fast4: FastScratch<WIDTH>,
    fast8: FastScratch<WIDTH8>,
    /// The other builders' triangle boxes.
    aabbs: Vec<Aabb>,
    /// The binned-SAH builder's buffers (quality preset).
    binned: BinnedScratch,
    /// The LBVH pipeline's buffers (balanced preset).
    arena: BuildArena,
    /// The wide collapse's plans and work lists.
    collapse: CollapseScratch,
    /// The treelet restructuring's per-node arrays (balanced preset).
    atr: AtrScratch,
    /// The buffers dropped structures built in this context gave back.
    spare: Arc<Spare>,
}

impl BuildContext {
    /// An empty context (its first build allocates).
    pub fn new() -> BuildContext {
        BuildContext::default()
    }

    /// Give back every buffer the context holds (its next build allocates afresh).
    pub fn clear(&mut self) {
        *self = BuildContext::default();
    }

    /// What a structure's own context keeps after a plain build or rebuild with `opts`: all
    /// of it for the fast path (rebuilt every frame, its scratch is ~100 bytes per triangle),
    /// only the triangle boxes for the others, whose builders' arrays (~250 bytes per
    /// triangle for binned SAH) would otherwise outweigh the tree; they are made afresh by
    /// the next rebuild. A shared context ([`Accel::build_in`]) keeps everything.
    fn keep_for(&mut self, opts: &BuildOptions) {
        if !fast_path(opts) {
            self.binned = BinnedScratch::default();
            self.arena = BuildArena::default();
            self.collapse = CollapseScratch::default();
            self.atr = AtrScratch::default();
        }
    }
}

/// Whether `opts` build on the fast path (the radix tree straight to the wide tree).
fn fast_path(opts: &BuildOptions) -> bool {
    let (builder, _, restructure) = opts.resolve();
    matches!(builder, Builder::Lbvh | Builder::LbvhApetrei)
        && !restructure
        && opts
            .leaf_size
            .is_none_or(|l| l == DEFAULT_LEAF_SIZE || l == 1)
}

/// The largest leaf of a fast-path build: one triangle when asked for, else the builder's own
/// choice up to [`LEAF_MAX`].
fn fast_leaf_max(opts: &BuildOptions) -> u32 {
    if opts.leaf_size == Some(1) {
        1
    } else {
        LEAF_MAX
    }
}

/// Buffers of dropped structures, waiting for the next build of their context: at most
/// [`SPARE_PER_KIND`] of each kind, the largest kept.
#[derive(Debug, Default)]
struct Spare(Mutex<SpareLists>);

/// How many buffers of each kind a context keeps from dropped structures (one structure
/// rebuilt in turn needs one; more would hold memory nobody asked for).
const SPARE_PER_KIND: usize = 2;

#[derive(Debug, Default)]
struct SpareLists {
    nodes4: Vec<Vec<WideNode>>,
    nodes8: Vec<Vec<WideNode8>>,
    packets: Vec<Vec<TriPacket>>,
    vertices: Vec<Vec<Vec3>>,
    indices: Vec<Vec<[u32; 3]>>,
}

/// Keep `v` in `list` if it is among the largest [`SPARE_PER_KIND`] (with its elements: the
/// builders that write in place keep them until they are overwritten; the others clear).
fn keep_spare<T>(list: &mut Vec<Vec<T>>, v: Vec<T>) {
    if v.capacity() == 0 {
        return;
    }
    if list.len() < SPARE_PER_KIND {
        list.push(v);
    } else if let Some(small) = list.iter_mut().min_by_key(|x| x.capacity()) {
        if small.capacity() < v.capacity() {
            *small = v;
        }
    }
}

/// The largest buffer of `list` (it may still hold elements), or a new empty one.
fn take_spare<T>(list: &mut Vec<Vec<T>>) -> Vec<T> {
    let best = (0..list.len()).max_by_key(|&i| list[i].capacity());
    best.map(|i| list.swap_remove(i)).unwrap_or_default()
}

impl Spare {
    fn lists(&self) -> std::sync::MutexGuard<'_, SpareLists> {
        // A panic while the lock was held leaves only buffers behind: still usable.
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The buffers of a new structure: the largest of each kind kept.
    fn take(&self) -> (WideBvh, Vec<Vec3>, Vec<[u32; 3]>) {
        let mut l = self.lists();
        let mut bvh = WideBvh::empty();
        bvh.nodes = take_spare(&mut l.nodes4);
        bvh.nodes8 = take_spare(&mut l.nodes8);
        bvh.packets = take_spare(&mut l.packets);
        (bvh, take_spare(&mut l.vertices), take_spare(&mut l.indices))
    }

    /// Keep a dropped structure's buffers.
    fn give(&self, a: &mut Accel) {
        let mut l = self.lists();
        keep_spare(&mut l.nodes4, std::mem::take(&mut a.bvh.nodes));
        keep_spare(&mut l.nodes8, std::mem::take(&mut a.bvh.nodes8));
        keep_spare(&mut l.packets, std::mem::take(&mut a.bvh.packets));
        keep_spare(&mut l.vertices, std::mem::take(&mut a.vertices));
        keep_spare(&mut l.indices, std::mem::take(&mut a.indices));
    }
}

impl Clone for BuildContext {
    /// An empty context: a copy of an [`Accel`] does not copy its build buffers (the only
    /// thing a build reads from them, the fast preset's last sorted order, is a rebuild's
    /// shortcut; its next build sorts from scratch).
    fn clone(&self) -> BuildContext {
        BuildContext::default()
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
    /// The traversal kernel of `test` on this tree (chosen again after every build).
    kernel: KernelChoice,
    /// The context of [`Accel::build`] and [`Accel::rebuild`] (empty after
    /// [`Accel::build_in`] until a plain rebuild).
    ctx: BuildContext,
    phases: FastTimes,
    /// The level order of [`Accel::refit`] and whether every vertex is referenced, made at
    /// the first refit after a build.
    refit: Option<(RefitPlan, bool)>,
    /// Where the buffers go when the structure is dropped (built with [`Accel::build_in`]).
    spare: Option<Arc<Spare>>,
    /// The build this structure came from (a clone keeps it): a context whose last fast build
    /// had this token keeps that sorted order for the rebuild's sort; every fresh build takes a
    /// new token, so it never has one.
    token: u64,
}

/// The next [`Accel`]'s token.
static NEXT_TOKEN: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// A token no other [`Accel`] of this process has had.
fn fresh_token() -> u64 {
    NEXT_TOKEN.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

impl Drop for Accel {
    fn drop(&mut self) {
        if let Some(spare) = self.spare.take() {
            spare.give(self);
        }
    }
}

impl Accel {
    /// Build over an indexed mesh. Fails on an out-of-range index, a non-finite vertex, an
    /// empty mesh, an unknown builder or layout, a width other than 4 or 8, or a tree too deep
    /// to trace. The structure keeps its build buffers for [`Accel::rebuild`]; to share them
    /// between structures, build with [`Accel::build_in`].
    pub fn build(
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        opts: &BuildOptions,
    ) -> Result<Accel, TraceError> {
        let mut ctx = BuildContext::new();
        let mut a = Accel::build_in(&mut ctx, vertices, indices, opts)?;
        // The structure's own context: nothing to give back to on drop.
        a.spare = None;
        ctx.keep_for(opts);
        a.ctx = ctx;
        Ok(a)
    }

    /// [`Accel::build`] in the buffers of `ctx` (kept there for the next build; the structure
    /// holds none).
    pub fn build_in(
        ctx: &mut BuildContext,
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        opts: &BuildOptions,
    ) -> Result<Accel, TraceError> {
        let width = opts.width.unwrap_or_else(default_width);
        if width != WIDTH && width != WIDTH8 {
            return Err(TraceError::Width(width));
        }
        let (bvh, mut vert_copy, mut index_copy) = ctx.spare.take();
        let test = NodeTest::for_width(width);
        let mut a = Accel {
            kernel: kernel_of(&bvh, test),
            bvh,
            vertices: Vec::new(),
            indices: Vec::new(),
            opts: *opts,
            test,
            ctx: BuildContext::new(),
            phases: FastTimes::default(),
            refit: None,
            spare: Some(Arc::clone(&ctx.spare)),
            token: fresh_token(),
        };
        build_over(
            a.token,
            &mut a.bvh,
            &mut a.phases,
            &a.opts,
            width,
            ctx,
            vertices,
            indices,
        )?;
        a.kernel = kernel_of(&a.bvh, a.test);
        crate::buffers::copied_par(&mut vert_copy, vertices);
        crate::buffers::copied_par(&mut index_copy, indices);
        a.vertices = vert_copy;
        a.indices = index_copy;
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
    /// order), with the same options, in the structure's own buffers (the wide tree's nodes
    /// and packets, and what its own context keeps: every scratch buffer of the fast preset,
    /// the boxes of the others; see [`BuildContext`] to keep all of them).
    /// Fails, leaving the structure as it was, on a vertex count that differs from the build's
    /// or on a non-finite vertex; a tree too deep to trace is an error that leaves the
    /// structure empty.
    pub fn rebuild(&mut self, vertices: &[Vec3]) -> Result<(), TraceError> {
        let mut ctx = std::mem::take(&mut self.ctx);
        let r = self.rebuild_in(&mut ctx, vertices);
        ctx.keep_for(&self.opts);
        self.ctx = ctx;
        r
    }

    /// [`Accel::rebuild`] with the scratch buffers of `ctx` (the wide tree's nodes and packets
    /// are still the structure's own).
    pub fn rebuild_in(
        &mut self,
        ctx: &mut BuildContext,
        vertices: &[Vec3],
    ) -> Result<(), TraceError> {
        if vertices.len() != self.vertices.len() {
            return Err(TraceError::VertexCount {
                given: vertices.len(),
                expected: self.vertices.len(),
            });
        }
        let width = self.test.width();
        let r = build_over(
            self.token,
            &mut self.bvh,
            &mut self.phases,
            &self.opts,
            width,
            ctx,
            vertices,
            &self.indices,
        );
        self.refit = None;
        // Chosen again for whatever tree the build left (the same one after a success).
        self.kernel = kernel_of(&self.bvh, self.test);
        r?;
        crate::buffers::copy_par(&mut self.vertices, vertices);
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
        if self.refit.is_none() {
            self.refit = Some((
                RefitPlan::new(bvh, indices)?,
                every_vertex_referenced(indices, nv),
            ));
        }
        let Some((plan, all_referenced)) = &mut self.refit else {
            unreachable!("made above")
        };
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
        crate::buffers::copy_par(&mut self.vertices, vertices);
        self.bvh.refit(plan, &self.vertices, max_abs)?;
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

    /// Wrap a BVH2 from any builder (validated against `tris`, then collapsed to the default
    /// width). A later [`Accel::rebuild`] builds with the default options.
    pub fn from_bvh2(bvh2: &Bvh, tris: Vec<[Vec3; 3]>) -> Result<Accel, TraceError> {
        let width = default_width();
        let bvh = WideBvh::from_bvh2_width(bvh2, &tris, width)?;
        let n = tris.len() as u32;
        let test = NodeTest::for_width(width);
        Ok(Accel {
            kernel: kernel_of(&bvh, test),
            bvh,
            vertices: tris.iter().flatten().copied().collect(),
            indices: (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(),
            opts: BuildOptions::default(),
            test,
            ctx: BuildContext::new(),
            phases: FastTimes::default(),
            refit: None,
            spare: None,
            token: fresh_token(),
        })
    }

    /// The closest hit of `ray` in `[tnear, tfar]` (`None` for a miss or an invalid ray:
    /// non-finite or zero direction, NaN interval).
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        if !ray.is_valid() {
            return None;
        }
        self.intersect_valid(ray)
    }

    /// [`Accel::intersect`] of a ray the caller has checked ([`Ray::is_valid`]).
    #[inline]
    pub(crate) fn intersect_valid(&self, ray: &Ray) -> Option<Hit> {
        closest_valid::<false>(&self.bvh, ray, self.kernel, &mut TraceStats::default())
    }

    /// True when `ray` hits anything in `[tnear, tfar]`.
    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        ray.is_valid() && self.occluded_valid(ray)
    }

    /// [`Accel::occluded`] of a ray the caller has checked ([`Ray::is_valid`]).
    #[inline]
    pub(crate) fn occluded_valid(&self, ray: &Ray) -> bool {
        occluded_valid::<false, false>(&self.bvh, ray, self.kernel, &mut TraceStats::default())
    }

    /// [`Accel::occluded_valid`] of a ray entering an instance of this mesh (which often
    /// misses the root's children): the same answer, the triangle constants made only after
    /// the root test.
    #[inline]
    pub(crate) fn occluded_entered(&self, ray: &Ray) -> bool {
        occluded_valid::<false, true>(&self.bvh, ray, self.kernel, &mut TraceStats::default())
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
        self.bvh
            .root_child_boxes()
            .iter()
            .filter(|b| b.is_valid())
            .fold(Aabb::EMPTY, |a, b| a.union(b))
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

/// Build `bvh` (its buffers reused) over the mesh with `opts` at `width`, in the scratch of
/// `ctx`, recording the fast path's phases in `phases`; `token` is the structure's (the fast
/// path's sort takes its previous order as a hint when `ctx` still holds it).
#[allow(clippy::too_many_arguments)]
fn build_over(
    token: u64,
    bvh: &mut WideBvh,
    phases: &mut FastTimes,
    opts: &BuildOptions,
    width: usize,
    ctx: &mut BuildContext,
    vertices: &[Vec3],
    indices: &[[u32; 3]],
) -> Result<(), TraceError> {
    let (_, layout, _) = opts.resolve();
    // The radix tree (Karras = Apetrei) without restructuring goes straight to the wide
    // tree; the other builders make a BVH2 that is then collapsed.
    *phases = FastTimes::default();
    if fast_path(opts) {
        // Straight into the structure's buffers; the other width's tree is emptied.
        let r = if width == WIDTH8 {
            bvh.nodes.clear();
            build_fast::<WIDTH8>(
                vertices,
                indices,
                &layout,
                fast_leaf_max(opts),
                token,
                &mut ctx.fast8,
                &mut bvh.nodes8,
                &mut bvh.packets,
                phases,
            )
        } else {
            bvh.nodes8.clear();
            build_fast::<WIDTH>(
                vertices,
                indices,
                &layout,
                fast_leaf_max(opts),
                token,
                &mut ctx.fast4,
                &mut bvh.nodes,
                &mut bvh.packets,
                phases,
            )
        };
        return r.map(|t| bvh.set_fast(indices.len(), t, width));
    }
    // The mesh is checked and boxed in one pass; the collapse reads the corners through the
    // indices (no triangle list is made).
    if indices.is_empty() {
        return Err(TraceError::NoTriangles);
    }
    let bounds = mesh_boxes(vertices, indices, &mut ctx.aabbs)?;
    let p = bounds.prim;
    let max_abs = p.min.abs().max_element().max(p.max.abs().max_element());
    let bvh2 = bvh2_of_boxes(opts, ctx, Some(width), Some(bounds))?;
    let mesh = Indexed { vertices, indices };
    // Restructuring rewrote treelets in place, scattering each subtree's nodes over the
    // arrays: its last pass planned the collapse node by node while they were in the cache
    // (stanford-dragon balanced, one thread: 274 → 258 ms for the whole build, against a
    // depth-first copy of the tree planned while it was made, which the collapse then read).
    let prep = if bvh2.planned {
        Prep::Planned
    } else {
        Prep::Fill
    };
    let r = bvh.rebuild_from_own_mesh(&bvh2.bvh, prep, mesh, max_abs, width, &mut ctx.collapse);
    ctx.recycle(bvh2);
    r
}

/// A BVH2 of `bvh2_of_boxes`: the tree, whether the binned builder made it (in its buffers),
/// and whether the restructuring filled the collapse plan of the traced width on the way
/// ([`Prep::Planned`]).
struct Bvh2 {
    bvh: Bvh,
    binned: bool,
    planned: bool,
}

impl Bvh2 {
    /// A tree of the LBVH pipeline (in its buffers), planned or not.
    fn of_lbvh(bvh: Bvh, planned: bool) -> Bvh2 {
        Bvh2 {
            bvh,
            binned: false,
            planned,
        }
    }
}

impl BuildContext {
    /// Take back a finished BVH2's arrays: to the binned builder's buffers when it made them,
    /// else to the pipeline's.
    fn recycle(&mut self, b: Bvh2) {
        if b.binned {
            self.binned.recycle(b.bvh);
        } else {
            self.arena.recycle_bvh(b.bvh);
        }
    }
}

/// The BVH2 a preset and its overrides ask for, built by the LBVH / binned-SAH pipeline.
pub fn build_bvh2(tris: &[[Vec3; 3]], opts: &BuildOptions) -> Result<Bvh, TraceError> {
    build_bvh2_in(tris, opts, &mut BuildContext::new()).map(|b| b.bvh)
}

/// [`build_bvh2`] in the buffers of `ctx`.
fn build_bvh2_in(
    tris: &[[Vec3; 3]],
    opts: &BuildOptions,
    ctx: &mut BuildContext,
) -> Result<Bvh2, TraceError> {
    if tris.is_empty() {
        return Err(TraceError::NoTriangles);
    }
    // Checked on the corners: a box's min/max can drop a NaN.
    if let Some(i) = tris.iter().position(|t| !t.iter().all(|v| v.is_finite())) {
        return Err(TraceError::NonFinite(i));
    }
    let aabbs = &mut ctx.aabbs;
    aabbs.clear();
    aabbs.par_extend(
        tris.par_iter()
            .map(|t| Aabb::from_triangle(t[0], t[1], t[2])),
    );
    bvh2_of_boxes(opts, ctx, None, None)
}

/// The BVH2 `opts` ask for over the (checked, non-empty) triangle boxes in `ctx.aabbs`, in the
/// buffers of `ctx` (the boxes stay there). With `plan_width`, a restructured tree that keeps
/// one triangle per leaf comes with the collapse plan of that width filled during the
/// restructuring's last pass. `bounds`, when given, are the boxes' scene bounds (saving the
/// LBVH a pass over them).
fn bvh2_of_boxes(
    opts: &BuildOptions,
    ctx: &mut BuildContext,
    plan_width: Option<usize>,
    bounds: Option<emc_core::SceneBounds>,
) -> Result<Bvh2, TraceError> {
    let aabbs = &mut ctx.aabbs;
    let (builder, layout, restructure) = opts.resolve();
    let max_leaf = opts.leaf_size.unwrap_or(DEFAULT_LEAF_SIZE);
    if max_leaf == 0 {
        return Err(TraceError::ZeroLeafSize);
    }
    let collapse = CollapseParams {
        max_leaf,
        ..CollapseParams::default()
    };
    if builder == Builder::BinnedSah && !restructure && max_leaf > 1 {
        // The pipeline's library path, in the context's buffers: the top-down build cut at
        // its SAH leaves.
        let rule = LeafRule {
            max_leaf,
            ct: collapse.ct,
            ci: collapse.ci,
        };
        return build_binned_sah_leaves_in(aabbs, DEFAULT_BINS, rule, &mut ctx.binned)
            .map(|b| Bvh2 {
                bvh: b.bvh,
                binned: true,
                planned: false,
            })
            .map_err(|e| TraceError::Build(crate::build::BuildError::Binned(e)));
    }
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
    let out = build_aabbs_inline_in(std::mem::take(aabbs), bounds, &bopts, &mut ctx.arena)
        .map_err(TraceError::Build)?;
    *aabbs = out.aabbs;
    if !restructure {
        return Ok(Bvh2::of_lbvh(out.bvh, false));
    }
    let mut bvh = out.bvh;
    let cfg = AtrConfig::default();
    // Without a leaf size of its own, the restructured tree keeps one triangle per leaf: the
    // wide collapse's cover DP chooses the leaves itself (up to eight triangles). An SAH leaf
    // collapse before it was measured to change nothing the DP chooses (same wide SAH and work
    // per ray on san-francisco, bathroom and dragon) and costs more than it saves here (1.39 vs
    // 1.24 G instructions for a san-francisco build); after binned SAH it saves more than it
    // costs, so that path keeps it. The tree the collapse reads is then the restructured one,
    // and the last pass plans it as it finishes the nodes.
    let in_place = plan_width.filter(|_| opts.leaf_size.is_none() && cfg.iterations > 0);
    let watch = in_place.map(|width| ctx.collapse.plan_in_place(bvh.nodes.len(), width));
    restructure_atr(&mut bvh, aabbs, &cfg, &mut ctx.atr, &watch)
        .map_err(TraceError::Restructure)?;
    let planned = watch.is_some();
    if opts.leaf_size.is_none() {
        return Ok(Bvh2::of_lbvh(bvh, planned));
    }
    Ok(Bvh2::of_lbvh(collapse_bvh(&bvh, &collapse), false))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A jittered grid of `n` small triangles (deterministic).
    fn mesh(n: usize, seed: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        let mut x = seed | 1;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x % 10_000) as f32 / 1000.0
        };
        let mut vertices = Vec::with_capacity(3 * n);
        for _ in 0..n {
            let o = Vec3::new(next(), next(), next());
            vertices.extend([o, o + Vec3::new(0.1, next() / 50.0, 0.0), o + Vec3::Z * 0.1]);
        }
        let indices = (0..n as u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect();
        (vertices, indices)
    }

    #[test]
    fn the_balanced_restructuring_plans_the_collapse_in_place() {
        // One context for all (a smaller mesh after a larger: rows the restructuring missed
        // would still hold the earlier build's), both widths, one and two threads: the plan
        // the restructuring made equals the one planned over its output afterwards.
        let mut ctx = BuildContext::new();
        for (n, seed) in [(5000, 3), (1200, 4), (1, 5), (2, 6)] {
            let (vertices, indices) = mesh(n, seed);
            for width in [WIDTH8, WIDTH] {
                for threads in [1, 2] {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .expect("a pool");
                    pool.install(|| {
                        let opts = BuildOptions::preset(Preset::Balanced);
                        let bounds =
                            mesh_boxes(&vertices, &indices, &mut ctx.aabbs).expect("a valid mesh");
                        let b = bvh2_of_boxes(&opts, &mut ctx, Some(width), Some(bounds))
                            .expect("a tree");
                        assert!(b.planned, "{n} triangles: not planned in place");
                        assert!(
                            ctx.collapse.plan_is_fill_of(&b.bvh, width),
                            "{n} triangles, {width}-wide, {threads} threads: another plan"
                        );
                        ctx.recycle(b);
                    });
                }
            }
        }
    }
}
