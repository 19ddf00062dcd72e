//! `/v1/evaluations`: a trained policy evaluated on a built-in environment with the paper's
//! metrics, as a background task (`POST /v1/policies/{id}/evaluate` queues one; the work
//! happens in [`crate::jobs::evaluations`]), or recorded from the user's own simulator
//! (`POST /v1/policies/{id}/evaluations`).

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::domain::evaluation::{ExternalEvaluation, RecordedEvaluation};
use crate::domain::PolicyId;
use crate::domain::{
    rfc3339, EvalProtocol, EvalRuntime, EvalSpec, EvaluationId, EvaluationRecord, EvaluationSource,
    EvaluationStatus,
};
use crate::envs::{self, Metrics, ReferenceStats};
use crate::store::evaluations::NewEvaluation;
use crate::store::{DeleteOutcome, Listing};

/// A policy's evaluation on a built-in environment.
#[derive(Debug, Serialize, ToSchema)]
pub struct Evaluation {
    pub id: String,
    pub policy_id: String,
    pub env: String,
    pub episodes: usize,
    pub seed: u64,
    pub deterministic: bool,
    /// `builtin` (run by a worker on a built-in environment) or `external` (recorded from the
    /// user's own simulator with `POST /v1/policies/{id}/evaluations`).
    pub source: EvaluationSource,
    /// How the policy acted: `builtin` for the service's own evaluations; for recorded ones
    /// `act`, `onnx` or `other` as the recorder said, `unspecified` where it did not.
    pub runtime: EvalRuntime,
    /// Environment, episodes, seed, deterministic or sampled, and runtime: results are compared
    /// and averaged only within one protocol (experiments group by its `key`).
    pub protocol: EvalProtocol,
    /// Set on the evaluation a job with an `eval` block takes at the end of training: the job's
    /// step it ran at (its last; every phase counts). The job's `eval/*` metrics at that step are
    /// the same numbers. `null` on evaluations run after training.
    #[schema(minimum = 0)]
    pub training_step: Option<u64>,
    pub status: EvaluationStatus,
    /// The paper's metrics over the episodes, once succeeded: normalized return, average cost,
    /// cost-violation ratio, CVaR k% cost and DSRL's normalized cost (definitions in
    /// README "Evaluation metrics").
    pub metrics: Option<Metrics>,
    pub mean_episode_length: Option<f64>,
    /// The environment's demonstrator statistics the normalized return and the cost threshold
    /// come from.
    pub reference: Option<ReferenceStats>,
    /// Why it failed.
    pub error: Option<String>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
}

impl From<EvaluationRecord> for Evaluation {
    fn from(evaluation: EvaluationRecord) -> Self {
        let protocol = evaluation.protocol();
        let (metrics, mean_episode_length, reference) = match evaluation.report {
            Some(r) => (Some(r.metrics), Some(r.mean_episode_length), Some(r.reference)),
            None => (None, None, None),
        };
        let spec = evaluation.spec;
        Evaluation {
            id: evaluation.id.into_string(),
            policy_id: evaluation.policy_id.into_string(),
            env: spec.env,
            episodes: spec.episodes,
            seed: spec.seed,
            deterministic: spec.deterministic,
            source: evaluation.source,
            runtime: evaluation.runtime,
            protocol,
            training_step: evaluation.training_step,
            status: evaluation.status,
            metrics,
            mean_episode_length,
            reference,
            error: evaluation.error,
            created_at: rfc3339(&evaluation.created_at),
            started_at: evaluation.started_at.as_ref().map(rfc3339),
            finished_at: evaluation.finished_at.as_ref().map(rfc3339),
        }
    }
}

/// `?policy_id=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct EvaluationFilter {
    /// Only the evaluations of this policy.
    #[param(value_type = Option<String>)]
    pub policy_id: Option<PolicyId>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(evaluate_policy))
        .routes(routes!(record_evaluation))
        .routes(routes!(list_evaluations))
        .routes(routes!(get_evaluation, delete_evaluation))
}

/// Evaluate a policy on a built-in environment with the paper's metrics, in the background.
/// Poll the returned evaluation (`Location`) until `succeeded` (500 episodes take about a
/// second) or `failed`. The same policy, environment, episodes, seed and `deterministic` give
/// the same metrics.
#[utoipa::path(post, path = "/v1/policies/{id}/evaluate", tag = "evaluations",
    params(("id" = String, Path, description = "Policy id")), request_body = EvalSpec,
    responses(
        (status = 202, description = "Queued", body = Evaluation),
        (status = 404, description = "No such policy", body = ErrorBody),
        (status = 422, description = "Unknown environment, episodes out of range or an \
            environment whose spaces do not match the policy's (`invalid_evaluation`), or a \
            malformed body (`invalid_body`)", body = ErrorBody),
    ))]
async fn evaluate_policy(
    State(state): State<AppState>,
    Path(policy_id): Path<PolicyId>,
    Json(spec): Json<EvalSpec>,
) -> Result<impl IntoResponse, ApiError> {
    let policy = state.store.policy(&policy_id).await?;
    spec.validate("").map_err(|e| ApiError::unprocessable("invalid_evaluation", e.0))?;
    envs::check_spaces(&spec.env, policy.obs_dim, &policy.action_space, "the policy's")
        .map_err(|e| ApiError::unprocessable("invalid_evaluation", format!("env: {e}")))?;
    let env = spec.env.clone();
    let id = EvaluationId::generate();
    let new = NewEvaluation { id, policy_id, spec, recorded: None };
    let evaluation = state.store.insert_evaluation(&new).await?;
    state.jobs.evaluator().wake();
    let id = &evaluation.id;
    tracing::info!(evaluation_id = %id, policy_id = %evaluation.policy_id, %env, "evaluation queued");
    let location = format!("/v1/evaluations/{id}");
    Ok((StatusCode::ACCEPTED, [(header::LOCATION, location)], Json(Evaluation::from(evaluation))))
}

/// Record an evaluation run in your own simulator (MuJoCo, gymnasium, a real robot): send each
/// episode's return and cost and the demonstrators' means on that simulator; the service
/// computes the paper's metrics with the same code as its own evaluations and keeps them with
/// the policy (`source: external`), beside the built-in ones, on the dashboard and in
/// `GET /v1/evaluations`.
#[utoipa::path(post, path = "/v1/policies/{id}/evaluations", tag = "evaluations",
    params(("id" = String, Path, description = "Policy id")), request_body = ExternalEvaluation,
    responses(
        (status = 201, description = "Recorded, with its metrics", body = Evaluation),
        (status = 404, description = "No such policy", body = ErrorBody),
        (status = 422, description = "Episodes out of range, returns and costs of different \
            lengths, a non-finite or negative value, or a reference that cannot normalise \
            (`invalid_evaluation`, naming the field), or a malformed body (`invalid_body`)",
            body = ErrorBody),
    ))]
async fn record_evaluation(
    State(state): State<AppState>,
    Path(policy_id): Path<PolicyId>,
    Json(recorded): Json<ExternalEvaluation>,
) -> Result<impl IntoResponse, ApiError> {
    let RecordedEvaluation { spec, runtime, report } =
        recorded.into_report().map_err(|e| ApiError::unprocessable("invalid_evaluation", e))?;
    let id = EvaluationId::generate();
    let new = NewEvaluation { id, policy_id, spec, recorded: Some((runtime, report)) };
    let evaluation = state.store.insert_evaluation(&new).await?;
    let id = &evaluation.id;
    tracing::info!(evaluation_id = %id, policy_id = %evaluation.policy_id, "external evaluation recorded");
    let location = format!("/v1/evaluations/{id}");
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(Evaluation::from(evaluation))))
}

/// List evaluations, newest first.
#[utoipa::path(get, path = "/v1/evaluations", tag = "evaluations",
    params(EvaluationFilter, PageParams),
    responses((status = 200, body = Page<Evaluation>), (status = 400, body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody),))]
async fn list_evaluations(
    State(state): State<AppState>,
    Query(filter): Query<EvaluationFilter>,
    Query(page): Query<PageParams>,
) -> Result<Json<Page<Evaluation>>, ApiError> {
    let page = page.resolve(&state.store, Listing::Evaluations).await?;
    let (records, total) = state.store.list_evaluations(filter.policy_id.as_ref(), &page).await?;
    let items = records.into_iter().map(Evaluation::from).collect();
    Ok(Json(Page::new(items, total, page, |e: &Evaluation| &e.id)))
}

/// An evaluation: status, and the paper's metrics once it succeeded.
#[utoipa::path(get, path = "/v1/evaluations/{id}", tag = "evaluations",
    params(("id" = String, Path)),
    responses((status = 200, body = Evaluation), (status = 404, body = ErrorBody)))]
async fn get_evaluation(
    State(state): State<AppState>,
    Path(id): Path<EvaluationId>,
) -> Result<Json<Evaluation>, ApiError> {
    Ok(Json(state.store.evaluation(&id).await?.into()))
}

/// Delete a finished evaluation.
#[utoipa::path(delete, path = "/v1/evaluations/{id}", tag = "evaluations",
    params(("id" = String, Path)),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, body = ErrorBody),
        (status = 409, description = "Still queued or running (`evaluation_active`)",
            body = ErrorBody),
    ))]
async fn delete_evaluation(
    State(state): State<AppState>,
    Path(id): Path<EvaluationId>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_evaluation(&id).await? {
        DeleteOutcome::Deleted => Ok(StatusCode::NO_CONTENT),
        DeleteOutcome::NotFound => Err(ApiError::not_found("evaluation", &id)),
        DeleteOutcome::InUse(_) | DeleteOutcome::Registered(_) => Err(ApiError::conflict(
            "evaluation_active",
            format!("evaluation {id} is queued or running; delete it once it has finished"),
        )),
    }
}
