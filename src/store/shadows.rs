//! The shadows' comparison series (`shadow_comparisons`): each serving process adds its counts
//! of a minute to the row of that minute, so a fleet's nodes make one series.

use chrono::{DateTime, SecondsFormat, Utc};

use super::{parse_time, Store, StoreError};
use crate::domain::model::ModelName;
use crate::domain::shadow::{ComparisonCounts, ComparisonKey, ComparisonPoint, ComparisonSeries};

/// A minute as its row keeps it: RFC 3339, milliseconds, UTC (text that sorts in time order).
pub fn minute_text(minute: &DateTime<Utc>) -> String {
    minute.to_rfc3339_opts(SecondsFormat::Millis, true)
}

/// Counts of one comparison's minute, to add.
pub struct ComparisonDelta<'a> {
    pub key: &'a ComparisonKey,
    pub minute: DateTime<Utc>,
    pub counts: &'a ComparisonCounts,
}

/// The counted columns, in the order [`ComparisonCounts`] binds them.
const COUNT_COLUMNS: [&str; 16] = [
    "requests",
    "skipped",
    "failures",
    "observations",
    "shadow_ns",
    "disagreements",
    "l2_sum",
    "l2_max",
    "max_abs_sum",
    "max_abs_max",
    "shadow_log_ratio_sum",
    "shadow_log_ratio_n",
    "production_log_ratio_sum",
    "production_log_ratio_n",
    "out_of_support_sum",
    "out_of_support_n",
];

#[derive(sqlx::FromRow)]
struct ComparisonRow {
    alias: String,
    production_version: i64,
    shadow_version: i64,
    minute: String,
    requests: i64,
    skipped: i64,
    failures: i64,
    observations: i64,
    shadow_ns: i64,
    disagreements: i64,
    l2_sum: f64,
    l2_max: f64,
    max_abs_sum: f64,
    max_abs_max: f64,
    shadow_log_ratio_sum: f64,
    shadow_log_ratio_n: i64,
    production_log_ratio_sum: f64,
    production_log_ratio_n: i64,
    out_of_support_sum: f64,
    out_of_support_n: i64,
}

impl ComparisonRow {
    fn counts(&self) -> ComparisonCounts {
        let n = |v: i64| v.max(0) as u64;
        ComparisonCounts {
            requests: n(self.requests),
            skipped: n(self.skipped),
            failed: n(self.failures),
            observations: n(self.observations),
            shadow_ns: n(self.shadow_ns),
            disagreements: n(self.disagreements),
            l2_sum: self.l2_sum,
            l2_max: self.l2_max,
            max_abs_sum: self.max_abs_sum,
            max_abs_max: self.max_abs_max,
            shadow_log_ratio_sum: self.shadow_log_ratio_sum,
            shadow_log_ratio_n: n(self.shadow_log_ratio_n),
            production_log_ratio_sum: self.production_log_ratio_sum,
            production_log_ratio_n: n(self.production_log_ratio_n),
            out_of_support_sum: self.out_of_support_sum,
            out_of_support_n: n(self.out_of_support_n),
        }
    }
}

/// The upsert of one minute: sums add, maxima keep the larger; a model deleted meanwhile gets
/// no row (`WHERE EXISTS`), nor does one created again under its name since the counts were
/// taken (its creation stamp differs).
fn upsert_sql() -> String {
    let sums = COUNT_COLUMNS
        .iter()
        .map(|c| {
            if c.ends_with("_max") {
                format!(
                    "{c} = CASE WHEN excluded.{c} > shadow_comparisons.{c} THEN excluded.{c} \
                     ELSE shadow_comparisons.{c} END"
                )
            } else {
                format!("{c} = shadow_comparisons.{c} + excluded.{c}")
            }
        })
        .collect::<Vec<_>>()
        .join(", ");
    let columns = COUNT_COLUMNS.join(", ");
    let values = (6..22).map(|i| format!("${i}")).collect::<Vec<_>>().join(", ");
    format!(
        "INSERT INTO shadow_comparisons (model, alias, production_version, shadow_version, \
             minute, {columns}) \
         SELECT $1, $2, $3, $4, $5, {values} WHERE EXISTS (SELECT 1 FROM models WHERE name = $1 AND created_at = $22) \
         ON CONFLICT (model, alias, production_version, shadow_version, minute) DO UPDATE SET \
             {sums}"
    )
}

impl Store {
    /// Adds the counts to their minutes' rows, in one transaction.
    pub async fn add_shadow_counts(
        &self,
        deltas: &[ComparisonDelta<'_>],
    ) -> Result<(), StoreError> {
        if deltas.is_empty() {
            return Ok(());
        }
        let sql = upsert_sql();
        let mut tx = self.begin_write().await?;
        for delta in deltas {
            let (k, c) = (delta.key, delta.counts);
            let i = |v: u64| v.min(i64::MAX as u64) as i64;
            sqlx::query(&sql)
                .bind(&k.model)
                .bind(&k.alias)
                .bind(i64::from(k.production_version))
                .bind(i64::from(k.shadow_version))
                .bind(minute_text(&delta.minute))
                .bind(i(c.requests))
                .bind(i(c.skipped))
                .bind(i(c.failed))
                .bind(i(c.observations))
                .bind(i(c.shadow_ns))
                .bind(i(c.disagreements))
                .bind(c.l2_sum)
                .bind(c.l2_max)
                .bind(c.max_abs_sum)
                .bind(c.max_abs_max)
                .bind(c.shadow_log_ratio_sum)
                .bind(i(c.shadow_log_ratio_n))
                .bind(c.production_log_ratio_sum)
                .bind(i(c.production_log_ratio_n))
                .bind(c.out_of_support_sum)
                .bind(i(c.out_of_support_n))
                .bind(&k.model_created)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// The model's comparisons (of `alias` only, when given) from `since` on, one series per
    /// alias, answering version and shadow version, each oldest minute first.
    pub async fn shadow_series(
        &self,
        model: &ModelName,
        alias: Option<&str>,
        since: &DateTime<Utc>,
    ) -> Result<Vec<ComparisonSeries>, StoreError> {
        let model = model.as_str();
        let model_created: String =
            sqlx::query_scalar("SELECT created_at FROM models WHERE name = $1")
                .bind(model)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| super::model_aliases::model_not_found(model))?;
        let rows: Vec<ComparisonRow> = sqlx::query_as(&format!(
            "SELECT alias, production_version, shadow_version, minute, {} \
             FROM shadow_comparisons WHERE model = $1 AND ($2 IS NULL OR alias = $2) \
             AND minute >= $3 ORDER BY alias, production_version, shadow_version, minute",
            COUNT_COLUMNS.join(", ")
        ))
        .bind(model)
        .bind(alias)
        .bind(minute_text(since))
        .fetch_all(self.pool())
        .await?;
        let mut series: Vec<ComparisonSeries> = Vec::new();
        for row in rows {
            let key = ComparisonKey {
                model: model.to_owned(),
                model_created: model_created.clone(),
                alias: row.alias.clone(),
                production_version: row.production_version as u32,
                shadow_version: row.shadow_version as u32,
            };
            let owner = format!("shadow comparison of {model}@{}", row.alias);
            let point =
                ComparisonPoint { minute: parse_time(&owner, &row.minute)?, counts: row.counts() };
            match series.last_mut() {
                Some(last) if last.key == key => last.points.push(point),
                _ => series.push(ComparisonSeries { key, points: vec![point] }),
            }
        }
        Ok(series)
    }
}
