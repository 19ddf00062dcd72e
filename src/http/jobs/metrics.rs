//! A job's metrics history: `/v1/jobs/{id}/metrics` (downsampled on the server),
//! `/metrics.csv` (every recorded value) and `/metrics/names`.

use axum::extract::State;
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use crate::domain::{rfc3339, JobId, MetricRecord};
use crate::http::error::ErrorBody;
use crate::http::extract::{Json, Path, Query};
use crate::http::{ApiError, AppState};
use crate::lttb::lttb_indices;

pub(super) fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(job_metrics))
        .routes(routes!(job_metrics_csv))
        .routes(routes!(job_metric_names))
}

/// `?names=&max_points=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MetricsParams {
    /// Comma-separated metric names (default: every metric of the job).
    pub names: Option<String>,
    /// Most points returned per metric, 2 to 10000 (default 500). Longer histories are
    /// downsampled by LTTB (largest triangle three buckets): recorded points only, the first
    /// and the last always, and the ones that keep the curve's shape (a one-step spike stays).
    #[param(minimum = 2, maximum = 10000, default = 500)]
    pub max_points: Option<usize>,
}

/// One recorded value of a metric.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct MetricPoint {
    pub name: String,
    /// Steps done when the value was recorded (every phase counted).
    pub step: u64,
    pub value: f64,
    /// When it was recorded (RFC 3339).
    pub time: String,
}

/// A job's metrics history.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobMetrics {
    pub job_id: String,
    /// Whether any metric had more than `max_points` points and was downsampled.
    pub downsampled: bool,
    /// Ordered by name, then step.
    pub rows: Vec<MetricPoint>,
}

const DEFAULT_MAX_POINTS: usize = 500;
const MAX_POINTS_LIMIT: usize = 10_000;

/// A job's metrics history (losses, alpha-hat, weight statistics), downsampled on the server.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics", tag = "jobs",
    params(("id" = String, Path), MetricsParams),
    responses(
        (status = 200, body = JobMetrics),
        (status = 400, description = "Bad max_points or names", body = ErrorBody),
        (status = 404, body = ErrorBody),
    ))]
async fn job_metrics(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
    Query(params): Query<MetricsParams>,
) -> Result<Json<JobMetrics>, ApiError> {
    let max_points = params.max_points.unwrap_or(DEFAULT_MAX_POINTS);
    if !(2..=MAX_POINTS_LIMIT).contains(&max_points) {
        return Err(ApiError::bad_request(
            "invalid_max_points",
            format!("max_points must be between 2 and {MAX_POINTS_LIMIT}, got {max_points}"),
        ));
    }
    let names = metric_names_param(params.names.as_deref());
    state.store.job(&id).await?;
    let rows = state.store.job_metrics(&id, names.as_deref()).await?;
    let (rows, downsampled) = downsample(rows, max_points);
    Ok(Json(JobMetrics { job_id: id.into_string(), downsampled, rows }))
}

fn metric_names_param(names: Option<&str>) -> Option<Vec<String>> {
    names.map(|names| {
        names.split(',').map(str::trim).filter(|n| !n.is_empty()).map(str::to_owned).collect()
    })
}

/// `?names=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct CsvParams {
    /// Comma-separated metric names (default: every metric of the job).
    pub names: Option<String>,
}

/// A job's whole metrics history as CSV (`name,step,value,time`, every recorded point, ordered
/// by name then step), as a file download.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics.csv", tag = "jobs",
    params(("id" = String, Path), CsvParams),
    responses(
        (status = 200, description = "CSV with a header line", content_type = "text/csv",
            body = String),
        (status = 404, body = ErrorBody),
    ))]
async fn job_metrics_csv(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
    Query(params): Query<CsvParams>,
) -> Result<impl IntoResponse, ApiError> {
    let names = metric_names_param(params.names.as_deref());
    state.store.job(&id).await?;
    let rows = state.store.job_metrics(&id, names.as_deref()).await?;
    let mut csv = String::from("name,step,value,time\n");
    for row in &rows {
        // Metric names are identifiers (letters, digits, `_`, `/`): no quoting needed.
        csv.push_str(&format!("{},{},{},{}\n", row.name, row.step, row.value, rfc3339(&row.time)));
    }
    crate::http::attachment(&format!("job-{id}-metrics.csv"), "text/csv; charset=utf-8", csv)
}

/// One metric a job recorded.
#[derive(Debug, Serialize, ToSchema)]
pub struct MetricName {
    pub name: String,
    /// Recorded points (before any downsampling).
    pub points: u64,
    pub first_step: u64,
    pub last_step: u64,
}

/// The names of the metrics a job recorded, with their point counts and step ranges.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics/names", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 200, body = Vec<MetricName>), (status = 404, body = ErrorBody)))]
async fn job_metric_names(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
) -> Result<Json<Vec<MetricName>>, ApiError> {
    state.store.job(&id).await?;
    let names = state.store.metric_names(&id).await?;
    Ok(Json(
        names
            .into_iter()
            .map(|m| MetricName {
                name: m.name,
                points: m.points as u64,
                first_step: m.first_step as u64,
                last_step: m.last_step as u64,
            })
            .collect(),
    ))
}

/// Per metric (rows come ordered by name, then step): at most `max_points` points, chosen by
/// LTTB ([`crate::lttb`]): real rows with their own step and time, the first and the last
/// exactly, and the points that shape the curve (spikes included).
fn downsample(rows: Vec<MetricRecord>, max_points: usize) -> (Vec<MetricPoint>, bool) {
    let mut out = Vec::with_capacity(rows.len().min(max_points * 16));
    let mut downsampled = false;
    for series in rows.chunk_by(|a, b| a.name == b.name) {
        if series.len() <= max_points {
            out.extend(series.iter().map(point));
            continue;
        }
        downsampled = true;
        let steps: Vec<f64> = series.iter().map(|r| r.step as f64).collect();
        let values: Vec<f64> = series.iter().map(|r| r.value).collect();
        out.extend(
            lttb_indices(&steps, &values, max_points).into_iter().map(|i| point(&series[i])),
        );
    }
    (out, downsampled)
}

fn point(row: &MetricRecord) -> MetricPoint {
    MetricPoint {
        name: row.name.clone(),
        step: row.step,
        value: row.value,
        time: rfc3339(&row.time),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Second `i` of the series.
    fn time(i: usize) -> chrono::DateTime<chrono::Utc> {
        chrono::DateTime::UNIX_EPOCH + chrono::Duration::seconds(i as i64)
    }

    fn series(name: &str, values: &[f64]) -> Vec<MetricRecord> {
        values
            .iter()
            .enumerate()
            .map(|(i, &value)| MetricRecord {
                name: name.into(),
                step: (i as u64 + 1) * 10,
                value,
                time: time(i),
            })
            .collect()
    }

    #[test]
    fn short_series_are_returned_whole() {
        let rows = series("loss", &[1.0, 2.0, 3.0]);
        let (out, downsampled) = downsample(rows.clone(), 3);
        assert!(!downsampled);
        assert_eq!(out, rows.iter().map(point).collect::<Vec<_>>());
    }

    #[test]
    fn long_series_keep_recorded_points_with_their_spikes_and_both_ends() {
        // 1,000 points of a slowly falling loss with one spike, into 20: the spike and both
        // ends are kept as recorded (step, value and time of the same row).
        let mut values: Vec<f64> = (0..1000).map(|i| 2.0 - f64::from(i) / 1000.0).collect();
        values[617] = 40.0;
        let mut rows = series("a", &values);
        rows.extend(series("b", &[5.0, 6.0]));
        let (out, downsampled) = downsample(rows.clone(), 20);
        assert!(downsampled);
        let a: Vec<&MetricPoint> = out.iter().filter(|p| p.name == "a").collect();
        assert_eq!(a.len(), 20);
        for p in &a {
            let row = rows.iter().find(|r| r.name == "a" && r.step == p.step).unwrap();
            assert_eq!((p.value, &p.time), (row.value, &rfc3339(&row.time)));
        }
        assert_eq!((a[0].step, a[19].step), (10, 10_000));
        assert!(a.iter().any(|p| p.value == 40.0 && p.time == rfc3339(&time(617))));
        assert_eq!(out.iter().filter(|p| p.name == "b").count(), 2);
    }
}
