//! Quantisation: from a primitive box to the four integer channel values a layout interleaves.
//! The arithmetic here is normative; every fast path (SIMD, the hardware model) must equal it.
//!
//! Positions, per axis `a` with `n` bits and position box origin `o`, extent `E`:
//!
//! ```text
//!   c2 = lo + hi                      f64, exact for ordinary inputs (twice the centre)
//!   v  = (c2 - 2·o) · (2^n / E / 2)   one f64 subtract, one f64 multiply by a per-frame constant
//!   q  = min(trunc_sat(v), 2^n - 1)   trunc_sat: NaN and negatives → 0, saturating above
//! ```
//!
//! Halving by 2 commutes with f64 rounding, so this equals `((lo+hi)/2 − o) · 2^n/E` bit for
//! bit: one multiply by the precomputed `2^n / E`, floor, clamp to `[0, 2^n − 1]`. The
//! precomputed scale is `2^n / E` rounded to nearest; only for channels wider than 52 bits is it
//! raised by a few ulps so that the max face still reaches `2^n − 1` ([`position_scale`]). A zero
//! extent gives the scale 0 and the value 0. Truncation equals floor on the values that survive
//! the clamp, so a centre on the max face gives `2^n − 1` and never wraps to 0.
//!
//! Size, with `S` bits, `d2 = (dx² + dy²) + dz²` (f64, no FMA) and `D` the frame diagonal:
//!
//! ```text
//!   sqrt transform:   q = min(trunc_sat(sqrt(sqrt(d2) / D) · 2^S), 2^S − 1)
//!   linear transform: q = min(trunc_sat((sqrt(d2) · 2^S) / D),     2^S − 1)
//! ```
//!
//! Both are non-decreasing in `d2`, so for `S ≤ 8` the value is also the number of per-frame
//! thresholds `T_k = min{ d2 : f(d2) ≥ k }` that `d2` reaches; the thresholds are found by
//! bisection on the formula itself, so the two forms agree by construction (and a hardware unit
//! needs no square root, only `S` comparisons).
#![forbid(unsafe_code)]

use crate::aabb::Aabb;
use crate::frame::Frame;
use crate::layout::{Channel, Layout, SizeTransform};

/// Largest size-bit count served by the threshold table.
pub const MAX_THRESHOLD_BITS: u32 = 8;

/// Saturating truncation to `u64` (NaN → 0, negative → 0), as Rust's `as` defines it.
#[inline(always)]
fn trunc_sat(v: f64) -> u64 {
    v as u64
}

/// `2^n` as an `f64` (exact for every `n` in 0..=64).
#[inline]
pub fn pow2(n: u32) -> f64 {
    libm::ldexp(1.0, n as i32)
}

/// The position scale of an axis with `n > 0` bits and extent `e > 0`: `2^n / e` rounded to
/// nearest, then raised by the fewest ulps that make the max face (`e · scale`, the exact
/// product of the same subtraction the position path computes) truncate to at least
/// `2^n − 1`. For `n ≤ 52` the raise never happens: `fl(e · fl(2^n / e)) ≥ 2^n (1 − 2^-52)`
/// truncates to at least `2^n − 1`. For wider channels (a line or needle scene gives one axis
/// up to 64 bits) plain rounding can land `e · scale` a few f64 ulps below `2^n`, which would
/// truncate the max face to `2^n − 2^(n−53)` instead of `2^n − 1`.
#[inline]
pub fn position_scale(n: u32, e: f64) -> f64 {
    let max = u64::MAX >> (64 - n);
    let mut s = pow2(n) / e;
    while trunc_sat(e * s) < max {
        s = s.next_up();
    }
    s
}

/// The per-frame, per-layout constants of quantisation.
#[derive(Clone, Debug)]
pub struct Quantizer {
    origin2: [f64; 3],
    half_scale: [f64; 3],
    max: [u64; 4],
    size_bits: u32,
    size_scale: f64,
    diag: f64,
    transform: SizeTransform,
    /// `thresholds[k]` = smallest `d2` whose size value is at least `k` (index 0 unused);
    /// filled for `size_bits <= MAX_THRESHOLD_BITS`, padded with +inf.
    thresholds: [f64; 256],
}

impl Quantizer {
    /// Constants for `layout` in `frame`.
    pub fn new(layout: &Layout, frame: &Frame) -> Quantizer {
        let o = frame.origin();
        let e = frame.extent();
        let mut half_scale = [0.0; 3];
        let mut origin2 = [0.0; 3];
        for a in 0..3 {
            let n = layout.bits(Channel::from_index(a));
            origin2[a] = 2.0 * o[a];
            half_scale[a] = if e[a] > 0.0 && n > 0 {
                position_scale(n, e[a]) * 0.5
            } else {
                0.0
            };
        }
        let max = [
            layout.channel_max(Channel::X),
            layout.channel_max(Channel::Y),
            layout.channel_max(Channel::Z),
            layout.channel_max(Channel::S),
        ];
        let size_bits = layout.bits(Channel::S);
        let mut q = Quantizer {
            origin2,
            half_scale,
            max,
            size_bits,
            size_scale: pow2(size_bits),
            diag: frame.diagonal(),
            transform: layout.transform(),
            thresholds: [f64::INFINITY; 256],
        };
        if size_bits > 0 && size_bits <= MAX_THRESHOLD_BITS {
            q.thresholds[0] = 0.0;
            for k in 1..(1u64 << size_bits) {
                q.thresholds[k as usize] = q.first_d2_reaching(k);
            }
        }
        q
    }

    /// Smallest non-negative `d2` with `size_from_d2(d2) >= k` (+inf if none): bisection on
    /// the bit patterns of non-negative `f64`, which order like the values.
    fn first_d2_reaching(&self, k: u64) -> f64 {
        let mut lo: u64 = 0; // f(lo) < k is not assumed; handled below
        let mut hi: u64 = f64::INFINITY.to_bits();
        if self.size_from_d2(f64::from_bits(hi)) < k {
            return f64::INFINITY;
        }
        if self.size_from_d2(0.0) >= k {
            return 0.0;
        }
        // Invariant: f(lo) < k <= f(hi).
        while hi - lo > 1 {
            let mid = lo + (hi - lo) / 2;
            if self.size_from_d2(f64::from_bits(mid)) >= k {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        f64::from_bits(hi)
    }

    /// Twice the origin of the position box (the constant subtracted from `lo + hi`).
    #[inline]
    pub fn origin2(&self) -> [f64; 3] {
        self.origin2
    }

    /// Half the per-axis scale `2^n / E` (0 for a flat or unused axis).
    #[inline]
    pub fn half_scale(&self) -> [f64; 3] {
        self.half_scale
    }

    /// Per-channel maxima `2^bits − 1` (x, y, z, s).
    #[inline]
    pub fn max(&self) -> [u64; 4] {
        self.max
    }

    /// Size bits of the layout.
    #[inline]
    pub fn size_bits(&self) -> u32 {
        self.size_bits
    }

    /// Frame diagonal `D`.
    #[inline]
    pub fn diagonal(&self) -> f64 {
        self.diag
    }

    /// Size transform of the layout.
    #[inline]
    pub fn transform(&self) -> SizeTransform {
        self.transform
    }

    /// The threshold table (`2^S` entries, index 0 = 0.0) when `S <= MAX_THRESHOLD_BITS`.
    #[inline]
    pub fn thresholds(&self) -> Option<&[f64]> {
        if self.size_bits > 0 && self.size_bits <= MAX_THRESHOLD_BITS {
            Some(&self.thresholds[..1 << self.size_bits])
        } else {
            None
        }
    }

    /// One position channel from `lo + hi` on that axis (see the module docs).
    #[inline(always)]
    pub fn position(&self, axis: usize, c2: f64) -> u64 {
        trunc_sat((c2 - self.origin2[axis]) * self.half_scale[axis]).min(self.max[axis])
    }

    /// The size value by the normative formula (square roots and a division).
    #[inline]
    pub fn size_from_d2(&self, d2: f64) -> u64 {
        if self.size_bits == 0 {
            return 0;
        }
        let d = libm::sqrt(d2);
        let v = match self.transform {
            SizeTransform::Sqrt => libm::sqrt(d / self.diag) * self.size_scale,
            SizeTransform::Linear => (d * self.size_scale) / self.diag,
        };
        trunc_sat(v).min(self.max[3])
    }

    /// The size value by the threshold table: a branch-free binary search of `S` steps. Equal
    /// to [`Quantizer::size_from_d2`] for every `d2` (by construction; tested exhaustively on
    /// the thresholds' neighbours). Falls back to the formula when `S > MAX_THRESHOLD_BITS`.
    #[inline]
    pub fn size_by_thresholds(&self, d2: f64) -> u64 {
        if self.size_bits == 0 || self.size_bits > MAX_THRESHOLD_BITS {
            return self.size_from_d2(d2);
        }
        let mut pos = 0usize;
        let mut step = 1usize << (self.size_bits - 1);
        while step > 0 {
            // Compiles to a compare and a conditional add; NaN compares false and stays at 0.
            pos += step * (self.thresholds[pos + step] <= d2) as usize;
            step >>= 1;
        }
        pos as u64
    }

    /// All four channel values of a primitive box (x, y, z, s).
    #[inline]
    pub fn quantize(&self, b: &Aabb) -> [u64; 4] {
        let c2x = b.min.x as f64 + b.max.x as f64;
        let c2y = b.min.y as f64 + b.max.y as f64;
        let c2z = b.min.z as f64 + b.max.z as f64;
        [
            self.position(0, c2x),
            self.position(1, c2y),
            self.position(2, c2z),
            self.size_by_thresholds(b.diagonal_sq_f64()),
        ]
    }

    /// The channel values by the plain formulas only (no threshold table): the oracle.
    #[inline]
    pub fn quantize_reference(&self, b: &Aabb) -> [u64; 4] {
        let c = b.center_f64();
        let o = [
            self.origin2[0] * 0.5,
            self.origin2[1] * 0.5,
            self.origin2[2] * 0.5,
        ];
        let mut q = [0u64; 4];
        for a in 0..3 {
            let scale = self.half_scale[a] * 2.0;
            q[a] = trunc_sat((c[a] - o[a]) * scale).min(self.max[a]);
        }
        q[3] = self.size_from_d2(b.diagonal_sq_f64());
        q
    }
}
