//! Each job's attempts (`job_attempts`: one row per claim) and the reaper that hands the job of
//! a vanished worker back to the queue after a backoff, or ends it once its attempts are spent.
//!
//! A claim starts an attempt ([`Store::claim_next_job`]); the worker's end of the run ends it in
//! the same transaction as the job's end (succeeded, failed, cancelled, released). A worker that
//! stops renewing its lease ends nothing: the next worker to look for work finds the expired
//! lease ([`Store::reap_expired_jobs`]), records the attempt as `crashed` (with what the worker
//! last said of its memory), and either queues the job again for `now + backoff` or, at its
//! `max_attempts`, discards it with the history in the message. Every decision is taken on the
//! database's clock.

use sqlx::{Any, Transaction};

use super::leases::Lease;
use super::logs::insert_log_line;
use super::{now_in, parse_optional_time, parse_time, Store, StoreError};
use crate::domain::attempt::{crash_message, gave_up_message, MemorySample};
use crate::domain::LogLevel;
use crate::domain::{AttemptOutcome, JobAttempt, JobId, JobStatus, RetryBackoff};

/// A job whose worker's lease expired, as the reaper found and left it.
#[derive(Clone, Debug, PartialEq)]
pub struct ReapedJob {
    pub id: JobId,
    /// `queued` (to be tried again) or `discarded` (its attempts are spent).
    pub status: JobStatus,
    pub message: String,
}

/// An expired running job as the reaper reads it.
#[derive(sqlx::FromRow)]
struct Expired {
    id: String,
    lease_token: i64,
    attempt: i64,
    max_attempts: i64,
    lease_owner: Option<String>,
    step: i64,
}

#[derive(sqlx::FromRow)]
struct AttemptRow {
    attempt: i64,
    worker: String,
    started_at: String,
    ended_at: Option<String>,
    outcome: String,
    message: Option<String>,
}

impl Store {
    /// Records the start of the attempt `lease` claimed (after the claim's own statement: a
    /// worker that dies in between leaves an attempt without a row, which the reaper tolerates).
    pub(super) async fn start_attempt(
        &self,
        lease: &Lease<JobId>,
        worker: &str,
        attempt: u32,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO job_attempts (job_id, claim, attempt, worker, started_at, outcome) \
             VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (job_id, claim) DO NOTHING",
        )
        .bind(lease.id.as_str())
        .bind(lease.token)
        .bind(i64::from(attempt))
        .bind(worker)
        .bind(self.db_now().await?)
        .bind(AttemptOutcome::Running.as_str())
        .execute(self.pool())
        .await?;
        Ok(())
    }

    /// A job's attempts, oldest first.
    pub async fn job_attempts(&self, id: &JobId) -> Result<Vec<JobAttempt>, StoreError> {
        let id = id.as_str();
        let rows: Vec<AttemptRow> = sqlx::query_as(
            "SELECT attempt, worker, started_at, ended_at, outcome, message FROM job_attempts \
             WHERE job_id = $1 ORDER BY claim",
        )
        .bind(id)
        .fetch_all(self.pool())
        .await?;
        let owner = format!("job {id}");
        rows.into_iter()
            .map(|row| {
                Ok(JobAttempt {
                    attempt: u32::try_from(row.attempt).unwrap_or(u32::MAX),
                    worker: row.worker,
                    started_at: parse_time(&owner, &row.started_at)?,
                    ended_at: parse_optional_time(&owner, row.ended_at.as_deref())?,
                    outcome: row
                        .outcome
                        .parse()
                        .map_err(|e| StoreError::Corrupt(owner.clone(), e))?,
                    message: row.message,
                })
            })
            .collect()
    }

    /// Finds running jobs whose lease expired and ends their attempt as `crashed`: each goes
    /// back to the queue, claimable after `backoff`, or is discarded once it has had
    /// `max_attempts`.
    /// Each job is one write transaction that only changes it while the same lease is still
    /// expired, so concurrent reapers (every worker runs this before it claims) and a late
    /// heartbeat never both win. `reaper` names the worker in the job's log.
    pub async fn reap_expired_jobs(
        &self,
        reaper: &str,
        backoff: &RetryBackoff,
    ) -> Result<Vec<ReapedJob>, StoreError> {
        let now_ms = self.backend.now_ms();
        let expired: Vec<Expired> = sqlx::query_as(&format!(
            "SELECT id, lease_token, attempt, max_attempts, lease_owner, step FROM jobs \
             WHERE status = $1 AND lease_expires_ms < {now_ms} ORDER BY id LIMIT 100"
        ))
        .bind(JobStatus::Running.as_str())
        .fetch_all(self.pool())
        .await?;
        let mut reaped = Vec::new();
        for job in expired {
            let memory = match &job.lease_owner {
                Some(worker) => self.worker_memory(worker).await?,
                None => None,
            };
            let worker = job.lease_owner.as_deref().unwrap_or("an unknown worker");
            let crash = crash_message(worker, job.step as u64, memory);
            let attempts = u32::try_from(job.attempt).unwrap_or(u32::MAX);
            let delay = backoff.delay(attempts, rand::random::<f64>());
            if let Some(done) = self.reap(&job, reaper, &crash, delay).await? {
                reaped.push(done);
            }
        }
        Ok(reaped)
    }

    /// One expired job, if its lease is still the expired one (see [`Store::reap_expired_jobs`]).
    async fn reap(
        &self,
        job: &Expired,
        reaper: &str,
        crash: &str,
        delay: std::time::Duration,
    ) -> Result<Option<ReapedJob>, StoreError> {
        let now_ms = self.backend.now_ms();
        let mut tx = self.begin_write().await?;
        // Another reaper (or the worker's own late heartbeat) may be changing this row: skip it
        // rather than wait, and look again on the next turn.
        let still: Option<String> = sqlx::query_scalar(&format!(
            "SELECT id FROM jobs WHERE id = $1 AND lease_token = $2 AND status = $3 \
               AND lease_expires_ms < {now_ms}{}",
            self.backend.skip_locked()
        ))
        .bind(&job.id)
        .bind(job.lease_token)
        .bind(JobStatus::Running.as_str())
        .fetch_optional(&mut *tx)
        .await?;
        if still.is_none() {
            return Ok(None);
        }
        let lease = Lease::new(job.id.clone(), job.lease_token);
        end_attempt(&mut tx, &lease, AttemptOutcome::Crashed, Some(crash)).await?;
        let time = now_in(&mut tx).await?;
        let give_up = job.attempt >= job.max_attempts;
        let (status, message) = if give_up {
            let history = self.crash_count(&mut tx, &job.id).await?;
            let message = gave_up_message(job.attempt as u32, history, crash);
            sqlx::query(
                "UPDATE jobs SET status = $1, error = $2, iterations_per_second = NULL, \
                     updated_at = $3, finished_at = $3, lease_expires_ms = 0, \
                     lease_takeovers = lease_takeovers + 1 WHERE id = $4",
            )
            .bind(JobStatus::Discarded.as_str())
            .bind(&message)
            .bind(&time)
            .bind(&job.id)
            .execute(&mut *tx)
            .await?;
            sqlx::query("DELETE FROM job_checkpoints WHERE job_id = $1")
                .bind(&job.id)
                .execute(&mut *tx)
                .await?;
            (JobStatus::Discarded, message)
        } else {
            let seconds = delay.as_secs_f64();
            let message = format!(
                "attempt {} of {} ended: {crash}; attempt {} starts in {seconds:.0} s or later, \
                 from the last checkpoint",
                job.attempt,
                job.max_attempts,
                job.attempt + 1
            );
            sqlx::query(&format!(
                "UPDATE jobs SET status = $1, iterations_per_second = NULL, updated_at = $2, \
                     lease_expires_ms = 0, scheduled_ms = {now_ms} + $3, \
                     lease_takeovers = lease_takeovers + 1 WHERE id = $4"
            ))
            .bind(JobStatus::Queued.as_str())
            .bind(&time)
            .bind(super::leases::millis(delay))
            .bind(&job.id)
            .execute(&mut *tx)
            .await?;
            (JobStatus::Queued, message)
        };
        insert_log_line(&mut tx, &lease.id, reaper, LogLevel::Error, &message).await?;
        tx.commit().await?;
        Ok(Some(ReapedJob { id: job.id.clone().into(), status, message }))
    }

    /// Attempts of the job that ended in a crash so far (the one being reaped included).
    async fn crash_count(
        &self,
        tx: &mut Transaction<'_, Any>,
        id: &str,
    ) -> Result<u32, sqlx::Error> {
        let count: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM job_attempts WHERE job_id = $1 AND outcome = $2",
        )
        .bind(id)
        .bind(AttemptOutcome::Crashed.as_str())
        .fetch_one(&mut **tx)
        .await?;
        Ok(u32::try_from(count).unwrap_or(u32::MAX))
    }

    /// What worker `id` said of its memory at its last heartbeat.
    async fn worker_memory(&self, id: &str) -> Result<Option<MemorySample>, StoreError> {
        let row: Option<(Option<i64>, Option<i64>)> =
            sqlx::query_as("SELECT rss_bytes, memory_available_bytes FROM workers WHERE id = $1")
                .bind(id)
                .fetch_optional(self.pool())
                .await?;
        Ok(row.and_then(|(rss, available)| {
            Some(MemorySample { rss_bytes: rss? as u64, available_bytes: available? as u64 })
        }))
    }

    /// A worker that came back after its lease expired says so on its attempt (the reaper had
    /// recorded a crash). Its own row only: no fencing needed, the job itself is not touched.
    pub async fn record_lease_lost(
        &self,
        lease: &Lease<JobId>,
        message: &str,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE job_attempts SET outcome = $1, message = $2, ended_at = COALESCE(ended_at, $3) \
             WHERE job_id = $4 AND claim = $5 AND outcome IN ($6, $7)",
        )
        .bind(AttemptOutcome::LeaseLost.as_str())
        .bind(message)
        .bind(self.db_now().await?)
        .bind(lease.id.as_str())
        .bind(lease.token)
        .bind(AttemptOutcome::Running.as_str())
        .bind(AttemptOutcome::Crashed.as_str())
        .execute(self.pool())
        .await?;
        Ok(())
    }
}

/// Ends the attempt `lease` started, inside the transaction that writes how the run ended.
pub(super) async fn end_attempt(
    tx: &mut Transaction<'_, Any>,
    lease: &Lease<JobId>,
    outcome: AttemptOutcome,
    message: Option<&str>,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "UPDATE job_attempts SET outcome = $1, message = $2, ended_at = $3 \
         WHERE job_id = $4 AND claim = $5",
    )
    .bind(outcome.as_str())
    .bind(message)
    .bind(now_in(tx).await?)
    .bind(lease.id.as_str())
    .bind(lease.token)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::algo::{Algorithm, Preset, ResolvedConfig};
    use crate::domain::NewJob;
    use crate::domain::RunnerOptions;
    use crate::store::test_support::store_with_a_dataset;

    const AT_ONCE: RetryBackoff = RetryBackoff { base: Duration::ZERO, max: Duration::ZERO };

    async fn queued_job(store: &Store, dataset: &str, max_attempts: u32) -> JobId {
        let id = JobId::generate();
        let job = NewJob {
            id: id.clone(),
            unlabeled_dataset: dataset.to_owned().into(),
            non_preferred_dataset: None,
            config: ResolvedConfig::preset(Algorithm::Bc, Preset::Service),
            runner: RunnerOptions::default(),
            eval: None,
            labels: Default::default(),
            max_attempts,
            register: None,
        };
        store.insert_job(&job).await.unwrap();
        id
    }

    /// A claim whose lease is already over: the worker "vanishes" at once.
    async fn claim_and_vanish(store: &Store, worker: &str) -> Lease<JobId> {
        let (_, lease) = store.claim_next_job(worker, Duration::ZERO).await.unwrap().unwrap();
        tokio::time::sleep(Duration::from_millis(5)).await;
        lease
    }

    fn outcomes(attempts: &[JobAttempt]) -> Vec<(u32, &str, AttemptOutcome)> {
        attempts.iter().map(|a| (a.attempt, a.worker.as_str(), a.outcome)).collect()
    }

    /// The poison job in the store: each attempt's worker vanishes; the job is queued again
    /// after the backoff (not claimable before it), and fails at its `max_attempts` with the
    /// history in its error, its checkpoint gone and every attempt recorded.
    #[tokio::test]
    async fn a_job_whose_workers_keep_vanishing_is_retried_after_a_backoff_then_fails() {
        let (_dir, store, dataset) = store_with_a_dataset().await;
        let id = queued_job(&store, &dataset, 2).await;
        let first = claim_and_vanish(&store, "w1").await;
        store.save_checkpoint(&first, 7, b"ckpt", &[]).await.unwrap();
        let job = store.job(&id).await.unwrap();
        assert_eq!((job.status, job.attempt, job.max_attempts), (JobStatus::Running, 1, 2));
        assert!(job.lease_expired_at.is_some(), "waiting for a worker");

        let minute = RetryBackoff::new(Duration::from_secs(60));
        let reaped = store.reap_expired_jobs("w2", &minute).await.unwrap();
        assert_eq!(reaped.len(), 1);
        assert_eq!((reaped[0].id.as_str(), reaped[0].status), (id.as_str(), JobStatus::Queued));
        assert!(reaped[0].message.starts_with("attempt 1 of 2 ended: worker w1 stopped"));
        let job = store.job(&id).await.unwrap();
        let wait = job.retry_at.unwrap() - chrono::Utc::now();
        assert!((40..=80).contains(&wait.num_seconds()), "{wait}");
        assert!(job.lease_expired_at.is_none());
        assert!(store.claim_next_job("w2", Duration::ZERO).await.unwrap().is_none(), "backoff");
        assert!(store.reap_expired_jobs("w2", &minute).await.unwrap().is_empty(), "reaped once");

        // Due now: the second attempt resumes from the checkpoint, and its worker vanishes too.
        sqlx::query("UPDATE jobs SET scheduled_ms = 0").execute(store.pool()).await.unwrap();
        let second = claim_and_vanish(&store, "w2").await;
        assert_eq!(store.checkpoint(&id).await.unwrap().map(|c| c.0), Some(7));
        let reaped = store.reap_expired_jobs("w3", &AT_ONCE).await.unwrap();
        assert_eq!(reaped[0].status, JobStatus::Discarded);
        let job = store.job(&id).await.unwrap();
        assert_eq!((job.status, job.attempt), (JobStatus::Discarded, 2));
        let error = job.error.unwrap();
        assert!(error.starts_with("gave up after 2 attempts (2 ended with the worker gone)"));
        assert!(error.contains("out-of-memory killer"), "{error}");
        assert!(job.finished_at.is_some() && store.checkpoint(&id).await.unwrap().is_none());
        let attempts = store.job_attempts(&id).await.unwrap();
        let crashed = AttemptOutcome::Crashed;
        assert_eq!(outcomes(&attempts), [(1, "w1", crashed), (2, "w2", crashed)]);
        assert!(attempts.iter().all(|a| a.ended_at.is_some() && a.message.is_some()));
        assert!(store.claim_next_job("w3", Duration::from_secs(9)).await.unwrap().is_none());
        // The vanished worker's late writes are refused; coming back, it says so on its attempt.
        assert!(matches!(
            store.finish_job(&second, JobStatus::Failed, Some("late"), &[]).await,
            Err(StoreError::LeaseLost(_))
        ));
        store.record_lease_lost(&second, "came back").await.unwrap();
        let attempts = store.job_attempts(&id).await.unwrap();
        assert_eq!(attempts[1].outcome, AttemptOutcome::LeaseLost);
        let job = store.job(&id).await.unwrap();
        assert_eq!((job.status, job.attempt), (JobStatus::Discarded, 2), "the job is untouched");
    }

    /// A run handed back on shutdown is not the job's fault: the attempt is given back, and the
    /// resumed run is the same attempt number; its success ends that attempt.
    #[tokio::test]
    async fn a_released_run_gives_its_attempt_back() {
        let (_dir, store, dataset) = store_with_a_dataset().await;
        let id = queued_job(&store, &dataset, 1).await;
        let (_, lease) =
            store.claim_next_job("w1", Duration::from_secs(60)).await.unwrap().unwrap();
        store.release_job(&lease, "the worker shut down").await.unwrap();
        assert_eq!(store.job(&id).await.unwrap().attempt, 0);
        let (job, lease) =
            store.claim_next_job("w2", Duration::from_secs(60)).await.unwrap().unwrap();
        assert_eq!((job.attempt, job.max_attempts), (1, 1));
        store.finish_job(&lease, JobStatus::Cancelled, None, &[]).await.unwrap();
        let attempts = store.job_attempts(&id).await.unwrap();
        let expected = [(1, "w1", AttemptOutcome::Released), (1, "w2", AttemptOutcome::Cancelled)];
        assert_eq!(outcomes(&attempts), expected);
        assert_eq!(attempts[0].message.as_deref(), Some("the worker shut down"));
    }
}
