//! # emc-cpu: scenes, parallel encoding and the LBVH pipeline
//!
//! The CPU side of emc: scene loading and built-in scenes, parallel batch encoding on top of
//! emc-core, radix sorting, LBVH builders, SAH metrics and the verbs of the `emc` binary.

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
pub use trace::{Accel, BuildOptions, CustomHit, GeomId, Hit, Preset, Ray, Scene, TraceError};
