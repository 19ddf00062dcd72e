//! Cost-vs-return scatter plots as plain SVG: one point per algorithm at (average cost,
//! normalized return) with standard-error bars on both axes. Hand-written: a few dozen elements
//! do not justify a plotting crate.

use std::fmt::Write as _;

use super::report::{display_name, EnvSummary, Stat};

const WIDTH: f64 = 640.0;
const HEIGHT: f64 = 440.0;
const LEFT: f64 = 70.0;
const RIGHT: f64 = 150.0;
const TOP: f64 = 40.0;
const BOTTOM: f64 = 60.0;
const COLORS: [&str; 5] = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e"];

/// A linear map from data to pixels.
#[derive(Clone, Copy)]
struct Axis {
    low: f64,
    high: f64,
    pixel_low: f64,
    pixel_high: f64,
}

impl Axis {
    /// An axis covering every `mean ± se`, padded by 8% and never empty.
    fn covering(stats: &[Stat], pixel_low: f64, pixel_high: f64, floor_at_zero: bool) -> Axis {
        let finite = stats.iter().filter(|s| s.mean.is_finite());
        let low = finite.clone().map(|s| s.mean - s.se).fold(f64::INFINITY, f64::min);
        let high = finite.map(|s| s.mean + s.se).fold(f64::NEG_INFINITY, f64::max);
        let (low, high) = if low.is_finite() { (low, high) } else { (0.0, 1.0) };
        let pad = ((high - low) * 0.08).max(1e-3 * high.abs().max(1.0));
        let mut low = low - pad;
        if floor_at_zero && low < 0.0 && low + pad >= 0.0 {
            low = 0.0;
        }
        Axis { low, high: high + pad, pixel_low, pixel_high }
    }

    fn px(&self, v: f64) -> f64 {
        self.pixel_low
            + (v - self.low) / (self.high - self.low) * (self.pixel_high - self.pixel_low)
    }

    /// About five round tick values inside the axis.
    fn ticks(&self) -> Vec<f64> {
        let raw = (self.high - self.low) / 5.0;
        let magnitude = 10f64.powf(raw.log10().floor());
        let step = [1.0, 2.0, 5.0, 10.0]
            .iter()
            .map(|m| m * magnitude)
            .find(|s| *s >= raw)
            .unwrap_or(10.0 * magnitude);
        let first = (self.low / step).ceil() as i64;
        let last = (self.high / step).floor() as i64;
        (first..=last).map(|i| i as f64 * step).collect()
    }
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// The SVG document for one environment.
pub fn cost_vs_return(env: &EnvSummary) -> String {
    let rows: Vec<_> = env.rows.iter().filter(|r| r.seeds > 0).collect();
    let x = Axis::covering(
        &rows.iter().map(|r| r.average_cost).collect::<Vec<_>>(),
        LEFT,
        WIDTH - RIGHT,
        true,
    );
    let y = Axis::covering(
        &rows.iter().map(|r| r.normalized_return).collect::<Vec<_>>(),
        HEIGHT - BOTTOM,
        TOP,
        false,
    );
    let mut svg = String::new();
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(svg, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        svg,
        r#"<text x="{}" y="22" text-anchor="middle" font-size="15">{}: average cost vs normalized return (mean ± s.e.)</text>"#,
        (LEFT + WIDTH - RIGHT) / 2.0,
        escape(&env.env)
    );
    write_axes(&mut svg, &x, &y);
    for (i, row) in rows.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let (cx, cy) = (x.px(row.average_cost.mean), y.px(row.normalized_return.mean));
        if !(cx.is_finite() && cy.is_finite()) {
            continue;
        }
        let (c, r) = (row.average_cost, row.normalized_return);
        let _ = writeln!(
            svg,
            r#"<g stroke="{color}" stroke-width="1.5"><line x1="{:.1}" y1="{cy:.1}" x2="{:.1}" y2="{cy:.1}"/><line x1="{cx:.1}" y1="{:.1}" x2="{cx:.1}" y2="{:.1}"/></g>"#,
            x.px(c.mean - c.se),
            x.px(c.mean + c.se),
            y.px(r.mean - r.se),
            y.px(r.mean + r.se)
        );
        let _ = writeln!(svg, r#"<circle cx="{cx:.1}" cy="{cy:.1}" r="5" fill="{color}"/>"#);
        let legend_y = TOP + 20.0 + 22.0 * i as f64;
        let _ = writeln!(
            svg,
            r#"<circle cx="{:.1}" cy="{legend_y:.1}" r="5" fill="{color}"/><text x="{:.1}" y="{:.1}">{}</text>"#,
            WIDTH - RIGHT + 25.0,
            WIDTH - RIGHT + 36.0,
            legend_y + 4.0,
            display_name(row.algorithm)
        );
    }
    svg.push_str("</svg>\n");
    svg
}

fn write_axes(svg: &mut String, x: &Axis, y: &Axis) {
    let (x0, x1, y0, y1) = (LEFT, WIDTH - RIGHT, HEIGHT - BOTTOM, TOP);
    let _ = writeln!(
        svg,
        r#"<rect x="{x0}" y="{y1}" width="{}" height="{}" fill="none" stroke="black"/>"#,
        x1 - x0,
        y0 - y1
    );
    for t in x.ticks() {
        let px = x.px(t);
        let _ = writeln!(
            svg,
            r##"<line x1="{px:.1}" y1="{y0}" x2="{px:.1}" y2="{y1}" stroke="#ddd"/><text x="{px:.1}" y="{}" text-anchor="middle">{}</text>"##,
            y0 + 16.0,
            tick_label(t)
        );
    }
    for t in y.ticks() {
        let py = y.px(t);
        let _ = writeln!(
            svg,
            r##"<line x1="{x0}" y1="{py:.1}" x2="{x1}" y2="{py:.1}" stroke="#ddd"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
            x0 - 6.0,
            py + 4.0,
            tick_label(t)
        );
    }
    let _ = writeln!(
        svg,
        r#"<text x="{}" y="{}" text-anchor="middle">average cost (lower is safer)</text>"#,
        (x0 + x1) / 2.0,
        HEIGHT - 18.0
    );
    let _ = writeln!(
        svg,
        r#"<text transform="translate(20 {}) rotate(-90)" text-anchor="middle">normalized return</text>"#,
        (y0 + y1) / 2.0
    );
}

fn tick_label(v: f64) -> String {
    let text = format!("{v:.3}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    if text == "-0" {
        "0".to_string()
    } else {
        text.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_inside_the_axis() {
        let axis = Axis { low: 0.3, high: 9.7, pixel_low: 0.0, pixel_high: 100.0 };
        assert_eq!(axis.ticks(), vec![2.0, 4.0, 6.0, 8.0]);
        assert_eq!(axis.px(0.3), 0.0);
        assert_eq!(axis.px(9.7), 100.0);
        assert_eq!(tick_label(2.5), "2.5");
        assert_eq!(tick_label(40.0), "40");
    }
}
