//! Verilog of exactly the configured unit: the model's stage list, stage for stage, as
//! synthesisable Verilog-2005, with the register image that programs it, a self-checking
//! testbench and a vectors file ([`crate::vectors`]).
//!
//! One description per block: every stage of [`Unit::stages`] is a [`crate::blocks::Block`]
//! whose `eval` is the model's behaviour, whose `emit` writes its Verilog in the netlist
//! language of [`net`] (the same calls give the cost model its gates) and whose `config` gives
//! its words of the register image ([`image`], from which the `$readmemh` file, the Verilog
//! configuration registers and the setup cost ([`crate::setup`]) are all made). Nothing the
//! configuration does not use is emitted: no lane for an axis without bits, no size datapath
//! without size bits, fixed wiring for a regular pattern, a Beneš network or crossbar sized
//! to the code length otherwise.
//!
//! Interface of `emc_unit`: a 64-bit configuration bus (`cfg_we`, `cfg_addr`, `cfg_data`, one
//! image word per cycle), `in_valid`/`in_box` (six binary32 fields, `min.x` in bits 31:0 up to
//! `max.z` in bits 191:160), and `out_valid`/`out_code` `depth` cycles later. The unit accepts
//! a box every cycle (II = 1); the memory port is the model's business, not the RTL's.
#![forbid(unsafe_code)]

pub mod arith;
pub mod net;

use core::fmt::Write;
use std::collections::HashMap;
use std::path::Path;

use emc_core::Aabb;

use crate::blocks::{Field, Signals};
use crate::datapath::{Unit, FP_LATENCY};
use crate::error::HwError;
use crate::vectors::{to_text, vectors, Vector};
use net::{Mod, Price};

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
pub(crate) fn lower_lanes(lanes: u32, d: u32) -> impl Iterator<Item = u32> {
    (0..lanes).filter(move |p| p & d == 0)
}

/// Bits per select of a crossbar with `lanes` outputs.
pub(crate) fn sel_bits(lanes: u32) -> u32 {
    lanes.trailing_zeros()
}

/// Selects per 64-bit configuration word.
pub(crate) fn sels_per_word(lanes: u32) -> u32 {
    64 / sel_bits(lanes)
}

/// The register image of a unit, in configuration-bus address order: every stage's words.
pub fn image(unit: &Unit) -> Vec<ImageWord> {
    unit.stages()
        .iter()
        .flat_map(|s| s.block.config())
        .collect()
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

/// Compile the files [`RtlFiles::write`] put in `dir` with Icarus Verilog (`iverilog -g2005`)
/// and run the testbench (`vvp`) on them, dumping the unit's top-level signals to the VCD file
/// `vcd` when given (the testbench's `+vcd=FILE`; a relative path is taken from the current
/// directory). Returns the testbench's verdict line (`PASS …` or the `FAIL`/`MISMATCH` lines);
/// a failed compilation, a missing simulator or a testbench that does not pass is an error.
pub fn simulate(dir: &Path, vcd: Option<&Path>) -> Result<String, HwError> {
    let run = |cmd: &mut std::process::Command, what: &str| {
        cmd.current_dir(dir).output().map_err(|e| {
            HwError::Rtl(format!(
                "cannot run {what}: {e} (Debian: apt-get install iverilog)"
            ))
        })
    };
    let c = run(
        std::process::Command::new("iverilog").args([
            "-g2005",
            "-o",
            "sim",
            "emc_unit.v",
            "emc_unit_tb.v",
        ]),
        "iverilog",
    )?;
    if !c.status.success() {
        return Err(HwError::Rtl(format!(
            "iverilog failed in {}: {}",
            dir.display(),
            String::from_utf8_lossy(&c.stderr)
        )));
    }
    let mut sim = std::process::Command::new("vvp");
    sim.args(["-n", "sim"]);
    if let Some(v) = vcd {
        let abs = if v.is_absolute() {
            v.to_path_buf()
        } else {
            std::env::current_dir()
                .map_err(|e| HwError::Rtl(e.to_string()))?
                .join(v)
        };
        sim.arg(format!("+vcd={}", abs.display()));
    }
    let r = run(&mut sim, "vvp")?;
    let out = String::from_utf8_lossy(&r.stdout).into_owned();
    let verdict: Vec<&str> = out
        .lines()
        .filter(|l| {
            l.starts_with("PASS")
                || l.starts_with("FAIL")
                || l.starts_with("MISMATCH")
                || l.starts_with("MISSING")
        })
        .collect();
    match verdict.first() {
        Some(l) if l.starts_with("PASS") && r.status.success() => Ok(l.to_string()),
        _ => Err(HwError::Rtl(format!(
            "the testbench did not pass in {}:\n{out}{}",
            dir.display(),
            String::from_utf8_lossy(&r.stderr)
        ))),
    }
}

/// The written unit: the `emc_unit` module (with its library of instantiated modules) and
/// the gate ranges each stage's block created.
#[derive(Debug)]
pub struct Written {
    /// The module.
    pub top: Mod,
    /// Gates of the configuration registers (created before the stages).
    pub config_gates: core::ops::Range<usize>,
    /// Gates each stage created, in stage order.
    pub stage_gates: Vec<core::ops::Range<usize>>,
}

/// Write `emc_unit` for a unit: the configuration registers of [`image`], then every stage's
/// block in order, the valid bits beside them.
pub fn write_unit(unit: &Unit) -> Written {
    let img = image(unit);
    let mut m = Mod::new("emc_unit");
    m.clock();
    let rst = m.input("rst", 1);
    let we = m.input("cfg_we", 1);
    let addr = m.input("cfg_addr", 9);
    let data = m.input("cfg_data", 64);
    let in_valid = m.input("in_valid", 1);
    let in_box = m.input("in_box", 192);
    let c0 = m.gate_count();
    let mut cfg = HashMap::new();
    for (a, w) in img.iter().enumerate() {
        let r = m.cfg_reg(&w.name, w.width, &we, &addr, a as u32, &data);
        cfg.insert(w.name.clone(), r);
    }
    let config_gates = c0..m.gate_count();
    cfg.insert("in_box".to_string(), in_box);
    let mut s = Signals::new(cfg);
    let mut valid = in_valid;
    let mut stage_gates = Vec::new();
    for st in unit.stages() {
        m.comment(&format!(
            "stage {} ({} cycles): {}",
            st.name, st.latency, st.hw
        ));
        let g0 = m.gate_count();
        st.block.emit(&mut m, &mut s);
        for _ in 0..st.latency {
            let n = format!("v{}", m.uid());
            valid = m.reg_rst(&n, &rst, &valid);
        }
        s.advance(st.latency);
        stage_gates.push(g0..m.gate_count());
    }
    let code = s.get(&mut m, Field::Word);
    m.output("out_valid", 1, &valid);
    m.output("out_code", 64, &code);
    Written {
        top: m,
        config_gates,
        stage_gates,
    }
}

/// The unit's Verilog file text: a header line, `emc_unit`, then the modules it instantiates.
fn verilog_of(unit: &Unit, top: &Mod) -> String {
    format!(
        "// emc_unit: {} ({}), {} — emitted by emc-hwsim; depth {} cycles, II 1.\n{}",
        unit.spec(),
        unit.layout(),
        unit.registers().net.name(),
        unit.depth(),
        top.text()
    )
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
    let verilog = verilog_of(unit, &write_unit(unit).top);
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

/// The self-checking testbench: loads the image over the configuration bus, offers each
/// vector's box at its cycle and checks every output cycle against the vectors (a code where
/// one is due, none elsewhere). Prints `PASS n vectors` or `FAIL …` and finishes.
fn testbench(unit: &Unit, words: usize, nv: usize) -> String {
    // Room for external vector files of up to 4096 boxes (override NV for more).
    let nv = nv.max(4096);
    format!(
        "// emc_unit_tb: self-checking testbench of emc_unit for {spec}; expected codes and cycles from
// the model (emc_unit.vectors). Plusargs: +vectors=FILE +regs=FILE, and +vcd=FILE to dump the
// unit's top-level signals (the ports and the wires of emc_unit itself) as a VCD waveform.
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
  reg [8*256-1:0] vname;
  reg [8*1024-1:0] skip;
  initial begin
    if ($value$plusargs(\"vcd=%s\", vname)) begin
      $dumpfile(vname);
      $dumpvars(1, dut);
    end
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

/// One module of the configured unit on its own, for synthesis and block-by-block pricing:
/// exactly the text `emc_unit.v` holds for it, and its gate network.
#[derive(Clone, Debug)]
pub struct BlockSource {
    /// Module name.
    pub module: String,
    /// Verilog of the module (and of the modules it instantiates).
    pub verilog: String,
    /// Instances of the module in the unit.
    pub instances: u32,
    /// Register levels inside the module.
    pub stages: u32,
    /// The model's price of one instance.
    pub price: Price,
}

/// The modules the unit instantiates (only those its configuration uses): the fp64 adder and
/// multiplier, the square root and divider, binary32→binary64, float→fixed, the threshold
/// search or bank, and the Beneš network or crossbar.
pub fn blocks(unit: &Unit) -> Vec<BlockSource> {
    let w = write_unit(unit);
    let top = w.top.text();
    w.top
        .library()
        .into_iter()
        .map(|m| BlockSource {
            module: m.name().to_string(),
            verilog: m.text(),
            instances: top.matches(&format!("{} u_", m.name())).count() as u32,
            stages: m.graph().register_levels(),
            price: m.graph().price(),
        })
        .collect()
}
