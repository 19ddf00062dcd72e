//! The training queue's table: queueing, reading, listing, labelling, cancelling and deleting
//! jobs. A claimed job's life under its lease is in [`super::job_runs`], its metrics in
//! [`super::job_metrics`].

use sqlx::{Any, Transaction};

use super::{now_in, parse_optional_time, parse_time, Listing, PageQuery, Store, StoreError};
use crate::algo::ResolvedConfig;
use crate::domain::model::Registration;
use crate::domain::{
    DatasetId, EvalOptions, JobId, JobLabels, JobRecord, JobStatus, NewJob, PolicyId, RunnerOptions,
};

/// A job row as the database returns it; [`JobRecord`] is its typed form.
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
    name: Option<String>,
    tags: String,
    notes: Option<String>,
    step: i64,
    total_steps: i64,
    phase: Option<String>,
    iterations_per_second: Option<f64>,
    alpha_hat: Option<f64>,
    policy_id: Option<String>,
    error: Option<String>,
    cancel_requested: i64,
    lease_owner: Option<String>,
    attempt: i64,
    max_attempts: i64,
    register_model: Option<String>,
    register_alias: Option<String>,
    experiment_id: Option<String>,
    experiment_arm: Option<String>,
    /// When a job queued again after a crash may next be claimed (null: now).
    retry_at_ms: Option<i64>,
    /// When the lease of a running job expired (null: it has not, or the job is not running).
    lease_expired_at_ms: Option<i64>,
    created_at: String,
    updated_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
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
        let tags: Vec<String> =
            serde_json::from_value(json("tags", &row.tags)?).map_err(|e| corrupt("tags", &e))?;
        let labels = JobLabels { name: row.name, tags, notes: row.notes };
        let owner = format!("job {}", row.id);
        Ok(JobRecord {
            created_at: parse_time(&owner, &row.created_at)?,
            updated_at: parse_time(&owner, &row.updated_at)?,
            started_at: parse_optional_time(&owner, row.started_at.as_deref())?,
            finished_at: parse_optional_time(&owner, row.finished_at.as_deref())?,
            id: row.id.into(),
            algorithm,
            status,
            unlabeled_dataset: row.unlabeled_dataset_id.into(),
            non_preferred_dataset: row.non_preferred_dataset_id.map(DatasetId::from),
            config,
            runner,
            eval,
            labels,
            step: row.step as u64,
            total_steps: row.total_steps as u64,
            phase: row.phase,
            iterations_per_second: row.iterations_per_second,
            alpha_hat: row.alpha_hat,
            policy_id: row.policy_id.map(Into::into),
            error: row.error,
            cancel_requested: row.cancel_requested != 0,
            worker: row.lease_owner,
            attempt: u32::try_from(row.attempt).unwrap_or(u32::MAX),
            max_attempts: u32::try_from(row.max_attempts).unwrap_or(u32::MAX),
            register: row
                .register_model
                .map(|model| Registration { model, alias: row.register_alias }),
            experiment: row.experiment_id.map(|id| (id, row.experiment_arm.unwrap_or_default())),
            retry_at: row.retry_at_ms.map(from_millis),
            lease_expired_at: row.lease_expired_at_ms.map(from_millis),
        })
    }
}

/// Which jobs a list shows: all of them, or those with a status, a tag, or a name or id that
/// contains a text.
#[derive(Clone, Debug, Default)]
pub struct JobQuery {
    pub status: Option<JobStatus>,
    pub tag: Option<String>,
    /// Case-insensitive substring of the name, or a prefix of the id.
    pub search: Option<String>,
}

/// What a job delete did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DeleteJobOutcome {
    /// Deleted, with its policy if it had one (and that policy's evaluations).
    Deleted {
        policy: Option<PolicyId>,
    },
    NotFound,
    /// Queued or running: cancel it first.
    Active(JobStatus),
    /// Its policy has evaluations queued or running (their ids).
    PolicyInUse(Vec<String>),
    /// Its policy is registered as these model versions (`name version n`).
    PolicyRegistered(Vec<String>),
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
     error, cancel_requested, lease_owner, created_at, updated_at, started_at, finished_at, name, \
     tags, notes, attempt, max_attempts, register_model, register_alias, experiment_id, \
     experiment_arm";

/// A stored time in milliseconds since the Unix epoch (the database's clock).
fn from_millis(ms: i64) -> chrono::DateTime<chrono::Utc> {
    chrono::DateTime::from_timestamp_millis(ms).unwrap_or_default()
}

impl Store {
    /// The columns of a [`JobRow`]: the stored ones and two the database's clock decides (a
    /// retry not yet due, a lease that expired with no worker having taken the job over yet).
    fn job_columns(&self) -> String {
        let (now_ms, running) = (self.backend.now_ms(), JobStatus::Running.sql());
        format!(
            "{JOB_COLUMNS}, CASE WHEN scheduled_ms > {now_ms} THEN scheduled_ms END AS retry_at_ms, \
             CASE WHEN status = {running} AND lease_expires_ms < {now_ms} THEN lease_expires_ms \
             END AS lease_expired_at_ms"
        )
    }

    /// Number of jobs in each status, every status listed (zero when there are none).
    pub async fn job_counts_by_status(&self) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        self.counts_by_status("jobs", &JobStatus::ALL.map(JobStatus::as_str)).await
    }

    /// Queues a job if its datasets still exist. The check and the insert are one write
    /// transaction that keeps the dataset rows from changing until it commits, so a concurrent
    /// [`Store::delete_dataset`] either commits first (and this answers `NotFound` for the
    /// dataset) or sees the queued job and refuses.
    pub async fn insert_job(&self, job: &NewJob) -> Result<JobRecord, StoreError> {
        let mut tx = self.begin_write().await?;
        self.insert_job_in(&mut tx, job, None).await?;
        let row: JobRow =
            sqlx::query_as(&format!("SELECT {} FROM jobs WHERE id = $1", self.job_columns()))
                .bind(job.id.as_str())
                .fetch_one(&mut *tx)
                .await?;
        tx.commit().await?;
        row.try_into()
    }

    /// Inserts a queued job inside the caller's write transaction, after checking (and, on
    /// PostgreSQL, share-locking) its datasets; `experiment` is (experiment id, arm label) for
    /// a job of an experiment's grid.
    pub(super) async fn insert_job_in(
        &self,
        tx: &mut Transaction<'_, Any>,
        job: &NewJob,
        experiment: Option<(&str, &str)>,
    ) -> Result<(), StoreError> {
        let config = to_json(&job.config);
        let runner = to_json(&job.runner);
        let eval = job.eval.as_ref().map(to_json);
        for dataset in std::iter::once(&job.unlabeled_dataset).chain(&job.non_preferred_dataset) {
            let found: Option<String> = sqlx::query_scalar(&format!(
                "SELECT id FROM datasets WHERE id = $1{}",
                self.backend.share_row()
            ))
            .bind(dataset.as_str())
            .fetch_optional(&mut **tx)
            .await?;
            if found.is_none() {
                return Err(StoreError::NotFound { kind: "dataset", id: dataset.to_string() });
            }
        }
        sqlx::query(
            "INSERT INTO jobs (id, algorithm, status, unlabeled_dataset_id, \
             non_preferred_dataset_id, config, runner, eval, total_steps, created_at, updated_at, \
             name, tags, notes, max_attempts, register_model, register_alias, experiment_id, \
             experiment_arm) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $10, $11, $12, $13, $14, $15, $16, \
             $17, $18)",
        )
        .bind(job.id.as_str())
        .bind(job.config.algorithm().as_str())
        .bind(JobStatus::Queued.as_str())
        .bind(job.unlabeled_dataset.as_str())
        .bind(job.non_preferred_dataset.as_ref().map(DatasetId::as_str))
        .bind(config)
        .bind(runner)
        .bind(eval)
        .bind(job.config.total_steps() as i64)
        .bind(now_in(tx).await?)
        .bind(job.labels.name.as_deref())
        .bind(to_json(&job.labels.tags))
        .bind(job.labels.notes.as_deref())
        .bind(i64::from(job.max_attempts))
        .bind(job.register.as_ref().map(|r| r.model.as_str()))
        .bind(job.register.as_ref().and_then(|r| r.alias.as_deref()))
        .bind(experiment.map(|(id, _)| id))
        .bind(experiment.map(|(_, arm)| arm))
        .execute(&mut **tx)
        .await?;
        Ok(())
    }

    pub async fn job(&self, id: &JobId) -> Result<JobRecord, StoreError> {
        let id = id.as_str();
        let row: JobRow =
            sqlx::query_as(&format!("SELECT {} FROM jobs WHERE id = $1", self.job_columns()))
                .bind(id)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        row.try_into()
    }

    /// A job's status alone (what a cancel waits on).
    pub async fn job_status(&self, id: &JobId) -> Result<JobStatus, StoreError> {
        let id = id.as_str();
        let status: String = sqlx::query_scalar("SELECT status FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        parse_status(id, &status)
    }

    /// A page of the jobs `query` selects, newest first; and how many it selects in all.
    pub async fn list_jobs(
        &self,
        query: &JobQuery,
        page: &PageQuery,
    ) -> Result<(Vec<JobRecord>, u64), StoreError> {
        const WHERE: &str = "WHERE ($1 IS NULL OR status = $1) \
             AND ($2 IS NULL OR tags LIKE $2 ESCAPE '\\') \
             AND ($3 IS NULL OR LOWER(COALESCE(name, '')) LIKE $3 ESCAPE '\\' OR id LIKE $4 ESCAPE '\\')";
        let status = query.status.map(JobStatus::as_str);
        let tag = query.tag.as_deref().map(|t| format!("%\"{}\"%", escape_like(t)));
        let search = query.search.as_deref().map(|q| escape_like(&q.to_lowercase()));
        let contains = search.as_deref().map(|q| format!("%{q}%"));
        let prefix = search.as_deref().map(|q| format!("{q}%"));
        let rows: Vec<JobRow> = sqlx::query_as(&format!(
            "SELECT {} FROM jobs {WHERE} AND {} ORDER BY created_at DESC, id DESC \
             LIMIT $5 OFFSET $6",
            self.job_columns(),
            Listing::Jobs.after(7)
        ))
        .bind(status)
        .bind(tag.as_deref())
        .bind(contains.as_deref())
        .bind(prefix.as_deref())
        .bind(i64::from(page.limit))
        .bind(page.offset as i64)
        .bind(page.after.as_deref())
        .fetch_all(self.pool())
        .await?;
        let total: i64 = sqlx::query_scalar(&format!("SELECT COUNT(*) FROM jobs {WHERE}"))
            .bind(status)
            .bind(tag.as_deref())
            .bind(contains.as_deref())
            .bind(prefix.as_deref())
            .fetch_one(self.pool())
            .await?;
        let jobs = rows.into_iter().map(JobRecord::try_from).collect::<Result<_, _>>()?;
        Ok((jobs, total as u64))
    }

    /// Replaces a job's name, tags and notes (any status: the runner never reads them).
    pub async fn update_job_labels(
        &self,
        id: &JobId,
        labels: &JobLabels,
    ) -> Result<JobRecord, StoreError> {
        let updated = sqlx::query(
            "UPDATE jobs SET name = $2, tags = $3, notes = $4, updated_at = $5 WHERE id = $1",
        )
        .bind(id.as_str())
        .bind(labels.name.as_deref())
        .bind(to_json(&labels.tags))
        .bind(labels.notes.as_deref())
        .bind(self.db_now().await?)
        .execute(self.pool())
        .await?;
        if updated.rows_affected() == 0 {
            return Err(StoreError::NotFound { kind: "job", id: id.to_string() });
        }
        self.job(id).await
    }

    /// Deletes a finished job with its metrics, checkpoint and log, and its policy with that
    /// policy's evaluations — unless the job is queued or running, or an evaluation of its
    /// policy is. One write transaction with the job's row locked, so a worker cannot claim it
    /// in between.
    pub async fn delete_job(&self, id: &JobId) -> Result<DeleteJobOutcome, StoreError> {
        let id = id.as_str();
        let Some((mut tx, status)) = self.begin_delete("jobs", "status", id).await? else {
            return Ok(DeleteJobOutcome::NotFound);
        };
        let status = parse_status(id, &status)?;
        if !status.is_final() {
            return Ok(DeleteJobOutcome::Active(status));
        }
        let busy = super::evaluations::unfinished_evaluations(
            &mut tx,
            "JOIN policies p ON p.id = e.policy_id WHERE p.job_id = $1",
            id,
        )
        .await?;
        if !busy.is_empty() {
            return Ok(DeleteJobOutcome::PolicyInUse(busy));
        }
        let policy: Option<String> =
            sqlx::query_scalar("SELECT id FROM policies WHERE job_id = $1")
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
        if let Some(policy) = &policy {
            let versions = super::models::versions_of_policy(&mut tx, policy).await?;
            if !versions.is_empty() {
                return Ok(DeleteJobOutcome::PolicyRegistered(versions));
            }
        }
        for statement in [
            "DELETE FROM evaluations WHERE policy_id IN (SELECT id FROM policies WHERE job_id = $1)",
            "DELETE FROM policies WHERE job_id = $1",
            "DELETE FROM job_metrics WHERE job_id = $1",
            "DELETE FROM job_checkpoints WHERE job_id = $1",
            "DELETE FROM job_logs WHERE job_id = $1",
            "DELETE FROM job_attempts WHERE job_id = $1",
            "DELETE FROM jobs WHERE id = $1",
        ] {
            sqlx::query(statement).bind(id).execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(DeleteJobOutcome::Deleted { policy: policy.map(PolicyId::from) })
    }

    /// Jobs changed since `since` (their `updated_at`, RFC 3339 as stored), oldest change first:
    /// how an API node follows jobs that workers in other processes run.
    pub async fn jobs_changed_since(&self, since: &str) -> Result<Vec<JobRecord>, StoreError> {
        let rows: Vec<JobRow> = sqlx::query_as(&format!(
            "SELECT {} FROM jobs WHERE updated_at > $1 ORDER BY updated_at, id LIMIT 1000",
            self.job_columns()
        ))
        .bind(since)
        .fetch_all(self.pool())
        .await?;
        rows.into_iter().map(JobRecord::try_from).collect()
    }

    /// Cancels a queued job at once, or flags a running one for its worker. The status read and
    /// the update are one write transaction (the row locked), so a claim cannot slip in between.
    pub async fn request_cancel(&self, job_id: &JobId) -> Result<CancelOutcome, StoreError> {
        let id = job_id.as_str();
        let mut tx = self.begin_write().await?;
        let now = now_in(&mut tx).await?;
        let status: String = sqlx::query_scalar(&format!(
            "SELECT status FROM jobs WHERE id = $1{}",
            self.backend.lock_row()
        ))
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?
        .ok_or_else(|| StoreError::NotFound { kind: "job", id: id.to_owned() })?;
        let outcome = match parse_status(id, &status)? {
            JobStatus::Queued => {
                sqlx::query(&format!(
                    "UPDATE jobs SET status = {}, cancel_requested = 1, updated_at = $1, \
                         finished_at = $1 WHERE id = $2",
                    JobStatus::Cancelled.sql()
                ))
                .bind(&now)
                .bind(id)
                .execute(&mut *tx)
                .await?;
                delete_checkpoint(&mut tx, job_id).await?;
                CancelOutcome::Cancelled
            }
            JobStatus::Running => {
                sqlx::query("UPDATE jobs SET cancel_requested = 1, updated_at = $1 WHERE id = $2")
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
pub(super) async fn delete_checkpoint(
    tx: &mut Transaction<'_, Any>,
    id: &JobId,
) -> Result<(), sqlx::Error> {
    sqlx::query("DELETE FROM job_checkpoints WHERE job_id = $1")
        .bind(id.as_str())
        .execute(&mut **tx)
        .await?;
    Ok(())
}

/// `text` with LIKE's wildcards and escape character escaped (the escape character is a backslash).
fn escape_like(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        if matches!(c, '%' | '_' | '\\') {
            out.push('\\');
        }
        out.push(c);
    }
    out
}
