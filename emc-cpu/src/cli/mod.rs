//! The verbs of the `emc` binary, one module each; `main.rs` only parses and dispatches.
#![forbid(unsafe_code)]

pub mod build;
pub mod compare;
pub mod frames;
pub mod hwsim;
pub mod instances;
pub mod layout;
pub mod paper;
pub mod render;
