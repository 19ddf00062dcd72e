//! `/v1/results`: jobs' results side by side (the dashboard's Compare), by the rule an
//! experiment's results follow: per job its policy's newest evaluation under one evaluation
//! protocol, the protocols found listed beside them, never a number from another protocol.

use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Query};
use super::{ApiError, AppState};
use crate::domain::{EvalProtocol, JobId};
use crate::jobs::results::{self, ExperimentScores, JobResult, ProtocolChoice, ProtocolResult};

/// Most jobs one request compares.
const MAX_COMPARED: usize = 100;

/// `?jobs=<id>,<id>&protocol=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ResultsQuery {
    /// The jobs, comma-separated: 1 to 100 ids.
    #[param(pattern = r"^[^,\s]+(,[^,\s]+){0,99}$", max_length = 4000)]
    pub jobs: String,
    /// The `key` of one of the `protocols` to show the results under (default: the newest
    /// protocol every job with a result has, else the one most of them have).
    pub protocol: Option<String>,
}

/// The jobs' results under one protocol.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobResults {
    /// The protocol `jobs[].metrics` are under; absent while no job has a result.
    pub protocol: Option<EvalProtocol>,
    /// Why `protocol` is the one shown.
    pub protocol_choice: Option<ProtocolChoice>,
    /// Every protocol one of the jobs has a result under, most jobs first.
    pub protocols: Vec<ProtocolResult>,
    /// The jobs in the order asked, each with its metrics under `protocol` (none where it has no
    /// result under it) and the protocols it has results under.
    pub jobs: Vec<JobResult>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(job_results))
}

/// The results of jobs side by side: each job's paper metrics from its policy's newest
/// evaluation under one evaluation protocol (environment, episodes, seed, deterministic or
/// sampled, runtime), else from its in-training evaluation; the protocols found are listed, and
/// `protocol` picks another.
#[utoipa::path(get, path = "/v1/results", tag = "evaluations", params(ResultsQuery),
    responses((status = 200, body = JobResults),
        (status = 400, description = "No job id or more than 100 (`invalid_jobs`)",
            body = ErrorBody),
        (status = 404, description = "No such job, or a `protocol` none of the jobs has a \
            result under (`not_found`, naming the protocols there are)", body = ErrorBody)))]
async fn job_results(
    State(state): State<AppState>,
    Query(query): Query<ResultsQuery>,
) -> Result<Json<JobResults>, ApiError> {
    let ids = job_ids(&query.jobs)?;
    let mut jobs = Vec::with_capacity(ids.len());
    for id in &ids {
        jobs.push(state.store.job(id).await?);
    }
    let scores = results::scores_of_jobs(&state.store, jobs).await?;
    let requested = query.protocol.map(|key| requested_protocol(&scores, &key)).transpose()?;
    let view = scores.view(requested);
    Ok(Json(JobResults {
        protocol: view.protocol,
        protocol_choice: view.choice,
        protocols: scores.protocols(),
        jobs: view.jobs,
    }))
}

/// The comma-separated ids: 1 to [`MAX_COMPARED`] (a job listed twice is answered twice).
fn job_ids(list: &str) -> Result<Vec<JobId>, ApiError> {
    let ids: Vec<&str> = list.split(',').map(str::trim).filter(|id| !id.is_empty()).collect();
    if ids.is_empty() || ids.len() > MAX_COMPARED {
        return Err(ApiError::bad_request(
            "invalid_jobs",
            format!("jobs: 1 to {MAX_COMPARED} comma-separated job ids, got {}", ids.len()),
        ));
    }
    Ok(ids.into_iter().map(|id| JobId::from(id.to_owned())).collect())
}

/// The protocol a `?protocol=` names, or 404 listing the ones there are (the view it asks for
/// does not exist, as a resource that does not).
pub(super) fn requested_protocol(
    scores: &ExperimentScores,
    key: &str,
) -> Result<EvalProtocol, ApiError> {
    scores.protocol(key).ok_or_else(|| {
        let known: Vec<String> = scores.protocols().into_iter().map(|p| p.protocol.key).collect();
        let known = if known.is_empty() { "none yet".to_owned() } else { known.join(", ") };
        ApiError::NotFound(format!(
            "protocol: no job here has a result under `{key}`; the protocols: {known}"
        ))
    })
}
