//! `/v1/jobs`: queue a training run, follow it, cancel it. The work itself happens in
//! [`crate::jobs`]. This file is the resource (create, list, read, edit, delete, cancel);
//! [`metrics`] serves a job's metrics history (JSON, CSV, names) and [`streams`] what stays open
//! (the event stream and the log).

mod metrics;
pub mod streams;

use std::time::Duration;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::algo::Algorithm;
use crate::domain::labels::{JobNameSchema, JobNotesSchema, TagSchema};
use crate::domain::model::Registration;
use crate::domain::JobId;
use crate::domain::{
    rfc3339, EvalOptions, JobLabels, JobProgress, JobRecord, JobStatus, RunnerOptions,
};
use crate::jobs::{JobEvent, JobRequest, SubmitLimits};
use crate::store::jobs::{CancelOutcome, DeleteJobOutcome, JobQuery};
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
    /// `normalize_observations` (the statistics travel with the policy), `threads` (1 to 64:
    /// the threads of one training step, part of the arithmetic like the seed; unset, the
    /// server's `--job-threads`, at most one per 128 rows of the batch). `safedice`:
    /// `discriminator_iterations` (unless set: `iterations` in the `service` preset, a tenth in the
    /// others), `lr_discriminator`,
    /// `lr_nu`, `discriminator_gp`, `nu_gp`, `gamma`, `terminal_handling` (`none`, `mask`,
    /// `reset`, `absorbing`), `standardize_reward`, `alpha_hat_estimator` (`bbe`: Best Bin
    /// Estimation on held-out episodes, the `service` default; `min`: the paper's minimum over
    /// D^U), `alpha_hat_quantile` (`min` only; 0: the minimum itself), `undefined_reward`
    /// (`exclude`: rows where Eq. 10 is −∞ get no weight, the `service` default; `floor`),
    /// `excluded_reward_gap` (with `exclude`: how far below the lowest defined reward such rows
    /// sit, before `reward_scale`; 30 by default, a weight of `e^{−30·reward_scale}`),
    /// `uniform_fallback` (train as BC when held-out data cannot tell D^N from D^U, or alpha-hat is 0 without `standardize_reward`, which weights by Eq. 10's limit as α → 0; `bbe`
    /// only), `calibrate_discriminator` (`bbe` only), `bbe_unlabeled_rows` (`bbe` only: the
    /// rows of D^U its ratio reads, `held_out` or `all`), `alpha_hat_point` (`bbe` only:
    /// `estimate`, the bin's ratio, `lower`, its interval's lower end, or `episodes_lower`, the lower end counting episodes), `reward_scale` (multiplies Eq. 10's
    /// reward after the standardisation; 1 by default), `cross_fit` (`bbe` only: two
    /// discriminators on two folds of D^U's episodes, each row scored by the one that did not
    /// train on it, and the safety head the mean of both; on in `service`), `cross_fit_labeled`
    /// (with `cross_fit`: D^N's episodes in two folds too, so alpha-hat and the held-out AUC read
    /// every row of D^N; off by default), `cross_fit_folds` (with `cross_fit`: 2 to 10 folds and
    /// as many discriminators, each trained on all folds but the one it scores; above 2 D^N is
    /// in folds too; 2 by default),
    /// `policy_uniform_share` (0 to 1: the share of each policy step's weight spread evenly over
    /// its rows, BC's weights, so states Eq. 37's weights leave empty still get D^U's behaviour;
    /// 0.05 in `service`; 0: Eq. 37 as written), `top_bin` (`bbe` only: what Eq. 10 reads on the rows of D^U in
    /// Best Bin Estimation's bin: `row_logits`, each row's own, by default; `bin_ratio`, at least
    /// the bin's density ratio; `bin_ratio_own_scale`, the same with the reward standardised on
    /// the rows' own logits, so that only the bin's rewards move; `ruled_out`, none of them
    /// allowed), `auc_interval` (`bbe` only: how the held-out AUC's interval, the uniform
    /// fallback's first test, counts its sample: `rows`, each row a draw, by default;
    /// `episodes`, DeLong's variance times each set's design effect from the rows'
    /// intra-episode correlation), `kept_share_test` (`bbe` only: also train as BC when the
    /// interval of the share of held-out D^N's mass that Eq. 10's weights keep reaches 1; off by
    /// default), `weighting_strength_from_auc` (`bbe` only: `reward_scale` times the share of the held-out
    /// AUC's excess over 0.5 that its interval's lower end keeps; off by default),
    /// `pool_scores_by_episode` (with `bbe` and `cross_fit`: Eq. 10 reads each row of D^U at its
    /// episode's mean cross-fitted logit, recalibrated, so a whole episode's evidence weighs it;
    /// alpha-hat and the fallback still read each row's own; on in `service`), `ess_warning_fraction`,
    /// `discriminator_early_stopping` (hold out a fifth of
    /// the data and stop the discriminator when its held-out loss stops improving;
    /// `discriminator_iterations` is then its most). `dwbc`: `eta`, `lr_discriminator`, `discriminator_gp`.
    /// `ppl`: `reward_model_iterations`, `lr_reward_model`, `pairs_per_batch`,
    /// `segment_length`, `ppl_weight` (`raw`, `sigmoid`). `dexperts`: `alpha`,
    /// `non_preferred_term` (continuous actions: `kernel`, Eq. 45's D^N term bounded, the
    /// `service` default; `log_likelihood`, Eq. 45 as written). `bc`: no further keys.
    #[schema(value_type = Object, example = json!({"preset": "service", "iterations": 20000, "seed": 0}))]
    pub config: Option<serde_json::Value>,
    /// Job-runner options (how often metrics and checkpoints are stored), beside the algorithm's
    /// configuration: they never change the trained policy.
    #[schema(value_type = Option<RunnerOptions>)]
    pub runner: Option<serde_json::Value>,
    /// Evaluate the policy on a built-in environment every `every` policy-learning steps and at
    /// the end (without `every`: only at the end); the paper's metrics go to the metrics history
    /// as `eval/...` (absent: no evaluation). The environment's spaces must match the datasets'.
    #[schema(value_type = Option<EvalOptions>)]
    pub eval: Option<serde_json::Value>,
    /// A name for people, at most 200 characters without control characters (the dashboard
    /// shows it instead of the id).
    #[schema(
        max_length = 200,
        pattern = "^[^\\x00-\\x1F\\x7F-\\x9F\\u061C\\u200E\\u200F\\u202A-\\u202E\\u2066-\\u2069]*$"
    )]
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
    #[schema(value_type = Option<JobNameSchema>)]
    pub name: Option<Option<String>>,
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<Vec<TagSchema>>)]
    pub tags: Option<Option<Vec<String>>>,
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<JobNotesSchema>)]
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
    /// Steps of the phase before policy learning (SafeDICE's discriminator, PPL's reward
    /// model), counted in `progress` and in the metrics' `step`: a metric at step `s` is policy
    /// iteration `s - pretraining_steps`. 0 for the algorithms without one.
    pub pretraining_steps: u64,
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
            pretraining_steps: job.config.pretraining_steps(),
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

/// How long `cancel` waits for a running job's worker to stop before answering.
const CANCEL_WAIT: Duration = Duration::from_secs(3);

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_job, list_jobs))
        .routes(routes!(get_job, update_job, delete_job))
        .routes(routes!(cancel_job))
        .merge(metrics::router())
}

/// Routes that stay open for long (exempt from the request timeout).
pub fn streams() -> OpenApiRouter<AppState> {
    streams::router()
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
        job_threads: state.config.job_threads(),
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
    Path(id): Path<JobId>,
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
    Path(id): Path<JobId>,
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
    Path(id): Path<JobId>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_job(&id).await? {
        DeleteJobOutcome::Deleted { policy } => {
            if let Some(policy) = policy {
                state.serving.policies.forget(&policy);
            }
            state.jobs.publish_api_change(JobEvent::Deleted { job_id: id.clone() });
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
    Path(id): Path<JobId>,
) -> Result<Json<Job>, ApiError> {
    match state.store.request_cancel(&id).await? {
        CancelOutcome::Cancelled => {
            let status = JobStatus::Cancelled;
            state.jobs.publish_api_change(JobEvent::Status { job_id: id.clone(), status });
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

async fn wait_until_stopped(store: &Store, id: &JobId) -> Result<(), StoreError> {
    let deadline = tokio::time::Instant::now() + CANCEL_WAIT;
    while tokio::time::Instant::now() < deadline {
        if store.job_status(id).await? != JobStatus::Running {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Ok(())
}
