//! The training queue's table, as far as the dataset API and /metrics read it.

use super::Store;

/// Every job status, in lifecycle order.
pub const JOB_STATUSES: [&str; 5] = ["queued", "running", "succeeded", "failed", "cancelled"];

impl Store {
    /// Number of jobs in each status, every status listed (zero when there are none).
    pub async fn job_counts_by_status(&self) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        let rows: Vec<(String, i64)> =
            sqlx::query_as("SELECT status, COUNT(*) FROM jobs GROUP BY status")
                .fetch_all(self.pool())
                .await?;
        Ok(JOB_STATUSES
            .iter()
            .map(|&status| {
                let count = rows.iter().find(|(s, _)| s == status).map_or(0, |(_, n)| *n);
                (status, count)
            })
            .collect())
    }
}
