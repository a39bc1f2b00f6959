//! SVG plots of `emc paper` (plotters, SVG backend, text as SVG `<text>` so no font files are
//! needed): per scene, build time against SAH and against time-to-image, one colour per
//! builder, the auto choice as a triangle, the Pareto front as a staircase with its points
//! ringed, layout labels placed clear of each other, log axes where values span a decade; the
//! label-box model a test checks every plot's texts with.
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

/// An axis of values that is drawn in log10 when they span a decade or more.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scale {
    /// True: the axis shows `log10` of the values, labelled with the values.
    pub log: bool,
}

impl Scale {
    /// Log when every value is positive and the largest is at least ten times the smallest.
    pub fn for_values(v: impl Iterator<Item = f64> + Clone) -> Scale {
        let lo = v.clone().fold(f64::INFINITY, f64::min);
        let hi = v.fold(f64::NEG_INFINITY, f64::max);
        Scale {
            log: lo > 0.0 && hi.is_finite() && hi >= 10.0 * lo,
        }
    }

    /// The drawn coordinate of a value.
    pub fn to(self, v: f64) -> f64 {
        if self.log {
            v.max(f64::MIN_POSITIVE).log10()
        } else {
            v
        }
    }

    /// The tick label of a drawn coordinate.
    fn label(self, t: f64) -> String {
        let v = if self.log { 10f64.powf(t) } else { t };
        let a = v.abs();
        if a >= 100.0 || a == 0.0 {
            format!("{v:.0}")
        } else if a >= 10.0 {
            format!("{v:.1}")
        } else if a >= 0.1 {
            format!("{v:.2}")
        } else {
            format!("{v:.1e}")
        }
    }

    /// The axis description with the scale.
    fn desc(self, d: &str) -> String {
        if self.log {
            format!("{d}, log scale")
        } else {
            d.to_string()
        }
    }
}

/// Font size (plotters' units) of the point labels.
const LABEL_FONT: f64 = 11.0;
/// Plotters writes font sizes into SVG divided by this.
const SVG_FONT_DIV: f64 = 1.24;

/// A text's box in SVG pixels: left, top, right, bottom.
pub type TextBox = (f64, f64, f64, f64);

/// The box of a label of `chars` characters at SVG font size `fs` with its top-left corner at
/// (`x`, `y`), by the width model [`text_boxes`] uses.
fn label_box(x: f64, y: f64, chars: usize, fs: f64) -> TextBox {
    (x, y, x + 0.6 * fs * chars as f64, y + fs)
}

/// Strictly overlapping (touching does not count).
pub fn boxes_overlap(a: &TextBox, b: &TextBox) -> bool {
    a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
}

/// Every `<text>` element of an SVG as plotters writes it, with its box: width 0.6 em per
/// character (a generous sans-serif average), height 1 em from 0.75 em above the baseline; the
/// baseline from `y` and `dy` (`em`, `ex` = 0.5 em, px), the horizontal extent by
/// `text-anchor`, a `rotate(90|270, …)` transform swapping the box about its anchor. Returns
/// (text, box) pairs.
pub fn text_boxes(svg: &str) -> Vec<(String, TextBox)> {
    fn attr(tag: &str, name: &str) -> Option<String> {
        let key = format!(" {name}=\"");
        let i = tag.find(&key)? + key.len();
        let j = tag[i..].find('"')? + i;
        Some(tag[i..j].to_string())
    }
    fn unescape(t: &str) -> String {
        t.replace("&lt;", "<")
            .replace("&gt;", ">")
            .replace("&quot;", "\"")
            .replace("&apos;", "'")
            .replace("&amp;", "&")
    }
    let mut out = Vec::new();
    let mut rest = svg;
    while let Some(i) = rest.find("<text") {
        rest = &rest[i..];
        let Some(close) = rest.find('>') else { break };
        let tag = &rest[..close];
        let Some(end) = rest.find("</text>") else {
            break;
        };
        let text = unescape(rest[close + 1..end].trim());
        rest = &rest[end..];
        let num = |n: &str| attr(tag, n).and_then(|v| v.parse::<f64>().ok());
        let (x, y, fs) = (
            num("x").unwrap_or(0.0),
            num("y").unwrap_or(0.0),
            num("font-size").unwrap_or(16.0),
        );
        let dy = attr(tag, "dy").map_or(0.0, |d| {
            let v = |s: &str| s.parse::<f64>().unwrap_or(0.0);
            if let Some(e) = d.strip_suffix("em") {
                v(e) * fs
            } else if let Some(e) = d.strip_suffix("ex") {
                v(e) * fs * 0.5
            } else {
                v(d.trim_end_matches("px"))
            }
        });
        let w = 0.6 * fs * text.chars().count() as f64;
        let base = y + dy;
        let (top, bottom) = (base - 0.75 * fs, base + 0.25 * fs);
        let (l, r) = match attr(tag, "text-anchor").as_deref() {
            Some("middle") => (x - w / 2.0, x + w / 2.0),
            Some("end") => (x - w, x),
            _ => (x, x + w),
        };
        let rotated = attr(tag, "transform").is_some_and(|t| {
            t.starts_with("rotate(90") || t.starts_with("rotate(270") || t.starts_with("rotate(-90")
        });
        let b = if rotated {
            // A quarter turn about (x, y): horizontal extents become vertical ones.
            (
                x - (bottom - y).abs().max((top - y).abs()),
                y - (r - x).abs().max((l - x).abs()),
                x + (bottom - y).abs().max((top - y).abs()),
                y + (r - x).abs().max((l - x).abs()),
            )
        } else {
            (l, top, r, bottom)
        };
        out.push((text, b));
    }
    out
}

/// Pairs of texts of an SVG whose boxes ([`text_boxes`]) overlap.
pub fn overlapping_texts(svg: &str) -> Vec<(String, String)> {
    let b = text_boxes(svg);
    let mut out = Vec::new();
    for i in 0..b.len() {
        for j in i + 1..b.len() {
            if boxes_overlap(&b[i].1, &b[j].1) {
                out.push((b[i].0.clone(), b[j].0.clone()));
            }
        }
    }
    out
}

/// Place labels next to their points (pixels) inside `area`: each takes the first free spot
/// on rings of growing radius around its point (12 directions per ring), free meaning its box
/// overlaps no placed label, no point and stays inside the area. Returns the top-left corner
/// per label and whether it sits far enough to need a leader line; a label with no free spot
/// anywhere is left out (`None`).
fn place_labels(
    points: &[(i32, i32)],
    labels: &[String],
    area: TextBox,
    fs: f64,
) -> Vec<Option<((i32, i32), bool)>> {
    let pad = 1.5;
    let grow = |b: TextBox| (b.0 - pad, b.1 - pad, b.2 + pad, b.3 + pad);
    let dots: Vec<TextBox> = points
        .iter()
        .map(|&(x, y)| {
            let (x, y) = (x as f64, y as f64);
            (x - 5.0, y - 5.0, x + 5.0, y + 5.0)
        })
        .collect();
    let mut placed: Vec<TextBox> = Vec::new();
    let mut out = Vec::with_capacity(labels.len());
    for (i, (&(px, py), text)) in points.iter().zip(labels).enumerate() {
        let chars = text.chars().count();
        let w = 0.6 * fs * chars as f64;
        let mut found = None;
        'rings: for ring in 1..=12 {
            let r = 7.0 + 11.0 * (ring - 1) as f64;
            for k in 0..12 {
                let a = std::f64::consts::PI * 2.0 * k as f64 / 12.0;
                let (cx, cy) = (px as f64 + r * a.cos(), py as f64 - r * a.sin());
                // The label's nearest edge faces the point.
                let x = if a.cos() > 0.3 {
                    cx
                } else if a.cos() < -0.3 {
                    cx - w
                } else {
                    cx - w / 2.0
                };
                let y = if a.sin() > 0.3 {
                    cy - fs
                } else if a.sin() < -0.3 {
                    cy
                } else {
                    cy - fs / 2.0
                };
                let b = grow(label_box(x, y, chars, fs));
                let inside = b.0 >= area.0 && b.1 >= area.1 && b.2 <= area.2 && b.3 <= area.3;
                let free = inside
                    && !placed.iter().any(|p| boxes_overlap(p, &b))
                    && !dots
                        .iter()
                        .enumerate()
                        .any(|(j, d)| (j != i || ring > 1) && boxes_overlap(d, &b));
                if free {
                    placed.push(b);
                    found = Some(((x.round() as i32, y.round() as i32), ring > 2));
                    break 'rings;
                }
            }
        }
        out.push(found);
    }
    out
}

/// Draw one scene's plot to `path`.
pub fn plot_scene(s: &SceneResult, axis: Axis, path: &Path) -> Result<(), PaperError> {
    draw(s, axis, path).map_err(|msg| PaperError::Plot {
        path: path.to_path_buf(),
        msg,
    })
}

/// Width of a Pareto plot; the right part of it is the legend panel.
const PLOT_W: u32 = 980;
/// Width of the legend panel.
const LEGEND_W: u32 = 200;

fn draw(s: &SceneResult, axis: Axis, path: &Path) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    let root = SVGBackend::new(path, (PLOT_W, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let (plot, panel) = root.split_horizontally(PLOT_W - LEGEND_W);
    let xs = Scale::for_values(s.runs.iter().map(|r| r.build_ms));
    let ys = Scale::for_values(s.runs.iter().map(|r| y_of(r, axis)));
    let (x0, x1) = range(s.runs.iter().map(|r| xs.to(r.build_ms)));
    let (y0, y1) = range(s.runs.iter().map(|r| ys.to(y_of(r, axis))));
    let ylabel = match axis {
        Axis::Sah => "SAH (collapsed)",
        Axis::TimeToImage => "time-to-image [CPU ms]",
    };
    let mut chart = ChartBuilder::on(&plot)
        .caption(
            format!("{}: build time vs {ylabel}", s.name),
            ("sans-serif", 20),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|x| e(&x))?;
    let (xd, yd) = (xs.desc("build [CPU ms]"), ys.desc(ylabel));
    chart
        .configure_mesh()
        .x_desc(xd.as_str())
        .y_desc(yd.as_str())
        .x_label_formatter(&|v| xs.label(*v))
        .y_label_formatter(&|v| ys.label(*v))
        .draw()
        .map_err(|x| e(&x))?;
    let at = |r: &Run| (xs.to(r.build_ms), ys.to(y_of(r, axis)));
    // The front as a staircase (each point dominates the region to its upper right).
    let mut front: Vec<(f64, f64)> = s
        .runs
        .iter()
        .filter(|r| on_front(r, axis))
        .map(at)
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut stairs = Vec::with_capacity(2 * front.len());
    for (k, &p) in front.iter().enumerate() {
        if k > 0 {
            stairs.push((p.0, front[k - 1].1));
        }
        stairs.push(p);
    }
    chart
        .draw_series(LineSeries::new(stairs, BLACK.stroke_width(2)))
        .map_err(|x| e(&x))?;
    for r in &s.runs {
        let c = colour(r.builder);
        let p = at(r);
        if on_front(r, axis) {
            chart
                .draw_series(std::iter::once(Circle::new(p, 8, BLACK.stroke_width(2))))
                .map_err(|x| e(&x))?;
        }
        let auto = r.variant.is_some_and(|v| v.auto);
        if auto {
            chart
                .draw_series([
                    TriangleMarker::new(p, 10, BLACK.filled()),
                    TriangleMarker::new(p, 7, c.filled()),
                ])
                .map_err(|x| e(&x))?;
        } else {
            chart
                .draw_series(std::iter::once(Circle::new(p, 4, c.filled())))
                .map_err(|x| e(&x))?;
        }
    }
    // Labels: the layout name beside each point, placed where no other label or point is.
    let pts: Vec<(i32, i32)> = s.runs.iter().map(|r| chart.backend_coord(&at(r))).collect();
    let labels: Vec<String> = s
        .runs
        .iter()
        .map(|r| match (&r.variant, &r.layout) {
            (Some(v), Some(l)) if v.auto => format!("auto = {}", short_layout(l)),
            _ => r.layout_name(),
        })
        .collect();
    let (pxr, pyr) = chart.plotting_area().get_pixel_range();
    let area = (
        pxr.start as f64,
        pyr.start as f64,
        pxr.end as f64,
        pyr.end as f64,
    );
    let fs = LABEL_FONT / SVG_FONT_DIV;
    let spots = place_labels(&pts, &labels, area, fs);
    for ((r, (&p, text)), spot) in s.runs.iter().zip(pts.iter().zip(&labels)).zip(spots) {
        let Some((at, leader)) = spot else { continue };
        let c = colour(r.builder);
        if leader {
            let w = (0.6 * fs * text.chars().count() as f64) as i32;
            let end = (at.0 + w / 2, at.1 + (fs / 2.0) as i32);
            let mid = (
                end.0.clamp(at.0, at.0 + w),
                if p.1 < at.1 { at.1 } else { at.1 + fs as i32 },
            );
            root.draw(&PathElement::new(vec![p, mid], c.mix(0.6).stroke_width(1)))
                .map_err(|x| e(&x))?;
        }
        root.draw(&Text::new(
            text.clone(),
            at,
            ("sans-serif", LABEL_FONT).into_font().color(&c),
        ))
        .map_err(|x| e(&x))?;
    }
    draw_legend(&panel).map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

/// A resolved layout as a label: a named layout as it is, a custom pattern by its bit counts.
fn short_layout(l: &str) -> String {
    match l.split_once(' ') {
        Some((counts, _)) => format!("custom {counts}"),
        None => l.to_string(),
    }
}

/// The legend panel: the builders' colours, the auto marker, the front.
fn draw_legend<DB: DrawingBackend>(
    panel: &DrawingArea<DB, plotters::coord::Shift>,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let font = ("sans-serif", 13).into_font();
    let (x, mut y) = (16, 60);
    let step = 26;
    panel.draw(&Text::new("legend", (x, y - 30), font.clone()))?;
    for b in [
        PaperBuilder::Lbvh,
        PaperBuilder::Atrbvh,
        PaperBuilder::BinnedSah,
    ] {
        let c = colour(b);
        panel.draw(&Circle::new((x + 6, y + 6), 4, c.filled()))?;
        panel.draw(&Text::new(b.name(), (x + 22, y), font.clone()))?;
        y += step;
    }
    panel.draw(&TriangleMarker::new((x + 6, y + 6), 10, BLACK.filled()))?;
    panel.draw(&TriangleMarker::new((x + 6, y + 6), 7, WHITE.filled()))?;
    panel.draw(&Text::new(
        "auto (builder's colour,",
        (x + 22, y - 6),
        font.clone(),
    ))?;
    panel.draw(&Text::new("choice timed)", (x + 22, y + 9), font.clone()))?;
    y += step;
    panel.draw(&Circle::new((x + 6, y + 6), 8, BLACK.stroke_width(2)))?;
    panel.draw(&Text::new("on the Pareto front", (x + 22, y), font.clone()))?;
    y += step;
    panel.draw(&PathElement::new(
        vec![(x - 2, y + 6), (x + 14, y + 6)],
        BLACK.stroke_width(2),
    ))?;
    panel.draw(&Text::new("Pareto front", (x + 22, y), font.clone()))?;
    y += step;
    panel.draw(&Text::new("labels: layout", (x, y + 10), font))?;
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
    let root = SVGBackend::new(path, (PLOT_W, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let (plot, panel) = root.split_horizontally(PLOT_W - LEGEND_W);
    let rows = &s.sweep;
    let (x0, x1) = (20.0, 68.0);
    let sah = rows.iter().flat_map(|r| [r.sah_headline, r.sah_collapsed]);
    let (y0, y1) = range(sah);
    let times = rows
        .iter()
        .flat_map(|r| [r.encode_ms, r.sort_ms, r.hierarchy_ms]);
    let ts = Scale::for_values(times.clone());
    let (t0, t1) = if ts.log {
        range(times.map(|t| ts.to(t)))
    } else {
        (0.0, range(times).1.max(1e-9))
    };
    let mut chart = ChartBuilder::on(&plot)
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
        .set_secondary_coord(x0..x1, t0..t1);
    chart
        .configure_mesh()
        .x_desc("code bits")
        .y_desc("SAH")
        .draw()
        .map_err(|x| e(&x))?;
    let td = ts.desc("build [CPU ms]");
    chart
        .configure_secondary_axes()
        .y_desc(td.as_str())
        .y_label_formatter(&|v| ts.label(*v))
        .draw()
        .map_err(|x| e(&x))?;
    let pts = |f: fn(&super::sweep::SweepRow) -> f64, sc: Scale| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (r.bits as f64, sc.to(f(r)))).collect()
    };
    let lin = Scale { log: false };
    let series: [Series; 2] = [
        ("SAH headline", RGBColor(31, 119, 180), |r| r.sah_headline),
        ("SAH collapsed", RGBColor(214, 39, 40), |r| r.sah_collapsed),
    ];
    let mut legend: Vec<(&str, RGBColor, u32)> = Vec::new();
    for (name, c, f) in series {
        chart
            .draw_series(LineSeries::new(pts(f, lin), c.stroke_width(2)).point_size(4))
            .map_err(|x| e(&x))?;
        legend.push((name, c, 2));
    }
    let tseries: [Series; 3] = [
        ("encode ms (right)", RGBColor(44, 160, 44), |r| r.encode_ms),
        ("sort ms (right)", RGBColor(148, 103, 189), |r| r.sort_ms),
        ("hierarchy ms (right)", RGBColor(140, 86, 75), |r| {
            r.hierarchy_ms
        }),
    ];
    for (name, c, f) in tseries {
        chart
            .draw_secondary_series(LineSeries::new(pts(f, ts), c.stroke_width(1)).point_size(3))
            .map_err(|x| e(&x))?;
        legend.push((name, c, 1));
    }
    let font = ("sans-serif", 13).into_font();
    let (x, mut y) = (16, 60);
    panel
        .draw(&Text::new("legend", (x, y - 30), font.clone()))
        .map_err(|x| e(&x))?;
    for (name, c, w) in legend {
        panel
            .draw(&PathElement::new(
                vec![(x - 2, y + 6), (x + 14, y + 6)],
                c.stroke_width(w),
            ))
            .map_err(|x| e(&x))?;
        panel
            .draw(&Text::new(name, (x + 22, y), font.clone()))
            .map_err(|x| e(&x))?;
        y += 26;
    }
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_boxes_follow_anchor_baseline_and_rotation() {
        let svg = r#"<svg><text x="100" y="50" dy="0.76em" text-anchor="start" font-size="10">abcd</text>
<text x="100" y="50" dy="0.5ex" text-anchor="end" font-size="10">ab&amp;</text>
<text x="12" y="200" dy="0.76em" text-anchor="middle" font-size="10" transform="rotate(270, 12, 200)">vertical label</text></svg>"#;
        let b = text_boxes(svg);
        assert_eq!(b.len(), 3);
        assert_eq!(b[0].0, "abcd");
        let (l, t, r, bo) = b[0].1;
        assert!((l - 100.0).abs() < 1e-9 && (r - 124.0).abs() < 1e-9);
        assert!((t - 50.1).abs() < 1e-9 && (bo - 60.1).abs() < 1e-9);
        assert_eq!(b[1].0, "ab&");
        assert!((b[1].1 .2 - 100.0).abs() < 1e-9 && (b[1].1 .0 - 82.0).abs() < 1e-9);
        // Rotated: taller than wide.
        let v = b[2].1;
        assert!(v.3 - v.1 > v.2 - v.0);
        // The first two share x = 100 only at an edge and overlap vertically: not a clash;
        // move the second right and they do.
        assert!(overlapping_texts(svg).is_empty());
        let moved = svg.replace(
            r#"x="100" y="50" dy="0.5ex""#,
            r#"x="110" y="50" dy="0.5ex""#,
        );
        assert_eq!(overlapping_texts(&moved).len(), 1);
    }

    #[test]
    fn placed_labels_never_overlap_even_on_one_spot() {
        // Twelve points on one pixel and a row of close ones, in a small area.
        let mut pts = vec![(200, 150); 12];
        pts.extend((0..10).map(|k| (100 + 6 * k, 100)));
        let labels: Vec<String> = (0..pts.len()).map(|k| format!("layout-{k}")).collect();
        let fs = LABEL_FONT / SVG_FONT_DIV;
        let area = (0.0, 0.0, 400.0, 300.0);
        let spots = place_labels(&pts, &labels, area, fs);
        let boxes: Vec<TextBox> = spots
            .iter()
            .zip(&labels)
            .filter_map(|(s, l)| {
                s.map(|((x, y), _)| label_box(x as f64, y as f64, l.chars().count(), fs))
            })
            .collect();
        assert_eq!(boxes.len(), pts.len(), "every label found a spot");
        for (i, a) in boxes.iter().enumerate() {
            assert!(a.0 >= 0.0 && a.1 >= 0.0 && a.2 <= 400.0 && a.3 <= 300.0);
            for b in &boxes[i + 1..] {
                assert!(!boxes_overlap(a, b), "{a:?} {b:?}");
            }
        }
    }
}
