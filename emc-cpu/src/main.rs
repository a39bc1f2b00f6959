//! The `emc` command-line tool: parses arguments and hands each verb to `emc_cpu::cli`.
#![forbid(unsafe_code)]

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "emc",
    version,
    about = "Extended Morton Codes: layouts, LBVH builds, reports"
)]
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
    /// emc's presets beside the peers (Embree 3, obvhs; `--features peers`) in one process on
    /// the benchmark protocol: build ms cold and warm, Mrays/s, counts, memory, ratios.
    Compare(emc_cpu::cli::compare::CompareArgs),
    /// The main report: the seed's tables, what accuracy costs in time (Pareto front), example
    /// codes; Markdown, CSV, SVG plots and PNG images in an output folder.
    Paper(emc_cpu::cli::paper::PaperArgs),
}

/// Parse the arguments; a usage mistake becomes one line naming the problem (exit 2), while
/// `--help` and `--version` print as usual.
fn parse_args() -> Cli {
    match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion) {
                e.exit();
            }
            if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand {
                let _ = e.print();
                std::process::exit(2);
            }
            let text = e.to_string();
            let line = text
                .lines()
                .map(str::trim)
                .find(|l| !l.is_empty())
                .unwrap_or("invalid arguments");
            let line = line.strip_prefix("error: ").unwrap_or(line);
            eprintln!("emc: {line} (see `emc --help`)");
            std::process::exit(2);
        }
    }
}

fn main() {
    let cli = parse_args();
    let result: anyhow::Result<()> = match cli.verb {
        Verb::Build(a) => emc_cpu::cli::build::run(&a),
        Verb::Layout(a) => emc_cpu::cli::layout::run(&a),
        Verb::Hwsim(a) => emc_cpu::cli::hwsim::run(&a),
        Verb::Render(a) => emc_cpu::cli::render::run(&a),
        Verb::Compare(a) => emc_cpu::cli::compare::run(&a),
        Verb::Paper(a) => emc_cpu::cli::paper::run(&a),
    };
    if let Err(e) = result {
        eprintln!("emc: {e:#}");
        std::process::exit(1);
    }
}
