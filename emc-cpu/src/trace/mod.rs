//! The ray tracer: a BVH2 from any builder becomes 4- and 8-wide SIMD BVHs ([`wide`]),
//! traced with watertight geometry ([`intersect`], [`traverse`]) by the benchmark workloads
//! ([`workload`]) and the library API ([`api`]). `emc render` drives it from the command line.

pub mod api;
pub mod cover;
#[cfg(feature = "image")]
pub mod image;
pub mod intersect;
pub mod refit;
pub mod scene;
pub mod traverse;
pub mod wide;
pub mod wide_lbvh;
pub mod workload;

pub use api::{Accel, BuildContext, BuildOptions, Preset};
pub use intersect::{Hit, Ray};
pub use scene::{CustomHit, GeomId, Intersector, Scene};
pub use traverse::{NodeTest, TraceStats};
pub use wide::WideBvh;

use crate::bvh::validate::ValidateError;

/// Why a BVH cannot be traced or an acceleration structure cannot be built.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TraceError {
    /// No triangle to build over.
    #[error("no triangles to trace")]
    NoTriangles,
    /// More triangles than 31-bit ids allow.
    #[error("{0} triangles exceed the tracer's limit of 2^31 - 1")]
    TooManyTriangles(usize),
    /// A triangle has a NaN or infinite vertex.
    #[error("triangle {0} has a non-finite vertex")]
    NonFinite(usize),
    /// A triangle index names a vertex that does not exist.
    #[error("triangle {tri} names vertex {index}, but there are only {vertices} vertices")]
    BadIndex {
        /// The triangle.
        tri: usize,
        /// The vertex index it holds.
        index: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// The BVH2 failed validation against the triangles.
    #[error("invalid BVH: {0}")]
    InvalidBvh(ValidateError),
    /// The collapsed tree is deeper than the traversal stack supports.
    #[error("wide BVH depth {depth} exceeds the supported maximum {max}")]
    TooDeep {
        /// Depth reached.
        depth: usize,
        /// [`wide::MAX_DEPTH`].
        max: usize,
    },
    /// The tree width of [`BuildOptions`] is neither 4 nor 8.
    #[error("the tree width must be 4 or 8, not {0}")]
    Width(usize),
    /// [`BuildOptions`] asks for leaves of zero triangles.
    #[error("the maximum leaf size must be at least 1")]
    ZeroLeafSize,
    /// A tree's packet names a triangle the mesh does not have (a refit plan of a tree over
    /// another mesh).
    #[error("the tree names triangle {tri}, but the mesh has {triangles} triangles")]
    MissingTriangle {
        /// The triangle id.
        tri: u32,
        /// Number of triangles of the mesh.
        triangles: usize,
    },
    /// A refit plan made for another tree.
    #[error("the refit plan was made for a tree of another shape")]
    RefitPlanMismatch,
    /// The fast builder was asked for a largest leaf outside the sizes it makes.
    #[error("the fast builder's largest leaf must be 1 to {max} triangles, not {given}")]
    FastLeafSize {
        /// The size asked for.
        given: u32,
        /// [`wide_lbvh::LEAF_MAX`].
        max: u32,
    },
    /// The codes could not be made (scene frame or encoder).
    #[error("encoding the triangles failed: {0}")]
    Encode(#[source] emc_core::Error),
    /// The radix sort refused its input.
    #[error("sorting the codes failed: {0}")]
    Sort(#[source] crate::sort::SortError),
    /// The BVH2 pipeline (LBVH or binned SAH) refused its input.
    #[error("BVH build failed: {0}")]
    Build(#[source] crate::build::BuildError),
    /// The automatic layout choice failed.
    #[error("choosing the layout failed: {0}")]
    Layout(#[source] crate::auto::AutoError),
    /// The treelet restructuring refused its input.
    #[error("treelet restructuring failed: {0}")]
    Restructure(#[source] crate::bvh::atrbvh::AtrError),
    /// A [`Scene`] has no geometry of this id.
    #[error("the scene has no geometry {0}")]
    NoGeometry(u32),
    /// A [`Scene`] edit named a geometry of another kind.
    #[error("geometry {id} is not {expected}")]
    WrongGeometry {
        /// The geometry named.
        id: u32,
        /// The kind the edit needs.
        expected: &'static str,
    },
    /// An instance transform is singular or not finite (or maps the scene's box out of range).
    #[error("the instance transform is not invertible (or not finite)")]
    NotInvertible,
    /// An instanced scene holds instances itself (one level of instancing is supported).
    #[error("an instanced scene must not hold instances (one level of instancing)")]
    NestedInstance,
    /// An instanced scene has no geometry.
    #[error("an instanced scene must hold at least one geometry")]
    EmptyScene,
    /// A custom primitive's box has a non-finite corner or `min > max`.
    #[error("custom primitive {0} has a non-finite or inverted box")]
    BadBox(usize),
    /// [`Scene::set_custom_boxes`] got a different number of boxes than the geometry has.
    #[error("got {given} boxes, but the custom geometry has {expected} primitives")]
    BoxCount {
        /// Boxes given.
        given: usize,
        /// Primitives of the geometry.
        expected: usize,
    },
    /// [`Accel::rebuild`] got a different number of vertices than the build.
    #[error("rebuild got {given} vertices, but the mesh was built with {expected}")]
    VertexCount {
        /// Vertices given.
        given: usize,
        /// Vertices of the build.
        expected: usize,
    },
}
