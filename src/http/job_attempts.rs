//! `GET /v1/jobs/{id}/attempts`: every claim of a job by a worker and how it ended — the
//! history behind a job that was retried after its worker vanished, or failed once its attempts
//! were spent.

use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path};
use super::{ApiError, AppState};
use crate::domain::JobId;
use crate::domain::{rfc3339, AttemptOutcome, JobAttempt};

/// One claim of a job by a worker.
#[derive(Debug, Serialize, ToSchema)]
pub struct Attempt {
    /// Which attempt (1 for the first). A run handed back to the queue on shutdown (outcome
    /// `released`) gives its attempt back: the claim that resumes it has the same number.
    pub attempt: u32,
    /// The worker that claimed the job.
    pub worker: String,
    pub started_at: String,
    /// Absent while it runs.
    pub ended_at: Option<String>,
    /// `running`, `succeeded`, `failed` (an error that retrying cannot fix: no further attempt),
    /// `cancelled`, `released` (shutdown, or a store that could not take the run's writes; not
    /// counted), `crashed` (the worker stopped renewing its lease: killed, out of memory,
    /// crashed or cut off from the database), `lease_lost` (the worker came back after another
    /// had taken the job over, and stopped without writing).
    pub outcome: AttemptOutcome,
    /// What ended it.
    pub message: Option<String>,
}

impl From<JobAttempt> for Attempt {
    fn from(a: JobAttempt) -> Self {
        Attempt {
            attempt: a.attempt,
            worker: a.worker,
            started_at: rfc3339(&a.started_at),
            ended_at: a.ended_at.as_ref().map(rfc3339),
            outcome: a.outcome,
            message: a.message,
        }
    }
}

/// A job's attempts.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobAttempts {
    pub job_id: String,
    /// Attempts started so far.
    pub attempt: u32,
    pub max_attempts: u32,
    /// Every claim, oldest first.
    pub attempts: Vec<Attempt>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(job_attempts))
}

/// A job's attempts: each claim by a worker, how it ended and why.
#[utoipa::path(get, path = "/v1/jobs/{id}/attempts", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = JobAttempts), (status = 404, body = ErrorBody)))]
async fn job_attempts(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
) -> Result<Json<JobAttempts>, ApiError> {
    let job = state.store.job(&id).await?;
    let attempts = state.store.job_attempts(&id).await?;
    Ok(Json(JobAttempts {
        job_id: job.id.into_string(),
        attempt: job.attempt,
        max_attempts: job.max_attempts,
        attempts: attempts.into_iter().map(Attempt::from).collect(),
    }))
}
