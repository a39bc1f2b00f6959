//! Per-frame setup of the unit: the scene-bounds pass over all AABBs through the memory port,
//! the layout schedule, the routing controls and the size thresholds, in cycles of the unit
//! (register writes over a 64-bit configuration bus, one per cycle) and in host work.
#![forbid(unsafe_code)]

use core::fmt;

use crate::datapath::{Network, SizeUnit, Unit};
use crate::error::HwError;
use crate::memory::{MemoryConfig, Port, AABB_BYTES};

/// Setup cost of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SetupCost {
    /// Cycles of the bounds pass (stream every AABB once; min/max units keep up at one AABB per
    /// lane per cycle), or 0 when the producer supplies the bounds.
    pub bounds_cycles: u64,
    /// Cycles of the halving schedule (one step per code bit for adaptive layouts).
    pub schedule_cycles: u64,
    /// Register writes for scales, origins, routing controls and thresholds (the words of
    /// [`crate::rtl::image`]).
    pub config_writes: u64,
    /// Host steps to route the network (looping algorithm: lanes × log2 lanes).
    pub host_routing_steps: u64,
    /// Host evaluations of the size formula to bisect the thresholds (≤ 64 per threshold).
    pub host_threshold_evals: u64,
}

impl SetupCost {
    /// Unit cycles of the whole setup (bounds pass, schedule, register writes).
    pub fn cycles(&self) -> u64 {
        self.bounds_cycles + self.schedule_cycles + self.config_writes
    }
}

/// The setup cost of `unit` for a frame of `n` primitives.
pub fn setup_cost(
    unit: &Unit,
    n: u64,
    mem: &MemoryConfig,
    bounds_supplied: bool,
) -> Result<SetupCost, HwError> {
    let port = Port::new(mem)?;
    let lanes = unit.options().lanes as u64;
    let bounds_cycles = if bounds_supplied || n == 0 {
        0
    } else {
        let bus = port.end_cycle(n * AABB_BYTES * port.ticks_per_byte);
        bus.max(n.div_ceil(lanes)) + port.latency
    };
    let r = unit.registers();
    let adaptive = unit.spec().is_adaptive();
    let schedule_cycles = if adaptive { r.len as u64 } else { 0 };
    // The register image the emitted RTL is programmed with, one bus write per word.
    let words = crate::rtl::image(unit).len() as u64;
    let mut host_routing_steps = 0;
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            host_routing_steps = b.lanes() as u64 * b.lanes().trailing_zeros() as u64;
        }
        Network::Crossbar(x) => {
            host_routing_steps = x.lanes() as u64;
        }
    }
    let mut host_threshold_evals = 0;
    if let SizeUnit::Thresholds { bits, .. } = &r.size {
        host_threshold_evals = 64 * ((1u64 << bits) - 1);
    }
    Ok(SetupCost {
        bounds_cycles,
        schedule_cycles,
        config_writes: words,
        host_routing_steps,
        host_threshold_evals,
    })
}

impl fmt::Display for SetupCost {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "  setup: {} cycles = bounds pass {} + schedule {} + {} register writes; host: {} routing steps, {} size-formula evaluations",
            self.cycles(),
            self.bounds_cycles,
            self.schedule_cycles,
            self.config_writes,
            self.host_routing_steps,
            self.host_threshold_evals
        )
    }
}
