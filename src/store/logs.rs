//! Each job's log: the lines its workers wrote about it, numbered per job.

use sqlx::{Any, Transaction};

use super::leases::{self, Lease, LeaseTable};
use super::{now, Store, StoreError};

/// How bad a log line is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogLevel {
    Info,
    Warn,
    Error,
}

impl LogLevel {
    pub fn as_str(self) -> &'static str {
        match self {
            LogLevel::Info => "info",
            LogLevel::Warn => "warn",
            LogLevel::Error => "error",
        }
    }
}

/// A stored log line.
#[derive(Clone, Debug, PartialEq, sqlx::FromRow)]
pub struct LogRow {
    pub seq: i64,
    pub time: String,
    pub level: String,
    pub worker: String,
    pub message: String,
}

impl Store {
    /// Appends `message` to job `lease.id`'s log as written by `worker`, numbered after the
    /// last line. Fenced like every worker write: refused once another worker took the job.
    pub async fn append_job_log(
        &self,
        lease: &Lease,
        worker: &str,
        level: LogLevel,
        message: &str,
    ) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        // Holding the lease row-locks the job on PostgreSQL, so two lines never get one number.
        leases::hold(&mut tx, LeaseTable::Jobs, lease).await?;
        insert_log_line(&mut tx, &lease.id, worker, level, message).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Up to `limit` lines of a job's log after line `after`, in order.
    pub async fn job_log(
        &self,
        id: &str,
        after: i64,
        limit: u32,
    ) -> Result<Vec<LogRow>, StoreError> {
        Ok(sqlx::query_as(
            "SELECT seq, time, level, worker, message FROM job_logs \
             WHERE job_id = $1 AND seq > $2 ORDER BY seq LIMIT $3",
        )
        .bind(id)
        .bind(after)
        .bind(i64::from(limit))
        .fetch_all(self.pool())
        .await?)
    }
}

/// Appends a line to job `id`'s log inside `tx`, numbered after its last line (the caller holds
/// the job's row, so two lines never get one number).
pub(super) async fn insert_log_line(
    tx: &mut Transaction<'_, Any>,
    id: &str,
    worker: &str,
    level: LogLevel,
    message: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO job_logs (job_id, seq, time, level, worker, message) \
         SELECT $1, COALESCE(MAX(seq), 0) + 1, $2, $3, $4, $5 FROM job_logs WHERE job_id = $1",
    )
    .bind(id)
    .bind(now())
    .bind(level.as_str())
    .bind(worker)
    .bind(message)
    .execute(&mut **tx)
    .await?;
    Ok(())
}
