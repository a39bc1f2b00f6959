//! The `emc` command-line tool.
fn main() {}
