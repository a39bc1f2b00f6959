//! Gates against the model: each block of the emitted RTL ([`crate::rtl::blocks`]) and the
//! whole unit synthesised by yosys to the OSU 0.18 µm standard cells (Debian's
//! `qflow-tech-osu018`, `osu018_stdcells.lib`: real timing tables, no tie cells, no enable
//! flip-flops), timed by OpenSTA (`sta`), and set beside the cost model's figures scaled to the
//! same node by the one rule of [`crate::cost::area_at`] / [`crate::cost::delay_at`].
//!
//! Calibration: one block, the fp64 adder, fixes the library factors (the synthesised area and
//! worst stage delay over the rule-scaled model figures); every other block must then sit
//! within ±25 % of the calibrated model, and the table marks those that do not.
#![forbid(unsafe_code)]

use core::fmt;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::cost::{
    area_at, benes_um2, cost, crossbar_um2, delay_at, threshold_search_um2, F2FIX64_UM2,
    FP64_ADD_UM2, FP64_MUL_UM2, SQRT_DIV_PIPELINED_UM2,
};
use crate::datapath::{Network, SizeUnit, Unit};
use crate::error::HwError;
use crate::rtl::{blocks, emit, BlockSource};

/// Default location of the OSU 0.18 µm liberty file in Debian's `qflow-tech-osu018`.
pub const OSU018_LIB: &str = "/usr/share/qflow/tech/osu018/osu018_stdcells.lib";
/// Feature size of the library, nm.
pub const OSU018_NM: f64 = 180.0;

/// Where the tools and the library are.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// The liberty file.
    pub liberty: PathBuf,
    /// Scratch directory (netlists, logs).
    pub work: PathBuf,
    /// ABC's delay target, ps (drives buffering and sizing).
    pub delay_target_ps: u32,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            liberty: PathBuf::from(OSU018_LIB),
            work: std::env::temp_dir().join(format!("emc-synth-{}", std::process::id())),
            delay_target_ps: 4500,
        }
    }
}

/// Synthesis and timing of one module.
#[derive(Clone, Debug, PartialEq)]
pub struct Gates {
    /// Standard cells.
    pub cells: u64,
    /// Cell area, µm².
    pub area_um2: f64,
    /// Cells on the critical path.
    pub depth: u32,
    /// Critical path, ns (the worst register-to-register, input-to-register or
    /// input-to-output path).
    pub delay_ns: f64,
}

/// One row of the comparison.
#[derive(Clone, Debug)]
pub struct Row {
    /// Block (module) name.
    pub name: String,
    /// Instances in the unit.
    pub instances: u32,
    /// Stages the model gives it.
    pub stages: u32,
    /// Synthesised figures of one instance.
    pub gates: Gates,
    /// The model's area of one instance at 40 nm (None: the model does not price it).
    pub model_um2_40: Option<f64>,
    /// The model's delay budget of the block at 40 nm, ns (its stages at 1 GHz).
    pub model_ns_40: Option<f64>,
}

/// The report of a unit.
#[derive(Clone, Debug)]
pub struct SynthReport {
    /// Label of the unit.
    pub label: String,
    /// Per block.
    pub blocks: Vec<Row>,
    /// The whole unit (flattened).
    pub total: Row,
    /// Area calibration factor (synthesised / rule-scaled model) from the fp64 adder.
    pub area_cal: f64,
    /// Delay calibration factor from the fp64 adder.
    pub delay_cal: f64,
}

fn tool(name: &str, args: &[&str], dir: &Path) -> Result<String, HwError> {
    let out = Command::new(name)
        .args(args)
        .current_dir(dir)
        .output()
        .map_err(|e| {
            HwError::Rtl(format!(
                "cannot run {name}: {e} (Debian: apt-get install yosys opensta qflow-tech-osu018)"
            ))
        })?;
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        let tail: Vec<&str> = text.lines().rev().take(15).collect();
        return Err(HwError::Rtl(format!(
            "{name} failed in {}:\n{}",
            dir.display(),
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        )));
    }
    Ok(text)
}

/// Synthesise module `top` of `verilog` (flattened) and time it.
pub fn gates(verilog: &str, top: &str, o: &SynthOptions) -> Result<Gates, HwError> {
    let dir = o.work.join(top);
    std::fs::create_dir_all(&dir).map_err(|e| HwError::Rtl(e.to_string()))?;
    std::fs::write(dir.join("in.v"), verilog).map_err(|e| HwError::Rtl(e.to_string()))?;
    if !o.liberty.is_file() {
        return Err(HwError::Rtl(format!(
            "liberty file {} not found (Debian: apt-get install qflow-tech-osu018)",
            o.liberty.display()
        )));
    }
    let lib = o.liberty.display().to_string();
    let script = format!(
        "read_verilog in.v\n\
         hierarchy -top {top}\n\
         synth -flatten -top {top}\n\
         dfflibmap -liberty {lib}\n\
         abc -D {d} -liberty {lib} -script +strash;dc2;strash;&get,-n;&dch,-f;&nf,{{D}};&put;buffer,-p;upsize,{{D}};dnsize,{{D}};stime,-p\n\
         opt_clean\n\
         stat -liberty {lib}\n\
         write_verilog -noattr -simple-lhs net.v\n",
        d = o.delay_target_ps
    );
    std::fs::write(dir.join("syn.ys"), script).map_err(|e| HwError::Rtl(e.to_string()))?;
    let log = tool("yosys", &["-q", "-l", "syn.log", "syn.ys"], &dir)?;
    let log = std::fs::read_to_string(dir.join("syn.log")).unwrap_or(log);
    let cells = log
        .lines()
        .filter_map(|l| l.trim().strip_prefix("Number of cells:"))
        .next_back()
        .and_then(|v| v.trim().parse().ok())
        .ok_or_else(|| HwError::Rtl(format!("no cell count in {}", dir.display())))?;
    let area_um2 = log
        .lines()
        .rfind(|l| l.contains("Chip area for module"))
        .and_then(|l| l.rsplit(':').next())
        .and_then(|v| v.trim().parse().ok())
        .ok_or_else(|| HwError::Rtl(format!("no area in {}", dir.display())))?;
    let sta = format!(
        "read_liberty {lib}\n\
         read_verilog net.v\n\
         link_design {top}\n\
         create_clock -name clk -period 1000 [get_ports -quiet clk]\n\
         set_input_delay 0 -clock clk [all_inputs]\n\
         set_output_delay 0 -clock clk [all_outputs]\n\
         report_checks -path_delay max -digits 3\n\
         exit\n"
    );
    std::fs::write(dir.join("sta.tcl"), sta).map_err(|e| HwError::Rtl(e.to_string()))?;
    let rep = tool("sta", &["-no_init", "-exit", "sta.tcl"], &dir)?;
    std::fs::write(dir.join("sta.log"), &rep).map_err(|e| HwError::Rtl(e.to_string()))?;
    let delay_ns = rep
        .lines()
        .find(|l| l.contains("data arrival time"))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| HwError::Rtl(format!("no critical path in {}/sta.log", dir.display())))?;
    // Cells on the path: lines `delay time ^/v inst/pin (CELL)` up to the arrival.
    let path = rep
        .split("data arrival time")
        .next()
        .unwrap_or("")
        .lines()
        .filter(|l| {
            let t = l.trim_end();
            t.ends_with(')') && t.contains('/') && !t.contains("(in)") && !t.contains("(out)")
        })
        .count() as u32;
    Ok(Gates {
        cells,
        area_um2,
        depth: path,
        delay_ns,
    })
}

/// The model's area (40 nm) of a block of `unit`, or None when the model does not price it.
fn model_area(unit: &Unit, b: &BlockSource) -> Option<f64> {
    let r = unit.registers();
    match b.module.as_str() {
        "emc_fp64_add" => Some(FP64_ADD_UM2),
        "emc_fp64_mul" => Some(FP64_MUL_UM2),
        "emc_fp64_sqrt" | "emc_fp64_div" => Some(SQRT_DIV_PIPELINED_UM2),
        "blk_f2fix" => Some(F2FIX64_UM2),
        "blk_search" | "blk_bank" => match r.size {
            SizeUnit::Thresholds { bits, .. } => {
                Some(threshold_search_um2(bits, b.module == "blk_bank"))
            }
            _ => None,
        },
        "blk_benes" => match &r.net {
            Network::Benes(n) => Some(benes_um2(n.control_bits())),
            _ => None,
        },
        "blk_crossbar" => match &r.net {
            Network::Crossbar(x) => Some(crossbar_um2(x.lanes())),
            _ => None,
        },
        _ => None,
    }
}

/// Synthesise every block of `unit` and the whole unit.
pub fn synthesize(unit: &Unit, o: &SynthOptions) -> Result<SynthReport, HwError> {
    let mut rows = Vec::new();
    for b in blocks(unit) {
        let g = gates(&b.verilog, &b.module, o)?;
        rows.push(Row {
            model_um2_40: model_area(unit, &b),
            // Pipelined blocks (fp units, one search step per cycle): the worst stage against
            // one cycle; combinational ones: the whole path against their stages.
            model_ns_40: (b.stages > 0).then_some(
                if b.module.starts_with("emc_fp64") || b.module == "blk_search" {
                    1.0
                } else {
                    b.stages as f64
                },
            ),
            name: b.module,
            instances: b.instances,
            stages: b.stages,
            gates: g,
        });
    }
    let files = emit(unit, &[])?;
    let tg = gates(&files.verilog, "emc_unit", o)?;
    let c = cost(unit);
    let total = Row {
        name: "emc_unit (whole)".into(),
        instances: 1,
        stages: unit.depth(),
        gates: tg,
        model_um2_40: Some(c.logic_area_um2()),
        model_ns_40: Some(1.0),
    };
    let add = rows
        .iter()
        .find(|r| r.name == "emc_fp64_add")
        .ok_or_else(|| HwError::Rtl("no fp64 adder to calibrate on".into()))?;
    let area_cal = add.gates.area_um2 / area_at(FP64_ADD_UM2, OSU018_NM);
    let delay_cal = add.gates.delay_ns / delay_at(1.0, OSU018_NM);
    Ok(SynthReport {
        label: format!("{} ({})", unit.spec(), unit.registers().net.name()),
        blocks: rows,
        total,
        area_cal,
        delay_cal,
    })
}

impl SynthReport {
    /// The calibrated model area of a row at 0.18 µm.
    pub fn model_area(&self, r: &Row) -> Option<f64> {
        r.model_um2_40
            .map(|a| area_at(a, OSU018_NM) * self.area_cal)
    }

    /// The calibrated model delay of a row at 0.18 µm.
    pub fn model_delay(&self, r: &Row) -> Option<f64> {
        r.model_ns_40
            .map(|d| delay_at(d, OSU018_NM) * self.delay_cal)
    }

    /// Rows whose synthesised area is outside ±25 % of the calibrated model (the adder is the
    /// calibration and always 1.00).
    pub fn outside(&self) -> Vec<&Row> {
        self.blocks
            .iter()
            .chain(core::iter::once(&self.total))
            .filter(|r| {
                self.model_area(r)
                    .is_some_and(|m| !(0.75..=1.25).contains(&(r.gates.area_um2 / m)))
            })
            .collect()
    }
}

impl fmt::Display for SynthReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "synthesis of {} to OSU 0.18 µm (yosys + ABC, OpenSTA); model scaled by area·(180/40)², delay·(180/40), \
             calibrated on emc_fp64_add: area ×{:.3}, delay ×{:.3}",
            self.label, self.area_cal, self.delay_cal
        )?;
        writeln!(
            f,
            "| block | inst | stages | cells | area µm² | model µm² | ratio | depth | delay ns | model ns | ratio |"
        )?;
        writeln!(f, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")?;
        for r in self.blocks.iter().chain(core::iter::once(&self.total)) {
            let ma = self.model_area(r);
            let md = self.model_delay(r);
            let opt =
                |v: Option<f64>, p: usize| v.map_or("—".to_string(), |x| format!("{x:.p$}"));
            writeln!(
                f,
                "| {} | {} | {} | {} | {:.0} | {} | {} | {} | {:.2} | {} | {} |",
                r.name,
                r.instances,
                r.stages,
                r.gates.cells,
                r.gates.area_um2,
                opt(ma, 0),
                opt(ma.map(|m| r.gates.area_um2 / m), 2),
                r.gates.depth,
                r.gates.delay_ns,
                opt(md, 2),
                opt(md.map(|m| r.gates.delay_ns / m), 2),
            )?;
        }
        let out: Vec<&str> = self.outside().iter().map(|r| r.name.as_str()).collect();
        if out.is_empty() {
            writeln!(
                f,
                "every priced block is within ±25 % of the calibrated model"
            )
        } else {
            writeln!(
                f,
                "outside ±25 % of the calibrated model: {}",
                out.join(", ")
            )
        }
    }
}
