//! The one error type of the HTTP API. Every 4xx/5xx body has the shape
//! `{"error": {"code": "snake_case_code", "message": "what is wrong and how to fix it"}}`;
//! 500s are logged with their cause and answered with a generic message.

use axum::extract::multipart::{MultipartError, MultipartRejection};
use axum::extract::rejection::{BytesRejection, JsonRejection, PathRejection, QueryRejection};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

/// nginx's status for a request the client abandoned.
const CLIENT_CLOSED_REQUEST: StatusCode = match StatusCode::from_u16(499) {
    Ok(status) => status,
    Err(_) => panic!("499 is a valid status code"),
};

/// Every error the API answers with.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// 400: the request itself is malformed (not the data it carries).
    #[error("{message}")]
    BadRequest { code: &'static str, message: String },
    /// 401: missing or wrong bearer token.
    #[error("{0}")]
    Unauthorized(&'static str),
    /// 403: a valid token that may not call this endpoint.
    #[error("{0}")]
    Forbidden(&'static str),
    /// 404: no such resource or route.
    #[error("{0}")]
    NotFound(String),
    /// 405: the route exists, the method does not.
    #[error("this route does not accept the request's method; see /v1/openapi.json")]
    MethodNotAllowed,
    /// 409: the request conflicts with the current state (e.g. a dataset in use by a job).
    #[error("{message}")]
    Conflict { code: &'static str, message: String },
    /// 413: an upload larger than `--max-upload-bytes`.
    #[error("the upload exceeds the server's limit of {limit} bytes (--max-upload-bytes)")]
    PayloadTooLarge { limit: u64 },
    /// 422: well-formed request, invalid content (a dataset that does not parse, a bad value).
    #[error("{message}")]
    Unprocessable { code: &'static str, message: String },
    /// A rejection from one of axum's extractors, with the status axum chose.
    #[error("{message}")]
    Rejected { status: StatusCode, code: &'static str, message: String },
    /// 408: the client paused its request body longer than `--body-idle-timeout-secs`.
    #[error(
        "the request body paused for longer than the server waits (--body-idle-timeout-secs); \
         the request was abandoned and nothing was stored, send it again"
    )]
    RequestTimeout,
    /// 408: the request body came slower than `--min-body-rate` on average.
    #[error(
        "the request body arrived slower than {0} bytes/s on average (--min-body-rate); the \
         request was abandoned and nothing was stored, send it again over a faster link"
    )]
    BodyTooSlow(u64),
    /// 499 (as nginx logs it): the client closed the connection before its request was read.
    /// Nobody reads the answer; the status keeps such requests apart from server errors in
    /// the log and the metrics.
    #[error("the client closed the connection before the request was complete")]
    ClientClosed,
    /// 507: the data directory's disk is full.
    #[error(
        "the server's disk is full; nothing was stored. Retry once an operator has freed space \
         (GET /readyz answers 200 again then)"
    )]
    InsufficientStorage,
    /// 503: the service cannot answer now (database unreachable or busy, request timed out).
    #[error("{message}")]
    Unavailable { code: &'static str, message: String },
    /// 500: anything unexpected. Logged, never shown to the client.
    #[error("internal error")]
    Internal(#[from] anyhow::Error),
}

/// The JSON body of every error response.
#[derive(Debug, Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// What went wrong: a stable machine-readable `code` and a human-readable `message`.
#[derive(Debug, Serialize, ToSchema)]
pub struct ErrorDetail {
    /// Stable snake_case code, e.g. `not_found`, `unauthorized`, `invalid_dataset`.
    #[schema(example = "not_found")]
    pub code: String,
    /// What is wrong and how to fix it.
    #[schema(example = "dataset 6f1c… does not exist")]
    pub message: String,
}

impl ApiError {
    pub fn not_found(kind: &str, id: impl std::fmt::Display) -> Self {
        ApiError::NotFound(format!("{kind} {id} does not exist"))
    }

    pub fn bad_request(code: &'static str, message: impl Into<String>) -> Self {
        ApiError::BadRequest { code, message: message.into() }
    }

    pub fn unprocessable(code: &'static str, message: impl Into<String>) -> Self {
        ApiError::Unprocessable { code, message: message.into() }
    }

    pub fn conflict(code: &'static str, message: impl Into<String>) -> Self {
        ApiError::Conflict { code, message: message.into() }
    }

    pub fn unavailable(code: &'static str, message: impl Into<String>) -> Self {
        ApiError::Unavailable { code, message: message.into() }
    }

    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::BadRequest { .. } => StatusCode::BAD_REQUEST,
            ApiError::Unauthorized(_) => StatusCode::UNAUTHORIZED,
            ApiError::Forbidden(_) => StatusCode::FORBIDDEN,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ApiError::Conflict { .. } => StatusCode::CONFLICT,
            ApiError::PayloadTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::Unprocessable { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::Rejected { status, .. } => *status,
            ApiError::RequestTimeout | ApiError::BodyTooSlow(_) => StatusCode::REQUEST_TIMEOUT,
            ApiError::ClientClosed => CLIENT_CLOSED_REQUEST,
            ApiError::InsufficientStorage => StatusCode::INSUFFICIENT_STORAGE,
            ApiError::Unavailable { .. } => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    pub fn code(&self) -> &'static str {
        match self {
            ApiError::BadRequest { code, .. }
            | ApiError::Conflict { code, .. }
            | ApiError::Unprocessable { code, .. }
            | ApiError::Unavailable { code, .. }
            | ApiError::Rejected { code, .. } => code,
            ApiError::Unauthorized(_) => "unauthorized",
            ApiError::Forbidden(_) => "forbidden",
            ApiError::NotFound(_) => "not_found",
            ApiError::MethodNotAllowed => "method_not_allowed",
            ApiError::PayloadTooLarge { .. } => "payload_too_large",
            ApiError::RequestTimeout => "request_timeout",
            ApiError::BodyTooSlow(_) => "request_too_slow",
            ApiError::ClientClosed => "client_closed_request",
            ApiError::InsufficientStorage => "insufficient_storage",
            ApiError::Internal(_) => "internal_error",
        }
    }

    /// The database cannot be reached: the request was fine and is worth repeating.
    pub(super) fn database_unavailable() -> Self {
        ApiError::unavailable(
            "database_unavailable",
            "the database cannot be reached (its connection was lost, or it is restarting); \
             nothing was changed, retry in a few seconds",
        )
    }

    /// A lock another writer held for too long: the request was fine and is worth repeating.
    fn database_busy() -> Self {
        ApiError::unavailable(
            "database_busy",
            "the database is busy with other writes; nothing was changed, retry in a moment",
        )
    }

    /// The disk is full: logged for the operator (it needs one), answered 507.
    fn storage_full(cause: anyhow::Error) -> Self {
        tracing::error!(error = %cause, "storage full: a write was refused");
        ApiError::InsufficientStorage
    }

    /// Maps an extractor rejection, keeping axum's status and its explanation.
    pub(super) fn rejected(status: StatusCode, message: String) -> Self {
        let code = match status {
            StatusCode::PAYLOAD_TOO_LARGE => "payload_too_large",
            StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
            StatusCode::UNPROCESSABLE_ENTITY => "invalid_body",
            StatusCode::BAD_REQUEST => "bad_request",
            s if s.is_server_error() => {
                return ApiError::Internal(anyhow::anyhow!("extractor failed: {message}"))
            }
            _ => "invalid_request",
        };
        ApiError::Rejected { status, code, message }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        let message = match &self {
            ApiError::Internal(cause) => {
                tracing::error!(error = ?cause, "internal error");
                "internal error; the server log has the details".to_owned()
            }
            // Messages may quote what the client sent (a JSON value, a query string): bounded
            // so that an error answer stays small whatever the request held.
            other => crate::text::bounded_message(other.to_string()),
        };
        let body = ErrorBody {
            error: ErrorDetail { code: self.code().to_owned(), message: message.clone() },
        };
        let mut response = (status, axum::Json(body)).into_response();
        response.extensions_mut().insert(ErrorCode(self.code()));
        response.extensions_mut().insert(ErrorMessage(message));
        let headers = response.headers_mut();
        match status {
            // Closed after the answer: a client without a valid token cannot hold a connection
            // slot with one unauthenticated request after another.
            StatusCode::UNAUTHORIZED => {
                headers.insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                headers.insert(header::CONNECTION, HeaderValue::from_static("close"));
            }
            // Busy or not ready (a burst of writes, an upload slot): worth retrying in a second.
            StatusCode::SERVICE_UNAVAILABLE => {
                headers.insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
            }
            _ => {}
        }
        response
    }
}

/// The code of an error answer, kept on the response for the middleware after the handler.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ErrorCode(pub &'static str);

/// The message of an error answer, kept on the response so that `/v2` can answer it in the
/// Open Inference Protocol's shape without reading the `/v1` body back.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ErrorMessage(pub String);

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        match e {
            crate::store::StoreError::NotFound { kind, id } => ApiError::not_found(kind, &id),
            crate::store::StoreError::Conflict { code, message } => {
                ApiError::conflict(code, message)
            }
            e if e.is_unreachable() => {
                tracing::warn!(error = %e, "database unreachable; answering 503");
                ApiError::database_unavailable()
            }
            e if e.is_busy() => {
                tracing::warn!(error = %e, "database busy; answering 503");
                ApiError::database_busy()
            }
            e if e.is_storage_full() => ApiError::storage_full(e.into()),
            other => ApiError::Internal(other.into()),
        }
    }
}

impl From<crate::jobs::SubmitError> for ApiError {
    fn from(e: crate::jobs::SubmitError) -> Self {
        use crate::jobs::SubmitError;
        match e {
            SubmitError::InvalidConfig(message) => {
                ApiError::unprocessable("invalid_config", message)
            }
            SubmitError::TooLarge(message) => ApiError::unprocessable("job_too_large", message),
            SubmitError::InvalidLabels(message) => {
                ApiError::unprocessable("invalid_labels", message)
            }
            SubmitError::Store(e) => e.into(),
        }
    }
}

impl From<crate::serving::registry::ResolveError> for ApiError {
    fn from(e: crate::serving::registry::ResolveError) -> Self {
        use crate::serving::registry::ResolveError;
        match e {
            ResolveError::NotFound(message) => ApiError::NotFound(message),
            unloaded @ ResolveError::Unloaded(_) => ApiError::NotFound(unloaded.to_string()),
            ResolveError::Load(e) => e.into(),
        }
    }
}

impl From<crate::serving::act::ServeError> for ApiError {
    fn from(e: crate::serving::act::ServeError) -> Self {
        use crate::serving::act::ServeError;
        match e {
            ServeError::Invalid { code, message } => ApiError::Unprocessable { code, message },
            ServeError::Resolve(e) => e.into(),
            ServeError::Internal(cause) => ApiError::Internal(cause),
        }
    }
}

impl From<crate::serving::PolicyLoadError> for ApiError {
    fn from(e: crate::serving::PolicyLoadError) -> Self {
        match e {
            crate::serving::PolicyLoadError::Store(e) => e.into(),
            unreadable => ApiError::Internal(unreadable.into()),
        }
    }
}

impl From<crate::data::ParseError> for ApiError {
    /// A rejected upload: 422 with the parser's code and its message naming the line/row/key.
    fn from(e: crate::data::ParseError) -> Self {
        ApiError::Unprocessable { code: e.code, message: e.message }
    }
}

impl From<sqlx::Error> for ApiError {
    fn from(e: sqlx::Error) -> Self {
        crate::store::StoreError::Database(e).into()
    }
}

impl From<std::io::Error> for ApiError {
    fn from(e: std::io::Error) -> Self {
        if crate::store::storage::is_io_storage_full(&e) {
            return ApiError::storage_full(e.into());
        }
        ApiError::Internal(e.into())
    }
}

impl From<tokio::task::JoinError> for ApiError {
    fn from(e: tokio::task::JoinError) -> Self {
        ApiError::Internal(e.into())
    }
}

macro_rules! from_rejection {
    ($($rejection:ty),*) => {$(
        impl From<$rejection> for ApiError {
            fn from(r: $rejection) -> Self {
                ApiError::rejected(r.status(), r.body_text())
            }
        }
    )*};
}

from_rejection!(BytesRejection, JsonRejection, QueryRejection, PathRejection);

impl From<MultipartError> for ApiError {
    /// A multipart body that stopped arriving is the client's doing (it paused past the body
    /// deadline, or went away), not a malformed form.
    fn from(e: MultipartError) -> Self {
        if find_source::<tower_http::timeout::TimeoutError>(&e).is_some() {
            return ApiError::RequestTimeout;
        }
        if let Some(slow) = find_source::<super::connections::BodyTooSlow>(&e) {
            return ApiError::BodyTooSlow(slow.min_rate);
        }
        if find_source::<hyper::Error>(&e).is_some_and(|h| h.is_incomplete_message())
            || find_source::<std::io::Error>(&e).is_some_and(|io| {
                matches!(
                    io.kind(),
                    std::io::ErrorKind::ConnectionReset
                        | std::io::ErrorKind::UnexpectedEof
                        | std::io::ErrorKind::BrokenPipe
                )
            })
        {
            return ApiError::ClientClosed;
        }
        ApiError::rejected(e.status(), e.body_text())
    }
}

/// The first error of type `T` in `error`'s chain of sources.
fn find_source<'a, T: std::error::Error + 'static>(
    error: &'a (dyn std::error::Error + 'static),
) -> Option<&'a T> {
    let mut current = Some(error);
    while let Some(e) = current {
        if let Some(found) = e.downcast_ref::<T>() {
            return Some(found);
        }
        current = e.source();
    }
    None
}

impl From<MultipartRejection> for ApiError {
    fn from(_: MultipartRejection) -> Self {
        ApiError::bad_request(
            "not_multipart",
            "send the upload as multipart/form-data with a `file` field, e.g. \
             `curl -F file=@demos.jsonl -F name=walker-unlabeled .../v1/datasets`",
        )
    }
}

/// Answers requests for routes that do not exist (the router's fallback).
pub async fn route_not_found(uri: axum::http::Uri) -> ApiError {
    ApiError::NotFound(format!("no route for {}; see /v1/openapi.json", uri.path()))
}

/// Answers requests whose route exists but not for this method.
pub async fn method_not_allowed() -> ApiError {
    ApiError::MethodNotAllowed
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::StoreError;

    #[test]
    fn a_busy_database_is_503_with_retry_after_not_500() {
        let response =
            ApiError::from(StoreError::Database(sqlx::Error::PoolTimedOut)).into_response();
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(response.headers()[header::RETRY_AFTER], "1");
        let other = ApiError::from(StoreError::Database(sqlx::Error::RowNotFound)).into_response();
        assert_eq!(other.status(), StatusCode::INTERNAL_SERVER_ERROR);
        assert!(other.headers().get(header::RETRY_AFTER).is_none());
    }

    #[test]
    fn a_full_disk_is_507_storage_full_not_500() {
        let enospc = std::io::Error::from(std::io::ErrorKind::StorageFull);
        let error = ApiError::from(StoreError::Io(enospc));
        assert_eq!(
            (error.status(), error.code()),
            (StatusCode::INSUFFICIENT_STORAGE, "insufficient_storage")
        );
    }

    /// A lost database connection says so (it is not a busy lock), and both are 503s.
    #[test]
    fn an_unreachable_database_is_told_apart_from_a_busy_one() {
        let reset = std::io::Error::from(std::io::ErrorKind::ConnectionReset);
        let lost = ApiError::from(StoreError::Database(sqlx::Error::Io(reset)));
        let waited = ApiError::from(StoreError::Database(sqlx::Error::PoolTimedOut));
        assert_eq!(
            [(lost.status(), lost.code()), (waited.status(), waited.code())],
            [
                (StatusCode::SERVICE_UNAVAILABLE, "database_unavailable"),
                (StatusCode::SERVICE_UNAVAILABLE, "database_busy")
            ]
        );
    }
}
