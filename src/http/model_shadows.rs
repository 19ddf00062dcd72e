//! `GET /v1/models/{name}/shadow`: how an alias's shadow compares with the versions that
//! answered, minute by minute (docs/shadow.md). Every serving node adds its counts to the same
//! minutes, so any node answers for the fleet; this node's own counts are stored first, so a
//! request this node answered before the read is in it (other nodes' within their flush
//! interval).

use std::time::Duration;

use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::{ApiError, AppState};
use crate::data::ActionSpace;
use crate::domain::model::ModelName;
use crate::domain::rfc3339;
use crate::domain::shadow::{ComparisonCounts, ComparisonSeries};

/// Longest window of a series, in minutes (a week).
const MAX_MINUTES: u32 = 7 * 24 * 60;
/// How long a read waits for this node's queued comparisons to finish.
const SETTLE: Duration = Duration::from_secs(2);

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(shadow_series))
}

/// `?alias=&minutes=`.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ShadowParams {
    /// Only this alias's comparisons (a filter, as the history's: a name no alias has matches
    /// nothing).
    pub alias: Option<String>,
    /// The window: the last `minutes` minutes, 1-10080 (default 60).
    #[param(minimum = 1, maximum = 10080)]
    pub minutes: Option<u32>,
}

/// The comparisons of a model's shadows.
#[derive(Debug, Serialize, ToSchema)]
pub struct ShadowReport {
    pub model: String,
    /// The window's start (the first minute reported).
    pub since: String,
    /// One series per alias, answering version and shadow version.
    pub series: Vec<ShadowSeriesResource>,
}

/// One shadow compared with one answering version.
#[derive(Debug, Serialize, ToSchema)]
pub struct ShadowSeriesResource {
    pub alias: String,
    /// The version that answered the requests.
    pub production_version: u32,
    /// The shadow's version.
    pub shadow_version: u32,
    /// `continuous` (L2 and max-abs differences) or `discrete` (disagreement rate); absent when
    /// the answering version is gone.
    pub actions: Option<String>,
    /// The whole window.
    pub total: ComparisonStats,
    /// Minute by minute, oldest first; minutes without a shadowed request are absent.
    pub points: Vec<ComparisonPointResource>,
}

/// One minute of a comparison.
#[derive(Debug, Serialize, ToSchema)]
pub struct ComparisonPointResource {
    /// The minute's start.
    pub minute: String,
    #[serde(flatten)]
    pub stats: ComparisonStats,
}

/// A comparison's counts and means. A mean is absent when nothing was counted.
#[derive(Debug, Serialize, ToSchema)]
pub struct ComparisonStats {
    /// Requests drawn for the shadow.
    pub requests: u64,
    /// Of them, not run: the shadow's queue was full or its policy not loaded on the node.
    pub skipped: u64,
    /// Of them, run but not comparable (the shadow failed).
    pub failed: u64,
    /// Observations compared.
    pub observations: u64,
    /// Continuous actions: mean and largest L2 distance between the two actions, in the
    /// action's units.
    pub mean_l2: Option<f64>,
    pub max_l2: Option<f64>,
    /// Continuous actions: mean and largest of the largest absolute difference of one
    /// coordinate.
    pub mean_max_abs: Option<f64>,
    pub max_max_abs: Option<f64>,
    /// Discrete actions: the share of observations where the two chose differently.
    pub disagreement_rate: Option<f64>,
    /// The shadow's mean `non_preferred_log_ratio` of its actions (SafeDICE shadows).
    pub shadow_mean_log_ratio: Option<f64>,
    /// The answering version's mean `non_preferred_log_ratio` of its actions (SafeDICE).
    pub production_mean_log_ratio: Option<f64>,
    /// The shadow's mean `out_of_support` of the observations (SafeDICE shadows).
    pub shadow_mean_out_of_support: Option<f64>,
    /// The shadow's mean compute time per request run, milliseconds.
    pub mean_shadow_ms: Option<f64>,
}

impl ComparisonStats {
    fn of(c: &ComparisonCounts, discrete: Option<bool>) -> Self {
        let mean = |sum: f64, n: u64| (n > 0).then(|| sum / n as f64);
        let continuous = discrete == Some(false) && c.observations > 0;
        let ran = c.requests - c.skipped;
        ComparisonStats {
            requests: c.requests,
            skipped: c.skipped,
            failed: c.failed,
            observations: c.observations,
            mean_l2: continuous.then(|| c.l2_sum / c.observations as f64),
            max_l2: continuous.then_some(c.l2_max),
            mean_max_abs: continuous.then(|| c.max_abs_sum / c.observations as f64),
            max_max_abs: continuous.then_some(c.max_abs_max),
            disagreement_rate: (discrete == Some(true))
                .then(|| mean(c.disagreements as f64, c.observations))
                .flatten(),
            shadow_mean_log_ratio: mean(c.shadow_log_ratio_sum, c.shadow_log_ratio_n),
            production_mean_log_ratio: mean(c.production_log_ratio_sum, c.production_log_ratio_n),
            shadow_mean_out_of_support: mean(c.out_of_support_sum, c.out_of_support_n),
            mean_shadow_ms: mean(c.shadow_ns as f64 / 1e6, ran),
        }
    }
}

/// How a model's shadows compare with the versions that answered, minute by minute, over the
/// last `minutes` (every node of a fleet adds to the same minutes). Set a shadow with
/// `PUT /v1/models/{name}/aliases/{alias}` and `shadow`.
#[utoipa::path(get, path = "/v1/models/{name}/shadow", tag = "models",
    params(("name" = String, Path), ShadowParams),
    responses((status = 200, body = ShadowReport),
        (status = 400, description = "`minutes` out of range (`invalid_window`)", body = ErrorBody),
        (status = 404, body = ErrorBody)))]
async fn shadow_series(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(params): Query<ShadowParams>,
) -> Result<Json<ShadowReport>, ApiError> {
    let model = super::model_names::model_name(&name)?;
    let minutes = params.minutes.unwrap_or(60);
    if !(1..=MAX_MINUTES).contains(&minutes) {
        return Err(ApiError::bad_request(
            "invalid_window",
            format!("minutes must be between 1 and {MAX_MINUTES}, got {minutes}"),
        ));
    }
    if let Err(e) = state.serving.models.shadows().settle(SETTLE).await {
        tracing::warn!(error = %e, "cannot store this node's shadow comparisons before a read");
    }
    let now = chrono::Utc::now();
    let since = now - chrono::TimeDelta::minutes(i64::from(minutes) - 1);
    let since = chrono::DurationRound::duration_trunc(since, chrono::TimeDelta::minutes(1))
        .map_err(|e| ApiError::Internal(anyhow::anyhow!("{e}")))?;
    let stored = state.store.shadow_series(&model, params.alias.as_deref(), &since).await?;
    let mut series = Vec::with_capacity(stored.len());
    for one in stored {
        series.push(resource(&state, &model, one).await);
    }
    Ok(Json(ShadowReport { model: name, since: rfc3339(&since), series }))
}

async fn resource(
    state: &AppState,
    model: &ModelName,
    series: ComparisonSeries,
) -> ShadowSeriesResource {
    let discrete = action_kind(state, model, series.key.production_version).await;
    let mut total = ComparisonCounts::default();
    let points = series
        .points
        .iter()
        .map(|p| {
            total.merge(&p.counts);
            ComparisonPointResource {
                minute: rfc3339(&p.minute),
                stats: ComparisonStats::of(&p.counts, discrete),
            }
        })
        .collect();
    ShadowSeriesResource {
        alias: series.key.alias,
        production_version: series.key.production_version,
        shadow_version: series.key.shadow_version,
        actions: discrete.map(|d| if d { "discrete" } else { "continuous" }.to_owned()),
        total: ComparisonStats::of(&total, discrete),
        points,
    }
}

/// Whether the version gives discrete actions (None: the version or its policy is gone).
async fn action_kind(state: &AppState, model: &ModelName, version: u32) -> Option<bool> {
    let record = state.store.model_version(model, version).await.ok()?;
    let policy = state.store.policy(&record.policy_id).await.ok()?;
    Some(matches!(policy.action_space, ActionSpace::Discrete { .. }))
}
