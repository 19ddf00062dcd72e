//! Actions from a named model: `POST /v1/models/{name}/act` (the latest version),
//! `POST /v1/models/{name}@{alias}/act` (the alias's version, or its canary's for its share),
//! `POST /v1/models/{name}/versions/{version}/act`. The answer names the version that gave it
//! (`x-safedice-model-version`); a client's `x-safedice-request-key` sends the same key to the
//! same side of a canary every time, on every node.

use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::{IntoResponse, Response};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::act::{act_on, ActRequest, ActResponse, ACTION_BODY_LIMIT};
use super::error::ErrorBody;
use super::extract::{Json, Path, StraightJson};
use super::model_names::{reference, request_key, tag_version};
use super::{ApiError, AppState};
use crate::domain::model::ModelRef;
use crate::serving::act::{resolve, ActTarget};

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(act_by_name))
        .routes(routes!(act_by_version))
        .layer(axum::extract::DefaultBodyLimit::max(ACTION_BODY_LIMIT))
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
    StraightJson(request): StraightJson<ActRequest>,
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
    StraightJson(request): StraightJson<ActRequest>,
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
    let served = resolve(&state.serving, &ActTarget::Model(reference.clone()), key).await?;
    let actions = served.timed(act_on(&served, request)).await?;
    let mut response = Json(actions).into_response();
    if let Some((answer, _)) = &served.answer {
        tag_version(&mut response, answer);
    }
    Ok(response)
}
