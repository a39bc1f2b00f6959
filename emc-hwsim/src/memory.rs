//! The memory port: one shared bus with a bandwidth in bytes per cycle (an exact rational from
//! GB/s and the clock), a read latency, and one transaction issued per cycle at most.
//! Time inside the port is kept in ticks of `1 / ticks_per_cycle` cycle so that fractional
//! bytes-per-cycle rates stay exact.
#![forbid(unsafe_code)]

use crate::error::HwError;

/// Memory system and clock, as the user states them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MemoryConfig {
    /// Peak DRAM bandwidth in GB/s (10^9 bytes per second).
    pub bandwidth_gbps: f64,
    /// Unit clock in GHz.
    pub clock_ghz: f64,
    /// Read latency in ns (request to data).
    pub latency_ns: f64,
}

impl Default for MemoryConfig {
    fn default() -> Self {
        MemoryConfig {
            bandwidth_gbps: 25.6,
            clock_ghz: 1.0,
            latency_ns: 100.0,
        }
    }
}

/// The port's exact timing constants.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Port {
    /// Ticks per cycle.
    pub ticks_per_cycle: u64,
    /// Ticks per byte on the bus.
    pub ticks_per_byte: u64,
    /// Read latency in cycles (added after the data transfer ends).
    pub latency: u64,
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

impl Port {
    /// Exact port constants: bandwidth rounded to 1 MB/s, clock to 1 MHz, latency to a cycle.
    pub fn new(m: &MemoryConfig) -> Result<Port, HwError> {
        if !m.bandwidth_gbps.is_finite() || m.bandwidth_gbps < 0.001 || m.bandwidth_gbps > 1e6 {
            return Err(HwError::Bandwidth(m.bandwidth_gbps));
        }
        if !m.clock_ghz.is_finite() || m.clock_ghz < 0.001 || m.clock_ghz > 1e3 {
            return Err(HwError::Clock(m.clock_ghz));
        }
        if !m.latency_ns.is_finite() || m.latency_ns < 0.0 || m.latency_ns > 1e9 {
            return Err(HwError::Latency(m.latency_ns));
        }
        // bytes per cycle = MB/s / MHz = p / q; one cycle = p ticks, one byte = q ticks.
        let p = (m.bandwidth_gbps * 1000.0).round() as u64;
        let q = (m.clock_ghz * 1000.0).round() as u64;
        let g = gcd(p, q);
        Ok(Port {
            ticks_per_cycle: p / g,
            ticks_per_byte: q / g,
            latency: (m.latency_ns * m.clock_ghz).round() as u64,
        })
    }

    /// Peak bytes per cycle.
    pub fn bytes_per_cycle(&self) -> f64 {
        self.ticks_per_cycle as f64 / self.ticks_per_byte as f64
    }

    /// First cycle at which a transaction may issue when the bus frees at tick `free`.
    #[inline(always)]
    pub fn ready_cycle(&self, free: u64) -> u64 {
        free / self.ticks_per_cycle
    }

    /// Issue a transfer of `bytes` at cycle `t` on a bus that frees at tick `free`: returns
    /// the tick at which the transfer ends.
    #[inline(always)]
    pub fn transfer(&self, free: u64, t: u64, bytes: u64) -> u64 {
        free.max(t * self.ticks_per_cycle) + bytes * self.ticks_per_byte
    }

    /// Cycle at which read data that finished transferring at tick `end` is usable.
    #[inline(always)]
    pub fn arrival(&self, end: u64) -> u64 {
        end.div_ceil(self.ticks_per_cycle) + self.latency
    }

    /// The cycle count of a run whose last transfer ends at tick `end`.
    #[inline(always)]
    pub fn end_cycle(&self, end: u64) -> u64 {
        end.div_ceil(self.ticks_per_cycle)
    }
}

/// A point on the bus timeline as whole cycles plus a fraction in ticks (`frac < p`): the
/// fast mode's division-free form of tick arithmetic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BusTime {
    /// Whole cycles.
    pub cycle: u64,
    /// Remaining ticks (less than the ticks per cycle).
    pub frac: u64,
}

impl Port {
    /// The duration of a transfer of `bytes`, as whole cycles and ticks.
    pub fn duration(&self, bytes: u64) -> BusTime {
        let t = bytes * self.ticks_per_byte;
        BusTime {
            cycle: t / self.ticks_per_cycle,
            frac: t % self.ticks_per_cycle,
        }
    }

    /// [`Port::transfer`] on [`BusTime`]: issue at cycle `t` on a bus free at `free`.
    #[inline(always)]
    pub fn transfer_at(&self, free: BusTime, t: u64, d: BusTime) -> BusTime {
        let start = if free.cycle >= t {
            free
        } else {
            BusTime { cycle: t, frac: 0 }
        };
        let mut frac = start.frac + d.frac;
        let mut cycle = start.cycle + d.cycle;
        if frac >= self.ticks_per_cycle {
            frac -= self.ticks_per_cycle;
            cycle += 1;
        }
        BusTime { cycle, frac }
    }

    /// The cycle count at a bus time (rounded up).
    #[inline(always)]
    pub fn ceil(&self, x: BusTime) -> u64 {
        x.cycle + (x.frac > 0) as u64
    }
}

/// The data-flow constants of a run (what timing depends on: never the data values).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Flow {
    /// Primitives to encode.
    pub n: u64,
    /// Lanes.
    pub lanes: u64,
    /// Lane initiation interval.
    pub ii: u64,
    /// Pipeline depth.
    pub depth: u64,
    /// Input buffer capacity (AABBs).
    pub in_cap: u64,
    /// Output FIFO capacity (codes).
    pub out_cap: u64,
    /// AABBs per read burst.
    pub read_burst: u64,
    /// Codes per write burst.
    pub write_burst: u64,
    /// Bytes per code.
    pub code_bytes: u64,
}

/// Bytes per AABB record.
pub const AABB_BYTES: u64 = 24;

impl Flow {
    /// Check the buffer sizes against the bursts (a smaller buffer could never issue).
    pub fn validate(&self) -> Result<(), HwError> {
        if self.lanes == 0 {
            return Err(HwError::NoLanes(0));
        }
        if self.read_burst == 0 || self.in_cap < self.read_burst {
            return Err(HwError::InputBuffer {
                cap: self.in_cap as u32,
                burst: self.read_burst as u32,
            });
        }
        if self.write_burst == 0 || self.out_cap < self.write_burst {
            return Err(HwError::OutputBuffer {
                cap: self.out_cap as u32,
                burst: self.write_burst as u32,
            });
        }
        Ok(())
    }
}
