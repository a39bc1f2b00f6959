//! Bounding volume hierarchies: the node layout and (in their own files) the builders,
//! validation and cost metrics.

pub mod node;

pub use node::{Bvh, Node};
