//! The obvhs crate (0.4, crates.io) as the second in-process peer of `emc compare`: its
//! fastest CPU build to a traceable tree and its single-ray queries, through its public API.
//!
//! What it is: `BvhBuildParams::fastest_build()` — PLOC (Meister & Bittner 2018) with search
//! radius 1 over 64-bit Morton codes, no reinsertion, one triangle per leaf — giving a BVH2
//! (binary, 48-byte nodes) traced by `Bvh2::ray_traverse` (closest hit) and
//! `Bvh2::ray_traverse_miss` (any hit) with its Möller–Trumbore triangle test (not watertight,
//! so counts may differ from Embree's by a few rays). As obvhs' own examples suggest, the
//! triangles are reordered into the tree's leaf order after the build (inside the timed build).
#![forbid(unsafe_code)]

use std::time::{Duration, Instant};

use ::obvhs::bvh2::builder::build_bvh2_from_tris;
use ::obvhs::bvh2::leaf_collapser::collapse;
use ::obvhs::bvh2::node::Bvh2Node;
use ::obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use ::obvhs::bvh2::Bvh2;
use ::obvhs::ploc::PlocBuilder;
use ::obvhs::ray::{Ray as ORay, RayHit};
use ::obvhs::triangle::Triangle;
use ::obvhs::BvhBuildParams;
use glam::{Vec3, Vec3A};

use crate::peers::{trace_closest, trace_occluded, Timing, Tracer};
use crate::trace::{Hit, Ray};

/// The build parameters measured: obvhs' fastest preset.
pub const PARAMS: BvhBuildParams = BvhBuildParams::fastest_build();

/// A short description for reports.
pub const DESCRIPTION: &str = "obvhs 0.4 fastest_build: PLOC r=1, 64-bit Morton, BVH2, 1 tri/leaf";

/// An obvhs BVH2 over a mesh, with the triangles in leaf order.
#[derive(Clone)]
pub struct Bvh {
    bvh: Bvh2,
    /// Triangles in the order the leaves address them.
    ordered: Vec<Triangle>,
    /// Scratch triangles in input order (the builder's input).
    input: Vec<Triangle>,
    indices: Vec<[u32; 3]>,
    vertex_count: usize,
    /// The PLOC builder's buffers, kept for [`Bvh::rebuild`].
    ploc: PlocBuilder,
}

impl std::fmt::Debug for Bvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("obvhs::Bvh")
            .field("nodes", &self.bvh.nodes.len())
            .field("triangles", &self.ordered.len())
            .finish()
    }
}

/// Why obvhs was not asked to build.
#[derive(Debug, thiserror::Error)]
pub enum ObvhsError {
    /// An index names a vertex that does not exist.
    #[error("triangle {tri} names vertex {index} of {vertices}")]
    BadIndex {
        /// The triangle.
        tri: usize,
        /// Its bad index.
        index: u32,
        /// Vertex count.
        vertices: usize,
    },
    /// A triangle has a NaN or infinite vertex (obvhs' builder asserts on them).
    #[error("triangle {0} has a non-finite vertex")]
    NonFinite(usize),
    /// No triangle, or more than 32-bit ids allow.
    #[error("obvhs needs 1 to 2^31 triangles, got {0}")]
    Count(usize),
    /// A rebuild with another vertex count.
    #[error("rebuild got {given} vertices, the build had {expected}")]
    VertexCount {
        /// Given.
        given: usize,
        /// Expected.
        expected: usize,
    },
}

/// Gather obvhs triangles from an indexed mesh into `out` (cleared first), checking indices and
/// finiteness.
fn gather(
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    out: &mut Vec<Triangle>,
) -> Result<(), ObvhsError> {
    out.clear();
    out.reserve(indices.len());
    for (tri, t) in indices.iter().enumerate() {
        let mut v = [Vec3A::ZERO; 3];
        for (k, &index) in t.iter().enumerate() {
            let p = *vertices.get(index as usize).ok_or(ObvhsError::BadIndex {
                tri,
                index,
                vertices: vertices.len(),
            })?;
            if !p.is_finite() {
                return Err(ObvhsError::NonFinite(tri));
            }
            v[k] = Vec3A::from(p);
        }
        out.push(Triangle {
            v0: v[0],
            v1: v[1],
            v2: v[2],
        });
    }
    Ok(())
}

/// Copy `input` into `out` in the tree's leaf order.
fn reorder(bvh: &Bvh2, input: &[Triangle], out: &mut Vec<Triangle>) {
    out.clear();
    out.extend(bvh.primitive_indices.iter().map(|&i| input[i as usize]));
}

impl Bvh {
    /// Build from an indexed mesh with [`PARAMS`] (fresh builder and tree, as a new user would);
    /// returns the structure and the wall time from the indexed mesh to a traceable tree.
    pub fn build(vertices: &[Vec3], indices: &[[u32; 3]]) -> Result<(Bvh, Duration), ObvhsError> {
        if indices.is_empty() || indices.len() > i32::MAX as usize {
            return Err(ObvhsError::Count(indices.len()));
        }
        let t0 = Instant::now();
        let mut input = Vec::new();
        gather(vertices, indices, &mut input)?;
        let mut core_time = Duration::ZERO;
        let bvh = build_bvh2_from_tris(&input, PARAMS, &mut core_time);
        let mut ordered = Vec::new();
        reorder(&bvh, &input, &mut ordered);
        let elapsed = t0.elapsed();
        Ok((
            Bvh {
                bvh,
                ordered,
                input,
                indices: indices.to_vec(),
                vertex_count: vertices.len(),
                ploc: PlocBuilder::new(),
            },
            elapsed,
        ))
    }

    /// Build again over new positions of the same mesh, reusing the tree's, the triangles' and
    /// the PLOC builder's allocations (`PlocBuilder::build_with_bvh`, then the same steps as
    /// `build_bvh2_from_tris`); returns the wall time.
    pub fn rebuild(&mut self, vertices: &[Vec3]) -> Result<Duration, ObvhsError> {
        if vertices.len() != self.vertex_count {
            return Err(ObvhsError::VertexCount {
                given: vertices.len(),
                expected: self.vertex_count,
            });
        }
        let t0 = Instant::now();
        gather(vertices, &self.indices, &mut self.input)?;
        let n = self.input.len() as u32;
        self.ploc.build_with_bvh(
            &mut self.bvh,
            PARAMS.ploc_search_distance,
            &self.input,
            (0..n).collect(),
            PARAMS.sort_precision,
            PARAMS.search_depth_threshold,
        );
        let mut reinsertion = ReinsertionOptimizer::default();
        reinsertion.run(&mut self.bvh, PARAMS.reinsertion_batch_ratio, None);
        collapse(
            &mut self.bvh,
            PARAMS.max_prims_per_leaf.clamp(1, 255),
            PARAMS.collapse_traversal_cost,
        );
        reinsertion.run(
            &mut self.bvh,
            PARAMS.reinsertion_batch_ratio
                * PARAMS.post_collapse_reinsertion_batch_ratio_multiplier,
            None,
        );
        reorder(&self.bvh, &self.input, &mut self.ordered);
        Ok(t0.elapsed())
    }

    /// Bytes of the traced structure: nodes, the leaf-to-input index map and the reordered
    /// triangles.
    pub fn memory_bytes(&self) -> usize {
        self.bvh.nodes.len() * size_of::<Bvh2Node>()
            + self.bvh.primitive_indices.len() * size_of::<u32>()
            + self.ordered.len() * size_of::<Triangle>()
    }

    /// Nodes of the BVH2.
    pub fn node_count(&self) -> usize {
        self.bvh.nodes.len()
    }

    #[inline]
    fn ray(r: &Ray) -> ORay {
        ORay::new(Vec3A::from(r.origin), Vec3A::from(r.dir), r.tnear, r.tfar)
    }

    /// Closest hit of one ray (`u`, `v` are not computed: 0).
    #[inline]
    pub fn intersect(&self, r: &Ray) -> Option<Hit> {
        let mut hit = RayHit::none();
        let tris = &self.ordered;
        self.bvh
            .ray_traverse(Self::ray(r), &mut hit, |ray, id| tris[id].intersect(ray))
            .then(|| {
                let prim = self.bvh.primitive_indices[hit.primitive_id as usize];
                Hit::triangle(hit.t, prim, 0.0, 0.0)
            })
    }

    /// Whether one ray hits anything in its interval.
    #[inline]
    pub fn occluded(&self, r: &Ray) -> bool {
        let tris = &self.ordered;
        !self
            .bvh
            .ray_traverse_miss(Self::ray(r), |ray, id| tris[id].intersect(ray))
    }
}

impl Tracer for Bvh {
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || (), |_, r| self.intersect(r))
    }
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(rays, threads, || (), |_, r| Bvh::occluded(self, r))
    }
}
