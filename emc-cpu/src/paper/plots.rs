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
