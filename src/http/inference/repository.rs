//! Two Open Inference Protocol extensions, as Triton serves them: the model repository
//! (`POST /v2/repository/index`, `POST /v2/repository/models/{name}/load` and `…/unload`) and
//! statistics (`GET /v2/models/{name}/stats`, `GET /v2/models/{name}/versions/{v}/stats`).
//!
//! The repository is the named models of the store (`/v1/models`); every API node loads all of
//! them at start and follows their changes. Load and unload act on the node that receives them
//! (as on a Triton server): an unloaded model answers 404 on that node until it is loaded
//! again, and the other nodes keep serving it. Statistics are this node's, since it started.

use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::binary::V2Error;
use crate::http::extract::Path;
use crate::http::{ApiError, AppState};
use crate::serving::inference::{
    load as load_model, statistics, unload as unload_model, Statistics,
};
use crate::serving::tally::ScoreCounts;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(index))
        .routes(routes!(load))
        .routes(routes!(unload))
        .routes(routes!(model_stats))
        .routes(routes!(version_stats))
}

/// One model of the repository index.
#[derive(Debug, Serialize, ToSchema)]
pub struct IndexItem {
    pub name: String,
    /// The latest version, when it has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// `READY` or `UNAVAILABLE`.
    pub state: String,
    /// Why it is unavailable.
    pub reason: String,
}

/// The named models and whether each is ready on this node. (A request body, such as
/// tritonclient's `{"ready": false}`, is accepted and not needed.)
#[utoipa::path(post, path = "/v2/repository/index", tag = "inference",
    responses((status = 200, body = Vec<IndexItem>)))]
async fn index(State(state): State<AppState>) -> Result<axum::Json<Vec<IndexItem>>, ApiError> {
    let entries = state.serving.models.index().await?;
    Ok(axum::Json(
        entries
            .into_iter()
            .map(|e| IndexItem {
                name: e.name,
                version: e.latest_version.map(|v| v.to_string()),
                state: e.state.into(),
                reason: e.reason,
            })
            .collect(),
    ))
}

/// Loads a named model on this node (again after an unload) and answers once it is ready.
#[utoipa::path(post, path = "/v2/repository/models/{name}/load", tag = "inference",
    params(("name" = String, Path)),
    responses((status = 200, description = "Loaded"), (status = 404, body = V2Error)))]
async fn load(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<serde_json::Value>, ApiError> {
    load_model(&state.serving, &name).await?;
    Ok(axum::Json(serde_json::json!({})))
}

/// Stops serving a named model on this node (other nodes keep serving it).
#[utoipa::path(post, path = "/v2/repository/models/{name}/unload", tag = "inference",
    params(("name" = String, Path)),
    responses((status = 200, description = "Unloaded"), (status = 404, body = V2Error)))]
async fn unload(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<serde_json::Value>, ApiError> {
    unload_model(&state.serving, &name).await?;
    Ok(axum::Json(serde_json::json!({})))
}

/// A count and the time it took, as the statistics extension reports them.
#[derive(Debug, Serialize, ToSchema)]
pub struct InferDuration {
    pub count: u64,
    pub ns: u64,
}

/// Successful and failed inferences.
#[derive(Debug, Serialize, ToSchema)]
pub struct InferStats {
    pub success: InferDuration,
    pub fail: InferDuration,
}

/// One version's statistics on this node.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelStat {
    pub name: String,
    pub version: String,
    /// Milliseconds since the Unix epoch of the last request (0: none).
    pub last_inference: u64,
    pub inference_count: u64,
    pub execution_count: u64,
    pub inference_stats: InferStats,
    /// This service's addition: counts of the safety scores the version answered on this node
    /// (docs/safety-scores.md), once it answered any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub safety_scores: Option<SafetyScoreCounts>,
}

/// Counts of each safety score in fixed bins.
#[derive(Debug, Serialize, ToSchema)]
pub struct SafetyScoreCounts {
    pub non_preferred_log_ratio: ScoreCounts,
    pub out_of_support: ScoreCounts,
}

/// `{"model_stats": [...]}`.
#[derive(Debug, Serialize, ToSchema)]
pub struct StatsResponse {
    pub model_stats: Vec<ModelStat>,
}

fn stat(stats: Statistics) -> ModelStat {
    ModelStat {
        name: stats.name,
        version: stats.version.to_string(),
        last_inference: stats.last_inference,
        inference_count: stats.success,
        execution_count: stats.success,
        inference_stats: InferStats {
            success: InferDuration { count: stats.success, ns: stats.success_ns },
            fail: InferDuration { count: stats.fail, ns: stats.fail_ns },
        },
        safety_scores: (stats.safety.0.total() + stats.safety.1.total() > 0).then(|| {
            let (non_preferred_log_ratio, out_of_support) = stats.safety;
            SafetyScoreCounts { non_preferred_log_ratio, out_of_support }
        }),
    }
}

/// Request counts and time of every version of a named model on this node.
#[utoipa::path(get, path = "/v2/models/{name}/stats", tag = "inference",
    params(("name" = String, Path)),
    responses((status = 200, body = StatsResponse), (status = 404, body = V2Error)))]
async fn model_stats(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<StatsResponse>, ApiError> {
    let model_stats = statistics(&state.serving, &name, None).await?;
    Ok(axum::Json(StatsResponse { model_stats: model_stats.into_iter().map(stat).collect() }))
}

/// `{name, version}` of the versioned route.
#[derive(Debug, serde::Deserialize)]
struct VersionPath {
    name: String,
    version: String,
}

/// Request counts and time of one version of a named model on this node.
#[utoipa::path(get, path = "/v2/models/{name}/versions/{version}/stats", tag = "inference",
    params(("name" = String, Path), ("version" = String, Path)),
    responses((status = 200, body = StatsResponse), (status = 404, body = V2Error)))]
async fn version_stats(
    State(state): State<AppState>,
    Path(path): Path<VersionPath>,
) -> Result<axum::Json<StatsResponse>, ApiError> {
    let model_stats = statistics(&state.serving, &path.name, Some(&path.version)).await?;
    Ok(axum::Json(StatsResponse { model_stats: model_stats.into_iter().map(stat).collect() }))
}
