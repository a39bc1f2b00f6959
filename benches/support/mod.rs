//! Shared helpers of the emc benchmarks.
