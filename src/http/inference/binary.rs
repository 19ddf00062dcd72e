//! The Open Inference Protocol's binary tensor data extension (what NVIDIA's `tritonclient` sends
//! by default) and the protocol's error shape.
//!
//! A request with binary inputs carries the header `Inference-Header-Content-Length: N`: the
//! first N bytes of the body are the JSON inference request, and the rest is the raw data of the
//! inputs whose `parameters.binary_data_size` says how many bytes they take, in input order
//! (little-endian, row-major). A response with binary outputs is laid out the same way: the JSON
//! header, then the outputs' bytes, each output saying its `binary_data_size`.

use axum::body::{Body, Bytes};
use axum::extract::{FromRequest, Request};
use axum::http::{header, HeaderName, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::Response;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::super::error::ErrorMessage;
use super::super::extract::deserialize_straight;
use super::super::ApiError;

/// Says how long the JSON header at the start of a body is.
pub const HEADER_LENGTH: HeaderName = HeaderName::from_static("inference-header-content-length");

/// An inference request body: the JSON request and the binary data after it (empty without the
/// binary extension).
pub struct InferBody<T> {
    pub request: T,
    pub binary: Bytes,
}

impl<T: serde::de::DeserializeOwned, S: Send + Sync> FromRequest<S> for InferBody<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, state: &S) -> Result<Self, ApiError> {
        let header_length = match request.headers().get(&HEADER_LENGTH) {
            None => None,
            Some(value) => {
                Some(value.to_str().ok().and_then(|v| v.trim().parse::<usize>().ok()).ok_or_else(
                    || bad_request(format!("{HEADER_LENGTH} must be a byte count, got {value:?}")),
                )?)
            }
        };
        let mut body = Bytes::from_request(request, state).await?;
        let json = match header_length {
            None => std::mem::take(&mut body),
            Some(length) if length <= body.len() => body.split_to(length),
            Some(length) => {
                return Err(bad_request(format!(
                    "{HEADER_LENGTH} is {length} but the body has only {} bytes",
                    body.len()
                )))
            }
        };
        Ok(InferBody { request: deserialize_straight(&json)?, binary: body })
    }
}

fn bad_request(message: String) -> ApiError {
    ApiError::rejected(StatusCode::BAD_REQUEST, message)
}

/// Takes the next `size` bytes of the binary data (the inputs' data, in order).
pub fn take(binary: &mut Bytes, size: u64, input: &str) -> Result<Bytes, ApiError> {
    match usize::try_from(size) {
        Ok(size) if size <= binary.len() => Ok(binary.split_to(size)),
        _ => Err(ApiError::unprocessable(
            "invalid_input",
            format!(
                "input `{input}` declares {size} bytes of binary data, but only {} are left",
                binary.len()
            ),
        )),
    }
}

/// A response of a JSON header followed by the outputs' bytes.
pub fn response(header_json: Vec<u8>, data: &[u8]) -> Response {
    let length = header_json.len();
    let mut body = header_json;
    body.extend_from_slice(data);
    let mut response = Response::new(Body::from(body));
    let headers = response.headers_mut();
    headers.insert(HEADER_LENGTH, HeaderValue::from(length));
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream"));
    response
}

/// An Open Inference Protocol error: `{"error": "message"}`.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct V2Error {
    pub error: String,
}

/// Middleware: every error answered under `/v2` (by its handlers, the token check, an unknown
/// route, a timeout) in the protocol's shape `{"error": "message"}` that KServe clients parse,
/// instead of the `/v1` shape `{"error": {"code", "message"}}`.
pub async fn v2_error_shape(request: Request, next: Next) -> Response {
    let is_v2 = request.uri().path() == "/v2" || request.uri().path().starts_with("/v2/");
    let response = next.run(request).await;
    if !is_v2 || !(response.status().is_client_error() || response.status().is_server_error()) {
        return response;
    }
    let (mut parts, _) = response.into_parts();
    // Every error of ours is an ApiError, which leaves its message on the response; anything
    // else (none is known) answers its status line.
    let message = match parts.extensions.get::<ErrorMessage>() {
        Some(ErrorMessage(message)) => message.clone(),
        None => parts.status.to_string(),
    };
    parts.headers.remove(header::CONTENT_LENGTH);
    let body = serde_json::to_vec(&V2Error { error: message }).expect("a string serialises");
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    Response::from_parts(parts, Body::from(body))
}
