//! # emc-cpu: scenes, parallel encoding, LBVH builders and a ray tracer
//!
//! The CPU side of emc: scene loading and built-in scenes, parallel batch encoding on top of
//! emc-core, radix sorting, LBVH / binned-SAH / treelet builders, SAH metrics, the wide-BVH
//! tracer and the verbs of the `emc` binary (feature `cli`).
//!
//! What a renderer uses: [`Accel`] for one triangle mesh (build with a [`Preset`], `rebuild`,
//! `refit`, `intersect`, `occluded`, batches in the caller's rayon pool) and [`Scene`] for
//! several geometries with ids and masks: meshes, custom primitives (boxes plus a callback) and
//! instances of other scenes under affine transforms ([`trace::scene`] shows one).
//!
//! ```
//! use emc_cpu::{Accel, BuildOptions, Preset, Ray};
//! use glam::Vec3;
//!
//! let v = [Vec3::ZERO, Vec3::X, Vec3::Y];
//! let accel = Accel::build(&v, &[[0, 1, 2]], &BuildOptions::preset(Preset::Fast))?;
//! let hit = accel.intersect(&Ray::new(Vec3::new(0.2, 0.2, 1.0), -Vec3::Z)).unwrap();
//! assert_eq!((hit.t, hit.prim), (1.0, 0));
//! # Ok::<(), emc_cpu::TraceError>(())
//! ```
//!
//! The examples (`cargo run --release -p emc-cpu --no-default-features --example NAME`):
//! `trace_mesh` (a mesh with each preset), `animate` (refit and rebuild per frame),
//! `instances` (10,000 instances with masks, moved and committed again) and `spheres`
//! (100,000 spheres as a custom primitive).
#![deny(missing_docs)]

pub mod aabbs;
pub mod auto;
pub mod buffers;
pub mod build;
pub mod bvh;
#[cfg(feature = "cli")]
#[doc(hidden)]
pub mod cli;
pub mod cputime;
pub mod encode;
#[cfg(feature = "fuzzing")]
#[doc(hidden)]
pub mod fuzzing;
pub mod hugepage;
#[cfg(feature = "cli")]
#[doc(hidden)]
pub mod paper;
#[cfg(feature = "cli")]
#[doc(hidden)]
pub mod peers;
pub mod scene;
pub mod sort;
pub mod trace;

pub use auto::LayoutChoice;
pub use build::Builder;
pub use emc_core::LayoutSpec;
pub use scene::Mesh;
pub use trace::{
    Accel, BuildContext, BuildOptions, CustomHit, GeomId, Hit, Preset, Ray, Scene, TraceError,
};
