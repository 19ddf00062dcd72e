//! The built-in benchmark environments (`src/envs`): what `safedice datagen` and the benchmark
//! can generate data for and evaluate policies on.

use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::Json;
use super::AppState;
use crate::envs::{self, EnvInfo};

/// The list of built-in environments.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct EnvList {
    pub items: Vec<EnvInfo>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(list_envs))
}

/// The built-in environments with their observation and action spaces, horizon, reward and
/// cost.
#[utoipa::path(get, path = "/v1/envs", tag = "environments",
    responses((status = 200, description = "Every built-in environment", body = EnvList)))]
async fn list_envs() -> Json<EnvList> {
    Json(EnvList { items: envs::list() })
}
