//! Server-side SVG scatter plots for the benchmark report (`safedice bench` writes one per
//! environment beside results.md): axes, tick labels, axis titles (units included), error bars
//! and a legend, as self-contained SVG (no scripts, no external references) with every text
//! escaped. The dashboard draws its charts in the browser (web/charts.js), where they can show
//! values on hover, zoom and switch to a log scale.

use serde::Deserialize;
use std::fmt::Write;

const WIDTH: f64 = 640.0;
const HEIGHT: f64 = 300.0;
const MARGIN_LEFT: f64 = 64.0;
const MARGIN_RIGHT: f64 = 16.0;
const MARGIN_TOP: f64 = 34.0;
const MARGIN_BOTTOM: f64 = 46.0;
/// Colours of further series when the caller names none (distinct, readable on white).
const PALETTE: [&str; 8] =
    ["#2563eb", "#d97706", "#059669", "#7c3aed", "#dc2626", "#0891b2", "#65a30d", "#db2777"];

/// One labelled point of a scatter plot.
#[derive(Debug, Clone, Deserialize)]
pub struct ScatterPoint {
    pub label: String,
    pub x: f64,
    pub y: f64,
    pub color: Option<String>,
    /// Legend group (e.g. the algorithm); points of a group share its first colour.
    pub group: Option<String>,
    /// Half-widths of error bars (e.g. standard errors over seeds), drawn when given.
    #[serde(default)]
    pub x_error: Option<f64>,
    #[serde(default)]
    pub y_error: Option<f64>,
}

impl ScatterPoint {
    /// The point's extent along x, its error bar included.
    fn x_range(&self) -> [f64; 2] {
        let e = self.x_error.filter(|e| e.is_finite()).unwrap_or(0.0).abs();
        [self.x - e, self.x + e]
    }

    fn y_range(&self) -> [f64; 2] {
        let e = self.y_error.filter(|e| e.is_finite()).unwrap_or(0.0).abs();
        [self.y - e, self.y + e]
    }
}

/// The accent colour of each algorithm, the same everywhere: benchmark plots, and the dashboard,
/// which reads it from `GET /v1/algorithms` (both from the algorithm table).
pub fn algorithm_color(algorithm: crate::algo::Algorithm) -> &'static str {
    algorithm.spec().color
}

/// A scatter plot of labelled points.
#[derive(Debug, Clone, Deserialize)]
pub struct ScatterChart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub points: Vec<ScatterPoint>,
}

/// A linear map of a data range onto a pixel range, with "nice" tick values.
struct Axis {
    low: f64,
    high: f64,
    ticks: Vec<f64>,
}

impl Axis {
    /// An axis covering `values` (finite ones), widened to round tick values.
    fn covering(values: impl Iterator<Item = f64>) -> Axis {
        let (mut low, mut high) = values
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
        if !low.is_finite() {
            (low, high) = (0.0, 1.0);
        }
        if high - low <= f64::EPSILON * high.abs().max(1.0) {
            // A constant series: centre it in a band of ±10 % of its magnitude (±1 around 0).
            let pad = if low == 0.0 { 1.0 } else { low.abs() * 0.1 };
            (low, high) = (low - pad, high + pad);
        }
        let step = nice_step((high - low) / 5.0);
        let low = (low / step).floor() * step;
        let high = (high / step).ceil() * step;
        let count = ((high - low) / step).round() as usize;
        let ticks = (0..=count).map(|i| low + i as f64 * step).collect();
        Axis { low, high, ticks }
    }

    /// Position of `v` in `[0, 1]`.
    fn fraction(&self, v: f64) -> f64 {
        (v - self.low) / (self.high - self.low)
    }
}

/// The round number (1, 2 or 5 times a power of ten) nearest above `raw`.
fn nice_step(raw: f64) -> f64 {
    let magnitude = 10f64.powf(raw.log10().floor());
    let normalised = raw / magnitude;
    let nice = if normalised <= 1.0 {
        1.0
    } else if normalised <= 2.0 {
        2.0
    } else if normalised <= 5.0 {
        5.0
    } else {
        10.0
    };
    nice * magnitude
}

/// A tick label: short, without float noise (0.30000000000000004 → "0.3"), exponent form for
/// very large or small magnitudes.
fn tick_label(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let magnitude = v.abs();
    if !(1e-3..1e5).contains(&magnitude) {
        return format!("{v:.1e}");
    }
    let text = format!("{v:.4}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    text.to_string()
}

/// Escapes text for SVG character data and attribute values.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A colour the caller gave, kept only when it is a plain CSS colour (hex or a name), so no
/// markup can ride along in an attribute.
fn safe_color(color: Option<&str>, fallback_index: usize) -> String {
    match color {
        Some(c)
            if !c.is_empty()
                && c.len() <= 32
                && c.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '#') =>
        {
            c.to_string()
        }
        _ => PALETTE[fallback_index % PALETTE.len()].to_string(),
    }
}

/// The plot area in pixels: below the title and the legend rows.
struct Frame {
    x: Axis,
    y: Axis,
    top: f64,
}

impl Frame {
    fn px(&self, x: f64) -> f64 {
        MARGIN_LEFT + self.x.fraction(x) * (WIDTH - MARGIN_LEFT - MARGIN_RIGHT)
    }

    fn py(&self, y: f64) -> f64 {
        HEIGHT - MARGIN_BOTTOM - self.y.fraction(y) * (HEIGHT - self.top - MARGIN_BOTTOM)
    }
}

/// Opening tag, title, axes with grid lines and tick labels, and the axis titles.
fn frame_svg(out: &mut String, kind: &str, title: &str, x_label: &str, y_label: &str, f: &Frame) {
    let (w, h) = (WIDTH, HEIGHT);
    let _ = write!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" class="chart chart-{kind}" viewBox="0 0 {w} {h}" role="img" aria-label="{t}" font-family="system-ui, sans-serif" font-size="11">"#,
        t = escape(title)
    );
    let _ = write!(out, r#"<title>{}</title>"#, escape(title));
    let _ = write!(
        out,
        r##"<text class="chart-title" x="{MARGIN_LEFT}" y="20" font-size="13" font-weight="600" fill="#111827">{}</text>"##,
        escape(title)
    );
    let (left, right) = (MARGIN_LEFT, WIDTH - MARGIN_RIGHT);
    let (top, bottom) = (f.top, HEIGHT - MARGIN_BOTTOM);
    out.push_str(r##"<g class="grid" stroke="#e5e7eb" stroke-width="1">"##);
    for &t in &f.y.ticks {
        let y = f.py(t);
        let _ = write!(out, r#"<line x1="{left}" x2="{right}" y1="{y:.1}" y2="{y:.1}"/>"#);
    }
    for &t in &f.x.ticks {
        let x = f.px(t);
        let _ = write!(out, r#"<line x1="{x:.1}" x2="{x:.1}" y1="{top}" y2="{bottom}"/>"#);
    }
    out.push_str("</g>");
    let _ = write!(
        out,
        r##"<g class="axes" stroke="#6b7280" stroke-width="1"><line x1="{left}" x2="{right}" y1="{bottom}" y2="{bottom}"/><line x1="{left}" x2="{left}" y1="{top}" y2="{bottom}"/></g>"##
    );
    out.push_str(r##"<g class="y-ticks" fill="#374151" text-anchor="end">"##);
    for &t in &f.y.ticks {
        let _ = write!(
            out,
            r#"<text x="{}" y="{:.1}">{}</text>"#,
            left - 6.0,
            f.py(t) + 4.0,
            tick_label(t)
        );
    }
    out.push_str("</g>");
    out.push_str(r##"<g class="x-ticks" fill="#374151" text-anchor="middle">"##);
    for &t in &f.x.ticks {
        let _ = write!(
            out,
            r#"<text x="{:.1}" y="{}">{}</text>"#,
            f.px(t),
            bottom + 15.0,
            tick_label(t)
        );
    }
    out.push_str("</g>");
    let _ = write!(
        out,
        r##"<text class="x-label" x="{:.1}" y="{}" text-anchor="middle" fill="#111827">{}</text>"##,
        (left + right) / 2.0,
        HEIGHT - 8.0,
        escape(x_label)
    );
    let mid = (top + bottom) / 2.0;
    let _ = write!(
        out,
        r##"<text class="y-label" x="14" y="{mid:.1}" text-anchor="middle" fill="#111827" transform="rotate(-90 14 {mid:.1})">{}</text>"##,
        escape(y_label)
    );
}

/// The "nothing to draw" message inside an empty frame.
fn empty_note(out: &mut String) {
    let _ = write!(
        out,
        r##"<text class="chart-empty" x="{:.1}" y="{:.1}" text-anchor="middle" fill="#6b7280">No data points yet</text>"##,
        (MARGIN_LEFT + WIDTH - MARGIN_RIGHT) / 2.0,
        (MARGIN_TOP + HEIGHT - MARGIN_BOTTOM) / 2.0
    );
}

/// Height of one legend row.
const LEGEND_ROW: f64 = 15.0;

/// Legend entries placed left to right under the title, wrapping at the chart's width:
/// (row, x, name, colour).
fn legend_layout(entries: &[(String, String)]) -> Vec<(usize, f64, &str, &str)> {
    let mut placed = Vec::with_capacity(entries.len());
    let (mut row, mut x) = (0, MARGIN_LEFT);
    for (name, color) in entries {
        // Approximate text width: 6.2 px per character at font-size 11.
        let width = 20.0 + 6.2 * name.chars().count() as f64;
        if x + width > WIDTH - MARGIN_RIGHT && x > MARGIN_LEFT {
            (row, x) = (row + 1, MARGIN_LEFT);
        }
        placed.push((row, x, name.as_str(), color.as_str()));
        x += width;
    }
    placed
}

fn legend_rows(entries: &[(String, String)]) -> usize {
    legend_layout(entries).last().map_or(0, |&(row, ..)| row + 1)
}

/// Top of the plot area below `rows` legend rows.
fn plot_top(rows: usize) -> f64 {
    MARGIN_TOP + LEGEND_ROW * rows as f64
}

fn legend(out: &mut String, entries: &[(String, String)]) {
    out.push_str(r#"<g class="legend">"#);
    for (row, x, name, color) in legend_layout(entries) {
        let y = 36.0 + LEGEND_ROW * row as f64;
        let _ = write!(
            out,
            r##"<rect x="{x:.1}" y="{:.1}" width="10" height="10" rx="2" fill="{color}"/><text x="{:.1}" y="{y:.1}" fill="#374151">{}</text>"##,
            y - 9.0,
            x + 14.0,
            escape(name)
        );
    }
    out.push_str("</g>");
}

/// Renders a scatter plot: a labelled `<circle class="point">` per finite point (with its error
/// bars when given), a legend of the groups.
pub fn scatter_svg(chart: &ScatterChart) -> String {
    let points: Vec<&ScatterPoint> =
        chart.points.iter().filter(|p| p.x.is_finite() && p.y.is_finite()).collect();
    let mut groups: Vec<(String, String)> = Vec::new();
    let mut colors = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let group = p.group.clone().unwrap_or_else(|| p.label.clone());
        let color = match groups.iter().find(|(g, _)| *g == group) {
            Some((_, c)) => c.clone(),
            None => {
                let c = safe_color(p.color.as_deref(), i);
                groups.push((group, c.clone()));
                c
            }
        };
        colors.push(color);
    }
    let frame = Frame {
        x: Axis::covering(points.iter().flat_map(|p| p.x_range())),
        y: Axis::covering(points.iter().flat_map(|p| p.y_range())),
        top: plot_top(legend_rows(&groups)),
    };
    let mut out = String::new();
    frame_svg(&mut out, "scatter", &chart.title, &chart.x_label, &chart.y_label, &frame);
    if points.is_empty() {
        empty_note(&mut out);
    }
    for (p, color) in points.iter().zip(&colors) {
        error_bars(&mut out, &frame, p, color);
        let (x, y) = (frame.px(p.x), frame.py(p.y));
        // Labels of points near the right edge go to their left, so they are not cut off.
        let near_right = x > WIDTH - MARGIN_RIGHT - 90.0;
        let anchor = if near_right { "end" } else { "start" };
        let _ = write!(
            out,
            r##"<g class="point" data-label="{l}"><circle cx="{x:.1}" cy="{y:.1}" r="5" fill="{color}" fill-opacity="0.85" stroke="#111827" stroke-width="0.6"><title>{l}: ({}, {})</title></circle><text x="{:.1}" y="{:.1}" text-anchor="{anchor}" fill="#374151">{l}</text></g>"##,
            tick_label(p.x),
            tick_label(p.y),
            if near_right { x - 7.0 } else { x + 7.0 },
            y - 6.0,
            l = escape(&p.label)
        );
    }
    legend(&mut out, &groups);
    out.push_str("</svg>");
    out
}

/// The horizontal and vertical error bars of a point, when it has them.
fn error_bars(out: &mut String, frame: &Frame, p: &ScatterPoint, color: &str) {
    if p.x_error.is_none() && p.y_error.is_none() {
        return;
    }
    let ([x0, x1], [y0, y1]) = (p.x_range(), p.y_range());
    let (x, y) = (frame.px(p.x), frame.py(p.y));
    let _ = write!(
        out,
        r#"<g class="error-bars" stroke="{color}" stroke-width="1.5"><line x1="{:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}"/><line x1="{x:.1}" y1="{:.1}" x2="{x:.1}" y2="{:.1}"/></g>"#,
        frame.px(x0),
        frame.px(x1),
        frame.py(y0),
        frame.py(y1)
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_steps_are_one_two_or_five_times_a_power_of_ten() {
        assert_eq!(nice_step(0.8), 1.0);
        assert_eq!(nice_step(1.3), 2.0);
        assert_eq!(nice_step(3.0), 5.0);
        assert_eq!(nice_step(7.0), 10.0);
        assert!((nice_step(0.031) - 0.05).abs() < 1e-12);
        assert_eq!(nice_step(2400.0), 5000.0);
    }

    #[test]
    fn axes_cover_the_data_with_round_ticks() {
        let axis = Axis::covering([0.3, 9.7, f64::NAN].into_iter());
        assert_eq!((axis.low, axis.high), (0.0, 10.0));
        assert_eq!(axis.ticks, [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        let constant = Axis::covering([5.0, 5.0].into_iter());
        assert!(constant.low < 5.0 && constant.high > 5.0);
        let empty = Axis::covering(std::iter::empty());
        assert_eq!((empty.low, empty.high), (0.0, 1.0));
    }

    #[test]
    fn tick_labels_drop_float_noise() {
        assert_eq!(tick_label(0.1 + 0.2), "0.3");
        assert_eq!(tick_label(200.0), "200");
        assert_eq!(tick_label(-1.5), "-1.5");
        assert_eq!(tick_label(0.0), "0");
        assert_eq!(tick_label(2.0e6), "2.0e6");
    }

    #[test]
    fn an_empty_scatter_plot_says_so() {
        let svg = scatter_svg(&ScatterChart {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            points: vec![],
        });
        assert!(svg.contains("No data points yet"));
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>"));
    }

    #[test]
    fn text_and_colours_cannot_inject_markup() {
        let svg = scatter_svg(&ScatterChart {
            title: "<script>alert(1)</script>".into(),
            x_label: "a\"b".into(),
            y_label: "y".into(),
            points: vec![ScatterPoint {
                label: "x' onload='evil".into(),
                x: 1.0,
                y: 2.0,
                group: None,
                color: Some("red\" onload=\"evil".into()),
                x_error: None,
                y_error: None,
            }],
        });
        assert!(!svg.contains("<script>") && !svg.contains("onload=\""));
        assert!(svg.contains("&lt;script&gt;") && svg.contains("a&quot;b"));
        assert!(svg.contains("x&#39; onload=&#39;evil"));
    }

    #[test]
    fn a_scatter_plot_labels_each_point_and_colours_groups_alike() {
        let point = |label: &str, x, y, group: &str, color: &str| ScatterPoint {
            label: label.into(),
            x,
            y,
            group: Some(group.into()),
            color: Some(color.into()),
            x_error: None,
            y_error: None,
        };
        let svg = scatter_svg(&ScatterChart {
            title: "Cost vs return".into(),
            x_label: "average cost".into(),
            y_label: "return".into(),
            points: vec![
                point("job a", 1.0, 10.0, "safedice", "#2563eb"),
                point("job b", 2.0, 20.0, "safedice", "#000000"),
                point("job c", 3.0, f64::INFINITY, "bc", "#6b7280"),
            ],
        });
        assert_eq!(svg.matches(r#"<g class="point""#).count(), 2);
        assert_eq!(svg.matches("fill=\"#2563eb\"").count(), 3, "two points and a legend swatch");
        assert!(!svg.contains("job c"));
    }

    #[test]
    fn error_bars_span_the_given_half_widths_and_widen_the_axes() {
        let point = ScatterPoint {
            label: "SafeDICE".into(),
            x: 5.0,
            y: 50.0,
            color: None,
            group: None,
            x_error: Some(1.0),
            y_error: Some(30.0),
        };
        let chart = ScatterChart {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            points: vec![point.clone()],
        };
        let svg = scatter_svg(&chart);
        assert_eq!(svg.matches(r#"<g class="error-bars""#).count(), 1);
        let frame = Frame {
            x: Axis::covering(point.x_range().into_iter()),
            y: Axis::covering(point.y_range().into_iter()),
            top: plot_top(1),
        };
        // The bars end at mean ± error, inside the axes (which cover them).
        let expected = format!(
            r#"<line x1="{:.1}" y1="{:.1}" x2="{:.1}""#,
            frame.px(4.0),
            frame.py(50.0),
            frame.px(6.0)
        );
        assert!(svg.contains(&expected), "{svg}");
        assert!(frame.y.low <= 20.0 && frame.y.high >= 80.0);
        let without = ScatterPoint { x_error: None, y_error: None, ..point };
        let svg = scatter_svg(&ScatterChart { points: vec![without], ..chart });
        assert!(!svg.contains("error-bars"));
    }
}
