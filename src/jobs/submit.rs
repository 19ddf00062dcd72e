//! Queueing a job: the request is resolved and checked against the stored datasets' metadata
//! (never their data, which may be gigabytes), then inserted in one write transaction that also
//! checks the datasets still exist.

use crate::algo::memory::{estimate_job_memory, DataShape};
use crate::algo::{self, Algorithm};
use crate::domain::attempt::MOST_ATTEMPTS;
use crate::domain::model::Registration;
use crate::domain::DatasetRecord;
use crate::domain::{
    DatasetId, DatasetRole, EvalOptions, JobId, JobLabels, JobRecord, NewJob, RunnerOptions,
};
use crate::store::{Store, StoreError};

/// What a client asks for: the algorithm, its datasets, and the raw `config`, `runner` and
/// `eval` objects (validated here, with messages that name the key).
#[derive(Clone, Debug)]
pub struct JobRequest {
    pub algorithm: Algorithm,
    pub unlabeled_dataset: DatasetId,
    pub non_preferred_dataset: Option<DatasetId>,
    pub config: Option<serde_json::Value>,
    pub runner: Option<serde_json::Value>,
    pub eval: Option<serde_json::Value>,
    /// Name, tags and notes (checked here).
    pub labels: JobLabels,
    /// Attempts before the job fails when its workers keep vanishing (None: the server's).
    pub max_attempts: Option<u32>,
    /// The model the policy becomes a version of on success (it must exist).
    pub register: Option<Registration>,
}

/// Why a job was not queued.
#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    /// The configuration, the options, or datasets that do not fit them.
    #[error("{0}")]
    InvalidConfig(String),
    /// A name, tag or notes that break their rules.
    #[error("{0}")]
    InvalidLabels(String),
    /// The job's estimated peak memory is above the limit; the message says what to change.
    #[error("{0}")]
    TooLarge(String),
    /// A dataset does not exist (`NotFound`), or the store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// The server's limits and defaults a job is queued under.
#[derive(Clone, Copy, Debug)]
pub struct SubmitLimits {
    /// Bounds the job's estimated peak memory: a job above it would take the worker's machine
    /// down when it starts, so it is refused with a message saying what to change.
    pub max_job_memory: u64,
    /// A job's `max_attempts` when it sets none.
    pub default_max_attempts: u32,
    /// A job's `threads` when its config sets none (`--job-threads`), fewer where its steps
    /// are too small to gain from them ([`algo::worthwhile_threads`]).
    pub job_threads: usize,
}

/// Validates `request` and queues it under `limits`.
pub async fn submit(
    store: &Store,
    request: JobRequest,
    limits: SubmitLimits,
) -> Result<JobRecord, SubmitError> {
    let job = prepare(store, request, limits).await?;
    let record = store.insert_job(&job).await?;
    tracing::info!(
        job_id = %record.id,
        algorithm = %record.algorithm,
        total_steps = record.total_steps,
        "job queued"
    );
    Ok(record)
}

/// Validates `request` under `limits` against the stored datasets' metadata: the job to insert.
pub async fn prepare(
    store: &Store,
    request: JobRequest,
    limits: SubmitLimits,
) -> Result<NewJob, SubmitError> {
    let max_attempts = request.max_attempts.unwrap_or(limits.default_max_attempts);
    if !(1..=MOST_ATTEMPTS).contains(&max_attempts) {
        return Err(SubmitError::InvalidConfig(format!(
            "max_attempts must be between 1 and {MOST_ATTEMPTS}, not {max_attempts}"
        )));
    }
    let labels = request.labels.validated().map_err(SubmitError::InvalidLabels)?;
    if let Some(register) = &request.register {
        check_registration(store, register).await?;
    }
    let invalid = SubmitError::InvalidConfig;
    let algorithm = request.algorithm;
    let raw_config = request.config.as_ref().unwrap_or(&serde_json::Value::Null);
    let mut config = algo::resolve_config(algorithm, raw_config).map_err(|e| invalid(e.message))?;
    let runner = RunnerOptions::parse(request.runner.as_ref()).map_err(|e| invalid(e.0))?;
    let eval = EvalOptions::parse(request.eval.as_ref()).map_err(|e| invalid(e.0))?;
    if algorithm.needs_non_preferred() && request.non_preferred_dataset.is_none() {
        return Err(invalid(format!(
            "algorithm {algorithm} needs non_preferred_dataset (a labeled non-preferred dataset id)"
        )));
    }
    let unlabeled = stored_dataset(store, &request.unlabeled_dataset).await?;
    check_role(&unlabeled, DatasetRole::Unlabeled, "unlabeled_dataset")?;
    let unlabeled = shape(&unlabeled);
    if raw_config.get("threads").is_none() {
        let worthwhile = algo::worthwhile_threads(&config, unlabeled.obs_dim as usize);
        config.common.threads = limits.job_threads.min(worthwhile);
    }
    let non_preferred = match &request.non_preferred_dataset {
        Some(id) => {
            let record = stored_dataset(store, id).await?;
            check_role(&record, DatasetRole::NonPreferred, "non_preferred_dataset")?;
            Some(shape(&record))
        }
        None => None,
    };
    check_memory(&config, &unlabeled, non_preferred.as_ref(), limits.max_job_memory)?;
    algo::check_fit(&config, &unlabeled, non_preferred.as_ref()).map_err(|e| invalid(e.message))?;
    if let Some(eval) = &eval {
        let (obs_dim, actions) = (unlabeled.obs_dim as usize, &unlabeled.action_space);
        crate::envs::check_spaces(&eval.env, obs_dim, actions, "the datasets'")
            .map_err(|e| invalid(format!("eval.env: {e}")))?;
    }
    let job = NewJob {
        id: JobId::generate(),
        unlabeled_dataset: request.unlabeled_dataset,
        non_preferred_dataset: request.non_preferred_dataset,
        config,
        runner,
        eval,
        labels,
        max_attempts,
        register: request.register,
    };
    Ok(job)
}

/// A job's `register` names an existing model and a valid alias. (A model deleted between this
/// check and the insert is no loss: the job then registers nothing and says so; deletes are
/// refused once the job is queued.)
async fn check_registration(store: &Store, register: &Registration) -> Result<(), SubmitError> {
    let model = register.validated().map_err(SubmitError::InvalidConfig)?;
    match store.model(&model).await {
        Ok(_) => Ok(()),
        Err(StoreError::NotFound { .. }) => Err(SubmitError::InvalidConfig(format!(
            "register.model: model {} does not exist; create it first (POST /v1/models)",
            register.model
        ))),
        Err(e) => Err(e.into()),
    }
}

/// A dataset uploaded with the other role is refused in this place (a swapped pair of ids is
/// an easy mistake that trains the opposite of what was meant).
fn check_role(record: &DatasetRecord, wanted: DatasetRole, field: &str) -> Result<(), SubmitError> {
    match record.role {
        Some(role) if role != wanted => Err(SubmitError::InvalidConfig(format!(
            "{field}: dataset {} was uploaded with role `{}`, not `{}`; are the two ids swapped?",
            record.id,
            role.as_str(),
            wanted.as_str()
        ))),
        _ => Ok(()),
    }
}

async fn stored_dataset(store: &Store, id: &DatasetId) -> Result<DatasetRecord, StoreError> {
    store
        .dataset(id)
        .await?
        .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.to_string() })
}

/// What training needs to know of a dataset, from its stored metadata.
fn shape(record: &DatasetRecord) -> DataShape {
    DataShape {
        transitions: record.transitions,
        obs_dim: record.obs_dim,
        action_space: record.action_space.clone(),
        longest_episode: record.stats.episode_length.max as u64,
    }
}

fn check_memory(
    config: &algo::ResolvedConfig,
    unlabeled: &DataShape,
    non_preferred: Option<&DataShape>,
    limit: u64,
) -> Result<(), SubmitError> {
    let estimate = estimate_job_memory(config, unlabeled, non_preferred);
    if estimate.total <= limit {
        return Ok(());
    }
    let ppl =
        if config.algorithm() == Algorithm::Ppl { ", pairs_per_batch, segment_length" } else { "" };
    Err(SubmitError::TooLarge(format!(
        "this job needs an estimated {} of memory ({} for the datasets, {} for the networks, {} \
         per training step), above the server's limit of {} (--max-job-memory); lower \
         batch_size, hidden_sizes{ppl}, or train on a smaller dataset",
        human_bytes(estimate.total),
        human_bytes(estimate.data),
        human_bytes(estimate.networks),
        human_bytes(estimate.step),
        human_bytes(limit),
    )))
}

/// `3.6 GiB (3865470976 bytes)`.
fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["bytes", "KiB", "MiB", "GiB", "TiB"];
    let exponent = ((63 - bytes.max(1).leading_zeros()) / 10).min(UNITS.len() as u32 - 1);
    if exponent == 0 {
        return format!("{bytes} bytes");
    }
    let value = bytes as f64 / (1u64 << (10 * exponent)) as f64;
    format!("{value:.1} {} ({bytes} bytes)", UNITS[exponent as usize])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_counts_read_in_binary_units_with_the_exact_count() {
        assert_eq!(human_bytes(0), "0 bytes");
        assert_eq!(human_bytes(1023), "1023 bytes");
        assert_eq!(human_bytes(1536), "1.5 KiB (1536 bytes)");
        assert_eq!(human_bytes(4 << 30), "4.0 GiB (4294967296 bytes)");
    }
}
