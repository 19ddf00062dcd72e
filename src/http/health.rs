//! Liveness and readiness. (`/` is left to the dashboard.)

use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::Json;
use super::{ApiError, AppState};
use crate::store::StorageProblem;

/// The answer of the health endpoints.
#[derive(Debug, Serialize, ToSchema)]
pub struct Health {
    #[schema(example = "ok")]
    pub status: &'static str,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(healthz)).routes(routes!(readyz))
}

/// Liveness: the process answers HTTP.
#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses((status = 200, description = "The process is alive", body = Health)))]
async fn healthz() -> Json<Health> {
    Json(Health { status: "ok" })
}

/// Readiness: the database answers a query, and the data directory takes writes and has at
/// least `--min-free-disk` bytes free.
#[utoipa::path(get, path = "/readyz", tag = "operations",
    responses(
        (status = 200, description = "Ready", body = Health),
        (status = 503, description = "Not ready: the database is unreachable (`not_ready`), a \
            file cannot be written in the data directory (`storage_unwritable`), or its file \
            system has less than `--min-free-disk` bytes free (`low_disk_space`)",
            body = ErrorBody),
    ))]
async fn readyz(State(state): State<AppState>) -> Result<Json<Health>, ApiError> {
    if let Err(e) = state.store.ping().await {
        tracing::warn!(error = %e, "readiness check failed");
        return Err(ApiError::unavailable(
            "not_ready",
            "the database is not reachable; retry shortly",
        ));
    }
    match state.store.check_storage(state.config.min_free_disk).await {
        Ok(()) => Ok(Json(Health { status: "ready" })),
        Err(problem) => {
            tracing::warn!(%problem, "readiness check failed");
            let code = match problem {
                StorageProblem::Unwritable { .. } => "storage_unwritable",
                StorageProblem::LowSpace { .. } => "low_disk_space",
            };
            Err(ApiError::unavailable(
                code,
                format!("{problem}; uploads and training need room to write"),
            ))
        }
    }
}
