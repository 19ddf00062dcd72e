//! Leases and the worker registry: what lets many worker processes, on one machine or many,
//! share one queue safely.
//!
//! A claim gives the worker a [`Lease`] on the job (or evaluation): the row's `lease_token`,
//! incremented by every claim, and an expiry on the database's clock that the worker's
//! heartbeat keeps pushing forward. A job whose lease expired (its worker died, lost its
//! machine, or stalled) is claimable again, and the next claim takes it over with a new token.
//! Every write a worker makes for the job names its token and is refused with
//! [`StoreError::LeaseLost`] once the token changed (fencing): a worker that was paused past its
//! lease and then wakes up cannot write anything more for a job another worker now runs.

use std::time::Duration;

use sqlx::{Any, Transaction};

use super::{parse_time, Store, StoreError};
use crate::domain::attempt::MemorySample;
use crate::domain::{EvaluationId, JobId, JobStatus, WorkerRecord};

/// What a lease is held on: a job or an evaluation, each in its own table. The lease's type
/// names its table, so a job's lease cannot fence a write to an evaluation.
pub trait Leased: Clone + std::fmt::Debug + std::fmt::Display + From<String> {
    const TABLE: LeaseTable;

    fn as_str(&self) -> &str;
}

impl Leased for JobId {
    const TABLE: LeaseTable = LeaseTable::Jobs;

    fn as_str(&self) -> &str {
        JobId::as_str(self)
    }
}

impl Leased for EvaluationId {
    const TABLE: LeaseTable = LeaseTable::Evaluations;

    fn as_str(&self) -> &str {
        EvaluationId::as_str(self)
    }
}

/// A worker's claim on one running job (`Lease<JobId>`) or evaluation (`Lease<EvaluationId>`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lease<I> {
    pub id: I,
    /// The row's `lease_token` at the claim; a later claim by anyone changes it.
    pub token: i64,
}

impl<I: Leased> Lease<I> {
    pub fn new(id: impl Into<I>, token: i64) -> Self {
        Lease { id: id.into(), token }
    }
}

/// A worker's row in the registry, as stored.
#[derive(sqlx::FromRow)]
struct WorkerRow {
    id: String,
    host: String,
    pid: i64,
    concurrency: i64,
    started_at: String,
    /// Milliseconds since its last heartbeat, on the database's clock.
    heartbeat_age_ms: i64,
}

impl WorkerRow {
    fn into_record(self) -> Result<WorkerRecord, StoreError> {
        let owner = format!("worker {}", self.id);
        let count = |what: &str, n: i64| {
            u32::try_from(n).map_err(|_| StoreError::Corrupt(owner.clone(), format!("{what} {n}")))
        };
        Ok(WorkerRecord {
            pid: count("pid", self.pid)?,
            concurrency: count("concurrency", self.concurrency)?,
            started_at: parse_time(&owner, &self.started_at)?,
            // A heartbeat from a clock a little ahead of the database's is not in the future.
            heartbeat_age: Duration::from_millis(self.heartbeat_age_ms.max(0) as u64),
            host: self.host,
            id: self.id,
        })
    }
}

/// Lease counts for /metrics.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LeaseStats {
    /// Running jobs whose lease has expired and that no worker has taken over yet.
    pub expired_jobs: i64,
    /// Claims, over all jobs, that took a job over after its worker's lease expired.
    pub takeovers: i64,
    /// Running jobs per lease owner.
    pub running_by_worker: Vec<(String, i64)>,
}

/// Lease durations in milliseconds as bound to SQL.
pub(super) fn millis(duration: Duration) -> i64 {
    i64::try_from(duration.as_millis()).unwrap_or(i64::MAX)
}

/// Inside a write transaction: confirms that `lease` still holds its running row (in its id's
/// table) and (on PostgreSQL) locks that row until the transaction ends, so no claim can take it
/// over between this check and the commit. Every fenced write starts with it.
pub(super) async fn hold<I: Leased>(
    tx: &mut Transaction<'_, Any>,
    lease: &Lease<I>,
) -> Result<(), StoreError> {
    let held = sqlx::query(&format!(
        "UPDATE {} SET lease_token = lease_token WHERE id = $1 AND lease_token = $2 \
         AND status = {}",
        I::TABLE.as_str(),
        JobStatus::Running.sql()
    ))
    .bind(lease.id.as_str())
    .bind(lease.token)
    .execute(&mut **tx)
    .await?;
    if held.rows_affected() == 0 {
        return Err(StoreError::LeaseLost(lease.id.to_string()));
    }
    Ok(())
}

/// The single statement that claims the next row of a queue: a queued row, or a running one
/// whose lease expired, in `order`; it becomes `running` under a new lease token for `worker`.
/// On PostgreSQL concurrent claimers skip the rows another is taking (`SKIP LOCKED`); SQLite
/// runs one write at a time. The statement binds `$1` now (RFC 3339), `$2` the worker, `$3` the
/// lease in milliseconds.
pub(super) struct Claim {
    pub claimable: Claimable,
    /// The table's own `SET` assignments (they see the row's old values).
    pub set: &'static str,
    pub order: &'static str,
}

/// Which rows a claim may take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Claimable {
    /// Queued rows, and running rows whose lease expired (taken over in the claim itself:
    /// evaluations, which are short and cheap to redo).
    QueuedOrExpired,
    /// Queued rows whose `scheduled_ms` has come (jobs: an expired lease first goes back to the
    /// queue through the reaper, which counts the attempt and sets the backoff).
    QueuedAndDue,
}

impl Claim {
    /// Runs the claim on `I`'s table: the lease on the claimed row.
    pub async fn run<I: Leased>(
        &self,
        store: &Store,
        worker: &str,
        lease: Duration,
    ) -> Result<Option<Lease<I>>, sqlx::Error> {
        let (table, now_ms) = (I::TABLE.as_str(), store.backend.now_ms());
        let (queued, running) = (JobStatus::Queued.sql(), JobStatus::Running.sql());
        let claimable = match self.claimable {
            Claimable::QueuedOrExpired => format!(
                "(status = {queued} OR (status = {running} AND lease_expires_ms < {now_ms}))"
            ),
            Claimable::QueuedAndDue => format!("(status = {queued} AND scheduled_ms <= {now_ms})"),
        };
        let claimed: Option<(String, i64)> = sqlx::query_as(&format!(
            "UPDATE {table} SET status = {running}, {}, lease_owner = $2, \
                 lease_token = lease_token + 1, lease_expires_ms = {now_ms} + $3 \
             WHERE id = (SELECT id FROM {table} WHERE {claimable} \
                         ORDER BY {} LIMIT 1{}) \
               AND {claimable} \
             RETURNING id, lease_token",
            self.set,
            self.order,
            store.backend.skip_locked()
        ))
        .bind(store.db_now().await?)
        .bind(worker)
        .bind(millis(lease))
        .fetch_optional(store.pool())
        .await?;
        Ok(claimed.map(|(id, token)| Lease::new(id, token)))
    }
}

impl Store {
    /// Pushes the lease's expiry `duration` past now (the worker's heartbeat).
    pub async fn renew_lease<I: Leased>(
        &self,
        lease: &Lease<I>,
        duration: Duration,
    ) -> Result<(), StoreError> {
        let renewed = sqlx::query(&format!(
            "UPDATE {} SET lease_expires_ms = {} + $1 \
             WHERE id = $2 AND lease_token = $3 AND status = {}",
            I::TABLE.as_str(),
            self.backend.now_ms(),
            JobStatus::Running.sql()
        ))
        .bind(millis(duration))
        .bind(lease.id.as_str())
        .bind(lease.token)
        .execute(self.pool())
        .await?;
        if renewed.rows_affected() == 0 {
            return Err(StoreError::LeaseLost(lease.id.to_string()));
        }
        Ok(())
    }

    /// Adds (or refreshes) a worker's row; rows of workers silent for `forget_after` are
    /// removed meanwhile (a worker that died without saying goodbye).
    pub async fn register_worker(
        &self,
        id: &str,
        concurrency: usize,
        forget_after: Duration,
    ) -> Result<(), StoreError> {
        let now_ms = self.backend.now_ms();
        sqlx::query(&format!("DELETE FROM workers WHERE heartbeat_ms < {now_ms} - $1"))
            .bind(millis(forget_after))
            .execute(self.pool())
            .await?;
        sqlx::query(&format!(
            "INSERT INTO workers (id, host, pid, concurrency, started_at, heartbeat_ms) \
             VALUES ($1, $2, $3, $4, $5, {now_ms}) \
             ON CONFLICT (id) DO UPDATE SET heartbeat_ms = excluded.heartbeat_ms"
        ))
        .bind(id)
        .bind(host_name())
        .bind(i64::from(std::process::id()))
        .bind(concurrency as i64)
        .bind(self.db_now().await?)
        .execute(self.pool())
        .await?;
        Ok(())
    }

    /// Records a worker's heartbeat, with what it says of its memory (kept so that the end of
    /// a job whose worker vanished can say whether memory ran out).
    pub async fn worker_heartbeat(
        &self,
        id: &str,
        memory: Option<MemorySample>,
    ) -> Result<(), StoreError> {
        let bytes = |b: u64| i64::try_from(b).unwrap_or(i64::MAX);
        sqlx::query(&format!(
            "UPDATE workers SET heartbeat_ms = {}, rss_bytes = $2, memory_available_bytes = $3 \
             WHERE id = $1",
            self.backend.now_ms()
        ))
        .bind(id)
        .bind(memory.map(|m| bytes(m.rss_bytes)))
        .bind(memory.map(|m| bytes(m.available_bytes)))
        .execute(self.pool())
        .await?;
        Ok(())
    }

    /// Removes a worker's row (it stops cleanly).
    pub async fn remove_worker(&self, id: &str) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM workers WHERE id = $1").bind(id).execute(self.pool()).await?;
        Ok(())
    }

    /// The registered workers, by id.
    pub async fn workers(&self) -> Result<Vec<WorkerRecord>, StoreError> {
        let rows: Vec<WorkerRow> = sqlx::query_as(&format!(
            "SELECT id, host, pid, concurrency, started_at, \
                 {} - heartbeat_ms AS heartbeat_age_ms \
             FROM workers ORDER BY id",
            self.backend.now_ms()
        ))
        .fetch_all(self.pool())
        .await?;
        rows.into_iter().map(WorkerRow::into_record).collect()
    }

    pub async fn lease_stats(&self) -> Result<LeaseStats, StoreError> {
        let expired_jobs: i64 = sqlx::query_scalar(&format!(
            "SELECT COUNT(*) FROM jobs WHERE status = {} AND lease_expires_ms < {}",
            JobStatus::Running.sql(),
            self.backend.now_ms()
        ))
        .fetch_one(self.pool())
        .await?;
        let takeovers: Option<i64> =
            sqlx::query_scalar("SELECT CAST(SUM(lease_takeovers) AS BIGINT) FROM jobs")
                .fetch_one(self.pool())
                .await?;
        let running_by_worker = sqlx::query_as(&format!(
            "SELECT COALESCE(lease_owner, ''), COUNT(*) FROM jobs WHERE status = {} \
             GROUP BY lease_owner ORDER BY 1",
            JobStatus::Running.sql()
        ))
        .fetch_all(self.pool())
        .await?;
        Ok(LeaseStats { expired_jobs, takeovers: takeovers.unwrap_or(0), running_by_worker })
    }
}

/// The two queues that hand out leases.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LeaseTable {
    Jobs,
    Evaluations,
}

impl LeaseTable {
    fn as_str(self) -> &'static str {
        match self {
            LeaseTable::Jobs => "jobs",
            LeaseTable::Evaluations => "evaluations",
        }
    }
}

/// This machine's name (for the worker registry and the default worker id).
pub fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|name| name.trim().to_owned())
        .filter(|name| !name.is_empty())
        .unwrap_or_else(|| "localhost".to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::{Algorithm, Preset, ResolvedConfig};
    use crate::domain::MetricRecord;
    use crate::domain::NewJob;
    use crate::domain::{JobId, JobStatus, RetryBackoff, RunnerOptions};
    use crate::store::job_runs::ProgressUpdate;
    use crate::store::test_support::store_with_a_dataset;

    async fn store_with_a_queued_job() -> (tempfile::TempDir, Store, JobId) {
        let (dir, store, dataset) = store_with_a_dataset().await;
        let id = JobId::generate();
        let job = NewJob {
            id: id.clone(),
            unlabeled_dataset: dataset.into(),
            non_preferred_dataset: None,
            config: ResolvedConfig::preset(Algorithm::Bc, Preset::Service),
            runner: RunnerOptions::default(),
            eval: None,
            labels: Default::default(),
            max_attempts: 3,
            register: None,
        };
        store.insert_job(&job).await.unwrap();
        (dir, store, id)
    }

    fn metric(step: u64) -> MetricRecord {
        MetricRecord { name: "loss".into(), step, value: 1.0, time: chrono::Utc::now() }
    }

    /// The fencing rule on its own: once a second worker claimed the job after the first one's
    /// lease expired, every write with the first lease is refused and changes nothing, while the
    /// second worker's writes go through.
    #[tokio::test]
    async fn a_taken_over_lease_can_write_nothing() {
        let (_dir, store, id) = store_with_a_queued_job().await;
        // A lease that is already over when granted: the next claim takes the job over.
        let (_, stale) = store.claim_next_job("worker-a", Duration::ZERO).await.unwrap().unwrap();
        // Past the expiry's millisecond: a lease is reaped once strictly expired.
        tokio::time::sleep(Duration::from_millis(5)).await;
        let at_once = RetryBackoff::new(Duration::ZERO);
        let reaped = store.reap_expired_jobs("worker-b", &at_once).await.unwrap();
        assert_eq!(reaped.iter().map(|r| r.status).collect::<Vec<_>>(), [JobStatus::Queued]);
        let (job, fresh) =
            store.claim_next_job("worker-b", Duration::from_secs(60)).await.unwrap().unwrap();
        assert_eq!((job.status, job.worker.as_deref()), (JobStatus::Running, Some("worker-b")));
        assert_eq!(fresh.token, stale.token + 1);
        assert!(store.claim_next_job("worker-c", Duration::from_secs(60)).await.unwrap().is_none());

        let progress = ProgressUpdate {
            step: 5,
            phase: "policy",
            iterations_per_second: None,
            alpha_hat: None,
        };
        let lost = |r: Result<(), StoreError>| matches!(r, Err(StoreError::LeaseLost(_)));
        assert!(lost(store.update_progress(&stale, &progress).await.map(drop)));
        assert!(lost(store.insert_metrics(&stale, &[metric(1)]).await));
        assert!(lost(store.save_checkpoint(&stale, 1, b"ckpt", &[metric(1)]).await));
        assert!(lost(store.discard_metrics_after(&stale, 0).await.map(drop)));
        assert!(lost(store.renew_lease(&stale, Duration::from_secs(60)).await));
        assert!(lost(store.release_job(&stale, "shutdown").await));
        assert!(lost(store.finish_job(&stale, JobStatus::Failed, Some("late"), &[]).await));
        let unchanged = store.job(&id).await.unwrap();
        assert_eq!((unchanged.status, unchanged.step), (JobStatus::Running, 0));
        assert!(store.job_metrics(&id, None).await.unwrap().is_empty());
        assert!(store.checkpoint(&id).await.unwrap().is_none());

        store.update_progress(&fresh, &progress).await.unwrap();
        store.save_checkpoint(&fresh, 5, b"ckpt", &[metric(5)]).await.unwrap();
        assert_eq!(store.job(&id).await.unwrap().step, 5);
        assert_eq!(store.job_metrics(&id, None).await.unwrap().len(), 1);
        let stats = store.lease_stats().await.unwrap();
        assert_eq!(stats.takeovers, 1);
        assert_eq!(stats.running_by_worker, vec![("worker-b".to_owned(), 1)]);
        assert_eq!(stats.expired_jobs, 0);
    }
}
