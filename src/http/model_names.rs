//! How a request names a model and learns which version answered: the path's model reference,
//! the client's request key, the version headers. Shared by `/v1/models/…/act`
//! ([`super::model_serving`]) and the Open Inference Protocol routes ([`super::inference`]); and
//! what the model routes ([`super::models`], [`super::model_aliases`]) share: the checks of a
//! name and of a move's note, and this server's refresh after a change.

use axum::http::{HeaderMap, HeaderName, HeaderValue};
use axum::response::Response;

use super::{ApiError, AppState};
use crate::domain::model::{self as model, MoveNote, MAX_ACTOR_CHARS};
use crate::domain::model::{ModelName, ModelRef};
use crate::serving::registry::Answer;

/// The version that answered a request by model name.
pub const MODEL_VERSION_HEADER: HeaderName = HeaderName::from_static("x-safedice-model-version");
/// The policy behind that version.
pub const POLICY_ID_HEADER: HeaderName = HeaderName::from_static("x-safedice-policy-id");
/// A client's key for a request: the same key always gets the same side of a canary.
pub const REQUEST_KEY_HEADER: HeaderName = HeaderName::from_static("x-safedice-request-key");

/// A model reference from a path: a name that breaks the rules names no model (404).
pub(crate) fn reference(name: &str, version: Option<&str>) -> Result<ModelRef, ApiError> {
    Ok(crate::serving::inference::reference(name, version)?)
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

pub(crate) fn invalid_name(message: String) -> ApiError {
    ApiError::unprocessable("invalid_name", message)
}

pub(crate) fn check_text(field: &str, text: &str, max: usize) -> Result<(), ApiError> {
    model::check_text(field, text, max).map_err(|e| ApiError::unprocessable("invalid_model", e))
}

/// A model name from the path: anything else than a model's name is 404 (a name that breaks
/// the rules cannot exist), except that `name@alias` says where to use it.
pub(crate) fn model_name(name: &str) -> Result<ModelName, ApiError> {
    ModelName::parse(name)
        .map_err(|rule| ApiError::NotFound(format!("model {name:?} does not exist ({rule})")))
}

pub(crate) fn note(
    actor: Option<String>,
    reason: Option<String>,
    expected_version: Option<u32>,
) -> Result<MoveNote, ApiError> {
    let actor = actor.unwrap_or_else(|| "api".into());
    check_text("actor", &actor, MAX_ACTOR_CHARS)?;
    if actor.trim().is_empty() {
        return Err(ApiError::unprocessable("invalid_model", "actor: must not be empty"));
    }
    if let Some(reason) = &reason {
        check_text("reason", reason, MAX_ACTOR_CHARS)?;
    }
    Ok(MoveNote { actor, reason, expected_version })
}

/// This server serves the change at once (the others of a fleet follow by notification or
/// poll). A failure to load leaves the previous table serving and is retried by the poll.
pub(crate) async fn refresh(state: &AppState, model: &crate::domain::model::ModelName) {
    if let Err(e) = state.serving.models.refresh_model(model.as_str()).await {
        tracing::error!(%model, error = %e, "cannot load the model's new versions yet; the previous ones keep serving");
    }
}
