//! The vectorised batch pipeline: quantise four (AVX2) or eight (AVX-512, pdep) boxes at a
//! time in `f64` lanes, then expand. Which path runs is decided once, when an
//! [`Encoder`](crate::Encoder) is built, and described by a [`Pipeline`]. Every path equals
//! the scalar normative arithmetic of [`crate::quantize`].
//!
//! ```text
//!   &[Aabb] ──4 boxes──► quantize (scalar | avx2 f64x4) ──q[x,y,z,s]──► expand (backend) ──► codes
//!           ──8 boxes──► quantize (avx-512 f64x8) ──ring──► pdep      (four-stage pipeline)
//!                                                                         n % 4 tail: scalar
//! ```

use core::fmt;

use crate::expand::Backend;

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;

/// How a batch quantises its boxes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum QuantizePath {
    /// One box at a time with [`Quantizer::quantize`](crate::Quantizer::quantize).
    Scalar,
    /// Four boxes at a time in AVX2 `f64` lanes (x86_64 with AVX2 only); eight at a time in
    /// AVX-512 lanes where [`Pipeline::wide`] says so.
    Avx2,
}

impl QuantizePath {
    /// The lower-case name (`scalar`, `avx2`).
    pub fn name(self) -> &'static str {
        match self {
            QuantizePath::Scalar => "scalar",
            QuantizePath::Avx2 => "avx2",
        }
    }
}

impl fmt::Display for QuantizePath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// How a batch expands quantised values into codes after the quantise step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ExpandPath {
    /// The backend's scalar `expand`, one code at a time.
    Scalar(Backend),
    /// Byte tables read with scalar loads from the four quantised lanes.
    TableLanes,
    /// Shift/mask spreads on four `u64` AVX2 lanes (regular patterns).
    MagicAvx2,
    /// BMI2 `pdep` on each of the four quantised lanes.
    PdepLanes,
    /// The reference bit loop on each lane (forced reference backend).
    ReferenceLanes,
    /// AVX-512 bit shuffles, eight codes at a time: the channels concatenated per `u64` lane,
    /// one `vpshufbitqmb` per code byte, one `vpermb` transpose (any pattern).
    BitShuffle512,
}

impl fmt::Display for ExpandPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExpandPath::Scalar(b) => write!(f, "{b}"),
            ExpandPath::TableLanes => f.write_str("table (byte tables, scalar loads per lane)"),
            ExpandPath::MagicAvx2 => f.write_str("magic (avx2 u64x4 shift/mask spreads)"),
            ExpandPath::PdepLanes => f.write_str("pdep (one per channel and lane)"),
            ExpandPath::ReferenceLanes => f.write_str("reference (bit loop per lane)"),
            ExpandPath::BitShuffle512 => {
                f.write_str("avx-512 bit shuffle (vpshufbitqmb per code byte, vpermb transpose)")
            }
        }
    }
}

/// How the AVX2 quantise step computes a size channel of at most 8 bits.
///
/// All give [`Quantizer::size_by_thresholds`](crate::Quantizer::size_by_thresholds) bit for
/// bit. Measured on an AMD family 0x19 (Zen 4) machine, `emc64-var` pipeline with pdep, in
/// cache: formula 3.4 ns/code, thresholds 3.9 ns/code — the `f64` divider is fast there. The
/// threshold path avoids `sqrtpd`/`divpd`, whose throughput is several times lower on AMD
/// before family 0x19, so dispatch keeps it there (a heuristic: not measured on such a CPU).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SizePath {
    /// An `f32` estimate (`rsqrt`/`rcp`) fixed up with one threshold comparison.
    Thresholds,
    /// The normative `f64` formula: `sqrt`, divide by `D`, `sqrt` (or `× 2^S / D`).
    Formula,
    /// Eight boxes at a time in AVX-512 `f64` lanes: an `rsqrt14`/`rcp14` estimate `k` fixed
    /// up with one comparison against the threshold `T(k)`: on the integer side, on bit
    /// patterns, in the dispatched pdep pipeline; with the thresholds held in registers
    /// (`vpermt2pd`) on the other expand paths. Needs AVX-512 F/DQ/BW/VL and `S <= 6`
    /// (64 thresholds); otherwise the formula.
    /// Measured on Zen 4 (`emc64-var`, pdep, both software-pipelined, 16K boxes in cache):
    /// 3.6 against 4.1 times the streaming baseline with the formula, before the eight-lane
    /// staged pdep pipeline (now 1.9 ns/code, about 2.1 times the baseline there).
    Avx512Lookup,
}

impl SizePath {
    /// The path dispatch picks on this CPU (see the type's docs).
    pub fn preferred(cpu: &crate::cpu::CpuInfo) -> SizePath {
        let amd_like = &cpu.vendor == b"AuthenticAMD" || &cpu.vendor == b"HygonGenuine";
        if amd_like && cpu.family < 0x19 {
            SizePath::Thresholds
        } else {
            SizePath::Formula
        }
    }
}

impl fmt::Display for SizePath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SizePath::Thresholds => "size by f32 estimate + threshold fix-up",
            SizePath::Formula => "size by the f64 formula",
            SizePath::Avx512Lookup => {
                "size by avx-512 f64x8 rsqrt14 estimate + one threshold comparison"
            }
        })
    }
}

/// What `encode_batch` runs: the quantise path, the expand path and why.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pipeline {
    /// The quantise step.
    pub quantize: QuantizePath,
    /// The expand step.
    pub expand: ExpandPath,
    /// Why the quantise path was chosen (one clause).
    pub quantize_reason: &'static str,
    /// How the AVX2 quantise step computes the size channel (`None`: scalar quantise or no
    /// size channel).
    pub size: Option<SizePath>,
    /// The AVX2 quantise step runs eight boxes at a time in AVX-512 `f64x8` lanes, in a
    /// four-stage software pipeline: the pdep expansion on an AVX-512 CPU, for layouts
    /// without a size channel or with [`SizePath::Avx512Lookup`] (same arithmetic).
    pub wide: bool,
}

impl fmt::Display for Pipeline {
    /// For example `quantize: avx2 f64x4; expand: table (byte tables, scalar loads per lane)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.quantize {
            QuantizePath::Avx2 if self.wide => write!(
                f,
                "quantize: avx-512 f64x8 (AVX-512 present, pdep backend: eight boxes per step)"
            )?,
            QuantizePath::Avx2 => write!(f, "quantize: avx2 f64x4 ({})", self.quantize_reason)?,
            QuantizePath::Scalar => write!(f, "quantize: scalar f64 ({})", self.quantize_reason)?,
        }
        if let Some(s) = self.size {
            write!(f, ", {s}")?;
        }
        write!(f, "; expand: {}", self.expand)
    }
}
