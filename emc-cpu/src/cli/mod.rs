//! The verbs of the `emc` binary, one module each; `main.rs` only parses and dispatches.

pub mod build;
pub mod layout;
pub mod render;
pub mod hwsim;
