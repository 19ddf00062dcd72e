//! A claimed job's life under its lease: the claim, progress, checkpoints, a release back to
//! the queue, and its end (succeeded with its policy, failed or cancelled), each checked
//! against the lease inside its write.

use std::time::Duration;

use sqlx::{Any, Transaction};

use super::attempts::end_attempt;
use super::evaluations::{insert_training_evaluation, TrainingEvaluation};
use super::job_metrics::{insert_metric_rows, last_metric_values_in};
use super::jobs::delete_checkpoint;
use super::leases::{self, Lease};
use super::policies::NewPolicy;
use super::{now_in, optional_real, Store, StoreError};
use crate::domain::model::{AliasName, ModelName, MoveNote};
use crate::domain::{
    AttemptOutcome, JobId, JobRecord, JobStatus, LogLevel, MetricRecord, PolicyId,
};

/// A running job's progress as the worker reports it.
#[derive(Clone, Debug)]
pub struct ProgressUpdate<'a> {
    pub step: u64,
    pub phase: &'a str,
    pub iterations_per_second: Option<f64>,
    pub alpha_hat: Option<f64>,
}

impl Store {
    /// Claims the next job for `worker` with a lease of `lease` from now, in one statement: a
    /// queued job whose retry time has come (a job whose worker died is queued again by
    /// [`Store::reap_expired_jobs`], and resumes from its checkpoint). Jobs that were already
    /// started once go first, then the oldest. On PostgreSQL concurrent claimers skip each
    /// other's rows. The claim starts the job's next attempt.
    pub async fn claim_next_job(
        &self,
        worker: &str,
        lease_duration: Duration,
    ) -> Result<Option<(JobRecord, Lease<JobId>)>, StoreError> {
        let claim = leases::Claim {
            claimable: leases::Claimable::QueuedAndDue,
            set: "updated_at = $1, started_at = COALESCE(started_at, $1), \
                  iterations_per_second = NULL, attempt = attempt + 1, scheduled_ms = 0",
            order: "started_at IS NULL, created_at, id",
        };
        let claimed = claim.run::<JobId>(self, worker, lease_duration).await?;
        let Some(lease) = claimed else { return Ok(None) };
        let job = self.job(&lease.id).await;
        if let Ok(job) = &job {
            self.start_attempt(&lease, worker, job.attempt).await?;
        }
        match job {
            // A row this version cannot read (e.g. written by another version) can never run:
            // it fails with the reason instead of blocking the queue.
            Err(StoreError::Corrupt(_, reason)) => {
                tracing::error!(job_id = %lease.id, %reason, "a queued job cannot be read; it fails");
                self.finish_job(&lease, JobStatus::Failed, Some(&reason), &[]).await?;
                Box::pin(self.claim_next_job(worker, lease_duration)).await
            }
            job => job.map(|job| Some((job, lease))),
        }
    }

    /// A running job handed back to the queue by the worker holding its lease (graceful
    /// shutdown after its checkpoint, or a store that cannot take its writes).
    pub async fn release_job(&self, lease: &Lease<JobId>, reason: &str) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        let now = now_in(&mut tx).await?;
        // Not the job's fault: the attempt is given back.
        sqlx::query(&format!(
            "UPDATE jobs SET status = {}, updated_at = $1, iterations_per_second = NULL, \
                 lease_expires_ms = 0, attempt = attempt - 1 WHERE id = $2",
            JobStatus::Queued.sql()
        ))
        .bind(now)
        .bind(lease.id.as_str())
        .execute(&mut *tx)
        .await?;
        end_attempt(&mut tx, lease, AttemptOutcome::Released, Some(reason)).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Records progress; returns whether a cancel was requested meanwhile.
    pub async fn update_progress(
        &self,
        lease: &Lease<JobId>,
        progress: &ProgressUpdate<'_>,
    ) -> Result<bool, StoreError> {
        let cancel: Option<i64> = sqlx::query_scalar(&format!(
            "UPDATE jobs SET step = $1, phase = $2, \
                 iterations_per_second = CAST($3 AS DOUBLE PRECISION), \
                 alpha_hat = COALESCE(CAST($4 AS DOUBLE PRECISION), alpha_hat), updated_at = $5 \
             WHERE id = $6 AND lease_token = $7 AND status = {} \
             RETURNING cancel_requested",
            JobStatus::Running.sql()
        ))
        .bind(progress.step as i64)
        .bind(progress.phase)
        .bind(optional_real(progress.iterations_per_second))
        .bind(optional_real(progress.alpha_hat))
        .bind(self.db_now().await?)
        .bind(lease.id.as_str())
        .bind(lease.token)
        .fetch_optional(self.pool())
        .await?;
        match cancel {
            Some(flag) => Ok(flag != 0),
            None => Err(StoreError::LeaseLost(lease.id.to_string())),
        }
    }

    /// Writes the pending metrics and replaces the job's checkpoint in one transaction, so the
    /// checkpoint never refers to metrics that are not stored.
    pub async fn save_checkpoint(
        &self,
        lease: &Lease<JobId>,
        step: u64,
        data: &[u8],
        pending_metrics: &[MetricRecord],
    ) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        insert_metric_rows(&mut tx, &lease.id, pending_metrics).await?;
        sqlx::query(
            "INSERT INTO job_checkpoints (job_id, step, data, created_at) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (job_id) DO UPDATE SET step = excluded.step, data = excluded.data, \
                 created_at = excluded.created_at",
        )
        .bind(lease.id.as_str())
        .bind(step as i64)
        .bind(data)
        .bind(now_in(&mut tx).await?)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// The job's last checkpoint: (step, bytes).
    pub async fn checkpoint(&self, id: &JobId) -> Result<Option<(u64, Vec<u8>)>, StoreError> {
        let id = id.as_str();
        let row: Option<(i64, Vec<u8>)> =
            sqlx::query_as("SELECT step, data FROM job_checkpoints WHERE job_id = $1")
                .bind(id)
                .fetch_optional(self.pool())
                .await?;
        Ok(row.map(|(step, data)| (step as u64, data)))
    }

    /// Deletes the metrics recorded after `step` (a resume from the checkpoint at `step`
    /// recomputes them; deleting first keeps every (name, step) row exactly once).
    pub async fn discard_metrics_after(
        &self,
        lease: &Lease<JobId>,
        step: u64,
    ) -> Result<u64, StoreError> {
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        let done = sqlx::query("DELETE FROM job_metrics WHERE job_id = $1 AND step > $2")
            .bind(lease.id.as_str())
            .bind(step as i64)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(done.rows_affected())
    }

    /// Completes a job in one transaction: its last metrics, its policy (whose final metrics are
    /// the last values stored, read in the same transaction; with the evaluation the run took at
    /// its end, if its job has an `eval` block), the model version its `register` asks for and
    /// the `succeeded` status; the checkpoint is no longer needed. Returns the version
    /// registered (model, number), if any; the job's log says what became of its `register` in
    /// the same transaction (as `worker`), so it never tells of a registration that did not
    /// commit.
    pub async fn finish_job_succeeded(
        &self,
        lease: &Lease<JobId>,
        worker: &str,
        pending_metrics: &[MetricRecord],
        run: &SucceededRun<'_>,
    ) -> Result<Option<(String, u32)>, StoreError> {
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        insert_metric_rows(&mut tx, &lease.id, pending_metrics).await?;
        let job_id = lease.id.clone();
        let final_metrics = last_metric_values_in(&mut tx, job_id.as_str()).await?;
        let policy = NewPolicy {
            id: run.policy_id,
            job_id: &job_id,
            artifact: run.artifact,
            final_metrics: &final_metrics,
            alpha_hat: run.alpha_hat,
        };
        super::policies::insert_policy(&mut tx, &policy).await?;
        let now = now_in(&mut tx).await?;
        if let Some(evaluation) = run.evaluation {
            insert_training_evaluation(&mut tx, policy.id, evaluation, &now).await?;
        }
        let registered = self.register_policy(&mut tx, &lease.id, worker, policy.id).await?;
        sqlx::query(&format!(
            "UPDATE jobs SET status = {}, policy_id = $1, step = $2, \
                 alpha_hat = COALESCE(CAST($3 AS DOUBLE PRECISION), alpha_hat), \
                 iterations_per_second = NULL, \
                 updated_at = $4, finished_at = $4 \
             WHERE id = $5",
            JobStatus::Succeeded.sql()
        ))
        .bind(policy.id.as_str())
        .bind(run.step as i64)
        .bind(optional_real(policy.alpha_hat))
        .bind(&now)
        .bind(lease.id.as_str())
        .execute(&mut *tx)
        .await?;
        delete_checkpoint(&mut tx, &lease.id).await?;
        end_attempt(&mut tx, lease, AttemptOutcome::Succeeded, None).await?;
        tx.commit().await?;
        Ok(registered)
    }

    /// The job's `register`, inside its completion. A delete of the model is refused while the
    /// job is queued or running; one that slipped in between the job's check and its insert
    /// leaves the policy unregistered (logged), never the job failed.
    async fn register_policy(
        &self,
        tx: &mut Transaction<'_, Any>,
        job_id: &JobId,
        worker: &str,
        policy_id: &PolicyId,
    ) -> Result<Option<(String, u32)>, StoreError> {
        let (model, alias): (Option<String>, Option<String>) =
            sqlx::query_as("SELECT register_model, register_alias FROM jobs WHERE id = $1")
                .bind(job_id.as_str())
                .fetch_one(&mut **tx)
                .await?;
        let Some(model) = model else { return Ok(None) };
        // Both were parsed when the job was queued; a stored name that no longer parses is a
        // corrupt row.
        let corrupt = |e: String| StoreError::Corrupt(format!("job {job_id}"), e);
        let model = ModelName::parse(&model).map_err(corrupt)?;
        let alias = alias.map(|a| AliasName::parse(&a)).transpose().map_err(corrupt)?;
        let source = format!("job {job_id}");
        let reason = Some("registered on success".into());
        let note = MoveNote { actor: source.clone(), reason, expected_version: None };
        let version = super::models::NewVersion {
            model: &model,
            policy_id: policy_id.as_str(),
            description: "",
            source: &source,
            alias: alias.as_ref().map(|alias| (alias, &note)),
        };
        let (level, message, registered) = match super::models::register_in(tx, self, &version)
            .await
        {
            Ok(number) => {
                let moved = alias.as_ref().map(|a| format!(", alias {a} moved to it"));
                let message = format!(
                    "registered the policy as version {number} of model {model}{}",
                    moved.unwrap_or_default()
                );
                (LogLevel::Info, message, Some((model.as_str().to_owned(), number)))
            }
            Err(StoreError::NotFound { kind: "model", .. }) => {
                tracing::warn!(%model, %job_id, "the job's model was deleted: policy not registered");
                let message = format!(
                    "model {model} was deleted before the job ended: the policy was not \
                     registered (register it with POST /v1/models/{{name}}/versions)"
                );
                (LogLevel::Warn, message, None)
            }
            Err(e) => return Err(e),
        };
        super::logs::insert_log_line(tx, job_id, worker, level, &message).await?;
        Ok(registered)
    }

    /// Ends a job as `failed` (with `error`) or `cancelled`, storing its last metrics; its
    /// metrics history stays.
    pub async fn finish_job(
        &self,
        lease: &Lease<JobId>,
        status: JobStatus,
        error: Option<&str>,
        pending_metrics: &[MetricRecord],
    ) -> Result<(), StoreError> {
        debug_assert!(matches!(status, JobStatus::Failed | JobStatus::Cancelled));
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        insert_metric_rows(&mut tx, &lease.id, pending_metrics).await?;
        let now = now_in(&mut tx).await?;
        sqlx::query(
            "UPDATE jobs SET status = $1, error = $2, iterations_per_second = NULL, \
                 updated_at = $3, finished_at = $3 WHERE id = $4",
        )
        .bind(status.as_str())
        .bind(error)
        .bind(now)
        .bind(lease.id.as_str())
        .execute(&mut *tx)
        .await?;
        delete_checkpoint(&mut tx, &lease.id).await?;
        let outcome = match status {
            JobStatus::Cancelled => AttemptOutcome::Cancelled,
            _ => AttemptOutcome::Failed,
        };
        end_attempt(&mut tx, lease, outcome, error).await?;
        tx.commit().await?;
        Ok(())
    }
}

/// What a succeeded run stores: its policy (the final metrics are read when it is stored), the
/// step it ended at and the evaluation it took at its end.
pub struct SucceededRun<'a> {
    pub policy_id: &'a crate::domain::PolicyId,
    pub artifact: &'a crate::algo::PolicyArtifact,
    pub alpha_hat: Option<f64>,
    pub step: u64,
    pub evaluation: Option<&'a TrainingEvaluation>,
}
