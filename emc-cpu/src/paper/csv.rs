//! The CSV files of `emc paper`: one row per measured configuration (`runs.csv`, columns named
//! with the shared builder and layout names) and the seed-table figures per scene
//! (`seed-tables.csv`).
#![forbid(unsafe_code)]

use std::fmt::Write as _;

use emc_core::LayoutSpec;

use super::measure::PaperBuilder;
use super::tables::{scene_change, Metric};
use super::PaperResults;

/// Header of `runs.csv`.
pub const RUNS_COLUMNS: [&str; 25] = [
    "scene",
    "triangles",
    "builder",
    "layout",
    "bits_xyzs",
    "pattern",
    "build_cpu_ms",
    "build_wall_ms",
    "sah_headline",
    "sah_collapsed",
    "primary_rays",
    "ao_rays",
    "primary_hits",
    "ao_occluded",
    "primary_cpu_ms",
    "ao_cpu_ms",
    "trace_cpu_ms",
    "trace_wall_ms",
    "time_to_image_cpu_ms",
    "time_to_image_wall_ms",
    "primary_mrays_per_cpu_s",
    "ao_mrays_per_cpu_s",
    "node_tests_per_ray",
    "tri_tests_per_ray",
    "pareto",
];

/// Quote a field when it holds a comma, quote or newline.
pub fn field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// `runs.csv`: one row per scene × builder × layout. `pareto` holds `sah`, `time`, both
/// (`sah+time`) or nothing: the fronts the run is on.
pub fn runs_csv(res: &PaperResults) -> String {
    let mut out = RUNS_COLUMNS.join(",");
    out.push('\n');
    for s in &res.scenes {
        for r in &s.runs {
            let l = r.layout.clone().unwrap_or_default();
            let (bits, pattern) = l.split_once(' ').unwrap_or(("", ""));
            let t = &r.traced;
            let pareto = match (r.pareto_sah, r.pareto_time) {
                (true, true) => "sah+time",
                (true, false) => "sah",
                (false, true) => "time",
                (false, false) => "",
            };
            let _ = writeln!(
                out,
                "{},{},{},{},{},{},{:.3},{:.3},{:.6},{:.6},{},{},{},{},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.4},{:.4},{:.4},{:.4},{}",
                field(&s.name),
                s.prims,
                r.builder.name(),
                r.layout_name(),
                bits,
                pattern,
                r.build_ms,
                r.build_wall_ms,
                r.sah_headline,
                r.sah_collapsed,
                t.primary_rays,
                t.ao_rays,
                t.primary_hits,
                t.ao_occluded,
                t.primary_ms,
                t.ao_ms,
                t.trace_ms(),
                t.trace_wall_ms(),
                r.time_to_image_ms(),
                r.build_wall_ms + t.trace_wall_ms(),
                t.primary_mrays(),
                t.ao_mrays(),
                t.node_tests_per_ray,
                t.tri_tests_per_ray,
                pareto
            );
        }
    }
    out
}

/// Header of `seed-tables.csv`.
pub const SEED_COLUMNS: [&str; 6] = [
    "scene",
    "builder",
    "layout",
    "metric",
    "value",
    "change_pct",
];

/// `seed-tables.csv`: for `lbvh` and `atrbvh`, each of `morton63`, `emc64-sort`, `emc64-var`,
/// each metric: the value and its change versus `morton63` in %.
pub fn seed_tables_csv(res: &PaperResults) -> String {
    let mut out = SEED_COLUMNS.join(",");
    out.push('\n');
    for b in [PaperBuilder::Lbvh, PaperBuilder::Atrbvh] {
        for s in &res.scenes {
            for spec in [
                LayoutSpec::Morton63,
                LayoutSpec::Emc64Sort,
                LayoutSpec::Emc64Var,
            ] {
                let Some(r) = s.find(b, spec) else { continue };
                for m in Metric::ALL {
                    let _ = writeln!(
                        out,
                        "{},{},{},{},{:.6},{:.3}",
                        field(&s.name),
                        b.name(),
                        spec,
                        m.key(),
                        m.of(r),
                        scene_change(s, b, spec, m)
                    );
                }
            }
        }
    }
    out
}
