//! `/v1/experiments`: a grid of algorithms × seeds on one pair of datasets, queued as ordinary
//! jobs (named, tagged `experiment=<id>`, in the fleet's queue), and its results: the paper's
//! metrics per algorithm as mean ± standard error over the seeds, with the per-seed values,
//! under one evaluation protocol at a time (the protocols found are listed beside them).

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::pagination::{Page, PageParams};
use super::results::requested_protocol;
use super::{ApiError, AppState};
use crate::algo::Algorithm;
use crate::domain::experiment::{Arm, ExperimentRecord};
use crate::domain::labels::TagSchema;
use crate::domain::{rfc3339, EvalProtocol, ExperimentId, JobStatus};
use crate::jobs::experiments::{self, ExperimentRequest};
use crate::jobs::results::{self, ArmResult, JobResult, ProtocolChoice, ProtocolResult};
use crate::jobs::{JobEvent, SubmitLimits};
use crate::store::experiments::DeleteExperimentOutcome;
use crate::store::jobs::CancelOutcome;
use crate::store::Listing;

/// An entry of `algorithms`: an algorithm's name, or the algorithm with a label and its own
/// configuration keys.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(untagged)]
pub enum ArmInput {
    Name(Algorithm),
    Arm(Arm),
}

/// `POST /v1/experiments` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateExperiment {
    /// For people; the jobs are named `<name> · <label> · seed <s>`.
    pub name: Option<String>,
    pub unlabeled_dataset: String,
    /// Used by the algorithms that need Dᴺ (never given to BC).
    pub non_preferred_dataset: Option<String>,
    /// E.g. `["safedice", "bc", {"algorithm": "dwbc", "label": "dwbc-eta", "config": {...}}]`.
    #[schema(min_items = 1)]
    pub algorithms: Vec<ArmInput>,
    /// The seeds (1-50, distinct), or `seed_count` for 0..n.
    pub seeds: Option<Vec<u64>>,
    pub seed_count: Option<u32>,
    /// Configuration keys every algorithm shares (e.g. `{"iterations": 20000}`); not `seed`.
    #[schema(value_type = Option<Object>)]
    pub config: Option<serde_json::Value>,
    /// Each job's in-training evaluation, as a job's `eval` block: its metrics are the
    /// experiment's results until an on-demand evaluation of the policy exists.
    #[schema(value_type = Option<Object>)]
    pub eval: Option<serde_json::Value>,
    /// Tags every job gets besides `experiment=<id>`.
    #[serde(default)]
    #[schema(value_type = Vec<TagSchema>)]
    pub tags: Vec<String>,
}

/// How many of the grid's jobs are in each status.
#[derive(Debug, Default, Serialize, ToSchema)]
pub struct GridProgress {
    pub total: usize,
    pub queued: usize,
    pub running: usize,
    pub succeeded: usize,
    pub failed: usize,
    pub cancelled: usize,
    /// Given up after their workers vanished `max_attempts` times.
    pub discarded: usize,
}

/// An experiment with its jobs and results.
#[derive(Debug, Serialize, ToSchema)]
pub struct Experiment {
    pub id: String,
    pub name: Option<String>,
    pub unlabeled_dataset: String,
    pub non_preferred_dataset: Option<String>,
    pub algorithms: Vec<Arm>,
    pub seeds: Vec<u64>,
    #[schema(value_type = Option<Object>)]
    pub config: Option<serde_json::Value>,
    #[schema(value_type = Option<Object>)]
    pub eval: Option<serde_json::Value>,
    pub tags: Vec<String>,
    pub created_at: String,
    pub progress: GridProgress,
    /// The evaluation protocol `jobs[].metrics` and `results` are under: the one asked for with
    /// `?protocol=`, else the newest protocol every job with a result has, else the one most
    /// jobs have. Absent while no job has a result.
    pub protocol: Option<EvalProtocol>,
    /// Why `protocol` is the one shown.
    pub protocol_choice: Option<ProtocolChoice>,
    /// Every protocol a job of the experiment has a result under, most jobs first. More than
    /// one: the results are mixed, and each is a view of its own (`?protocol=<key>`).
    pub protocols: Vec<ProtocolResult>,
    /// Every job: its arm, seed, status, policy, the protocols it has results under, and its
    /// metrics under `protocol`.
    pub jobs: Vec<JobResult>,
    /// Per algorithm: mean ± standard error over the seeds with metrics under `protocol`.
    pub results: Vec<ArmResult>,
}

/// `?protocol=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ProtocolParam {
    /// The `key` of one of the experiment's `protocols` to show the results under.
    pub protocol: Option<String>,
}

/// An experiment as lists show it.
#[derive(Debug, Serialize, ToSchema)]
pub struct ExperimentSummary {
    pub id: String,
    pub name: Option<String>,
    pub algorithms: Vec<String>,
    pub seeds: Vec<u64>,
    pub created_at: String,
    pub progress: GridProgress,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_experiment, list_experiments))
        .routes(routes!(get_experiment, delete_experiment))
        .routes(routes!(cancel_experiment))
        .routes(routes!(experiment_csv))
}

fn progress(jobs: &[JobResult]) -> GridProgress {
    let mut progress = GridProgress::default();
    for job in jobs {
        progress.count(job.status, 1);
    }
    progress
}

impl GridProgress {
    fn count(&mut self, status: JobStatus, n: usize) {
        let slot = match status {
            JobStatus::Queued => &mut self.queued,
            JobStatus::Running => &mut self.running,
            JobStatus::Succeeded => &mut self.succeeded,
            JobStatus::Failed => &mut self.failed,
            JobStatus::Cancelled => &mut self.cancelled,
            JobStatus::Discarded => &mut self.discarded,
        };
        *slot += n;
        self.total += n;
    }
}

/// The experiment with its results under the protocol `key` names (else the default one).
async fn resource(
    state: &AppState,
    record: ExperimentRecord,
    key: Option<&str>,
) -> Result<Experiment, ApiError> {
    let scores = results::scores(&state.store, &record).await?;
    let requested = key.map(|key| requested_protocol(&scores, key)).transpose()?;
    let view = scores.view(requested);
    let spec = record.spec;
    Ok(Experiment {
        id: record.id.into_string(),
        name: record.name,
        unlabeled_dataset: spec.unlabeled_dataset,
        non_preferred_dataset: spec.non_preferred_dataset,
        algorithms: spec.arms,
        seeds: spec.seeds,
        config: spec.config,
        eval: spec.eval,
        tags: spec.tags,
        created_at: rfc3339(&record.created_at),
        progress: progress(&view.jobs),
        protocol: view.protocol,
        protocol_choice: view.choice,
        protocols: scores.protocols(),
        jobs: view.jobs,
        results: view.arms,
    })
}

/// Queue an experiment: every algorithm × every seed as a job, all or none (each job is
/// validated as `POST /v1/jobs` would; a refusal names the entry and the field).
#[utoipa::path(post, path = "/v1/experiments", tag = "experiments", request_body = CreateExperiment,
    responses(
        (status = 201, body = Experiment, headers(("location" = String))),
        (status = 404, description = "A dataset does not exist", body = ErrorBody),
        (status = 422, description = "No algorithm, an unknown one, 0 or repeated seeds, more \
            than 100 jobs, a bad configuration (`invalid_config`, naming `algorithms[i]`), bad \
            tags (`invalid_labels`), a job above --max-job-memory (`job_too_large`)",
         body = ErrorBody),
    ))]
async fn create_experiment(
    State(state): State<AppState>,
    Json(body): Json<CreateExperiment>,
) -> Result<impl IntoResponse, ApiError> {
    let arms = body
        .algorithms
        .into_iter()
        .map(|arm| match arm {
            ArmInput::Name(algorithm) => Arm { label: None, algorithm, config: None },
            ArmInput::Arm(arm) => arm,
        })
        .collect();
    let request = ExperimentRequest {
        name: body.name,
        unlabeled_dataset: body.unlabeled_dataset,
        non_preferred_dataset: body.non_preferred_dataset,
        arms,
        seeds: body.seeds,
        seed_count: body.seed_count,
        config: body.config,
        eval: body.eval,
        tags: body.tags,
    };
    let limits = SubmitLimits {
        max_job_memory: state.config.max_job_memory,
        default_max_attempts: state.config.max_attempts,
        job_threads: state.config.job_threads(),
    };
    let record = experiments::submit_experiment(&state.store, request, limits).await?;
    state.jobs.wake();
    let location = format!("/v1/experiments/{}", record.id);
    let experiment = resource(&state, record, None).await?;
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(experiment)))
}

/// List experiments, newest first.
#[utoipa::path(get, path = "/v1/experiments", tag = "experiments", params(PageParams),
    responses((status = 200, body = Page<ExperimentSummary>), (status = 400, body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody)))]
async fn list_experiments(
    State(state): State<AppState>,
    Query(page): Query<PageParams>,
) -> Result<Json<Page<ExperimentSummary>>, ApiError> {
    let page = page.resolve(&state.store, Listing::Experiments).await?;
    let (records, total) = state.store.list_experiments(&page).await?;
    let mut items = Vec::with_capacity(records.len());
    for r in records {
        let mut progress = GridProgress::default();
        for (status, n) in state.store.experiment_status_counts(&r.id).await? {
            progress.count(status, n as usize);
        }
        items.push(ExperimentSummary {
            algorithms: r.spec.arms.iter().map(Arm::label).collect(),
            seeds: r.spec.seeds,
            created_at: rfc3339(&r.created_at),
            name: r.name,
            id: r.id.into_string(),
            progress,
        });
    }
    Ok(Json(Page::new(items, total, page, |e: &ExperimentSummary| &e.id)))
}

/// An experiment: its grid, progress, every job's metrics and each algorithm's mean ± SE under
/// one evaluation protocol, and every protocol its jobs have results under.
#[utoipa::path(get, path = "/v1/experiments/{id}", tag = "experiments",
    params(("id" = String, Path), ProtocolParam),
    responses((status = 200, body = Experiment),
        (status = 404, description = "No such experiment, or a `protocol` no job of it has a \
            result under (`not_found`, naming the protocols there are)", body = ErrorBody)))]
async fn get_experiment(
    State(state): State<AppState>,
    Path(id): Path<ExperimentId>,
    Query(param): Query<ProtocolParam>,
) -> Result<Json<Experiment>, ApiError> {
    let record = state.store.experiment(&id).await?;
    Ok(Json(resource(&state, record, param.protocol.as_deref()).await?))
}

/// Cancel every queued or running job of the experiment (finished ones stay).
#[utoipa::path(post, path = "/v1/experiments/{id}/cancel", tag = "experiments",
    params(("id" = String, Path)),
    responses((status = 200, body = Experiment), (status = 404, body = ErrorBody)))]
async fn cancel_experiment(
    State(state): State<AppState>,
    Path(id): Path<ExperimentId>,
) -> Result<Json<Experiment>, ApiError> {
    let record = state.store.experiment(&id).await?;
    for job in state.store.experiment_jobs(&id).await? {
        match state.store.request_cancel(&job.id).await? {
            CancelOutcome::Cancelled => {
                let status = JobStatus::Cancelled;
                let event = JobEvent::Status { job_id: job.id.clone(), status };
                state.jobs.publish_api_change(event);
            }
            CancelOutcome::Requested => state.jobs.cancel_running(&job.id),
            CancelOutcome::AlreadyFinished(_) => {}
        }
    }
    tracing::info!(experiment_id = %id, "experiment cancelled");
    Ok(Json(resource(&state, record, None).await?))
}

/// Delete an experiment whose jobs have all ended, with its jobs (their metrics, logs,
/// policies and evaluations). Refused while a job of it is queued or running.
#[utoipa::path(delete, path = "/v1/experiments/{id}", tag = "experiments",
    params(("id" = String, Path)),
    responses((status = 204, description = "Deleted"), (status = 404, body = ErrorBody),
        (status = 409, description = "Jobs of it are queued or running (`experiment_active`), \
            or a model version points at one of its policies (`policy_in_use`)",
         body = ErrorBody)))]
async fn delete_experiment(
    State(state): State<AppState>,
    Path(id): Path<ExperimentId>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_experiment(&id).await? {
        DeleteExperimentOutcome::Deleted { policies, jobs } => {
            for policy in &policies {
                state.serving.policies.forget(policy);
            }
            for job in jobs {
                state.jobs.publish_api_change(JobEvent::Deleted { job_id: job.into() });
            }
            tracing::info!(experiment_id = %id, "experiment deleted");
            Ok(StatusCode::NO_CONTENT)
        }
        DeleteExperimentOutcome::NotFound => Err(ApiError::not_found("experiment", &id)),
        DeleteExperimentOutcome::Active(jobs) => Err(ApiError::conflict(
            "experiment_active",
            format!(
                "job(s) {} of experiment {id} are queued or running; cancel the experiment \
                 (POST /v1/experiments/{id}/cancel), then delete it",
                jobs.join(", ")
            ),
        )),
    }
}

/// The results as CSV, long format (one value per row) under every protocol: each job's
/// metrics (`stat` `value`, `seed` a number) and each algorithm's `mean`, `se` and `n` over its
/// seeds (`seed` and `job_id` empty), one aggregate per protocol, never across two.
#[utoipa::path(get, path = "/v1/experiments/{id}/results.csv", tag = "experiments",
    params(("id" = String, Path)),
    responses((status = 200,
        description = "CSV: arm,algorithm,protocol,stat,seed,job_id,metric,value",
        content_type = "text/csv", body = String), (status = 404, body = ErrorBody)))]
async fn experiment_csv(
    State(state): State<AppState>,
    Path(id): Path<ExperimentId>,
) -> Result<Response, ApiError> {
    let record = state.store.experiment(&id).await?;
    let scores = results::scores(&state.store, &record).await?;
    let mut csv = String::from("arm,algorithm,protocol,stat,seed,job_id,metric,value\n");
    let algorithm_of = |label: &str| {
        let arm = record.spec.arms.iter().find(|a| a.label() == label);
        arm.map(|a| a.algorithm.to_string()).unwrap_or_default()
    };
    for protocol in scores.protocols() {
        let key = csv_field(&protocol.protocol.key);
        let jobs = scores.jobs_under(Some(&protocol.protocol.key));
        for job in &jobs {
            let (arm, algorithm) = (csv_field(&job.arm), algorithm_of(&job.arm));
            for (metric, value) in &job.metrics {
                let (seed, job_id) = (job.seed, &job.job_id);
                csv.push_str(&format!(
                    "{arm},{algorithm},{key},value,{seed},{job_id},{metric},{value}\n"
                ));
            }
        }
        for arm in scores.arms_of(&jobs) {
            let (label, algorithm) = (csv_field(&arm.label), &arm.algorithm);
            for (metric, summary) in &arm.metrics {
                let stats = [("mean", Some(summary.mean)), ("se", summary.se)];
                for (stat, value) in stats.into_iter().filter_map(|(s, v)| Some((s, v?))) {
                    csv.push_str(&format!("{label},{algorithm},{key},{stat},,,{metric},{value}\n"));
                }
                csv.push_str(&format!("{label},{algorithm},{key},n,,,{metric},{}\n", summary.n));
            }
        }
    }
    let disposition = format!("attachment; filename=\"experiment-{id}.csv\"");
    Ok((
        [(header::CONTENT_TYPE, "text/csv".to_owned()), (header::CONTENT_DISPOSITION, disposition)],
        csv,
    )
        .into_response())
}

/// A CSV field, quoted where it holds a comma, a quote or a line break (RFC 4180).
fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::GridProgress;
    use crate::domain::JobStatus;

    /// Clients count a grid's unfinished and finished jobs from the served vocabulary, so the
    /// progress must have a count for every status and nothing but `total` besides.
    #[test]
    fn grid_progress_counts_every_status_of_the_vocabulary() {
        let progress = serde_json::to_value(GridProgress::default()).unwrap();
        let mut keys: Vec<&str> =
            progress.as_object().unwrap().keys().map(String::as_str).collect();
        let mut expected: Vec<&str> = JobStatus::ALL.iter().map(|s| s.as_str()).collect();
        expected.push("total");
        keys.sort_unstable();
        expected.sort_unstable();
        assert_eq!(keys, expected);
    }
}
