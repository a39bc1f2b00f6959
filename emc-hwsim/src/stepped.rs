//! Cycle-stepped mode: the reference timing model. Every cycle runs four phases on real data —
//! read data arrives in the input buffer, every in-flight token's completing stage computes,
//! finished codes enter the output FIFO, the bus issues at most one transaction (writes first),
//! and the lanes accept new AABBs under output credit — so the fast mode can be checked.
#![forbid(unsafe_code)]

use std::collections::VecDeque;

use emc_core::Aabb;

use crate::datapath::{Token, Unit};
use crate::error::HwError;
use crate::memory::{Flow, Port, AABB_BYTES};
use crate::stats::{Occupancy, Stats};

/// Result of a cycle-stepped run.
#[derive(Clone, Debug)]
pub struct SteppedRun {
    /// Codes in the order the unit wrote them to memory.
    pub codes: Vec<u64>,
    /// Statistics (same definitions as the fast mode).
    pub stats: Stats,
    /// Per-cycle FIFO occupancy histograms.
    pub occupancy: Occupancy,
}

/// The ring index `off` cycles before ring index `cur` (`off < slots`).
#[inline(always)]
fn back(cur: usize, off: usize, slots: usize) -> usize {
    if cur >= off {
        cur - off
    } else {
        cur + slots - off
    }
}

/// Run the unit cycle by cycle over `boxes`.
pub fn run(unit: &Unit, boxes: &[Aabb], flow: &Flow, port: &Port) -> Result<SteppedRun, HwError> {
    flow.validate()?;
    let n = boxes.len() as u64;
    debug_assert_eq!(n, flow.n);
    let mut st = Stats {
        codes: n,
        lanes: flow.lanes,
        depth: flow.depth,
        ticks_per_cycle: port.ticks_per_cycle,
        ..Stats::default()
    };
    let mut occ = Occupancy {
        input: vec![0; flow.in_cap as usize + 1],
        output: vec![0; flow.out_cap as usize + 1],
    };
    let mut out_mem = Vec::with_capacity(boxes.len());
    if n == 0 {
        return Ok(SteppedRun {
            codes: out_mem,
            stats: st,
            occupancy: occ,
        });
    }
    // Completion offset of every stage (cycles after entry).
    let mut done_at = Vec::new();
    let mut off = 0u64;
    for s in unit.stages() {
        off += s.latency as u64;
        done_at.push((off, s.block.clone()));
    }
    let depth = off;
    debug_assert_eq!(depth, flow.depth);
    let slots = depth as usize + 1;
    // Tokens by entry cycle modulo (depth + 1): a delay line of stage registers.
    let mut pipe: Vec<Vec<Token>> = vec![Vec::new(); slots];
    // (arrival cycle, first primitive, count) of reads in flight.
    let mut inflight: VecDeque<(u64, u64, u64)> = VecDeque::new();
    // Input buffer: tokens with their arrival cycle.
    let mut in_buf: VecDeque<(Token, u64)> = VecDeque::new();
    let mut out_fifo: VecDeque<u64> = VecDeque::new();
    // (first primitive, count, issue cycle) of writes, for credit attribution.
    let mut write_log: VecDeque<(u64, u64, u64)> = VecDeque::new();
    let mut lane_next = vec![0u64; flow.lanes as usize];
    let mut recent: VecDeque<u64> = VecDeque::with_capacity(flow.lanes as usize + 1);
    let (mut reserved, mut requested, mut accepted, mut exited, mut written) = (0u64, 0, 0, 0, 0);
    let mut bus_free = 0u64;
    let mut prev_acc = 0u64;
    let mut t = 0u64;
    // `t mod slots`, kept incrementally (the ring index of tokens entering this cycle).
    let mut cur = 0usize;
    loop {
        // Phase 1: read data arriving this cycle.
        while inflight.front().is_some_and(|f| f.0 <= t) {
            let (_, first, count) = inflight.pop_front().expect("checked");
            for i in first..first + count {
                in_buf.push_back((Token::new(i, &boxes[i as usize]), t));
            }
            reserved -= count;
        }
        // Stage completions: tokens that entered `off` cycles ago finish the stage at `off`.
        for (off, blk) in &done_at {
            if t >= *off {
                for tok in pipe[back(cur, *off as usize, slots)].iter_mut() {
                    blk.eval(tok);
                }
            }
        }
        // Phase 2: finished codes into the output FIFO.
        if t >= depth {
            let slot = &mut pipe[back(cur, depth as usize, slots)];
            for tok in slot.drain(..) {
                out_fifo.push_back(tok.code());
                exited += 1;
            }
        }
        // Phase 3: the bus.
        if port.ready_cycle(bus_free) <= t {
            let flush = exited == n && !out_fifo.is_empty();
            if out_fifo.len() as u64 >= flow.write_burst || flush {
                let cnt = flow.write_burst.min(out_fifo.len() as u64);
                let bytes = cnt * flow.code_bytes;
                bus_free = port.transfer(bus_free, t, bytes);
                st.bus_ticks += bytes * port.ticks_per_byte;
                out_mem.extend(out_fifo.drain(..cnt as usize));
                write_log.push_back((written, cnt, t));
                written += cnt;
                st.writes += 1;
                st.bytes_written += bytes;
            } else if requested < n {
                let cnt = flow.read_burst.min(n - requested);
                if in_buf.len() as u64 + reserved + cnt <= flow.in_cap {
                    let bytes = cnt * AABB_BYTES;
                    bus_free = port.transfer(bus_free, t, bytes);
                    st.bus_ticks += bytes * port.ticks_per_byte;
                    inflight.push_back((port.arrival(bus_free), requested, cnt));
                    reserved += cnt;
                    requested += cnt;
                    st.reads += 1;
                    st.bytes_read += bytes;
                }
            }
        }
        // Phase 4: lanes accept under output credit.
        let slot = cur;
        for lane in lane_next.iter_mut() {
            if *lane > t {
                continue;
            }
            let credit = flow.out_cap - (accepted - written);
            if credit == 0 || in_buf.is_empty() {
                break;
            }
            let (tok, arr) = in_buf.pop_front().expect("checked");
            // Attribution: how long past the structural limit did this primitive wait, and why.
            let i = accepted;
            let lane_limit = if i >= flow.lanes {
                recent[0] + flow.ii
            } else {
                0
            };
            let structural = prev_acc.max(lane_limit);
            if t > structural {
                let cr = if i >= flow.out_cap {
                    let j = i - flow.out_cap;
                    while write_log.front().is_some_and(|w| w.0 + w.1 <= j) {
                        write_log.pop_front();
                    }
                    write_log.front().map_or(0, |w| w.2)
                } else {
                    0
                };
                if arr >= cr {
                    st.stall_input += t - structural;
                } else {
                    st.stall_output += t - structural;
                }
            }
            if i == 0 {
                st.first_accept = t;
            }
            if recent.len() as u64 == flow.lanes {
                recent.pop_front();
            }
            recent.push_back(t);
            prev_acc = t;
            pipe[slot].push(tok);
            *lane = t + flow.ii;
            accepted += 1;
        }
        let (i_occ, o_occ) = (in_buf.len(), out_fifo.len());
        occ.input[i_occ] += 1;
        occ.output[o_occ] += 1;
        st.in_fifo_sum += i_occ as u64;
        st.out_fifo_sum += o_occ as u64;
        if written == n {
            break;
        }
        t += 1;
        cur = if cur + 1 == slots { 0 } else { cur + 1 };
    }
    st.last_accept = prev_acc;
    st.cycles = port.end_cycle(bus_free);
    // The last write is still on the bus: both FIFOs are empty for the remaining cycles.
    let tail = st.cycles - (t + 1);
    occ.input[0] += tail;
    occ.output[0] += tail;
    Ok(SteppedRun {
        codes: out_mem,
        stats: st,
        occupancy: occ,
    })
}
