//! The netlist language every emitted block is written in. Each call writes one Verilog wire or
//! register of a module and, in the same step, expands it into the gate network that the
//! generic synthesis library builds for it — yosys's techmap structures: Brent–Kung carry
//! trees (`_90_lcu`), logarithmic shifters (`_90_shift_ops`), full-adder trees for products
//! (`maccmap`), balanced reduction trees, 2:1 multiplexers and flip-flops — with constant
//! propagation, structural hashing and removal of logic no output needs. The cost model prices
//! that gate network ([`Graph::price`]), so the Verilog and its price cannot drift apart.
#![forbid(unsafe_code)]

use core::fmt::Write;
use std::collections::{BTreeMap, HashMap};
use std::ops::{Add, BitAnd, BitOr, BitXor, Mul, Not, Sub};

/// A bit of the gate model: net `n` (net 0 is constant false) with an inversion flag in bit 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Bit(u32);

impl Bit {
    /// Constant 0.
    pub const ZERO: Bit = Bit(0);
    /// Constant 1.
    pub const ONE: Bit = Bit(1);

    fn net(self) -> usize {
        (self.0 >> 1) as usize
    }
    fn inverted(self) -> bool {
        self.0 & 1 == 1
    }
    fn is_const(self) -> bool {
        self.net() == 0
    }
    fn of(b: bool) -> Bit {
        Bit(b as u32)
    }
    fn inv(self) -> Bit {
        Bit(self.0 ^ 1)
    }
    fn plain(self) -> Bit {
        Bit(self.0 & !1)
    }
}

/// What drives a net.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Kind {
    /// Net 0.
    Const,
    /// A module input (in the model, driven by a flip-flop of the surrounding design).
    Input,
    /// A flip-flop; `a` is its D input.
    Dff,
    /// 2-input AND of `a`, `b` (OR is an AND of inverted inputs, inverted).
    And,
    /// 2-input XOR of `a`, `b`.
    Xor,
    /// 2:1 multiplexer: `a ? b : c`.
    Mux,
    /// AND-OR `a | (b & c)`, one complex gate (a carry-tree node).
    Ao21,
}

#[derive(Clone, Copy, Debug)]
struct Gate {
    kind: Kind,
    a: Bit,
    b: Bit,
    c: Bit,
}

/// Transistors of the generic gates, yosys's CMOS estimate (`stat -tech cmos`, the unit of
/// hardware-anchors.md §2.5): AND/OR 6, XOR 12, 2:1 MUX 12, AND-OR (AOI3 and an inverter) 8,
/// D flip-flop 16. Inverters are
/// free (mapping folds them into NAND/NOR/AOI forms).
fn transistors(k: Kind) -> u64 {
    match k {
        Kind::Const | Kind::Input => 0,
        Kind::And => 6,
        Kind::Xor | Kind::Mux => 12,
        Kind::Ao21 => 8,
        Kind::Dff => 16,
    }
}

/// Gate levels of a logic gate: one for the AND/OR forms (a NAND or NOR and the inverter the
/// mapper folds into the next gate) and for AND-OR; [`XOR_LEVELS`] for an XOR and
/// [`MUX_LEVELS`] for a 2:1 multiplexer.
fn levels_of(k: Kind) -> f64 {
    match k {
        Kind::Xor => XOR_LEVELS,
        Kind::Mux => MUX_LEVELS,
        _ => 1.0,
    }
}

/// Gate levels of an XOR on a path. The library's XOR is a two-stage cell whose inputs load
/// the driving gate like two to three NAND inputs (OSU 0.18 µm: `XOR2X1` 0.030 pF per input
/// against 0.0125 pF for `NAND2X1`, `MUX2X1` 0.017 pF on its data inputs): about twice an
/// AND/OR level once its own load is counted; a chain of them (a carry-save tree's sums) is
/// the typical multiplier path.
pub const XOR_LEVELS: f64 = 2.0;
/// Gate levels of a 2:1 multiplexer on a path: its static-CMOS form stacks a second stage on
/// part of its inputs (12 transistors against 6 for an AND in the estimate of
/// the generic gate estimate; half of the second stage is on the path on average).
pub const MUX_LEVELS: f64 = 1.5;

/// Gate levels of a flip-flop's clock-to-output (also charged to module inputs, which a
/// flip-flop of the surrounding pipeline drives): two gate delays.
pub const CLK_TO_Q_LEVELS: f64 = 2.0;
/// Loads on each module output (the flip-flop inputs of the next stage, as the synthesis
/// driver's `set_load` assumes).
pub const OUTPUT_LOADS: u32 = 4;

/// The gate network of a module (and of every module instance inside it, flattened).
#[derive(Clone, Debug)]
pub struct Graph {
    gates: Vec<Gate>,
    hash: HashMap<(Kind, Bit, Bit, Bit), Bit>,
    outputs: Vec<Bit>,
}

impl Default for Graph {
    fn default() -> Self {
        Graph {
            gates: vec![Gate {
                kind: Kind::Const,
                a: Bit::ZERO,
                b: Bit::ZERO,
                c: Bit::ZERO,
            }],
            hash: HashMap::new(),
            outputs: Vec::new(),
        }
    }
}

/// The price of a gate network: area in transistors and flip-flops, the critical path in gate
/// levels (fan-out included) and the gates on it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Price {
    /// Transistors of the live logic gates (flip-flops excluded).
    pub logic_t: u64,
    /// Live flip-flops.
    pub flops: u64,
    /// Gates (logic and flip-flops).
    pub gates: u64,
    /// The longest register-to-register, input-to-register or to-output path, in gate levels,
    /// counting clock-to-output and the fan-out delay of every net on it.
    pub levels: f64,
    /// Logic gates on that path.
    pub depth: u32,
}

impl Price {
    /// All transistors (logic and 16 per flip-flop).
    pub fn transistors(&self) -> u64 {
        self.logic_t + 16 * self.flops
    }
}

impl Graph {
    fn push(&mut self, kind: Kind, a: Bit, b: Bit, c: Bit) -> Bit {
        let id = self.gates.len() as u32;
        self.gates.push(Gate { kind, a, b, c });
        Bit(id << 1)
    }

    fn hashed(&mut self, kind: Kind, a: Bit, b: Bit, c: Bit) -> Bit {
        if let Some(&x) = self.hash.get(&(kind, a, b, c)) {
            return x;
        }
        let x = self.push(kind, a, b, c);
        self.hash.insert((kind, a, b, c), x);
        x
    }

    /// A fresh module input bit.
    pub fn input(&mut self) -> Bit {
        self.push(Kind::Input, Bit::ZERO, Bit::ZERO, Bit::ZERO)
    }

    /// A flip-flop of `d` (identical flip-flops merge, as yosys's `opt_merge` does).
    pub fn dff(&mut self, d: Bit) -> Bit {
        if d.is_const() {
            return d; // a constant register is a constant after `opt_dff`
        }
        self.hashed(Kind::Dff, d, Bit::ZERO, Bit::ZERO)
    }

    /// A flip-flop whose D input is set later ([`Graph::set_d`]), for feedback loops.
    pub fn dff_open(&mut self) -> Bit {
        self.push(Kind::Dff, Bit::ZERO, Bit::ZERO, Bit::ZERO)
    }

    /// Close the loop of a [`Graph::dff_open`] flip-flop.
    pub fn set_d(&mut self, q: Bit, d: Bit) {
        self.gates[q.net()].a = d;
    }

    /// Mark bits as module outputs (the roots of the live logic).
    pub fn mark_output(&mut self, bits: &[Bit]) {
        self.outputs.extend_from_slice(bits);
    }

    /// `a & b`.
    pub fn and(&mut self, a: Bit, b: Bit) -> Bit {
        if a == Bit::ZERO || b == Bit::ZERO || a == b.inv() {
            return Bit::ZERO;
        }
        if a == Bit::ONE || a == b {
            return b;
        }
        if b == Bit::ONE {
            return a;
        }
        let (a, b) = if a < b { (a, b) } else { (b, a) };
        self.hashed(Kind::And, a, b, Bit::ZERO)
    }

    /// `a | b`. An OR of two ANDs under complementary selects, `(s & x) | (!s & y)`, is the
    /// 2:1 multiplexer it is (as ABC's structural choices find it): one gate, not three.
    pub fn or(&mut self, a: Bit, b: Bit) -> Bit {
        if let (Some((a0, a1)), Some((b0, b1))) = (self.and_inputs(a), self.and_inputs(b)) {
            for (s, x) in [(a0, a1), (a1, a0)] {
                for (t, y) in [(b0, b1), (b1, b0)] {
                    if s == t.inv() && !s.is_const() {
                        return self.mux(s, x, y);
                    }
                }
            }
        }
        self.and(a.inv(), b.inv()).inv()
    }

    /// The inputs of `b` when it is the plain output of a 2-input AND gate.
    fn and_inputs(&self, b: Bit) -> Option<(Bit, Bit)> {
        let g = self.gates.get(b.net())?;
        (!b.inverted() && g.kind == Kind::And).then_some((g.a, g.b))
    }

    /// `a ^ b`.
    pub fn xor(&mut self, a: Bit, b: Bit) -> Bit {
        let flip = a.inverted() ^ b.inverted();
        let (a, b) = (a.plain(), b.plain());
        let r = if a == b {
            Bit::ZERO
        } else if a == Bit::ZERO {
            b
        } else if b == Bit::ZERO {
            a
        } else {
            let (a, b) = if a < b { (a, b) } else { (b, a) };
            self.hashed(Kind::Xor, a, b, Bit::ZERO)
        };
        if flip {
            r.inv()
        } else {
            r
        }
    }

    /// `s ? x1 : x0`.
    pub fn mux(&mut self, s: Bit, x1: Bit, x0: Bit) -> Bit {
        if s.is_const() {
            return if s == Bit::ONE { x1 } else { x0 };
        }
        if x1 == x0 {
            return x1;
        }
        if s.inverted() {
            return self.mux(s.inv(), x0, x1);
        }
        match (x1, x0) {
            (Bit::ONE, Bit::ZERO) => s,
            (Bit::ZERO, Bit::ONE) => s.inv(),
            (Bit::ZERO, x) => self.and(s.inv(), x),
            (x, Bit::ZERO) => self.and(s, x),
            (Bit::ONE, x) => self.or(s, x),
            (x, Bit::ONE) => self.or(s.inv(), x),
            (x, y) if x == y.inv() => self.xor(s, y),
            (x, y) if x == s => self.or(s, y),
            (x, y) if y == s => self.and(s, x),
            _ => self.hashed(Kind::Mux, s, x1, x0),
        }
    }

    /// `a | (b & c)`.
    pub fn ao21(&mut self, a: Bit, b: Bit, c: Bit) -> Bit {
        if a == Bit::ONE || b.is_const() || c.is_const() || a.is_const() || b == c || b == c.inv() {
            let t = self.and(b, c);
            return self.or(a, t);
        }
        let (b, c) = if b < c { (b, c) } else { (c, b) };
        self.hashed(Kind::Ao21, a, b, c)
    }

    /// Brent–Kung carries of `p`, `g` with carry-in `ci`, as yosys's `_90_lcu` builds them.
    fn lcu(&mut self, p: &[Bit], g: &[Bit], ci: Bit) -> Vec<Bit> {
        let w = p.len();
        let mut p = p.to_vec();
        let mut g = g.to_vec();
        if w == 0 {
            return g;
        }
        g[0] = self.ao21(g[0], p[0], ci);
        let levels = usize::BITS - (w - 1).leading_zeros(); // clog2(w)
        for i in 1..=levels {
            let step = 1usize << i;
            let half = 1usize << (i - 1);
            let mut j = step - 1;
            while j < w {
                g[j] = self.ao21(g[j], p[j], g[j - half]);
                p[j] = self.and(p[j], p[j - half]);
                j += step;
            }
        }
        for i in (1..=levels).rev() {
            let step = 1usize << i;
            let half = 1usize << (i - 1);
            let mut j = step + half - 1;
            while j < w {
                g[j] = self.ao21(g[j], p[j], g[j - half]);
                p[j] = self.and(p[j], p[j - half]);
                j += step;
            }
        }
        g
    }

    /// `a + (bi ? ~b : b) + ci` over `a.len()` bits (yosys's `_90_alu`); returns the sum and
    /// the carries.
    fn alu(&mut self, a: &[Bit], b: &[Bit], bi: bool, ci: Bit) -> (Vec<Bit>, Vec<Bit>) {
        let bb: Vec<Bit> = b.iter().map(|&x| if bi { x.inv() } else { x }).collect();
        let x: Vec<Bit> = a.iter().zip(&bb).map(|(&p, &q)| self.xor(p, q)).collect();
        let g: Vec<Bit> = a.iter().zip(&bb).map(|(&p, &q)| self.and(p, q)).collect();
        let co = self.lcu(&x, &g, ci);
        let mut y = Vec::with_capacity(x.len());
        for i in 0..x.len() {
            let c = if i == 0 { ci } else { co[i - 1] };
            y.push(self.xor(x[i], c));
        }
        (y, co)
    }

    /// `a + b` (equal widths).
    pub fn add(&mut self, a: &[Bit], b: &[Bit]) -> Vec<Bit> {
        self.alu(a, b, false, Bit::ZERO).0
    }

    /// `a − b` (equal widths).
    pub fn sub(&mut self, a: &[Bit], b: &[Bit]) -> Vec<Bit> {
        self.alu(a, b, true, Bit::ONE).0
    }

    /// `a >= b`, unsigned, equal widths: the carry out of `a − b` (yosys's `alumacc`).
    pub fn ge(&mut self, a: &[Bit], b: &[Bit]) -> Bit {
        if a.is_empty() {
            return Bit::ONE;
        }
        *self.alu(a, b, true, Bit::ONE).1.last().expect("non-empty")
    }

    /// OR of all bits, a balanced tree of 2-input gates (yosys's `simplemap`).
    pub fn reduce_or(&mut self, v: &[Bit]) -> Bit {
        let mut v = v.to_vec();
        if v.is_empty() {
            return Bit::ZERO;
        }
        while v.len() > 1 {
            let mut n = Vec::with_capacity(v.len().div_ceil(2));
            for c in v.chunks(2) {
                n.push(if c.len() == 2 {
                    self.or(c[0], c[1])
                } else {
                    c[0]
                });
            }
            v = n;
        }
        v[0]
    }

    /// AND of all bits.
    pub fn reduce_and(&mut self, v: &[Bit]) -> Bit {
        let inv: Vec<Bit> = v.iter().map(|b| b.inv()).collect();
        self.reduce_or(&inv).inv()
    }

    /// `a == b` (equal widths).
    pub fn eq(&mut self, a: &[Bit], b: &[Bit]) -> Bit {
        let d: Vec<Bit> = a.iter().zip(b).map(|(&x, &y)| self.xor(x, y)).collect();
        self.reduce_or(&d).inv()
    }

    /// `a << n` or `a >> n` (logical) into `yw` bits, as yosys's `_90_shift_ops` builds it:
    /// an overflow test of the amount's high bits, then one multiplexer row per amount bit.
    pub fn shift(&mut self, a: &[Bit], n: &[Bit], yw: usize, left: bool) -> Vec<Bit> {
        let width = a.len().max(yw);
        let clog = |x: usize| (usize::BITS - x.saturating_sub(1).leading_zeros()) as usize;
        let bb = (clog(if left { yw } else { a.len() }) + 1).min(n.len());
        let over = self.reduce_or(&n[bb..]);
        let mut buf: Vec<Bit> = (0..width)
            .map(|i| a.get(i).copied().unwrap_or(Bit::ZERO))
            .collect();
        for x in buf.iter_mut() {
            *x = self.and(over.inv(), *x);
        }
        for (i, &s) in n.iter().enumerate().take(bb) {
            let d = 1usize << i.min(usize::BITS as usize - 2);
            let prev = buf.clone();
            for j in 0..width {
                let moved = if left {
                    if j >= d {
                        prev[j - d]
                    } else {
                        Bit::ZERO
                    }
                } else if j + d < width {
                    prev[j + d]
                } else {
                    Bit::ZERO
                };
                buf[j] = self.mux(s, moved, prev[j]);
            }
        }
        buf.truncate(yw);
        buf.resize(yw, Bit::ZERO);
        buf
    }

    /// A full adder as the mapper builds yosys's `$fa`: the sum an XOR of three (two XOR
    /// cells), the carry the majority `ab | c(a | b)` (ABC restructures `_90_fa`'s
    /// `ab | c(a ^ b)` into it: the carry no longer waits for the first XOR, so the critical
    /// path of a carry-save tree runs through its sums); returns (sum, carry).
    fn fa(&mut self, a: Bit, b: Bit, c: Bit) -> (Bit, Bit) {
        let t1 = self.xor(a, b);
        let sum = self.xor(t1, c);
        if a.is_const() || b.is_const() || c.is_const() {
            // Folds to a half adder or a wire: the plain form simplifies best.
            let t2 = self.and(a, b);
            let t3 = self.and(c, t1);
            return (sum, self.or(t2, t3));
        }
        let t2 = self.and(a, b);
        let o = self.or(a, b);
        (sum, self.ao21(t2, c, o))
    }

    /// `a × b` truncated to `yw` bits as yosys's `maccmap` builds it: one partial-product row
    /// per bit of `b`, rows reduced three to two by rows of full adders (a carry-save tree;
    /// constant-zero positions fold away), then one carry-propagate adder.
    pub fn mul(&mut self, a: &[Bit], b: &[Bit], yw: usize) -> Vec<Bit> {
        let mut rows: Vec<Vec<Bit>> = b
            .iter()
            .enumerate()
            .map(|(j, &y)| {
                (0..yw)
                    .map(|i| match i.checked_sub(j).and_then(|k| a.get(k)) {
                        Some(&x) => self.and(x, y),
                        None => Bit::ZERO,
                    })
                    .collect()
            })
            .collect();
        while rows.len() > 2 {
            let mut next = Vec::with_capacity(rows.len() * 2 / 3 + 2);
            let mut it = rows.chunks(3);
            for grp in &mut it {
                if grp.len() < 3 {
                    next.extend_from_slice(grp);
                    continue;
                }
                let mut sum = vec![Bit::ZERO; yw];
                let mut carry = vec![Bit::ZERO; yw];
                for i in 0..yw {
                    let (s, c) = self.fa(grp[0][i], grp[1][i], grp[2][i]);
                    sum[i] = s;
                    if i + 1 < yw {
                        carry[i + 1] = c;
                    }
                }
                next.push(sum);
                next.push(carry);
            }
            rows = next;
        }
        match rows.len() {
            0 => vec![Bit::ZERO; yw],
            1 => rows.remove(0),
            _ => self.add(&rows[0], &rows[1]),
        }
    }

    /// Price the live part of the network: the logic and flip-flops that some output needs,
    /// and the longest path through it. Levels: one per gate; a flip-flop's output (and a
    /// module input, which one drives) starts at [`CLK_TO_Q_LEVELS`]; a net with fan-out `F`
    /// adds the delay of the fan-out-4 buffer tree that drives it, `ceil(log4 F) − 1` levels
    /// (flip-flop outputs and module inputs too: synthesis buffers them).
    pub fn price(&self) -> Price {
        self.price_split(&[]).0
    }

    /// Register levels between the inputs and the outputs: the most flip-flops on any path
    /// (a module's pipeline depth).
    pub fn register_levels(&self) -> u32 {
        let mut lv = vec![0u32; self.gates.len()];
        for (i, g) in self.gates.iter().enumerate() {
            lv[i] = match g.kind {
                Kind::Const | Kind::Input => 0,
                Kind::Dff => {
                    if g.a.net() < i {
                        lv[g.a.net()] + 1
                    } else {
                        1
                    }
                }
                Kind::And | Kind::Xor => lv[g.a.net()].max(lv[g.b.net()]),
                Kind::Mux | Kind::Ao21 => lv[g.a.net()].max(lv[g.b.net()]).max(lv[g.c.net()]),
            };
        }
        self.outputs.iter().map(|b| lv[b.net()]).max().unwrap_or(0)
    }

    /// [`Graph::price`], and the live logic transistors and flip-flops of the gates created in
    /// each of `ranges` (gate indices, to attribute the network to the blocks that wrote it).
    pub fn price_split(&self, ranges: &[core::ops::Range<usize>]) -> (Price, Vec<(u64, u64)>) {
        let n = self.gates.len();
        let mut live = vec![false; n];
        let mut stack: Vec<usize> = self.outputs.iter().map(|b| b.net()).collect();
        while let Some(i) = stack.pop() {
            if i == 0 || live[i] {
                continue;
            }
            live[i] = true;
            let g = self.gates[i];
            match g.kind {
                Kind::Const | Kind::Input => {}
                Kind::Dff => stack.push(g.a.net()),
                Kind::And | Kind::Xor => {
                    stack.push(g.a.net());
                    stack.push(g.b.net());
                }
                Kind::Mux | Kind::Ao21 => {
                    stack.push(g.a.net());
                    stack.push(g.b.net());
                    stack.push(g.c.net());
                }
            }
        }
        let mut fanout = vec![0u32; n];
        let mut p = Price::default();
        for (i, g) in self.gates.iter().enumerate() {
            if !live[i] {
                continue;
            }
            let ins: &[Bit] = match g.kind {
                Kind::Const | Kind::Input => &[],
                Kind::Dff => core::slice::from_ref(&g.a),
                Kind::And | Kind::Xor => &[g.a, g.b][..],
                Kind::Mux | Kind::Ao21 => &[g.a, g.b, g.c][..],
            };
            for b in ins {
                fanout[b.net()] += 1;
            }
            match g.kind {
                Kind::Dff => p.flops += 1,
                Kind::Const | Kind::Input => {}
                k => p.logic_t += transistors(k),
            }
            if !matches!(g.kind, Kind::Const | Kind::Input) {
                p.gates += 1;
            }
        }
        for b in &self.outputs {
            fanout[b.net()] += OUTPUT_LOADS;
        }
        let drive = |_: &Gate, f: u32| -> f64 {
            if f <= 1 {
                return 0.0;
            }
            ((f as f64).log(4.0).ceil() - 1.0).max(0.0)
        };
        // Arrival (levels, gates on the path) at every net's loads, in creation order (every
        // gate's inputs are older than it, flip-flops start new paths).
        let mut at = vec![(0.0f64, 0u32); n];
        let mut worst = (0.0f64, 0u32);
        let arrive = |at: &[(f64, u32)], b: Bit| if b.is_const() { (0.0, 0) } else { at[b.net()] };
        for i in 1..n {
            if !live[i] {
                continue;
            }
            let g = self.gates[i];
            let start = match g.kind {
                Kind::Input | Kind::Dff => (CLK_TO_Q_LEVELS, 0),
                _ => {
                    let ins: &[Bit] = match g.kind {
                        Kind::And | Kind::Xor => &[g.a, g.b][..],
                        _ => &[g.a, g.b, g.c][..],
                    };
                    let mut m = (0.0f64, 0u32);
                    for &b in ins {
                        let a = arrive(&at, b);
                        if a.0 > m.0 {
                            m = a;
                        }
                    }
                    (m.0 + levels_of(g.kind), m.1 + 1)
                }
            };
            at[i] = (start.0 + drive(&g, fanout[i]), start.1);
            if g.kind == Kind::Dff {
                let d = arrive(&at, g.a);
                if d.0 > worst.0 {
                    worst = d;
                }
            }
        }
        for &b in &self.outputs {
            let d = arrive(&at, b);
            if d.0 > worst.0 {
                worst = d;
            }
        }
        // Flip-flop D arrivals were read before later gates were timed only when the D net is
        // older than the flip-flop; feedback flip-flops (configuration registers) close their
        // loop through a multiplexer created after them, so time their D inputs again.
        for (i, g) in self.gates.iter().enumerate() {
            if live[i] && g.kind == Kind::Dff && g.a.net() > i {
                let d = arrive(&at, g.a);
                if d.0 > worst.0 {
                    worst = d;
                }
            }
        }
        p.levels = worst.0;
        p.depth = worst.1;
        let split = ranges
            .iter()
            .map(|r| {
                let mut t = (0u64, 0u64);
                for i in r.clone() {
                    if live[i] {
                        match self.gates[i].kind {
                            Kind::Dff => t.1 += 1,
                            k => t.0 += transistors(k),
                        }
                    }
                }
                t
            })
            .collect();
        (p, split)
    }
}

/// One piece of a signal's text: a slice of a named wire, or a constant.
#[derive(Clone, Debug)]
enum Part {
    Name {
        name: String,
        full: u32,
        hi: u32,
        lo: u32,
    },
    Const {
        w: u32,
        v: Vec<bool>,
    },
}

/// A signal: a named wire, a slice, a concatenation or a constant, with its bits in the gate
/// model (least significant first).
#[derive(Clone, Debug)]
pub struct Sig {
    parts: Vec<Part>, // most significant first
    bits: Vec<Bit>,
}

impl Sig {
    fn named(name: &str, bits: Vec<Bit>) -> Sig {
        let w = bits.len() as u32;
        Sig {
            parts: vec![Part::Name {
                name: name.to_string(),
                full: w,
                hi: w - 1,
                lo: 0,
            }],
            bits,
        }
    }

    /// A `w`-bit constant.
    pub fn k(w: u32, v: u128) -> Sig {
        let v: Vec<bool> = (0..w).map(|i| i < 128 && (v >> i) & 1 == 1).collect();
        Sig {
            bits: v.iter().map(|&b| Bit::of(b)).collect(),
            parts: vec![Part::Const { w, v }],
        }
    }

    /// `w` copies of `b` (a constant).
    pub fn fill(w: u32, b: bool) -> Sig {
        Sig::k(w, if b { u128::MAX } else { 0 })
    }

    /// Width in bits.
    pub fn w(&self) -> u32 {
        self.bits.len() as u32
    }

    /// Bits `hi..=lo`.
    pub fn at(&self, hi: u32, lo: u32) -> Sig {
        assert!(
            hi >= lo && hi < self.w(),
            "slice [{hi}:{lo}] of {} bits",
            self.w()
        );
        let mut parts = Vec::new();
        let mut top = self.w(); // exclusive top of the current part, counted from bit 0
        for p in &self.parts {
            let pw = match p {
                Part::Name { hi, lo, .. } => hi - lo + 1,
                Part::Const { w, .. } => *w,
            };
            let base = top - pw;
            // This part holds bits base..top; take the overlap with lo..=hi.
            let (a, b) = (lo.max(base), hi.min(top - 1));
            if a <= b {
                parts.push(match p {
                    Part::Name {
                        name,
                        full,
                        lo: plo,
                        ..
                    } => Part::Name {
                        name: name.clone(),
                        full: *full,
                        hi: plo + (b - base),
                        lo: plo + (a - base),
                    },
                    Part::Const { v, .. } => Part::Const {
                        w: b - a + 1,
                        v: v[(a - base) as usize..=(b - base) as usize].to_vec(),
                    },
                });
            }
            top = base;
        }
        Sig {
            parts,
            bits: self.bits[lo as usize..=hi as usize].to_vec(),
        }
    }

    /// Bit `i`.
    pub fn bit(&self, i: u32) -> Sig {
        self.at(i, i)
    }

    /// The concatenation `{parts[0], parts[1], …}` (most significant first).
    pub fn cat(parts: &[Sig]) -> Sig {
        let mut p = Vec::new();
        let mut bits = Vec::new();
        for s in parts.iter().rev() {
            bits.extend_from_slice(&s.bits);
        }
        for s in parts {
            p.extend(s.parts.iter().cloned());
        }
        Sig { parts: p, bits }
    }

    /// Zero-extended to `w` bits by a leading constant.
    pub fn zext(&self, w: u32) -> Sig {
        if w == self.w() {
            return self.clone();
        }
        Sig::cat(&[Sig::k(w - self.w(), 0), self.clone()])
    }

    /// The model bits (least significant first).
    pub fn bits(&self) -> &[Bit] {
        &self.bits
    }

    /// Whether every bit is a constant of the gate model.
    pub fn is_const(&self) -> bool {
        self.bits.iter().all(|b| b.is_const())
    }

    fn text(&self) -> String {
        let t: Vec<String> = self.parts.iter().map(part_text).collect();
        if t.len() == 1 {
            t.into_iter().next().expect("one part")
        } else {
            format!("{{{}}}", t.join(", "))
        }
    }
}

fn part_text(p: &Part) -> String {
    match p {
        Part::Name { name, full, hi, lo } => {
            if *full == 1 || (*lo == 0 && *hi == full - 1) {
                name.clone()
            } else if hi == lo {
                format!("{name}[{hi}]")
            } else {
                format!("{name}[{hi}:{lo}]")
            }
        }
        Part::Const { w, v } => {
            let ones = v.iter().all(|&b| b);
            if ones && *w > 1 {
                return format!("{{{w}{{1'b1}}}}");
            }
            if *w <= 128 {
                let val = v
                    .iter()
                    .enumerate()
                    .fold(0u128, |a, (i, &b)| a | ((b as u128) << i));
                if *w <= 8 {
                    format!("{w}'d{val}")
                } else {
                    format!("{w}'h{val:x}")
                }
            } else {
                let s: String = v.iter().rev().map(|&b| if b { '1' } else { '0' }).collect();
                format!("{w}'b{s}")
            }
        }
    }
}

/// An expression of one wire: operators over signals with Verilog-2005 sizing (unsigned).
#[derive(Clone, Debug)]
pub enum E {
    /// A signal.
    S(Sig),
    /// `~a`.
    Not(Box<E>),
    /// `a & b`.
    And(Box<E>, Box<E>),
    /// `a | b`.
    Or(Box<E>, Box<E>),
    /// `a ^ b`.
    Xor(Box<E>, Box<E>),
    /// `a + b`.
    Add(Box<E>, Box<E>),
    /// `a - b`.
    Sub(Box<E>, Box<E>),
    /// `a * b`.
    Mul(Box<E>, Box<E>),
    /// `a << n`.
    Shl(Box<E>, Box<E>),
    /// `a >> n`.
    Shr(Box<E>, Box<E>),
    /// `a == b`.
    Eq(Box<E>, Box<E>),
    /// `a != b`.
    Ne(Box<E>, Box<E>),
    /// `a < b`.
    Lt(Box<E>, Box<E>),
    /// `a <= b`.
    Le(Box<E>, Box<E>),
    /// `a > b`.
    Gt(Box<E>, Box<E>),
    /// `a >= b`.
    Ge(Box<E>, Box<E>),
    /// `c ? a : b`.
    Mux(Box<E>, Box<E>, Box<E>),
    /// `|a`.
    RedOr(Box<E>),
    /// `{a, b, …}` of expressions.
    Cat(Vec<E>),
    /// `s[i]`: the bit of a signal at a variable index (a multiplexer tree).
    Pick(Sig, Box<E>),
}

impl From<Sig> for E {
    fn from(s: Sig) -> E {
        E::S(s)
    }
}

impl From<&Sig> for E {
    fn from(s: &Sig) -> E {
        E::S(s.clone())
    }
}

macro_rules! binop {
    ($tr:ident, $f:ident, $v:ident) => {
        impl<T: Into<E>> $tr<T> for E {
            type Output = E;
            fn $f(self, r: T) -> E {
                E::$v(Box::new(self), Box::new(r.into()))
            }
        }
        impl<T: Into<E>> $tr<T> for &Sig {
            type Output = E;
            fn $f(self, r: T) -> E {
                E::$v(Box::new(self.into()), Box::new(r.into()))
            }
        }
        impl<T: Into<E>> $tr<T> for Sig {
            type Output = E;
            fn $f(self, r: T) -> E {
                E::$v(Box::new(self.into()), Box::new(r.into()))
            }
        }
    };
}
binop!(BitAnd, bitand, And);
binop!(BitOr, bitor, Or);
binop!(BitXor, bitxor, Xor);
binop!(Add, add, Add);
binop!(Sub, sub, Sub);
binop!(Mul, mul, Mul);

impl Not for E {
    type Output = E;
    fn not(self) -> E {
        E::Not(Box::new(self))
    }
}

impl Not for &Sig {
    type Output = E;
    fn not(self) -> E {
        E::Not(Box::new(self.into()))
    }
}

fn bx(e: impl Into<E>) -> Box<E> {
    Box::new(e.into())
}

/// `c ? a : b`.
pub fn mux(c: impl Into<E>, a: impl Into<E>, b: impl Into<E>) -> E {
    E::Mux(bx(c), bx(a), bx(b))
}
/// `a << n`.
pub fn shl(a: impl Into<E>, n: impl Into<E>) -> E {
    E::Shl(bx(a), bx(n))
}
/// `a >> n`.
pub fn shr(a: impl Into<E>, n: impl Into<E>) -> E {
    E::Shr(bx(a), bx(n))
}
/// `a == b`.
pub fn eq(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Eq(bx(a), bx(b))
}
/// `a != b`.
pub fn ne(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Ne(bx(a), bx(b))
}
/// `a < b`.
pub fn lt(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Lt(bx(a), bx(b))
}
/// `a <= b`.
pub fn le(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Le(bx(a), bx(b))
}
/// `a > b`.
pub fn gt(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Gt(bx(a), bx(b))
}
/// `a >= b`.
pub fn ge(a: impl Into<E>, b: impl Into<E>) -> E {
    E::Ge(bx(a), bx(b))
}
/// `|a`.
pub fn red_or(a: impl Into<E>) -> E {
    E::RedOr(bx(a))
}
/// `s[i]` for a variable index `i`.
pub fn pick(s: &Sig, i: impl Into<E>) -> E {
    E::Pick(s.clone(), bx(i))
}
/// `{a, b, …}`.
pub fn cat(parts: Vec<E>) -> E {
    E::Cat(parts)
}

impl E {
    /// Self-determined width (IEEE 1364-2005 §5.4.1).
    pub fn width(&self) -> u32 {
        match self {
            E::S(s) => s.w(),
            E::Not(a) => a.width(),
            E::And(a, b)
            | E::Or(a, b)
            | E::Xor(a, b)
            | E::Add(a, b)
            | E::Sub(a, b)
            | E::Mul(a, b) => a.width().max(b.width()),
            E::Shl(a, _) | E::Shr(a, _) => a.width(),
            E::Eq(..) | E::Ne(..) | E::Lt(..) | E::Le(..) | E::Gt(..) | E::Ge(..) => 1,
            E::RedOr(_) | E::Pick(..) => 1,
            E::Mux(_, a, b) => a.width().max(b.width()),
            E::Cat(v) => v.iter().map(|e| e.width()).sum(),
        }
    }

    fn text(&self, top: bool) -> String {
        let t = match self {
            E::S(s) => return s.text(),
            E::Not(a) => return format!("~{}", a.text(false)),
            E::RedOr(a) => return format!("|{}", a.text(false)),
            E::Pick(s, i) => return format!("{}[{}]", s.text(), i.text(true)),
            E::Cat(v) => {
                let p: Vec<String> = v.iter().map(|e| e.text(true)).collect();
                return format!("{{{}}}", p.join(", "));
            }
            E::Mux(c, a, b) => format!("{} ? {} : {}", c.text(false), a.text(false), b.text(false)),
            E::And(a, b) => bin(a, "&", b),
            E::Or(a, b) => bin(a, "|", b),
            E::Xor(a, b) => bin(a, "^", b),
            E::Add(a, b) => bin(a, "+", b),
            E::Sub(a, b) => bin(a, "-", b),
            E::Mul(a, b) => bin(a, "*", b),
            E::Shl(a, b) => bin(a, "<<", b),
            E::Shr(a, b) => bin(a, ">>", b),
            E::Eq(a, b) => bin(a, "==", b),
            E::Ne(a, b) => bin(a, "!=", b),
            E::Lt(a, b) => bin(a, "<", b),
            E::Le(a, b) => bin(a, "<=", b),
            E::Gt(a, b) => bin(a, ">", b),
            E::Ge(a, b) => bin(a, ">=", b),
        };
        if top {
            t
        } else {
            format!("({t})")
        }
    }

    /// The expression's bits in a context of `ctx` bits (operands extended first, as Verilog
    /// sizes context-determined operators); returns at least `ctx` bits.
    fn bits(&self, g: &mut Graph, ctx: u32) -> Vec<Bit> {
        let c = ctx.max(self.width()) as usize;
        let ext = |mut v: Vec<Bit>| {
            v.resize(c.max(v.len()), Bit::ZERO);
            v
        };
        match self {
            E::S(s) => ext(s.bits.clone()),
            E::Cat(v) => {
                let mut out = Vec::new();
                for e in v.iter().rev() {
                    out.extend(e.bits(g, e.width()));
                }
                ext(out)
            }
            E::Not(a) => a.bits(g, c as u32).into_iter().map(|b| b.inv()).collect(),
            E::And(a, b) | E::Or(a, b) | E::Xor(a, b) => {
                let x = a.bits(g, c as u32);
                let y = b.bits(g, c as u32);
                x.iter()
                    .zip(&y)
                    .map(|(&p, &q)| match self {
                        E::And(..) => g.and(p, q),
                        E::Or(..) => g.or(p, q),
                        _ => g.xor(p, q),
                    })
                    .collect()
            }
            E::Add(a, b) => {
                let (x, y) = (a.bits(g, c as u32), b.bits(g, c as u32));
                g.add(&x, &y)
            }
            E::Sub(a, b) => {
                let (x, y) = (a.bits(g, c as u32), b.bits(g, c as u32));
                g.sub(&x, &y)
            }
            E::Mul(a, b) => {
                let x = a.bits(g, a.width());
                let y = b.bits(g, b.width());
                g.mul(&x, &y, c)
            }
            E::Shl(a, n) | E::Shr(a, n) => {
                let x = a.bits(g, c as u32);
                let k = n.bits(g, n.width());
                g.shift(&x, &k, c, matches!(self, E::Shl(..)))
            }
            E::Eq(a, b) | E::Ne(a, b) | E::Lt(a, b) | E::Le(a, b) | E::Gt(a, b) | E::Ge(a, b) => {
                let w = a.width().max(b.width());
                let x = a.bits(g, w);
                let y = b.bits(g, w);
                let r = match self {
                    E::Eq(..) => g.eq(&x, &y),
                    E::Ne(..) => g.eq(&x, &y).inv(),
                    E::Ge(..) => g.ge(&x, &y),
                    E::Lt(..) => g.ge(&x, &y).inv(),
                    E::Le(..) => g.ge(&y, &x),
                    _ => g.ge(&y, &x).inv(),
                };
                ext(vec![r])
            }
            E::RedOr(a) => {
                let x = a.bits(g, a.width());
                ext(vec![g.reduce_or(&x)])
            }
            E::Pick(s, i) => {
                let k = i.bits(g, i.width());
                let b = g.shift(s.bits(), &k, 1, false);
                ext(b)
            }
            E::Mux(s, a, b) => {
                let sv = s.bits(g, s.width());
                let sel = g.reduce_or(&sv);
                let x = a.bits(g, c as u32);
                let y = b.bits(g, c as u32);
                x.iter().zip(&y).map(|(&p, &q)| g.mux(sel, p, q)).collect()
            }
        }
    }
}

fn bin(a: &E, op: &str, b: &E) -> String {
    format!("{} {op} {}", a.text(false), b.text(false))
}

/// A module being written: its ports, body text, the library of modules it instantiates and
/// its gate network.
#[derive(Clone, Debug)]
pub struct Mod {
    name: String,
    ports: Vec<String>,
    body: String,
    /// Module definitions this one instantiates (name → the module written alone), and the
    /// order of first use.
    lib: BTreeMap<String, Mod>,
    lib_order: Vec<String>,
    graph: Graph,
    /// Port bindings of an instance being expanded: input name → parent bits.
    bind: Option<HashMap<String, Vec<Bit>>>,
    /// Outputs of an instance being expanded: port name → bits.
    outs: Vec<(String, Vec<Bit>)>,
    clocked: bool,
    uid: usize,
}

impl Mod {
    /// A new module.
    pub fn new(name: &str) -> Mod {
        Mod {
            name: name.to_string(),
            ports: Vec::new(),
            body: String::new(),
            lib: BTreeMap::new(),
            lib_order: Vec::new(),
            graph: Graph::default(),
            bind: None,
            outs: Vec::new(),
            clocked: false,
            uid: 0,
        }
    }

    /// The module's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// A fresh number for unique names.
    pub fn uid(&mut self) -> usize {
        self.uid += 1;
        self.uid
    }

    /// A line of the body.
    pub fn line(&mut self, l: &str) {
        self.body.push_str("  ");
        self.body.push_str(l);
        self.body.push('\n');
    }

    /// A comment line.
    pub fn comment(&mut self, c: &str) {
        self.line(&format!("// {c}"));
    }

    /// The clock input (first port).
    pub fn clock(&mut self) {
        if !self.clocked {
            self.clocked = true;
            self.ports.insert(0, "input clk".into());
        }
    }

    /// A `w`-bit input port.
    pub fn input(&mut self, name: &str, w: u32) -> Sig {
        self.ports.push(decl("input", w, name));
        let bits = match &self.bind {
            Some(b) => b
                .get(name)
                .unwrap_or_else(|| panic!("instance of {} lacks input {name}", self.name))
                .clone(),
            None => (0..w).map(|_| self.graph.input()).collect(),
        };
        assert_eq!(bits.len() as u32, w, "input {name} of {}", self.name);
        Sig::named(name, bits)
    }

    /// An output port driven by `e` (`assign name = e;`).
    pub fn output(&mut self, name: &str, w: u32, e: impl Into<E>) {
        let e = e.into();
        self.ports.push(decl("output", w, name));
        let mut bits = e.bits(&mut self.graph, w);
        bits.truncate(w as usize);
        self.line(&format!("assign {name} = {};", e.text(true)));
        if self.bind.is_some() {
            self.outs.push((name.to_string(), bits));
        } else {
            self.graph.mark_output(&bits);
        }
    }

    /// `wire [w-1:0] name = e;`
    pub fn wire(&mut self, name: &str, w: u32, e: impl Into<E>) -> Sig {
        let e = e.into();
        let mut bits = e.bits(&mut self.graph, w);
        bits.truncate(w as usize);
        self.line(&format!("{} = {};", decl("wire", w, name), e.text(true)));
        Sig::named(name, bits)
    }

    /// A pipeline register of `e`: `reg [w-1:0] name; always @(posedge clk) name <= e;`
    pub fn reg(&mut self, name: &str, w: u32, e: impl Into<E>) -> Sig {
        self.clock();
        let e = e.into();
        let mut d = e.bits(&mut self.graph, w);
        d.truncate(w as usize);
        let q: Vec<Bit> = d.iter().map(|&b| self.graph.dff(b)).collect();
        self.line(&format!("{};", decl("reg", w, name)));
        self.line(&format!(
            "always @(posedge clk) {name} <= {};",
            e.text(true)
        ));
        Sig::named(name, q)
    }

    /// A register with synchronous reset to 0 (the valid bits).
    pub fn reg_rst(&mut self, name: &str, rst: &Sig, e: impl Into<E>) -> Sig {
        self.clock();
        let e = e.into();
        let d = e.bits(&mut self.graph, 1)[0];
        let d = self.graph.and(rst.bits[0].inv(), d);
        let q = self.graph.dff(d);
        self.line(&format!("reg {name};"));
        self.line(&format!(
            "always @(posedge clk) {name} <= {} ? 1'b0 : {};",
            rst.text(),
            e.text(false)
        ));
        Sig::named(name, vec![q])
    }

    /// A configuration register written from the bus when `we` and `addr == a`.
    pub fn cfg_reg(&mut self, name: &str, w: u32, we: &Sig, addr: &Sig, a: u32, data: &Sig) -> Sig {
        self.clock();
        let hit = E::from(we) & eq(addr, Sig::k(addr.w(), a as u128));
        let en = hit.bits(&mut self.graph, 1)[0];
        let mut q = Vec::new();
        for i in 0..w as usize {
            let f = self.graph.dff_open();
            let d = self.graph.mux(en, data.bits[i], f);
            self.graph.set_d(f, d);
            q.push(f);
        }
        self.line(&format!("{};", decl("reg", w, name)));
        self.line(&format!(
            "always @(posedge clk) if ({} && {} == {}) {name} <= {};",
            we.text(),
            addr.text(),
            Sig::k(addr.w(), a as u128).text(),
            data.at(w - 1, 0).text()
        ));
        Sig::named(name, q)
    }

    /// Instantiate the module that `body` writes, with `inputs` bound by port name; returns
    /// its outputs as wires of this module named `<inst>_<port>`, or `<inst>` for a module
    /// with one output. The instance's gates join this module's network (synthesis
    /// flattens); its text joins the library once per module name.
    pub fn inst(
        &mut self,
        module: &str,
        inst: &str,
        inputs: &[(&str, &Sig)],
        body: &dyn Fn(&mut Mod),
    ) -> Vec<Sig> {
        let mut child = Mod::new(module);
        child.graph = std::mem::take(&mut self.graph);
        child.bind = Some(
            inputs
                .iter()
                .map(|(n, s)| (n.to_string(), s.bits.clone()))
                .collect(),
        );
        body(&mut child);
        self.graph = std::mem::take(&mut child.graph);
        for n in std::mem::take(&mut child.lib_order) {
            if !self.lib.contains_key(&n) {
                let d = child.lib.remove(&n).expect("listed");
                self.lib.insert(n.clone(), d);
                self.lib_order.push(n);
            }
        }
        if !self.lib.contains_key(module) {
            // The definition on its own, with inputs of its own (for synthesis and pricing
            // block by block).
            let mut alone = Mod::new(module);
            body(&mut alone);
            self.lib.insert(module.to_string(), alone);
            self.lib_order.push(module.to_string());
        }
        let single = child.outs.len() == 1;
        let mut conns = Vec::new();
        if child.clocked {
            conns.push(".clk(clk)".to_string());
        }
        for (n, s) in inputs {
            conns.push(format!(".{n}({})", s.text()));
        }
        let mut outs = Vec::new();
        for (port, bits) in &child.outs {
            let name = if single {
                inst.to_string()
            } else {
                format!("{inst}_{port}")
            };
            self.line(&format!("{};", decl("wire", bits.len() as u32, &name)));
            conns.push(format!(".{port}({name})"));
            outs.push(Sig::named(&name, bits.clone()));
        }
        if child.clocked {
            self.clocked = true;
            if !self.ports.iter().any(|p| p == "input clk") {
                self.ports.insert(0, "input clk".into());
            }
        }
        self.line(&format!("{module} u_{inst} ({});", conns.join(", ")));
        outs
    }

    /// The module's own text (`module … endmodule`).
    pub fn text_alone(&self) -> String {
        format!(
            "module {} (\n  {}\n);\n{}endmodule\n\n",
            self.name,
            self.ports.join(",\n  "),
            self.body
        )
    }

    /// The module and, after it, every module it instantiates.
    pub fn text(&self) -> String {
        let mut s = self.text_alone();
        for n in &self.lib_order {
            let _ = write!(s, "{}", self.lib[n].text_alone());
        }
        s
    }

    /// The modules this one instantiates, each written alone, in order of first use.
    pub fn library(&self) -> Vec<&Mod> {
        self.lib_order.iter().map(|n| &self.lib[n]).collect()
    }

    /// The gate network (this module and its instances, flattened).
    pub fn graph(&self) -> &Graph {
        &self.graph
    }

    /// Gates created so far (to attribute a range of them to a block).
    pub fn gate_count(&self) -> usize {
        self.graph.gates.len()
    }
}

fn decl(kind: &str, w: u32, name: &str) -> String {
    if w == 1 {
        format!("{kind} {name}")
    } else {
        format!("{kind} [{}:0] {name}", w - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Evaluate the gate network on input values (combinational part only).
    fn eval(g: &Graph, inputs: &HashMap<usize, bool>, b: Bit) -> bool {
        fn go(
            g: &Graph,
            inputs: &HashMap<usize, bool>,
            b: Bit,
            memo: &mut HashMap<usize, bool>,
        ) -> bool {
            let n = b.net();
            let v = if n == 0 {
                false
            } else if let Some(&v) = memo.get(&n) {
                v
            } else {
                let x = g.gates[n];
                let v = match x.kind {
                    Kind::Input => inputs[&n],
                    Kind::And => go(g, inputs, x.a, memo) & go(g, inputs, x.b, memo),
                    Kind::Xor => go(g, inputs, x.a, memo) ^ go(g, inputs, x.b, memo),
                    Kind::Mux => {
                        if go(g, inputs, x.a, memo) {
                            go(g, inputs, x.b, memo)
                        } else {
                            go(g, inputs, x.c, memo)
                        }
                    }
                    Kind::Ao21 => {
                        go(g, inputs, x.a, memo)
                            | (go(g, inputs, x.b, memo) & go(g, inputs, x.c, memo))
                    }
                    Kind::Const | Kind::Dff => unreachable!(),
                };
                memo.insert(n, v);
                v
            };
            v ^ b.inverted()
        }
        go(g, inputs, b, &mut HashMap::new())
    }

    fn val(bits: &[Bit], g: &Graph, inp: &HashMap<usize, bool>) -> u128 {
        bits.iter()
            .enumerate()
            .fold(0u128, |a, (i, &b)| a | ((eval(g, inp, b) as u128) << i))
    }

    /// The gate expansions compute what the Verilog operators compute.
    #[test]
    fn gate_expansions_compute_the_operators() {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for _ in 0..300 {
            let mut m = Mod::new("t");
            let wa = 1 + (rnd() % 20) as u32;
            let wb = 1 + (rnd() % 20) as u32;
            let a = m.input("a", wa);
            let b = m.input("b", wb);
            let n = m.input("n", 5);
            let mut inp = HashMap::new();
            let (va, vb, vn) = (
                rnd() as u128 & ((1 << wa) - 1),
                rnd() as u128 & ((1 << wb) - 1),
                rnd() as u128 & 31,
            );
            for (sig, v) in [(&a, va), (&b, vb), (&n, vn)] {
                for (i, bit) in sig.bits().iter().enumerate() {
                    inp.insert(bit.net(), (v >> i) & 1 == 1);
                }
            }
            let w = 24u32;
            let mask = (1u128 << w) - 1;
            let cases: Vec<(E, u128)> = vec![
                (&a + &b, (va + vb) & mask),
                (&a - &b, va.wrapping_sub(vb) & mask),
                (&a * &b, (va * vb) & mask),
                (&a & &b, va & vb),
                (&a | &b, va | vb),
                (&a ^ &b, va ^ vb),
                (!&a, !va & mask),
                (shl(&a, &n), (va << vn) & mask),
                (shr(&a, &n), va >> vn),
                (ge(&a, &b), (va >= vb) as u128),
                (lt(&a, &b), (va < vb) as u128),
                (le(&a, &b), (va <= vb) as u128),
                (gt(&a, &b), (va > vb) as u128),
                (eq(&a, &b), (va == vb) as u128),
                (ne(&a, &b), (va != vb) as u128),
                (red_or(&a), (va != 0) as u128),
                (mux(ge(&a, &b), &a, &b), va.max(vb)),
                (
                    cat(vec![(&a).into(), (&b).into()]),
                    ((va << wb) | vb) & mask,
                ),
                (pick(&a, &n), (va >> vn) & 1),
            ];
            for (k, (e, want)) in cases.into_iter().enumerate() {
                let bits = e.bits(&mut m.graph, w);
                let got = val(&bits[..w as usize], &m.graph, &inp);
                assert_eq!(
                    got,
                    want,
                    "case {k}: {} with a={va} ({wa}b) b={vb} ({wb}b) n={vn}",
                    e.text(true)
                );
            }
        }
    }

    #[test]
    fn slices_and_concatenations_print_and_map_their_bits() {
        let mut m = Mod::new("t");
        let a = m.input("a", 8);
        let b = m.input("b", 4);
        let c = Sig::cat(&[a.at(5, 2), Sig::k(3, 5), b.clone()]);
        assert_eq!(c.text(), "{a[5:2], 3'd5, b}");
        assert_eq!(c.at(8, 3).text(), "{a[3:2], 3'd5, b[3]}");
        assert_eq!(c.at(8, 3).bits()[5], a.bits()[3]);
        assert_eq!(c.at(8, 3).bits()[0], b.bits()[3]);
        assert_eq!(c.at(8, 3).bits()[1], Bit::ONE);
        assert_eq!(c.at(8, 3).bits()[2], Bit::ZERO);
        assert_eq!(Sig::fill(56, true).text(), "{56{1'b1}}");
    }

    /// A ripple structure is deeper than a carry tree, and the price counts only live logic.
    #[test]
    fn price_counts_live_logic_and_levels() {
        let mut m = Mod::new("t");
        let a = m.input("a", 32);
        let b = m.input("b", 32);
        let s = m.wire("s", 32, &a + &b);
        let _dead = m.wire("dead", 32, &a * &b);
        m.output("y", 32, &s);
        let p = m.graph().price();
        // A 32-bit Brent–Kung adder: 2·log2(32) + 1 levels of carry logic, not 32.
        assert!(p.depth <= 13 && p.depth >= 9, "{p:?}");
        assert!(p.logic_t > 32 * 30 && p.logic_t < 32 * 80, "{p:?}");
        assert_eq!(p.flops, 0);
    }
}
