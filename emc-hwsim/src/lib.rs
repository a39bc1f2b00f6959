//! # emc-hwsim: a cycle-level model of a fixed-function EMC unit
//!
//! Checks the claim that Extended Morton Codes are easy to build in hardware, with numbers: a
//! unit configured per layout and frame ([`Unit`]), a cycle-stepped simulator ([`stepped`]), an
//! exact fast timing mode ([`fast`]), a memory port ([`memory`]), per-frame setup costs
//! ([`setup`]) and an area/energy/latency model ([`cost`]).
//!
//! The unit computes every code through its own stage operations (fp64 adders and multipliers,
//! float→fixed shifters, threshold comparators or the sqrt/divide path, a Beneš network or
//! fixed wiring); its firmware model ([`firmware`]) derives the bit schedule, position scales
//! and size thresholds itself. emc-core parses layout names and is the test oracle.
//!
//! ```
//! use emc_core::{Aabb, Frame, LayoutSpec};
//! use emc_hwsim::{MemoryConfig, Mode, Unit, UnitOptions};
//! use emc_core::glam::Vec3;
//!
//! let boxes: Vec<Aabb> = (0..100)
//!     .map(|i| {
//!         let p = Vec3::new(i as f32, (i * 7 % 13) as f32, (i * 3 % 5) as f32);
//!         Aabb::new(p, p + Vec3::splat(0.5 + (i % 4) as f32))
//!     })
//!     .collect();
//! let frame = Frame::new(&boxes).unwrap();
//! let unit = Unit::for_spec(&LayoutSpec::Emc64Var, &frame, &UnitOptions::default()).unwrap();
//! let fast = unit.run(&boxes, &MemoryConfig::default(), Mode::Fast).unwrap();
//! let stepped = unit.run(&boxes, &MemoryConfig::default(), Mode::Stepped).unwrap();
//! assert_eq!(fast.stats, stepped.stats);
//! assert_eq!(fast.codes, stepped.codes);
//! ```

// Every module says `#![forbid(unsafe_code)]` except `ffi`, the C ABI, which is the one
// documented exception (raw pointers from C); the crate root only denies, so that `ffi` can
// allow it for itself.
#![deny(unsafe_code)]
#![deny(missing_docs)]

pub mod blocks;
pub mod cost;
pub mod datapath;
mod error;
pub mod fast;
pub mod ffi;
pub mod firmware;
pub mod fixed;
pub mod memory;
pub mod routing;
pub mod rtl;
pub mod setup;
pub mod stats;
pub mod stepped;
pub mod synth;
pub mod vectors;

pub use blocks::Block;
pub use datapath::{Network, RoutingChoice, SizeSearch, SizeUnit, Stage, Unit, UnitOptions};
pub use error::HwError;
pub use memory::{Flow, MemoryConfig, Port};
pub use stats::{Occupancy, Stats};

use emc_core::Aabb;

/// How timing is derived.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Mode {
    /// Per-primitive and per-transaction recurrences (idle cycles cost nothing).
    #[default]
    Fast,
    /// Every cycle simulated, data carried through the stage registers.
    Stepped,
}

/// The outcome of a run over a batch of boxes.
#[derive(Clone, Debug)]
pub struct Run {
    /// The codes the unit wrote, in input order.
    pub codes: Vec<u64>,
    /// Timing statistics.
    pub stats: Stats,
    /// Per-cycle occupancy histograms (cycle-stepped mode only).
    pub occupancy: Option<Occupancy>,
}

impl Unit {
    /// The data-flow constants of a run of `n` primitives on this unit.
    pub fn flow(&self, n: u64) -> Flow {
        let o = self.options();
        let cb = self.code_bytes() as u64;
        Flow {
            n,
            lanes: o.lanes as u64,
            ii: self.lane_ii() as u64,
            depth: self.depth() as u64,
            in_cap: o.input_capacity as u64,
            out_cap: self.output_capacity() as u64,
            read_burst: o.read_burst as u64,
            write_burst: self.write_burst() as u64,
            code_bytes: cb,
        }
    }

    /// Timing of `n` primitives without computing codes (fast mode).
    pub fn timing(&self, n: u64, mem: &MemoryConfig) -> Result<Stats, HwError> {
        fast::timing(&self.flow(n), &Port::new(mem)?)
    }

    /// Encode `boxes` and time the run.
    pub fn run(&self, boxes: &[Aabb], mem: &MemoryConfig, mode: Mode) -> Result<Run, HwError> {
        let port = Port::new(mem)?;
        let flow = self.flow(boxes.len() as u64);
        match mode {
            Mode::Fast => {
                // Timing and the codes are independent (timing never depends on data): the
                // host computes them on separate threads, the codes in chunks.
                let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
                let chunk = boxes.len().div_ceil(threads).max(datapath::BLOCK * 256);
                let mut codes = vec![0u64; boxes.len()];
                let stats = std::thread::scope(|s| {
                    let timing = s.spawn(|| fast::timing(&flow, &port));
                    for (o, b) in codes.chunks_mut(chunk).zip(boxes.chunks(chunk)) {
                        s.spawn(move || self.codes_into(b, o));
                    }
                    timing
                        .join()
                        .unwrap_or_else(|e| std::panic::resume_unwind(e))
                })?;
                Ok(Run {
                    codes,
                    stats,
                    occupancy: None,
                })
            }
            Mode::Stepped => {
                let r = stepped::run(self, boxes, &flow, &port)?;
                Ok(Run {
                    codes: r.codes,
                    stats: r.stats,
                    occupancy: Some(r.occupancy),
                })
            }
        }
    }
}
