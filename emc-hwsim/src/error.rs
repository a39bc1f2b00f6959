//! Errors of the hardware model: bad knobs (lanes, FIFO depths, bandwidth, clock) are refused
//! when the unit or its memory port is built, never discovered as a hang or a panic later.
#![forbid(unsafe_code)]

use thiserror::Error;

/// Everything that can go wrong when configuring or running the modelled unit.
#[derive(Clone, Debug, PartialEq, Error)]
#[non_exhaustive]
pub enum HwError {
    /// The unit needs at least one lane.
    #[error("the unit needs at least one lane (got {0})")]
    NoLanes(u32),
    /// A read burst of zero AABBs, or an input buffer smaller than one burst.
    #[error("input buffer of {cap} AABBs cannot hold a read burst of {burst} AABBs (need burst >= 1 and cap >= burst)")]
    InputBuffer {
        /// Input buffer capacity in AABBs.
        cap: u32,
        /// Read burst in AABBs.
        burst: u32,
    },
    /// A write burst of zero codes, or an output FIFO smaller than one burst.
    #[error("output FIFO of {cap} codes cannot hold a write burst of {burst} codes (need burst >= 1 and cap >= burst)")]
    OutputBuffer {
        /// Output FIFO capacity in codes.
        cap: u32,
        /// Write burst in codes.
        burst: u32,
    },
    /// Bandwidth not a positive finite number of GB/s (resolution 1 MB/s).
    #[error("memory bandwidth must be a finite number of GB/s >= 0.001, got {0}")]
    Bandwidth(f64),
    /// Clock not a positive finite number of GHz (resolution 1 MHz).
    #[error("clock must be a finite number of GHz >= 0.001, got {0}")]
    Clock(f64),
    /// Memory latency negative or not finite.
    #[error("memory latency must be a finite number of ns >= 0, got {0}")]
    Latency(f64),
    /// A fixed-wiring unit was asked to serve a layout it is not wired for.
    #[error("fixed wiring serves only regular fixed patterns (one group of distinct channels repeated), not {0}")]
    NotFixedLayout(String),
    /// The unit cannot be emitted as RTL (or its RTL run failed).
    #[error("RTL: {0}")]
    Rtl(String),
    /// The firmware's bit schedule is not a valid layout.
    #[error("layout: {0}")]
    Layout(emc_core::Error),
    /// The frame (scene bounds) could not be built from the input boxes.
    #[error("scene bounds: {0}")]
    Frame(emc_core::Error),
}
