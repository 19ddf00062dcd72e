//! Experiments: a grid of arms × seeds validated as a whole and queued as ordinary jobs in one
//! transaction, and its results: per job the paper's metrics from the newest succeeded
//! evaluation of its policy (built-in or recorded from the user's simulator), else from the
//! job's in-training `eval/*` metrics; per arm their mean ± standard error over the seeds.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;
use utoipa::ToSchema;

use super::submit::{prepare, JobRequest, SubmitError, SubmitLimits};
use crate::domain::experiment::{
    experiment_tag, job_config, Arm, ExperimentRecord, ExperimentSpec, Summary, MAX_GRID, MAX_SEEDS,
};
use crate::domain::{ExperimentId, JobLabels, JobRecord, JobStatus};
use crate::store::{PageQuery, Store, StoreError};

/// What a client asks for.
#[derive(Clone, Debug)]
pub struct ExperimentRequest {
    pub name: Option<String>,
    pub unlabeled_dataset: String,
    pub non_preferred_dataset: Option<String>,
    pub arms: Vec<Arm>,
    /// The seeds, or `seed_count` seeds 0..n.
    pub seeds: Option<Vec<u64>>,
    pub seed_count: Option<u32>,
    pub config: Option<serde_json::Value>,
    pub eval: Option<serde_json::Value>,
    pub tags: Vec<String>,
}

fn invalid(message: String) -> SubmitError {
    SubmitError::InvalidConfig(message)
}

/// The seeds of the grid: given, or 0..count; 1 to [`MAX_SEEDS`], no repeats.
fn seeds_of(request: &ExperimentRequest) -> Result<Vec<u64>, SubmitError> {
    let seeds = match (&request.seeds, request.seed_count) {
        (Some(seeds), None) => seeds.clone(),
        // Checked before the list is made: a count of 2^31 would be 16 GiB of seeds.
        (None, Some(count)) if (1..=MAX_SEEDS).contains(&(count as usize)) => {
            (0..u64::from(count)).collect()
        }
        (None, Some(count)) => {
            return Err(invalid(format!("seed_count: 1 to {MAX_SEEDS} seeds, got {count}")))
        }
        (None, None) => return Err(invalid("seeds: give `seeds` (a list) or `seed_count`".into())),
        (Some(_), Some(_)) => {
            return Err(invalid("seeds: give `seeds` or `seed_count`, not both".into()))
        }
    };
    if seeds.is_empty() || seeds.len() > MAX_SEEDS {
        return Err(invalid(format!("seeds: 1 to {MAX_SEEDS} seeds, got {}", seeds.len())));
    }
    if let Some(seed) = seeds.iter().find(|&&s| s > crate::domain::MAX_SEED) {
        return Err(invalid(format!(
            "seeds: {seed} is above {}, the largest 64-bit signed integer (seeds are int64)",
            crate::domain::MAX_SEED
        )));
    }
    if seeds.iter().collect::<BTreeSet<_>>().len() != seeds.len() {
        return Err(invalid(format!("seeds: {seeds:?} repeats a seed")));
    }
    Ok(seeds)
}

fn check_arms(arms: &[Arm], seeds: usize) -> Result<(), SubmitError> {
    if arms.is_empty() {
        return Err(invalid("algorithms: at least one algorithm".into()));
    }
    for (index, arm) in arms.iter().enumerate() {
        crate::domain::labels::check_tag(&arm.label())
            .map_err(|e| invalid(format!("algorithms[{index}].label: {}", &e["tags: ".len()..])))?;
    }
    let labels: BTreeSet<String> = arms.iter().map(Arm::label).collect();
    if labels.len() != arms.len() {
        return Err(invalid(
            "algorithms: two entries share a label; give each a distinct `label`".into(),
        ));
    }
    if arms.len() * seeds > MAX_GRID {
        return Err(invalid(format!(
            "algorithms × seeds: {} × {seeds} = {} jobs, above the limit of {MAX_GRID} per \
             experiment",
            arms.len(),
            arms.len() * seeds
        )));
    }
    Ok(())
}

/// Validates every job of the grid, then queues them all with the experiment, or none.
pub async fn submit_experiment(
    store: &Store,
    request: ExperimentRequest,
    limits: SubmitLimits,
) -> Result<ExperimentRecord, SubmitError> {
    let seeds = seeds_of(&request)?;
    check_arms(&request.arms, seeds.len())?;
    let id = ExperimentId::generate();
    let mut tags = request.tags.clone();
    tags.push(experiment_tag(&id));
    let title = request.name.clone().unwrap_or_else(|| format!("experiment {}", &id[..8]));
    let mut jobs = Vec::with_capacity(request.arms.len() * seeds.len());
    for (index, arm) in request.arms.iter().enumerate() {
        for &seed in &seeds {
            let config = job_config(request.config.as_ref(), arm.config.as_ref(), seed)
                .map_err(|e| invalid(format!("algorithms[{index}]: {e}")))?;
            let job = JobRequest {
                algorithm: arm.algorithm,
                unlabeled_dataset: request.unlabeled_dataset.clone().into(),
                non_preferred_dataset: arm
                    .algorithm
                    .needs_non_preferred()
                    .then(|| request.non_preferred_dataset.clone().map(Into::into))
                    .flatten(),
                config: Some(config),
                runner: None,
                eval: request.eval.clone(),
                labels: JobLabels {
                    name: Some(format!("{title} · {} · seed {seed}", arm.label())),
                    tags: tags.clone(),
                    notes: None,
                },
                max_attempts: None,
                register: None,
            };
            let prepared = prepare(store, job, limits).await.map_err(|e| match e {
                SubmitError::InvalidConfig(m) => invalid(format!("algorithms[{index}]: {m}")),
                other => other,
            })?;
            jobs.push((prepared, arm.label()));
        }
    }
    let record = ExperimentRecord {
        id,
        name: request.name,
        spec: ExperimentSpec {
            unlabeled_dataset: request.unlabeled_dataset,
            non_preferred_dataset: request.non_preferred_dataset,
            arms: request.arms,
            seeds,
            config: request.config,
            eval: request.eval,
            tags: request.tags,
        },
        created_at: chrono::Utc::now(),
    };
    store.insert_experiment(&record, &jobs).await?;
    tracing::info!(experiment_id = %record.id, jobs = jobs.len(), "experiment queued");
    Ok(record)
}

/// One job of the grid and the metrics it contributes.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct JobResult {
    pub job_id: String,
    pub arm: String,
    pub seed: u64,
    pub status: JobStatus,
    pub policy_id: Option<String>,
    /// Where the metrics come from: `evaluation <id> (<source>, <env>)`, `in-training eval`,
    /// or absent while there are none.
    pub metrics_from: Option<String>,
    /// The paper's metrics (normalized_return, average_cost, cost_violation_ratio,
    /// cvar_cost_{50,20,10,5}, normalized_cost, …).
    pub metrics: BTreeMap<String, f64>,
}

/// An arm's results over its seeds.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct ArmResult {
    pub label: String,
    pub algorithm: String,
    pub jobs: usize,
    pub succeeded: usize,
    /// Per metric: mean ± standard error over the seeds that have it, and the values.
    pub metrics: BTreeMap<String, Summary>,
}

/// Every job's metrics and every arm's aggregate.
pub async fn results(
    store: &Store,
    experiment: &ExperimentRecord,
) -> Result<(Vec<JobResult>, Vec<ArmResult>), StoreError> {
    let jobs = store.experiment_jobs(&experiment.id).await?;
    let mut per_job = Vec::with_capacity(jobs.len());
    for job in jobs {
        per_job.push(job_result(store, job).await?);
    }
    // Arm by arm, each in the order of the experiment's seeds.
    let spec = &experiment.spec;
    let position = |job: &JobResult| {
        let arm = spec.arms.iter().position(|a| a.label() == job.arm);
        (arm, spec.seeds.iter().position(|&s| s == job.seed))
    };
    per_job.sort_by_key(position);
    let arms = experiment
        .spec
        .arms
        .iter()
        .map(|arm| {
            let label = arm.label();
            let mine: Vec<&JobResult> = per_job.iter().filter(|j| j.arm == label).collect();
            let names: BTreeSet<&String> = mine.iter().flat_map(|j| j.metrics.keys()).collect();
            let metrics = names
                .into_iter()
                .filter_map(|name| {
                    let values = mine.iter().filter_map(|j| j.metrics.get(name).copied()).collect();
                    Summary::of(values).map(|s| (name.clone(), s))
                })
                .collect();
            ArmResult {
                algorithm: arm.algorithm.to_string(),
                jobs: mine.len(),
                succeeded: mine.iter().filter(|j| j.status == JobStatus::Succeeded).count(),
                label,
                metrics,
            }
        })
        .collect();
    Ok((per_job, arms))
}

async fn job_result(store: &Store, job: JobRecord) -> Result<JobResult, StoreError> {
    let (metrics_from, metrics) = match &job.policy_id {
        Some(policy) => match newest_evaluation(store, policy.as_str()).await? {
            Some(found) => (Some(found.0), found.1),
            None => in_training(store, &job).await?,
        },
        None => in_training(store, &job).await?,
    };
    Ok(JobResult {
        job_id: job.id.to_string(),
        arm: job.experiment.map(|(_, arm)| arm).unwrap_or_default(),
        seed: job.config.seed(),
        status: job.status,
        policy_id: job.policy_id.map(|p| p.into_string()),
        metrics_from,
        metrics,
    })
}

/// The newest succeeded evaluation of a policy: (where from, metrics).
async fn newest_evaluation(
    store: &Store,
    policy: &str,
) -> Result<Option<(String, BTreeMap<String, f64>)>, StoreError> {
    let page = PageQuery { limit: 100, offset: 0, after: None };
    let (evaluations, _) = store.list_evaluations(Some(policy), &page).await?;
    Ok(evaluations.into_iter().find_map(|e| {
        let report = e.report?;
        let source = match e.training_step {
            Some(step) => format!("taken at training step {step}"),
            None => e.source.as_str().to_owned(),
        };
        let from = format!("evaluation {} ({source}, {})", e.id, report.env);
        Some((from, named(report.metrics.named_values().to_vec())))
    }))
}

/// The job's last in-training `eval/*` values, if it evaluated itself.
async fn in_training(
    store: &Store,
    job: &JobRecord,
) -> Result<(Option<String>, BTreeMap<String, f64>), StoreError> {
    let last = store.last_metric_values(&job.id).await?;
    let metrics = named(last.iter().map(|(n, v)| (n.as_str(), *v)).collect());
    let from = (!metrics.is_empty()).then(|| "in-training eval".to_owned());
    Ok((from, metrics))
}

/// `eval/<name>` values under their plain names.
fn named<S: AsRef<str>>(values: Vec<(S, f64)>) -> BTreeMap<String, f64> {
    values
        .into_iter()
        .filter_map(|(name, v)| Some((name.as_ref().strip_prefix("eval/")?.to_owned(), v)))
        .collect()
}
