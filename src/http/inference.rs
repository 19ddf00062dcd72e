//! Actions from trained policies ([`crate::serving::PolicyCache`], shared with
//! `POST /v1/policies/{id}/act`) over the Open Inference Protocol (KServe v2) routes served here:
//! `GET /v2/health/live`, `GET /v2/health/ready`, `GET /v2/models/{id}`,
//! `GET /v2/models/{id}/ready`, `POST /v2/models/{id}/infer`.
//!
//! A v2 model is a policy (its id is the model name). `infer` takes one FP32 input of shape
//! `[B, obs_dim]` and answers one output `actions`: FP32 `[B, action_dim]` for continuous
//! spaces, INT64 `[B]` for discrete ones; deterministic unless the request's `parameters` say
//! `"deterministic": false` (with an optional `"seed"`), exactly as `/act`.

use std::sync::Arc;

use axum::extract::State;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{AnyContentTypeJson, Json, Path};
use super::{ApiError, AppState};
use crate::algo::Policy;
use crate::data::{ActionSpace, Actions};

/// The name of a model's one input tensor (KServe v2 metadata and `infer`).
const INPUT_NAME: &str = "observations";

/// Largest batch one request may send.
pub const MAX_BATCH_ROWS: usize = 16_384;
/// Batches up to this many rows run on the request's task (a few microseconds of matrix
/// products); larger ones move to a blocking thread so they cannot stall other requests.
const INLINE_ROWS: usize = 64;

/// Validated observations: `rows × obs_dim`, row-major, all finite.
pub struct Observations {
    pub values: Vec<f32>,
    pub rows: usize,
}

impl Observations {
    /// From `/act`'s list of rows.
    pub fn from_rows(rows: &[Vec<f64>], obs_dim: usize) -> Result<Self, ApiError> {
        check_batch_size(rows.len())?;
        let mut values = Vec::with_capacity(rows.len() * obs_dim);
        for (i, row) in rows.iter().enumerate() {
            if row.len() != obs_dim {
                return Err(invalid(format!(
                    "observations[{i}] has {} values; this policy takes {obs_dim} per observation",
                    row.len()
                )));
            }
            for (j, &v) in row.iter().enumerate() {
                values.push(finite(v, || format!("observations[{i}][{j}]"))?);
            }
        }
        Ok(Observations { values, rows: rows.len() })
    }

    /// From a flat row-major buffer of `rows × obs_dim` values.
    fn from_flat(flat: &[f64], rows: usize, obs_dim: usize) -> Result<Self, ApiError> {
        check_batch_size(rows)?;
        let values = flat
            .iter()
            .enumerate()
            .map(|(k, &v)| finite(v, || format!("data[{}][{}]", k / obs_dim, k % obs_dim)))
            .collect::<Result<_, _>>()?;
        Ok(Observations { values, rows })
    }
}

fn check_batch_size(rows: usize) -> Result<(), ApiError> {
    if rows == 0 {
        return Err(invalid("the batch is empty: send at least one observation".into()));
    }
    if rows > MAX_BATCH_ROWS {
        return Err(ApiError::unprocessable(
            "batch_too_large",
            format!("{rows} observations in one request; at most {MAX_BATCH_ROWS}"),
        ));
    }
    Ok(())
}

fn finite(v: f64, at: impl FnOnce() -> String) -> Result<f32, ApiError> {
    let x = v as f32;
    if x.is_finite() {
        Ok(x)
    } else {
        Err(invalid(format!("{} is {v}, which is not a finite 32-bit float", at())))
    }
}

fn invalid(message: String) -> ApiError {
    ApiError::unprocessable("invalid_observations", message)
}

/// Runs the policy on validated observations: deterministic (tanh of the mean / argmax), or
/// sampled with `seed` (reproducible) or fresh entropy.
pub async fn act(
    policy: Arc<Policy>,
    observations: Observations,
    deterministic: bool,
    seed: Option<u64>,
) -> Result<Actions, ApiError> {
    let mut rng = match seed {
        Some(seed) => ChaCha8Rng::seed_from_u64(seed),
        None if deterministic => ChaCha8Rng::seed_from_u64(0),
        None => ChaCha8Rng::from_os_rng(),
    };
    let mut run = move || {
        policy
            .act(&observations.values, deterministic, &mut rng)
            .map_err(|e| ApiError::Internal(anyhow::anyhow!("policy inference failed: {e}")))
    };
    if observations.rows <= INLINE_ROWS {
        run()
    } else {
        tokio::task::spawn_blocking(run).await?
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(live))
        .routes(routes!(ready))
        .routes(routes!(model_metadata))
        .routes(routes!(model_ready))
        .routes(routes!(infer))
}

/// KServe v2 liveness / readiness answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct V2Health {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live: Option<bool>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ready: Option<bool>,
}

/// KServe v2 server liveness.
#[utoipa::path(get, path = "/v2/health/live", tag = "inference",
    responses((status = 200, body = V2Health)))]
async fn live() -> Json<V2Health> {
    Json(V2Health { live: Some(true), ready: None })
}

/// KServe v2 server readiness: the database answers.
#[utoipa::path(get, path = "/v2/health/ready", tag = "inference",
    responses((status = 200, body = V2Health), (status = 503, body = ErrorBody)))]
async fn ready(State(state): State<AppState>) -> Result<Json<V2Health>, ApiError> {
    state
        .store
        .ping()
        .await
        .map_err(|_| ApiError::unavailable("not_ready", "the database is not reachable"))?;
    Ok(Json(V2Health { live: None, ready: Some(true) }))
}

/// A tensor's description in model metadata.
#[derive(Debug, Serialize, ToSchema)]
pub struct TensorMetadata {
    pub name: String,
    /// `FP32` or `INT64`.
    pub datatype: String,
    /// -1 marks the batch dimension.
    pub shape: Vec<i64>,
}

/// KServe v2 model metadata.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelMetadata {
    /// The policy id.
    pub name: String,
    pub versions: Vec<String>,
    pub platform: String,
    pub inputs: Vec<TensorMetadata>,
    pub outputs: Vec<TensorMetadata>,
}

fn output_layout(space: &ActionSpace) -> (&'static str, Vec<i64>) {
    match space {
        ActionSpace::Continuous { dim, .. } => ("FP32", vec![-1, *dim as i64]),
        ActionSpace::Discrete { .. } => ("INT64", vec![-1]),
    }
}

/// KServe v2 model metadata of a policy.
#[utoipa::path(get, path = "/v2/models/{id}", tag = "inference", params(("id" = String, Path)),
    responses((status = 200, body = ModelMetadata), (status = 404, body = ErrorBody)))]
async fn model_metadata(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ModelMetadata>, ApiError> {
    let policy = state.policies.get(&id).await?;
    let spec = policy.spec();
    let (datatype, shape) = output_layout(&spec.action_space);
    Ok(Json(ModelMetadata {
        name: id,
        versions: vec!["1".into()],
        platform: format!("safedice-{}", spec.algorithm),
        inputs: vec![TensorMetadata {
            name: INPUT_NAME.into(),
            datatype: "FP32".into(),
            shape: vec![-1, spec.obs_dim as i64],
        }],
        outputs: vec![TensorMetadata { name: "actions".into(), datatype: datatype.into(), shape }],
    }))
}

/// KServe v2 model readiness answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelReady {
    pub name: String,
    pub ready: bool,
}

/// KServe v2 model readiness (loads the policy into the cache).
#[utoipa::path(get, path = "/v2/models/{id}/ready", tag = "inference",
    params(("id" = String, Path)),
    responses((status = 200, body = ModelReady), (status = 404, body = ErrorBody)))]
async fn model_ready(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ModelReady>, ApiError> {
    state.policies.get(&id).await?;
    Ok(Json(ModelReady { name: id, ready: true }))
}

/// One input tensor of an inference request.
#[derive(Debug, Deserialize, ToSchema)]
pub struct InferInput {
    pub name: String,
    /// `[B, obs_dim]`.
    pub shape: Vec<i64>,
    /// Must be `FP32`.
    pub datatype: String,
    /// Row-major values, flat or nested.
    #[schema(value_type = Vec<f32>)]
    pub data: serde_json::Value,
}

/// Inference parameters (this service's extension; both optional).
#[derive(Debug, Default, Deserialize, ToSchema)]
pub struct InferParameters {
    /// Default true: tanh of the mean / argmax. false samples.
    pub deterministic: Option<bool>,
    /// Makes sampling reproducible.
    pub seed: Option<u64>,
}

/// KServe v2 inference request.
#[derive(Debug, Deserialize, ToSchema)]
pub struct InferRequest {
    pub id: Option<String>,
    pub inputs: Vec<InferInput>,
    #[serde(default)]
    pub parameters: InferParameters,
}

/// One output tensor.
#[derive(Debug, Serialize, ToSchema)]
pub struct InferOutput {
    pub name: String,
    pub shape: Vec<i64>,
    pub datatype: String,
    /// Row-major values.
    #[schema(value_type = Vec<f32>)]
    pub data: serde_json::Value,
}

/// KServe v2 inference response.
#[derive(Debug, Serialize, ToSchema)]
pub struct InferResponse {
    pub model_name: String,
    pub model_version: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    pub outputs: Vec<InferOutput>,
}

/// KServe v2 inference: actions for a batch of observations.
#[utoipa::path(post, path = "/v2/models/{id}/infer", tag = "inference",
    params(("id" = String, Path)), request_body = InferRequest,
    responses(
        (status = 200, body = InferResponse),
        (status = 404, body = ErrorBody),
        (status = 422, description = "Wrong input count, datatype or shape \
            (`invalid_input`), bad values (`invalid_observations`)", body = ErrorBody),
    ))]
async fn infer(
    State(state): State<AppState>,
    Path(id): Path<String>,
    AnyContentTypeJson(request): AnyContentTypeJson<InferRequest>,
) -> Result<Json<InferResponse>, ApiError> {
    let policy = state.policies.get(&id).await?;
    let obs_dim = policy.spec().obs_dim;
    let [input] = &request.inputs[..] else {
        return Err(bad_input(format!(
            "expected exactly one input tensor, got {}",
            request.inputs.len()
        )));
    };
    if input.name != INPUT_NAME {
        return Err(bad_input(format!(
            "unknown input `{}`; this model's only input is `{INPUT_NAME}` (see its metadata)",
            input.name
        )));
    }
    if input.datatype != "FP32" {
        return Err(bad_input(format!("input datatype must be FP32, got {}", input.datatype)));
    }
    let rows = match input.shape[..] {
        [rows, dim] if rows >= 0 && dim == obs_dim as i64 => rows as usize,
        _ => {
            return Err(bad_input(format!(
                "input shape must be [B, {obs_dim}], got {:?}",
                input.shape
            )))
        }
    };
    // Sized by the data that came, never by the shape the client declared.
    let mut flat = Vec::new();
    flatten_numbers(&input.data, &mut flat)?;
    if rows.checked_mul(obs_dim) != Some(flat.len()) {
        return Err(bad_input(format!(
            "input data has {} values; shape {:?} needs {}",
            flat.len(),
            input.shape,
            (rows as u128) * (obs_dim as u128)
        )));
    }
    let observations = Observations::from_flat(&flat, rows, obs_dim)?;
    let deterministic = request.parameters.deterministic.unwrap_or(true);
    let actions = act(policy.clone(), observations, deterministic, request.parameters.seed).await?;
    let (datatype, mut shape) = output_layout(&policy.spec().action_space);
    shape[0] = rows as i64;
    let data = match actions {
        Actions::Continuous(values) => serde_json::to_value(values),
        Actions::Discrete(indices) => serde_json::to_value(indices),
    }
    .map_err(anyhow::Error::from)?;
    Ok(Json(InferResponse {
        model_name: id,
        model_version: "1".into(),
        id: request.id,
        outputs: vec![InferOutput {
            name: "actions".into(),
            shape,
            datatype: datatype.into(),
            data,
        }],
    }))
}

fn bad_input(message: String) -> ApiError {
    ApiError::unprocessable("invalid_input", message)
}

/// Appends the numbers of a (possibly nested) JSON array in row-major order.
fn flatten_numbers(value: &serde_json::Value, out: &mut Vec<f64>) -> Result<(), ApiError> {
    match value {
        serde_json::Value::Array(items) => items.iter().try_for_each(|v| flatten_numbers(v, out)),
        serde_json::Value::Number(n) => {
            out.push(n.as_f64().unwrap_or(f64::NAN));
            Ok(())
        }
        other => Err(ApiError::unprocessable(
            "invalid_observations",
            format!("input data must hold numbers only, found {other}"),
        )),
    }
}
