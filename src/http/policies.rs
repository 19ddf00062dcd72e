//! `/v1/policies`: the policies trained jobs produced, their artefacts, and actions from them.

use axum::extract::State;
use axum::http::{HeaderName, HeaderValue, StatusCode};
use axum::response::Response;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::act::{act_on, ActRequest, ActResponse, ACTION_BODY_LIMIT};
use super::client_slots::RequestClient;
use super::error::ErrorBody;
use super::extract::{Json, Path, Query, StraightJson};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState, OCTET_STREAM};
use crate::algo::Algorithm;
use crate::domain::{rfc3339, JobId, PolicyId, PolicyRecord};
use crate::serving::act::{resolve, ActTarget};
use crate::store::{DeleteOutcome, Listing};

/// Header of `GET /v1/policies/{id}/weights` carrying the policy's spec (JSON), which
/// `algo::Policy::load` needs beside the weights.
pub const SPEC_HEADER: HeaderName = HeaderName::from_static("x-safedice-policy-spec");

/// A trained policy.
#[derive(Debug, Serialize, ToSchema)]
pub struct PolicyResource {
    pub id: String,
    pub algorithm: Algorithm,
    /// The job that trained it.
    pub job_id: String,
    /// That job's name (absent: none).
    pub job_name: Option<String>,
    pub obs_dim: usize,
    /// The dataset's action space; actions are returned in its units.
    #[schema(value_type = Object)]
    pub action_space: serde_json::Value,
    /// The last recorded value of each training metric.
    #[schema(value_type = Object)]
    pub final_metrics: serde_json::Value,
    /// SafeDICE's alpha-hat (Eq. 15).
    pub alpha_hat: Option<f64>,
    /// Everything needed besides the weights to rebuild the policy (architecture, action
    /// scaling, observation normalisation); also sent as the `x-safedice-policy-spec` header of
    /// the weights download.
    #[schema(value_type = Object)]
    pub spec: serde_json::Value,
    /// Where the safetensors weights are downloaded.
    pub weights_url: String,
    pub created_at: String,
}

impl From<PolicyRecord> for PolicyResource {
    fn from(policy: PolicyRecord) -> Self {
        PolicyResource {
            weights_url: format!("/v1/policies/{}/weights", policy.id),
            algorithm: policy.algorithm,
            job_id: policy.job_id.into_string(),
            job_name: policy.job_name,
            obs_dim: policy.obs_dim,
            action_space: serde_json::to_value(&policy.action_space).unwrap_or_default(),
            final_metrics: serde_json::Value::Object(policy.final_metrics),
            alpha_hat: policy.alpha_hat,
            spec: serde_json::to_value(&policy.spec).unwrap_or_default(),
            created_at: rfc3339(&policy.created_at),
            id: policy.id.into_string(),
        }
    }
}

/// `?job_id=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PolicyFilter {
    /// Only the policy of this job.
    #[param(value_type = Option<String>)]
    pub job_id: Option<JobId>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_policies))
        .routes(routes!(get_policy, delete_policy))
        .routes(routes!(policy_weights))
        .routes(routes!(export_policy))
        .merge(
            OpenApiRouter::new()
                .routes(routes!(act))
                .layer(axum::extract::DefaultBodyLimit::max(ACTION_BODY_LIMIT)),
        )
}

/// List trained policies, newest first.
#[utoipa::path(get, path = "/v1/policies", tag = "policies", params(PolicyFilter, PageParams),
    responses((status = 200, body = Page<PolicyResource>), (status = 400, body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody),))]
async fn list_policies(
    State(state): State<AppState>,
    Query(filter): Query<PolicyFilter>,
    Query(page): Query<PageParams>,
) -> Result<Json<Page<PolicyResource>>, ApiError> {
    let page = page.resolve(&state.store, Listing::Policies).await?;
    let (records, total) = state.store.list_policies(filter.job_id.as_ref(), &page).await?;
    let items = records.into_iter().map(PolicyResource::from).collect();
    Ok(Json(Page::new(items, total, page, |p: &PolicyResource| &p.id)))
}

/// Delete a policy and its finished evaluations (download it first to keep it); its job stays,
/// without a policy. Refused while a model version points at it or an evaluation of it is
/// queued or running.
#[utoipa::path(delete, path = "/v1/policies/{id}", tag = "policies", params(("id" = String, Path)),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, body = ErrorBody),
        (status = 409, description = "A model version points at it, or an evaluation of it \
            is queued or running (`policy_in_use`)", body = ErrorBody),
    ))]
async fn delete_policy(
    State(state): State<AppState>,
    Path(id): Path<PolicyId>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_policy(&id).await? {
        DeleteOutcome::Deleted => {
            state.serving.policies.forget(&id);
            Ok(StatusCode::NO_CONTENT)
        }
        DeleteOutcome::NotFound => Err(ApiError::not_found("policy", &id)),
        DeleteOutcome::Registered(versions) => Err(ApiError::conflict(
            "policy_in_use",
            format!(
                "policy {id} is registered as {}; delete those versions first (DELETE \
                 /v1/models/{{name}}/versions/{{n}}), after pointing their aliases elsewhere",
                versions.join(", ")
            ),
        )),
        DeleteOutcome::InUse(evaluations) => Err(ApiError::conflict(
            "policy_in_use",
            format!(
                "policy {id} has queued or running evaluation(s) {}; wait for them, then \
                 delete it",
                evaluations.join(", ")
            ),
        )),
    }
}

/// A trained policy.
#[utoipa::path(get, path = "/v1/policies/{id}", tag = "policies", params(("id" = String, Path)),
    responses((status = 200, body = PolicyResource), (status = 404, body = ErrorBody)))]
async fn get_policy(
    State(state): State<AppState>,
    Path(id): Path<PolicyId>,
) -> Result<Json<PolicyResource>, ApiError> {
    Ok(Json(state.store.policy(&id).await?.into()))
}

/// Download the policy as one safetensors file that rebuilds it alone: the weights, and under the
/// metadata key `safedice.policy` the spec (architecture, spaces, action scaling, observation
/// normalisation, algorithm) and the training run (resolved configuration, dataset ids). The
/// `x-safedice-policy-spec` header (and the policy resource's `spec`) repeat the spec.
#[utoipa::path(get, path = "/v1/policies/{id}/weights", tag = "policies",
    params(("id" = String, Path)),
    responses(
        (status = 200, description = "safetensors file", content_type = "application/octet-stream",
         body = Vec<u8>,
         headers(("x-safedice-policy-spec" = String, description = "The policy spec (JSON)"))),
        (status = 404, body = ErrorBody),
        (status = 503, description = "--max-heavy-reads dataset or policy files are being \
            built or sent (`too_many_heavy_reads`), or half of them to this client \
            (`too_many_heavy_reads_from_address`); retry after `Retry-After` seconds", body = ErrorBody),
    ))]
async fn policy_weights(
    State(state): State<AppState>,
    RequestClient(client): RequestClient,
    Path(id): Path<PolicyId>,
) -> Result<Response, ApiError> {
    let permit = super::heavy_read_permit(&state, client)?;
    // The spec from the policy's row; the weights (the large part) are read once, by the file.
    let spec = serde_json::to_string(&state.store.policy(&id).await?.spec)
        .map_err(|e| ApiError::Internal(anyhow::anyhow!("policy {id}: spec: {e}")))?;
    let weights = crate::serving::portable_weights(&state.store, &id).await?;
    let spec = HeaderValue::from_str(&spec)
        .map_err(|e| ApiError::Internal(anyhow::anyhow!("policy {id}: spec header: {e}")))?;
    let name = format!("policy-{id}.safetensors");
    let mut response = super::attachment_holding(&name, OCTET_STREAM, weights, permit)?;
    response.headers_mut().insert(SPEC_HEADER, spec);
    Ok(response)
}

/// `?format=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ExportQuery {
    /// The model format (default `onnx`, for now the only one).
    pub format: Option<ExportFormat>,
}

/// The formats a policy exports to.
#[derive(Debug, Clone, Copy, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ExportFormat {
    Onnx,
}

/// Export the policy for another runtime. `format=onnx`: an ONNX model (opset 13) from
/// observations `[B, obs_dim]` (FP32, the dataset's units) to the deterministic action in the
/// dataset's units: output `actions`, FP32 `[B, dim]` (continuous) or INT64 `[B]` (discrete,
/// with `probabilities` FP32 `[B, n]` as a second output). Same actions as `/act` with
/// `deterministic: true`.
#[utoipa::path(get, path = "/v1/policies/{id}/export", tag = "policies",
    params(("id" = String, Path), ExportQuery),
    responses(
        (status = 200, description = "ONNX model", content_type = "application/octet-stream",
         body = Vec<u8>),
        (status = 400, description = "Unknown format", body = ErrorBody),
        (status = 404, body = ErrorBody),
        (status = 503, description = "--max-heavy-reads dataset or policy files are being \
            built or sent (`too_many_heavy_reads`), or half of them to this client \
            (`too_many_heavy_reads_from_address`); retry after `Retry-After` seconds", body = ErrorBody),
    ))]
async fn export_policy(
    State(state): State<AppState>,
    RequestClient(client): RequestClient,
    Path(id): Path<PolicyId>,
    Query(query): Query<ExportQuery>,
) -> Result<Response, ApiError> {
    let ExportFormat::Onnx = query.format.unwrap_or(ExportFormat::Onnx);
    let permit = super::heavy_read_permit(&state, client)?;
    let model = crate::serving::onnx_model(&state.store, &id).await?;
    let len = model.len();
    let body = super::body_written_by(move |out| model.write_to(out).map_err(|e| e.to_string()));
    let mut response =
        super::attachment_holding(&format!("policy-{id}.onnx"), OCTET_STREAM, body, permit)?;
    response.headers_mut().insert(axum::http::header::CONTENT_LENGTH, len.into());
    Ok(response)
}

/// Actions for a batch of observations. Callable with the inference token.
#[utoipa::path(post, path = "/v1/policies/{id}/act", tag = "policies",
    params(("id" = String, Path)), request_body = ActRequest,
    responses(
        (status = 200, body = ActResponse),
        (status = 404, body = ErrorBody),
        (status = 422, description = "Empty batch, wrong observation width or a non-finite \
            value (`invalid_observations`), too many rows (`batch_too_large`), malformed body \
            (`invalid_body`)", body = ErrorBody),
    ))]
async fn act(
    State(state): State<AppState>,
    Path(id): Path<PolicyId>,
    StraightJson(request): StraightJson<ActRequest>,
) -> Result<Json<ActResponse>, ApiError> {
    let served = resolve(&state.serving, &ActTarget::Policy(id), None).await?;
    Ok(Json(act_on(&served, request).await?))
}
