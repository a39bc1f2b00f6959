//! SVG plots of `emc paper` (plotters, SVG backend, text as SVG `<text>` so no font files are
//! needed): per scene, build time against SAH and against time-to-image, one colour per
//! builder, Pareto-front points ringed and joined.
#![forbid(unsafe_code)]

use std::path::Path;

use plotters::prelude::*;

use super::measure::PaperBuilder;
use super::{PaperError, Run, SceneResult};

/// The y axis of a plot (x is always build thread-CPU ms).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Axis {
    /// Collapsed SAH; the front is the (build, SAH) front.
    Sah,
    /// Build + trace ms; the front is the (build, trace) front.
    TimeToImage,
}

fn colour(b: PaperBuilder) -> RGBColor {
    match b {
        PaperBuilder::Lbvh => RGBColor(31, 119, 180),
        PaperBuilder::Atrbvh => RGBColor(214, 39, 40),
        PaperBuilder::BinnedSah => RGBColor(44, 160, 44),
    }
}

fn y_of(r: &Run, axis: Axis) -> f64 {
    match axis {
        Axis::Sah => r.sah_collapsed,
        Axis::TimeToImage => r.time_to_image_ms(),
    }
}

fn on_front(r: &Run, axis: Axis) -> bool {
    match axis {
        Axis::Sah => r.pareto_sah,
        Axis::TimeToImage => r.pareto_time,
    }
}

fn range(v: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let lo = v.clone().fold(f64::INFINITY, f64::min);
    let hi = v.fold(f64::NEG_INFINITY, f64::max);
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(hi.abs() * 0.01).max(1e-9);
    (lo - pad, hi + pad)
}

/// Draw one scene's plot to `path`.
pub fn plot_scene(s: &SceneResult, axis: Axis, path: &Path) -> Result<(), PaperError> {
    draw(s, axis, path).map_err(|msg| PaperError::Plot {
        path: path.to_path_buf(),
        msg,
    })
}

fn draw(s: &SceneResult, axis: Axis, path: &Path) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    let root = SVGBackend::new(path, (800, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let (x0, x1) = range(s.runs.iter().map(|r| r.build_ms));
    let (y0, y1) = range(s.runs.iter().map(|r| y_of(r, axis)));
    let ylabel = match axis {
        Axis::Sah => "SAH (collapsed)",
        Axis::TimeToImage => "time-to-image [CPU ms]",
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{}: build time vs {ylabel}", s.name),
            ("sans-serif", 20),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("build [CPU ms]")
        .y_desc(ylabel)
        .draw()
        .map_err(|x| e(&x))?;
    let mut front: Vec<(f64, f64)> = s
        .runs
        .iter()
        .filter(|r| on_front(r, axis))
        .map(|r| (r.build_ms, y_of(r, axis)))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    chart
        .draw_series(LineSeries::new(front, BLACK.stroke_width(1)))
        .map_err(|x| e(&x))?
        .label("Pareto front")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
    for b in [
        PaperBuilder::Lbvh,
        PaperBuilder::Atrbvh,
        PaperBuilder::BinnedSah,
    ] {
        let c = colour(b);
        let pts: Vec<&Run> = s.runs.iter().filter(|r| r.builder == b).collect();
        chart
            .draw_series(
                pts.iter()
                    .map(|r| Circle::new((r.build_ms, y_of(r, axis)), 4, c.filled())),
            )
            .map_err(|x| e(&x))?
            .label(b.name())
            .legend(move |(x, y)| Circle::new((x + 8, y), 4, c.filled()));
        chart
            .draw_series(
                pts.iter()
                    .filter(|r| on_front(r, axis))
                    .map(|r| Circle::new((r.build_ms, y_of(r, axis)), 7, BLACK.stroke_width(1))),
            )
            .map_err(|x| e(&x))?;
        chart
            .draw_series(pts.iter().map(|r| {
                Text::new(
                    r.layout_name(),
                    (r.build_ms, y_of(r, axis)),
                    ("sans-serif", 11).into_font().color(&c),
                )
            }))
            .map_err(|x| e(&x))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

/// The bit-budget sweep of one scene to `path`: headline and collapsed SAH (left axis) and
/// build thread-CPU ms per phase (right axis) against the code length.
pub fn plot_sweep(s: &SceneResult, path: &Path) -> Result<(), PaperError> {
    draw_sweep(s, path).map_err(|msg| PaperError::Plot {
        path: path.to_path_buf(),
        msg,
    })
}

/// A sweep line: its legend, colour and value.
type Series = (&'static str, RGBColor, fn(&super::sweep::SweepRow) -> f64);

fn draw_sweep(s: &SceneResult, path: &Path) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    let root = SVGBackend::new(path, (800, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let rows = &s.sweep;
    let (x0, x1) = (20.0, 68.0);
    let sah = rows.iter().flat_map(|r| [r.sah_headline, r.sah_collapsed]);
    let (y0, y1) = range(sah);
    let times = rows
        .iter()
        .flat_map(|r| [r.encode_ms, r.sort_ms, r.hierarchy_ms]);
    let (_, t1) = range(times);
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{}: SAH and build time against code length", s.name),
            ("sans-serif", 20),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .right_y_label_area_size(70)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|x| e(&x))?
        .set_secondary_coord(x0..x1, 0.0..t1.max(1e-9));
    chart
        .configure_mesh()
        .x_desc("code bits")
        .y_desc("SAH")
        .draw()
        .map_err(|x| e(&x))?;
    chart
        .configure_secondary_axes()
        .y_desc("build [CPU ms]")
        .draw()
        .map_err(|x| e(&x))?;
    let pts = |f: fn(&super::sweep::SweepRow) -> f64| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (r.bits as f64, f(r))).collect()
    };
    let series: [Series; 2] = [
        ("SAH headline", RGBColor(31, 119, 180), |r| r.sah_headline),
        ("SAH collapsed", RGBColor(214, 39, 40), |r| r.sah_collapsed),
    ];
    for (name, c, f) in series {
        chart
            .draw_series(LineSeries::new(pts(f), c.stroke_width(2)).point_size(4))
            .map_err(|x| e(&x))?
            .label(name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(2)));
    }
    let tseries: [Series; 3] = [
        ("encode ms", RGBColor(44, 160, 44), |r| r.encode_ms),
        ("sort ms", RGBColor(148, 103, 189), |r| r.sort_ms),
        ("hierarchy ms", RGBColor(140, 86, 75), |r| r.hierarchy_ms),
    ];
    for (name, c, f) in tseries {
        chart
            .draw_secondary_series(LineSeries::new(pts(f), c.stroke_width(1)).point_size(3))
            .map_err(|x| e(&x))?
            .label(name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(1)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}
