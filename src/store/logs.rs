//! Each job's log: the lines its workers wrote about it, numbered per job.

use sqlx::{Any, Transaction};

use super::leases::{self, Lease};
use super::{now_in, parse_time, Store, StoreError};
use crate::domain::{JobId, LogLevel, LogRecord};

/// A log line as stored (time and level as text).
#[derive(sqlx::FromRow)]
struct LogRow {
    seq: i64,
    time: String,
    level: String,
    worker: String,
    message: String,
}

impl LogRow {
    fn into_record(self, job: &JobId) -> Result<LogRecord, StoreError> {
        let owner = format!("job {job} log line {}", self.seq);
        let level = LogLevel::parse(&self.level).ok_or_else(|| {
            StoreError::Corrupt(owner.clone(), format!("log level {:?}", self.level))
        })?;
        Ok(LogRecord {
            seq: self.seq as u64,
            time: parse_time(&owner, &self.time)?,
            level,
            worker: self.worker,
            message: self.message,
        })
    }
}

impl Store {
    /// Appends `message` to job `lease.id`'s log as written by `worker`, numbered after the
    /// last line. Fenced like every worker write: refused once another worker took the job.
    pub async fn append_job_log(
        &self,
        lease: &Lease<JobId>,
        worker: &str,
        level: LogLevel,
        message: &str,
    ) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        // Holding the lease row-locks the job on PostgreSQL, so two lines never get one number.
        leases::hold(&mut tx, lease).await?;
        insert_log_line(&mut tx, &lease.id, worker, level, message).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Up to `limit` lines of a job's log after line `after`, in order.
    pub async fn job_log(
        &self,
        id: &JobId,
        after: i64,
        limit: u32,
    ) -> Result<Vec<LogRecord>, StoreError> {
        let rows: Vec<LogRow> = sqlx::query_as(
            "SELECT seq, time, level, worker, message FROM job_logs \
             WHERE job_id = $1 AND seq > $2 ORDER BY seq LIMIT $3",
        )
        .bind(id.as_str())
        .bind(after)
        .bind(i64::from(limit))
        .fetch_all(self.pool())
        .await?;
        rows.into_iter().map(|row| row.into_record(id)).collect()
    }
}

/// Appends a line to job `id`'s log inside `tx`, numbered after its last line (the caller holds
/// the job's row, so two lines never get one number).
pub(super) async fn insert_log_line(
    tx: &mut Transaction<'_, Any>,
    id: &JobId,
    worker: &str,
    level: LogLevel,
    message: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO job_logs (job_id, seq, time, level, worker, message) \
         SELECT $1, COALESCE(MAX(seq), 0) + 1, $2, $3, $4, $5 FROM job_logs WHERE job_id = $1",
    )
    .bind(id.as_str())
    .bind(now_in(tx).await?)
    .bind(level.as_str())
    .bind(worker)
    .bind(message)
    .execute(&mut **tx)
    .await?;
    Ok(())
}
