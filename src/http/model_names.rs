//! How a request names a model and learns which version answered: the path's model reference,
//! the client's request key, the version headers. Shared by `/v1/models/…/act`
//! ([`super::model_serving`]) and the Open Inference Protocol routes ([`super::inference`]).

use axum::http::{HeaderMap, HeaderName, HeaderValue};
use axum::response::Response;

use super::ApiError;
use crate::domain::model::ModelRef;
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
