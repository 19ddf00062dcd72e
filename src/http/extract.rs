//! axum's extractors with their rejections turned into [`ApiError`], so malformed JSON, query
//! strings and path parameters get the same `{"error": {...}}` body as every other error.
//! Handlers use these instead of `axum::Json` / `Query` / `Path`.

use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;

use super::error::ApiError;

/// JSON request and response body.
///
/// As a request body it is read like `axum::Json` (content type, body limit, 400 for a syntax
/// error, 422 naming the path of a value that does not fit), with one difference: a number
/// written with a fraction of zero (`12.0`) counts as the integer it equals, as JSON Schema
/// says (`type: integer` accepts `12.0`), so integer fields take it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Json<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for Json<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, state: &S) -> Result<Self, ApiError> {
        let axum::Json(value) =
            axum::Json::<serde_json::Value>::from_request(request, state).await?;
        deserialize_body(value).map(Json)
    }
}

/// A JSON request body whatever content type the client declares, or none: the Open Inference
/// Protocol's HTTP binding does not require `application/json`, and stock clients leave it out.
/// Otherwise read exactly like [`Json`] (body limit, 400 for a syntax error, 422 naming the path
/// of a value that does not fit).
#[derive(Debug, Clone, Copy, Default)]
pub struct AnyContentTypeJson<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for AnyContentTypeJson<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, state: &S) -> Result<Self, ApiError> {
        let bytes = axum::body::Bytes::from_request(request, state).await?;
        let value = serde_json::from_slice(&bytes).map_err(|e| {
            let message = format!("Failed to parse the request body as JSON: {e}");
            ApiError::rejected(StatusCode::BAD_REQUEST, message)
        })?;
        deserialize_body(value).map(AnyContentTypeJson)
    }
}

/// A parsed JSON body as `T`, integral floats taken as integers.
pub(super) fn deserialize_body<T: DeserializeOwned>(
    mut value: serde_json::Value,
) -> Result<T, ApiError> {
    integral_floats_to_integers(&mut value);
    serde_path_to_error::deserialize(value).map_err(|e| ApiError::Rejected {
        status: StatusCode::UNPROCESSABLE_ENTITY,
        code: "invalid_body",
        message: format!(
            "Failed to deserialize the JSON body into the target type: {}: {}",
            e.path(),
            e.inner()
        ),
    })
}

/// Rewrites every float with no fractional part that fits an i64 or u64 as that integer.
fn integral_floats_to_integers(value: &mut serde_json::Value) {
    use serde_json::Value;
    match value {
        Value::Number(n) if n.is_f64() => {
            let f = n.as_f64().unwrap_or(f64::NAN);
            // 2^63 and 2^64 are exact in f64; the ranges below convert without rounding.
            if f.fract() == 0.0 && f >= -(2f64.powi(63)) && f < 2f64.powi(63) {
                *value = Value::from(f as i64);
            } else if f.fract() == 0.0 && f >= 0.0 && f < 2f64.powi(64) {
                *value = Value::from(f as u64);
            }
        }
        Value::Array(items) => items.iter_mut().for_each(integral_floats_to_integers),
        Value::Object(fields) => fields.values_mut().for_each(integral_floats_to_integers),
        _ => {}
    }
}

impl<T: serde::Serialize> IntoResponse for Json<T> {
    fn into_response(self) -> Response {
        axum::Json(self.0).into_response()
    }
}

/// Query string parameters.
#[derive(Debug, Clone, Copy, Default, FromRequestParts)]
#[from_request(via(axum::extract::Query), rejection(ApiError))]
pub struct Query<T>(pub T);

/// Path parameters.
#[derive(Debug, Clone, Copy, FromRequestParts)]
#[from_request(via(axum::extract::Path), rejection(ApiError))]
pub struct Path<T>(pub T);

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn integral_floats_become_integers_and_others_stay() {
        let mut value = json!({"episodes": 12.0, "seed": -3.0, "lr": 0.5, "big": 1e300,
            "nested": [[1.0, 2.5]], "top": 1.8446744073709552e19, "exact": 9.2e18});
        integral_floats_to_integers(&mut value);
        assert_eq!(
            value,
            json!({"episodes": 12, "seed": -3, "lr": 0.5, "big": 1e300, "nested": [[1, 2.5]],
                "top": 1.8446744073709552e19, "exact": 9_200_000_000_000_000_000_u64})
        );
    }
}
