//! Area, energy and latency of a configured unit, from published unit figures: the node is a
//! commercial 40 nm process at 1 GHz (28 nm by quadratic scaling, ×0.49, as MergeTree does).
//! Every constant names its source; `[D]` marks a figure derived here from sourced ones and
//! `[E]` an engineering estimate with no direct anchor (stated so that it can be replaced).
//!
//! Sources:
//! - Aladdin (Shao, Reagen, Wei, Brooks, ISCA 2014), power/area tables normalised to a
//!   commercial 40 nm library, Synopsys DesignWare 3-stage FP units at a 1 ns cycle: fp32
//!   add 4,361 µm², fp32 mul 8,967 µm², fp64 add 9,885 µm², fp64 mul 22,270 µm², int32 add
//!   278 µm², 32-bit barrel shifter 250 µm², flip-flop 5.98 µm² and ≈9 fJ per bit and cycle.
//! - Horowitz, "Computing's energy problem", ISSCC 2014 (45 nm): fp32 add 0.9 pJ, fp32 mul
//!   3.7 pJ, int32 add 0.1 pJ, 64-bit read of an 8 KB SRAM ≈10 pJ.
//! - MergeTree (Viitanen et al., ACM TOG 36(5), 2017): LPDDR3 dynamic energy from DRAMPower,
//!   ≈55–59 pJ per byte (507–1,112 mW at 9.2–18.9 GB/s); quadratic node scaling; SRAM density
//!   ≈4.4 µm²/B for 256 KB (small buffers taken at ≈9 µm²/B).
//! - Generic-gate transistor estimates (Yosys + ABC `abc -g cmos2; stat -tech cmos`)
//!   calibrated to Aladdin's 40 nm shifter and adder at 0.134–0.183 µm² per transistor (0.158
//!   used): 64-lane Beneš network 9,152 T (352 switches), 64×64 crossbar 49,192 T, 31-bit
//!   comparator 904 T, 6-step search over 63 31-bit thresholds 26.8k T, 63-comparator bank 61k T.
//! - OpenHW CV32E40P FPU documentation: iterative fp32 div/sqrt ≈7 kGE, 5–8 cycles.
#![forbid(unsafe_code)]

use core::fmt;

use crate::datapath::{Network, SizeSearch, SizeUnit, Unit};

/// Node the model is stated at.
pub const NODE_NM: u32 = 40;
/// Area factor from 40 nm to 28 nm ([`area_at`]).
pub const TO_28NM: f64 = (28.0 / 40.0) * (28.0 / 40.0);

/// The node-scaling rule, one for every figure of the model (hardware-anchors.md §1.2 and
/// §5.1): area scales with the square of the feature size (MergeTree's convention for its
/// cross-node table), gate delay linearly with it (constant-field scaling; the anchors' fp
/// units meet 1 ns at 40 nm). `area_at(a, n)` is a 40 nm area at `n` nm.
pub fn area_at(um2_at_40nm: f64, nm: f64) -> f64 {
    um2_at_40nm * (nm / NODE_NM as f64) * (nm / NODE_NM as f64)
}

/// A 40 nm delay at `n` nm ([`area_at`] states the rule).
pub fn delay_at(ns_at_40nm: f64, nm: f64) -> f64 {
    ns_at_40nm * nm / NODE_NM as f64
}

/// Delay of one gate level at 40 nm, ns \[D\]: Aladdin's 32-bit barrel shifter, 0.70 ns over
/// its 11 gate levels (hardware-anchors.md §2.5). The gate model of [`crate::rtl::net`]
/// counts levels (fan-out buffering included); this converts them.
pub const NS_PER_LEVEL: f64 = 0.70 / 11.0;

/// Area of the `S`-step binary threshold search or of the comparator bank on 63-bit keys,
/// µm² at 40 nm \[D\]: the yosys estimates (26.8k T for 6 steps over 63 31-bit thresholds,
/// 61k T for the 63-comparator bank) scaled to 63-bit keys and `2^S − 1` thresholds.
pub fn threshold_search_um2(bits: u32, bank: bool) -> f64 {
    let t = ((1u32 << bits) - 1) as f64;
    let tr = if bank { 61_000.0 } else { 26_800.0 };
    tr * (63.0 / 31.0) * t / 63.0 * UM2_PER_T
}

/// Area of a Beneš network with `control_bits` switches, µm² at 40 nm \[D\] (yosys: 9,152 T
/// per 352 switches, 26 T each).
pub fn benes_um2(control_bits: usize) -> f64 {
    control_bits as f64 * 26.0 * UM2_PER_T
}

/// Area of an `n × n` crossbar, µm² at 40 nm \[D\] (yosys: 49,192 T per 64×64, 12 T a point).
pub fn crossbar_um2(n: u32) -> f64 {
    (n * n) as f64 * 12.0 * UM2_PER_T
}

/// fp64 adder/subtractor, µm² (Aladdin).
pub const FP64_ADD_UM2: f64 = 9_885.0;
/// fp64 multiplier, µm² (Aladdin).
pub const FP64_MUL_UM2: f64 = 22_270.0;
/// fp32 adder, µm² (Aladdin; used to scale energies).
pub const FP32_ADD_UM2: f64 = 4_361.0;
/// fp32 multiplier, µm² (Aladdin; used to scale energies).
pub const FP32_MUL_UM2: f64 = 8_967.0;
/// int32 adder, µm² (Aladdin).
pub const INT32_ADD_UM2: f64 = 278.0;
/// 32-bit barrel shifter, µm² (Aladdin).
pub const SHIFT32_UM2: f64 = 250.0;
/// Flip-flop area per bit, µm² (Aladdin).
pub const FLOP_UM2: f64 = 5.98;
/// Flip-flop energy per bit per cycle, pJ (Aladdin).
pub const FLOP_PJ: f64 = 0.009;
/// µm² per estimated transistor at 40 nm (calibration midpoint).
pub const UM2_PER_T: f64 = 0.158;
/// Small SRAM buffer area per byte, µm² \[D\].
pub const SRAM_UM2_PER_B: f64 = 9.0;
/// 64-bit access to a small SRAM, pJ (Horowitz).
pub const SRAM_PJ_PER_64B: f64 = 10.0;
/// LPDDR3 dynamic energy per byte, pJ (MergeTree, midpoint).
pub const DRAM_PJ_PER_B: f64 = 57.0;
/// fp32 add energy, pJ (Horowitz).
pub const FP32_ADD_PJ: f64 = 0.9;
/// fp32 mul energy, pJ (Horowitz).
pub const FP32_MUL_PJ: f64 = 3.7;
/// int32 add energy, pJ (Horowitz).
pub const INT32_ADD_PJ: f64 = 0.1;
/// Control and handshakes, µm² \[E\].
pub const CONTROL_UM2: f64 = 2_000.0;

/// fp64 add energy \[D\]: fp32 energy scaled by the fp64/fp32 area ratio.
pub fn fp64_add_pj() -> f64 {
    FP32_ADD_PJ * FP64_ADD_UM2 / FP32_ADD_UM2
}

/// fp64 mul energy \[D\]: fp32 energy scaled by the fp64/fp32 area ratio.
pub fn fp64_mul_pj() -> f64 {
    FP32_MUL_PJ * FP64_MUL_UM2 / FP32_MUL_UM2
}

/// Energy of an integer logic block with no direct anchor \[D\]: the int32 adder's energy per µm².
pub fn logic_pj(area_um2: f64) -> f64 {
    INT32_ADD_PJ * area_um2 / INT32_ADD_UM2
}

/// Pipelined fp64 sqrt or divider \[E\]: a multiplicative (Goldschmidt) unit ≈ two fp64
/// multipliers plus a seed table.
pub const SQRT_DIV_PIPELINED_UM2: f64 = 2.0 * FP64_MUL_UM2;
/// Iterative radix-4 fp64 sqrt/divider \[E\]: twice CV32E40P's fp32 7 kGE, 4 T per gate.
pub const SQRT_DIV_ITERATIVE_UM2: f64 = 14_000.0 * 4.0 * UM2_PER_T;
/// float→fixed with clamp and 64-bit field shift \[D\]: two 32-bit barrel shifters and a
/// 64-bit clamp comparator (2 × 904 T).
pub const F2FIX64_UM2: f64 = 2.0 * SHIFT32_UM2 + 2.0 * 904.0 * UM2_PER_T;
/// 63-bit unsigned comparator \[D\] (the 31-bit one scaled by width).
pub const CMP63_UM2: f64 = 904.0 * 63.0 / 31.0 * UM2_PER_T;

/// One line of a cost breakdown.
#[derive(Clone, Debug, PartialEq)]
pub struct Item {
    /// What it is.
    pub name: String,
    /// Instances in the whole unit.
    pub count: f64,
    /// Area of all instances, µm² at 40 nm.
    pub area_um2: f64,
    /// Energy per code, pJ.
    pub energy_pj: f64,
    /// Source tag of the figure.
    pub source: &'static str,
}

/// Cost of one configured unit.
#[derive(Clone, Debug, PartialEq)]
pub struct Cost {
    /// Layout name and routing, for tables.
    pub label: String,
    /// Breakdown.
    pub items: Vec<Item>,
    /// Pipeline latency in cycles.
    pub latency_cycles: u32,
    /// Per-stage latencies (name, cycles).
    pub stage_latency: Vec<(&'static str, u32)>,
    /// Bytes moved per code (AABB in, code out).
    pub bytes_per_code: u32,
}

impl Cost {
    /// Total area, µm² at 40 nm.
    pub fn area_um2(&self) -> f64 {
        self.items.iter().map(|i| i.area_um2).sum()
    }

    /// Area of the datapath without the input/output buffers, µm² at 40 nm.
    pub fn logic_area_um2(&self) -> f64 {
        self.items
            .iter()
            .filter(|i| !i.name.contains("buffer") && !i.name.contains("FIFO"))
            .map(|i| i.area_um2)
            .sum()
    }

    /// Energy per code inside the unit (datapath, registers, buffers), pJ.
    pub fn energy_pj(&self) -> f64 {
        self.items.iter().map(|i| i.energy_pj).sum()
    }

    /// DRAM energy per code, pJ.
    pub fn dram_pj(&self) -> f64 {
        self.bytes_per_code as f64 * DRAM_PJ_PER_B
    }
}

/// The cost of a unit as configured (only instantiated parts are counted), priced from the
/// published anchors above (Aladdin's fp units, the generic-gate estimates of the routing
/// and search): the area, energy and latency figures of `emc hwsim`'s cost table and the
/// energy per code of the EMC-vs-Morton table come from here. The gate model of the emitted
/// Verilog ([`crate::rtl::net::Graph::price`], held against synthesis in [`crate::synth`])
/// prices the same unit independently; `--synth-compare` prints both area ratios to Morton.
pub fn cost(unit: &Unit) -> Cost {
    let r = unit.registers();
    let o = unit.options();
    let lanes = o.lanes as f64;
    let axes = r.axis_on.iter().filter(|&&a| a).count() as f64;
    let pos_bits: u32 = (0..3).map(|a| r.bits[a]).sum();
    let mut items = Vec::new();
    let mut add = |name: String, count: f64, unit_um2: f64, unit_pj: f64, source| {
        if count > 0.0 {
            items.push(Item {
                name,
                count,
                area_um2: count * unit_um2,
                energy_pj: count * unit_pj,
                source,
            });
        }
    };
    let add_pj = fp64_add_pj();
    let mul_pj = fp64_mul_pj();
    // Position lanes: lo+hi, −2·origin, ×scale/2, float→fixed.
    add(
        "fp64 add/sub (position)".into(),
        2.0 * axes * lanes,
        FP64_ADD_UM2,
        add_pj,
        "Aladdin",
    );
    add(
        "fp64 mul (position)".into(),
        axes * lanes,
        FP64_MUL_UM2,
        mul_pj,
        "Aladdin",
    );
    add(
        "float→fixed+clamp (64-bit field shift)".into(),
        axes * lanes,
        F2FIX64_UM2,
        logic_pj(F2FIX64_UM2),
        "[D] Aladdin shifter + comparator",
    );
    // Size path.
    let s = r.size_bits();
    match &r.size {
        SizeUnit::None => {}
        _ => {
            add(
                "fp64 add/sub (size: Δ, sums)".into(),
                5.0 * lanes,
                FP64_ADD_UM2,
                add_pj,
                "Aladdin",
            );
            add(
                "fp64 mul (size: Δ²)".into(),
                3.0 * lanes,
                FP64_MUL_UM2,
                mul_pj,
                "Aladdin",
            );
        }
    }
    match &r.size {
        SizeUnit::None => {}
        SizeUnit::Thresholds { bits, .. } => {
            let t = ((1u32 << bits) - 1) as f64;
            let (name, bank) = match o.size_search {
                SizeSearch::Binary => (format!("{bits}-step threshold search"), false),
                SizeSearch::Bank => (format!("{t}-comparator bank + popcount"), true),
            };
            let a = threshold_search_um2(*bits, bank);
            add(
                name,
                lanes,
                a,
                logic_pj(a),
                "[D] yosys estimate scaled to 63-bit keys",
            );
            add(
                format!("threshold registers ({t} × 63 b)"),
                t * 63.0,
                FLOP_UM2,
                0.0,
                "Aladdin flop (static, clock-gated)",
            );
        }
        SizeUnit::Formula { transform, .. } => {
            let (um2, src) = if o.iterative_formula {
                (SQRT_DIV_ITERATIVE_UM2, "[E] 2× CV32E40P iterative div/sqrt")
            } else {
                (SQRT_DIV_PIPELINED_UM2, "[E] Goldschmidt ≈ 2 fp64 mul")
            };
            let units = match transform {
                emc_core::SizeTransform::Linear => 2.0,
                emc_core::SizeTransform::Sqrt => 3.0,
            };
            add(
                "fp64 sqrt/divide".into(),
                units * lanes,
                um2,
                2.0 * mul_pj,
                src,
            );
            add(
                "exponent adder (×2^S) + float→fixed".into(),
                lanes,
                INT32_ADD_UM2 / 2.0 + F2FIX64_UM2,
                logic_pj(INT32_ADD_UM2 / 2.0 + F2FIX64_UM2),
                "[D] Aladdin",
            );
            add(
                "size formula registers (D, S)".into(),
                70.0,
                FLOP_UM2,
                0.0,
                "Aladdin flop",
            );
        }
    }
    // Routing.
    match &r.net {
        Network::Fixed { .. } => {}
        Network::Benes(b) => {
            let a = benes_um2(b.control_bits());
            add(
                format!(
                    "Beneš network ({} lanes, {} columns)",
                    b.lanes(),
                    b.columns()
                ),
                lanes,
                a,
                logic_pj(a),
                "[D] yosys 9,152 T per 352 switches",
            );
            add(
                "Beneš control registers".into(),
                b.control_bits() as f64,
                FLOP_UM2,
                0.0,
                "Aladdin flop",
            );
        }
        Network::Crossbar(x) => {
            let n = x.lanes() as f64;
            let a = crossbar_um2(x.lanes());
            add(
                format!("{n}×{n} crossbar"),
                lanes,
                a,
                logic_pj(a),
                "[D] yosys 49,192 T per 64×64",
            );
            add(
                "crossbar select registers".into(),
                n * n.log2(),
                FLOP_UM2,
                0.0,
                "Aladdin flop",
            );
        }
    }
    // Scalar configuration registers: origin2 and scale per axis, bit counts and offsets.
    add(
        "scale/origin/offset registers".into(),
        128.0 * axes + 48.0,
        FLOP_UM2,
        0.0,
        "Aladdin flop",
    );
    // Pipeline registers (per lane), clocked once per code.
    let regs = pipeline_register_bits(unit, pos_bits, s);
    add(
        "pipeline + balance registers".into(),
        regs as f64 * lanes,
        FLOP_UM2,
        FLOP_PJ,
        "Aladdin flop",
    );
    // Buffers.
    let cb = unit.code_bytes() as f64;
    // The input buffer: 24 B written and read once per code (3 + 3 64-bit accesses).
    let in_bytes = o.input_capacity as f64 * 24.0;
    add(
        format!("input buffer ({} AABBs, SRAM)", o.input_capacity),
        in_bytes,
        SRAM_UM2_PER_B,
        6.0 * SRAM_PJ_PER_64B / in_bytes,
        "[D] MergeTree SRAM density; Horowitz SRAM access",
    );
    // The output FIFO: each code's bits clocked in and out once.
    let out_bits = unit.output_capacity() as f64 * cb * 8.0;
    add(
        format!("output FIFO ({} codes)", unit.output_capacity()),
        out_bits,
        FLOP_UM2,
        2.0 * cb * 8.0 * FLOP_PJ / out_bits,
        "Aladdin flop",
    );
    add(
        "control and handshakes".into(),
        1.0,
        CONTROL_UM2,
        0.0,
        "[E]",
    );
    Cost {
        label: format!("{} ({})", unit.spec(), r.net.name()),
        items,
        latency_cycles: unit.depth(),
        stage_latency: unit.stages().iter().map(|s| (s.name, s.latency)).collect(),
        bytes_per_code: 24 + unit.code_bytes(),
    }
}

/// Register bits of one lane: one boundary register per stage cycle of the values live there,
/// plus the delay registers that hold one branch while the other computes (the FP units'
/// internal pipeline registers are part of their DesignWare area).
fn pipeline_register_bits(unit: &Unit, pos_bits: u32, s: u32) -> u64 {
    let r = unit.registers();
    let axes = r.axis_on.iter().filter(|&&a| a).count() as u64;
    let size = !matches!(r.size, SizeUnit::None);
    let mut bits = 0u64;
    for st in unit.stages() {
        let l = st.latency as u64;
        let w = match st.name {
            "unpack" => 192,
            "centre" | "offset" => 64 * axes + if size { 192 } else { 0 },
            "scale" => 64 * axes + if size { 128 } else { 0 },
            // float→fixed takes 1 cycle; with a size path its result waits 2 more.
            "float→fixed" => {
                if size {
                    (pos_bits as u64) * l + 64
                } else {
                    pos_bits as u64
                }
            }
            n if n.starts_with("size") => (pos_bits as u64 + 64 + s as u64) * l,
            n if n.starts_with("route") => 64 * l,
            _ => 8 * unit.code_bytes() as u64 * l,
        };
        bits += w + l; // + a valid bit per cycle
    }
    bits
}

impl fmt::Display for Cost {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "  cost of {} at {NODE_NM} nm, 1 GHz:", self.label)?;
        writeln!(
            f,
            "    {:<44} {:>8} {:>11} {:>9}  source",
            "item", "count", "area µm²", "pJ/code"
        )?;
        for i in &self.items {
            writeln!(
                f,
                "    {:<44} {:>8} {:>11.0} {:>9.2}  {}",
                i.name, i.count, i.area_um2, i.energy_pj, i.source
            )?;
        }
        writeln!(
            f,
            "    total {:.0} µm² ({:.3} mm² at 28 nm), logic {:.0} µm²; {:.1} pJ/code in the unit + {:.0} pJ/code DRAM ({} B)",
            self.area_um2(),
            self.area_um2() * TO_28NM * 1e-6,
            self.logic_area_um2(),
            self.energy_pj(),
            self.dram_pj(),
            self.bytes_per_code
        )?;
        write!(f, "    latency {} cycles:", self.latency_cycles)?;
        for (n, l) in &self.stage_latency {
            write!(f, " {n} {l}")?;
        }
        writeln!(f)
    }
}

/// One row of the "is it easy?" table.
#[derive(Clone, Debug)]
pub struct EasyRow {
    /// The unit's cost.
    pub cost: Cost,
    /// Codes per cycle sustained at each bandwidth of the table.
    pub codes_per_cycle: Vec<f64>,
}

/// The "is it easy?" table: area, latency and energy of each unit and their increase over the
/// first row (the baseline, e.g. `morton63` with fixed wiring), and the codes per cycle the
/// unit sustains at each bandwidth.
pub fn easy_table(rows: &[EasyRow], bandwidths: &[f64], clock_ghz: f64) -> String {
    use fmt::Write;
    let mut s = String::new();
    let Some(base) = rows.first() else {
        return s;
    };
    let _ = write!(
        s,
        "| unit | area µm² (40 nm) | vs base | mm² (28 nm) | latency cycles (ns) | vs base | pJ/code unit | vs base | pJ/code incl. DRAM |"
    );
    for bw in bandwidths {
        let _ = write!(s, " codes/cycle @{bw} GB/s |");
    }
    s.push('\n');
    s.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for _ in bandwidths {
        s.push_str("---:|");
    }
    s.push('\n');
    let ba = base.cost.area_um2();
    let bl = base.cost.latency_cycles as f64;
    let be = base.cost.energy_pj();
    for r in rows {
        let c = &r.cost;
        let _ = write!(
            s,
            "| {} | {:.0} | {:+.0} ({:.2}×) | {:.3} | {} ({:.1}) | {:+} | {:.1} | {:+.1} ({:.2}×) | {:.0} |",
            c.label,
            c.area_um2(),
            c.area_um2() - ba,
            c.area_um2() / ba,
            c.area_um2() * TO_28NM * 1e-6,
            c.latency_cycles,
            c.latency_cycles as f64 / clock_ghz,
            c.latency_cycles as f64 - bl,
            c.energy_pj(),
            c.energy_pj() - be,
            c.energy_pj() / be,
            c.energy_pj() + c.dram_pj()
        );
        for v in &r.codes_per_cycle {
            let _ = write!(s, " {v:.3} |");
        }
        s.push('\n');
    }
    s
}

/// Pipeline stages of the fp64 square root and divider: 55 digit steps of the restoring
/// recurrences, four or five per stage (each a 56–60-bit subtractor and a multiplexer).
pub fn recurrence_stages() -> u32 {
    12
}

/// Pipeline stages of a Beneš network: its columns split over two register stages (each half
/// is 5–6 multiplexer levels, as deep as the crossbar's one stage).
pub fn benes_stages(_b: &crate::routing::Benes) -> u32 {
    2
}
