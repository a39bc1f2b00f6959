//! Verilog of exactly the configured unit: the model's stage list, stage for stage, as
//! synthesisable Verilog-2005, with the register image that programs it, a self-checking
//! testbench and a vectors file ([`crate::vectors`]).
//!
//! One description per block: every pipeline stage of [`Unit::stages`] is an [`Op`]; the model's
//! behaviour of an op is [`Unit::apply`], its Verilog is the arm of the emitter's stage loop for the
//! same op, emitted with the stage's latency as register levels, and its configuration words
//! come from [`image`] — the single list that the `$readmemh` file, the Verilog configuration
//! registers and the setup cost ([`crate::setup`]) are all made from. Nothing the configuration
//! does not use is emitted: no lane for an axis without bits, no size datapath without size
//! bits, fixed wiring for a regular pattern, a Beneš network or crossbar sized to the code
//! length otherwise.
//!
//! Interface of `emc_unit`: a 64-bit configuration bus (`cfg_we`, `cfg_addr`, `cfg_data`, one
//! image word per cycle), `in_valid`/`in_box` (six binary32 fields, `min.x` in bits 31:0 up to
//! `max.z` in bits 191:160), and `out_valid`/`out_code` `depth` cycles later. The unit accepts
//! a box every cycle (II = 1); the memory port is the model's business, not the RTL's.
#![forbid(unsafe_code)]
// Per-axis registers and names are parallel arrays indexed by the axis number.
#![allow(clippy::needless_range_loop)]

pub mod arith;

use core::fmt::Write;
use std::path::Path;

use emc_core::Aabb;

use crate::datapath::{Network, Op, SizeUnit, Unit, FP_LATENCY, SQRT_DIV_PIPELINED_LATENCY};
use crate::error::HwError;
use crate::vectors::{to_text, vectors, Vector};

const _: () = assert!(
    FP_LATENCY == 3,
    "the emitted fp64 adder and multiplier have 3 stages"
);

/// One word of the register image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageWord {
    /// Register name in the Verilog.
    pub name: String,
    /// Bits used (from bit 0 of the word).
    pub width: u32,
    /// The value.
    pub value: u64,
}

/// The lower lanes of the 2×2 switches of a Beneš column with exchange distance `d`, in
/// order (lane `p` is switched with `p + d`).
fn lower_lanes(lanes: u32, d: u32) -> impl Iterator<Item = u32> {
    (0..lanes).filter(move |p| p & d == 0)
}

/// Bits per select of a crossbar with `lanes` outputs.
fn sel_bits(lanes: u32) -> u32 {
    lanes.trailing_zeros()
}

/// Selects per 64-bit configuration word.
fn sels_per_word(lanes: u32) -> u32 {
    64 / sel_bits(lanes)
}

/// The register image of a unit, in configuration-bus address order.
pub fn image(unit: &Unit) -> Vec<ImageWord> {
    let r = unit.registers();
    let mut v = Vec::new();
    let axes = ['x', 'y', 'z'];
    for a in 0..3 {
        if r.axis_on[a] {
            v.push(ImageWord {
                name: format!("origin2_{}", axes[a]),
                width: 64,
                value: r.origin2[a].to_bits(),
            });
            v.push(ImageWord {
                name: format!("scale_{}", axes[a]),
                width: 64,
                value: r.half_scale[a].to_bits(),
            });
        }
    }
    if !matches!(r.net, Network::Fixed { .. }) {
        // Bit counts of x, y, z and field offsets of x, y, z, s: 7 bits each.
        let f = [
            r.bits[0],
            r.bits[1],
            r.bits[2],
            r.offset[0],
            r.offset[1],
            r.offset[2],
            r.offset[3],
        ];
        let value = f
            .iter()
            .enumerate()
            .fold(0u64, |w, (i, &x)| w | ((x as u64) << (7 * i)));
        v.push(ImageWord {
            name: "fields".into(),
            width: 49,
            value,
        });
    }
    match &r.size {
        SizeUnit::None => {}
        SizeUnit::Thresholds { keys, .. } => {
            for (k, &key) in keys.iter().enumerate().skip(1) {
                v.push(ImageWord {
                    name: format!("thr[{k}]"),
                    width: 63,
                    value: key,
                });
            }
        }
        SizeUnit::Formula { diag, .. } => v.push(ImageWord {
            name: "diag".into(),
            width: 64,
            value: diag.to_bits(),
        }),
    }
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            // One control bit per switch: the mask bits of the lower lanes, in lane order.
            for (i, &m) in b.masks().iter().enumerate() {
                let value = lower_lanes(b.lanes(), b.distance(i))
                    .enumerate()
                    .fold(0u64, |v, (j, p)| v | (((m >> p) & 1) << j));
                v.push(ImageWord {
                    name: format!("ctl{i}"),
                    width: b.lanes() / 2,
                    value,
                });
            }
        }
        Network::Crossbar(x) => {
            let sb = sel_bits(x.lanes());
            let per = sels_per_word(x.lanes());
            let src = crate::routing::layout_permutation(unit.layout());
            for w in 0..x.lanes().div_ceil(per) {
                let mut value = 0u64;
                for j in w * per..((w + 1) * per).min(x.lanes()) {
                    value |= (src[j as usize] as u64) << (sb * (j - w * per));
                }
                v.push(ImageWord {
                    name: format!("sel{w}"),
                    width: sb * per,
                    value,
                });
            }
        }
    }
    v
}

/// The files of an emitted unit.
#[derive(Clone, Debug)]
pub struct RtlFiles {
    /// `emc_unit.v`: the unit and the arithmetic blocks it uses.
    pub verilog: String,
    /// `emc_unit_tb.v`: the self-checking testbench.
    pub testbench: String,
    /// `emc_unit.regs.hex`: the register image for `$readmemh`.
    pub image_hex: String,
    /// `emc_unit.vectors`: the test vectors ([`crate::vectors`] format).
    pub vectors: String,
    /// The register image.
    pub image: Vec<ImageWord>,
    /// The vectors.
    pub vector_list: Vec<Vector>,
}

/// Names of the emitted files.
pub const FILES: [&str; 4] = [
    "emc_unit.v",
    "emc_unit_tb.v",
    "emc_unit.regs.hex",
    "emc_unit.vectors",
];

impl RtlFiles {
    /// Write the four files into `dir` (created if missing).
    pub fn write(&self, dir: &Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        for (name, text) in FILES.iter().zip([
            &self.verilog,
            &self.testbench,
            &self.image_hex,
            &self.vectors,
        ]) {
            std::fs::write(dir.join(name), text)?;
        }
        Ok(())
    }
}

/// Emit the unit's Verilog, image, testbench and the vectors of `boxes`. Boxes must be finite
/// (the unit's domain); units with more than one lane or an iterative sqrt/divide are refused.
pub fn emit(unit: &Unit, boxes: &[Aabb]) -> Result<RtlFiles, HwError> {
    if unit.options().lanes != 1 {
        return Err(HwError::Rtl(format!(
            "RTL is emitted for one lane (got {}); lanes are identical copies",
            unit.options().lanes
        )));
    }
    if unit.lane_ii() != 1 {
        return Err(HwError::Rtl(
            "the iterative sqrt/divide unit has no RTL; use the pipelined one".into(),
        ));
    }
    if let Some(i) = boxes.iter().position(|b| !b.is_finite()) {
        return Err(HwError::Rtl(format!(
            "box {i} is not finite; the unit's domain is finite boxes"
        )));
    }
    let img = image(unit);
    let verilog = Emitter::new(unit, &img).top();
    let vector_list = vectors(unit, boxes);
    let mut image_hex = format!(
        "// register image of emc_unit for {} ({}): one 64-bit word per configuration-bus address\n",
        unit.spec(),
        unit.layout()
    );
    for (addr, w) in img.iter().enumerate() {
        let _ = writeln!(image_hex, "{:016x} // {addr}: {}", w.value, w.name);
    }
    let testbench = testbench(unit, img.len(), vector_list.len());
    Ok(RtlFiles {
        verilog,
        testbench,
        image_hex,
        vectors: to_text(unit, &vector_list),
        image: img,
        vector_list,
    })
}

/// The top-module emitter: a text buffer, unique names and the configuration.
struct Emitter<'a> {
    unit: &'a Unit,
    img: &'a [ImageWord],
    s: String,
    uid: usize,
}

const AX: [char; 3] = ['x', 'y', 'z'];

impl<'a> Emitter<'a> {
    fn new(unit: &'a Unit, img: &'a [ImageWord]) -> Self {
        Emitter {
            unit,
            img,
            s: String::new(),
            uid: 0,
        }
    }

    fn line(&mut self, l: &str) {
        self.s.push_str("  ");
        self.s.push_str(l);
        self.s.push('\n');
    }

    /// `wire [w-1:0] name = expr;`
    fn wire(&mut self, w: u32, name: &str, expr: &str) -> String {
        let l = if w == 1 {
            format!("wire {name} = {expr};")
        } else {
            format!("wire [{}:0] {name} = {expr};", w - 1)
        };
        self.line(&l);
        name.to_string()
    }

    /// A pipeline register of `expr`.
    fn reg(&mut self, w: u32, name: &str, expr: &str) -> String {
        self.line(&format!("reg [{}:0] {name};", w - 1));
        self.line(&format!("always @(posedge clk) {name} <= {expr};"));
        name.to_string()
    }

    /// `expr` delayed by `n` register levels.
    fn delay(&mut self, w: u32, expr: &str, n: u32) -> String {
        let mut cur = expr.to_string();
        for _ in 0..n {
            self.uid += 1;
            let name = format!("dly{}", self.uid);
            cur = self.reg(w, &name, &cur);
        }
        cur
    }

    /// A configuration register from the image, or a constant in a fixed unit.
    fn cfg_regs(&mut self) {
        let mut thr = 0;
        for (addr, w) in self.img.iter().enumerate() {
            if w.name.starts_with("thr[") {
                thr += 1;
                if thr == 1 {
                    let n = self
                        .img
                        .iter()
                        .filter(|x| x.name.starts_with("thr["))
                        .count();
                    self.line(&format!("reg [62:0] thr [1:{n}];"));
                }
                self.line(&format!(
                    "always @(posedge clk) if (cfg_we && cfg_addr == 9'd{addr}) {} <= cfg_data[62:0];",
                    w.name
                ));
                continue;
            }
            self.line(&format!("reg [{}:0] {};", w.width - 1, w.name));
            self.line(&format!(
                "always @(posedge clk) if (cfg_we && cfg_addr == 9'd{addr}) {} <= cfg_data[{}:0];",
                w.name,
                w.width - 1
            ));
        }
        let r = self.unit.registers();
        if matches!(r.net, Network::Fixed { .. }) {
            for a in 0..3 {
                self.wire(7, &format!("nbits_{}", AX[a]), &format!("7'd{}", r.bits[a]));
            }
        } else {
            for a in 0..3 {
                let lo = 7 * a;
                self.wire(
                    7,
                    &format!("nbits_{}", AX[a]),
                    &format!("fields[{}:{}]", lo + 6, lo),
                );
            }
            for (c, n) in ["x", "y", "z", "s"].iter().enumerate() {
                let lo = 21 + 7 * c;
                self.wire(
                    7,
                    &format!("off_{n}"),
                    &format!("fields[{}:{}]", lo + 6, lo),
                );
            }
        }
    }

    /// binary32 → binary64 (exact; subnormal inputs normalised by a leading-one search; the
    /// unit's inputs are finite, so there is no infinity/NaN path).
    fn f32_to_f64(&mut self, p: &str, f: &str) -> String {
        self.wire(8, &format!("{p}_e"), &format!("{f}[30:23]"));
        self.wire(23, &format!("{p}_m"), &format!("{f}[22:0]"));
        let mut lead = "5'd0".to_string();
        for i in 0..23 {
            lead = self.wire(
                5,
                &format!("{p}_l{i}"),
                &format!("{p}_m[{i}] ? 5'd{i} : {lead}"),
            );
        }
        self.wire(
            23,
            &format!("{p}_ms"),
            &format!("{p}_m << (5'd23 - {lead})"),
        );
        self.wire(
            11,
            &format!("{p}_se"),
            &format!("{{6'd0, {lead}}} + 11'd874"),
        );
        self.wire(
            11,
            &format!("{p}_ne"),
            &format!("{{3'd0, {p}_e}} + 11'd896"),
        );
        self.wire(
            64,
            &format!("{p}_d"),
            &format!(
                "({p}_e == 8'd0) ? (({p}_m == 23'd0) ? {{{f}[31], 63'd0}} : {{{f}[31], {p}_se, {p}_ms, 29'd0}}) : \
                 {{{f}[31], {p}_ne, {p}_m, 29'd0}}"
            ),
        )
    }

    /// Float→fixed with clamp to `n` bits (`n` a 7-bit signal or constant), as [`crate::fixed`].
    /// `nan` adds the NaN → 0 rule (only the size formula can form a NaN: `0 / D` with `D = 0`).
    fn f2fix(&mut self, p: &str, v: &str, n: &str, nan: bool) -> String {
        self.wire(
            13,
            &format!("{p}_k"),
            &format!("{{2'b00, {v}[62:52]}} - 13'd1023"),
        );
        self.wire(
            64,
            &format!("{p}_m"),
            &format!("{{11'd0, 1'b1, {v}[51:0]}}"),
        );
        self.wire(
            64,
            &format!("{p}_max"),
            &format!("({n} == 7'd64) ? {{64{{1'b1}}}} : ((64'd1 << {n}) - 64'd1)"),
        );
        self.wire(
            64,
            &format!("{p}_sh"),
            &format!(
                "({p}_k <= 13'd52) ? ({p}_m >> (13'd52 - {p}_k)) : ({p}_m << ({p}_k - 13'd52))"
            ),
        );
        self.wire(
            1,
            &format!("{p}_z"),
            &if nan {
                format!("{v}[63] | ({v}[62:0] > 63'h7ff0000000000000) | {p}_k[12]")
            } else {
                format!("{v}[63] | {p}_k[12]")
            },
        );
        self.wire(
            64,
            &format!("{p}_q"),
            &format!("{p}_z ? 64'd0 : (({p}_k >= {{6'd0, {n}}}) ? {p}_max : {p}_sh)"),
        )
    }

    fn fp_add(&mut self, y: &str, a: &str, b: &str, sub: bool) -> String {
        self.line(&format!("wire [63:0] {y};"));
        self.line(&format!(
            "emc_fp64_add u_{y} (.clk(clk), .a({a}), .b({b}), .sub(1'b{}), .y({y}));",
            sub as u8
        ));
        y.to_string()
    }

    fn fp_mul(&mut self, y: &str, a: &str, b: &str) -> String {
        self.line(&format!("wire [63:0] {y};"));
        self.line(&format!(
            "emc_fp64_mul u_{y} (.clk(clk), .a({a}), .b({b}), .y({y}));"
        ));
        y.to_string()
    }

    /// The comparator key of d² (its pattern when a non-negative number, else 0).
    fn key(&mut self, d2: &str) -> String {
        self.wire(
            63,
            "key0",
            &format!("({d2}[63] | ({d2}[62:0] > 63'h7ff0000000000000)) ? 63'd0 : {d2}[62:0]"),
        )
    }

    /// The `S`-step binary threshold search (one register level per step); returns the size.
    fn search(&mut self, d2: &str, sbits: u32) -> String {
        let mut key = self.key(d2);
        let mut spos = String::new();
        for k in 0..sbits {
            // spos has k decided bits; the candidate index is {spos, 1, 0...}.
            let low = sbits - 1 - k;
            let idx = match (k, low) {
                (0, 0) => "1'b1".to_string(),
                (0, l) => format!("{{1'b1, {l}'d0}}"),
                (_, 0) => format!("{{{spos}, 1'b1}}"),
                (_, l) => format!("{{{spos}, 1'b1, {l}'d0}}"),
            };
            let sel = self.wire(63, &format!("thrsel{k}"), &format!("thr[{idx}]"));
            let ge = self.wire(1, &format!("ge{k}"), &format!("{sel} <= {key}"));
            spos = if k == 0 {
                self.reg(1, "spos1", &ge)
            } else {
                self.reg(
                    k + 1,
                    &format!("spos{}", k + 1),
                    &format!("{{{spos}, {ge}}}"),
                )
            };
            if k + 1 < sbits {
                key = self.reg(63, &format!("key{}", k + 1), &key.clone());
            }
        }
        spos
    }

    /// The comparator bank and population count (two register levels); returns the size.
    fn bank(&mut self, d2: &str, sbits: u32) -> String {
        let t = (1u32 << sbits) - 1;
        let key0 = self.key(d2);
        let mut bits = Vec::new();
        for k in 1..=t {
            bits.push(self.wire(1, &format!("bge{k}"), &format!("thr[{k}] <= {key0}")));
        }
        bits.reverse();
        let v = self.reg(t, "bank", &format!("{{{}}}", bits.join(", ")));
        let sum: Vec<String> = (0..t)
            .map(|k| format!("{{{}'d0, {v}[{k}]}}", sbits))
            .collect();
        let cnt = self.wire(sbits + 1, "popcnt", &sum.join(" + "));
        self.reg(sbits, "qsize", &format!("{cnt}[{}:0]", sbits - 1))
    }

    /// Beneš columns `cols` on the word `w` (controls `ctl<i>`); returns the output word.
    fn benes(
        &mut self,
        w: &str,
        b: &crate::routing::Benes,
        cols: core::ops::Range<usize>,
    ) -> String {
        let lanes = b.lanes();
        let mut w = w.to_string();
        for i in cols {
            let d = b.distance(i);
            // The control of the switch at lower lane p sits at mask bit p (upper lanes 0).
            let mut bits = vec!["1'b0".to_string(); 64];
            for (j, p) in lower_lanes(lanes, d).enumerate() {
                bits[p as usize] = format!("ctl{i}[{j}]");
            }
            bits.reverse();
            let m = self.wire(64, &format!("bm{i}"), &format!("{{{}}}", bits.join(", ")));
            let mh = self.wire(64, &format!("bh{i}"), &format!("{m} << {d}"));
            // Each switch is a pair of 2:1 multiplexers: exchange lanes p and p + d when set.
            w = self.wire(
                64,
                &format!("bw{i}"),
                &format!("({w} & ~({m} | {mh})) | (({w} >> {d}) & {m}) | (({w} << {d}) & {mh})"),
            );
        }
        w
    }

    /// The crossbar on `w` (selects packed in `sel<k>` words); returns the output word.
    fn crossbar(&mut self, w: &str, lanes: u32) -> String {
        let sb = sel_bits(lanes);
        let per = sels_per_word(lanes);
        let mut bits = Vec::new();
        for j in 0..lanes {
            let (wd, k) = (j / per, j % per);
            let lo = k * sb;
            bits.push(self.wire(
                1,
                &format!("xb{j}"),
                &format!("{w}[sel{wd}[{}:{}]]", lo + sb - 1, lo),
            ));
        }
        bits.reverse();
        let pad = if lanes < 64 {
            format!("{}'d0, ", 64 - lanes)
        } else {
            String::new()
        };
        self.wire(64, "xbar", &format!("{{{pad}{}}}", bits.join(", ")))
    }

    /// The whole file: the arithmetic blocks used, then `emc_unit`.
    fn top(mut self) -> String {
        let u = self.unit;
        let r = u.registers();
        let size = !matches!(r.size, SizeUnit::None);
        let axes: Vec<usize> = (0..3).filter(|&a| r.axis_on[a]).collect();
        // Which boxes fields the datapath reads: positions of active axes, all three with size.
        let need: Vec<usize> = if size { vec![0, 1, 2] } else { axes.clone() };
        self.s.push_str(&format!(
            "// emc_unit: {} ({}), {} — emitted by emc-hwsim; depth {} cycles, II 1.\n",
            u.spec(),
            u.layout(),
            r.net.name(),
            u.depth()
        ));
        self.s.push_str(
            "module emc_unit (
  input clk,
  input rst,
  input cfg_we,
  input [8:0] cfg_addr,
  input [63:0] cfg_data,
  input in_valid,
  input [191:0] in_box,
  output out_valid,
  output [63:0] out_code
);
",
        );
        self.cfg_regs();
        // Valid bits travel beside the data; data registers run freely.
        let mut valid = "in_valid".to_string();
        let mut lo = vec![String::new(); 3];
        let mut hi = vec![String::new(); 3];
        let mut pos: Vec<String> = vec![String::new(); 3];
        let mut dl: Vec<String> = vec![String::new(); 3];
        let mut acc = String::new();
        let mut d2 = String::new();
        let mut sd = String::new();
        let mut qs = String::new();
        let mut word = String::new();
        let sbits = r.size_bits();
        for st in u.stages() {
            self.line(&format!(
                "// stage {} ({} cycles): {}",
                st.name, st.latency, st.hw
            ));
            let lat = st.latency;
            match st.op {
                Op::Unpack => {
                    for &a in &need {
                        lo[a] = self.reg(
                            32,
                            &format!("lo_{}", AX[a]),
                            &format!("in_box[{}:{}]", 32 * a + 31, 32 * a),
                        );
                        hi[a] = self.reg(
                            32,
                            &format!("hi_{}", AX[a]),
                            &format!("in_box[{}:{}]", 32 * a + 127, 32 * a + 96),
                        );
                    }
                }
                Op::Centre => {
                    for &a in &need {
                        let l = self.f32_to_f64(&format!("lo{}", AX[a]), &lo[a].clone());
                        let h = self.f32_to_f64(&format!("hi{}", AX[a]), &hi[a].clone());
                        if r.axis_on[a] {
                            pos[a] = self.fp_add(&format!("c2_{}", AX[a]), &l, &h, false);
                        }
                        if size {
                            dl[a] = self.fp_add(&format!("dl_{}", AX[a]), &h, &l, true);
                        }
                    }
                }
                Op::Offset => {
                    for &a in &need {
                        if r.axis_on[a] {
                            pos[a] = self.fp_add(
                                &format!("c2o_{}", AX[a]),
                                &pos[a].clone(),
                                &format!("origin2_{}", AX[a]),
                                true,
                            );
                        }
                        if size {
                            let d = dl[a].clone();
                            dl[a] = self.fp_mul(&format!("sq_{}", AX[a]), &d, &d);
                        }
                    }
                }
                Op::Scale => {
                    for &a in &axes {
                        pos[a] = self.fp_mul(
                            &format!("sc_{}", AX[a]),
                            &pos[a].clone(),
                            &format!("scale_{}", AX[a]),
                        );
                    }
                    if size {
                        acc = self.fp_add("acc", &dl[0].clone(), &dl[1].clone(), false);
                        dl[2] = self.delay(64, &dl[2].clone(), lat);
                    }
                }
                Op::Fix => {
                    for &a in &axes {
                        let q = self.f2fix(
                            &format!("fx{}", AX[a]),
                            &pos[a].clone(),
                            &format!("nbits_{}", AX[a]),
                            false,
                        );
                        let q = self.reg(64, &format!("q_{}", AX[a]), &q);
                        pos[a] = self.delay(64, &q, lat - 1);
                    }
                    if size {
                        d2 = self.fp_add("d2", &acc.clone(), &dl[2].clone(), false);
                    }
                }
                Op::SearchStep(k) => {
                    if k == 0 {
                        qs = self.search(&d2.clone(), sbits);
                    }
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), 1);
                    }
                }
                Op::Bank => {
                    qs = self.bank(&d2.clone(), sbits);
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), 2);
                    }
                }
                Op::Sqrt | Op::Sqrt2 => {
                    let input = if st.op == Op::Sqrt {
                        d2.clone()
                    } else {
                        sd.clone()
                    };
                    self.uid += 1;
                    let y = format!("sqrt{}", self.uid);
                    self.line(&format!("wire [63:0] {y};"));
                    self.line(&format!(
                        "emc_fp64_sqrt u_{y} (.clk(clk), .x({input}), .y({y}));"
                    ));
                    sd = y;
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), lat);
                    }
                }
                Op::Div => {
                    self.line("wire [63:0] quot;");
                    self.line(&format!(
                        "emc_fp64_div u_div (.clk(clk), .a({sd}), .b(diag), .y(quot));"
                    ));
                    sd = "quot".into();
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), lat);
                    }
                }
                Op::SizeScale => {
                    let e = self.wire(11, "sse", &format!("{sd}[62:52]"));
                    let ep = self.wire(11, "ssep", &format!("{e} + 11'd{sbits}"));
                    let y = self.wire(
                        64,
                        "ssy",
                        &format!("(({e} == 11'd0) | ({e} == 11'h7ff)) ? {sd} : {{{sd}[63], {ep}, {sd}[51:0]}}"),
                    );
                    sd = self.reg(64, "sscaled", &y);
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), 1);
                    }
                }
                Op::SizeFix => {
                    let q = self.f2fix("fxs", &sd.clone(), &format!("7'd{sbits}"), true);
                    qs = self.reg(sbits, "qsize", &format!("{q}[{}:0]", sbits - 1));
                    for &a in &axes {
                        pos[a] = self.delay(64, &pos[a].clone(), 1);
                    }
                }
                Op::Route(from, to) => {
                    let mut w = if from == 0 {
                        let mut parts = Vec::new();
                        for &a in &axes {
                            parts.push(format!("({} << off_{})", pos[a], AX[a]));
                        }
                        if size {
                            parts.push(format!("({{{}'d0, {qs}}} << off_s)", 64 - sbits));
                        }
                        if parts.is_empty() {
                            parts.push("64'd0".into());
                        }
                        self.wire(64, "pword", &parts.join(" | "))
                    } else {
                        word.clone()
                    };
                    match &r.net {
                        Network::Benes(b) => w = self.benes(&w, b, from as usize..to as usize),
                        Network::Crossbar(x) => w = self.crossbar(&w, x.lanes()),
                        Network::Fixed { .. } => {}
                    }
                    self.uid += 1;
                    word = self.reg(64, &format!("route{}", self.uid), &w);
                }
                Op::Pack => {
                    let code = match &r.net {
                        Network::Fixed { src, .. } => {
                            // Constant field offsets: every code bit is one wire of a channel.
                            let mut off = [0u32; 4];
                            off.copy_from_slice(&r.offset);
                            let mut bits = Vec::new();
                            for j in (0..64).rev() {
                                if j >= r.len as usize {
                                    bits.push("1'b0".to_string());
                                    continue;
                                }
                                let p = src[j] as u32;
                                // The channel whose field holds packed bit p.
                                let c = (0..4)
                                    .find(|&c| {
                                        r.bits[c] > 0 && p >= off[c] && p < off[c] + r.bits[c]
                                    })
                                    .expect("a fixed pattern's packed bit lies in a field");
                                let v = if c == 3 { qs.clone() } else { pos[c].clone() };
                                bits.push(format!("{v}[{}]", p - off[c]));
                            }
                            self.wire(64, "wired", &format!("{{{}}}", bits.join(", ")))
                        }
                        _ => word.clone(),
                    };
                    word = self.reg(64, "code", &code);
                }
            }
            valid = self.delay_valid(&valid, lat);
        }
        self.line(&format!("assign out_valid = {valid};"));
        self.line(&format!("assign out_code = {word};"));
        self.s.push_str("endmodule\n\n");
        let mut lib = String::new();
        lib.push_str(&arith::fp64_add());
        lib.push_str(&arith::fp64_mul());
        if let SizeUnit::Formula { .. } = r.size {
            lib.push_str(&arith::fp64_sqrt(SQRT_DIV_PIPELINED_LATENCY as usize));
            lib.push_str(&arith::fp64_div(SQRT_DIV_PIPELINED_LATENCY as usize));
        }
        self.s.push_str(&lib);
        self.s
    }

    /// The valid bit through `n` register levels with synchronous reset.
    fn delay_valid(&mut self, v: &str, n: u32) -> String {
        let mut cur = v.to_string();
        for _ in 0..n {
            self.uid += 1;
            let name = format!("v{}", self.uid);
            self.line(&format!("reg {name};"));
            self.line(&format!(
                "always @(posedge clk) {name} <= rst ? 1'b0 : {cur};"
            ));
            cur = name;
        }
        cur
    }
}

/// The self-checking testbench: loads the image over the configuration bus, offers each
/// vector's box at its cycle and checks every output cycle against the vectors (a code where
/// one is due, none elsewhere). Prints `PASS n vectors` or `FAIL …` and finishes.
fn testbench(unit: &Unit, words: usize, nv: usize) -> String {
    // Room for external vector files of up to 4096 boxes (override NV for more).
    let nv = nv.max(4096);
    format!(
        "// emc_unit_tb: self-checking testbench of emc_unit for {spec}; expected codes and cycles from
// the model (emc_unit.vectors). Plusargs: +vectors=FILE +regs=FILE.
`timescale 1ns/1ps
module emc_unit_tb;
  parameter NV = {nv};
  parameter NW = {words};
  reg clk = 1'b0;
  always #5 clk = ~clk;
  reg rst = 1'b1;
  reg cfg_we = 1'b0;
  reg [8:0] cfg_addr = 9'd0;
  reg [63:0] cfg_data = 64'd0;
  reg in_valid = 1'b0;
  reg [191:0] in_box = 192'd0;
  wire out_valid;
  wire [63:0] out_code;
  emc_unit dut (.clk(clk), .rst(rst), .cfg_we(cfg_we), .cfg_addr(cfg_addr), .cfg_data(cfg_data),
                .in_valid(in_valid), .in_box(in_box), .out_valid(out_valid), .out_code(out_code));
  reg [63:0] img [0:NW];
  reg [191:0] vbox [0:NV-1];
  reg [63:0] vcode [0:NV-1];
  integer vin [0:NV-1];
  integer vout [0:NV-1];
  reg [31:0] f0, f1, f2, f3, f4, f5;
  reg [63:0] c;
  integer fd, rc, ch, n, i, cyc, ni, no, errors, last;
  reg [8*256-1:0] fname;
  reg [8*256-1:0] rname;
  reg [8*1024-1:0] skip;
  initial begin
    if (!$value$plusargs(\"vectors=%s\", fname)) fname = \"emc_unit.vectors\";
    if (!$value$plusargs(\"regs=%s\", rname)) rname = \"emc_unit.regs.hex\";
    $readmemh(rname, img, 0, NW - 1);
    fd = $fopen(fname, \"r\");
    if (fd == 0) begin
      $display(\"FAIL cannot open the vectors file\");
      $finish;
    end
    n = 0;
    ch = $fgetc(fd);
    while (ch != -1) begin
      if (ch == 35 || ch == 10) begin
        if (ch == 35) rc = $fgets(skip, fd);
      end else begin
        rc = $ungetc(ch, fd);
        if (n >= NV) begin
          $display(\"FAIL more than NV = %0d vectors; rerun with a larger NV\", NV);
          $finish;
        end
        rc = $fscanf(fd, \"%h %h %h %h %h %h %h %d %d\\n\", f0, f1, f2, f3, f4, f5, c, vin[n], vout[n]);
        if (rc != 9) begin
          $display(\"FAIL malformed vector line %0d\", n + 1);
          $finish;
        end
        vbox[n] = {{f5, f4, f3, f2, f1, f0}};
        vcode[n] = c;
        n = n + 1;
      end
      ch = $fgetc(fd);
    end
    $fclose(fd);
    last = (n > 0) ? vout[n - 1] : 0;
    errors = 0;
    // Reset, then one image word per cycle over the configuration bus.
    @(negedge clk);
    @(negedge clk);
    rst = 1'b0;
    for (i = 0; i < NW; i = i + 1) begin
      cfg_we = 1'b1;
      cfg_addr = i;
      cfg_data = img[i];
      @(negedge clk);
    end
    cfg_we = 1'b0;
    ni = 0;
    no = 0;
    for (cyc = 0; cyc <= last + 4; cyc = cyc + 1) begin
      // Outputs of this cycle (registered at the previous edge), then this cycle's input.
      if (out_valid) begin
        if (no < n && vout[no] == cyc && out_code === vcode[no]) begin
          no = no + 1;
        end else begin
          if (errors < 10)
            $display(\"MISMATCH cycle %0d: got %h, expected vector %0d code %h at cycle %0d\",
                     cyc, out_code, no, (no < n) ? vcode[no] : 64'd0, (no < n) ? vout[no] : -1);
          errors = errors + 1;
          no = no + 1;
        end
      end else if (no < n && vout[no] == cyc) begin
        if (errors < 10) $display(\"MISSING code of vector %0d at cycle %0d\", no, cyc);
        errors = errors + 1;
        no = no + 1;
      end
      if (ni < n && vin[ni] == cyc) begin
        in_valid = 1'b1;
        in_box = vbox[ni];
        ni = ni + 1;
      end else begin
        in_valid = 1'b0;
      end
      @(negedge clk);
    end
    if (errors == 0 && no == n && ni == n)
      $display(\"PASS %0d vectors, depth {depth}, II {ii}\", n);
    else
      $display(\"FAIL %0d errors in %0d vectors\", errors, n);
    $finish;
  end
endmodule
",
        spec = unit.spec(),
        depth = unit.depth(),
        ii = unit.lane_ii(),
    )
}

/// One block of the configured unit as a module of its own, for synthesis: the same emitter
/// code as in `emc_unit`, with the block's operands (and configuration registers) as ports.
#[derive(Clone, Debug)]
pub struct BlockSource {
    /// Module name.
    pub module: String,
    /// Verilog of the module (and of the blocks it instantiates).
    pub verilog: String,
    /// Instances of the block in the unit.
    pub instances: u32,
    /// Pipeline stages the model gives the block (register levels inside it; a combinational
    /// block with `n` stages is split over `n` cycles in the unit).
    pub stages: u32,
}

impl<'a> Emitter<'a> {
    /// A wrapper module around an emitter body.
    fn module(name: &str, ports: &str, body: &str) -> String {
        format!("module {name} (\n{ports}\n);\n{body}endmodule\n\n")
    }
}

/// The blocks of a unit as separate modules (only those the configuration instantiates): the
/// fp64 adder and multiplier, the square root and divider, binary32→binary64, float→fixed,
/// the threshold search or bank, and the Beneš network or crossbar.
pub fn blocks(unit: &Unit) -> Vec<BlockSource> {
    let r = unit.registers();
    let img = image(unit);
    let top = Emitter::new(unit, &img).top();
    let count = |m: &str| top.matches(&format!("{m} u_")).count() as u32;
    let mut v = vec![
        BlockSource {
            module: "emc_fp64_add".into(),
            verilog: arith::fp64_add(),
            instances: count("emc_fp64_add"),
            stages: FP_LATENCY,
        },
        BlockSource {
            module: "emc_fp64_mul".into(),
            verilog: arith::fp64_mul(),
            instances: count("emc_fp64_mul"),
            stages: FP_LATENCY,
        },
    ];
    if let SizeUnit::Formula { .. } = r.size {
        let l = SQRT_DIV_PIPELINED_LATENCY;
        v.push(BlockSource {
            module: "emc_fp64_sqrt".into(),
            verilog: arith::fp64_sqrt(l as usize),
            instances: count("emc_fp64_sqrt"),
            stages: l,
        });
        v.push(BlockSource {
            module: "emc_fp64_div".into(),
            verilog: arith::fp64_div(l as usize),
            instances: count("emc_fp64_div"),
            stages: l,
        });
    }
    let body = |f: &mut dyn FnMut(&mut Emitter) -> String| {
        let mut e = Emitter::new(unit, &img);
        let out = f(&mut e);
        e.line(&format!("assign y = {out};"));
        e.s
    };
    let n_conv = top.matches("_se = ").count() as u32;
    v.push(BlockSource {
        module: "blk_f32_to_f64".into(),
        verilog: Emitter::module(
            "blk_f32_to_f64",
            "  input [31:0] f,\n  output [63:0] y",
            &body(&mut |e| e.f32_to_f64("cv", "f")),
        ),
        instances: n_conv,
        stages: 0,
    });
    let axes = r.axis_on.iter().filter(|&&a| a).count() as u32;
    v.push(BlockSource {
        module: "blk_f2fix".into(),
        verilog: Emitter::module(
            "blk_f2fix",
            "  input [63:0] v,\n  input [6:0] n,\n  output [63:0] y",
            &body(&mut |e| e.f2fix("fx", "v", "n", false)),
        ),
        instances: axes,
        stages: 1,
    });
    if let SizeUnit::Thresholds { bits, .. } = &r.size {
        let t = (1u32 << bits) - 1;
        let mut decl = format!("  wire [62:0] thr [1:{t}];\n");
        for k in 1..=t {
            decl.push_str(&format!(
                "  assign thr[{k}] = thr_flat[{}:{}];\n",
                63 * k - 1,
                63 * (k - 1)
            ));
        }
        let bank = unit.stages().iter().any(|s| s.op == Op::Bank);
        let name = if bank { "blk_bank" } else { "blk_search" };
        let b = *bits;
        let inner = body(&mut |e| {
            if bank {
                e.bank("d2", b)
            } else {
                e.search("d2", b)
            }
        });
        v.push(BlockSource {
            module: name.into(),
            verilog: Emitter::module(
                name,
                &format!(
                    "  input clk,\n  input [63:0] d2,\n  input [{}:0] thr_flat,\n  output [{}:0] y",
                    63 * t - 1,
                    b - 1
                ),
                &format!("{decl}{inner}"),
            ),
            instances: 1,
            stages: if bank { 2 } else { b },
        });
    }
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            let mut ports = String::from("  input [63:0] w,\n");
            for i in 0..b.columns() {
                ports.push_str(&format!("  input [{}:0] ctl{i},\n", b.lanes() / 2 - 1));
            }
            ports.push_str("  output [63:0] y");
            let cols = b.columns();
            v.push(BlockSource {
                module: "blk_benes".into(),
                verilog: Emitter::module(
                    "blk_benes",
                    &ports,
                    &body(&mut |e| e.benes("w", b, 0..cols)),
                ),
                instances: 1,
                stages: 2,
            });
        }
        Network::Crossbar(x) => {
            let lanes = x.lanes();
            let words = lanes.div_ceil(sels_per_word(lanes));
            let mut ports = String::from("  input [63:0] w,\n");
            for k in 0..words {
                ports.push_str(&format!("  input [63:0] sel{k},\n"));
            }
            ports.push_str("  output [63:0] y");
            v.push(BlockSource {
                module: "blk_crossbar".into(),
                verilog: Emitter::module(
                    "blk_crossbar",
                    &ports,
                    &body(&mut |e| e.crossbar("w", lanes)),
                ),
                instances: 1,
                stages: 1,
            });
        }
    }
    v.retain(|b| b.instances > 0);
    v
}
