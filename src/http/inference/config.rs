//! Triton's model configuration extension: `GET /v2/models/{name}/config` and
//! `GET /v2/models/{name}/versions/{v}/config`, what `tritonclient`'s `get_model_config` reads.
//! The configuration is written from the policy's spec in Triton's JSON form of its
//! `ModelConfig`: one FP32 input `observations` `[-1, obs_dim]` and the output `actions` (FP32
//! `[-1, action_dim]` or INT64 `[-1]`), then a SafeDICE policy's safety outputs, with the batch dimension in `dims` and `max_batch_size`
//! 0 (Triton's convention for a model that takes any batch as its first dimension).

use axum::extract::State;
use serde::Serialize;
use std::collections::BTreeMap;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::binary::V2Error;
use super::{served, ModelVersion};
use crate::http::extract::{Json, Path};
use crate::http::{ApiError, AppState};
use crate::serving::inference::{Tensor, PLATFORM};

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(model_config)).routes(routes!(version_config))
}

/// A tensor of the configuration.
#[derive(Debug, Serialize, ToSchema)]
pub struct ConfigTensor {
    pub name: String,
    /// `TYPE_FP32` or `TYPE_INT64`.
    pub data_type: String,
    /// -1 marks the batch dimension.
    pub dims: Vec<i64>,
}

/// A string parameter, as Triton writes `parameters`.
#[derive(Debug, Serialize, ToSchema)]
pub struct ConfigParameter {
    pub string_value: String,
}

/// Triton's model configuration (the fields that describe a policy).
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelConfig {
    /// The name as requested.
    pub name: String,
    /// `safedice`.
    pub platform: String,
    pub backend: String,
    /// 0: the batch is the first of `dims`, any size.
    pub max_batch_size: u32,
    pub input: Vec<ConfigTensor>,
    pub output: Vec<ConfigTensor>,
    /// `algorithm` (what trained it) and `version` (the version that answers).
    pub parameters: BTreeMap<String, ConfigParameter>,
}

/// Triton's model configuration of a policy or named model (`name`, `name@alias`).
#[utoipa::path(get, path = "/v2/models/{id}/config", tag = "inference",
    params(("id" = String, Path)),
    responses((status = 200, body = ModelConfig), (status = 404, body = V2Error)))]
async fn model_config(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ModelConfig>, ApiError> {
    config_of(&state, id, None).await
}

/// Triton's model configuration of one version.
#[utoipa::path(get, path = "/v2/models/{id}/versions/{version}/config", tag = "inference",
    params(("id" = String, Path), ("version" = String, Path)),
    responses((status = 200, body = ModelConfig), (status = 404, body = V2Error)))]
async fn version_config(
    State(state): State<AppState>,
    Path(model): Path<ModelVersion>,
) -> Result<Json<ModelConfig>, ApiError> {
    config_of(&state, model.id, Some(model.version)).await
}

async fn config_of(
    state: &AppState,
    id: String,
    version: Option<String>,
) -> Result<Json<ModelConfig>, ApiError> {
    let model = served(state, id, version, None).await?.describe();
    let tensor = |t: Tensor| ConfigTensor {
        name: t.name.into(),
        data_type: format!("TYPE_{}", t.datatype),
        dims: t.shape,
    };
    let parameter = |value: String| ConfigParameter { string_value: value };
    Ok(Json(ModelConfig {
        name: model.name,
        platform: PLATFORM.into(),
        backend: PLATFORM.into(),
        max_batch_size: 0,
        input: vec![tensor(model.input)],
        output: model.outputs.into_iter().map(tensor).collect(),
        parameters: BTreeMap::from([
            ("algorithm".to_owned(), parameter(model.algorithm)),
            ("version".to_owned(), parameter(model.version)),
        ]),
    }))
}
