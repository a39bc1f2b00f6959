//! # emc-cpu: scenes, parallel encoding and the LBVH pipeline
//!
//! The CPU side of emc: scene loading and built-in scenes, parallel batch encoding on top of
//! emc-core, and (in later modules) sorting, LBVH builders and tracing.
