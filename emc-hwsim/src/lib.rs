//! # emc-hwsim: a cycle-level model of a fixed-function EMC unit
//!
//! Placeholder crate root: the unit model is tracked by its own issue and lands there.

#![forbid(unsafe_code)]
