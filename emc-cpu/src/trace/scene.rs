//! Scenes the way renderers hold them: several geometries (triangle meshes, custom primitives
//! given as boxes plus an intersection callback, and instances of other scenes under affine
//! transforms), each with an id and a 32-bit mask, under a top-level tree that the fast LBVH
//! rebuilds over the geometries' boxes at every [`Scene::commit`].
//!
//! ```
//! use std::sync::Arc;
//! use emc_cpu::trace::{BuildOptions, Preset, Ray, Scene};
//! use glam::{Affine3A, Vec3};
//!
//! // One unit square (two triangles) as a scene of its own...
//! let v = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y];
//! let mut square = Scene::new();
//! square.add_mesh(&v, &[[0, 1, 2], [0, 2, 3]], &BuildOptions::preset(Preset::Quality))?;
//! square.commit()?;
//! let square = Arc::new(square);
//!
//! // ...placed twice in a top-level scene: once as it is, once 10 units along x.
//! let mut top = Scene::new();
//! let a = top.add_instance(square.clone(), Affine3A::IDENTITY)?;
//! let b = top.add_instance(square, Affine3A::from_translation(Vec3::new(10.0, 0.0, 0.0)))?;
//! top.set_mask(b, 0b10)?;
//! top.commit()?;
//!
//! let down = Vec3::new(0.0, 0.0, -1.0);
//! let hit = top.intersect(&Ray::new(Vec3::new(10.5, 0.25, 1.0), down)).unwrap();
//! assert_eq!((hit.instance, hit.geom, hit.prim, hit.t), (b, 0, 0, 1.0));
//! // A ray whose mask shares no bit with instance b's passes through it.
//! assert!(top.intersect(&Ray::new(Vec3::new(10.5, 0.25, 1.0), down).with_mask(0b01)).is_none());
//! assert_eq!(top.intersect(&Ray::new(Vec3::new(0.5, 0.25, 1.0), down)).unwrap().instance, a);
//! # Ok::<(), emc_cpu::trace::TraceError>(())
//! ```
//!
//! Queries see every edit at once: between an edit and the next commit they are answered
//! without the top-level tree (each geometry's box tested in turn), so an uncommitted scene is
//! slower, never wrong. Ties at equal distance go to the lowest (instance, geometry,
//! primitive).
#![forbid(unsafe_code)]

use std::sync::Arc;

use emc_core::Aabb;
use glam::{Affine3A, Vec3, Vec3A};
use rayon::prelude::*;

use crate::trace::api::{Accel, BuildOptions, Preset};
use crate::trace::intersect::{slab_test, Hit, PreRay, Ray};
use crate::trace::traverse::{closest_items, occluded_items};
use crate::trace::TraceError;

/// A geometry's id in its scene: the order it was added in, from 0.
pub type GeomId = u32;

/// What a custom primitive's intersection callback reports: the distance along the ray (in
/// units of its direction) and two values handed back in [`Hit::u`] / [`Hit::v`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CustomHit {
    /// Distance along the ray; counted only inside the ray's `[tnear, tfar]`.
    pub t: f32,
    /// Returned as [`Hit::u`].
    pub u: f32,
    /// Returned as [`Hit::v`].
    pub v: f32,
}

/// The intersection callback of custom primitives: `f(ray, prim)` is the closest hit of
/// primitive `prim` with `ray` in `[ray.tnear, ray.tfar]` (in the geometry's own space, so
/// under an instance the ray is the transformed one), or `None`. Called only for primitives
/// whose box the ray enters (the box as the tree holds it, padded by 2^-16 of the largest
/// coordinate); an answer outside the interval is ignored.
pub type Intersector = dyn Fn(&Ray, u32) -> Option<CustomHit> + Send + Sync;

/// What a geometry is.
#[derive(Clone)]
enum Kind {
    /// A triangle mesh with its own tree.
    Mesh(Box<Accel>),
    /// Custom primitives: their boxes' tree and the callback.
    Custom(Box<Custom>),
    /// Another scene under a transform.
    Instance(Instance),
}

/// Custom primitives: a tree over their boxes (see [`box_tree`]; always `Some`) and the
/// callback.
#[derive(Clone)]
struct Custom {
    tree: Option<Accel>,
    count: usize,
    intersect: Arc<Intersector>,
}

/// An instance: the scene it shows, object-to-world and world-to-object.
#[derive(Clone)]
struct Instance {
    scene: Arc<Scene>,
    to_world: Affine3A,
    to_object: Affine3A,
}

/// One geometry of a scene.
#[derive(Clone)]
struct Geometry {
    kind: Kind,
    mask: u32,
    /// Box in the scene's space (conservative).
    bounds: Aabb,
}

/// Several geometries with ids and masks under one top-level tree; see the module docs.
/// `Send + Sync`: any number of threads may trace one scene at once.
#[derive(Clone, Default)]
pub struct Scene {
    geoms: Vec<Geometry>,
    /// The top-level tree over the geometries' boxes (`None` before the first commit and for
    /// an empty scene).
    top: Option<Accel>,
    /// Box corners of the last commit, two per geometry (the top tree's vertices).
    corners: Vec<Vec3>,
    /// No edit since the last commit.
    committed: bool,
    /// Union of the geometries' boxes at the last commit.
    bounds: Aabb,
    /// Boxes whose union holds the scene, tighter than `bounds` under a rotation: the child
    /// boxes of its traced tree's root at the last commit (what an instance transforms), as
    /// centres and half extents.
    hull: Vec<(Vec3A, Vec3A)>,
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene")
            .field("geometries", &self.geoms.len())
            .field("committed", &self.committed)
            .field("bounds", &self.bounds)
            .finish()
    }
}

/// Write the vertices of the tree over `boxes` (see [`box_tree`]) into `corners`: two per
/// box, its min and max.
fn box_corners(boxes: impl IndexedParallelIterator<Item = Aabb>, corners: &mut Vec<Vec3>) {
    corners.clear();
    corners.resize(2 * boxes.len(), Vec3::ZERO);
    corners
        .par_chunks_mut(2)
        .zip(boxes)
        .for_each(|(c, b)| (c[0], c[1]) = (b.min, b.max));
}

/// A tree over boxes: an [`Accel`] (fast preset, one box per leaf) over one degenerate
/// triangle per box, with corners `(min, max, min)` (vertices `2i`, `2i + 1` of
/// [`box_corners`]), whose own box is exactly the box; so triangle `i` stands for box `i`, and
/// each leaf names one box.
/// `tree`, when it holds as many boxes, is rebuilt in place (its buffers reused).
fn box_tree(corners: &[Vec3], tree: &mut Option<Accel>) -> Result<(), TraceError> {
    let n = corners.len() / 2;
    if let Some(a) = tree.as_mut().filter(|a| a.triangle_count() == n) {
        return a.rebuild(corners);
    }
    if n > crate::trace::wide::MAX_TRIANGLES {
        return Err(TraceError::TooManyTriangles(n));
    }
    let indices: Vec<[u32; 3]> = (0..n as u32).map(|i| [2 * i, 2 * i + 1, 2 * i]).collect();
    *tree = Some(Accel::build(
        corners,
        &indices,
        // One box per leaf: the node test is the item's box test (see `closest_items`).
        &BuildOptions::preset(Preset::Fast).with_leaf_size(1),
    )?);
    Ok(())
}

/// True when `b` is a usable box: finite corners, `min <= max`.
fn box_ok(b: &Aabb) -> bool {
    b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all()
}

/// `b` grown by 2^-20 of its largest coordinate: room for the rounding of a transform.
fn widen(b: Aabb) -> Aabb {
    let m = b.min.abs().max(b.max.abs()).max_element();
    let pad = m * (1.0 / 1_048_576.0) + f32::MIN_POSITIVE;
    Aabb::new(b.min - pad, b.max + pad)
}

/// The box of `b` under `m` (all eight corners transformed), widened for rounding.
fn transform_box(m: &Affine3A, b: &Aabb) -> Aabb {
    let mut out = Aabb::EMPTY;
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { b.min.x } else { b.max.x },
            if i & 2 == 0 { b.min.y } else { b.max.y },
            if i & 4 == 0 { b.min.z } else { b.max.z },
        );
        out.grow(m.transform_point3(c));
    }
    widen(out)
}

/// Keep `h` when it beats `best`: closer, or as close with a lower (instance, geometry,
/// primitive).
#[inline]
fn offer(best: &mut Option<Hit>, h: Hit) {
    let wins = match best {
        None => true,
        Some(b) => {
            h.t < b.t || (h.t == b.t && (h.instance, h.geom, h.prim) < (b.instance, b.geom, b.prim))
        }
    };
    if wins {
        *best = Some(h);
    }
}

impl Scene {
    /// An empty scene (committed: it answers every ray with a miss).
    pub fn new() -> Scene {
        Scene {
            committed: true,
            bounds: Aabb::EMPTY,
            ..Scene::default()
        }
    }

    /// Number of geometries.
    pub fn geometry_count(&self) -> usize {
        self.geoms.len()
    }

    /// True when no edit was made since the last [`Scene::commit`] (queries then use the
    /// top-level tree).
    pub fn is_committed(&self) -> bool {
        self.committed
    }

    /// The union of the geometries' boxes (computed anew when the scene is not committed).
    pub fn bounds(&self) -> Aabb {
        if self.committed {
            return self.bounds;
        }
        self.geoms
            .iter()
            .fold(Aabb::EMPTY, |a, g| a.union(&g.bounds))
    }

    /// Bytes this scene holds: its geometry records, the top-level tree (nodes, packets and
    /// its copy of the box corners) and the trees of its own meshes and custom primitives.
    /// Instanced scenes are shared (`Arc`) and counted where they are owned, not here.
    pub fn memory_bytes(&self) -> usize {
        let accel = |a: &Accel| {
            a.wide_bvh().memory_bytes()
                + a.triangle_count() * core::mem::size_of::<[u32; 3]>()
                + a.vertex_count() * core::mem::size_of::<Vec3>()
        };
        let own: usize = self
            .geoms
            .iter()
            .map(|g| match &g.kind {
                Kind::Mesh(a) => accel(a),
                Kind::Custom(c) => c.tree.as_ref().map_or(0, accel),
                Kind::Instance(_) => 0,
            })
            .sum();
        self.geoms.capacity() * core::mem::size_of::<Geometry>()
            + self.corners.capacity() * core::mem::size_of::<Vec3>()
            + self.top.as_ref().map_or(0, accel)
            + own
    }

    fn push(&mut self, kind: Kind, bounds: Aabb) -> Result<GeomId, TraceError> {
        if self.geoms.len() >= crate::trace::wide::MAX_TRIANGLES {
            return Err(TraceError::TooManyTriangles(self.geoms.len() + 1));
        }
        self.geoms.push(Geometry {
            kind,
            mask: Ray::ALL,
            bounds,
        });
        self.committed = false;
        Ok((self.geoms.len() - 1) as GeomId)
    }

    fn geometry(&self, id: GeomId) -> Result<&Geometry, TraceError> {
        self.geoms
            .get(id as usize)
            .ok_or(TraceError::NoGeometry(id))
    }

    fn geometry_mut(&mut self, id: GeomId) -> Result<&mut Geometry, TraceError> {
        self.geoms
            .get_mut(id as usize)
            .ok_or(TraceError::NoGeometry(id))
    }

    /// Add a triangle mesh, built with `opts` (the errors of [`Accel::build`]); returns its id.
    pub fn add_mesh(
        &mut self,
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        opts: &BuildOptions,
    ) -> Result<GeomId, TraceError> {
        let accel = Accel::build(vertices, indices, opts)?;
        let b = accel.bounds();
        self.push(Kind::Mesh(Box::new(accel)), b)
    }

    /// Add `boxes.len()` custom primitives: primitive `i` lies inside `boxes[i]` and
    /// `intersect` finds its hits (see [`Intersector`]). Fails on no boxes or on a box with a
    /// non-finite corner or `min > max`.
    pub fn add_custom(
        &mut self,
        boxes: &[Aabb],
        intersect: impl Fn(&Ray, u32) -> Option<CustomHit> + Send + Sync + 'static,
    ) -> Result<GeomId, TraceError> {
        let mut tree = None;
        let b = custom_tree(boxes, &mut tree)?;
        let c = Custom {
            tree,
            count: boxes.len(),
            intersect: Arc::new(intersect),
        };
        self.push(Kind::Custom(Box::new(c)), b)
    }

    /// Add an instance of `scene` (whose geometries are meshes and custom primitives: one
    /// level of instancing) placed by the object-to-world transform `to_world`. Fails on a
    /// transform that is not invertible (or not finite), on an empty scene and on a scene
    /// holding instances.
    pub fn add_instance(
        &mut self,
        scene: Arc<Scene>,
        to_world: Affine3A,
    ) -> Result<GeomId, TraceError> {
        let (inst, b) = instance(scene, to_world)?;
        self.push(Kind::Instance(inst), b)
    }

    /// Set geometry `id`'s mask: a ray sees it only when `ray.mask & mask != 0` (for an
    /// instance, its geometries' own masks apply too). Every mask starts as [`Ray::ALL`].
    pub fn set_mask(&mut self, id: GeomId, mask: u32) -> Result<(), TraceError> {
        self.geometry_mut(id)?.mask = mask;
        Ok(())
    }

    /// Geometry `id`'s mask.
    pub fn mask(&self, id: GeomId) -> Result<u32, TraceError> {
        Ok(self.geometry(id)?.mask)
    }

    /// Move instance `id` to `to_world` (errors as [`Scene::add_instance`]).
    pub fn set_transform(&mut self, id: GeomId, to_world: Affine3A) -> Result<(), TraceError> {
        let g = self.geometry_mut(id)?;
        let Kind::Instance(inst) = &g.kind else {
            return Err(TraceError::WrongGeometry {
                id,
                expected: "an instance",
            });
        };
        let (inst, b) = instance(inst.scene.clone(), to_world)?;
        g.kind = Kind::Instance(inst);
        g.bounds = b;
        self.committed = false;
        Ok(())
    }

    /// Instance `id`'s object-to-world transform.
    pub fn transform(&self, id: GeomId) -> Result<Affine3A, TraceError> {
        match &self.geometry(id)?.kind {
            Kind::Instance(i) => Ok(i.to_world),
            _ => Err(TraceError::WrongGeometry {
                id,
                expected: "an instance",
            }),
        }
    }

    /// The mesh of geometry `id`.
    pub fn mesh(&self, id: GeomId) -> Result<&Accel, TraceError> {
        match &self.geometry(id)?.kind {
            Kind::Mesh(a) => Ok(a),
            _ => Err(TraceError::WrongGeometry {
                id,
                expected: "a mesh",
            }),
        }
    }

    /// Apply `f` to mesh `id` and take its new box.
    fn edit_mesh(
        &mut self,
        id: GeomId,
        f: impl FnOnce(&mut Accel) -> Result<(), TraceError>,
    ) -> Result<(), TraceError> {
        let g = self.geometry_mut(id)?;
        let Kind::Mesh(a) = &mut g.kind else {
            return Err(TraceError::WrongGeometry {
                id,
                expected: "a mesh",
            });
        };
        f(a)?;
        g.bounds = a.bounds();
        self.committed = false;
        Ok(())
    }

    /// Refit mesh `id` to new vertex positions ([`Accel::refit`]: same topology, boxes moved).
    pub fn refit_mesh(&mut self, id: GeomId, vertices: &[Vec3]) -> Result<(), TraceError> {
        self.edit_mesh(id, |a| a.refit(vertices))
    }

    /// Rebuild mesh `id` over new vertex positions ([`Accel::rebuild`]).
    pub fn rebuild_mesh(&mut self, id: GeomId, vertices: &[Vec3]) -> Result<(), TraceError> {
        self.edit_mesh(id, |a| a.rebuild(vertices))
    }

    /// Give custom geometry `id` new boxes (same count; its tree is rebuilt, reusing its
    /// buffers).
    pub fn set_custom_boxes(&mut self, id: GeomId, boxes: &[Aabb]) -> Result<(), TraceError> {
        let g = self.geometry_mut(id)?;
        let Kind::Custom(c) = &mut g.kind else {
            return Err(TraceError::WrongGeometry {
                id,
                expected: "custom primitives",
            });
        };
        if boxes.len() != c.count {
            return Err(TraceError::BoxCount {
                given: boxes.len(),
                expected: c.count,
            });
        }
        g.bounds = custom_tree(boxes, &mut c.tree)?;
        self.committed = false;
        Ok(())
    }

    /// Rebuild the top-level tree over the geometries' current boxes (the fast LBVH, reusing
    /// the previous commit's buffers when the geometry count is unchanged). Queries before a
    /// commit are right but slow (see the module docs).
    pub fn commit(&mut self) -> Result<(), TraceError> {
        self.bounds = self
            .geoms
            .par_iter()
            .map(|g| g.bounds)
            .reduce(|| Aabb::EMPTY, |a, b| a.union(&b));
        if self.geoms.is_empty() {
            self.top = None;
        } else {
            box_corners(self.geoms.par_iter().map(|g| g.bounds), &mut self.corners);
            box_tree(&self.corners, &mut self.top)?;
        }
        self.committed = true;
        self.hull = self
            .root_boxes()
            .iter()
            .map(|b| {
                // Halves first: no overflow near the largest floats.
                let (lo, hi) = (Vec3A::from(b.min) * 0.5, Vec3A::from(b.max) * 0.5);
                (lo + hi, hi - lo)
            })
            .collect();
        Ok(())
    }

    /// The child boxes of the root of the tree a ray through this (committed) scene walks
    /// first: its one mesh's or custom primitives' own tree, or the top-level tree; the
    /// scene's box when that tree is missing; none for an empty scene.
    fn root_boxes(&self) -> Vec<Aabb> {
        if self.geoms.is_empty() {
            return Vec::new();
        }
        let tree = match self.geoms.as_slice() {
            [Geometry {
                kind: Kind::Mesh(a),
                ..
            }] => Some(&**a),
            [Geometry {
                kind: Kind::Custom(c),
                ..
            }] => c.tree.as_ref(),
            _ => self.top.as_ref(),
        };
        let Some(w) = tree.map(Accel::wide_bvh) else {
            return vec![self.bounds];
        };
        let boxes = w.root_child_boxes();
        if boxes.is_empty() {
            vec![self.bounds]
        } else {
            boxes
        }
    }

    /// The world box of this scene under `m`: the union of its hull boxes' transformed
    /// boxes (see `hull`), or of its box before a commit.
    ///
    /// Each box goes through its centre and half extent (Arvo 1990: `M·c + t`, `|M|·e`). Every
    /// value computed is at most twice `bound = |M|·(|c| + e) + |t|` in size, and all the
    /// roundings on the way (the centre and half extent made at the commit, the products and
    /// sums here, the final `centre ± slack`) move a bound of the box by under 20 units of
    /// 2^-24 of `bound`: the box is grown by 2^-18 of `bound` (64 such units), so it holds the
    /// exactly transformed box whatever the roundings; `f32::MIN_POSITIVE` more covers what
    /// the roundings of values near zero lose to underflow (a few subnormal units).
    fn world_box(&self, m: &Affine3A) -> Aabb {
        if !self.committed || self.hull.is_empty() {
            return transform_box(m, &self.bounds());
        }
        let a = m.matrix3;
        let abs = [a.x_axis.abs(), a.y_axis.abs(), a.z_axis.abs()];
        let t = m.translation;
        let (mut lo, mut hi) = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY));
        for &(c, e) in &self.hull {
            let centre = a.x_axis * c.x + a.y_axis * c.y + a.z_axis * c.z + t;
            let half = abs[0] * e.x + abs[1] * e.y + abs[2] * e.z;
            let reach = c.abs() + e;
            let bound = abs[0] * reach.x + abs[1] * reach.y + abs[2] * reach.z + t.abs();
            let slack = half + bound * (1.0 / 262_144.0) + Vec3A::splat(f32::MIN_POSITIVE);
            lo = lo.min(centre - slack);
            hi = hi.max(centre + slack);
        }
        Aabb::new(lo.into(), hi.into())
    }

    /// The closest hit of `ray` (`None` for a miss or an invalid ray).
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        if !ray.is_valid() {
            return None;
        }
        let mut best = None;
        self.closest_into(ray, Hit::NO_INSTANCE, &mut best);
        best
    }

    /// True when `ray` hits anything in `[tnear, tfar]`.
    pub fn occluded(&self, ray: &Ray) -> bool {
        ray.is_valid() && self.any(ray)
    }

    /// Closest hits of many rays, in parallel (in the caller's rayon pool), in order.
    pub fn intersect_batch(&self, rays: &[Ray]) -> Vec<Option<Hit>> {
        rays.par_iter().map(|r| self.intersect(r)).collect()
    }

    /// Occlusion of many rays, in parallel, in order.
    pub fn occluded_batch(&self, rays: &[Ray]) -> Vec<bool> {
        rays.par_iter().map(|r| self.occluded(r)).collect()
    }

    /// Fold the hits of this scene's geometries into `best` (the ray is valid; `instance`
    /// names the instance the ray came through).
    fn closest_into(&self, ray: &Ray, instance: u32, best: &mut Option<Hit>) {
        if self.geoms.len() == 1 {
            // One geometry (an instanced mesh, typically): no tree above it.
            return self.geom_closest(0, ray, ray.tfar, instance, best);
        }
        match (&self.top, self.committed) {
            (Some(top), true) => {
                closest_items(top.wide_bvh(), ray, top.node_test(), |id, t| {
                    self.geom_closest(id, ray, t, instance, best);
                    best.map_or(t, |h| h.t)
                });
            }
            _ => {
                let r = PreRay::new(ray);
                for id in 0..self.geoms.len() as u32 {
                    let t = best.map_or(ray.tfar, |h| h.t);
                    let b = &self.geoms[id as usize].bounds;
                    if slab_test(&r, b.min.to_array(), b.max.to_array(), t).is_some() {
                        self.geom_closest(id, ray, t, instance, best);
                    }
                }
            }
        }
    }

    /// Fold the hits of geometry `id` up to distance `t` into `best`.
    #[inline]
    fn geom_closest(&self, id: GeomId, ray: &Ray, t: f32, instance: u32, best: &mut Option<Hit>) {
        let g = &self.geoms[id as usize];
        if g.mask & ray.mask == 0 {
            return;
        }
        match &g.kind {
            Kind::Mesh(a) => {
                // Valid: `ray` is (checked at the top, or on entering an instance) and
                // `tnear ≤ t ≤ ray.tfar`.
                if let Some(mut h) = a.intersect_valid(&Ray { tfar: t, ..*ray }) {
                    h.geom = id;
                    h.instance = instance;
                    offer(best, h);
                }
            }
            Kind::Custom(c) => {
                let Some(tree) = &c.tree else { return };
                let r = Ray { tfar: t, ..*ray };
                closest_items(tree.wide_bvh(), &r, tree.node_test(), |prim, t| {
                    let q = Ray { tfar: t, ..r };
                    if let Some(ch) = (c.intersect)(&q, prim) {
                        if ch.t >= q.tnear && ch.t <= t {
                            let h = Hit {
                                t: ch.t,
                                prim,
                                u: ch.u,
                                v: ch.v,
                                geom: id,
                                instance,
                            };
                            offer(best, h);
                        }
                    }
                    best.map_or(t, |h| h.t)
                });
            }
            Kind::Instance(inst) => {
                let o = Ray {
                    tfar: t,
                    ..inst.object_ray(ray)
                };
                if !o.is_valid() {
                    return;
                }
                // An instanced mesh (the usual instance) is traced straight away.
                match inst.scene.lone_mesh() {
                    Some((a, mask)) => {
                        if mask & o.mask != 0 {
                            if let Some(mut h) = a.intersect_valid(&o) {
                                h.geom = 0;
                                h.instance = id;
                                offer(best, h);
                            }
                        }
                    }
                    None => inst.scene.closest_into(&o, id, best),
                }
            }
        }
    }

    /// True when some geometry is hit (the ray is valid).
    fn any(&self, ray: &Ray) -> bool {
        if self.geoms.len() == 1 {
            return self.geom_any(0, ray);
        }
        match (&self.top, self.committed) {
            (Some(top), true) => occluded_items(top.wide_bvh(), ray, top.node_test(), |id| {
                self.geom_any(id, ray)
            }),
            _ => {
                let r = PreRay::new(ray);
                (0..self.geoms.len() as u32).any(|id| {
                    let b = &self.geoms[id as usize].bounds;
                    slab_test(&r, b.min.to_array(), b.max.to_array(), ray.tfar).is_some()
                        && self.geom_any(id, ray)
                })
            }
        }
    }

    /// True when geometry `id` is hit.
    #[inline]
    fn geom_any(&self, id: GeomId, ray: &Ray) -> bool {
        let g = &self.geoms[id as usize];
        if g.mask & ray.mask == 0 {
            return false;
        }
        match &g.kind {
            // Valid: checked at the top, or on entering an instance.
            Kind::Mesh(a) => a.occluded_valid(ray),
            Kind::Custom(c) => {
                let Some(tree) = &c.tree else { return false };
                occluded_items(tree.wide_bvh(), ray, tree.node_test(), |prim| {
                    (c.intersect)(ray, prim).is_some_and(|h| h.t >= ray.tnear && h.t <= ray.tfar)
                })
            }
            Kind::Instance(inst) => {
                let o = inst.object_ray(ray);
                if !o.is_valid() {
                    return false;
                }
                match inst.scene.lone_mesh() {
                    Some((a, mask)) => mask & o.mask != 0 && a.occluded_entered(&o),
                    None => inst.scene.any(&o),
                }
            }
        }
    }

    /// The mesh of a scene of one geometry, a mesh, and its mask.
    #[inline]
    fn lone_mesh(&self) -> Option<(&Accel, u32)> {
        match self.geoms.as_slice() {
            [g] => match &g.kind {
                Kind::Mesh(a) => Some((a, g.mask)),
                _ => None,
            },
            _ => None,
        }
    }
}

impl Instance {
    /// `r` in the instanced scene's space (same parameter `t`: the direction is not
    /// renormalised).
    #[inline]
    fn object_ray(&self, r: &Ray) -> Ray {
        Ray {
            origin: self.to_object.transform_point3(r.origin),
            dir: self.to_object.transform_vector3(r.dir),
            ..*r
        }
    }
}

/// An instance of `scene` under `to_world` and its world box, checked.
fn instance(scene: Arc<Scene>, to_world: Affine3A) -> Result<(Instance, Aabb), TraceError> {
    if scene.geoms.is_empty() {
        return Err(TraceError::EmptyScene);
    }
    if scene
        .geoms
        .iter()
        .any(|g| matches!(g.kind, Kind::Instance(_)))
    {
        return Err(TraceError::NestedInstance);
    }
    let to_object = inverse_f64(&to_world).ok_or(TraceError::NotInvertible)?;
    // The root's child boxes transformed: under a rotation much tighter than the scene's
    // box transformed, so fewer rays enter an instance they then miss.
    let b = scene.world_box(&to_world);
    if !box_ok(&b) {
        return Err(TraceError::NotInvertible);
    }
    Ok((
        Instance {
            scene,
            to_world,
            to_object,
        },
        b,
    ))
}

/// The inverse of `m`, computed in f64 and rounded once (an f32 inverse carries the
/// matrix's condition number times the rounding, which then moves every transformed ray);
/// `None` when `m` is not finite or singular, or its inverse is not finite in f32.
fn inverse_f64(m: &Affine3A) -> Option<Affine3A> {
    if !m.is_finite() {
        return None;
    }
    let c = [m.matrix3.x_axis, m.matrix3.y_axis, m.matrix3.z_axis];
    // a[row][col] of the linear part (its columns are the axes).
    let a: [[f64; 3]; 3] = core::array::from_fn(|r| core::array::from_fn(|k| c[k][r] as f64));
    let t = [m.translation.x, m.translation.y, m.translation.z].map(f64::from);
    let minor =
        |r0: usize, r1: usize, c0: usize, c1: usize| a[r0][c0] * a[r1][c1] - a[r0][c1] * a[r1][c0];
    // The adjugate: adj[r][k] = (-1)^(r+k) · minor of a without row k and column r.
    let adj = [
        [minor(1, 2, 1, 2), -minor(0, 2, 1, 2), minor(0, 1, 1, 2)],
        [-minor(1, 2, 0, 2), minor(0, 2, 0, 2), -minor(0, 1, 0, 2)],
        [minor(1, 2, 0, 1), -minor(0, 2, 0, 1), minor(0, 1, 0, 1)],
    ];
    let det = a[0][0] * adj[0][0] + a[0][1] * adj[1][0] + a[0][2] * adj[2][0];
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv: [[f64; 3]; 3] = core::array::from_fn(|r| core::array::from_fn(|k| adj[r][k] / det));
    let ti: [f64; 3] =
        core::array::from_fn(|r| -(inv[r][0] * t[0] + inv[r][1] * t[1] + inv[r][2] * t[2]));
    let col = |k: usize| Vec3::new(inv[0][k] as f32, inv[1][k] as f32, inv[2][k] as f32);
    let out = Affine3A::from_cols(
        col(0).into(),
        col(1).into(),
        col(2).into(),
        Vec3::new(ti[0] as f32, ti[1] as f32, ti[2] as f32).into(),
    );
    out.is_finite().then_some(out)
}

/// Build (or rebuild) `tree` over custom primitives' boxes, checked; returns their union.
fn custom_tree(boxes: &[Aabb], tree: &mut Option<Accel>) -> Result<Aabb, TraceError> {
    if boxes.is_empty() {
        return Err(TraceError::NoTriangles);
    }
    if let Some(i) = boxes.iter().position(|b| !box_ok(b)) {
        return Err(TraceError::BadBox(i));
    }
    let mut corners = Vec::new();
    box_corners(boxes.par_iter().copied(), &mut corners);
    box_tree(&corners, tree)?;
    Ok(boxes.iter().fold(Aabb::EMPTY, |a, b| a.union(b)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::builtin::Pcg32;
    use crate::trace::workload::instance_grid;

    #[test]
    #[allow(clippy::needless_range_loop)] // axes `r` of several vectors at once
    fn a_world_box_holds_the_exactly_transformed_hull_boxes() {
        // The hull boxes' corners transformed in f64 (exact enough: 53-bit products of 24-bit
        // values) must lie in the f32 world box, for boxes and transforms whose terms cancel
        // (large coordinates brought back near the origin), mirrors, stretches and scales (the
        // rotations and scales of `instance_grid`, stretched further on every other case).
        let mut rng = Pcg32::new(99, 3);
        let turns = instance_grid(4000, Vec3::splat(-1.0), Vec3::ONE, 99);
        for (k, turn) in turns.iter().enumerate() {
            let big = [1.0, 1.0e3, 1.0e6, 3.0e7][k % 4];
            let boxes: Vec<Aabb> = (0..1 + k % 8)
                .map(|_| {
                    let c = Vec3::new(
                        rng.range(-big, big),
                        rng.range(-big, big),
                        rng.range(-big, big),
                    );
                    let e = Vec3::new(
                        rng.range(0.0, big * 0.01),
                        rng.range(0.0, big * 0.01),
                        rng.range(0.0, big * 0.01),
                    );
                    Aabb::new(c - e, c + e)
                })
                .collect();
            let stretch = if k % 2 == 0 {
                Vec3::new(rng.range(0.2, 5.0), rng.range(0.2, 5.0), 1.0)
            } else {
                Vec3::ONE
            };
            let m0 = Affine3A::from_scale(stretch)
                * Affine3A {
                    matrix3: turn.matrix3,
                    translation: Vec3A::ZERO,
                };
            // A translation that brings the first box's centre back near the origin.
            let centre = (boxes[0].min + boxes[0].max) * 0.5;
            let t = -m0.transform_point3(centre) + Vec3::splat(rng.range(-1.0, 1.0));
            let m = Affine3A::from_translation(t) * m0;
            let mut scene = Scene::new();
            scene.committed = true;
            scene.hull = boxes
                .iter()
                .map(|b| {
                    let (lo, hi) = (Vec3A::from(b.min) * 0.5, Vec3A::from(b.max) * 0.5);
                    (lo + hi, hi - lo)
                })
                .collect();
            let w = scene.world_box(&m);
            let a = m.matrix3;
            let col = [a.x_axis, a.y_axis, a.z_axis];
            for b in &boxes {
                for i in 0..8 {
                    let p = [
                        if i & 1 == 0 { b.min.x } else { b.max.x },
                        if i & 2 == 0 { b.min.y } else { b.max.y },
                        if i & 4 == 0 { b.min.z } else { b.max.z },
                    ];
                    for r in 0..3 {
                        let exact = (0..3).map(|j| col[j][r] as f64 * p[j] as f64).sum::<f64>()
                            + m.translation[r] as f64;
                        assert!(
                            w.min[r] as f64 <= exact && exact <= w.max[r] as f64,
                            "case {k}: corner {p:?} axis {r} at {exact} outside {w:?}"
                        );
                    }
                }
            }
        }
    }
}
