//! The unit's blocks, each described once: a struct per pipeline stage implementing
//! [`Block`] — its bit-level behaviour on a token ([`Block::eval`], what the model computes),
//! its Verilog ([`Block::emit`], written in [`crate::rtl::net`], whose gate expansion is what the
//! cost model prices) and the configuration words it owns ([`Block::config`]). The model's
//! datapath ([`crate::Unit::code`], the fast and the cycle-stepped modes), the emitter
//! ([`crate::rtl::emit`]), the register image ([`crate::rtl::image`]) and the cost model
//! ([`crate::cost::cost`]) all walk the same list, [`crate::Unit::stages`].
#![forbid(unsafe_code)]
// Per-axis registers and names are parallel arrays indexed by the axis number.
#![allow(clippy::needless_range_loop)]

use core::fmt;
use std::collections::HashMap;

use emc_core::SizeTransform;

use crate::datapath::{Token, FP_LATENCY};
use crate::fixed::{compare_key, exp_add, float_to_fixed};
use crate::routing::{morton_wires, permute, Benes, Crossbar, Permutation};
use crate::rtl::arith;
use crate::rtl::net::{cat, eq, gt, le, mux, pick, shl, shr, Mod, Sig, E};
use crate::rtl::ImageWord;

/// Axis letters of names.
pub const AX: [char; 3] = ['x', 'y', 'z'];

/// The floating-point work of a block per code (for the energy model).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FpOps {
    /// fp64 additions and subtractions.
    pub add: u32,
    /// fp64 multiplications.
    pub mul: u32,
    /// fp64 square roots and divisions.
    pub sqrt_div: u32,
}

/// One pipeline stage of the unit, described once for the model, the Verilog and the
/// configuration.
pub trait Block: fmt::Debug + Send + Sync {
    /// Stage name in printouts.
    fn name(&self) -> &'static str;
    /// Cycles from entry to result.
    fn latency(&self) -> u32;
    /// Initiation interval.
    fn ii(&self) -> u32 {
        1
    }
    /// The hardware it instantiates, for the structure printout.
    fn hw(&self) -> String;
    /// The model's behaviour: the stage's operation on a token, bit for bit what the
    /// Verilog of [`Block::emit`] computes.
    fn eval(&self, t: &mut Token);
    /// [`Block::eval`] over a slice of tokens (the fast mode runs the stages across a block
    /// of boxes).
    fn eval_all(&self, ts: &mut [Token]) {
        for t in ts {
            self.eval(t);
        }
    }
    /// The stage's Verilog: reads the token's signals from `s` as they stand at the stage's
    /// entry cycle and writes the ones it produces (with the cycle they are ready).
    fn emit(&self, m: &mut Mod, s: &mut Signals);
    /// The configuration words the stage owns (in configuration-bus order).
    fn config(&self) -> Vec<ImageWord> {
        Vec::new()
    }
    /// Floating-point operations per code.
    fn fp_ops(&self) -> FpOps {
        FpOps::default()
    }
}

/// A token field in the Verilog.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Field {
    /// `lo[a]` (binary32).
    Lo(usize),
    /// `hi[a]` (binary32).
    Hi(usize),
    /// The position lane of axis `a` (binary64, then the fixed-point value).
    Pos(usize),
    /// The size lane's per-axis value (Δ, then Δ²).
    Dl(usize),
    /// `Δx² + Δy²`.
    Acc,
    /// `d²`.
    D2,
    /// The size value in the formula path (binary64).
    Sd,
    /// The quantised size.
    Qs,
    /// The routing word (then the code).
    Word,
}

/// The Verilog signals of a token: each field with the cycle its signal holds the token's
/// value; reading a field at a later cycle inserts the balancing registers.
#[derive(Debug, Default)]
pub struct Signals {
    now: u32,
    fields: HashMap<Field, (Sig, u32)>,
    cfg: HashMap<String, Sig>,
    /// For a block written alone: the widths of what it may read, which become inputs.
    alone: Option<(u32, HashMap<String, u32>)>,
}

impl Signals {
    /// Signals at cycle 0 with the unit's inputs and configuration registers by name.
    pub fn new(cfg: HashMap<String, Sig>) -> Signals {
        Signals {
            now: 0,
            fields: HashMap::new(),
            cfg,
            alone: None,
        }
    }

    /// Signals of a block written alone: every field or configuration register it reads is an
    /// input of the module (driven, in the model, by a register). `qs_bits` is the width of
    /// the quantised size; `cfg` the widths of configuration words.
    pub fn alone(qs_bits: u32, cfg: HashMap<String, u32>) -> Signals {
        Signals {
            alone: Some((qs_bits, cfg)),
            ..Signals::default()
        }
    }

    /// The current stage's entry cycle.
    pub fn now(&self) -> u32 {
        self.now
    }

    /// Advance to the next stage.
    pub fn advance(&mut self, cycles: u32) {
        self.now += cycles;
    }

    /// A configuration register or unit input by name.
    pub fn cfg(&mut self, m: &mut Mod, name: &str) -> Sig {
        if let Some(s) = self.cfg.get(name) {
            return s.clone();
        }
        let w = match &self.alone {
            Some((_, widths)) => widths.get(name).copied().unwrap_or(match name {
                "in_box" => 192,
                n if n.starts_with("nbits_") || n.starts_with("off_") => 7,
                _ => 64,
            }),
            None => panic!("no configuration signal {name}"),
        };
        let s = m.input(name, w);
        self.cfg.insert(name.to_string(), s.clone());
        s
    }

    /// Declare a derived configuration signal.
    pub fn set_cfg(&mut self, name: &str, s: Sig) {
        self.cfg.insert(name.to_string(), s);
    }

    /// Field `f` as it stands at the current cycle (delayed by registers if produced earlier).
    pub fn get(&mut self, m: &mut Mod, f: Field) -> Sig {
        if !self.fields.contains_key(&f) {
            if let Some((qs, _)) = &self.alone {
                let (name, w) = match f {
                    Field::Lo(a) => (format!("lo_{}", AX[a]), 32),
                    Field::Hi(a) => (format!("hi_{}", AX[a]), 32),
                    Field::Pos(a) => (format!("pos_{}", AX[a]), 64),
                    Field::Dl(a) => (format!("dl_{}", AX[a]), 64),
                    Field::Acc => ("acc".into(), 64),
                    Field::D2 => ("d2".into(), 64),
                    Field::Sd => ("sd".into(), 64),
                    Field::Qs => ("qs".into(), *qs),
                    Field::Word => ("word".into(), 64),
                };
                let sig = m.input(&format!("in_{name}"), w);
                self.fields.insert(f, (sig, self.now));
            }
        }
        let (mut sig, at) = self
            .fields
            .get(&f)
            .unwrap_or_else(|| panic!("field {f:?} read before it is written"))
            .clone();
        assert!(at <= self.now, "field {f:?} read before its cycle");
        for _ in at..self.now {
            let n = format!("dly{}", m.uid());
            sig = m.reg(&n, sig.w(), &sig);
        }
        self.fields.insert(f, (sig.clone(), self.now));
        sig
    }

    /// Field `f` is `s`, ready `after` cycles after the stage's entry.
    pub fn put(&mut self, f: Field, s: Sig, after: u32) {
        self.fields.insert(f, (s, self.now + after));
    }

    /// Whether field `f` has been written.
    pub fn has(&self, f: Field) -> bool {
        self.fields.contains_key(&f)
    }

    /// Every field written, as module outputs (a block written alone).
    fn outputs(&mut self, m: &mut Mod) {
        let mut fs: Vec<(Field, Sig, u32)> = self
            .fields
            .iter()
            .map(|(f, (s, a))| (*f, s.clone(), *a))
            .collect();
        fs.sort_by_key(|x| format!("{:?}", x.0));
        for (f, s, _) in fs {
            let n = format!("{f:?}").to_lowercase().replace(['(', ')'], "");
            m.output(&format!("out_{n}"), s.w(), &s);
        }
    }
}

/// A block written alone as a module (what it reads are inputs, what it writes outputs),
/// for pricing it on its own; `qs_bits` is the quantised size's width.
pub fn alone(b: &dyn Block, qs_bits: u32) -> Mod {
    let mut m = Mod::new(&format!(
        "stage_{}",
        b.name().replace(['.', '→', '^', '×'], "_")
    ));
    let widths = b.config().into_iter().map(|w| (w.name, w.width)).collect();
    let mut s = Signals::alone(qs_bits.max(1), widths);
    b.emit(&mut m, &mut s);
    s.advance(b.latency());
    s.outputs(&mut m);
    m
}

fn k(w: u32, v: u128) -> Sig {
    Sig::k(w, v)
}

/// binary32 → binary64, exact (module `emc_f32_to_f64`): subnormal inputs are normalised by a
/// leading-zero count written as a log-depth tree (each node of the 32-bit word: any one below
/// it, and its count, the upper half's when that has a one, else the lower half's with the
/// half's weight added) and a logarithmic shifter; the unit's inputs are finite, so there is
/// no infinity/NaN path.
pub fn f32_to_f64(m: &mut Mod) {
    m.comment("emc_f32_to_f64: exact binary32 -> binary64 of a finite value.");
    let f = m.input("f", 32);
    let e = m.wire("e", 8, f.at(30, 23));
    let mm = m.wire("m", 23, f.at(22, 0));
    let x = m.wire("x", 32, Sig::cat(&[k(9, 0), mm.clone()]));
    // Level l: 32 >> l nodes, node i covering bits [i 2^l, (i + 1) 2^l); `any` has one bit
    // per node, `cnt` l bits per node (the node's leading zeros).
    let mut any = x.clone();
    let mut cnt: Option<Sig> = None;
    for l in 1..=5u32 {
        let nodes = 32 >> l;
        let mut a_parts = Vec::new();
        let mut c_parts = Vec::new();
        for i in (0..nodes).rev() {
            let (hi, lo) = (2 * i + 1, 2 * i);
            let a_hi = any.bit(hi);
            a_parts.push(E::from(&a_hi) | any.bit(lo));
            c_parts.push(match &cnt {
                None => !&a_hi,
                Some(c) => {
                    let w = l - 1;
                    let c_hi = c.at(hi * w + w - 1, hi * w);
                    let c_lo = c.at(lo * w + w - 1, lo * w);
                    mux(
                        &a_hi,
                        Sig::cat(&[k(1, 0), c_hi]),
                        Sig::cat(&[k(1, 1), c_lo]),
                    )
                }
            });
        }
        any = m.wire(&format!("any{l}"), nodes, cat(a_parts));
        cnt = Some(m.wire(&format!("cnt{l}"), nodes * l, cat(c_parts)));
    }
    let lzc = cnt.expect("five levels");
    let sh = m.wire("sh", 32, shl(&x, &lzc));
    let ms = m.wire("ms", 23, sh.at(30, 8));
    let lead = m.wire("lead", 5, !&lzc);
    let se = m.wire("se", 11, E::from(Sig::cat(&[k(6, 0), lead])) + k(11, 874));
    let ne = m.wire(
        "ne",
        11,
        E::from(Sig::cat(&[k(3, 0), e.clone()])) + k(11, 896),
    );
    let y = m.wire(
        "d",
        64,
        mux(
            eq(&e, k(8, 0)),
            mux(
                eq(&mm, k(23, 0)),
                Sig::cat(&[f.bit(31), k(63, 0)]),
                Sig::cat(&[f.bit(31), se, ms, k(29, 0)]),
            ),
            Sig::cat(&[f.bit(31), ne, mm, k(29, 0)]),
        ),
    );
    m.output("y", 64, &y);
}

/// Float→fixed with clamp to `n` bits (module `emc_f2fix`, or `emc_f2fix_nan` with the
/// NaN → 0 rule, which only the size formula needs: `0 / D` with `D = 0`), as
/// [`crate::fixed::float_to_fixed`].
pub fn f2fix(m: &mut Mod, nan: bool) {
    m.comment("float -> fixed: truncate toward zero, clamp to n bits (n = 1..64).");
    let v = m.input("v", 64);
    let n = m.input("n", 7);
    let kk = m.wire(
        "k",
        13,
        E::from(Sig::cat(&[k(2, 0), v.at(62, 52)])) - k(13, 1023),
    );
    let mm = m.wire("m", 64, Sig::cat(&[k(11, 0), k(1, 1), v.at(51, 0)]));
    let max = m.wire(
        "max",
        64,
        mux(
            eq(&n, k(7, 64)),
            Sig::fill(64, true),
            shl(k(64, 1), &n) - k(64, 1),
        ),
    );
    let sh = m.wire(
        "sh",
        64,
        mux(
            le(&kk, k(13, 52)),
            shr(&mm, k(13, 52) - &kk),
            shl(&mm, &kk - k(13, 52)),
        ),
    );
    let z = m.wire(
        "z",
        1,
        if nan {
            E::from(v.bit(63)) | gt(v.at(62, 0), k(63, 0x7ff0_0000_0000_0000)) | kk.bit(12)
        } else {
            &v.bit(63) | &kk.bit(12)
        },
    );
    let q = m.wire(
        "q",
        64,
        mux(
            &z,
            k(64, 0),
            mux(
                E::Ge(
                    Box::new((&kk).into()),
                    Box::new(Sig::cat(&[k(6, 0), n.clone()]).into()),
                ),
                &max,
                &sh,
            ),
        ),
    );
    m.output("y", 64, &q);
}

/// The comparator key of `d²`: its pattern when a non-negative number, else 0.
fn key(m: &mut Mod, d2: &Sig) -> Sig {
    m.wire(
        "key0",
        63,
        mux(
            E::from(d2.bit(63)) | gt(d2.at(62, 0), k(63, 0x7ff0_0000_0000_0000)),
            k(63, 0),
            d2.at(62, 0),
        ),
    )
}

/// The `S`-step binary threshold search (module `emc_search`, one register level per step):
/// step `k` compares the key with the threshold at index `{decided bits, 1, 0…}`, chosen from
/// the `2^k` candidates by a multiplexer tree on the decided bits.
pub fn search(m: &mut Mod, sbits: u32) {
    m.comment(&format!(
        "emc_search: {sbits}-step binary search over the size thresholds."
    ));
    m.clock();
    let d2 = m.input("d2", 64);
    let t = (1u32 << sbits) - 1;
    let thr: Vec<Sig> = (1..=t).map(|i| m.input(&format!("thr{i}"), 63)).collect();
    let mut key0 = key(m, &d2);
    let mut spos: Option<Sig> = None;
    for st in 0..sbits {
        let low = sbits - 1 - st;
        // Candidates in the order of the decided bits' value j: index (2j + 1) << low.
        let mut cands: Vec<Sig> = (0..1u32 << st)
            .map(|j| thr[(((2 * j + 1) << low) - 1) as usize].clone())
            .collect();
        let mut lvl = 0;
        while cands.len() > 1 {
            let s = spos.as_ref().expect("decided bits").bit(lvl);
            cands = cands
                .chunks(2)
                .enumerate()
                .map(|(i, c)| m.wire(&format!("thrsel{st}_{lvl}_{i}"), 63, mux(&s, &c[1], &c[0])))
                .collect();
            lvl += 1;
        }
        let sel = m.wire(&format!("thrsel{st}"), 63, &cands[0]);
        let g = m.wire(&format!("ge{st}"), 1, le(&sel, &key0));
        spos = Some(match &spos {
            None => m.reg("spos1", 1, &g),
            Some(p) => m.reg(
                &format!("spos{}", st + 1),
                st + 1,
                Sig::cat(&[p.clone(), g]),
            ),
        });
        if st + 1 < sbits {
            key0 = m.reg(&format!("key{}", st + 1), 63, &key0);
        }
    }
    m.output("y", sbits, spos.as_ref().expect("S >= 1"));
}

/// The comparator bank and population count (module `emc_bank`, two register levels).
pub fn bank(m: &mut Mod, sbits: u32) {
    m.comment(&format!(
        "emc_bank: {} comparators and a population count.",
        (1u32 << sbits) - 1
    ));
    m.clock();
    let d2 = m.input("d2", 64);
    let t = (1u32 << sbits) - 1;
    let thr: Vec<Sig> = (1..=t).map(|i| m.input(&format!("thr{i}"), 63)).collect();
    let key0 = key(m, &d2);
    let mut bits = Vec::new();
    for i in 1..=t {
        bits.push(m.wire(&format!("bge{i}"), 1, le(&thr[i as usize - 1], &key0)));
    }
    bits.reverse();
    let v = m.reg("bank", t, Sig::cat(&bits));
    let mut sum = E::from(Sig::cat(&[k(sbits, 0), v.bit(0)]));
    for i in 1..t {
        sum = sum + Sig::cat(&[k(sbits, 0), v.bit(i)]);
    }
    let cnt = m.wire("popcnt", sbits + 1, sum);
    let q = m.reg("qsize", sbits, cnt.at(sbits - 1, 0));
    m.output("y", sbits, &q);
}

/// Beneš columns `cols` (module `emc_benes` for the whole network): column `i` exchanges lanes
/// `p` and `p + d` under its control bits, each switch a pair of 2:1 multiplexers.
pub fn benes(m: &mut Mod, b: &Benes, cols: core::ops::Range<usize>) {
    m.comment(&format!(
        "Beneš columns {}..{} of {} ({} lanes).",
        cols.start,
        cols.end,
        b.columns(),
        b.lanes()
    ));
    let mut w = m.input("w", 64);
    let lanes = b.lanes();
    let ctl: Vec<(usize, Sig)> = cols
        .clone()
        .map(|i| (i, m.input(&format!("ctl{i}"), lanes / 2)))
        .collect();
    for (i, c) in ctl {
        let d = b.distance(i);
        // The control of the switch at lower lane p sits at mask bit p (upper lanes 0).
        let mut bits = vec![k(1, 0); 64];
        for (j, p) in crate::rtl::lower_lanes(lanes, d).enumerate() {
            bits[p as usize] = c.bit(j as u32);
        }
        bits.reverse();
        let bm = m.wire(&format!("bm{i}"), 64, Sig::cat(&bits));
        let bh = m.wire(&format!("bh{i}"), 64, shl(&bm, k(7, d as u128)));
        w = m.wire(
            &format!("bw{i}"),
            64,
            (&w & !(&bm | &bh))
                | (shr(&w, k(7, d as u128)) & &bm)
                | (shl(&w, k(7, d as u128)) & &bh),
        );
    }
    m.output("y", 64, &w);
}

/// The crossbar (module `emc_crossbar`): every output lane picks a packed bit by its select.
pub fn crossbar(m: &mut Mod, lanes: u32) {
    m.comment(&format!(
        "emc_crossbar: {lanes}x{lanes}, one select per output lane."
    ));
    let w = m.input("w", 64);
    let sb = crate::rtl::sel_bits(lanes);
    let per = crate::rtl::sels_per_word(lanes);
    let words = lanes.div_ceil(per);
    let sel: Vec<Sig> = (0..words)
        .map(|i| m.input(&format!("sel{i}"), sb * per))
        .collect();
    let mut bits = Vec::new();
    for j in 0..lanes {
        let (wd, kk) = (j / per, j % per);
        let lo = kk * sb;
        let idx = sel[wd as usize].at(lo + sb - 1, lo);
        bits.push(m.wire(&format!("xb{j}"), 1, pick(&w, &idx)));
    }
    bits.reverse();
    if lanes < 64 {
        bits.insert(0, k(64 - lanes, 0));
    }
    let x = m.wire("xbar", 64, Sig::cat(&bits));
    m.output("y", 64, &x);
}

/// Names of the three axes' configuration words.
fn axis_word(prefix: &str, a: usize) -> String {
    format!("{prefix}_{}", AX[a])
}

/// Instantiate a binary32 → binary64 converter.
fn conv(m: &mut Mod, name: &str, f: &Sig) -> Sig {
    m.inst("emc_f32_to_f64", name, &[("f", f)], &f32_to_f64)
        .remove(0)
}

/// Instantiate an fp64 adder (`sub` = subtract).
fn fp_add(m: &mut Mod, y: &str, a: &Sig, b: &Sig, sub: bool) -> Sig {
    m.inst(
        "emc_fp64_add",
        y,
        &[("a", a), ("b", b), ("sub", &k(1, sub as u128))],
        &arith::fp64_add,
    )
    .remove(0)
}

/// Instantiate an fp64 multiplier.
fn fp_mul(m: &mut Mod, y: &str, a: &Sig, b: &Sig) -> Sig {
    m.inst("emc_fp64_mul", y, &[("a", a), ("b", b)], &arith::fp64_mul)
        .remove(0)
}

/// Unpack: the 192-bit input register (only the fields the datapath reads).
#[derive(Clone, Debug)]
pub struct Unpack {
    /// Axes whose `lo`/`hi` fields are read (active axes; all three with a size path).
    pub need: Vec<usize>,
}

impl Block for Unpack {
    fn name(&self) -> &'static str {
        "unpack"
    }
    fn latency(&self) -> u32 {
        1
    }
    fn hw(&self) -> String {
        format!("{}-bit input register", 64 * self.need.len())
    }
    fn eval(&self, _t: &mut Token) {}
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        let inb = s.cfg(m, "in_box");
        for &a in &self.need {
            let lo = m.reg(
                &format!("lo_{}", AX[a]),
                32,
                inb.at(32 * a as u32 + 31, 32 * a as u32),
            );
            let hi = m.reg(
                &format!("hi_{}", AX[a]),
                32,
                inb.at(32 * a as u32 + 127, 32 * a as u32 + 96),
            );
            s.put(Field::Lo(a), lo, 1);
            s.put(Field::Hi(a), hi, 1);
        }
    }
}

/// Centre: `c2 = lo + hi` per active axis ∥ size: `Δ = hi − lo` (binary32 inputs converted
/// exactly to binary64 first).
#[derive(Clone, Debug)]
pub struct Centre {
    /// Axes with position bits.
    pub axis_on: [bool; 3],
    /// Whether the size path exists.
    pub size: bool,
}

impl Block for Centre {
    fn name(&self) -> &'static str {
        "centre"
    }
    fn latency(&self) -> u32 {
        FP_LATENCY
    }
    fn hw(&self) -> String {
        let axes = self.axis_on.iter().filter(|&&o| o).count();
        let conv = 2 * if self.size { 3 } else { axes };
        format!(
            "{conv}× binary32→binary64, {axes}× fp64 add (lo+hi){}",
            if self.size {
                " ∥ size: 3× fp64 sub (hi−lo)"
            } else {
                ""
            }
        )
    }
    fn eval(&self, t: &mut Token) {
        self.eval_all(core::slice::from_mut(t));
    }
    fn eval_all(&self, ts: &mut [Token]) {
        for a in 0..3 {
            if self.axis_on[a] {
                for t in ts.iter_mut() {
                    t.c2[a] = t.lo[a] as f64 + t.hi[a] as f64;
                }
            }
            if self.size {
                for t in ts.iter_mut() {
                    t.dl[a] = t.hi[a] as f64 - t.lo[a] as f64;
                }
            }
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        for a in 0..3 {
            if !(self.axis_on[a] || self.size) {
                continue;
            }
            let lo = s.get(m, Field::Lo(a));
            let hi = s.get(m, Field::Hi(a));
            let l = conv(m, &format!("lo{}_d", AX[a]), &lo);
            let h = conv(m, &format!("hi{}_d", AX[a]), &hi);
            if self.axis_on[a] {
                let c = fp_add(m, &format!("c2_{}", AX[a]), &l, &h, false);
                s.put(Field::Pos(a), c, FP_LATENCY);
            }
            if self.size {
                let d = fp_add(m, &format!("dl_{}", AX[a]), &h, &l, true);
                s.put(Field::Dl(a), d, FP_LATENCY);
            }
        }
    }
    fn fp_ops(&self) -> FpOps {
        FpOps {
            add: self.axis_on.iter().filter(|&&o| o).count() as u32 + 3 * self.size as u32,
            ..FpOps::default()
        }
    }
}

/// Offset: `c2 − 2·origin` ∥ size: `Δ²`.
#[derive(Clone, Debug)]
pub struct Offset {
    /// Axes with position bits.
    pub axis_on: [bool; 3],
    /// Whether the size path exists.
    pub size: bool,
    /// `2·origin` per axis (configuration).
    pub origin2: [f64; 3],
}

impl Block for Offset {
    fn name(&self) -> &'static str {
        "offset"
    }
    fn latency(&self) -> u32 {
        FP_LATENCY
    }
    fn hw(&self) -> String {
        let axes = self.axis_on.iter().filter(|&&o| o).count();
        format!(
            "{axes}× fp64 sub (−2·origin){}",
            if self.size {
                " ∥ size: 3× fp64 mul (Δ²)"
            } else {
                ""
            }
        )
    }
    fn eval(&self, t: &mut Token) {
        self.eval_all(core::slice::from_mut(t));
    }
    fn eval_all(&self, ts: &mut [Token]) {
        for a in 0..3 {
            if self.axis_on[a] {
                let o = self.origin2[a];
                for t in ts.iter_mut() {
                    t.c2[a] -= o;
                }
            }
            if self.size {
                for t in ts.iter_mut() {
                    t.dl[a] *= t.dl[a];
                }
            }
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        for a in 0..3 {
            if self.axis_on[a] {
                let c = s.get(m, Field::Pos(a));
                let o = s.cfg(m, &axis_word("origin2", a));
                let y = fp_add(m, &format!("c2o_{}", AX[a]), &c, &o, true);
                s.put(Field::Pos(a), y, FP_LATENCY);
            }
            if self.size {
                let d = s.get(m, Field::Dl(a));
                let y = fp_mul(m, &format!("sq_{}", AX[a]), &d, &d);
                s.put(Field::Dl(a), y, FP_LATENCY);
            }
        }
    }
    fn config(&self) -> Vec<ImageWord> {
        (0..3)
            .filter(|&a| self.axis_on[a])
            .map(|a| ImageWord {
                name: axis_word("origin2", a),
                width: 64,
                value: self.origin2[a].to_bits(),
            })
            .collect()
    }
    fn fp_ops(&self) -> FpOps {
        FpOps {
            add: self.axis_on.iter().filter(|&&o| o).count() as u32,
            mul: 3 * self.size as u32,
            ..FpOps::default()
        }
    }
}

/// Scale: `× scale/2` ∥ size: `Δx² + Δy²`.
#[derive(Clone, Debug)]
pub struct Scale {
    /// Axes with position bits.
    pub axis_on: [bool; 3],
    /// Whether the size path exists.
    pub size: bool,
    /// `2^n / E / 2` per axis (configuration).
    pub half_scale: [f64; 3],
}

impl Block for Scale {
    fn name(&self) -> &'static str {
        "scale"
    }
    fn latency(&self) -> u32 {
        FP_LATENCY
    }
    fn hw(&self) -> String {
        let axes = self.axis_on.iter().filter(|&&o| o).count();
        format!(
            "{axes}× fp64 mul (×scale/2){}",
            if self.size {
                " ∥ size: 1× fp64 add"
            } else {
                ""
            }
        )
    }
    fn eval(&self, t: &mut Token) {
        self.eval_all(core::slice::from_mut(t));
    }
    fn eval_all(&self, ts: &mut [Token]) {
        for a in 0..3 {
            if self.axis_on[a] {
                let h = self.half_scale[a];
                for t in ts.iter_mut() {
                    t.c2[a] *= h;
                }
            }
        }
        if self.size {
            for t in ts.iter_mut() {
                t.acc = t.dl[0] + t.dl[1];
            }
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        for a in 0..3 {
            if self.axis_on[a] {
                let c = s.get(m, Field::Pos(a));
                let sc = s.cfg(m, &axis_word("scale", a));
                let y = fp_mul(m, &format!("sc_{}", AX[a]), &c, &sc);
                s.put(Field::Pos(a), y, FP_LATENCY);
            }
        }
        if self.size {
            let x = s.get(m, Field::Dl(0));
            let y = s.get(m, Field::Dl(1));
            let acc = fp_add(m, "acc", &x, &y, false);
            s.put(Field::Acc, acc, FP_LATENCY);
        }
    }
    fn config(&self) -> Vec<ImageWord> {
        (0..3)
            .filter(|&a| self.axis_on[a])
            .map(|a| ImageWord {
                name: axis_word("scale", a),
                width: 64,
                value: self.half_scale[a].to_bits(),
            })
            .collect()
    }
    fn fp_ops(&self) -> FpOps {
        FpOps {
            add: self.size as u32,
            mul: self.axis_on.iter().filter(|&&o| o).count() as u32,
            ..FpOps::default()
        }
    }
}

/// Float→fixed: truncate and clamp each position to its bit count ∥ size: `d² = acc + Δz²`.
/// With a programmable interleave it owns the `fields` word (bit counts and field offsets);
/// with fixed wiring the bit counts are constants.
#[derive(Clone, Debug)]
pub struct Fix {
    /// Axes with position bits.
    pub axis_on: [bool; 3],
    /// Whether the size path exists.
    pub size: bool,
    /// Bits per channel (x, y, z, s).
    pub bits: [u32; 4],
    /// Field offsets (x, y, z, s) of the packed word.
    pub offset: [u32; 4],
    /// Whether the bit counts and offsets are registers (a programmable interleave).
    pub programmable: bool,
}

impl Block for Fix {
    fn name(&self) -> &'static str {
        "float→fixed"
    }
    fn latency(&self) -> u32 {
        if self.size {
            FP_LATENCY
        } else {
            1
        }
    }
    fn hw(&self) -> String {
        let axes = self.axis_on.iter().filter(|&&o| o).count();
        format!(
            "{axes}× float→fixed+clamp (64-bit field shifter){}",
            if self.size {
                " ∥ size: 1× fp64 add (d²)"
            } else {
                ""
            }
        )
    }
    fn eval(&self, t: &mut Token) {
        self.eval_all(core::slice::from_mut(t));
    }
    fn eval_all(&self, ts: &mut [Token]) {
        for a in 0..3 {
            if self.axis_on[a] {
                let n = self.bits[a];
                for t in ts.iter_mut() {
                    t.q[a] = float_to_fixed(t.c2[a], n);
                }
            }
        }
        if self.size {
            for t in ts.iter_mut() {
                t.d2 = t.acc + t.dl[2];
            }
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        if self.programmable {
            let f = s.cfg(m, "fields");
            for a in 0..3 {
                let lo = 7 * a as u32;
                let n = m.wire(&format!("nbits_{}", AX[a]), 7, f.at(lo + 6, lo));
                s.set_cfg(&format!("nbits_{}", AX[a]), n);
            }
            for (c, n) in ["x", "y", "z", "s"].iter().enumerate() {
                let lo = 21 + 7 * c as u32;
                let o = m.wire(&format!("off_{n}"), 7, f.at(lo + 6, lo));
                s.set_cfg(&format!("off_{n}"), o);
            }
        } else {
            for a in 0..3 {
                let n = m.wire(&format!("nbits_{}", AX[a]), 7, k(7, self.bits[a] as u128));
                s.set_cfg(&format!("nbits_{}", AX[a]), n);
            }
        }
        for a in 0..3 {
            if self.axis_on[a] {
                let v = s.get(m, Field::Pos(a));
                let n = s.cfg(m, &format!("nbits_{}", AX[a]));
                let q = m
                    .inst(
                        "emc_f2fix",
                        &format!("fx{}", AX[a]),
                        &[("v", &v), ("n", &n)],
                        &|c: &mut Mod| f2fix(c, false),
                    )
                    .remove(0);
                let q = m.reg(&format!("q_{}", AX[a]), 64, &q);
                s.put(Field::Pos(a), q, 1);
            }
        }
        if self.size {
            let acc = s.get(m, Field::Acc);
            let dz = s.get(m, Field::Dl(2));
            let d2 = fp_add(m, "d2", &acc, &dz, false);
            s.put(Field::D2, d2, FP_LATENCY);
        }
    }
    fn config(&self) -> Vec<ImageWord> {
        if !self.programmable {
            return Vec::new();
        }
        // Bit counts of x, y, z and field offsets of x, y, z, s: 7 bits each.
        let f = [
            self.bits[0],
            self.bits[1],
            self.bits[2],
            self.offset[0],
            self.offset[1],
            self.offset[2],
            self.offset[3],
        ];
        vec![ImageWord {
            name: "fields".into(),
            width: 49,
            value: f
                .iter()
                .enumerate()
                .fold(0u64, |w, (i, &x)| w | ((x as u64) << (7 * i))),
        }]
    }
    fn fp_ops(&self) -> FpOps {
        FpOps {
            add: self.size as u32,
            ..FpOps::default()
        }
    }
}

/// The threshold size unit: `S` pipelined binary-search steps, or the comparator bank with a
/// population count (2 cycles), over `2^S − 1` thresholds on `d²`.
#[derive(Clone, Debug)]
pub struct Thresholds {
    /// Size bits `S`.
    pub bits: u32,
    /// `keys[k]` = bit pattern of the smallest `d²` whose size value is `>= k` (index 0
    /// unused), padded to 256 entries with `u64::MAX`.
    pub keys: Box<[u64; 256]>,
    /// Comparator bank instead of the binary search.
    pub bank: bool,
}

impl Block for Thresholds {
    fn name(&self) -> &'static str {
        if self.bank {
            "size.bank"
        } else {
            "size.search"
        }
    }
    fn latency(&self) -> u32 {
        if self.bank {
            2
        } else {
            self.bits
        }
    }
    fn hw(&self) -> String {
        let t = (1u32 << self.bits) - 1;
        if self.bank {
            format!("{t}× 63-bit comparator + popcount")
        } else {
            format!(
                "{}× (63-bit comparator + threshold mux tree), one step per cycle",
                self.bits
            )
        }
    }
    fn eval_all(&self, ts: &mut [Token]) {
        if self.bank {
            for t in ts {
                self.eval(t);
            }
            return;
        }
        for t in ts.iter_mut() {
            t.q[3] = 0;
        }
        for step in 0..self.bits {
            let stride = 1u64 << (self.bits - 1 - step);
            for t in ts.iter_mut() {
                let p = t.q[3];
                let key = compare_key(t.d2);
                t.q[3] = p + stride * (self.keys[((p + stride) & 255) as usize] <= key) as u64;
            }
        }
    }
    #[inline]
    fn eval(&self, t: &mut Token) {
        let key = compare_key(t.d2);
        if self.bank {
            let n = (1usize << self.bits) - 1;
            t.q[3] = self.keys[1..=n].iter().filter(|&&x| x <= key).count() as u64;
        } else {
            let mut p = 0u64;
            for step in 0..self.bits {
                let stride = 1u64 << (self.bits - 1 - step);
                p += stride * (self.keys[((p + stride) & 255) as usize] <= key) as u64;
            }
            t.q[3] = p;
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        let d2 = s.get(m, Field::D2);
        let t = (1u32 << self.bits) - 1;
        let thr: Vec<(String, Sig)> = (1..=t)
            .map(|i| (format!("thr{i}"), s.cfg(m, &format!("thr{i}"))))
            .collect();
        let mut ins: Vec<(&str, &Sig)> = vec![("d2", &d2)];
        ins.extend(thr.iter().map(|(n, v)| (n.as_str(), v)));
        let b = self.bits;
        let q = if self.bank {
            m.inst("emc_bank", "qs_bank", &ins, &|c: &mut Mod| bank(c, b))
        } else {
            m.inst("emc_search", "qs_search", &ins, &|c: &mut Mod| search(c, b))
        }
        .remove(0);
        s.put(Field::Qs, q, self.latency());
    }
    fn config(&self) -> Vec<ImageWord> {
        (1..1usize << self.bits)
            .map(|i| ImageWord {
                name: format!("thr{i}"),
                width: 63,
                value: self.keys[i],
            })
            .collect()
    }
}

/// The formula size path's fp64 square root (`Sqrt`) and divider (`Div`), its `× 2^S`
/// exponent adder (`Scale2S`) and its float→fixed (`Fix`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FormulaOp {
    /// `sd = sqrt(d²)`.
    Sqrt,
    /// `sd = sqrt(sd)` (sqrt transform).
    Sqrt2,
    /// `sd ×= 2^S` by an exponent add.
    Scale2S,
    /// `sd /= D`.
    Div,
    /// `q_s = float→fixed(sd)`.
    Fix,
}

/// One stage of the formula size path (`S > 8`, e.g. `emc64-sort`).
#[derive(Clone, Debug)]
pub struct Formula {
    /// What the stage does.
    pub op: FormulaOp,
    /// Size bits `S`.
    pub bits: u32,
    /// Frame diagonal `D` (the divider's configuration).
    pub diag: f64,
    /// Pipeline stages of the square root and divider.
    pub stages: u32,
    /// Iterative (II = latency) instead of pipelined sqrt/divide (no RTL).
    pub iterative: bool,
    /// Cycles of the iterative unit.
    pub iterative_latency: u32,
    /// The transform (for the printout).
    pub transform: SizeTransform,
}

impl Block for Formula {
    fn name(&self) -> &'static str {
        match self.op {
            FormulaOp::Sqrt => "size.sqrt",
            FormulaOp::Sqrt2 => "size.sqrt2",
            FormulaOp::Scale2S => "size.×2^S",
            FormulaOp::Div => "size.div",
            FormulaOp::Fix => "size.fix",
        }
    }
    fn latency(&self) -> u32 {
        match self.op {
            FormulaOp::Sqrt | FormulaOp::Sqrt2 | FormulaOp::Div => {
                if self.iterative {
                    self.iterative_latency
                } else {
                    self.stages
                }
            }
            FormulaOp::Scale2S | FormulaOp::Fix => 1,
        }
    }
    fn ii(&self) -> u32 {
        match self.op {
            FormulaOp::Sqrt | FormulaOp::Sqrt2 | FormulaOp::Div if self.iterative => {
                self.iterative_latency
            }
            _ => 1,
        }
    }
    fn hw(&self) -> String {
        let kind = if self.iterative {
            "iterative".to_string()
        } else {
            format!("pipelined, {} stages", self.stages)
        };
        match self.op {
            FormulaOp::Sqrt | FormulaOp::Sqrt2 => format!("fp64 sqrt ({kind})"),
            FormulaOp::Div => format!("fp64 divide by D ({kind})"),
            FormulaOp::Scale2S => "11-bit exponent adder".into(),
            FormulaOp::Fix => "float→fixed+clamp".into(),
        }
    }
    fn eval(&self, t: &mut Token) {
        match self.op {
            FormulaOp::Sqrt => t.sd = t.d2.sqrt(),
            FormulaOp::Sqrt2 => t.sd = t.sd.sqrt(),
            FormulaOp::Scale2S => t.sd = exp_add(t.sd, self.bits),
            FormulaOp::Div => t.sd /= self.diag,
            FormulaOp::Fix => t.q[3] = float_to_fixed(t.sd, self.bits),
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        let st = self.stages as usize;
        match self.op {
            FormulaOp::Sqrt | FormulaOp::Sqrt2 => {
                let x = if self.op == FormulaOp::Sqrt {
                    s.get(m, Field::D2)
                } else {
                    s.get(m, Field::Sd)
                };
                let name = format!("sqrt{}", m.uid());
                let y = m
                    .inst("emc_fp64_sqrt", &name, &[("x", &x)], &|c: &mut Mod| {
                        arith::fp64_sqrt(c, st)
                    })
                    .remove(0);
                s.put(Field::Sd, y, self.stages);
            }
            FormulaOp::Div => {
                let a = s.get(m, Field::Sd);
                let d = s.cfg(m, "diag");
                let y = m
                    .inst(
                        "emc_fp64_div",
                        "quot",
                        &[("a", &a), ("b", &d)],
                        &|c: &mut Mod| arith::fp64_div(c, st),
                    )
                    .remove(0);
                s.put(Field::Sd, y, self.stages);
            }
            FormulaOp::Scale2S => {
                let sd = s.get(m, Field::Sd);
                let e = m.wire("sse", 11, sd.at(62, 52));
                let ep = m.wire("ssep", 11, &e + k(11, self.bits as u128));
                let y = m.wire(
                    "ssy",
                    64,
                    mux(
                        eq(&e, k(11, 0)) | eq(&e, k(11, 0x7ff)),
                        &sd,
                        Sig::cat(&[sd.bit(63), ep, sd.at(51, 0)]),
                    ),
                );
                let r = m.reg("sscaled", 64, &y);
                s.put(Field::Sd, r, 1);
            }
            FormulaOp::Fix => {
                let sd = s.get(m, Field::Sd);
                let n = k(7, self.bits as u128);
                let q = m
                    .inst(
                        "emc_f2fix_nan",
                        "fxs",
                        &[("v", &sd), ("n", &n)],
                        &|c: &mut Mod| f2fix(c, true),
                    )
                    .remove(0);
                let q = m.reg("qsize", self.bits, q.at(self.bits - 1, 0));
                s.put(Field::Qs, q, 1);
            }
        }
    }
    fn config(&self) -> Vec<ImageWord> {
        if self.op == FormulaOp::Div {
            vec![ImageWord {
                name: "diag".into(),
                width: 64,
                value: self.diag.to_bits(),
            }]
        } else {
            Vec::new()
        }
    }
    fn fp_ops(&self) -> FpOps {
        FpOps {
            sqrt_div: matches!(self.op, FormulaOp::Sqrt | FormulaOp::Sqrt2 | FormulaOp::Div) as u32,
            ..FpOps::default()
        }
    }
}

/// The packed routing word: each channel value at its field offset.
fn packed(bits: &[u32; 4], offset: &[u32; 4], q: &[u64; 4]) -> u64 {
    let mut w = 0u64;
    for (c, &v) in q.iter().enumerate() {
        if bits[c] > 0 {
            w |= v << offset[c];
        }
    }
    w
}

/// The interleave of a programmable layout: the packed word (from stage `from == 0`) through
/// Beneš columns `from..to`, or through the crossbar.
#[derive(Clone, Debug)]
pub struct Route {
    /// Bits per channel.
    pub bits: [u32; 4],
    /// Field offsets.
    pub offset: [u32; 4],
    /// The network and the part of it this stage passes.
    pub net: RouteNet,
    /// Stage name.
    pub stage_name: &'static str,
}

/// The network of a [`Route`] stage.
#[derive(Clone, Debug)]
pub enum RouteNet {
    /// Beneš columns `from..to` of the network.
    Benes {
        /// The network (control masks per column).
        net: Benes,
        /// First column of this stage.
        from: usize,
        /// One past the last column.
        to: usize,
    },
    /// A crossbar with its selects.
    Crossbar(Crossbar),
}

impl Route {
    fn first(&self) -> bool {
        match &self.net {
            RouteNet::Benes { from, .. } => *from == 0,
            RouteNet::Crossbar(_) => true,
        }
    }
}

impl Block for Route {
    fn name(&self) -> &'static str {
        self.stage_name
    }
    fn latency(&self) -> u32 {
        1
    }
    fn hw(&self) -> String {
        match &self.net {
            RouteNet::Benes { net, from, to } => format!(
                "Beneš columns {from}..{to} of {} ({} lanes)",
                net.columns(),
                net.lanes()
            ),
            RouteNet::Crossbar(x) => format!("{0}×{0} crossbar", x.lanes()),
        }
    }
    fn eval_all(&self, ts: &mut [Token]) {
        if self.first() {
            for t in ts.iter_mut() {
                t.word = packed(&self.bits, &self.offset, &t.q);
            }
        }
        match &self.net {
            RouteNet::Benes { net, from, to } => {
                for i in *from..*to {
                    let (d, mask) = (net.distance(i), net.masks()[i]);
                    for t in ts.iter_mut() {
                        let x = t.word;
                        let y = ((x >> d) ^ x) & mask;
                        t.word = x ^ (y | (y << d));
                    }
                }
            }
            RouteNet::Crossbar(x) => {
                for t in ts.iter_mut() {
                    t.word = x.apply(t.word);
                }
            }
        }
    }
    #[inline]
    fn eval(&self, t: &mut Token) {
        if self.first() {
            t.word = packed(&self.bits, &self.offset, &t.q);
        }
        match &self.net {
            RouteNet::Benes { net, from, to } => t.word = net.apply_columns(t.word, *from..*to),
            RouteNet::Crossbar(x) => t.word = x.apply(t.word),
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        let w = if self.first() {
            let mut parts: Vec<E> = Vec::new();
            for a in 0..3 {
                if self.bits[a] > 0 {
                    let p = s.get(m, Field::Pos(a));
                    parts.push(shl(&p, s.cfg(m, &format!("off_{}", AX[a]))));
                }
            }
            if self.bits[3] > 0 {
                let q = s.get(m, Field::Qs);
                parts.push(shl(q.zext(64), s.cfg(m, "off_s")));
            }
            let e = parts
                .into_iter()
                .reduce(|a, b| a | b)
                .unwrap_or_else(|| k(64, 0).into());
            m.wire("pword", 64, e)
        } else {
            s.get(m, Field::Word)
        };
        let y = match &self.net {
            RouteNet::Benes { net, from, to } => {
                let (f, t) = (*from, *to);
                let whole = f == 0 && t == net.columns();
                let module = if whole {
                    "emc_benes".to_string()
                } else {
                    format!("emc_benes_{f}_{t}")
                };
                let ctl: Vec<(String, Sig)> = (f..t)
                    .map(|i| (format!("ctl{i}"), s.cfg(m, &format!("ctl{i}"))))
                    .collect();
                let mut ins: Vec<(&str, &Sig)> = vec![("w", &w)];
                ins.extend(ctl.iter().map(|(n, v)| (n.as_str(), v)));
                let n = net.clone();
                let name = format!("bn{}", m.uid());
                m.inst(&module, &name, &ins, &move |c: &mut Mod| benes(c, &n, f..t))
                    .remove(0)
            }
            RouteNet::Crossbar(x) => {
                let lanes = &x.lanes();
                let per = crate::rtl::sels_per_word(*lanes);
                let sel: Vec<(String, Sig)> = (0..lanes.div_ceil(per))
                    .map(|i| (format!("sel{i}"), s.cfg(m, &format!("sel{i}"))))
                    .collect();
                let mut ins: Vec<(&str, &Sig)> = vec![("w", &w)];
                ins.extend(sel.iter().map(|(n, v)| (n.as_str(), v)));
                let l = *lanes;
                m.inst("emc_crossbar", "xb", &ins, &move |c: &mut Mod| {
                    crossbar(c, l)
                })
                .remove(0)
            }
        };
        let name = format!("route{}", m.uid());
        let r = m.reg(&name, 64, &y);
        s.put(Field::Word, r, 1);
    }
    fn config(&self) -> Vec<ImageWord> {
        match &self.net {
            RouteNet::Benes { net, from, to } => (*from..*to)
                .map(|i| {
                    // One control bit per switch: the mask bits of the lower lanes, in order.
                    let m = net.masks()[i];
                    let value = crate::rtl::lower_lanes(net.lanes(), net.distance(i))
                        .enumerate()
                        .fold(0u64, |v, (j, p)| v | (((m >> p) & 1) << j));
                    ImageWord {
                        name: format!("ctl{i}"),
                        width: net.lanes() / 2,
                        value,
                    }
                })
                .collect(),
            RouteNet::Crossbar(x) => {
                let (lanes, src) = (&x.lanes(), x.selects());
                let sb = crate::rtl::sel_bits(*lanes);
                let per = crate::rtl::sels_per_word(*lanes);
                (0..lanes.div_ceil(per))
                    .map(|w| {
                        let mut value = 0u64;
                        for j in w * per..((w + 1) * per).min(*lanes) {
                            value |= (src[j as usize] as u64) << (sb * (j - w * per));
                        }
                        ImageWord {
                            name: format!("sel{w}"),
                            width: sb * per,
                            value,
                        }
                    })
                    .collect()
            }
        }
    }
}

/// Pack: the code register; fixed wiring (a regular fixed pattern, Morton or `custom:`) is
/// only wires into it.
#[derive(Clone, Debug)]
pub struct Pack {
    /// Bits per channel.
    pub bits: [u32; 4],
    /// Field offsets.
    pub offset: [u32; 4],
    /// Code length.
    pub len: u32,
    /// `Some` for fixed wiring: code bit `j` is packed bit `src[j]`.
    pub wires: Option<Box<Permutation>>,
    /// `Some(n)` when the wiring is Morton's `(xyz)^n` (the model's shift-and-mask path).
    pub morton: Option<u32>,
}

impl Block for Pack {
    fn name(&self) -> &'static str {
        "pack"
    }
    fn latency(&self) -> u32 {
        1
    }
    fn hw(&self) -> String {
        match (&self.wires, self.morton) {
            (Some(_), Some(n)) => format!("code register (Morton wires, 3×{n})"),
            (Some(_), None) => "code register (fixed wires)".into(),
            _ => "code register".into(),
        }
    }
    #[inline]
    fn eval(&self, t: &mut Token) {
        if let Some(src) = &self.wires {
            t.word = match self.morton {
                Some(_) => morton_wires(t.q[0], t.q[1], t.q[2]),
                None => permute(src, packed(&self.bits, &self.offset, &t.q), self.len),
            };
        }
    }
    fn emit(&self, m: &mut Mod, s: &mut Signals) {
        let code = match &self.wires {
            Some(src) => {
                // Constant field offsets: every code bit is one wire of a channel.
                let mut vals: [Option<Sig>; 4] = [None, None, None, None];
                for c in 0..4 {
                    if self.bits[c] > 0 {
                        vals[c] = Some(if c == 3 {
                            s.get(m, Field::Qs)
                        } else {
                            s.get(m, Field::Pos(c))
                        });
                    }
                }
                let mut bits = Vec::new();
                for j in (0..64).rev() {
                    if j >= self.len as usize {
                        bits.push(k(1, 0));
                        continue;
                    }
                    let p = src[j] as u32;
                    // The channel whose field holds packed bit p.
                    let c = (0..4)
                        .find(|&c| {
                            self.bits[c] > 0
                                && p >= self.offset[c]
                                && p < self.offset[c] + self.bits[c]
                        })
                        .expect("a fixed pattern's packed bit lies in a field");
                    bits.push(
                        vals[c]
                            .as_ref()
                            .expect("field read")
                            .bit(p - self.offset[c]),
                    );
                }
                m.wire("wired", 64, Sig::cat(&bits))
            }
            None => s.get(m, Field::Word),
        };
        let r = m.reg("code", 64, &code);
        s.put(Field::Word, r, 1);
    }
}
