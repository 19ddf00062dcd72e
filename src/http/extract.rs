//! axum's extractors with their rejections turned into [`ApiError`], so malformed JSON, query
//! strings and path parameters get the same `{"error": {...}}` body as every other error.
//! Handlers use these instead of `axum::Json` / `Query` / `Path`.

use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::de::{DeserializeOwned, Deserializer, Error as _, MapAccess, SeqAccess, Visitor};
use serde::Deserialize;

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
        let axum::Json(StrictValue(value)) =
            axum::Json::<StrictValue>::from_request(request, state).await?;
        deserialize_body(value).map(Json)
    }
}

/// A JSON object body read straight into `T`, with no `serde_json::Value` tree in between: for
/// the action routes (`/act`, `/v2/…/infer`), whose bodies carry up to 16,384 rows of numbers.
/// axum's extractor does the reading (content type, body limit, 400 for a syntax error, 422
/// naming the path of a value that does not fit); [`Object`] refuses any body but an object.
///
/// [`Json`]'s two rules on the tree are the type's to keep here: a derived struct refuses a
/// repeated field itself (keys it ignores cannot change the answer), and integer fields take
/// integral floats through [`crate::domain::integral`].
#[derive(Debug, Clone, Copy, Default)]
pub struct StraightJson<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for StraightJson<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, state: &S) -> Result<Self, ApiError> {
        let axum::Json(Object(value)) =
            axum::Json::<Object<T>>::from_request(request, state).await?;
        Ok(StraightJson(value))
    }
}

/// [`StraightJson`]'s reading of JSON text that came without a content type to check (the
/// binary tensor data extension's JSON header).
pub(super) fn deserialize_straight<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    let axum::Json(Object(value)) = axum::Json::<Object<T>>::from_bytes(bytes)?;
    Ok(value)
}

/// `T` from a JSON object only: serde would otherwise fill a struct from an array by position.
struct Object<T>(T);

impl<'de, T: Deserialize<'de>> Deserialize<'de> for Object<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct ObjectVisitor<T>(std::marker::PhantomData<T>);

        impl<'de, T: Deserialize<'de>> Visitor<'de> for ObjectVisitor<T> {
            type Value = T;

            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object (the request body must be a JSON object)")
            }

            fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<T, A::Error> {
                T::deserialize(serde::de::value::MapAccessDeserializer::new(map))
            }
        }

        deserializer.deserialize_map(ObjectVisitor(std::marker::PhantomData)).map(Object)
    }
}

/// A parsed JSON body as `T`, integral floats taken as integers. Every body is an object: serde
/// would otherwise fill a struct from an array by position (`[null, null]` as a PATCH clearing
/// the first two fields), which no client means.
fn deserialize_body<T: DeserializeOwned>(mut value: serde_json::Value) -> Result<T, ApiError> {
    if !value.is_object() {
        return Err(ApiError::Rejected {
            status: StatusCode::UNPROCESSABLE_ENTITY,
            code: "invalid_body",
            message: "the request body must be a JSON object".to_owned(),
        });
    }
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

/// A JSON value read with every object's keys checked for repeats: serde_json keeps the last of
/// a repeated key silently, so `{"seed": 1, "seed": 2}` would train with seed 2 while the client
/// may have meant either.
struct StrictValue(serde_json::Value);

impl<'de> Deserialize<'de> for StrictValue {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        deserializer.deserialize_any(StrictVisitor).map(StrictValue)
    }
}

struct StrictVisitor;

impl<'de> Visitor<'de> for StrictVisitor {
    type Value = serde_json::Value;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a JSON value")
    }

    fn visit_bool<E>(self, v: bool) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_i64<E>(self, v: i64) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_u64<E>(self, v: u64) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_f64<E>(self, v: f64) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_str<E>(self, v: &str) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_string<E>(self, v: String) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_unit<E>(self) -> Result<Self::Value, E> {
        Ok(serde_json::Value::Null)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut items = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
        while let Some(StrictValue(item)) = seq.next_element()? {
            items.push(item);
        }
        Ok(serde_json::Value::Array(items))
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
        let mut fields = serde_json::Map::new();
        while let Some(key) = map.next_key::<String>()? {
            if fields.contains_key(&key) {
                return Err(A::Error::custom(format!("the key `{key}` appears twice")));
            }
            let StrictValue(value) = map.next_value()?;
            fields.insert(key, value);
        }
        Ok(serde_json::Value::Object(fields))
    }
}

#[cfg(test)]
mod strict_tests {
    use super::*;

    /// JSON text as [`Json`] reads it before the type: a value with no repeated keys.
    fn parse_strict(bytes: &[u8]) -> Result<serde_json::Value, ApiError> {
        axum::Json::<StrictValue>::from_bytes(bytes)
            .map(|axum::Json(StrictValue(value))| value)
            .map_err(ApiError::from)
    }

    #[test]
    fn repeated_keys_are_refused_at_any_depth_and_everything_else_reads_as_serde_json() {
        let text =
            r#"{"a": [1, -2, 3.5, "x", null, true, {"b": {}}], "c": {"d": 18446744073709551615}}"#;
        let strict = parse_strict(text.as_bytes()).unwrap();
        assert_eq!(strict, serde_json::from_str::<serde_json::Value>(text).unwrap());
        for repeated in [r#"{"seed": 1, "seed": 2}"#, r#"{"config": [{"x": 1, "x": 1}]}"#] {
            let error = parse_strict(repeated.as_bytes()).unwrap_err();
            assert_eq!(error.status(), StatusCode::UNPROCESSABLE_ENTITY);
            assert!(error.to_string().contains("appears twice"), "{error}");
        }
        assert_eq!(parse_strict(b"{").unwrap_err().status(), StatusCode::BAD_REQUEST);
    }

    #[test]
    fn a_body_must_be_an_object() {
        #[derive(Deserialize, Debug)]
        #[allow(dead_code)]
        struct Patch {
            name: Option<String>,
            notes: Option<String>,
        }
        let positional = deserialize_body::<Patch>(serde_json::json!([null, null])).unwrap_err();
        assert_eq!(positional.code(), "invalid_body");
        assert!(deserialize_body::<Patch>(serde_json::json!({"name": "x"})).is_ok());
    }
}

#[cfg(test)]
mod straight_tests {
    use super::*;
    use crate::http::act::ActRequest;
    use crate::http::inference::InferRequest;

    fn refusal<T: DeserializeOwned>(text: &str) -> (StatusCode, String) {
        match deserialize_straight::<T>(text.as_bytes()) {
            Ok(_) => panic!("{text} was read"),
            Err(e) => (e.status(), e.to_string()),
        }
    }

    #[test]
    fn action_bodies_read_like_every_other_body() {
        let act: ActRequest = deserialize_straight(
            br#"{"observations": [[1, 2.5], [-3e0, 4]], "deterministic": false, "seed": 7.0}"#,
        )
        .unwrap();
        assert_eq!(act.observations, vec![vec![1.0, 2.5], vec![-3.0, 4.0]]);
        assert_eq!((act.deterministic, act.seed), (false, Some(7)));
        let infer: InferRequest = deserialize_straight(
            br#"{"inputs": [{"name": "observations", "datatype": "FP32", "shape": [2.0, 2],
                 "data": [[1, 2], [3, 4.5]], "parameters": {"binary_data_size": 16.0}}]}"#,
        )
        .unwrap();
        let input = &infer.inputs[0];
        assert_eq!(input.shape, vec![2, 2]);
        assert_eq!(input.data.as_ref().unwrap().0, vec![1.0, 2.0, 3.0, 4.5]);
        assert_eq!(input.parameters.binary_data_size, Some(16));
    }

    #[test]
    fn action_bodies_are_refused_with_the_status_and_path_of_every_other_body() {
        let unprocessable = StatusCode::UNPROCESSABLE_ENTITY;
        for (text, status, says) in [
            ("{", StatusCode::BAD_REQUEST, "parse the request body as JSON"),
            (r#"{"observations": [[1]]} x"#, StatusCode::BAD_REQUEST, "trailing characters"),
            ("[[[1]], false]", unprocessable, "JSON object"),
            (r#"{"observations": [[1, "x"]]}"#, unprocessable, "observations[0][1]"),
            (r#"{"observations": [[1]], "observations": [[2]]}"#, unprocessable, "duplicate"),
            (r#"{"observations": [[1]], "seed": 0.5}"#, unprocessable, "seed"),
        ] {
            assert_eq!(refusal::<ActRequest>(text).0, status, "{text}");
            assert!(
                refusal::<ActRequest>(text).1.contains(says),
                "{text}: {:?}",
                refusal::<ActRequest>(text)
            );
        }
        let (status, message) = refusal::<InferRequest>(
            r#"{"inputs": [{"name": "o", "datatype": "FP32", "shape": [1, 1], "data": [["x"]]}]}"#,
        );
        assert_eq!(status, unprocessable);
        assert!(
            message.contains("inputs[0].data") && message.contains("numbers only"),
            "{message}"
        );
    }
}
