//! The Verilog-2005 arithmetic blocks the emitted unit instantiates: the 3-stage fp64 adder and
//! multiplier, and the pipelined fp64 divider and square root (digit recurrences unrolled over
//! the model's stage count). Each is written one wire per signal, so that the mutation test can
//! swap any single wire, and each is emitted only when the configuration uses it.
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

use core::fmt::Write;

/// The 3-stage fp64 adder/subtractor `y = a ± b`, round to nearest even.
///
/// Stage 1 swaps by magnitude and aligns the smaller significand with guard, round and sticky
/// bits; stage 2 adds or subtracts and counts leading zeros; stage 3 normalises and rounds.
pub fn fp64_add() -> String {
    let mut s = String::from(
        "// emc_fp64_add: y = a + b (sub = 0) or a - b (sub = 1), round to nearest even, 3 stages.
module emc_fp64_add (
  input clk,
  input [63:0] a,
  input [63:0] b,
  input sub,
  output [63:0] y
);
  wire sa = a[63];
  wire sb = b[63] ^ sub;
  wire [10:0] ea = a[62:52];
  wire [10:0] eb = b[62:52];
  wire za = (ea == 11'd0);
  wire zb = (eb == 11'd0);
  wire [52:0] ma = za ? 53'd0 : {1'b1, a[51:0]};
  wire [52:0] mb = zb ? 53'd0 : {1'b1, b[51:0]};
  wire swap = {eb, mb} > {ea, ma};
  wire [10:0] el = swap ? eb : ea;
  wire [10:0] es = swap ? ea : eb;
  wire [52:0] ml = swap ? mb : ma;
  wire [52:0] ms = swap ? ma : mb;
  wire sl = swap ? sb : sa;
  wire [10:0] d = el - es;
  wire [55:0] msx = {ms, 3'b000};
  wire far = (d > 11'd55);
  wire [55:0] msh = far ? 56'd0 : (msx >> d);
  wire [55:0] lost = far ? {56{1'b1}} : ((56'd1 << d) - 56'd1);
  wire stk = |(msx & lost);
  wire [55:0] msa = {msh[55:1], msh[0] | stk};
  wire eff = sa ^ sb;
  wire bz = za & zb;
  reg s1_sl, s1_eff, s1_bz;
  reg [10:0] s1_el;
  reg [52:0] s1_ml;
  reg [55:0] s1_ms;
  always @(posedge clk) begin
    s1_sl <= sl;
    s1_eff <= eff;
    s1_bz <= bz;
    s1_el <= el;
    s1_ml <= ml;
    s1_ms <= msa;
  end
  wire [56:0] mlx = {1'b0, s1_ml, 3'b000};
  wire [56:0] msx2 = {1'b0, s1_ms};
  wire [56:0] sum = s1_eff ? (mlx - msx2) : (mlx + msx2);
",
    );
    // Leading-zero count of the 57-bit sum as one priority chain of wires. Bits 1 and 0 never
    // lead: they are non-zero only when the smaller operand was shifted by d >= 2, and then
    // the difference keeps its leading one at bit 54 or above (a zero sum is flagged apart).
    let _ = writeln!(s, "  wire [6:0] lz57 = 7'd57;");
    let mut prev = "lz57".to_string();
    for i in 2..57 {
        let name = format!("lz{i}");
        let _ = writeln!(
            s,
            "  wire [6:0] {name} = sum[{i}] ? 7'd{} : {prev};",
            56 - i
        );
        prev = name;
    }
    let _ = write!(
        s,
        "  reg s2_sl, s2_bz;
  reg [10:0] s2_el;
  reg [56:0] s2_sum;
  reg [6:0] s2_lz;
  always @(posedge clk) begin
    s2_sl <= s1_sl;
    s2_bz <= s1_bz;
    s2_el <= s1_el;
    s2_sum <= sum;
    s2_lz <= {prev};
  end
  wire [55:0] nsh = s2_sum[55:0] << (s2_lz - 7'd1);
  wire [55:0] nrm = (s2_lz == 7'd0) ? {{s2_sum[56:2], s2_sum[1] | s2_sum[0]}} : nsh;
  wire [12:0] ex = {{2'b00, s2_el}} + 13'd1 - {{6'd0, s2_lz}};
  wire [52:0] mt = nrm[55:3];
  wire up = nrm[2] & (nrm[1] | nrm[0] | mt[0]);
  wire [53:0] mr = {{1'b0, mt}} + {{53'd0, up}};
  wire [12:0] ex2 = ex + {{12'd0, mr[53]}};
  wire [51:0] fr = mr[53] ? mr[52:1] : mr[51:0];
  wire zero = (s2_sum == 57'd0);
  wire [63:0] res = (s2_bz | zero) ? 64'd0 : {{s2_sl, ex2[10:0], fr}};
  reg [63:0] s3;
  always @(posedge clk) s3 <= res;
  assign y = s3;
endmodule

"
    );
    s
}

/// The 3-stage fp64 multiplier, round to nearest even: stage 1 forms two 53×27 partial
/// products, stage 2 adds them, stage 3 normalises and rounds.
pub fn fp64_mul() -> String {
    "// emc_fp64_mul: y = a * b, round to nearest even, 3 stages.
module emc_fp64_mul (
  input clk,
  input [63:0] a,
  input [63:0] b,
  output [63:0] y
);
  wire za = (a[62:52] == 11'd0);
  wire zb = (b[62:52] == 11'd0);
  wire [52:0] ma = {1'b1, a[51:0]};
  wire [52:0] mb = {1'b1, b[51:0]};
  wire [79:0] plo = ma * mb[26:0];
  wire [78:0] phi = ma * mb[52:27];
  wire [12:0] es = {2'b00, a[62:52]} + {2'b00, b[62:52]};
  wire sg = a[63] ^ b[63];
  wire z = za | zb;
  reg [79:0] s1_lo;
  reg [78:0] s1_hi;
  reg [12:0] s1_es;
  reg s1_s, s1_z;
  always @(posedge clk) begin
    s1_lo <= plo;
    s1_hi <= phi;
    s1_es <= es;
    s1_s <= sg;
    s1_z <= z;
  end
  wire [105:0] p = {26'd0, s1_lo} + {s1_hi, 27'd0};
  reg [105:0] s2_p;
  reg [12:0] s2_es;
  reg s2_s, s2_z;
  always @(posedge clk) begin
    s2_p <= p;
    s2_es <= s1_es;
    s2_s <= s1_s;
    s2_z <= s1_z;
  end
  wire hi = s2_p[105];
  wire [52:0] mt = hi ? s2_p[105:53] : s2_p[104:52];
  wire g = hi ? s2_p[52] : s2_p[51];
  wire st = hi ? (|s2_p[51:0]) : (|s2_p[50:0]);
  wire up = g & (st | mt[0]);
  wire [53:0] mr = {1'b0, mt} + {53'd0, up};
  wire [12:0] ex = s2_es - 13'd1023 + {12'd0, hi} + {12'd0, mr[53]};
  wire [51:0] fr = mr[53] ? mr[52:1] : mr[51:0];
  wire [63:0] res = s2_z ? 64'd0 : {s2_s, ex[10:0], fr};
  reg [63:0] s3;
  always @(posedge clk) s3 <= res;
  assign y = s3;
endmodule

"
    .to_string()
}

/// Which iterations of an `n`-step recurrence stage `s` of `stages` performs.
fn stage_range(n: usize, stages: usize, s: usize) -> core::ops::Range<usize> {
    n * s / stages..n * (s + 1) / stages
}

/// Emit register copies of the carried signals at a stage boundary; returns the new names.
fn boundary(s: &mut String, stage: usize, carried: &[(String, u32)]) -> Vec<(String, u32)> {
    let mut out = Vec::new();
    for (name, w) in carried {
        let r = format!("{}_r{stage}", name.split('_').next().unwrap_or(name));
        let _ = writeln!(s, "  reg [{}:0] {r};", w - 1);
        let _ = writeln!(s, "  always @(posedge clk) {r} <= {name};");
        out.push((r, *w));
    }
    out
}

/// The final rounding of a 53-bit significand with guard and sticky, shared by the divider and
/// the square root: writes `res` from `sp` (0 normal, 1 zero, 2 infinity, 3 NaN, 4 pass `x`).
fn round_tail(s: &mut String, mt: &str, g: &str, st: &str, ex: &str, sp: &str) {
    let _ = write!(
        s,
        "  wire up = {g} & ({st} | {mt}[0]);
  wire [53:0] mr = {{1'b0, {mt}}} + {{53'd0, up}};
  wire [12:0] exf = {ex} + {{12'd0, mr[53]}};
  wire [51:0] fr = mr[53] ? mr[52:1] : mr[51:0];
  wire [63:0] res = ({sp} == 3'd1) ? 64'd0 :
                    ({sp} == 3'd2) ? 64'h7ff0000000000000 :
                    ({sp} == 3'd3) ? 64'h7ff8000000000000 :
                    {{1'b0, exf[10:0], fr}};
"
    );
}

/// The fp64 divider `y = a / b` over `stages` pipeline registers: a restoring division of the
/// significands producing 55 quotient bits (one a stage-local wire each) and a sticky
/// remainder, then round to nearest even. `b = 0` gives +infinity (NaN for `0/0`).
pub fn fp64_div(stages: usize) -> String {
    let mut s = format!(
        "// emc_fp64_div: y = a / b, round to nearest even, {stages} stages (restoring, 55 quotient bits).
module emc_fp64_div (
  input clk,
  input [63:0] a,
  input [63:0] b,
  output [63:0] y
);
  wire za = (a[62:52] == 11'd0);
  wire zb = (b[62:52] == 11'd0);
  wire [54:0] r0 = {{2'b00, 1'b1, a[51:0]}};
  wire [52:0] dv = {{1'b1, b[51:0]}};
  wire [12:0] ex = {{2'b00, a[62:52]}} - {{2'b00, b[62:52]}} + 13'd1023;
  wire [2:0] sp = zb ? (za ? 3'd3 : 3'd2) : (za ? 3'd1 : 3'd0);
  wire [54:0] q0 = 55'd0;
"
    );
    let n = 55;
    let mut r = "r0".to_string();
    let mut q = "q0".to_string();
    let mut carried_ctx = vec![
        ("dv".to_string(), 53u32),
        ("ex".to_string(), 13),
        ("sp".to_string(), 3),
    ];
    for st in 0..stages {
        for i in stage_range(n, stages, st) {
            let dvn = &carried_ctx[0].0;
            let _ = writeln!(s, "  wire ge{i} = {r} >= {{2'b00, {dvn}}};");
            let _ = writeln!(
                s,
                "  wire [54:0] rs{i} = ge{i} ? ({r} - {{2'b00, {dvn}}}) : {r};"
            );
            let _ = writeln!(s, "  wire [54:0] r{} = {{rs{i}[53:0], 1'b0}};", i + 1);
            let _ = writeln!(s, "  wire [54:0] q{} = {{{q}[53:0], ge{i}}};", i + 1);
            r = format!("r{}", i + 1);
            q = format!("q{}", i + 1);
        }
        if st + 1 < stages {
            let mut all = vec![(r.clone(), 55u32), (q.clone(), 55)];
            all.extend(carried_ctx.iter().cloned());
            let regs = boundary(&mut s, st + 1, &all);
            r = regs[0].0.clone();
            q = regs[1].0.clone();
            carried_ctx = regs[2..].to_vec();
        }
    }
    let (ex, sp) = (&carried_ctx[1].0, &carried_ctx[2].0);
    let _ = writeln!(s, "  wire hi = {q}[54];");
    let _ = writeln!(s, "  wire [52:0] mt = hi ? {q}[54:2] : {q}[53:1];");
    let _ = writeln!(s, "  wire g = hi ? {q}[1] : {q}[0];");
    let _ = writeln!(s, "  wire st = (hi & {q}[0]) | ({r} != 55'd0);");
    let _ = writeln!(s, "  wire [12:0] exn = {ex} - {{12'd0, ~hi}};");
    round_tail(&mut s, "mt", "g", "st", "exn", sp);
    s.push_str(
        "  reg [63:0] yo;\n  always @(posedge clk) yo <= res;\n  assign y = yo;\nendmodule\n\n",
    );
    s
}

/// The fp64 square root over `stages` pipeline registers: the bit-pair restoring recurrence on
/// the significand (made even-exponent) shifted by 56, giving a 55-bit root and a sticky
/// remainder, then round to nearest even. Zero gives +0; infinity and NaN pass.
pub fn fp64_sqrt(stages: usize) -> String {
    let mut s = format!(
        "// emc_fp64_sqrt: y = sqrt(x), round to nearest even, {stages} stages (restoring, 55 root bits).
module emc_fp64_sqrt (
  input clk,
  input [63:0] x,
  output [63:0] y
);
  wire [10:0] e = x[62:52];
  wire [53:0] rx = e[0] ? {{2'b01, x[51:0]}} : {{1'b1, x[51:0], 1'b0}};
  wire [12:0] ex = ({{2'b00, e}} + 13'd1023) >> 1;
  wire [2:0] sp = (e == 11'd0) ? 3'd1 : ((e == 11'h7ff) ? 3'd4 : 3'd0);
  wire [63:0] xp = x;
  wire [58:0] m0 = 59'd0;
  wire [54:0] t0 = 55'd0;
"
    );
    let n = 55;
    let mut m = "m0".to_string();
    let mut t = "t0".to_string();
    let mut ctx = vec![
        ("rx".to_string(), 54u32),
        ("ex".to_string(), 13),
        ("sp".to_string(), 3),
        ("xp".to_string(), 64),
    ];
    for st in 0..stages {
        for i in stage_range(n, stages, st) {
            let rx = &ctx[0].0;
            // Pairs of the radicand rx << 56, MSB first: rx's 27 pairs, then zeros.
            let pair = if i < 27 {
                format!("{rx}[{}:{}]", 53 - 2 * i, 52 - 2 * i)
            } else {
                "2'b00".to_string()
            };
            let _ = writeln!(s, "  wire [58:0] rp{i} = {{{m}[56:0], {pair}}};");
            let _ = writeln!(s, "  wire [58:0] tr{i} = {{2'b00, {t}, 2'b01}};");
            let _ = writeln!(s, "  wire ge{i} = rp{i} >= tr{i};");
            let _ = writeln!(
                s,
                "  wire [58:0] m{} = ge{i} ? (rp{i} - tr{i}) : rp{i};",
                i + 1
            );
            let _ = writeln!(s, "  wire [54:0] t{} = {{{t}[53:0], ge{i}}};", i + 1);
            m = format!("m{}", i + 1);
            t = format!("t{}", i + 1);
        }
        if st + 1 < stages {
            let mut all = vec![(m.clone(), 59u32), (t.clone(), 55)];
            all.extend(ctx.iter().cloned());
            let regs = boundary(&mut s, st + 1, &all);
            m = regs[0].0.clone();
            t = regs[1].0.clone();
            ctx = regs[2..].to_vec();
        }
    }
    let (ex, sp, xp) = (&ctx[1].0, &ctx[2].0, &ctx[3].0);
    let _ = writeln!(s, "  wire [52:0] mt = {t}[54:2];");
    let _ = writeln!(s, "  wire g = {t}[1];");
    let _ = writeln!(s, "  wire st = {t}[0] | ({m} != 59'd0);");
    round_tail(&mut s, "mt", "g", "st", ex, sp);
    let _ = writeln!(s, "  wire [63:0] resp = ({sp} == 3'd4) ? {xp} : res;");
    s.push_str(
        "  reg [63:0] yo;\n  always @(posedge clk) yo <= resp;\n  assign y = yo;\nendmodule\n\n",
    );
    s
}
