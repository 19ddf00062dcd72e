//! Experiments: a grid of arms × seeds validated as a whole and queued as ordinary jobs in one
//! transaction. Their results, grouped by evaluation protocol, are [`super::results`].

use std::collections::BTreeSet;

use super::submit::{prepare, JobRequest, SubmitError, SubmitLimits};
use crate::domain::experiment::{
    experiment_tag, job_config, Arm, ExperimentRecord, ExperimentSpec, MAX_GRID, MAX_SEEDS,
};
use crate::domain::{ExperimentId, JobLabels};
use crate::store::Store;

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
    let title = request.name.clone().unwrap_or_else(|| format!("experiment {}", id.short()));
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
