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

use crate::cost::{area_at, delay_at, NS_PER_LEVEL, UM2_PER_T};
use crate::datapath::Unit;
use crate::error::HwError;
use crate::rtl::net::Price;
use crate::rtl::{blocks, emit, write_unit, BlockSource};

/// Default location of the OSU 0.18 µm liberty file in Debian's `qflow-tech-osu018`.
pub const OSU018_LIB: &str = "/usr/share/qflow/tech/osu018/osu018_stdcells.lib";
/// Feature size of the library, nm.
pub const OSU018_NM: f64 = 180.0;

/// The cell that drives a block's inputs, for ABC (which then buffers high-fan-out inputs
/// and flip-flop outputs as a commercial flow would; without it ABC takes every input as
/// ideal and leaves a flip-flop driving a thousand loads) and for OpenSTA. An `INVX1` drives
/// like the `DFFPOSX1` output that drives the input in the unit.
pub const DRIVER: &str = "INVX1";
/// Load on each block output, pF: four `DFFPOSX1` D pins (0.0088 pF each), the next
/// stage's registers ([`crate::rtl::net::OUTPUT_LOADS`]).
pub const LOAD_PF: f64 = 0.035;
/// ABC's constraints file: [`DRIVER`] and [`LOAD_PF`].
fn abc_constr() -> String {
    format!("set_driving_cell {DRIVER}\nset_load {LOAD_PF}\n")
}

/// Where the tools and the library are.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// The liberty file.
    pub liberty: PathBuf,
    /// Scratch directory (netlists, logs).
    pub work: PathBuf,
    /// ABC's delay target, ps (drives buffering and sizing).
    pub delay_target_ps: u32,
    /// Synthesise the whole unit too (the blocks alone otherwise; the whole unit takes
    /// minutes).
    pub whole_unit: bool,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            liberty: PathBuf::from(OSU018_LIB),
            work: std::env::temp_dir().join(format!("emc-synth-{}", std::process::id())),
            delay_target_ps: 4500,
            whole_unit: true,
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
    /// The whole unit (flattened), when synthesised ([`SynthOptions::whole_unit`]).
    pub total: Option<Row>,
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
    // The same module text synthesised before in this work directory (another unit's copy of
    // a shared block): read its logs instead of running the tools again.
    let same = std::fs::read_to_string(dir.join("in.v")).is_ok_and(|t| t == verilog);
    let done = |f: &str| std::fs::read_to_string(dir.join(f)).ok();
    if let (true, Some(log), Some(rep)) = (same, done("syn.log"), done("sta.log")) {
        if let Ok(g) = parse(&log, &rep, &dir) {
            return Ok(g);
        }
    }
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
         abc -constr abc.constr -D {d} -liberty {lib} -script +strash;&get,-n;&dch,-f;&nf,{{D}};&put;buffer,-p;upsize,{{D}};dnsize,{{D}};stime,-p\n\
         opt_clean\n\
         stat -liberty {lib}\n\
         write_verilog -noattr -simple-lhs net.v\n",
        d = o.delay_target_ps
    );
    std::fs::write(dir.join("syn.ys"), script).map_err(|e| HwError::Rtl(e.to_string()))?;
    std::fs::write(dir.join("abc.constr"), abc_constr())
        .map_err(|e| HwError::Rtl(e.to_string()))?;
    let log = tool("yosys", &["-q", "-l", "syn.log", "syn.ys"], &dir)?;
    let log = std::fs::read_to_string(dir.join("syn.log")).unwrap_or(log);
    let sta = STA_SCRIPT
        .replace("{lib}", &lib)
        .replace("{top}", top)
        .replace("{driver}", DRIVER)
        .replace("{load}", &LOAD_PF.to_string());
    std::fs::write(dir.join("sta.tcl"), sta).map_err(|e| HwError::Rtl(e.to_string()))?;
    let rep = tool("sta", &["-no_init", "-exit", "sta.tcl"], &dir)?;
    std::fs::write(dir.join("sta.log"), &rep).map_err(|e| HwError::Rtl(e.to_string()))?;
    parse(&log, &rep, &dir)
}

/// [`gates`] of every block, in order, on as many threads as the machine has cores (at most
/// one per block). Every block runs even when one fails; the caller returns the first
/// failure in block order.
fn gates_parallel(blocks: &[BlockSource], o: &SynthOptions) -> Vec<Result<Gates, HwError>> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Mutex;
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(blocks.len())
        .max(1);
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<Result<Gates, HwError>>>> =
        Mutex::new((0..blocks.len()).map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(b) = blocks.get(i) else { break };
                let g = gates(&b.verilog, &b.module, o);
                out.lock().unwrap_or_else(|e| e.into_inner())[i] = Some(g);
            });
        }
    });
    out.into_inner()
        .unwrap_or_else(|e| e.into_inner())
        .into_iter()
        .map(|g| g.expect("every block taken by a thread"))
        .collect()
}

/// OpenSTA's script: the worst register-to-register, input-to-register or input-to-output
/// path with [`DRIVER`] on the inputs and [`LOAD_PF`] on the outputs.
const STA_SCRIPT: &str = "read_liberty {lib}
read_verilog net.v
link_design {top}
create_clock -name clk -period 1000 [get_ports -quiet clk]
set_input_delay 0 -clock clk [all_inputs]
set_output_delay 0 -clock clk [all_outputs]
set_driving_cell -lib_cell {driver} [all_inputs]
set_load {load} [all_outputs]
report_checks -path_delay max -digits 3
exit
";

/// The figures of a yosys log and an OpenSTA report.
fn parse(log: &str, rep: &str, dir: &Path) -> Result<Gates, HwError> {
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

/// The model's figures of a gate network at 40 nm: its area (every transistor of the generic
/// gate estimate at [`UM2_PER_T`]) and its critical path ([`Price::levels`] at
/// [`NS_PER_LEVEL`]).
pub fn model_40nm(p: &Price) -> (f64, f64) {
    (p.transistors() as f64 * UM2_PER_T, p.levels * NS_PER_LEVEL)
}

/// The block whose synthesis fixes the library's area factor (synthesised area over the
/// rule-scaled model): the fp64 adder, the unit's most numerous block.
pub const AREA_CALIBRATION: &str = "emc_fp64_add";
/// The block whose synthesis fixes the library's delay factor: the fp64 adder too (a
/// mixture of shifters, carry trees and leading-zero logic, the unit's typical path).
pub const DELAY_CALIBRATION: &str = "emc_fp64_add";
/// Synthesise every block of `unit` and the whole unit.
pub fn synthesize(unit: &Unit, o: &SynthOptions) -> Result<SynthReport, HwError> {
    let blocks = blocks(unit);
    // The blocks are synthesised side by side, one tool run per core (each in its own
    // directory; yosys and OpenSTA are single-threaded).
    let mut synthesised = gates_parallel(&blocks, o).into_iter();
    let mut rows = Vec::new();
    for b in blocks {
        let g = synthesised.next().expect("one result per block")?;
        let (a, d) = model_40nm(&b.price);
        rows.push(Row {
            model_um2_40: Some(a),
            model_ns_40: Some(d),
            name: b.module,
            instances: b.instances,
            stages: b.stages,
            gates: g,
        });
    }
    let total = if o.whole_unit {
        let files = emit(unit, &[])?;
        let tg = gates(&files.verilog, "emc_unit", o)?;
        let (a, d) = model_40nm(&write_unit(unit).top.graph().price());
        Some(Row {
            name: "emc_unit (whole)".into(),
            instances: 1,
            stages: unit.depth(),
            gates: tg,
            model_um2_40: Some(a),
            model_ns_40: Some(d),
        })
    } else {
        None
    };
    let find = |name: &str| {
        rows.iter().find(|r| r.name == name).ok_or_else(|| {
            HwError::Rtl(format!(
                "the unit has no {name} to calibrate on (every layout's unit has one)"
            ))
        })
    };
    let ca = find(AREA_CALIBRATION)?;
    let area_cal = ca.gates.area_um2 / area_at(ca.model_um2_40.unwrap_or(1.0), OSU018_NM);
    let cd = find(DELAY_CALIBRATION)?;
    let delay_cal = cd.gates.delay_ns / delay_at(cd.model_ns_40.unwrap_or(1.0), OSU018_NM);
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

    /// Synthesised over calibrated model: (area, delay).
    pub fn ratios(&self, r: &Row) -> (Option<f64>, Option<f64>) {
        (
            self.model_area(r).map(|m| r.gates.area_um2 / m),
            self.model_delay(r).map(|m| r.gates.delay_ns / m),
        )
    }

    /// Rows (blocks and the whole unit) whose synthesised area or delay lies outside ±25 % of
    /// the calibrated model, with what is outside. The calibration block is 1.00 by
    /// construction.
    pub fn outside(&self) -> Vec<(&Row, String)> {
        let band = |x: Option<f64>| x.is_some_and(|v| !(0.75..=1.25).contains(&v));
        self.blocks
            .iter()
            .chain(self.total.iter())
            .filter_map(|r| {
                let (a, d) = self.ratios(r);
                let mut why = Vec::new();
                if band(a) && r.name != AREA_CALIBRATION {
                    why.push(format!("area {:.2}", a.unwrap_or(0.0)));
                }
                if band(d) && r.name != DELAY_CALIBRATION {
                    why.push(format!("delay {:.2}", d.unwrap_or(0.0)));
                }
                (!why.is_empty()).then(|| (r, why.join(", ")))
            })
            .collect()
    }
}

impl fmt::Display for SynthReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "synthesis of {} to OSU 0.18 µm (yosys + ABC, OpenSTA) against the gate model of the same \
             Verilog; node rule: area × (180/40)², delay × 180/40; library factors: area ×{:.3} \
             from {AREA_CALIBRATION}, delay ×{:.3} from {DELAY_CALIBRATION}",
            self.label, self.area_cal, self.delay_cal
        )?;
        writeln!(
            f,
            "| block | inst | stages | cells | area µm² | model µm² | ratio | depth | delay ns | model ns | ratio |"
        )?;
        writeln!(f, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")?;
        for r in self.blocks.iter().chain(self.total.iter()) {
            let (ma, md) = (self.model_area(r), self.model_delay(r));
            let (ra, rd) = self.ratios(r);
            let opt =
                |v: Option<f64>, p: usize| v.map_or("—".to_string(), |x| format!("{x:.p$}"));
            let cal = |x: Option<f64>, c: bool| {
                let t = opt(x, 2);
                if c {
                    format!("{t} (cal.)")
                } else {
                    t
                }
            };
            writeln!(
                f,
                "| {} | {} | {} | {} | {:.0} | {} | {} | {} | {:.2} | {} | {} |",
                r.name,
                r.instances,
                r.stages,
                r.gates.cells,
                r.gates.area_um2,
                opt(ma, 0),
                cal(ra, r.name == AREA_CALIBRATION),
                r.gates.depth,
                r.gates.delay_ns,
                opt(md, 2),
                cal(rd, r.name == DELAY_CALIBRATION),
            )?;
        }
        let out: Vec<String> = self
            .outside()
            .iter()
            .map(|(r, why)| format!("{} ({why})", r.name))
            .collect();
        if out.is_empty() {
            writeln!(
                f,
                "every other block is within ±25 % of the calibrated model in area and delay"
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
