//! The browser dashboard: `/` and its assets (embedded in the binary at build time, so the
//! service needs no files and no network beyond itself), plus the two chart renderers the pages
//! post the data they fetched from the API to. The pages call the `/v1` API from the browser with
//! the user's token; these routes hold no data, so they stay open like `/healthz`.

use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use utoipa_axum::router::OpenApiRouter;

use super::extract::Json;
use super::{ApiError, AppState};
use crate::charts::{self, LineChart, ScatterChart};

const INDEX_HTML: &str = include_str!("../../web/index.html");
const APP_JS: &str = include_str!("../../web/app.js");
const STYLE_CSS: &str = include_str!("../../web/style.css");
const FAVICON_SVG: &str = include_str!("../../web/favicon.svg");

/// Most points one chart request may carry (the metrics endpoint returns at most 500 per metric
/// by default; this leaves room for a few dozen series while keeping a render cheap).
pub const MAX_CHART_POINTS: usize = 50_000;
/// Most series of a line chart.
pub const MAX_CHART_SERIES: usize = 32;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .route("/", get(|| asset("text/html; charset=utf-8", INDEX_HTML)))
        .route("/ui/app.js", get(|| asset("text/javascript; charset=utf-8", APP_JS)))
        .route("/ui/style.css", get(|| asset("text/css; charset=utf-8", STYLE_CSS)))
        .route("/ui/favicon.svg", get(|| asset("image/svg+xml", FAVICON_SVG)))
        .route("/ui/charts/line", post(line_chart))
        .route("/ui/charts/scatter", post(scatter_chart))
}

/// An embedded asset. `no-cache` makes the browser revalidate, so a new binary's dashboard is
/// picked up without a hard reload.
async fn asset(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(content_type)),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff")),
        ],
        body,
    )
        .into_response()
}

fn svg(body: String) -> Response {
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/svg+xml")),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-store")),
        ],
        body,
    )
        .into_response()
}

fn too_large(what: &str, count: usize, limit: usize) -> ApiError {
    ApiError::unprocessable(
        "chart_too_large",
        format!("a chart takes at most {limit} {what}, got {count}; ask the metrics endpoint for fewer points (max_points)"),
    )
}

/// `POST /ui/charts/line`: a [`LineChart`] as JSON → SVG.
async fn line_chart(Json(chart): Json<LineChart>) -> Result<Response, ApiError> {
    if chart.series.len() > MAX_CHART_SERIES {
        return Err(too_large("series", chart.series.len(), MAX_CHART_SERIES));
    }
    let points: usize = chart.series.iter().map(|s| s.points.len()).sum();
    if points > MAX_CHART_POINTS {
        return Err(too_large("points", points, MAX_CHART_POINTS));
    }
    Ok(svg(charts::line_svg(&chart)))
}

/// `POST /ui/charts/scatter`: a [`ScatterChart`] as JSON → SVG.
async fn scatter_chart(Json(chart): Json<ScatterChart>) -> Result<Response, ApiError> {
    if chart.points.len() > MAX_CHART_POINTS {
        return Err(too_large("points", chart.points.len(), MAX_CHART_POINTS));
    }
    Ok(svg(charts::scatter_svg(&chart)))
}
