//! Fast mode timing: the unit's timing never depends on data values, so it is derived per
//! primitive and per memory transaction instead of per cycle. Entry times obey a max-plus
//! recurrence; the bus is an event loop over transactions. Idle cycles cost nothing, and the
//! result equals the cycle-stepped mode exactly (tests compare every statistic).
//!
//! With `acc(i)` the cycle primitive `i` enters the datapath, `arr(i)` the cycle its read burst
//! arrives, `wr(j)` the cycle write burst `j` issues, `L` lanes, `II`, depth `P` and an output
//! FIFO of `C` codes (credits):
//!
//! ```text
//!   acc(i) = max( acc(i−1), acc(i−L) + II, arr(i), wr(burst of i − C) )
//!   write j may issue at  acc(last item of j) + P            (its codes are in the FIFO)
//!   read b may issue at   acc(b·rb + cnt − cap − 1) + 1       (its buffer space is free)
//! ```
//!
//! and the bus takes, at the first cycle it is free (one issue per cycle), the write if it may
//! issue, else the read.
#![forbid(unsafe_code)]

use std::collections::VecDeque;

use crate::error::HwError;
use crate::memory::{BusTime, Flow, Port, AABB_BYTES};
use crate::stats::Stats;

/// An issued transaction: first primitive, count, and arrival (reads) or issue cycle (writes).
#[derive(Clone, Copy, Debug)]
struct Span {
    first: u64,
    count: u64,
    cycle: u64,
}

/// The cycle of the span covering `item` and the end of that span (popping passed spans).
#[inline(always)]
fn span(q: &mut VecDeque<Span>, item: u64) -> (u64, u64) {
    while let Some(s) = q.front() {
        if s.first + s.count <= item {
            q.pop_front();
        } else {
            return (s.cycle, s.first + s.count);
        }
    }
    unreachable!("a span covering every looked-up primitive has been issued")
}

/// Statistics of a run of `flow` on `port`, without stepping cycles.
pub fn timing(flow: &Flow, port: &Port) -> Result<Stats, HwError> {
    flow.validate()?;
    let mut st = Stats {
        codes: flow.n,
        lanes: flow.lanes,
        depth: flow.depth,
        ticks_per_cycle: port.ticks_per_cycle,
        ..Stats::default()
    };
    let n = flow.n;
    if n == 0 {
        return Ok(st);
    }
    let size = (flow.in_cap + flow.out_cap + flow.lanes + flow.write_burst + 4).next_power_of_two();
    let mask = size - 1;
    let mut acc = vec![0u64; size as usize];
    let mut reads: VecDeque<Span> = VecDeque::new();
    let mut writes: VecDeque<Span> = VecDeque::new();
    const NEVER: u64 = u64::MAX;
    let (mut a, mut requested, mut written) = (0u64, 0u64, 0u64);
    let mut prev = 0u64;
    let mut bus_free = BusTime::default();
    // Durations of the full bursts (the last burst of each kind may be shorter).
    let full_write = port.duration(flow.write_burst * flow.code_bytes);
    let full_read = port.duration(flow.read_burst * AABB_BYTES);
    let mut next_issue = 0u64;
    loop {
        // Entry times of every primitive whose data and credit are already scheduled, in runs
        // that share one read burst and one credit-releasing write burst.
        while a < requested {
            let (arr, rend) = span(&mut reads, a);
            let (cr, cend) = if a >= flow.out_cap {
                let i = a - flow.out_cap;
                if i >= written {
                    break;
                }
                let (c, e) = span(&mut writes, i);
                (c, e + flow.out_cap)
            } else {
                (0, flow.out_cap)
            };
            let end = rend.min(cend).min(requested);
            let bound = arr.max(cr);
            let input = (arr >= cr) as u64;
            if a == 0 {
                st.first_accept = bound;
            }
            for i in a..end {
                let lane = if i >= flow.lanes {
                    acc[((i - flow.lanes) & mask) as usize] + flow.ii
                } else {
                    0
                };
                let structural = prev.max(lane);
                let t = structural.max(bound);
                let wait = t - structural;
                st.stall_input += wait * input;
                st.stall_output += wait * (1 - input);
                st.in_fifo_sum += t - arr;
                acc[(i & mask) as usize] = t;
                prev = t;
            }
            a = end;
        }
        if written == n {
            break;
        }
        // The next transaction.
        let ready = bus_free.cycle.max(next_issue);
        let wcnt = flow.write_burst.min(n - written);
        let wlast = written + wcnt - 1;
        let w = if wlast < a {
            acc[(wlast & mask) as usize] + flow.depth
        } else {
            NEVER
        };
        let rcnt = flow.read_burst.min(n - requested);
        let r = if requested >= n {
            NEVER
        } else if requested + rcnt <= flow.in_cap {
            0
        } else {
            let m = requested + rcnt - flow.in_cap - 1;
            if m < a {
                acc[(m & mask) as usize] + 1
            } else {
                NEVER
            }
        };
        debug_assert!(w != NEVER || r != NEVER, "no transaction can ever issue");
        let u = ready.max(w.min(r));
        if w <= u {
            let bytes = wcnt * flow.code_bytes;
            let d = if wcnt == flow.write_burst {
                full_write
            } else {
                port.duration(bytes)
            };
            bus_free = port.transfer_at(bus_free, u, d);
            st.bus_ticks += bytes * port.ticks_per_byte;
            for i in written..written + wcnt {
                st.out_fifo_sum += u - (acc[(i & mask) as usize] + flow.depth);
            }
            writes.push_back(Span {
                first: written,
                count: wcnt,
                cycle: u,
            });
            written += wcnt;
            st.writes += 1;
            st.bytes_written += bytes;
        } else {
            let bytes = rcnt * AABB_BYTES;
            let d = if rcnt == flow.read_burst {
                full_read
            } else {
                port.duration(bytes)
            };
            bus_free = port.transfer_at(bus_free, u, d);
            st.bus_ticks += bytes * port.ticks_per_byte;
            reads.push_back(Span {
                first: requested,
                count: rcnt,
                cycle: port.ceil(bus_free) + port.latency,
            });
            requested += rcnt;
            st.reads += 1;
            st.bytes_read += bytes;
        }
        next_issue = u + 1;
    }
    st.last_accept = prev;
    st.cycles = port.ceil(bus_free);
    Ok(st)
}
