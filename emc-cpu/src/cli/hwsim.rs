//! `emc hwsim`: configure the modelled EMC unit for a scene, check every code against
//! emc-core, simulate it against a memory system (fast mode, optionally also cycle-stepped),
//! and print the "is it easy?" table: area, latency and energy over Morton, codes per cycle.
#![forbid(unsafe_code)]

use std::time::Instant;

use anyhow::{bail, Context};
use emc_core::{Aabb, Encoder, Frame, LayoutSpec};
use emc_hwsim::cost::{cost, easy_table, EasyRow};
use emc_hwsim::setup::setup_cost;
use emc_hwsim::{MemoryConfig, Mode, RoutingChoice, SizeSearch, Unit, UnitOptions};
use rayon::prelude::*;

use crate::scene::{load_with, SceneOptions};

/// Arguments of `emc hwsim`.
#[derive(clap::Args, Debug, Clone)]
pub struct HwsimArgs {
    /// A scene file (`.obj`, `.obj.zst`), a shared scene name, or `builtin:NAME`.
    #[arg(default_value = "builtin:uniform")]
    pub scene: String,
    /// Triangle count of a built-in scene.
    #[arg(long, default_value_t = 1 << 20)]
    pub prims: usize,
    /// The layout whose unit is simulated and printed in detail (the table always has
    /// morton63, emc64-var and emc64-sort).
    #[arg(long, default_value = "emc64-var")]
    pub layout: String,
    /// DRAM bandwidths in GB/s (repeatable; default 12.8, 25.6 and 51.2).
    #[arg(long = "bandwidth")]
    pub bandwidths: Vec<f64>,
    /// Datapath lanes.
    #[arg(long, default_value_t = 1)]
    pub lanes: u32,
    /// Unit clock in GHz.
    #[arg(long, default_value_t = 1.0)]
    pub clock: f64,
    /// DRAM read latency in ns.
    #[arg(long, default_value_t = 100.0)]
    pub latency_ns: f64,
    /// Interleave hardware of programmable layouts: auto, benes, crossbar (fixed layouts get
    /// wires under auto).
    #[arg(long, default_value = "auto")]
    pub routing: String,
    /// Threshold search: binary (S pipelined steps) or bank (all comparators at once).
    #[arg(long, default_value = "binary")]
    pub size_search: String,
    /// Input buffer in AABBs.
    #[arg(long, default_value_t = 256)]
    pub input_capacity: u32,
    /// Output FIFO in codes (0: sized to the codes in flight, lanes × depth + 2 bursts).
    #[arg(long, default_value_t = 0)]
    pub output_capacity: u32,
    /// AABBs per read burst.
    #[arg(long, default_value_t = 8)]
    pub read_burst: u32,
    /// Scene bounds come with the input (no bounds pass in the setup cost).
    #[arg(long)]
    pub bounds_supplied: bool,
    /// Also run the cycle-stepped simulation of the detailed layout and compare it with the
    /// fast mode.
    #[arg(long)]
    pub stepped: bool,
    /// Write synthesisable Verilog of the configured unit into DIR: `emc_unit.v`, the register
    /// image `emc_unit.regs.hex`, the self-checking testbench `emc_unit_tb.v` and the vectors
    /// `emc_unit.vectors` (run: `iverilog -g2005 -o sim emc_unit.v emc_unit_tb.v && vvp sim`).
    #[arg(long, value_name = "DIR")]
    pub verilog: Option<std::path::PathBuf>,
    /// With --verilog: also simulate the written RTL with Icarus Verilog (`iverilog`, `vvp`)
    /// and dump the unit's top-level signals (its ports and the wires of `emc_unit`) to FILE
    /// as a VCD waveform, for a viewer such as GTKWave.
    #[arg(long, value_name = "FILE", requires = "verilog")]
    pub vcd: Option<std::path::PathBuf>,
    /// Write test vectors of the configured unit to FILE (TestFloat-style text: six binary32
    /// box fields and the code in hex, the cycle the box enters and the cycle its code leaves).
    #[arg(long, value_name = "FILE")]
    pub vectors: Option<std::path::PathBuf>,
    /// Boxes of the scene (evenly spaced) in the vectors of --verilog and --vectors.
    #[arg(long, default_value_t = 1000)]
    pub vector_count: usize,
    /// Synthesise the unit's blocks and the whole unit with yosys to the OSU 0.18 µm cells and
    /// time them with OpenSTA; print them beside the cost model, and the EMC-vs-Morton table.
    #[arg(long)]
    pub synth: bool,
    /// With --synth: also synthesise whole morton63, emc64-var (Beneš and crossbar) and
    /// emc64-sort units and print the EMC-vs-Morton table (several minutes each).
    #[arg(long)]
    pub synth_compare: bool,
    /// Liberty file for --synth.
    #[arg(long, default_value = emc_hwsim::synth::OSU018_LIB)]
    pub liberty: std::path::PathBuf,
}

/// Boxes of the scene for vectors: `count` evenly spaced ones.
fn vector_boxes(boxes: &[Aabb], count: usize) -> Vec<Aabb> {
    if count == 0 || boxes.is_empty() {
        return Vec::new();
    }
    let step = boxes.len().div_ceil(count).max(1);
    boxes.iter().step_by(step).copied().collect()
}

/// `--verilog`, `--vectors` and `--synth` of the detailed unit.
fn hardware_outputs(
    a: &HwsimArgs,
    unit: &Unit,
    frame: &Frame,
    boxes: &[Aabb],
) -> anyhow::Result<()> {
    let vb = vector_boxes(boxes, a.vector_count);
    if let Some(dir) = &a.verilog {
        let files = emc_hwsim::rtl::emit(unit, &vb)?;
        files
            .write(dir)
            .with_context(|| format!("writing the RTL into {}", dir.display()))?;
        println!(
            "\nRTL of {} written to {}: {} register words, {} vectors, depth {} cycles, II {} (run: cd {} && iverilog -g2005 -o sim emc_unit.v emc_unit_tb.v && vvp sim)",
            unit.spec(),
            dir.display(),
            files.image.len(),
            files.vector_list.len(),
            unit.depth(),
            unit.lane_ii(),
            dir.display()
        );
        if let Some(vcd) = &a.vcd {
            let verdict = emc_hwsim::rtl::simulate(dir, Some(vcd))?;
            println!(
                "Icarus Verilog run of the testbench: {verdict}; waveform written to {}",
                vcd.display()
            );
        }
    }
    if let Some(path) = &a.vectors {
        let v = emc_hwsim::vectors::vectors(unit, &vb);
        std::fs::write(path, emc_hwsim::vectors::to_text(unit, &v))
            .with_context(|| format!("writing vectors to {}", path.display()))?;
        println!("\n{} vectors written to {}", v.len(), path.display());
    }
    if a.synth {
        let o = emc_hwsim::synth::SynthOptions {
            liberty: a.liberty.clone(),
            ..Default::default()
        };
        let t0 = Instant::now();
        let rep = emc_hwsim::synth::synthesize(unit, &o);
        let _ = std::fs::remove_dir_all(&o.work);
        println!("\n{}", rep?);
        println!("(synthesis took {:.0} s)", t0.elapsed().as_secs_f64());
    }
    if a.synth && a.synth_compare {
        let o = emc_hwsim::synth::SynthOptions {
            liberty: a.liberty.clone(),
            ..Default::default()
        };
        let t0 = Instant::now();
        // The seed's question: the EMC unit against the plain Morton unit, in gates.
        let d = *unit.options();
        let mut rows = Vec::new();
        for (s, r) in [
            (LayoutSpec::Morton63, RoutingChoice::Auto),
            (LayoutSpec::Emc64Var, RoutingChoice::Benes),
            (LayoutSpec::Emc64Var, RoutingChoice::Crossbar),
            (LayoutSpec::Emc64Sort, RoutingChoice::Benes),
        ] {
            let u = Unit::for_spec(&s, frame, &UnitOptions { routing: r, ..d })?;
            let files = emc_hwsim::rtl::emit(&u, &[])?;
            eprintln!(
                "synthesising the whole {s} ({}) unit ...",
                u.registers().net.name()
            );
            let g = emc_hwsim::synth::gates(
                &files.verilog,
                "emc_unit",
                &emc_hwsim::synth::SynthOptions {
                    work: o.work.join(format!(
                        "{s}-{}",
                        u.registers().net.name().replace(' ', "-")
                    )),
                    ..o.clone()
                },
            )?;
            // The gate model of the same Verilog (40 nm; its ratio to Morton is node-free).
            let (gate_um2, _) =
                emc_hwsim::synth::model_40nm(&emc_hwsim::rtl::write_unit(&u).top.graph().price());
            rows.push((
                format!("{s} ({})", u.registers().net.name()),
                g,
                cost(&u),
                u.depth(),
                gate_um2,
            ));
        }
        println!(
            "EMC unit vs plain Morton unit (OSU 0.18 µm synthesis; area vs Morton also from the gate \
             model of the same Verilog and from cost::cost()'s Aladdin anchors; energy from \
             cost::cost() at 40 nm, Aladdin anchors):"
        );
        println!("| unit | cells | area µm² | vs Morton | gate model | anchors | latency cycles | critical path ns | max clock MHz | pJ/code (anchors) | vs Morton |");
        println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        let (ba, be) = (rows[0].1.area_um2, rows[0].2.energy_pj());
        let (bg, bc) = (rows[0].4, rows[0].2.area_um2());
        for (label, g, c, depth, gate_um2) in &rows {
            println!(
                "| {label} | {} | {:.0} | {:.2}× | {:.2}× | {:.2}× | {depth} | {:.2} | {:.0} | {:.1} | {:.2}× |",
                g.cells,
                g.area_um2,
                g.area_um2 / ba,
                gate_um2 / bg,
                c.area_um2() / bc,
                g.delay_ns,
                1000.0 / g.delay_ns,
                c.energy_pj(),
                c.energy_pj() / be
            );
        }
        println!("(synthesis took {:.0} s)", t0.elapsed().as_secs_f64());
        let _ = std::fs::remove_dir_all(&o.work);
    }
    Ok(())
}

/// Codes of the unit that differ from emc-core's encoder, over the whole scene.
fn mismatches(unit: &Unit, enc: &Encoder, boxes: &[Aabb]) -> usize {
    boxes
        .par_chunks(1 << 16)
        .map(|chunk| {
            let mut codes = Vec::new();
            unit.codes(chunk, &mut codes);
            codes
                .iter()
                .zip(chunk)
                .filter(|(c, b)| **c != enc.encode(b))
                .count()
        })
        .sum()
}

/// Run `emc hwsim`.
pub fn run(a: &HwsimArgs) -> anyhow::Result<()> {
    let bandwidths = if a.bandwidths.is_empty() {
        vec![12.8, 25.6, 51.2]
    } else {
        a.bandwidths.clone()
    };
    let routing: RoutingChoice = a.routing.parse().map_err(anyhow::Error::msg)?;
    let size_search = match a.size_search.as_str() {
        "binary" => SizeSearch::Binary,
        "bank" => SizeSearch::Bank,
        s => bail!("unknown size search {s:?} (expected binary or bank)"),
    };
    let spec: LayoutSpec = a
        .layout
        .parse()
        .with_context(|| format!("layout {:?}", a.layout))?;
    let opts = UnitOptions {
        lanes: a.lanes,
        routing,
        size_search,
        input_capacity: a.input_capacity,
        output_capacity: a.output_capacity,
        read_burst: a.read_burst,
        ..UnitOptions::default()
    };
    let mem_at = |bw: f64| MemoryConfig {
        bandwidth_gbps: bw,
        clock_ghz: a.clock,
        latency_ns: a.latency_ns,
    };
    let scene = load_with(
        &a.scene,
        &SceneOptions {
            prims: Some(a.prims),
            ..SceneOptions::default()
        },
    )
    .with_context(|| format!("loading scene {:?}", a.scene))?;
    let boxes = scene.aabbs();
    let frame = Frame::new(&boxes).context("scene frame")?;
    let n = boxes.len() as u64;
    println!(
        "scene {}: {} primitives, extent {:.4?}, diagonal {:.4}",
        a.scene,
        n,
        frame.extent(),
        frame.diagonal()
    );
    let unit = Unit::for_spec(&spec, &frame, &opts)?;
    // Refuse bad buffer sizes and memory settings before any work.
    unit.flow(n).validate()?;
    for &bw in &bandwidths {
        emc_hwsim::Port::new(&mem_at(bw))?;
    }
    println!("\n{unit}");
    println!(
        "{}",
        setup_cost(&unit, n, &mem_at(bandwidths[0]), a.bounds_supplied)?
    );
    print!("{}", cost(&unit));

    // Bit-exactness over the whole scene, for every layout of the table.
    let mut table_specs = vec![
        LayoutSpec::Morton63,
        LayoutSpec::Emc64Var,
        LayoutSpec::Emc64Sort,
    ];
    if !table_specs.contains(&spec) {
        table_specs.push(spec);
    }
    println!("\nbit-exactness against emc-core Encoder::encode over all {n} primitives:");
    for s in &table_specs {
        let u = if *s == spec {
            unit.clone()
        } else {
            Unit::for_spec(s, &frame, &opts)?
        };
        let enc = Encoder::new(s, &frame);
        let bad = mismatches(&u, &enc, &boxes);
        println!("  {:<12} {}: {bad} mismatches", s.to_string(), u.layout());
        if bad != 0 {
            bail!("the unit's codes differ from emc-core for {s}: {bad} mismatches");
        }
    }

    hardware_outputs(a, &unit, &frame, &boxes)?;

    // Timing of the detailed unit.
    for &bw in &bandwidths {
        let mem = mem_at(bw);
        let t0 = Instant::now();
        let fast = unit.run(&boxes, &mem, Mode::Fast)?;
        let host = t0.elapsed().as_secs_f64();
        println!(
            "\n{} at {bw} GB/s, {} GHz, {} ns latency — fast mode ({:.3} s host, {:.1} M codes/s):",
            spec,
            a.clock,
            a.latency_ns,
            host,
            n as f64 / host / 1e6
        );
        println!("{}", fast.stats);
        if a.stepped {
            let t0 = Instant::now();
            let st = unit.run(&boxes, &mem, Mode::Stepped)?;
            let host = t0.elapsed().as_secs_f64();
            println!(
                "  cycle-stepped ({:.3} s host, {:.2} M cycles/s): {} cycles, statistics {} the fast mode's, codes {}",
                host,
                st.stats.cycles as f64 / host / 1e6,
                st.stats.cycles,
                if st.stats == fast.stats { "equal to" } else { "DIFFERENT from" },
                if st.codes == fast.codes { "equal" } else { "DIFFERENT" }
            );
            if let Some(o) = &st.occupancy {
                print!("{o}");
            }
            if st.stats != fast.stats || st.codes != fast.codes {
                bail!("fast and cycle-stepped modes disagree");
            }
        }
    }

    // The "is it easy?" table.
    let mut rows = Vec::new();
    let variants: Vec<(LayoutSpec, RoutingChoice)> = {
        let mut v = vec![
            (LayoutSpec::Morton63, RoutingChoice::Auto),
            (LayoutSpec::Emc64Var, RoutingChoice::Benes),
            (LayoutSpec::Emc64Var, RoutingChoice::Crossbar),
            (LayoutSpec::Emc64Sort, RoutingChoice::Benes),
        ];
        if !matches!(
            spec,
            LayoutSpec::Morton63 | LayoutSpec::Emc64Var | LayoutSpec::Emc64Sort
        ) {
            v.push((spec, routing));
        }
        v
    };
    for (s, r) in variants {
        let u = Unit::for_spec(&s, &frame, &UnitOptions { routing: r, ..opts })?;
        let mut cpc = Vec::new();
        for &bw in &bandwidths {
            cpc.push(u.timing(n, &mem_at(bw))?.codes_per_cycle());
        }
        rows.push(EasyRow {
            cost: cost(&u),
            codes_per_cycle: cpc,
        });
    }
    println!(
        "\nis it easy? (40 nm, {} GHz, {} lane(s); energy excludes DRAM except the last energy column; base = first row)",
        a.clock, a.lanes
    );
    print!("{}", easy_table(&rows, &bandwidths, a.clock));
    Ok(())
}
