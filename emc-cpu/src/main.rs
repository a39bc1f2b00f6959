//! The `emc` command-line tool: parses arguments and hands each verb to `emc_cpu::cli`.

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "emc", version, about = "Extended Morton Codes: layouts, LBVH builds, reports")]
struct Cli {
    #[command(subcommand)]
    verb: Verb,
}

#[derive(Subcommand, Debug)]
enum Verb {
    /// Build a BVH over a scene and print per-phase timings, tree shape and SAH.
    Build(emc_cpu::cli::build::BuildArgs),
    /// Print each layout of a scene, every backend's throughput against a streaming baseline,
    /// and which backend dispatch picks and why.
    Layout(emc_cpu::cli::layout::LayoutArgs),
    /// Simulate the fixed-function EMC unit on a scene: bit-exactness against emc-core,
    /// cycle statistics, and area/latency/energy over Morton with codes/cycle per bandwidth.
    Hwsim(emc_cpu::cli::hwsim::HwsimArgs),
    /// Trace the benchmark protocol (primary, AO, bounce rays) on a scene: Mrays/s, rays per
    /// thread-CPU-second, node and triangle tests per ray; optionally write a shaded PNG.
    Render(emc_cpu::cli::render::RenderArgs),
    /// The main report: the seed's tables, what accuracy costs in time (Pareto front), example
    /// codes; Markdown, CSV, SVG plots and PNG images in an output folder.
    Paper(emc_cpu::cli::paper::PaperArgs),
}

fn main() {
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.verb {
        Verb::Build(a) => emc_cpu::cli::build::run(&a),
        Verb::Layout(a) => emc_cpu::cli::layout::run(&a),
        Verb::Hwsim(a) => emc_cpu::cli::hwsim::run(&a),
        Verb::Render(a) => emc_cpu::cli::render::run(&a),
        Verb::Paper(a) => emc_cpu::cli::paper::run(&a),
    };
    if let Err(e) = result {
        eprintln!("emc: {e:#}");
        std::process::exit(1);
    }
}
