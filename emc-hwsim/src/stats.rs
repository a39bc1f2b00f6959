//! Run statistics of the modelled unit: cycles, throughput, entry stalls by cause, FIFO
//! occupancy and memory utilisation. Both simulation modes fill [`Stats`] identically; the
//! cycle-stepped mode adds per-cycle occupancy histograms ([`Occupancy`]).
#![forbid(unsafe_code)]

use core::fmt;

/// Statistics of one run (identical between the fast and the cycle-stepped modes).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Codes produced.
    pub codes: u64,
    /// Cycles until the last code is written to memory.
    pub cycles: u64,
    /// Lanes.
    pub lanes: u64,
    /// Pipeline depth (cycles).
    pub depth: u64,
    /// Cycle the first AABB entered the datapath.
    pub first_accept: u64,
    /// Cycle the last AABB entered the datapath.
    pub last_accept: u64,
    /// Entry-stall cycles waiting for input data (summed over primitives: how far each
    /// primitive entered after the lanes could have taken it, when its data was the reason).
    pub stall_input: u64,
    /// Entry-stall cycles waiting for output credit (output FIFO full: write back-pressure).
    pub stall_output: u64,
    /// Sum over cycles of the input buffer occupancy (AABBs) at the end of each cycle.
    pub in_fifo_sum: u64,
    /// Sum over cycles of the output FIFO occupancy (codes) at the end of each cycle.
    pub out_fifo_sum: u64,
    /// Read transactions.
    pub reads: u64,
    /// Write transactions.
    pub writes: u64,
    /// Bytes read.
    pub bytes_read: u64,
    /// Bytes written.
    pub bytes_written: u64,
    /// Bus busy time in ticks.
    pub bus_ticks: u64,
    /// Ticks per cycle of the port.
    pub ticks_per_cycle: u64,
}

impl Stats {
    /// Codes per cycle sustained over the whole run.
    pub fn codes_per_cycle(&self) -> f64 {
        if self.cycles == 0 {
            0.0
        } else {
            self.codes as f64 / self.cycles as f64
        }
    }

    /// Bus utilisation (busy time over run time).
    pub fn memory_utilisation(&self) -> f64 {
        if self.cycles == 0 {
            0.0
        } else {
            self.bus_ticks as f64 / (self.cycles * self.ticks_per_cycle) as f64
        }
    }

    /// Mean input buffer occupancy (AABBs).
    pub fn in_fifo_mean(&self) -> f64 {
        if self.cycles == 0 {
            0.0
        } else {
            self.in_fifo_sum as f64 / self.cycles as f64
        }
    }

    /// Mean output FIFO occupancy (codes).
    pub fn out_fifo_mean(&self) -> f64 {
        if self.cycles == 0 {
            0.0
        } else {
            self.out_fifo_sum as f64 / self.cycles as f64
        }
    }

    /// Lane-cycles left unused over the run (`cycles × lanes − codes`).
    pub fn idle_lane_cycles(&self) -> u64 {
        (self.cycles * self.lanes).saturating_sub(self.codes)
    }
}

impl fmt::Display for Stats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "  cycles {}  codes {}  codes/cycle {:.4}  (lanes {}, depth {})",
            self.cycles,
            self.codes,
            self.codes_per_cycle(),
            self.lanes,
            self.depth
        )?;
        writeln!(
            f,
            "  first entry at cycle {}, last at {}; entry stalls: input {} cycles, output back-pressure {} cycles; idle lane-cycles {}",
            self.first_accept,
            self.last_accept,
            self.stall_input,
            self.stall_output,
            self.idle_lane_cycles()
        )?;
        writeln!(
            f,
            "  FIFO occupancy mean: input {:.2} AABBs, output {:.2} codes",
            self.in_fifo_mean(),
            self.out_fifo_mean()
        )?;
        write!(
            f,
            "  memory: {} reads ({} B), {} writes ({} B), bus utilisation {:.1} %",
            self.reads,
            self.bytes_read,
            self.writes,
            self.bytes_written,
            100.0 * self.memory_utilisation()
        )
    }
}

/// Per-cycle FIFO occupancy histograms (cycle-stepped mode only).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Occupancy {
    /// `input[v]` = cycles that ended with `v` AABBs in the input buffer.
    pub input: Vec<u64>,
    /// `output[v]` = cycles that ended with `v` codes in the output FIFO.
    pub output: Vec<u64>,
}

impl Occupancy {
    /// Sum over cycles of occupancy (must equal the matching [`Stats`] sum).
    pub fn weighted_sums(&self) -> (u64, u64) {
        let s = |h: &[u64]| h.iter().enumerate().map(|(v, &c)| v as u64 * c).sum();
        (s(&self.input), s(&self.output))
    }

    /// Histogram in eight equal-width buckets, as percentages of cycles.
    pub fn buckets(h: &[u64]) -> Vec<(usize, usize, f64)> {
        let total: u64 = h.iter().sum();
        let n = h.len().max(1);
        let w = n.div_ceil(8);
        (0..n)
            .step_by(w)
            .map(|lo| {
                let hi = (lo + w).min(n);
                let c: u64 = h[lo..hi].iter().sum();
                (lo, hi - 1, 100.0 * c as f64 / total.max(1) as f64)
            })
            .collect()
    }
}

impl fmt::Display for Occupancy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (name, h) in [("input", &self.input), ("output", &self.output)] {
            write!(f, "  {name} FIFO histogram (% of cycles):")?;
            for (lo, hi, p) in Occupancy::buckets(h) {
                write!(f, " [{lo}-{hi}] {p:.1}")?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}
