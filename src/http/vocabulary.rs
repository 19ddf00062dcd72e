//! `/v1/vocabulary`: the words the service's resources use, with what each means: job statuses
//! (which are final, which a success) and evaluation metrics (labels, which way is better, which the paper
//! reports). The dashboard loads the same table as `/ui/vocabulary.js` and the Python client
//! reads it, so neither keeps a copy that a new status or metric would leave behind.

use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::Json;
use super::AppState;
use crate::domain::JobStatus;
use crate::envs::metrics::{MetricInfo, METRICS};

/// A job status and what it means.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct JobStatusInfo {
    pub name: JobStatus,
    /// The job never runs again.
    #[serde(rename = "final")]
    pub is_final: bool,
    /// The job ended with what it was for (its policy stored); every other final status is a
    /// failure to the client that waited.
    #[serde(rename = "success")]
    pub is_success: bool,
    pub meaning: &'static str,
}

/// The service's vocabulary.
#[derive(Debug, serde::Serialize, ToSchema)]
pub struct Vocabulary {
    /// Every job status, in lifecycle order.
    pub job_statuses: Vec<JobStatusInfo>,
    /// Every evaluation metric, in the order a job's history records them.
    pub evaluation_metrics: Vec<MetricInfo>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(get_vocabulary))
}

/// The job statuses and evaluation metrics, with what each means.
#[utoipa::path(get, path = "/v1/vocabulary", tag = "operations",
    responses((status = 200, description = "The vocabulary", body = Vocabulary)))]
async fn get_vocabulary() -> Json<Vocabulary> {
    Json(vocabulary())
}

/// The table behind `/v1/vocabulary` (and the dashboard's copy of it).
pub fn vocabulary() -> Vocabulary {
    let job_statuses = JobStatus::ALL
        .into_iter()
        .map(|name| JobStatusInfo {
            name,
            is_final: name.is_final(),
            is_success: name.is_success(),
            meaning: name.meaning(),
        })
        .collect();
    Vocabulary { job_statuses, evaluation_metrics: METRICS.to_vec() }
}
