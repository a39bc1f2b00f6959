//! Bit-level models of the unit's small integer blocks: float→fixed with clamp (a barrel shift
//! driven by the exponent), the exact ×2^S exponent adder and the threshold comparator key.
//! These operate on IEEE-754 binary64 bit patterns, as the hardware would; tests prove them
//! equal to the Rust float semantics the normative arithmetic is written in.
#![forbid(unsafe_code)]

/// Sign bit of a binary64.
const SIGN: u64 = 1 << 63;
/// Exponent field mask (after shifting down by 52).
const EXP_MASK: u64 = 0x7ff;
/// Fraction field mask.
const FRAC: u64 = (1 << 52) - 1;
/// Bit pattern of +infinity; non-negative non-NaN patterns are `<=` this.
pub const POS_INF_BITS: u64 = 0x7ff0_0000_0000_0000;

/// Float→fixed with clamp: truncate toward zero to an unsigned integer of `n` bits
/// (`1 <= n <= 64`), saturating at `2^n − 1`; negative values, `−0.0` and NaN give 0.
///
/// The datapath, on the binary64 fields `s | e (11) | f (52)`:
///
/// ```text
///   s = 1 or NaN           → 0
///   e < 1023 (|v| < 1)     → 0
///   k = e − 1023 >= n      → 2^n − 1          (includes +inf)
///   otherwise              → (1.f) >> (52 − k)   or  (1.f) << (k − 52) when k > 52
/// ```
///
/// In the unit the same shifter also places the value at its field offset in the packed
/// routing word (the offset is added to the shift amount), so packing costs no extra shifter.
#[inline(always)]
pub fn float_to_fixed(v: f64, n: u32) -> u64 {
    // Written without early exits so that the host compiles it to selects, like the hardware.
    let b = v.to_bits();
    let k = ((b >> 52) & EXP_MASK) as i64 - 1023;
    let m = (b & FRAC) | (1 << 52);
    // k < 0 shifts the 53-bit significand out entirely (a shift of 63 leaves 0).
    let shifted = if k <= 52 {
        m >> (52 - k).min(63)
    } else {
        m << (k - 52).min(63)
    };
    let max = u64::MAX.checked_shr(64 - n).unwrap_or(0);
    let sat = if k >= n as i64 { max } else { shifted };
    let zero = (b & SIGN != 0) | ((b & !SIGN) > POS_INF_BITS);
    if zero {
        0
    } else {
        sat
    }
}

/// Multiply a binary64 by `2^s` with an 11-bit exponent adder (exact: no rounding happens).
///
/// Zeros, infinities and NaN pass unchanged (as the multiply would give). The unit applies
/// it only to square roots of squared diagonals (or of their ratio to the frame diagonal),
/// which are normal numbers far from both ends of the exponent range (their magnitude lies
/// in `[1e-201, 1e85]` for any finite `f32` boxes), so no subnormal or overflow path exists;
/// [`exp_add`] falls back to the plain product there so that the model never lies.
#[inline(always)]
pub fn exp_add(x: f64, s: u32) -> f64 {
    let b = x.to_bits();
    let e = (b >> 52) & EXP_MASK;
    if e == 0 || e == EXP_MASK {
        // zero, subnormal (unreachable, see above), inf, NaN
        return if e == 0 && (b & FRAC) != 0 {
            x * f64::from_bits(((1023 + s as u64) & EXP_MASK) << 52)
        } else {
            x
        };
    }
    if e + s as u64 >= EXP_MASK {
        return x * f64::from_bits(((1023 + s as u64) & EXP_MASK) << 52);
    }
    f64::from_bits(b + ((s as u64) << 52))
}

/// The comparator key of a squared diagonal: its bit pattern when it is a non-negative number
/// (there the unsigned order of patterns equals the numeric order), else 0 (NaN and negative
/// values reach no threshold, as the float comparison `T <= d2` would decide for `T > 0`).
#[inline(always)]
pub fn compare_key(d2: f64) -> u64 {
    let b = d2.to_bits();
    if b > POS_INF_BITS {
        0
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edge_values() -> Vec<f64> {
        let mut v = vec![
            0.0,
            -0.0,
            0.5,
            0.999_999_999_999_999_9,
            1.0,
            1.5,
            2.0,
            3.999_999,
            f64::MIN_POSITIVE,
            5e-324,
            -5e-324,
            -1.0,
            -0.5,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
            f64::MAX,
            1e30,
            1e-30,
            4503599627370495.5,
            4503599627370496.0,
            9007199254740993.0,
            18446744073709551615.0,
            18446744073709551616.0,
        ];
        for k in 0..70 {
            let p = 2f64.powi(k);
            v.extend([
                p,
                p - 1.0,
                p + 1.0,
                p * 0.75,
                p * 1.5,
                -p,
                p.next_down(),
                p.next_up(),
            ]);
        }
        v
    }

    #[test]
    fn float_to_fixed_equals_rust_cast_with_clamp() {
        for &x in &edge_values() {
            for n in 1..=64u32 {
                let max = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
                assert_eq!(float_to_fixed(x, n), (x as u64).min(max), "x={x:e} n={n}");
            }
        }
    }

    #[test]
    fn exp_add_equals_multiply() {
        for &x in &edge_values() {
            for s in 0..=32u32 {
                let want = x * 2f64.powi(s as i32);
                let got = exp_add(x, s);
                assert!(
                    got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                    "x={x:e} s={s}"
                );
            }
        }
    }

    #[test]
    fn compare_key_orders_like_floats() {
        let v = edge_values();
        for &a in &v {
            for &t in &v {
                if t.is_sign_negative() || t.is_nan() || t == 0.0 {
                    continue; // thresholds are positive
                }
                assert_eq!(t.to_bits() <= compare_key(a), t <= a, "t={t:e} a={a:e}");
            }
        }
    }
}
