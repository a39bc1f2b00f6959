//! The host-side model of the unit's firmware: what a driver computes once per frame before it
//! writes the configuration registers — the bit schedule of a layout, the position scales and
//! the size thresholds — using the unit's own arithmetic (its float→fixed and size-formula
//! operations), never emc-core's quantiser. emc-core stays the test oracle of all three.
#![forbid(unsafe_code)]

use emc_core::{Channel, LayoutSpec, SizeTransform};

use crate::fixed::{exp_add, float_to_fixed, POS_INF_BITS};

/// `2^n` for `n <= 64`, built from its exponent field (exact).
pub fn pow2(n: u32) -> f64 {
    f64::from_bits((1023 + n as u64) << 52)
}

/// The code pattern (MSB first) and size transform the firmware programs for a layout name on
/// a frame with position extents `extent`.
///
/// The rules, restated from the EMC definition the workspace fixed (emc-core's `layout`
/// module documents them): Morton is `(xyz)^n`; `emc64-sort` takes the axes by descending
/// extent (stable on ties, x before y before z) in `(a0 a1 a2 s)^16` with the linear size
/// transform; the `-var` layouts put a size bit at every seventh position (0-based 6, 13, …)
/// until their size bits are placed, and fill the other positions by halving the currently
/// longest extent (ties x > y > z; round robin x, y, z once every extent is zero).
pub fn schedule(spec: &LayoutSpec, extent: [f64; 3]) -> (Vec<Channel>, SizeTransform) {
    const XYZ: [Channel; 3] = [Channel::X, Channel::Y, Channel::Z];
    let repeat = |group: &[Channel], times: usize| -> Vec<Channel> {
        (0..times).flat_map(|_| group.iter().copied()).collect()
    };
    match spec {
        LayoutSpec::Morton30 => (repeat(&XYZ, 10), SizeTransform::Sqrt),
        LayoutSpec::Morton63 => (repeat(&XYZ, 21), SizeTransform::Sqrt),
        LayoutSpec::Emc64Sort => {
            let mut order = XYZ;
            // Three elements: pick the longest, then the longer of the other two, keeping the
            // earlier axis on equal extents.
            order.sort_by(|a, b| {
                extent[b.index()]
                    .partial_cmp(&extent[a.index()])
                    .unwrap_or(core::cmp::Ordering::Equal)
            });
            let group = [order[0], order[1], order[2], Channel::S];
            (repeat(&group, 16), SizeTransform::Linear)
        }
        LayoutSpec::Emc64Var => (halving(extent, 64, 6), SizeTransform::Sqrt),
        LayoutSpec::Emc32Var => (halving(extent, 32, 4), SizeTransform::Sqrt),
        LayoutSpec::Emc64VarNoSize => (halving(extent, 64, 0), SizeTransform::Sqrt),
        LayoutSpec::Custom(p) => (p.channels().to_vec(), p.transform()),
    }
}

/// The `-var` pattern of `len` positions with `size_bits` size bits at period 7.
fn halving(extent: [f64; 3], len: usize, size_bits: usize) -> Vec<Channel> {
    let mut e = extent;
    let mut out = Vec::with_capacity(len);
    let mut spatial = 0;
    for pos in 0..len {
        let sizes_so_far = out.iter().filter(|&&c| c == Channel::S).count();
        if pos % 7 == 6 && sizes_so_far < size_bits {
            out.push(Channel::S);
            continue;
        }
        let longest = (0..3).fold(0, |best, a| if e[a] > e[best] { a } else { best });
        let a = if e[longest] > 0.0 {
            longest
        } else {
            spatial % 3
        };
        out.push(Channel::from_index(a));
        e[a] /= 2.0;
        spatial += 1;
    }
    out
}

/// The position scale register of an axis with `n` bits (1..=64) and extent `e > 0`: `2^n / e`
/// rounded to nearest, then raised one ulp at a time until the unit's own datapath maps the
/// max face to `2^n − 1`. The max face reaches the multiplier as `2e` (the centre sum minus
/// twice the origin, both exact doubles of the frame's values), times the half scale, which is
/// `e · scale` exactly; float→fixed then truncates it. Channels of at most 52 bits never need
/// the raise; wider ones (a line scene gives one axis up to 64 bits) can land a few ulps short,
/// which would truncate the max face to `2^n − 2^(n−53)`.
pub fn position_scale(n: u32, e: f64) -> f64 {
    let max = u64::MAX >> (64 - n);
    let mut s = pow2(n) / e;
    // e·s grows by at least one ulp of 2^n per raised ulp of s; 2^12 raises cover any n ≤ 64.
    for _ in 0..4096 {
        if float_to_fixed(e * s, n) >= max {
            break;
        }
        s = f64::from_bits(s.to_bits() + 1);
    }
    s
}

/// The size value the unit's formula path gives a squared diagonal (the `S > 8` stages in
/// order: square root, ×2^S by exponent add, divide by `D`, or the sqrt transform's divide,
/// second root and exponent add; then float→fixed with clamp).
pub fn size_formula(d2: f64, bits: u32, transform: SizeTransform, diag: f64) -> u64 {
    let d = d2.sqrt();
    let v = match transform {
        SizeTransform::Linear => exp_add(d, bits) / diag,
        SizeTransform::Sqrt => exp_add((d / diag).sqrt(), bits),
    };
    float_to_fixed(v, bits)
}

/// The threshold registers of a size channel with `bits` (1..=8) bits: `keys[k]` is the bit
/// pattern of the smallest non-negative `d²` whose size value is at least `k` (`keys[0] = 0`,
/// unused; +∞ when no finite `d²` reaches `k`). Found by bisecting the bit patterns of
/// non-negative doubles (ordered like their values) with the unit's own size formula, which
/// is non-decreasing in `d²`; so the comparator search equals the formula for every input.
pub fn size_thresholds(bits: u32, transform: SizeTransform, diag: f64) -> Vec<u64> {
    let f = |p: u64| size_formula(f64::from_bits(p), bits, transform, diag);
    let mut keys = vec![0u64; 1 << bits];
    for (k, key) in keys.iter_mut().enumerate().skip(1) {
        let k = k as u64;
        *key = if f(0) >= k {
            0
        } else if f(POS_INF_BITS) < k {
            POS_INF_BITS
        } else {
            // f(below) < k <= f(at)
            let (mut below, mut at) = (0u64, POS_INF_BITS);
            while at - below > 1 {
                let mid = below + (at - below) / 2;
                if f(mid) >= k {
                    at = mid;
                } else {
                    below = mid;
                }
            }
            at
        };
    }
    keys
}

/// Whether a fixed (not scene-adaptive) pattern is regular: one group of distinct channels
/// repeated a whole number of times (`(xyz)^21`, `(xyzs)^k`, `(zyx)^k` …). Such a pattern is
/// plain wiring in the unit; an irregular one needs the programmable network.
pub fn is_regular(chans: &[Channel]) -> bool {
    let n = chans.len();
    (1..=4.min(n)).any(|p| {
        n.is_multiple_of(p)
            && (0..p).all(|i| (0..i).all(|j| chans[i] != chans[j]))
            && (p..n).all(|i| chans[i] == chans[i - p])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regular_patterns() {
        let p = |s: &str| -> Vec<Channel> {
            s.chars()
                .map(|c| Channel::from_letter(c).unwrap())
                .collect()
        };
        assert!(is_regular(&p("xyzxyzxyz")));
        assert!(is_regular(&p("xyzs")));
        assert!(is_regular(&p("zzzz")));
        assert!(!is_regular(&p("xyzx")));
        assert!(!is_regular(&p("xxyy")));
        assert!(!is_regular(&p("xyzsxyz")));
    }

    #[test]
    fn wide_channels_reach_their_maximum() {
        for n in 1..=64u32 {
            for e in [0.49f64, 1.0, 3.0, 0.1 + 0.49, 1e-7, 7e12] {
                let s = position_scale(n, e);
                let max = u64::MAX >> (64 - n);
                assert_eq!(float_to_fixed(e * s, n), max, "n={n} e={e}");
                // The raise is minimal: one ulp less falls short (or no raise happened).
                let less = f64::from_bits(s.to_bits() - 1);
                assert!(s == pow2(n) / e || float_to_fixed(e * less, n) < max);
            }
        }
    }
}
