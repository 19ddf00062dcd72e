//! A job's metrics: the time series a run records, written under its lease and read by name.

use sqlx::{Any, Transaction};

use super::leases::{self, Lease};
use super::{parse_time, placeholders, Store, StoreError};
use crate::domain::{rfc3339, JobId, MetricRecord};

/// A metric a job recorded: how many points, over which steps, and its latest value.
#[derive(Clone, Debug, PartialEq, sqlx::FromRow)]
pub struct MetricSummary {
    pub name: String,
    pub points: i64,
    pub first_step: i64,
    pub last_step: i64,
}

/// A metric sample as stored (its time as text).
#[derive(sqlx::FromRow)]
struct MetricRow {
    name: String,
    step: i64,
    value: f64,
    time: String,
}

impl MetricRow {
    fn into_record(self, job: &JobId) -> Result<MetricRecord, StoreError> {
        let owner = format!("job {job} metric {} at step {}", self.name, self.step);
        Ok(MetricRecord {
            time: parse_time(&owner, &self.time)?,
            name: self.name,
            step: self.step as u64,
            value: self.value,
        })
    }
}

impl Store {
    /// The metrics a job recorded, by name, with their point counts and step range.
    pub async fn metric_names(&self, id: &JobId) -> Result<Vec<MetricSummary>, StoreError> {
        let id = id.as_str();
        Ok(sqlx::query_as(
            "SELECT name, COUNT(*) AS points, MIN(step) AS first_step, MAX(step) AS last_step \
             FROM job_metrics WHERE job_id = $1 GROUP BY name ORDER BY name",
        )
        .bind(id)
        .fetch_all(self.pool())
        .await?)
    }

    pub async fn insert_metrics(
        &self,
        lease: &Lease<JobId>,
        rows: &[MetricRecord],
    ) -> Result<(), StoreError> {
        if rows.is_empty() {
            return Ok(());
        }
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        insert_metric_rows(&mut tx, &lease.id, rows).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Every metric row of a job (only `names` when given), ordered by name then step.
    pub async fn job_metrics(
        &self,
        id: &JobId,
        names: Option<&[String]>,
    ) -> Result<Vec<MetricRecord>, StoreError> {
        let filter = match names {
            Some([]) => return Ok(Vec::new()),
            Some(names) => format!(" AND name IN ({})", placeholders(2, names.len())),
            None => String::new(),
        };
        let sql = format!(
            "SELECT name, step, value, time FROM job_metrics WHERE job_id = $1{filter} \
             ORDER BY name, step"
        );
        let mut query = sqlx::query_as(&sql).bind(id.as_str());
        for name in names.unwrap_or_default() {
            query = query.bind(name);
        }
        let rows: Vec<MetricRow> = query.fetch_all(self.pool()).await?;
        rows.into_iter().map(|row| row.into_record(id)).collect()
    }

    /// The last recorded value of each metric of a job.
    pub async fn last_metric_values(&self, id: &JobId) -> Result<Vec<(String, f64)>, StoreError> {
        Ok(sqlx::query_as(LAST_METRIC_VALUES).bind(id.as_str()).fetch_all(self.pool()).await?)
    }
}

/// Metric rows in as few statements as the parameter limits allow.
pub(super) async fn insert_metric_rows(
    tx: &mut Transaction<'_, Any>,
    id: &JobId,
    rows: &[MetricRecord],
) -> Result<(), sqlx::Error> {
    if rows.is_empty() {
        return Ok(());
    }
    let offset = super::clock_offset_in(tx).await?;
    // SQLite's bound-parameter limit is 32766, PostgreSQL's 65535; 5 per row.
    for chunk in rows.chunks(4000) {
        let values = (0..chunk.len())
            .map(|row| format!("({})", placeholders(row * 5 + 1, 5)))
            .collect::<Vec<_>>()
            .join(", ");
        let sql =
            format!("INSERT INTO job_metrics (job_id, name, step, value, time) VALUES {values}");
        let mut insert = sqlx::query(&sql);
        for metric in chunk {
            insert = insert
                .bind(id.as_str())
                .bind(&metric.name)
                .bind(metric.step as i64)
                .bind(metric.value)
                .bind(rfc3339(&(metric.time + offset)));
        }
        insert.execute(&mut **tx).await?;
    }
    Ok(())
}

/// The last stored value of each of a job's metrics, by name.
const LAST_METRIC_VALUES: &str = "SELECT name, value FROM job_metrics AS m WHERE job_id = $1 \
       AND step = (SELECT MAX(step) FROM job_metrics WHERE job_id = $1 AND name = m.name) \
     ORDER BY name";

/// [`Store::last_metric_values`] inside a transaction (the metrics it just inserted included).
pub(super) async fn last_metric_values_in(
    tx: &mut Transaction<'_, Any>,
    job_id: &str,
) -> Result<Vec<(String, f64)>, StoreError> {
    Ok(sqlx::query_as(LAST_METRIC_VALUES).bind(job_id).fetch_all(&mut **tx).await?)
}
