//! Bounding volume hierarchies: the node layout and (in their own files) the builders,
//! validation and cost metrics.

pub mod apetrei;
pub mod atrbvh;
pub mod binned_sah;
pub mod collapse;
pub mod karras;
pub mod node;
pub mod refit;
pub mod sah;
pub mod sweep;
pub mod validate;

pub use node::{Bvh, Node};
pub use sah::{sah_collapsed, sah_cost, sah_headline, SahConstants};
pub use validate::{BvhStats, ValidateError};
