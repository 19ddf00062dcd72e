//! The benchmark's cost-vs-return plot of one environment: a point per algorithm at (average
//! cost, normalized return) with standard-error bars on both axes, drawn by the dashboard's SVG
//! renderer ([`crate::charts`]) in the dashboard's colours, so a plot in `bench/` and the
//! compare page look alike. Ablation rows (`--ablations`) are left out: they share their
//! algorithm's colour and would read as that algorithm.

use super::summary::EnvSummary;
use crate::charts::{algorithm_color, scatter_svg, ScatterChart, ScatterPoint};

/// The SVG document for one environment.
pub fn cost_vs_return(env: &EnvSummary) -> String {
    let points = env
        .rows
        .iter()
        .filter(|row| row.seeds > 0 && row.variant.is_standard())
        .map(|row| ScatterPoint {
            label: row.algorithm.display_name().into(),
            x: row.average_cost.mean,
            y: row.normalized_return.mean,
            color: Some(algorithm_color(row.algorithm).into()),
            group: Some(row.algorithm.display_name().into()),
            x_error: row.average_cost.error(),
            y_error: row.normalized_return.error(),
        })
        .collect();
    let mut svg = scatter_svg(&ScatterChart {
        title: format!("{}: average cost vs normalized return (mean ± s.e. over seeds)", env.env),
        x_label: "average cost per episode (lower is safer)".into(),
        y_label: "normalized return (100 = preferred demos)".into(),
        points,
    });
    svg.push('\n');
    svg
}
