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

use std::collections::VecDeque;

use crate::error::HwError;
use crate::memory::{Flow, Port, AABB_BYTES};
use crate::stats::Stats;

/// An issued transaction: first primitive, count, and arrival (reads) or issue cycle (writes).
#[derive(Clone, Copy, Debug)]
struct Span {
    first: u64,
    count: u64,
    cycle: u64,
}

/// The cycle at which `item` is covered by the front span (popping spans it has passed).
#[inline(always)]
fn span_cycle(q: &mut VecDeque<Span>, item: u64) -> u64 {
    while let Some(s) = q.front() {
        if s.first + s.count <= item {
            q.pop_front();
        } else {
            return s.cycle;
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
    let mut bus_free = 0u64;
    let mut next_issue = 0u64;
    loop {
        // Entry times of every primitive whose data and credit are already scheduled.
        while a < requested {
            let cr = if a >= flow.out_cap {
                let i = a - flow.out_cap;
                if i >= written {
                    break;
                }
                span_cycle(&mut writes, i)
            } else {
                0
            };
            let arr = span_cycle(&mut reads, a);
            let lane = if a >= flow.lanes {
                acc[((a - flow.lanes) & mask) as usize] + flow.ii
            } else {
                0
            };
            let structural = prev.max(lane);
            let t = structural.max(arr).max(cr);
            if t > structural {
                if arr >= cr {
                    st.stall_input += t - structural;
                } else {
                    st.stall_output += t - structural;
                }
            }
            st.in_fifo_sum += t - arr;
            if a == 0 {
                st.first_accept = t;
            }
            acc[(a & mask) as usize] = t;
            prev = t;
            a += 1;
        }
        if written == n {
            break;
        }
        // The next transaction.
        let ready = port.ready_cycle(bus_free).max(next_issue);
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
            bus_free = port.transfer(bus_free, u, bytes);
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
            bus_free = port.transfer(bus_free, u, bytes);
            st.bus_ticks += bytes * port.ticks_per_byte;
            reads.push_back(Span {
                first: requested,
                count: rcnt,
                cycle: port.arrival(bus_free),
            });
            requested += rcnt;
            st.reads += 1;
            st.bytes_read += bytes;
        }
        next_issue = u + 1;
    }
    st.last_accept = prev;
    st.cycles = port.end_cycle(bus_free);
    Ok(st)
}
