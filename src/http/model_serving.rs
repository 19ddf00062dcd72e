//! Actions from a named model: `POST /v1/models/{name}/act` (the latest version),
//! `POST /v1/models/{name}@{alias}/act` (the alias's version, or its canary's for its share),
//! `POST /v1/models/{name}/versions/{version}/act`. The answer names the version that gave it
//! (`x-safedice-model-version`); a client's `x-safedice-request-key` sends the same key to the
//! same side of a canary every time, on every node.

use std::time::Instant;

use axum::extract::State;
use axum::http::{HeaderMap, HeaderName, HeaderValue};
use axum::response::{IntoResponse, Response};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path};
use super::policies::{act_on, ActRequest, ActResponse};
use super::{ApiError, AppState};
use crate::domain::model::ModelRef;
use crate::serving::registry::Answer;

/// The version that answered a request by model name.
pub const MODEL_VERSION_HEADER: HeaderName = HeaderName::from_static("x-safedice-model-version");
/// The policy behind that version.
pub const POLICY_ID_HEADER: HeaderName = HeaderName::from_static("x-safedice-policy-id");
/// A client's key for a request: the same key always gets the same side of a canary.
pub const REQUEST_KEY_HEADER: HeaderName = HeaderName::from_static("x-safedice-request-key");

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(act_by_name)).routes(routes!(act_by_version))
}

/// A model reference from a path: a name that breaks the rules names no model (404).
pub(crate) fn reference(name: &str, version: Option<&str>) -> Result<ModelRef, ApiError> {
    match version {
        None => ModelRef::parse(name),
        Some(version) => ModelRef::with_version(name, version),
    }
    .map_err(|rule| ApiError::NotFound(format!("model {name:?} does not exist ({rule})")))
}

/// The request key header, if the client sent one.
pub(crate) fn request_key(headers: &HeaderMap) -> Option<&str> {
    headers.get(REQUEST_KEY_HEADER).and_then(|v| v.to_str().ok())
}

/// Adds which version answered (and its policy) to a response.
pub(crate) fn tag_version(response: &mut Response, answer: &Answer) {
    let headers = response.headers_mut();
    headers.insert(MODEL_VERSION_HEADER, HeaderValue::from(answer.target.version));
    if let Ok(policy) = HeaderValue::from_str(answer.target.policy_id.as_str()) {
        headers.insert(POLICY_ID_HEADER, policy);
    }
}

/// Actions from a named model: `name` serves its latest version, `name@alias` the alias's
/// version (or its canary's, for the canary's share of requests). Callable with the inference
/// token.
#[utoipa::path(post, path = "/v1/models/{name}/act", tag = "models",
    params(("name" = String, Path, description = "`name` or `name@alias`"),
        ("x-safedice-request-key" = Option<String>, Header,
         description = "Requests with the same key get the same side of a canary")),
    request_body = ActRequest,
    responses(
        (status = 200, body = ActResponse, headers(
            ("x-safedice-model-version" = u32, description = "The version that answered"),
            ("x-safedice-policy-id" = String, description = "Its policy"))),
        (status = 404, description = "No such model or alias, or no version yet", body = ErrorBody),
        (status = 422, description = "As `POST /v1/policies/{id}/act`", body = ErrorBody),
    ))]
async fn act_by_name(
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    Json(request): Json<ActRequest>,
) -> Result<Response, ApiError> {
    let reference = reference(&name, None)?;
    act(&state, &reference, request_key(&headers), request).await
}

/// `{name, version}` of the versioned route.
#[derive(Debug, serde::Deserialize)]
struct VersionPath {
    name: String,
    version: String,
}

/// Actions from one version of a named model. Callable with the inference token.
#[utoipa::path(post, path = "/v1/models/{name}/versions/{version}/act", tag = "models",
    params(("name" = String, Path), ("version" = u32, Path)), request_body = ActRequest,
    responses(
        (status = 200, body = ActResponse, headers(
            ("x-safedice-model-version" = u32, description = "The version that answered"))),
        (status = 404, body = ErrorBody),
        (status = 422, body = ErrorBody),
    ))]
async fn act_by_version(
    State(state): State<AppState>,
    Path(path): Path<VersionPath>,
    Json(request): Json<ActRequest>,
) -> Result<Response, ApiError> {
    let reference = reference(&path.name, Some(&path.version))?;
    act(&state, &reference, None, request).await
}

async fn act(
    state: &AppState,
    reference: &ModelRef,
    key: Option<&str>,
    request: ActRequest,
) -> Result<Response, ApiError> {
    let answer = state.models.resolve(reference, key).await?;
    let started = Instant::now();
    let result = act_on(answer.target.policy.clone(), request).await;
    answer.target.stats.record(result.is_ok(), started.elapsed());
    let mut response = Json(result?).into_response();
    tag_version(&mut response, &answer);
    Ok(response)
}
