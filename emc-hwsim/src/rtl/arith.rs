//! The arithmetic blocks the emitted unit instantiates, written in the netlist language of
//! [`super::net`]: the 3-stage fp64 adder and multiplier, and the pipelined fp64 divider and
//! square root (digit recurrences unrolled over a stage count). Each signal is one wire, so
//! the mutation test can swap any single one, and each block is emitted only when the
//! configuration uses it; the same calls give the cost model its gates.
//!
//! Their domain is the unit's: finite operands whose exact results are normal doubles or zero.
//! The sign of a zero never reaches a code (float→fixed maps ±0 to 0, squares and sums of
//! squares are non-negative), so zeros are produced as +0; the divider and the square root
//! only ever see non-negative operands, so their results carry no sign logic either.
//! Every value the datapath forms from finite `f32` boxes lies there (sums, differences,
//! products and roots of `f32`-range values stay within 2^-300..2^270); subnormal operands are
//! read as zero and nothing rounds to a subnormal, as the module docs of [`crate::fixed`]
//! argue for the exponent adder.
#![forbid(unsafe_code)]

use super::net::{cat, eq, gt, mux, ne, red_or, shl, shr, Mod, Sig, E};

fn k(w: u32, v: u128) -> Sig {
    Sig::k(w, v)
}

/// The 3-stage fp64 adder/subtractor `y = a ± b`, round to nearest even (module
/// `emc_fp64_add`, ports `a`, `b`, `sub`, `y`).
///
/// Stage 1 swaps by magnitude and aligns the smaller significand with guard, round and sticky
/// bits; stage 2 adds or subtracts and counts leading zeros; stage 3 normalises and rounds.
pub fn fp64_add(m: &mut Mod) {
    m.comment(
        "emc_fp64_add: y = a + b (sub = 0) or a - b (sub = 1), round to nearest even, 3 stages.",
    );
    m.clock();
    let a = m.input("a", 64);
    let b = m.input("b", 64);
    let sub = m.input("sub", 1);
    let sa = m.wire("sa", 1, a.bit(63));
    let sb = m.wire("sb", 1, &b.bit(63) ^ &sub);
    let ea = m.wire("ea", 11, a.at(62, 52));
    let eb = m.wire("eb", 11, b.at(62, 52));
    let za = m.wire("za", 1, eq(&ea, k(11, 0)));
    let zb = m.wire("zb", 1, eq(&eb, k(11, 0)));
    let ma = m.wire(
        "ma",
        53,
        mux(&za, k(53, 0), Sig::cat(&[k(1, 1), a.at(51, 0)])),
    );
    let mb = m.wire(
        "mb",
        53,
        mux(&zb, k(53, 0), Sig::cat(&[k(1, 1), b.at(51, 0)])),
    );
    let swap = m.wire(
        "swap",
        1,
        gt(
            Sig::cat(&[eb.clone(), mb.clone()]),
            Sig::cat(&[ea.clone(), ma.clone()]),
        ),
    );
    let el = m.wire("el", 11, mux(&swap, &eb, &ea));
    let es = m.wire("es", 11, mux(&swap, &ea, &eb));
    let ml = m.wire("ml", 53, mux(&swap, &mb, &ma));
    let ms = m.wire("ms", 53, mux(&swap, &ma, &mb));
    let sl = m.wire("sl", 1, mux(&swap, &sb, &sa));
    let d = m.wire("d", 11, &el - &es);
    let msx = m.wire("msx", 56, Sig::cat(&[ms, k(3, 0)]));
    let far = m.wire("far", 1, gt(&d, k(11, 55)));
    let msh = m.wire("msh", 56, mux(&far, k(56, 0), shr(&msx, &d)));
    let lost = m.wire(
        "lost",
        56,
        mux(&far, Sig::fill(56, true), shl(k(56, 1), &d) - k(56, 1)),
    );
    let stk = m.wire("stk", 1, red_or(&msx & &lost));
    let msa = m.wire(
        "msa",
        56,
        cat(vec![msh.at(55, 1).into(), &msh.bit(0) | &stk]),
    );
    let eff = m.wire("eff", 1, &sa ^ &sb);
    let bz = m.wire("bz", 1, &za & &zb);
    let s1_sl = m.reg("s1_sl", 1, &sl);
    let s1_eff = m.reg("s1_eff", 1, &eff);
    let s1_bz = m.reg("s1_bz", 1, &bz);
    let s1_el = m.reg("s1_el", 11, &el);
    let s1_ml = m.reg("s1_ml", 53, &ml);
    let s1_ms = m.reg("s1_ms", 56, &msa);
    let mlx = m.wire("mlx", 57, Sig::cat(&[k(1, 0), s1_ml, k(3, 0)]));
    let msx2 = m.wire("msx2", 57, Sig::cat(&[k(1, 0), s1_ms]));
    let sum = m.wire("sum", 57, mux(&s1_eff, &mlx - &msx2, &mlx + &msx2));
    // Leading-zero count of the 57-bit sum as one priority chain of wires. Bits 1 and 0 never
    // lead: they are non-zero only when the smaller operand was shifted by d >= 2, and then
    // the difference keeps its leading one at bit 54 or above (a zero sum is flagged apart).
    let mut lz = m.wire("lz57", 7, k(7, 57));
    for i in 2..57u32 {
        lz = m.wire(
            &format!("lz{i}"),
            7,
            mux(sum.bit(i), k(7, 56 - i as u128), &lz),
        );
    }
    let s2_sl = m.reg("s2_sl", 1, &s1_sl);
    let s2_bz = m.reg("s2_bz", 1, &s1_bz);
    let s2_el = m.reg("s2_el", 11, &s1_el);
    let s2_sum = m.reg("s2_sum", 57, &sum);
    let s2_lz = m.reg("s2_lz", 7, &lz);
    let nsh = m.wire("nsh", 56, shl(s2_sum.at(55, 0), &s2_lz - k(7, 1)));
    let nrm = m.wire(
        "nrm",
        56,
        mux(
            eq(&s2_lz, k(7, 0)),
            cat(vec![
                s2_sum.at(56, 2).into(),
                &s2_sum.bit(1) | &s2_sum.bit(0),
            ]),
            &nsh,
        ),
    );
    let ex = m.wire(
        "ex",
        13,
        E::from(Sig::cat(&[k(2, 0), s2_el])) + k(13, 1) - Sig::cat(&[k(6, 0), s2_lz]),
    );
    let mt = m.wire("mt", 53, nrm.at(55, 3));
    let up = m.wire(
        "up",
        1,
        &nrm.bit(2) & (&nrm.bit(1) | &nrm.bit(0) | mt.bit(0)),
    );
    let mr = m.wire(
        "mr",
        54,
        E::from(Sig::cat(&[k(1, 0), mt])) + Sig::cat(&[k(53, 0), up]),
    );
    let ex2 = m.wire("ex2", 13, &ex + Sig::cat(&[k(12, 0), mr.bit(53)]));
    let fr = m.wire("fr", 52, mux(mr.bit(53), mr.at(52, 1), mr.at(51, 0)));
    let zero = m.wire("zero", 1, eq(&s2_sum, k(57, 0)));
    let res = m.wire(
        "res",
        64,
        mux(
            &s2_bz | &zero,
            k(64, 0),
            Sig::cat(&[s2_sl, ex2.at(10, 0), fr]),
        ),
    );
    let s3 = m.reg("s3", 64, &res);
    m.output("y", 64, &s3);
}

/// The 3-stage fp64 multiplier `y = a × b`, round to nearest even (module `emc_fp64_mul`):
/// stage 1 forms two 53×27 partial products, stage 2 adds them, stage 3 normalises and
/// rounds.
pub fn fp64_mul(m: &mut Mod) {
    m.comment("emc_fp64_mul: y = a * b, round to nearest even, 3 stages.");
    m.clock();
    let a = m.input("a", 64);
    let b = m.input("b", 64);
    let za = m.wire("za", 1, eq(a.at(62, 52), k(11, 0)));
    let zb = m.wire("zb", 1, eq(b.at(62, 52), k(11, 0)));
    let ma = m.wire("ma", 53, Sig::cat(&[k(1, 1), a.at(51, 0)]));
    let mb = m.wire("mb", 53, Sig::cat(&[k(1, 1), b.at(51, 0)]));
    let plo = m.wire("plo", 80, &ma * mb.at(26, 0));
    let phi = m.wire("phi", 79, &ma * mb.at(52, 27));
    let es = m.wire(
        "es",
        13,
        E::from(Sig::cat(&[k(2, 0), a.at(62, 52)])) + Sig::cat(&[k(2, 0), b.at(62, 52)]),
    );
    let sg = m.wire("sg", 1, &a.bit(63) ^ &b.bit(63));
    let z = m.wire("z", 1, &za | &zb);
    let s1_lo = m.reg("s1_lo", 80, &plo);
    let s1_hi = m.reg("s1_hi", 79, &phi);
    let s1_es = m.reg("s1_es", 13, &es);
    let s1_s = m.reg("s1_s", 1, &sg);
    let s1_z = m.reg("s1_z", 1, &z);
    let p = m.wire(
        "p",
        106,
        E::from(Sig::cat(&[k(26, 0), s1_lo])) + Sig::cat(&[s1_hi, k(27, 0)]),
    );
    let s2_p = m.reg("s2_p", 106, &p);
    let s2_es = m.reg("s2_es", 13, &s1_es);
    let s2_s = m.reg("s2_s", 1, &s1_s);
    let s2_z = m.reg("s2_z", 1, &s1_z);
    let hi = m.wire("hi", 1, s2_p.bit(105));
    let mt = m.wire("mt", 53, mux(&hi, s2_p.at(105, 53), s2_p.at(104, 52)));
    let g = m.wire("g", 1, mux(&hi, s2_p.bit(52), s2_p.bit(51)));
    let st = m.wire(
        "st",
        1,
        mux(&hi, red_or(s2_p.at(51, 0)), red_or(s2_p.at(50, 0))),
    );
    let up = m.wire("up", 1, &g & (&st | mt.bit(0)));
    let mr = m.wire(
        "mr",
        54,
        E::from(Sig::cat(&[k(1, 0), mt])) + Sig::cat(&[k(53, 0), up]),
    );
    let ex = m.wire(
        "ex",
        13,
        E::from(&s2_es) - k(13, 1023)
            + Sig::cat(&[k(12, 0), hi])
            + Sig::cat(&[k(12, 0), mr.bit(53)]),
    );
    let fr = m.wire("fr", 52, mux(mr.bit(53), mr.at(52, 1), mr.at(51, 0)));
    let res = m.wire(
        "res",
        64,
        mux(&s2_z, k(64, 0), Sig::cat(&[s2_s, ex.at(10, 0), fr])),
    );
    let s3 = m.reg("s3", 64, &res);
    m.output("y", 64, &s3);
}

/// Which iterations of an `n`-step recurrence stage `s` of `stages` performs.
pub fn stage_range(n: usize, stages: usize, s: usize) -> core::ops::Range<usize> {
    n * s / stages..n * (s + 1) / stages
}

/// Register copies of the carried signals at a stage boundary.
fn boundary(m: &mut Mod, stage: usize, carried: &[Sig], names: &[&str]) -> Vec<Sig> {
    carried
        .iter()
        .zip(names)
        .map(|(s, n)| m.reg(&format!("{n}_r{stage}"), s.w(), s))
        .collect()
}

/// The final rounding of a 53-bit significand with guard and sticky, shared by the divider and
/// the square root: returns `res` from `sp` (0 normal, 1 zero, 2 infinity, 3 NaN).
fn round_tail(m: &mut Mod, mt: &Sig, g: &Sig, st: &Sig, ex: &Sig, sp: &Sig) -> Sig {
    let up = m.wire("up", 1, g & (st | mt.bit(0)));
    let mr = m.wire(
        "mr",
        54,
        E::from(Sig::cat(&[k(1, 0), mt.clone()])) + Sig::cat(&[k(53, 0), up]),
    );
    let exf = m.wire("exf", 13, ex + Sig::cat(&[k(12, 0), mr.bit(53)]));
    let fr = m.wire("fr", 52, mux(mr.bit(53), mr.at(52, 1), mr.at(51, 0)));
    m.wire(
        "res",
        64,
        mux(
            eq(sp, k(3, 1)),
            k(64, 0),
            mux(
                eq(sp, k(3, 2)),
                k(64, 0x7ff0_0000_0000_0000),
                mux(
                    eq(sp, k(3, 3)),
                    k(64, 0x7ff8_0000_0000_0000),
                    Sig::cat(&[k(1, 0), exf.at(10, 0), fr]),
                ),
            ),
        ),
    )
}

/// The fp64 divider `y = a / b` over `stages` pipeline registers (module `emc_fp64_div`): a
/// restoring division of the significands producing 55 quotient bits (one a stage-local wire
/// each) and a sticky remainder, then round to nearest even. `b = 0` gives +infinity (NaN
/// for `0/0`).
pub fn fp64_div(m: &mut Mod, stages: usize) {
    m.comment(&format!(
        "emc_fp64_div: y = a / b, round to nearest even, {stages} stages (restoring, 55 quotient bits)."
    ));
    m.clock();
    let a = m.input("a", 64);
    let b = m.input("b", 64);
    let za = m.wire("za", 1, eq(a.at(62, 52), k(11, 0)));
    let zb = m.wire("zb", 1, eq(b.at(62, 52), k(11, 0)));
    let mut r = m.wire("r0", 55, Sig::cat(&[k(3, 1), a.at(51, 0)]));
    let mut dv = m.wire("dv", 53, Sig::cat(&[k(1, 1), b.at(51, 0)]));
    let mut ex = m.wire(
        "ex",
        13,
        E::from(Sig::cat(&[k(2, 0), a.at(62, 52)])) - Sig::cat(&[k(2, 0), b.at(62, 52)])
            + k(13, 1023),
    );
    let mut sp = m.wire(
        "sp",
        3,
        mux(&zb, mux(&za, k(3, 3), k(3, 2)), mux(&za, k(3, 1), k(3, 0))),
    );
    let mut q = m.wire("q0", 55, k(55, 0));
    let n = 55;
    for st in 0..stages {
        for i in stage_range(n, stages, st) {
            // One subtractor gives both the trial remainder and, by its borrow, the digit.
            let df = m.wire(
                &format!("df{i}"),
                56,
                E::from(Sig::cat(&[k(1, 0), r.clone()])) - Sig::cat(&[k(3, 0), dv.clone()]),
            );
            let gei = m.wire(&format!("ge{i}"), 1, !&df.bit(55));
            let rs = m.wire(&format!("rs{i}"), 55, mux(&gei, df.at(54, 0), &r));
            r = m.wire(
                &format!("r{}", i + 1),
                55,
                Sig::cat(&[rs.at(53, 0), k(1, 0)]),
            );
            q = m.wire(&format!("q{}", i + 1), 55, Sig::cat(&[q.at(53, 0), gei]));
        }
        if st + 1 < stages {
            let rn = format!("r{}", stage_range(n, stages, st).end);
            let qn = format!("q{}", stage_range(n, stages, st).end);
            let v = boundary(
                m,
                st + 1,
                &[r, q, dv, ex, sp],
                &[&rn, &qn, "dv", "ex", "sp"],
            );
            (r, q, dv, ex, sp) = (
                v[0].clone(),
                v[1].clone(),
                v[2].clone(),
                v[3].clone(),
                v[4].clone(),
            );
        }
    }
    let _ = dv;
    let hi = m.wire("hi", 1, q.bit(54));
    let mt = m.wire("mt", 53, mux(&hi, q.at(54, 2), q.at(53, 1)));
    let g = m.wire("g", 1, mux(&hi, q.bit(1), q.bit(0)));
    let stk = m.wire("st", 1, (&hi & q.bit(0)) | ne(&r, k(55, 0)));
    let exn = m.wire("exn", 13, &ex - cat(vec![k(12, 0).into(), !&hi]));
    let res = round_tail(m, &mt, &g, &stk, &exn, &sp);
    let yo = m.reg("yo", 64, &res);
    m.output("y", 64, &yo);
}

/// The fp64 square root over `stages` pipeline registers (module `emc_fp64_sqrt`): the
/// bit-pair restoring recurrence on the significand (made even-exponent) shifted by 56, giving
/// a 55-bit root and a sticky remainder, then round to nearest even. Zero gives +0; infinity
/// and NaN pass.
pub fn fp64_sqrt(m: &mut Mod, stages: usize) {
    m.comment(&format!(
        "emc_fp64_sqrt: y = sqrt(x), round to nearest even, {stages} stages (restoring, 55 root bits)."
    ));
    m.clock();
    let x = m.input("x", 64);
    let e = m.wire("e", 11, x.at(62, 52));
    let mut rx = m.wire(
        "rx",
        54,
        mux(
            e.bit(0),
            Sig::cat(&[k(2, 1), x.at(51, 0)]),
            Sig::cat(&[k(1, 1), x.at(51, 0), k(1, 0)]),
        ),
    );
    let mut ex = m.wire(
        "ex",
        13,
        shr(
            E::from(Sig::cat(&[k(2, 0), e.clone()])) + k(13, 1023),
            k(1, 1),
        ),
    );
    let mut sp = m.wire(
        "sp",
        3,
        mux(
            eq(&e, k(11, 0)),
            k(3, 1),
            mux(eq(&e, k(11, 0x7ff)), k(3, 4), k(3, 0)),
        ),
    );
    let mut xp = m.wire("xp", 64, &x);
    let mut rm = m.wire("m0", 59, k(59, 0));
    let mut t = m.wire("t0", 55, k(55, 0));
    let n = 55;
    for st in 0..stages {
        for i in stage_range(n, stages, st) {
            // Pairs of the radicand rx << 56, MSB first: rx's 27 pairs, then zeros.
            let pair = if i < 27 {
                rx.at(53 - 2 * i as u32, 52 - 2 * i as u32)
            } else {
                k(2, 0)
            };
            let rp = m.wire(&format!("rp{i}"), 59, Sig::cat(&[rm.at(56, 0), pair]));
            let tr = m.wire(
                &format!("tr{i}"),
                59,
                Sig::cat(&[k(2, 0), t.clone(), k(2, 1)]),
            );
            let df = m.wire(
                &format!("df{i}"),
                60,
                E::from(Sig::cat(&[k(1, 0), rp.clone()])) - Sig::cat(&[k(1, 0), tr]),
            );
            let gei = m.wire(&format!("ge{i}"), 1, !&df.bit(59));
            rm = m.wire(&format!("m{}", i + 1), 59, mux(&gei, df.at(58, 0), &rp));
            t = m.wire(&format!("t{}", i + 1), 55, Sig::cat(&[t.at(53, 0), gei]));
        }
        if st + 1 < stages {
            let end = stage_range(n, stages, st).end;
            let (mn, tn) = (format!("m{end}"), format!("t{end}"));
            let v = boundary(
                m,
                st + 1,
                &[rm, t, rx, ex, sp, xp],
                &[&mn, &tn, "rx", "ex", "sp", "xp"],
            );
            (rm, t, rx, ex, sp, xp) = (
                v[0].clone(),
                v[1].clone(),
                v[2].clone(),
                v[3].clone(),
                v[4].clone(),
                v[5].clone(),
            );
        }
    }
    let _ = rx;
    let mt = m.wire("mt", 53, t.at(54, 2));
    let g = m.wire("g", 1, t.bit(1));
    let stk = m.wire("st", 1, &t.bit(0) | ne(&rm, k(59, 0)));
    let res = round_tail(m, &mt, &g, &stk, &ex, &sp);
    let resp = m.wire("resp", 64, mux(eq(&sp, k(3, 4)), &xp, &res));
    let yo = m.reg("yo", 64, &resp);
    m.output("y", 64, &yo);
}
