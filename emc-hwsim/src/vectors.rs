//! Test vectors of the unit in the manner of Berkeley TestFloat's generators: one line per box,
//! the operands and the expected result in hex, then the cycle the box enters and the cycle its
//! code leaves the unit. The same text drives the emitted Verilog testbench ([`crate::rtl`])
//! and any external DUT (`emc hwsim --vectors FILE`).
//!
//! ```text
//! # comment lines start with '#'
//! <min.x> <min.y> <min.z> <max.x> <max.y> <max.z> <code> <in> <out>
//! 3dcccccd 00000000 3f800000 3e4ccccd 00000000 3f800000 00000000f2a9c101 0 22
//! ```
//!
//! The six box fields are the IEEE-754 binary32 bit patterns (8 hex digits each), the code is
//! 16 hex digits (right-aligned, upper bits zero for codes of fewer than 64 bits), `in` is the
//! cycle (decimal, counted from the first cycle after configuration) at which the box is
//! offered, `out` the cycle in which the code is on the unit's output. Cycles come from the
//! model: the lane recurrence `in(i) = max(in(i−1), in(i−L) + II)` with the stage list's
//! initiation interval, and `out = in + depth` (the sum of the stage latencies).
#![forbid(unsafe_code)]

use core::fmt::Write;

use emc_core::glam::Vec3;
use emc_core::Aabb;

use crate::datapath::Unit;

/// One test vector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vector {
    /// The input box.
    pub aabb: Aabb,
    /// The expected code.
    pub code: u64,
    /// Cycle the box is offered (and accepted).
    pub cycle_in: u64,
    /// Cycle the code is on the output.
    pub cycle_out: u64,
}

/// Why a vectors file could not be read.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("vectors line {line}: {what}")]
pub struct VectorError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong.
    pub what: String,
}

/// The vectors of `boxes` on `unit`: codes from the unit's datapath, cycles from its stage
/// list with a box offered every cycle a lane can accept one (one lane).
pub fn vectors(unit: &Unit, boxes: &[Aabb]) -> Vec<Vector> {
    let ii = unit.lane_ii() as u64;
    let lanes = unit.options().lanes as usize;
    let depth = unit.depth() as u64;
    let mut entries: Vec<u64> = Vec::with_capacity(boxes.len());
    for i in 0..boxes.len() {
        let prev = if i > 0 { entries[i - 1] } else { 0 };
        let lane = if i >= lanes {
            entries[i - lanes] + ii
        } else {
            0
        };
        entries.push(prev.max(lane));
    }
    boxes
        .iter()
        .zip(entries)
        .map(|(b, t)| Vector {
            aabb: *b,
            code: unit.code(b),
            cycle_in: t,
            cycle_out: t + depth,
        })
        .collect()
}

/// The vectors as text, with a header of `#` lines naming the unit.
pub fn to_text(unit: &Unit, v: &[Vector]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# emc unit vectors: {} ({}), depth {} cycles, lane II {}",
        unit.spec(),
        unit.layout(),
        unit.depth(),
        unit.lane_ii()
    );
    let _ = writeln!(
        s,
        "# min.x min.y min.z max.x max.y max.z (f32 hex) code (hex) cycle_in cycle_out"
    );
    for x in v {
        for f in x
            .aabb
            .min
            .to_array()
            .iter()
            .chain(x.aabb.max.to_array().iter())
        {
            let _ = write!(s, "{:08x} ", f.to_bits());
        }
        let _ = writeln!(s, "{:016x} {} {}", x.code, x.cycle_in, x.cycle_out);
    }
    s
}

/// Parse vectors text (the format of [`to_text`]).
pub fn parse(text: &str) -> Result<Vec<Vector>, VectorError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let err = |what: String| VectorError { line: i + 1, what };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() != 9 {
            return Err(err(format!("expected 9 fields, found {}", f.len())));
        }
        let mut c = [0f32; 6];
        for (k, v) in c.iter_mut().enumerate() {
            let bits = u32::from_str_radix(f[k], 16)
                .map_err(|e| err(format!("field {} {:?}: {e}", k + 1, f[k])))?;
            *v = f32::from_bits(bits);
        }
        let code =
            u64::from_str_radix(f[6], 16).map_err(|e| err(format!("code {:?}: {e}", f[6])))?;
        let cycle_in: u64 = f[7]
            .parse()
            .map_err(|e| err(format!("cycle_in {:?}: {e}", f[7])))?;
        let cycle_out: u64 = f[8]
            .parse()
            .map_err(|e| err(format!("cycle_out {:?}: {e}", f[8])))?;
        out.push(Vector {
            aabb: Aabb::new(Vec3::new(c[0], c[1], c[2]), Vec3::new(c[3], c[4], c[5])),
            code,
            cycle_in,
            cycle_out,
        });
    }
    Ok(out)
}
