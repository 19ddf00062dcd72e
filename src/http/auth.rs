//! Bearer-token access control for `/v1` and `/v2`. The API token may call everything; the
//! optional inference token only the action endpoints (`POST /v1/policies/{id}/act` and the
//! `/v2` Open Inference Protocol routes), so a deployed agent's credential cannot read or delete
//! data. `/`, `/healthz`, `/readyz` and `/metrics` stay open. Without an API token nothing is
//! checked (the server then only listens on loopback, see [`crate::config`]). The gRPC service
//! (`crate::grpc`) checks its `authorization` metadata with the same [`Tokens::authorize`].

use axum::extract::{Request, State};
use axum::http::{header, Method};
use axum::middleware::Next;
use axum::response::Response;
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use super::{ApiError, AppState};

/// SHA-256 digests of the configured tokens: comparing fixed-size digests in constant time
/// leaks neither the tokens' contents nor their lengths.
#[derive(Debug)]
pub struct Tokens {
    api: Option<[u8; 32]>,
    inference: Option<[u8; 32]>,
}

/// What a route requires.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Requirement {
    Open,
    /// The API token.
    Api,
    /// The API token or the inference token.
    Action,
}

/// Whom a presented token identifies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Caller {
    Api,
    Inference,
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Tokens {
    pub fn new(api: Option<&str>, inference: Option<&str>) -> Self {
        Tokens { api: api.map(digest), inference: inference.map(digest) }
    }

    fn identify(&self, presented: &str) -> Option<Caller> {
        let presented = digest(presented);
        let matches = |expected: &Option<[u8; 32]>| {
            expected.map_or(subtle::Choice::from(0), |e| e.ct_eq(&presented))
        };
        // Both comparisons always run, whatever the outcome of the first.
        let (is_api, is_inference) = (matches(&self.api), matches(&self.inference));
        if bool::from(is_api) {
            Some(Caller::Api)
        } else if bool::from(is_inference) {
            Some(Caller::Inference)
        } else {
            None
        }
    }
}

/// Why a token does not let a request through; each transport words it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// No bearer token came.
    Missing,
    /// The token is neither the API token nor the inference token.
    Invalid,
    /// The inference token, on what needs the API token.
    InferenceOnly,
}

impl Tokens {
    /// Whether a request bearing `presented` may call what needs `required`. Without an API
    /// token every request may.
    pub fn authorize(&self, presented: Option<&str>, required: Requirement) -> Result<(), Refusal> {
        if self.api.is_none() || required == Requirement::Open {
            return Ok(());
        }
        let presented = presented.ok_or(Refusal::Missing)?;
        match (self.identify(presented), required) {
            (None, _) => Err(Refusal::Invalid),
            (Some(Caller::Inference), Requirement::Api) => Err(Refusal::InferenceOnly),
            (Some(_), _) => Ok(()),
        }
    }
}

/// The token of an `Authorization` value `Bearer <token>` (the scheme in any case).
pub fn bearer(value: &str) -> Option<&str> {
    let (scheme, token) = value.split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then(|| token.trim())
}

/// The requirement of a route, from its method and path.
pub fn requirement(method: &Method, path: &str) -> Requirement {
    let segments: Vec<&str> = path.trim_start_matches('/').split('/').collect();
    match segments.as_slice() {
        // Loading and unloading models changes what this server serves: not an agent's call.
        ["v2", "repository", ..] => Requirement::Api,
        ["v2", ..] => Requirement::Action,
        ["v1", "policies" | "models", _, "act"] if method == Method::POST => Requirement::Action,
        ["v1", "models", _, "versions", _, "act"] if method == Method::POST => Requirement::Action,
        ["v1", ..] => Requirement::Api,
        _ => Requirement::Open,
    }
}

fn bearer_token(request: &Request) -> Option<&str> {
    bearer(request.headers().get(header::AUTHORIZATION)?.to_str().ok()?)
}

/// Middleware: lets the request through when its token allows the route.
pub async fn require_token(
    State(state): State<AppState>,
    request: Request,
    next: Next,
) -> Result<Response, ApiError> {
    if state.tokens.api.is_none() {
        return Ok(next.run(request).await);
    }
    let required = requirement(request.method(), request.uri().path());
    match state.tokens.authorize(bearer_token(&request), required) {
        Ok(()) => Ok(next.run(request).await),
        Err(Refusal::Missing) => Err(ApiError::Unauthorized(
            "this route needs a bearer token: send `Authorization: Bearer <token>`",
        )),
        Err(Refusal::Invalid) => {
            Err(ApiError::Unauthorized("the bearer token is not valid for this server"))
        }
        Err(Refusal::InferenceOnly) => Err(ApiError::Forbidden(
            "the inference token may only call the action endpoints \
             (POST /v1/policies/{id}/act, POST /v1/models/{name}/act, /v2/... but \
             /v2/repository); use the API token",
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_are_classified_by_prefix_and_action() {
        assert_eq!(requirement(&Method::GET, "/healthz"), Requirement::Open);
        assert_eq!(requirement(&Method::GET, "/metrics"), Requirement::Open);
        assert_eq!(requirement(&Method::GET, "/"), Requirement::Open);
        assert_eq!(requirement(&Method::GET, "/v1"), Requirement::Api);
        assert_eq!(requirement(&Method::GET, "/v1/datasets"), Requirement::Api);
        assert_eq!(requirement(&Method::POST, "/v1/policies/p1/act"), Requirement::Action);
        assert_eq!(requirement(&Method::GET, "/v1/policies/p1/act"), Requirement::Api);
        assert_eq!(requirement(&Method::GET, "/v1/policies/p1/weights"), Requirement::Api);
        assert_eq!(requirement(&Method::POST, "/v2/models/p1/infer"), Requirement::Action);
        assert_eq!(requirement(&Method::GET, "/v1x/datasets"), Requirement::Open);
        assert_eq!(requirement(&Method::POST, "/v1/models/m@prod/act"), Requirement::Action);
        assert_eq!(requirement(&Method::POST, "/v1/models/m/versions/2/act"), Requirement::Action);
        assert_eq!(requirement(&Method::PUT, "/v1/models/m/aliases/prod"), Requirement::Api);
        assert_eq!(requirement(&Method::POST, "/v2/repository/index"), Requirement::Api);
    }

    #[test]
    fn tokens_identify_their_caller() {
        let tokens = Tokens::new(Some("api-secret"), Some("agent-secret"));
        assert_eq!(tokens.identify("api-secret"), Some(Caller::Api));
        assert_eq!(tokens.identify("agent-secret"), Some(Caller::Inference));
        assert_eq!(tokens.identify("api-secre"), None);
        assert_eq!(tokens.identify(""), None);
        let api_only = Tokens::new(Some("api-secret"), None);
        assert_eq!(api_only.identify("agent-secret"), None);
    }
}
