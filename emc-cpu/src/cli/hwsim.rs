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
