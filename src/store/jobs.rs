//! The training queue's table: creating, claiming, progressing and finishing jobs, their
//! metrics and checkpoints.

use chrono::{DateTime, Utc};
use sqlx::{Sqlite, SqliteConnection, Transaction};

use super::policies::NewPolicy;
use super::{now, Store, StoreError};
use crate::algo::ResolvedConfig;
use crate::domain::{DatasetId, EvalOptions, JobId, JobRecord, JobStatus, RunnerOptions};

/// A job row as SQLite returns it; [`JobRecord`] is its typed form.
#[derive(sqlx::FromRow)]
struct JobRow {
    id: String,
    algorithm: String,
    status: String,
    unlabeled_dataset_id: String,
    non_preferred_dataset_id: Option<String>,
    config: String,
    runner: String,
    eval: Option<String>,
    step: i64,
    total_steps: i64,
    phase: Option<String>,
    iterations_per_second: Option<f64>,
    alpha_hat: Option<f64>,
    policy_id: Option<String>,
    error: Option<String>,
    cancel_requested: bool,
    created_at: DateTime<Utc>,
    updated_at: DateTime<Utc>,
    started_at: Option<DateTime<Utc>>,
    finished_at: Option<DateTime<Utc>>,
}

impl TryFrom<JobRow> for JobRecord {
    type Error = StoreError;

    fn try_from(row: JobRow) -> Result<Self, StoreError> {
        let corrupt = |what: &str, e: &dyn std::fmt::Display| {
            StoreError::Corrupt(format!("job {}", row.id), format!("stored {what}: {e}"))
        };
        let json = |what: &str, text: &str| -> Result<serde_json::Value, StoreError> {
            serde_json::from_str(text).map_err(|e| corrupt(what, &e))
        };
        let algorithm = serde_json::from_value(row.algorithm.clone().into())
            .map_err(|e| corrupt("algorithm", &e))?;
        let status = row.status.parse().map_err(|e: String| corrupt("status", &e))?;
        let config: ResolvedConfig = serde_json::from_value(json("config", &row.config)?)
            .map_err(|e| corrupt("config", &e))?;
        let runner: RunnerOptions = serde_json::from_value(json("runner", &row.runner)?)
            .map_err(|e| corrupt("runner", &e))?;
        let eval: Option<EvalOptions> = match row.eval.as_deref() {
            Some(text) => {
                Some(serde_json::from_value(json("eval", text)?).map_err(|e| corrupt("eval", &e))?)
            }
            None => None,
        };
        Ok(JobRecord {
            id: row.id.into(),
            algorithm,
            status,
            unlabeled_dataset: row.unlabeled_dataset_id.into(),
            non_preferred_dataset: row.non_preferred_dataset_id.map(DatasetId::from),
            config,
            runner,
            eval,
            step: row.step as u64,
            total_steps: row.total_steps as u64,
            phase: row.phase,
            iterations_per_second: row.iterations_per_second,
            alpha_hat: row.alpha_hat,
            policy_id: row.policy_id.map(Into::into),
            error: row.error,
            cancel_requested: row.cancel_requested,
            created_at: row.created_at,
            updated_at: row.updated_at,
            started_at: row.started_at,
            finished_at: row.finished_at,
        })
    }
}

/// A job to queue: its datasets, resolved configuration and options.
#[derive(Clone, Debug)]
pub struct NewJob {
    pub id: JobId,
    pub unlabeled_dataset: DatasetId,
    pub non_preferred_dataset: Option<DatasetId>,
    pub config: ResolvedConfig,
    pub runner: RunnerOptions,
    pub eval: Option<EvalOptions>,
}

/// One recorded scalar of a training step.
#[derive(Clone, Debug, PartialEq, sqlx::FromRow)]
pub struct MetricRow {
    pub name: String,
    pub step: i64,
    pub value: f64,
    pub time: String,
}

/// A running job's progress as the worker reports it.
#[derive(Clone, Debug)]
pub struct ProgressUpdate<'a> {
    pub step: u64,
    pub phase: &'a str,
    pub iterations_per_second: Option<f64>,
    pub alpha_hat: Option<f64>,
}

/// What a cancel request did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CancelOutcome {
    /// The job was queued and is now cancelled.
    Cancelled,
    /// The job is running; its worker stops at the next step.
    Requested,
    /// The job had already finished with this status.
    AlreadyFinished(JobStatus),
}

const JOB_COLUMNS: &str = "id, algorithm, status, unlabeled_dataset_id, non_preferred_dataset_id, \
     config, runner, eval, step, total_steps, phase, iterations_per_second, alpha_hat, policy_id, \
     error, cancel_requested, created_at, updated_at, started_at, finished_at";

impl Store {
    /// Number of jobs in each status, every status listed (zero when there are none).
    pub async fn job_counts_by_status(&self) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        self.counts_by_status("jobs", &JobStatus::ALL.map(JobStatus::as_str)).await
    }

    /// Queues a job if its datasets still exist. The check and the insert are one write
    /// transaction, so a concurrent [`Store::delete_dataset`] either commits first (and this
    /// answers `NotFound` for the dataset) or sees the queued job and refuses.
    pub async fn insert_job(&self, job: &NewJob) -> Result<JobRecord, StoreError> {
        let now = now();
        let config = to_json(&job.config);
        let runner = to_json(&job.runner);
        let eval = job.eval.as_ref().map(to_json);
        let mut tx = self.begin_write().await?;
        for dataset in std::iter::once(&job.unlabeled_dataset).chain(&job.non_preferred_dataset) {
            let exists: bool =
                sqlx::query_scalar("SELECT EXISTS (SELECT 1 FROM datasets WHERE id = ?)")
                    .bind(dataset.as_str())
                    .fetch_one(&mut *tx)
                    .await?;
            if !exists {
                return Err(StoreError::NotFound { kind: "dataset", id: dataset.to_string() });
            }
        }
        sqlx::query(
            "INSERT INTO jobs (id, algorithm, status, unlabeled_dataset_id, \
             non_preferred_dataset_id, config, runner, eval, total_steps, created_at, updated_at) \
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(job.id.as_str())
        .bind(job.config.algorithm().as_str())
        .bind(JobStatus::Queued.as_str())
        .bind(job.unlabeled_dataset.as_str())
        .bind(job.non_preferred_dataset.as_deref())
        .bind(config)
        .bind(runner)
        .bind(eval)
        .bind(job.config.total_steps() as i64)
        .bind(&now)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        let row: JobRow = sqlx::query_as(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?"))
            .bind(job.id.as_str())
            .fetch_one(&mut *tx)
            .await?;
        tx.commit().await?;
        row.try_into()
    }

    pub async fn job(&self, id: &str) -> Result<JobRecord, StoreError> {
        let row: JobRow = sqlx::query_as(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?"))
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        row.try_into()
    }

    /// A job's status alone (what a cancel waits on).
    pub async fn job_status(&self, id: &str) -> Result<JobStatus, StoreError> {
        let status: String = sqlx::query_scalar("SELECT status FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        parse_status(id, &status)
    }

    /// A page of jobs, newest first, optionally only those in `status`; and the total count.
    pub async fn list_jobs(
        &self,
        status: Option<JobStatus>,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<JobRecord>, u64), StoreError> {
        let status = status.map(JobStatus::as_str);
        let rows: Vec<JobRow> = sqlx::query_as(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE (?1 IS NULL OR status = ?1) \
             ORDER BY created_at DESC, id DESC LIMIT ?2 OFFSET ?3"
        ))
        .bind(status)
        .bind(i64::from(limit))
        .bind(offset as i64)
        .fetch_all(self.pool())
        .await?;
        let total: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE ?1 IS NULL OR status = ?1")
                .bind(status)
                .fetch_one(self.pool())
                .await?;
        let jobs = rows.into_iter().map(JobRecord::try_from).collect::<Result<_, _>>()?;
        Ok((jobs, total as u64))
    }

    /// Atomically moves the next job from `queued` to `running` and returns it. Jobs that were
    /// already started once (interrupted by a shutdown or crash) go first, then the oldest.
    pub async fn claim_next_job(&self) -> Result<Option<JobRecord>, StoreError> {
        let now = now();
        let claimed: Option<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'running', updated_at = ?1, \
                 started_at = COALESCE(started_at, ?1) \
             WHERE id = (SELECT id FROM jobs WHERE status = 'queued' \
                         ORDER BY started_at IS NULL, created_at, id LIMIT 1) \
               AND status = 'queued' \
             RETURNING id",
        )
        .bind(&now)
        .fetch_optional(self.pool())
        .await?;
        let Some(id) = claimed else { return Ok(None) };
        match self.job(&id).await {
            // A row this version cannot read (e.g. written by another version) can never run:
            // it fails with the reason instead of blocking the queue.
            Err(StoreError::Corrupt(_, reason)) => {
                tracing::error!(job_id = %id, %reason, "a queued job cannot be read; it fails");
                self.finish_job(&id, JobStatus::Failed, Some(&reason), &[]).await?;
                Box::pin(self.claim_next_job()).await
            }
            job => job.map(Some),
        }
    }

    /// At start-up: jobs left `running` by a process that died go back to the queue (they
    /// resume from their checkpoint). Returns how many.
    pub async fn requeue_interrupted_jobs(&self) -> Result<u64, StoreError> {
        let done = sqlx::query(
            "UPDATE jobs SET status = 'queued', updated_at = ?, iterations_per_second = NULL \
             WHERE status = 'running'",
        )
        .bind(now())
        .execute(self.pool())
        .await?;
        Ok(done.rows_affected())
    }

    /// A running job handed back to the queue (graceful shutdown after its checkpoint).
    pub async fn release_job(&self, id: &str) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE jobs SET status = 'queued', updated_at = ?, iterations_per_second = NULL \
             WHERE id = ? AND status = 'running'",
        )
        .bind(now())
        .bind(id)
        .execute(self.pool())
        .await?;
        Ok(())
    }

    /// Records progress; returns whether a cancel was requested meanwhile.
    pub async fn update_progress(
        &self,
        id: &str,
        progress: &ProgressUpdate<'_>,
    ) -> Result<bool, StoreError> {
        let cancel: Option<bool> = sqlx::query_scalar(
            "UPDATE jobs SET step = ?, phase = ?, iterations_per_second = ?, \
                 alpha_hat = COALESCE(?, alpha_hat), updated_at = ? \
             WHERE id = ? RETURNING cancel_requested",
        )
        .bind(progress.step as i64)
        .bind(progress.phase)
        .bind(progress.iterations_per_second)
        .bind(progress.alpha_hat)
        .bind(now())
        .bind(id)
        .fetch_optional(self.pool())
        .await?;
        Ok(cancel.unwrap_or(false))
    }

    pub async fn insert_metrics(&self, id: &str, rows: &[MetricRow]) -> Result<(), StoreError> {
        if rows.is_empty() {
            return Ok(());
        }
        let mut tx = self.begin_write().await?;
        insert_metric_rows(&mut tx, id, rows).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Writes the pending metrics and replaces the job's checkpoint in one transaction, so the
    /// checkpoint never refers to metrics that are not stored.
    pub async fn save_checkpoint(
        &self,
        id: &str,
        step: u64,
        data: &[u8],
        pending_metrics: &[MetricRow],
    ) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        insert_metric_rows(&mut tx, id, pending_metrics).await?;
        sqlx::query(
            "INSERT INTO job_checkpoints (job_id, step, data, created_at) VALUES (?, ?, ?, ?) \
             ON CONFLICT (job_id) DO UPDATE SET step = excluded.step, data = excluded.data, \
                 created_at = excluded.created_at",
        )
        .bind(id)
        .bind(step as i64)
        .bind(data)
        .bind(now())
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// The job's last checkpoint: (step, bytes).
    pub async fn checkpoint(&self, id: &str) -> Result<Option<(u64, Vec<u8>)>, StoreError> {
        let row: Option<(i64, Vec<u8>)> =
            sqlx::query_as("SELECT step, data FROM job_checkpoints WHERE job_id = ?")
                .bind(id)
                .fetch_optional(self.pool())
                .await?;
        Ok(row.map(|(step, data)| (step as u64, data)))
    }

    /// Deletes the metrics recorded after `step` (a resume from the checkpoint at `step`
    /// recomputes them; deleting first keeps every (name, step) row exactly once).
    pub async fn discard_metrics_after(&self, id: &str, step: u64) -> Result<u64, StoreError> {
        let done = sqlx::query("DELETE FROM job_metrics WHERE job_id = ? AND step > ?")
            .bind(id)
            .bind(step as i64)
            .execute(self.pool())
            .await?;
        Ok(done.rows_affected())
    }

    /// Every metric row of a job (only `names` when given), ordered by name then step.
    pub async fn job_metrics(
        &self,
        id: &str,
        names: Option<&[String]>,
    ) -> Result<Vec<MetricRow>, StoreError> {
        let names_json = names.map(|n| serde_json::to_string(n).expect("names serialize"));
        let rows = sqlx::query_as(
            "SELECT name, step, value, time FROM job_metrics WHERE job_id = ?1 \
               AND (?2 IS NULL OR name IN (SELECT value FROM json_each(?2))) \
             ORDER BY name, step",
        )
        .bind(id)
        .bind(names_json)
        .fetch_all(self.pool())
        .await?;
        Ok(rows)
    }

    /// The last recorded value of each metric of a job.
    pub async fn last_metric_values(&self, id: &str) -> Result<Vec<(String, f64)>, StoreError> {
        let rows = sqlx::query_as(
            "SELECT name, value FROM job_metrics AS m WHERE job_id = ?1 \
               AND step = (SELECT MAX(step) FROM job_metrics WHERE job_id = ?1 AND name = m.name) \
             ORDER BY name",
        )
        .bind(id)
        .fetch_all(self.pool())
        .await?;
        Ok(rows)
    }

    /// Completes a job: its last metrics, its policy and the `succeeded` status in one
    /// transaction; the checkpoint is no longer needed.
    pub async fn finish_job_succeeded(
        &self,
        id: &str,
        pending_metrics: &[MetricRow],
        policy: &NewPolicy<'_>,
        step: u64,
    ) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        insert_metric_rows(&mut tx, id, pending_metrics).await?;
        super::policies::insert_policy(&mut tx, policy).await?;
        let now = now();
        sqlx::query(
            "UPDATE jobs SET status = 'succeeded', policy_id = ?, step = ?, \
                 alpha_hat = COALESCE(?, alpha_hat), updated_at = ?, finished_at = ? \
             WHERE id = ?",
        )
        .bind(policy.id)
        .bind(step as i64)
        .bind(policy.alpha_hat)
        .bind(&now)
        .bind(&now)
        .bind(id)
        .execute(&mut *tx)
        .await?;
        delete_checkpoint(&mut tx, id).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Ends a job as `failed` (with `error`) or `cancelled`, storing its last metrics; its
    /// metrics history stays.
    pub async fn finish_job(
        &self,
        id: &str,
        status: JobStatus,
        error: Option<&str>,
        pending_metrics: &[MetricRow],
    ) -> Result<(), StoreError> {
        debug_assert!(matches!(status, JobStatus::Failed | JobStatus::Cancelled));
        let mut tx = self.begin_write().await?;
        insert_metric_rows(&mut tx, id, pending_metrics).await?;
        let now = now();
        sqlx::query(
            "UPDATE jobs SET status = ?, error = ?, iterations_per_second = NULL, updated_at = ?, \
                 finished_at = ? WHERE id = ?",
        )
        .bind(status.as_str())
        .bind(error)
        .bind(&now)
        .bind(&now)
        .bind(id)
        .execute(&mut *tx)
        .await?;
        delete_checkpoint(&mut tx, id).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Cancels a queued job at once, or flags a running one for its worker. The status read and
    /// the update are one write transaction, so a worker's claim cannot slip in between.
    pub async fn request_cancel(&self, id: &str) -> Result<CancelOutcome, StoreError> {
        let now = now();
        let mut tx = self.begin_write().await?;
        let status: String = sqlx::query_scalar("SELECT status FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        let outcome = match parse_status(id, &status)? {
            JobStatus::Queued => {
                sqlx::query(
                    "UPDATE jobs SET status = 'cancelled', cancel_requested = 1, updated_at = ?1, \
                         finished_at = ?1 WHERE id = ?2",
                )
                .bind(&now)
                .bind(id)
                .execute(&mut *tx)
                .await?;
                delete_checkpoint(&mut tx, id).await?;
                CancelOutcome::Cancelled
            }
            JobStatus::Running => {
                sqlx::query("UPDATE jobs SET cancel_requested = 1, updated_at = ? WHERE id = ?")
                    .bind(&now)
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                CancelOutcome::Requested
            }
            finished => CancelOutcome::AlreadyFinished(finished),
        };
        tx.commit().await?;
        Ok(outcome)
    }
}

/// The JSON of a job's configuration or options as stored.
fn to_json(value: &impl serde::Serialize) -> String {
    // Plain structs of numbers, strings and enums: serialising them cannot fail.
    serde_json::to_string(value).expect("job options serialise to JSON")
}

fn parse_status(id: &str, status: &str) -> Result<JobStatus, StoreError> {
    status.parse().map_err(|e| StoreError::Corrupt(format!("job {id}"), e))
}

/// A finished job keeps no checkpoint: it would only be read to resume.
async fn delete_checkpoint(tx: &mut Transaction<'_, Sqlite>, id: &str) -> Result<(), sqlx::Error> {
    sqlx::query("DELETE FROM job_checkpoints WHERE job_id = ?")
        .bind(id)
        .execute(&mut **tx as &mut SqliteConnection)
        .await?;
    Ok(())
}

async fn insert_metric_rows(
    tx: &mut Transaction<'_, Sqlite>,
    id: &str,
    rows: &[MetricRow],
) -> Result<(), sqlx::Error> {
    // SQLite's bound-parameter limit is 32766; 4 per row plus the job id.
    for chunk in rows.chunks(4000) {
        let mut insert = sqlx::QueryBuilder::<Sqlite>::new(
            "INSERT INTO job_metrics (job_id, name, step, value, time) ",
        );
        insert.push_values(chunk, |mut row, metric| {
            row.push_bind(id)
                .push_bind(&metric.name)
                .push_bind(metric.step)
                .push_bind(metric.value)
                .push_bind(&metric.time);
        });
        insert.build().execute(&mut **tx as &mut SqliteConnection).await?;
    }
    Ok(())
}
