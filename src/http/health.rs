//! Liveness, readiness and the service index.

use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::Json;
use super::{ApiError, AppState};

/// The answer of the health endpoints.
#[derive(Debug, Serialize, ToSchema)]
pub struct Health {
    #[schema(example = "ok")]
    pub status: &'static str,
}

/// What this server is and where its API is described.
#[derive(Debug, Serialize, ToSchema)]
pub struct ServiceIndex {
    #[schema(example = "safedice")]
    pub service: &'static str,
    #[schema(example = "0.1.0")]
    pub version: &'static str,
    /// Path of the OpenAPI description.
    #[schema(example = "/v1/openapi.json")]
    pub openapi: &'static str,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(index)).routes(routes!(healthz)).routes(routes!(readyz))
}

/// Service name, version and the location of the API description.
#[utoipa::path(get, path = "/", tag = "operations",
    responses((status = 200, body = ServiceIndex)))]
async fn index() -> Json<ServiceIndex> {
    Json(ServiceIndex {
        service: "safedice",
        version: env!("CARGO_PKG_VERSION"),
        openapi: "/v1/openapi.json",
    })
}

/// Liveness: the process answers HTTP.
#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses((status = 200, body = Health)))]
async fn healthz() -> Json<Health> {
    Json(Health { status: "ok" })
}

/// Readiness: the database answers a query.
#[utoipa::path(get, path = "/readyz", tag = "operations",
    responses(
        (status = 200, body = Health),
        (status = 503, description = "The database is unreachable", body = ErrorBody),
    ))]
async fn readyz(State(state): State<AppState>) -> Result<Json<Health>, ApiError> {
    match state.store.ping().await {
        Ok(()) => Ok(Json(Health { status: "ready" })),
        Err(e) => {
            tracing::warn!(error = %e, "readiness check failed");
            Err(ApiError::unavailable("not_ready", "the database is not reachable; retry shortly"))
        }
    }
}
