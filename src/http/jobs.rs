// ceiling: all eleven /v1/jobs routes and their API types, one module per resource as in http/
//! `/v1/jobs`: queue a training run, follow it (resource, metrics history, event stream), cancel
//! it. The work itself happens in [`crate::jobs`].

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::IntoResponse;
use futures::{Stream, StreamExt};
use serde::{Deserialize, Serialize};
use tokio::sync::broadcast;
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::algo::Algorithm;
use crate::domain::labels::TagSchema;
use crate::domain::model::Registration;
use crate::domain::{
    rfc3339, EvalOptions, JobLabels, JobProgress, JobRecord, JobStatus, RunnerOptions,
};
use crate::jobs::{JobEvent, JobRequest, SubmitLimits};
use crate::lttb::lttb_indices;
use crate::store::jobs::{CancelOutcome, DeleteJobOutcome, JobQuery, MetricRow};
use crate::store::logs::LogRow;
use crate::store::{Listing, Store, StoreError};

/// `POST /v1/jobs` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    pub algorithm: Algorithm,
    /// Id of the unlabeled dataset D^U.
    pub unlabeled_dataset: String,
    /// Id of the labeled non-preferred dataset D^N; required by every algorithm except `bc`.
    pub non_preferred_dataset: Option<String>,
    /// The algorithm's configuration: `"preset"` plus overrides of any knob; absent keys take
    /// the preset's values, unknown keys and out-of-range values are rejected (422
    /// `invalid_config`). The job resource shows the resolved configuration.
    ///
    /// Presets: `service` (default), `paper` (Tables 2/4 of the paper), `authors-code` (what
    /// the authors' published code runs). `GET /v1/algorithms` lists every preset's value of
    /// every knob.
    ///
    /// Keys of every algorithm: `seed`, `iterations`, `batch_size`, `hidden_sizes`, `lr_actor`,
    /// `normalize_observations` (the statistics travel with the policy). `safedice`:
    /// `discriminator_iterations` (unless set: `iterations` in the `service` preset, a tenth in the
    /// others), `lr_discriminator`,
    /// `lr_nu`, `discriminator_gp`, `nu_gp`, `gamma`, `terminal_handling` (`none`, `mask`,
    /// `reset`, `absorbing`), `standardize_reward`, `alpha_hat_quantile` (0: the paper's
    /// minimum), `ess_warning_fraction`, `discriminator_early_stopping` (hold out a fifth of
    /// the data and stop the discriminator when its held-out loss stops improving;
    /// `discriminator_iterations` is then its most). `dwbc`: `eta`, `lr_discriminator`, `discriminator_gp`.
    /// `ppl`: `reward_model_iterations`, `lr_reward_model`, `pairs_per_batch`,
    /// `segment_length`, `ppl_weight` (`raw`, `sigmoid`). `dexperts`: `alpha`. `bc`: no further
    /// keys.
    #[schema(value_type = Object, example = json!({"preset": "service", "iterations": 20000, "seed": 0}))]
    pub config: Option<serde_json::Value>,
    /// Job-runner options (how often metrics and checkpoints are stored), beside the algorithm's
    /// configuration: they never change the trained policy.
    #[schema(value_type = Option<RunnerOptions>)]
    pub runner: Option<serde_json::Value>,
    /// Evaluate the policy on a built-in environment every `every` policy-learning steps and at
    /// the end; the paper's metrics go to the metrics history as `eval/...` (absent: no
    /// evaluation). The environment's spaces must match the datasets'.
    #[schema(value_type = Option<EvalOptions>)]
    pub eval: Option<serde_json::Value>,
    /// A name for people, at most 200 characters (the dashboard shows it instead of the id).
    pub name: Option<String>,
    /// Up to 32 tags of 1-64 characters from letters, digits and `- _ . : / =`, e.g.
    /// `env=point-goal`; `GET /v1/jobs?tag=` filters by one.
    #[serde(default)]
    #[schema(value_type = Vec<TagSchema>)]
    pub tags: Vec<String>,
    /// Free text, at most 10,000 characters.
    pub notes: Option<String>,
    /// Attempts (1-100) before the job fails when the worker running it vanishes (killed, out
    /// of memory, its machine lost); absent: the server's `--max-attempts` (3 by default).
    /// Errors that retrying cannot fix fail the job at once.
    pub max_attempts: Option<u32>,
    /// When the job succeeds, its policy becomes the next version of this existing model (and
    /// `alias`, if given, moves to that version) in the same transaction.
    pub register: Option<Registration>,
}

/// `PATCH /v1/jobs/{id}` body (JSON merge patch): a key present replaces the field (`null`
/// clears it), a key absent keeps it. Any status: the labels never change what a job computes.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct UpdateJob {
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<String>)]
    pub name: Option<Option<String>>,
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<Vec<TagSchema>>)]
    pub tags: Option<Option<Vec<String>>>,
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<String>)]
    pub notes: Option<Option<String>>,
}

/// A key that is present: `Some(value)`, `Some(None)` for `null` (absent keys stay `None`).
fn present<'de, D, T>(deserializer: D) -> Result<Option<Option<T>>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    Option::<T>::deserialize(deserializer).map(Some)
}

/// A training job.
#[derive(Debug, Serialize, ToSchema)]
pub struct Job {
    pub id: String,
    /// The name given at creation or by `PATCH` (absent: none).
    pub name: Option<String>,
    pub tags: Vec<String>,
    pub notes: Option<String>,
    pub algorithm: Algorithm,
    pub status: JobStatus,
    pub unlabeled_dataset: String,
    pub non_preferred_dataset: Option<String>,
    /// The resolved configuration: every knob of the algorithm with its value.
    #[schema(value_type = Object)]
    pub config: serde_json::Value,
    pub runner: RunnerOptions,
    /// The eval block, if the job evaluates its policy while it trains.
    pub eval: Option<EvalOptions>,
    pub progress: JobProgress,
    /// SafeDICE's alpha-hat (Eq. 15) once the discriminator phase has computed it.
    pub alpha_hat: Option<f64>,
    /// The trained policy, once the job succeeded.
    pub policy_id: Option<String>,
    /// Why the job failed.
    pub error: Option<String>,
    /// A cancel was requested while the job ran.
    pub cancel_requested: bool,
    /// The worker that runs (or last ran) the job, `<host>-<pid>-<suffix>`: a `safedice worker`
    /// process or the worker pool of a `safedice serve` process.
    pub worker: Option<String>,
    /// Attempts started so far (`GET /v1/jobs/{id}/attempts` lists them with how each ended).
    pub attempt: u32,
    /// Attempts before the job fails when its workers keep vanishing.
    pub max_attempts: u32,
    /// A `queued` job whose last worker vanished: no worker claims it before this time (the
    /// retry backoff).
    pub retry_at: Option<String>,
    /// A `running` job whose worker stopped renewing its lease at this time: the job waits for
    /// another worker to take it over (its progress is frozen meanwhile).
    pub lease_expired_at: Option<String>,
    /// The model its policy becomes a version of when it succeeds.
    pub register: Option<Registration>,
    /// The experiment whose grid it belongs to (`GET /v1/experiments/{id}`).
    pub experiment_id: Option<String>,
    pub created_at: String,
    pub updated_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
}

impl From<JobRecord> for Job {
    fn from(job: JobRecord) -> Self {
        let progress = job.progress();
        Job {
            id: job.id.into_string(),
            name: job.labels.name,
            tags: job.labels.tags,
            notes: job.labels.notes,
            algorithm: job.algorithm,
            status: job.status,
            unlabeled_dataset: job.unlabeled_dataset.into_string(),
            non_preferred_dataset: job.non_preferred_dataset.map(|id| id.into_string()),
            config: serde_json::to_value(&job.config).unwrap_or_default(),
            runner: job.runner,
            eval: job.eval,
            progress,
            alpha_hat: job.alpha_hat,
            policy_id: job.policy_id.map(|id| id.into_string()),
            error: job.error,
            cancel_requested: job.cancel_requested,
            worker: job.worker,
            attempt: job.attempt,
            max_attempts: job.max_attempts,
            retry_at: job.retry_at.as_ref().map(rfc3339),
            lease_expired_at: job.lease_expired_at.as_ref().map(rfc3339),
            register: job.register,
            experiment_id: job.experiment.map(|(id, _)| id),
            created_at: rfc3339(&job.created_at),
            updated_at: rfc3339(&job.updated_at),
            started_at: job.started_at.as_ref().map(rfc3339),
            finished_at: job.finished_at.as_ref().map(rfc3339),
        }
    }
}

/// `?status=&tag=&q=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct JobFilter {
    /// Only jobs in this status.
    pub status: Option<JobStatus>,
    /// Only jobs with this tag.
    #[param(pattern = r"^[A-Za-z0-9_.:/=-]{1,64}$", min_length = 1, max_length = 64)]
    pub tag: Option<String>,
    /// Only jobs whose name contains this text (any case) or whose id starts with it.
    #[param(max_length = 200)]
    pub q: Option<String>,
}

impl JobFilter {
    fn query(self) -> Result<JobQuery, ApiError> {
        if let Some(tag) = &self.tag {
            crate::domain::labels::check_tag(tag)
                .map_err(|e| ApiError::bad_request("invalid_filter", e))?;
        }
        let search = self.q.map(|q| q.trim().to_owned()).filter(|q| !q.is_empty());
        if search.as_ref().is_some_and(|q| q.chars().count() > 200) {
            return Err(ApiError::bad_request("invalid_filter", "q: at most 200 characters"));
        }
        Ok(JobQuery { status: self.status, tag: self.tag, search })
    }
}

/// `?names=&max_points=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MetricsParams {
    /// Comma-separated metric names (default: every metric of the job).
    pub names: Option<String>,
    /// Most points returned per metric, 2 to 10000 (default 500). Longer histories are
    /// downsampled by LTTB (largest triangle three buckets): recorded points only, the first
    /// and the last always, and the ones that keep the curve's shape (a one-step spike stays).
    #[param(minimum = 2, maximum = 10000, default = 500)]
    pub max_points: Option<usize>,
}

/// One recorded value of a metric.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct MetricPoint {
    pub name: String,
    /// Steps done when the value was recorded (every phase counted).
    pub step: u64,
    pub value: f64,
    /// When it was recorded (RFC 3339).
    pub time: String,
}

/// A job's metrics history.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobMetrics {
    pub job_id: String,
    /// Whether any metric had more than `max_points` points and was downsampled.
    pub downsampled: bool,
    /// Ordered by name, then step.
    pub rows: Vec<MetricPoint>,
}

const DEFAULT_MAX_POINTS: usize = 500;
const MAX_POINTS_LIMIT: usize = 10_000;
/// How long `cancel` waits for a running job's worker to stop before answering.
const CANCEL_WAIT: Duration = Duration::from_secs(3);

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_job, list_jobs))
        .routes(routes!(get_job, update_job, delete_job))
        .routes(routes!(cancel_job))
        .routes(routes!(job_metrics))
        .routes(routes!(job_metrics_csv))
        .routes(routes!(job_metric_names))
}

/// Routes that stay open for long (exempt from the request timeout).
pub fn streams() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(job_events)).routes(routes!(job_log))
}

/// Queue a training job.
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs", request_body = CreateJob,
    responses(
        (status = 201, description = "Queued", body = Job),
        (status = 404, description = "A dataset does not exist", body = ErrorBody),
        (status = 422, description = "Invalid configuration or datasets that do not fit it \
            (`invalid_config`), a job whose estimated memory is above the server's \
            `--max-job-memory` (`job_too_large`; the message names the estimate and the limit), \
            or a malformed body (`invalid_body`)", body = ErrorBody),
    ))]
async fn create_job(
    State(state): State<AppState>,
    Json(request): Json<CreateJob>,
) -> Result<impl IntoResponse, ApiError> {
    let request = JobRequest {
        algorithm: request.algorithm,
        unlabeled_dataset: request.unlabeled_dataset.into(),
        non_preferred_dataset: request.non_preferred_dataset.map(Into::into),
        config: request.config,
        runner: request.runner,
        eval: request.eval,
        labels: JobLabels { name: request.name, tags: request.tags, notes: request.notes },
        max_attempts: request.max_attempts,
        register: request.register,
    };
    let limits = SubmitLimits {
        max_job_memory: state.config.max_job_memory,
        default_max_attempts: state.config.max_attempts,
    };
    let job = crate::jobs::submit(&state.store, request, limits).await?;
    state.jobs.wake();
    let location = format!("/v1/jobs/{}", job.id);
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(Job::from(job))))
}

/// List jobs, newest first; filtered by status, tag, or a text in the name or the id's start.
#[utoipa::path(get, path = "/v1/jobs", tag = "jobs", params(JobFilter, PageParams),
    responses(
        (status = 200, body = Page<Job>),
        (status = 400, description = "Bad status, tag, q or pagination", body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody),
    ))]
async fn list_jobs(
    State(state): State<AppState>,
    Query(filter): Query<JobFilter>,
    Query(page): Query<PageParams>,
) -> Result<Json<Page<Job>>, ApiError> {
    let query = filter.query()?;
    let page = page.resolve(&state.store, Listing::Jobs).await?;
    let (records, total) = state.store.list_jobs(&query, &page).await?;
    let jobs = records.into_iter().map(Job::from).collect();
    Ok(Json(Page::new(jobs, total, page, |j: &Job| &j.id)))
}

/// A job: status, resolved configuration, progress, result.
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = Job), (status = 404, body = ErrorBody)))]
async fn get_job(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Job>, ApiError> {
    Ok(Json(state.store.job(&id).await?.into()))
}

/// Rename, retag or annotate a job (JSON merge patch of `name`, `tags`, `notes`).
#[utoipa::path(patch, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    request_body = UpdateJob,
    responses(
        (status = 200, body = Job),
        (status = 404, body = ErrorBody),
        (status = 422, description = "A name, tag or notes that break their rules \
            (`invalid_labels`), or a malformed body (`invalid_body`)", body = ErrorBody),
    ))]
async fn update_job(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Json(patch): Json<UpdateJob>,
) -> Result<Json<Job>, ApiError> {
    let job = state.store.job(&id).await?;
    let labels = JobLabels {
        name: patch.name.unwrap_or(job.labels.name),
        tags: patch.tags.map(Option::unwrap_or_default).unwrap_or(job.labels.tags),
        notes: patch.notes.unwrap_or(job.labels.notes),
    }
    .validated()
    .map_err(|e| ApiError::unprocessable("invalid_labels", e))?;
    Ok(Json(state.store.update_job_labels(&id, &labels).await?.into()))
}

/// Delete a finished job: its metrics, checkpoint and log, and its policy with that policy's
/// evaluations (download the policy first to keep it). Refused while the job is queued or
/// running (cancel it first) or while an evaluation of its policy is.
#[utoipa::path(delete, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, body = ErrorBody),
        (status = 409, description = "The job is queued or running (`job_active`), or an \
            evaluation of its policy is, or a model version points at its policy \
            (`policy_in_use`)", body = ErrorBody),
    ))]
async fn delete_job(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_job(&id).await? {
        DeleteJobOutcome::Deleted { policy } => {
            if let Some(policy) = policy {
                state.policies.forget(&policy);
            }
            state.jobs.publish_api_change(JobEvent::Deleted { job_id: id.clone().into() });
            tracing::info!(job_id = %id, "job deleted");
            Ok(StatusCode::NO_CONTENT)
        }
        DeleteJobOutcome::NotFound => Err(ApiError::not_found("job", &id)),
        DeleteJobOutcome::Active(status) => Err(ApiError::conflict(
            "job_active",
            format!("job {id} is {status}; cancel it (POST /v1/jobs/{id}/cancel), then delete it"),
        )),
        DeleteJobOutcome::PolicyRegistered(versions) => Err(ApiError::conflict(
            "policy_in_use",
            format!(
                "the policy of job {id} is registered as {}; delete those versions first \
                 (DELETE /v1/models/{{name}}/versions/{{n}}), then the job",
                versions.join(", ")
            ),
        )),
        DeleteJobOutcome::PolicyInUse(evaluations) => Err(ApiError::conflict(
            "policy_in_use",
            format!(
                "the policy of job {id} has queued or running evaluation(s) {}; wait for them, \
                 then delete the job",
                evaluations.join(", ")
            ),
        )),
    }
}

/// Cancel a job. A queued job is cancelled at once; a running one stops at its next step
/// (normally within milliseconds; the answer waits up to 3 s for it) and keeps its metrics.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs", params(("id" = String, Path)),
    responses(
        (status = 200, description = "The job after the request (`cancelled`, or still \
            `running` with `cancel_requested` if its worker has not stopped yet)", body = Job),
        (status = 404, body = ErrorBody),
        (status = 409, description = "The job already finished (`job_finished`)", body = ErrorBody),
    ))]
async fn cancel_job(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Job>, ApiError> {
    match state.store.request_cancel(&id).await? {
        CancelOutcome::Cancelled => {
            let status = JobStatus::Cancelled;
            state.jobs.publish_api_change(JobEvent::Status { job_id: id.clone().into(), status });
            tracing::info!(job_id = %id, "queued job cancelled");
        }
        CancelOutcome::Requested => {
            state.jobs.cancel_running(&id);
            wait_until_stopped(&state.store, &id).await?;
        }
        CancelOutcome::AlreadyFinished(status) => {
            return Err(ApiError::conflict(
                "job_finished",
                format!("job {id} already finished with status {status}"),
            ));
        }
    }
    Ok(Json(state.store.job(&id).await?.into()))
}

async fn wait_until_stopped(store: &Store, id: &str) -> Result<(), StoreError> {
    let deadline = tokio::time::Instant::now() + CANCEL_WAIT;
    while tokio::time::Instant::now() < deadline {
        if store.job_status(id).await? != JobStatus::Running {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Ok(())
}

/// A job's metrics history (losses, alpha-hat, weight statistics), downsampled on the server.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics", tag = "jobs",
    params(("id" = String, Path), MetricsParams),
    responses(
        (status = 200, body = JobMetrics),
        (status = 400, description = "Bad max_points or names", body = ErrorBody),
        (status = 404, body = ErrorBody),
    ))]
async fn job_metrics(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(params): Query<MetricsParams>,
) -> Result<Json<JobMetrics>, ApiError> {
    let max_points = params.max_points.unwrap_or(DEFAULT_MAX_POINTS);
    if !(2..=MAX_POINTS_LIMIT).contains(&max_points) {
        return Err(ApiError::bad_request(
            "invalid_max_points",
            format!("max_points must be between 2 and {MAX_POINTS_LIMIT}, got {max_points}"),
        ));
    }
    let names = metric_names_param(params.names.as_deref());
    state.store.job(&id).await?;
    let rows = state.store.job_metrics(&id, names.as_deref()).await?;
    let (rows, downsampled) = downsample(rows, max_points);
    Ok(Json(JobMetrics { job_id: id, downsampled, rows }))
}

fn metric_names_param(names: Option<&str>) -> Option<Vec<String>> {
    names.map(|names| {
        names.split(',').map(str::trim).filter(|n| !n.is_empty()).map(str::to_owned).collect()
    })
}

/// `?names=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct CsvParams {
    /// Comma-separated metric names (default: every metric of the job).
    pub names: Option<String>,
}

/// A job's whole metrics history as CSV (`name,step,value,time`, every recorded point, ordered
/// by name then step), as a file download.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics.csv", tag = "jobs",
    params(("id" = String, Path), CsvParams),
    responses(
        (status = 200, description = "CSV with a header line", content_type = "text/csv",
            body = String),
        (status = 404, body = ErrorBody),
    ))]
async fn job_metrics_csv(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(params): Query<CsvParams>,
) -> Result<impl IntoResponse, ApiError> {
    let names = metric_names_param(params.names.as_deref());
    state.store.job(&id).await?;
    let rows = state.store.job_metrics(&id, names.as_deref()).await?;
    let mut csv = String::from("name,step,value,time\n");
    for row in &rows {
        // Metric names are identifiers (letters, digits, `_`, `/`): no quoting needed.
        csv.push_str(&format!("{},{},{},{}\n", row.name, row.step, row.value, row.time));
    }
    super::attachment(&format!("job-{id}-metrics.csv"), "text/csv; charset=utf-8", csv)
}

/// One metric a job recorded.
#[derive(Debug, Serialize, ToSchema)]
pub struct MetricName {
    pub name: String,
    /// Recorded points (before any downsampling).
    pub points: u64,
    pub first_step: u64,
    pub last_step: u64,
}

/// The names of the metrics a job recorded, with their point counts and step ranges.
#[utoipa::path(get, path = "/v1/jobs/{id}/metrics/names", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 200, body = Vec<MetricName>), (status = 404, body = ErrorBody)))]
async fn job_metric_names(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Vec<MetricName>>, ApiError> {
    state.store.job(&id).await?;
    let names = state.store.metric_names(&id).await?;
    Ok(Json(
        names
            .into_iter()
            .map(|m| MetricName {
                name: m.name,
                points: m.points as u64,
                first_step: m.first_step as u64,
                last_step: m.last_step as u64,
            })
            .collect(),
    ))
}

/// `?after=&limit=&follow=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct LogParams {
    /// Only lines after this line number (default 0: from the first line).
    #[param(minimum = 0)]
    pub after: Option<u64>,
    /// Most lines returned, 1 to 1000 (default 1000; without `follow`).
    #[param(minimum = 1, maximum = 1000, default = 1000)]
    pub limit: Option<u32>,
    /// Stream the lines as Server-Sent Events (`event: log`), new ones as they are written,
    /// until the job has finished and its last line was sent.
    #[serde(default)]
    pub follow: bool,
}

/// A line of a job's log.
#[derive(Debug, Serialize, ToSchema)]
pub struct LogLine {
    /// The line's number in the job's log, from 1.
    pub seq: u64,
    /// When it was written (RFC 3339).
    pub time: String,
    /// `info`, `warn` or `error`.
    pub level: String,
    /// The worker that wrote it.
    pub worker: String,
    pub message: String,
}

impl From<LogRow> for LogLine {
    fn from(row: LogRow) -> Self {
        LogLine {
            seq: row.seq as u64,
            time: row.time,
            level: row.level,
            worker: row.worker,
            message: row.message,
        }
    }
}

const LOG_LIMIT: u32 = 1000;

/// A job's log: what its workers wrote about it (claimed, resumed from a checkpoint, phases,
/// alpha-hat, evaluations, checkpoints, how it ended, why it failed). JSON lines in order, or
/// with `follow=true` an event stream that ends when the job has finished.
#[utoipa::path(get, path = "/v1/jobs/{id}/logs", tag = "jobs",
    params(("id" = String, Path), LogParams),
    responses(
        (status = 200, description = "The lines (JSON), or with `follow=true` a server-sent \
            event stream of `event: log` events whose data is a LogLine",
         content(
            (Vec<LogLine> = "application/json"),
            (String = "text/event-stream"),
         )),
        (status = 400, description = "Bad `after` or `limit`", body = ErrorBody),
        (status = 404, body = ErrorBody),
    ))]
async fn job_log(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(params): Query<LogParams>,
    headers: axum::http::HeaderMap,
) -> Result<axum::response::Response, ApiError> {
    let limit = params.limit.unwrap_or(LOG_LIMIT);
    if !(1..=LOG_LIMIT).contains(&limit) {
        return Err(ApiError::bad_request(
            "invalid_limit",
            format!("limit must be between 1 and {LOG_LIMIT}, got {limit}"),
        ));
    }
    let after = i64::try_from(params.after.unwrap_or(0))
        .map_err(|_| ApiError::bad_request("invalid_after", "after must be at most 2^63 - 1"))?;
    state.store.job(&id).await?;
    if !params.follow {
        let rows = state.store.job_log(&id, after, limit).await?;
        return Ok(Json(rows.into_iter().map(LogLine::from).collect::<Vec<_>>()).into_response());
    }
    let permit = stream_permit(&state)?;
    // A client reconnecting (a stream ends after STREAM_LIFETIME) resumes after the last line
    // it saw: each line's event id is its `seq`. Subscribed before anything is read.
    let after = last_event_id(&headers).unwrap_or(after);
    let rows = super::log_follower::follow(state.store.clone(), state.jobs.subscribe(), id, after);
    let lines = rows.map(|row| {
        let seq = row.seq.to_string();
        json_event("log", &LogLine::from(row)).id(seq)
    });
    Ok(Sse::new(bounded(lines, &state, permit)).keep_alive(KeepAlive::default()).into_response())
}

/// Per metric (rows come ordered by name, then step): at most `max_points` points, chosen by
/// LTTB ([`crate::lttb`]): real rows with their own step and time, the first and the last
/// exactly, and the points that shape the curve (spikes included).
fn downsample(rows: Vec<MetricRow>, max_points: usize) -> (Vec<MetricPoint>, bool) {
    let mut out = Vec::with_capacity(rows.len().min(max_points * 16));
    let mut downsampled = false;
    for series in rows.chunk_by(|a, b| a.name == b.name) {
        if series.len() <= max_points {
            out.extend(series.iter().map(point));
            continue;
        }
        downsampled = true;
        let steps: Vec<f64> = series.iter().map(|r| r.step as f64).collect();
        let values: Vec<f64> = series.iter().map(|r| r.value).collect();
        out.extend(
            lttb_indices(&steps, &values, max_points).into_iter().map(|i| point(&series[i])),
        );
    }
    (out, downsampled)
}

fn point(row: &MetricRow) -> MetricPoint {
    MetricPoint {
        name: row.name.clone(),
        step: row.step as u64,
        value: row.value,
        time: row.time.clone(),
    }
}

/// Server-Sent Events of a job: first a `status` event with the job resource, then `progress`
/// events (a [`JobProgress`], about twice a second while it runs) and a `status` event with the
/// job at every status change. The stream ends after a final status (`succeeded`, `failed`,
/// `cancelled`) or when the server shuts down.
#[utoipa::path(get, path = "/v1/jobs/{id}/events", tag = "jobs", params(("id" = String, Path)),
    responses(
        (status = 200, description = "`event: status` (data: Job) and `event: progress` \
            (data: JobProgress); the stream ends after a final status, or with `event: deleted` \
            (data: `{\"id\": ...}`) once the job is deleted", content_type = "text/event-stream", body = String),
        (status = 404, body = ErrorBody),
    ))]
async fn job_events(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let permit = stream_permit(&state)?;
    // Subscribe before reading the job, so no change between the two is missed.
    let receiver = state.jobs.subscribe();
    let job = Job::from(state.store.job(&id).await?);
    let finished = job.status.is_final();
    let first = status_event(&job);
    let updates = futures::stream::unfold(
        (receiver, state.store.clone(), id, finished),
        |(mut receiver, store, id, finished)| async move {
            if finished {
                return None;
            }
            let event = next_event(&mut receiver, &store, &id).await?;
            let finished = match &event {
                Update::Status(job) => job.status.is_final(),
                Update::Progress(_) => false,
                Update::Deleted => true,
            };
            let event = match event {
                Update::Progress(progress) => json_event("progress", &progress),
                Update::Status(job) => status_event(&job),
                Update::Deleted => json_event("deleted", &serde_json::json!({"id": id})),
            };
            Some((event, (receiver, store, id, finished)))
        },
    );
    let stream = futures::stream::once(std::future::ready(first)).chain(updates);
    Ok(Sse::new(bounded(stream, &state, permit)).keep_alive(KeepAlive::default()))
}

enum Update {
    Progress(JobProgress),
    Status(Box<Job>),
    /// The job is gone (deleted here, or on another API node).
    Deleted,
}

/// How long a stream waits for an event before it checks that its job still exists: a job
/// deleted through another API node announces nothing here.
const STREAM_CHECK: Duration = Duration::from_secs(5);

/// The next event of job `id`; None when the runner is gone or the job cannot be read.
async fn next_event(
    receiver: &mut broadcast::Receiver<JobEvent>,
    store: &Store,
    id: &str,
) -> Option<Update> {
    loop {
        let Ok(received) = tokio::time::timeout(STREAM_CHECK, receiver.recv()).await else {
            match store.job_status(id).await {
                Err(StoreError::NotFound { .. }) => return Some(Update::Deleted),
                _ => continue,
            }
        };
        match received {
            Ok(event) if event.job_id().as_str() != id => continue,
            Ok(JobEvent::Progress { progress, .. }) => return Some(Update::Progress(progress)),
            Ok(JobEvent::Deleted { .. }) => return Some(Update::Deleted),
            Ok(JobEvent::Status { .. }) => match store.job(id).await {
                Ok(job) => return Some(Update::Status(Box::new(job.into()))),
                Err(StoreError::NotFound { .. }) => return Some(Update::Deleted),
                Err(_) => return None,
            },
            // A slow reader skipped some progress; the next event brings it up to date.
            Err(broadcast::error::RecvError::Lagged(_)) => continue,
            Err(broadcast::error::RecvError::Closed) => return None,
        }
    }
}

/// How long one event stream stays open: clients reconnect (an EventSource does so by itself,
/// `Last-Event-ID` resumes a log), so a slot held by a forgotten tab turns over.
const STREAM_LIFETIME: Duration = Duration::from_secs(15 * 60);

/// A slot for one more event stream, or 503 `too_many_streams`.
fn stream_permit(state: &AppState) -> Result<tokio::sync::OwnedSemaphorePermit, ApiError> {
    state.streams.clone().try_acquire_owned().map_err(|_| {
        ApiError::unavailable(
            "too_many_streams",
            format!(
                "{} event streams are open already (--max-streams); retry shortly",
                state.config.max_streams
            ),
        )
    })
}

/// `events` ended by shutdown or after [`STREAM_LIFETIME`], holding `permit` while it runs.
fn bounded(
    events: impl Stream<Item = Event> + Send + 'static,
    state: &AppState,
    permit: tokio::sync::OwnedSemaphorePermit,
) -> impl Stream<Item = Result<Event, Infallible>> + Send + 'static {
    events
        .take_until(state.shutdown.clone().cancelled_owned())
        .take_until(tokio::time::sleep(STREAM_LIFETIME))
        .map(move |event| {
            let _held = &permit;
            Ok(event)
        })
}

/// The `Last-Event-ID` a reconnecting event-stream client sends.
fn last_event_id(headers: &axum::http::HeaderMap) -> Option<i64> {
    headers.get("last-event-id")?.to_str().ok()?.trim().parse().ok().filter(|id| *id >= 0)
}

fn status_event(job: &Job) -> Event {
    json_event("status", job)
}

fn json_event(name: &str, data: &impl Serialize) -> Event {
    Event::default().event(name).json_data(data).unwrap_or_else(|e| {
        tracing::error!(error = %e, "cannot serialise an event");
        Event::default().event("error").data("event serialisation failed")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(name: &str, values: &[f64]) -> Vec<MetricRow> {
        values
            .iter()
            .enumerate()
            .map(|(i, &value)| MetricRow {
                name: name.into(),
                step: (i as i64 + 1) * 10,
                value,
                time: format!("t{i}"),
            })
            .collect()
    }

    #[test]
    fn short_series_are_returned_whole() {
        let rows = series("loss", &[1.0, 2.0, 3.0]);
        let (out, downsampled) = downsample(rows.clone(), 3);
        assert!(!downsampled);
        assert_eq!(out, rows.iter().map(point).collect::<Vec<_>>());
    }

    #[test]
    fn long_series_keep_recorded_points_with_their_spikes_and_both_ends() {
        // 1,000 points of a slowly falling loss with one spike, into 20: the spike and both
        // ends are kept as recorded (step, value and time of the same row).
        let mut values: Vec<f64> = (0..1000).map(|i| 2.0 - f64::from(i) / 1000.0).collect();
        values[617] = 40.0;
        let mut rows = series("a", &values);
        rows.extend(series("b", &[5.0, 6.0]));
        let (out, downsampled) = downsample(rows.clone(), 20);
        assert!(downsampled);
        let a: Vec<&MetricPoint> = out.iter().filter(|p| p.name == "a").collect();
        assert_eq!(a.len(), 20);
        for p in &a {
            let row = rows.iter().find(|r| r.name == "a" && r.step as u64 == p.step).unwrap();
            assert_eq!((p.value, &p.time), (row.value, &row.time));
        }
        assert_eq!((a[0].step, a[19].step), (10, 10_000));
        assert!(a.iter().any(|p| p.value == 40.0 && p.time == "t617"));
        assert_eq!(out.iter().filter(|p| p.name == "b").count(), 2);
    }
}
