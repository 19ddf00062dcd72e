//! Actions from trained policies ([`crate::serving::PolicyCache`], shared with
//! `POST /v1/policies/{id}/act`) over the Open Inference Protocol (KServe v2) routes served here:
//! `GET /v2` (server metadata), `GET /v2/health/live`, `GET /v2/health/ready`, and per model
//! `GET /v2/models/{id}`, `GET …/ready`, `POST …/infer`, each also under
//! `/v2/models/{id}/versions/{version}/`; the repository and statistics extensions
//! ([`repository`]) and Triton's model configuration ([`config`]). Errors under `/v2` have the protocol's shape `{"error": "message"}`
//! ([`binary::v2_error_shape`]).
//!
//! A v2 model is a policy (its id is the model name, its one version `1`) or a named model
//! (`name`: its latest version; `name@alias`: the alias's version; `/versions/{n}`: version n;
//! the answer's `model_version` says which answered). `infer` takes one
//! FP32 input `observations` of shape `[B, obs_dim]`, as JSON or as binary tensor data
//! ([`binary`]), and answers one output `actions`: FP32 `[B, action_dim]` for continuous spaces,
//! INT64 `[B]` for discrete ones, as JSON or binary as the request asks; deterministic unless
//! the request's `parameters` say `"deterministic": false` (with an optional `"seed"`), exactly
//! as `/act`.

pub mod binary;
pub mod config;
pub mod repository;

use axum::extract::State;
use axum::http::HeaderMap;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use axum::response::{IntoResponse, Response};
use binary::{InferBody, V2Error};

use super::act::ACTION_BODY_LIMIT;
use super::extract::{Json, Path};
use super::model_names;
use super::{ApiError, AppState};
use crate::serving::inference::{self as protocol, Input, InputData, OutputData, Served};

pub fn router() -> OpenApiRouter<AppState> {
    let infer = OpenApiRouter::new()
        .routes(routes!(infer))
        .routes(routes!(version_infer))
        .layer(axum::extract::DefaultBodyLimit::max(ACTION_BODY_LIMIT));
    OpenApiRouter::new()
        .routes(routes!(server_metadata))
        .routes(routes!(live))
        .routes(routes!(ready))
        .routes(routes!(model_metadata))
        .routes(routes!(model_ready))
        .routes(routes!(version_metadata))
        .routes(routes!(version_ready))
        .merge(infer)
        .merge(repository::router())
        .merge(config::router())
}

/// KServe v2 server metadata.
#[derive(Debug, Serialize, ToSchema)]
pub struct ServerMetadata {
    pub name: String,
    pub version: String,
    /// Protocol extensions served: `binary_tensor_data`, `model_repository`, `statistics`,
    /// `model_configuration`.
    pub extensions: Vec<String>,
}

/// KServe v2 server metadata.
#[utoipa::path(get, path = "/v2", tag = "inference",
    responses((status = 200, body = ServerMetadata)))]
async fn server_metadata() -> Json<ServerMetadata> {
    Json(ServerMetadata {
        name: "safedice".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        extensions: protocol::EXTENSIONS.map(String::from).to_vec(),
    })
}

/// `{id, version}` of the versioned routes.
#[derive(Debug, Deserialize)]
struct ModelVersion {
    id: String,
    version: String,
}

/// What a v2 model name resolves to ([`protocol::served`]).
async fn served(
    state: &AppState,
    name: String,
    version: Option<String>,
    key: Option<&str>,
) -> Result<Served, ApiError> {
    Ok(protocol::served(&state.serving, name, version, key).await?)
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
    responses((status = 200, body = V2Health), (status = 503, body = V2Error)))]
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

/// What else the metadata says of a model.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelParameters {
    /// The algorithm that trained the policy.
    pub algorithm: String,
}

/// KServe v2 model metadata.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelMetadata {
    /// The policy id.
    pub name: String,
    pub versions: Vec<String>,
    /// `safedice`.
    pub platform: String,
    pub parameters: ModelParameters,
    pub inputs: Vec<TensorMetadata>,
    pub outputs: Vec<TensorMetadata>,
}

/// KServe v2 model metadata of a policy.
#[utoipa::path(get, path = "/v2/models/{id}", tag = "inference", params(("id" = String, Path)),
    responses((status = 200, body = ModelMetadata), (status = 404, body = V2Error)))]
async fn model_metadata(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ModelMetadata>, ApiError> {
    metadata_of(&state, id, None).await
}

/// KServe v2 model metadata of a policy's version (always `1`).
#[utoipa::path(get, path = "/v2/models/{id}/versions/{version}", tag = "inference",
    params(("id" = String, Path), ("version" = String, Path)),
    responses((status = 200, body = ModelMetadata), (status = 404, body = V2Error)))]
async fn version_metadata(
    State(state): State<AppState>,
    Path(model): Path<ModelVersion>,
) -> Result<Json<ModelMetadata>, ApiError> {
    metadata_of(&state, model.id, Some(model.version)).await
}

async fn metadata_of(
    state: &AppState,
    id: String,
    version: Option<String>,
) -> Result<Json<ModelMetadata>, ApiError> {
    let model = served(state, id, version, None).await?.describe();
    let tensor = |t: protocol::Tensor| TensorMetadata {
        name: t.name.into(),
        datatype: t.datatype.into(),
        shape: t.shape,
    };
    Ok(Json(ModelMetadata {
        name: model.name,
        versions: model.versions,
        // The runtime, as other servers name theirs (`onnxruntime_onnx`, `pytorch_libtorch`);
        // the algorithm is in `parameters`.
        platform: protocol::PLATFORM.into(),
        parameters: ModelParameters { algorithm: model.algorithm },
        inputs: vec![tensor(model.input)],
        outputs: model.outputs.into_iter().map(tensor).collect(),
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
    responses((status = 200, body = ModelReady), (status = 404, body = V2Error)))]
async fn model_ready(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ModelReady>, ApiError> {
    ready_of(&state, id, None).await
}

/// KServe v2 readiness of a policy's version (always `1`).
#[utoipa::path(get, path = "/v2/models/{id}/versions/{version}/ready", tag = "inference",
    params(("id" = String, Path), ("version" = String, Path)),
    responses((status = 200, body = ModelReady), (status = 404, body = V2Error)))]
async fn version_ready(
    State(state): State<AppState>,
    Path(model): Path<ModelVersion>,
) -> Result<Json<ModelReady>, ApiError> {
    ready_of(&state, model.id, Some(model.version)).await
}

async fn ready_of(
    state: &AppState,
    id: String,
    version: Option<String>,
) -> Result<Json<ModelReady>, ApiError> {
    let served = served(state, id, version, None).await?;
    Ok(Json(ModelReady { name: served.name, ready: true }))
}

/// One input tensor of an inference request.
#[derive(Debug, Deserialize, ToSchema)]
pub struct InferInput {
    pub name: String,
    /// `[B, obs_dim]`.
    #[serde(deserialize_with = "crate::domain::integral::signed_list")]
    pub shape: Vec<i64>,
    /// Must be `FP32`.
    pub datatype: String,
    /// Row-major values, flat or nested; absent when the values come as binary tensor data.
    #[schema(value_type = Option<Vec<f32>>)]
    #[serde(default)]
    pub data: Option<TensorData>,
    #[serde(default)]
    pub parameters: TensorParameters,
}

/// Binary tensor data extension: the tensor's bytes follow the JSON header.
#[derive(Debug, Default, Serialize, Deserialize, ToSchema)]
pub struct TensorParameters {
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::domain::integral::optional_unsigned"
    )]
    pub binary_data_size: Option<u64>,
}

/// An output the request asks for.
#[derive(Debug, Deserialize, ToSchema)]
pub struct RequestedOutput {
    pub name: String,
    #[serde(default)]
    pub parameters: RequestedOutputParameters,
}

#[derive(Debug, Default, Deserialize, ToSchema)]
pub struct RequestedOutputParameters {
    /// true: the output's values as binary tensor data after the JSON header.
    pub binary_data: Option<bool>,
}

/// Inference parameters: this service's `deterministic` and `seed`, and the binary tensor data
/// extension's `binary_data_output`.
#[derive(Debug, Default, Deserialize, ToSchema)]
pub struct InferParameters {
    /// Default true: tanh of the mean / argmax. false samples.
    pub deterministic: Option<bool>,
    /// Makes sampling reproducible (at most 2^63 - 1).
    #[serde(default, deserialize_with = "crate::domain::deserialize_optional_seed")]
    #[schema(maximum = 9223372036854775807_u64)]
    pub seed: Option<u64>,
    /// Every output as binary tensor data (when `outputs` names none).
    pub binary_data_output: Option<bool>,
    /// true: also the outputs `non_preferred_log_ratio` and `out_of_support`, the safety scores
    /// of the returned actions (SafeDICE policies; others answer 422
    /// `safety_score_unavailable`).
    pub safety_score: Option<bool>,
}

/// KServe v2 inference request.
#[derive(Debug, Deserialize, ToSchema)]
pub struct InferRequest {
    pub id: Option<String>,
    #[schema(min_items = 1)]
    pub inputs: Vec<InferInput>,
    /// The outputs wanted (absent: `actions`, with the safety outputs when
    /// `parameters.safety_score` is true).
    pub outputs: Option<Vec<RequestedOutput>>,
    #[serde(default)]
    pub parameters: InferParameters,
}

/// One output tensor.
#[derive(Debug, Serialize, ToSchema)]
pub struct InferOutput {
    pub name: String,
    pub shape: Vec<i64>,
    pub datatype: String,
    /// Row-major values; absent when they follow as binary tensor data.
    #[schema(value_type = Option<Vec<f32>>)]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data: Option<serde_json::Value>,
    #[serde(skip_serializing_if = "is_default")]
    pub parameters: TensorParameters,
}

fn is_default(parameters: &TensorParameters) -> bool {
    parameters.binary_data_size.is_none()
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
        (status = 200, body = InferResponse, description = "JSON, or with binary outputs the \
            JSON header (`Inference-Header-Content-Length` bytes) and the outputs' bytes"),
        (status = 400, description = "Unparsable body or header length", body = V2Error),
        (status = 404, body = V2Error),
        (status = 422, description = "Wrong input count, name, datatype or shape, an unknown \
            output, binary data that does not fit, bad values", body = V2Error),
    ))]
async fn infer(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: InferBody<InferRequest>,
) -> Result<Response, ApiError> {
    let served = served(&state, id, None, model_names::request_key(&headers)).await?;
    infer_timed(served, body).await
}

/// KServe v2 inference on a policy's version (always `1`).
#[utoipa::path(post, path = "/v2/models/{id}/versions/{version}/infer", tag = "inference",
    params(("id" = String, Path), ("version" = String, Path)), request_body = InferRequest,
    responses(
        (status = 200, body = InferResponse),
        (status = 400, body = V2Error),
        (status = 404, body = V2Error),
        (status = 422, body = V2Error),
    ))]
async fn version_infer(
    State(state): State<AppState>,
    Path(model): Path<ModelVersion>,
    body: InferBody<InferRequest>,
) -> Result<Response, ApiError> {
    let served = served(&state, model.id, Some(model.version), None).await?;
    infer_timed(served, body).await
}

/// Runs the inference, counting it in the version's statistics (named models) and naming the
/// version that answered in the `x-safedice-model-version` header.
async fn infer_timed(served: Served, body: InferBody<InferRequest>) -> Result<Response, ApiError> {
    let result = served.timed(infer_with(&served, body)).await;
    let Some((answer, _)) = &served.answer else { return result };
    let mut response = result?;
    model_names::tag_version(&mut response, answer);
    Ok(response)
}

async fn infer_with(
    served: &Served,
    InferBody { request, mut binary }: InferBody<InferRequest>,
) -> Result<Response, ApiError> {
    let mut inputs = Vec::with_capacity(request.inputs.len());
    let mut raw = Vec::with_capacity(request.inputs.len());
    // The binary data of the inputs, in input order, cut by their declared sizes.
    for input in &request.inputs {
        raw.push(match input.parameters.binary_data_size {
            Some(size) => Some(binary::take(&mut binary, size, &input.name)?),
            None => None,
        });
    }
    for (input, raw) in request.inputs.iter().zip(&raw) {
        let data = match (raw, &input.data) {
            (Some(bytes), _) => InputData::Raw(bytes),
            (None, Some(TensorData(flat))) => InputData::Numbers(flat),
            (None, None) => {
                InputData::Missing("has neither `data` nor `parameters.binary_data_size`")
            }
        };
        inputs.push(Input::new(&input.name, &input.datatype, &input.shape, data));
    }
    let observations = protocol::observations(inputs, served.policy.spec().obs_dim)?;
    if !binary.is_empty() {
        return Err(bad_input(format!(
            "{} bytes of binary data after the inputs' declared sizes",
            binary.len()
        )));
    }
    let binary_output = wants_binary_output(&request);
    let requested: Vec<&str> =
        request.outputs.iter().flatten().map(|output| output.name.as_str()).collect();
    let policy = &served.policy;
    let wanted = protocol::wanted_outputs(&requested, request.parameters.safety_score, policy)?;
    let outputs = protocol::infer(
        served,
        observations,
        request.parameters.deterministic.unwrap_or(true),
        request.parameters.seed,
        &wanted,
    )
    .await?;
    let mut bytes = Vec::new();
    let mut tensors = Vec::with_capacity(outputs.len());
    for output in outputs {
        let mut tensor = InferOutput {
            name: output.name.into(),
            shape: output.shape,
            datatype: output.datatype.into(),
            data: None,
            parameters: TensorParameters::default(),
        };
        if binary_output {
            let raw = output.data.little_endian();
            tensor.parameters.binary_data_size = Some(raw.len() as u64);
            bytes.extend(raw);
        } else {
            tensor.data = Some(match output.data {
                OutputData::Fp32(values) => serde_json::json!(values),
                OutputData::Int64(values) => serde_json::json!(values),
            });
        }
        tensors.push(tensor);
    }
    let response = InferResponse {
        model_name: served.name.clone(),
        model_version: served.version.clone(),
        id: request.id,
        outputs: tensors,
    };
    if binary_output {
        let header = serde_json::to_vec(&response).map_err(anyhow::Error::from)?;
        Ok(binary::response(header, &bytes))
    } else {
        Ok(Json(response).into_response())
    }
}

/// Whether the response carries its outputs as binary tensor data: `binary_data_output`, or
/// what the last requested output says.
fn wants_binary_output(request: &InferRequest) -> bool {
    let Some(outputs) = &request.outputs else {
        return request.parameters.binary_data_output.unwrap_or(false);
    };
    outputs.last().and_then(|output| output.parameters.binary_data).unwrap_or(false)
}

fn bad_input(message: String) -> ApiError {
    ApiError::unprocessable("invalid_input", message)
}

/// An input's `data`: numbers, flat or nested in arrays, in row-major order, read straight from
/// the request text into one flat list.
#[derive(Debug, Default)]
pub struct TensorData(pub Vec<f64>);

impl<'de> Deserialize<'de> for TensorData {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let mut values = Vec::new();
        deserializer.deserialize_any(Flatten(&mut values))?;
        Ok(TensorData(values))
    }
}

/// Appends a number, or the numbers of a (nested) array in order, to the list it holds.
struct Flatten<'a>(&'a mut Vec<f64>);

impl<'de> serde::de::DeserializeSeed<'de> for Flatten<'_> {
    type Value = ();

    fn deserialize<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for Flatten<'_> {
    type Value = ();

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("numbers only (flat, or nested in arrays)")
    }

    fn visit_f64<E>(self, v: f64) -> Result<(), E> {
        self.0.push(v);
        Ok(())
    }

    fn visit_i64<E>(self, v: i64) -> Result<(), E> {
        self.0.push(v as f64);
        Ok(())
    }

    fn visit_u64<E>(self, v: u64) -> Result<(), E> {
        self.0.push(v as f64);
        Ok(())
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        let values = self.0;
        while seq.next_element_seed(Flatten(&mut *values))?.is_some() {}
        Ok(())
    }
}
