//! Experiments: the grid's row and its jobs, queued together in one transaction (all or none).

use super::jobs::DeleteJobOutcome;
use super::{parse_time, Listing, PageQuery, Store, StoreError};
use crate::domain::experiment::{ExperimentRecord, ExperimentSpec};
use crate::domain::NewJob;
use crate::domain::{ExperimentId, JobId, JobRecord, JobStatus};

#[derive(sqlx::FromRow)]
struct ExperimentRow {
    id: String,
    name: Option<String>,
    spec: String,
    created_at: String,
}

impl TryFrom<ExperimentRow> for ExperimentRecord {
    type Error = StoreError;

    fn try_from(row: ExperimentRow) -> Result<Self, StoreError> {
        let owner = format!("experiment {}", row.id);
        let spec: ExperimentSpec = serde_json::from_str(&row.spec)
            .map_err(|e| StoreError::Corrupt(owner.clone(), format!("stored spec: {e}")))?;
        Ok(ExperimentRecord {
            created_at: parse_time(&owner, &row.created_at)?,
            id: ExperimentId::from(row.id),
            name: row.name,
            spec,
        })
    }
}

/// Why an experiment was not deleted.
#[derive(Debug)]
pub enum DeleteExperimentOutcome {
    Deleted {
        /// The policies that went with its jobs (for the serving cache to forget).
        policies: Vec<crate::domain::PolicyId>,
        jobs: Vec<String>,
    },
    NotFound,
    /// Jobs of it are queued or running (cancel it first).
    Active(Vec<String>),
}

impl Store {
    /// Stores the experiment and queues its jobs (each with its arm's label) in one write
    /// transaction: a dataset deleted meanwhile queues none of them.
    pub async fn insert_experiment(
        &self,
        experiment: &ExperimentRecord,
        jobs: &[(NewJob, String)],
    ) -> Result<(), StoreError> {
        let spec = serde_json::to_string(&experiment.spec)
            .map_err(|e| StoreError::Corrupt(experiment.id.to_string(), e.to_string()))?;
        let mut tx = self.begin_write().await?;
        sqlx::query("INSERT INTO experiments (id, name, spec, created_at) VALUES ($1, $2, $3, $4)")
            .bind(experiment.id.as_str())
            .bind(experiment.name.as_deref())
            .bind(spec)
            .bind(crate::domain::rfc3339(&experiment.created_at))
            .execute(&mut *tx)
            .await?;
        for (job, arm) in jobs {
            self.insert_job_in(&mut tx, job, Some((experiment.id.as_str(), arm))).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    pub async fn experiment(&self, id: &ExperimentId) -> Result<ExperimentRecord, StoreError> {
        let row: ExperimentRow =
            sqlx::query_as("SELECT id, name, spec, created_at FROM experiments WHERE id = $1")
                .bind(id.as_str())
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| StoreError::NotFound { kind: "experiment", id: id.to_string() })?;
        row.try_into()
    }

    /// A page of experiments, newest first; and the total.
    pub async fn list_experiments(
        &self,
        page: &PageQuery,
    ) -> Result<(Vec<ExperimentRecord>, u64), StoreError> {
        let (rows, total) = Listing::Experiments
            .page::<ExperimentRow>(self, "id, name, spec, created_at", page)
            .await?;
        let records = rows.into_iter().map(TryInto::try_into).collect::<Result<_, _>>()?;
        Ok((records, total))
    }

    /// How many of an experiment's jobs are in each status (statuses with none left out).
    pub async fn experiment_status_counts(
        &self,
        id: &ExperimentId,
    ) -> Result<Vec<(JobStatus, u64)>, StoreError> {
        let rows: Vec<(String, i64)> = sqlx::query_as(
            "SELECT status, COUNT(*) FROM jobs WHERE experiment_id = $1 GROUP BY status",
        )
        .bind(id.as_str())
        .fetch_all(self.pool())
        .await?;
        rows.into_iter()
            .map(|(status, n)| {
                let status = status
                    .parse()
                    .map_err(|e: String| StoreError::Corrupt(format!("experiment {id}"), e))?;
                Ok((status, n as u64))
            })
            .collect()
    }

    /// The jobs of an experiment, in the order they were queued (arm by arm, seed by seed).
    pub async fn experiment_jobs(&self, id: &ExperimentId) -> Result<Vec<JobRecord>, StoreError> {
        let ids: Vec<JobId> = sqlx::query_scalar::<_, String>(
            "SELECT id FROM jobs WHERE experiment_id = $1 ORDER BY created_at, name, id",
        )
        .bind(id.as_str())
        .fetch_all(self.pool())
        .await?
        .into_iter()
        .map(JobId::from)
        .collect();
        let mut jobs = Vec::with_capacity(ids.len());
        for job in ids {
            jobs.push(self.job(&job).await?);
        }
        Ok(jobs)
    }

    /// Deletes an experiment whose jobs have all ended, with those jobs (as `DELETE
    /// /v1/jobs/{id}` would: metrics, logs, policy and its evaluations). A job whose policy a
    /// model version points at stops the delete there (409 `policy_in_use`, the experiment and
    /// its remaining jobs stay).
    pub async fn delete_experiment(
        &self,
        id: &ExperimentId,
    ) -> Result<DeleteExperimentOutcome, StoreError> {
        let jobs = match self.experiment(id).await {
            Ok(_) => self.experiment_jobs(id).await?,
            Err(StoreError::NotFound { .. }) => return Ok(DeleteExperimentOutcome::NotFound),
            Err(e) => return Err(e),
        };
        let active: Vec<String> = jobs
            .iter()
            .filter(|job| matches!(job.status, JobStatus::Queued | JobStatus::Running))
            .map(|job| job.id.to_string())
            .collect();
        if !active.is_empty() {
            return Ok(DeleteExperimentOutcome::Active(active));
        }
        let (mut policies, mut deleted) = (Vec::new(), Vec::new());
        for job in &jobs {
            match self.delete_job(&job.id).await? {
                DeleteJobOutcome::Deleted { policy } => {
                    policies.extend(policy);
                    deleted.push(job.id.to_string());
                }
                DeleteJobOutcome::NotFound => {}
                DeleteJobOutcome::Active(_) => {
                    return Ok(DeleteExperimentOutcome::Active(vec![job.id.to_string()]))
                }
                DeleteJobOutcome::PolicyInUse(uses) | DeleteJobOutcome::PolicyRegistered(uses) => {
                    return Err(StoreError::Conflict {
                        code: "policy_in_use",
                        message: format!(
                            "the policy of job {} is in use ({}); the experiment keeps it and the \
                             jobs not yet deleted",
                            job.id,
                            uses.join(", ")
                        ),
                    })
                }
            }
        }
        sqlx::query("DELETE FROM experiments WHERE id = $1")
            .bind(id.as_str())
            .execute(self.pool())
            .await?;
        Ok(DeleteExperimentOutcome::Deleted { policies, jobs: deleted })
    }
}
