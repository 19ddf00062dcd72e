//! Policy evaluations: a queue like the jobs' (claimed atomically, requeued after a crash) whose
//! rows end with the evaluation report or the reason it failed.

use chrono::{DateTime, Utc};

use super::{now, Store, StoreError};
use crate::domain::{EvalSpec, EvaluationId, EvaluationRecord, EvaluationStatus, PolicyId};
use crate::envs::EvalReport;

/// An evaluation row as SQLite returns it; [`EvaluationRecord`] is its typed form.
#[derive(sqlx::FromRow)]
struct EvaluationRow {
    id: String,
    policy_id: String,
    env: String,
    episodes: i64,
    seed: i64,
    deterministic: bool,
    status: String,
    /// JSON of `envs::EvalReport`, once succeeded.
    report: Option<String>,
    error: Option<String>,
    created_at: DateTime<Utc>,
    started_at: Option<DateTime<Utc>>,
    finished_at: Option<DateTime<Utc>>,
}

impl TryFrom<EvaluationRow> for EvaluationRecord {
    type Error = StoreError;

    fn try_from(row: EvaluationRow) -> Result<Self, StoreError> {
        let corrupt = |what: &str, e: &dyn std::fmt::Display| {
            StoreError::Corrupt(format!("evaluation {}", row.id), format!("stored {what}: {e}"))
        };
        let status = row.status.parse().map_err(|e: String| corrupt("status", &e))?;
        let report = row.report.as_deref().map(serde_json::from_str::<EvalReport>).transpose();
        let report = report.map_err(|e| corrupt("report", &e))?;
        Ok(EvaluationRecord {
            id: row.id.into(),
            policy_id: row.policy_id.into(),
            spec: EvalSpec {
                env: row.env,
                episodes: row.episodes as usize,
                // Stored bit for bit as SQLite's signed integer (see insert_evaluation).
                seed: row.seed as u64,
                deterministic: row.deterministic,
            },
            status,
            report,
            error: row.error,
            created_at: row.created_at,
            started_at: row.started_at,
            finished_at: row.finished_at,
        })
    }
}

/// An evaluation to queue.
#[derive(Clone, Debug)]
pub struct NewEvaluation {
    pub id: EvaluationId,
    pub policy_id: PolicyId,
    pub spec: EvalSpec,
}

const EVALUATION_COLUMNS: &str = "id, policy_id, env, episodes, seed, deterministic, status, \
     report, error, created_at, started_at, finished_at";

impl Store {
    /// Number of evaluations in each status, every status listed.
    pub async fn evaluation_counts_by_status(
        &self,
    ) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        let statuses = EvaluationStatus::ALL.map(EvaluationStatus::as_str);
        self.counts_by_status("evaluations", &statuses).await
    }

    pub async fn insert_evaluation(
        &self,
        evaluation: &NewEvaluation,
    ) -> Result<EvaluationRecord, StoreError> {
        sqlx::query(
            "INSERT INTO evaluations (id, policy_id, env, episodes, seed, deterministic, status, \
             created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(evaluation.id.as_str())
        .bind(evaluation.policy_id.as_str())
        .bind(&evaluation.spec.env)
        .bind(evaluation.spec.episodes as i64)
        // SQLite integers are signed: seeds above i64::MAX are stored bit for bit.
        .bind(evaluation.spec.seed as i64)
        .bind(evaluation.spec.deterministic)
        .bind(EvaluationStatus::Queued.as_str())
        .bind(now())
        .execute(self.pool())
        .await?;
        self.evaluation(&evaluation.id).await
    }

    pub async fn evaluation(&self, id: &str) -> Result<EvaluationRecord, StoreError> {
        let row: EvaluationRow =
            sqlx::query_as(&format!("SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE id = ?"))
                .bind(id)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| StoreError::NotFound { kind: "evaluation", id: id.to_owned() })?;
        row.try_into()
    }

    /// A page of evaluations, newest first (only those of `policy_id` when given); and the total.
    pub async fn list_evaluations(
        &self,
        policy_id: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<EvaluationRecord>, u64), StoreError> {
        let rows: Vec<EvaluationRow> = sqlx::query_as(&format!(
            "SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE (?1 IS NULL OR policy_id = ?1) \
             ORDER BY created_at DESC, id DESC LIMIT ?2 OFFSET ?3"
        ))
        .bind(policy_id)
        .bind(i64::from(limit))
        .bind(offset as i64)
        .fetch_all(self.pool())
        .await?;
        let total: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM evaluations WHERE ?1 IS NULL OR policy_id = ?1",
        )
        .bind(policy_id)
        .fetch_one(self.pool())
        .await?;
        let records = rows.into_iter().map(EvaluationRecord::try_from).collect::<Result<_, _>>()?;
        Ok((records, total as u64))
    }

    /// Atomically moves the oldest queued evaluation to `running` and returns it.
    pub async fn claim_next_evaluation(&self) -> Result<Option<EvaluationRecord>, StoreError> {
        let claimed: Option<String> = sqlx::query_scalar(
            "UPDATE evaluations SET status = 'running', started_at = ?1 \
             WHERE id = (SELECT id FROM evaluations WHERE status = 'queued' \
                         ORDER BY created_at, id LIMIT 1) \
               AND status = 'queued' \
             RETURNING id",
        )
        .bind(now())
        .fetch_optional(self.pool())
        .await?;
        match claimed {
            Some(id) => Ok(Some(self.evaluation(&id).await?)),
            None => Ok(None),
        }
    }

    /// Puts a running evaluation back in the queue: at start-up for those a dead process left
    /// `running` (`id` None: all of them), or for one interrupted by a shutdown. Evaluations are
    /// deterministic, so running one again gives the same report. Returns how many.
    pub async fn requeue_evaluations(&self, id: Option<&str>) -> Result<u64, StoreError> {
        let done = sqlx::query(
            "UPDATE evaluations SET status = 'queued', started_at = NULL \
             WHERE status = 'running' AND (?1 IS NULL OR id = ?1)",
        )
        .bind(id)
        .execute(self.pool())
        .await?;
        Ok(done.rows_affected())
    }

    /// Ends a running evaluation: `Ok(report)` → `succeeded`, `Err(message)` → `failed`.
    pub async fn finish_evaluation(
        &self,
        id: &str,
        result: Result<&EvalReport, &str>,
    ) -> Result<(), StoreError> {
        let (status, report, error) = match result.map(serde_json::to_string) {
            Ok(Ok(json)) => (EvaluationStatus::Succeeded, Some(json), None),
            Ok(Err(e)) => (EvaluationStatus::Failed, None, Some(e.to_string())),
            Err(message) => (EvaluationStatus::Failed, None, Some(message.to_owned())),
        };
        sqlx::query(
            "UPDATE evaluations SET status = ?, report = ?, error = ?, finished_at = ? \
             WHERE id = ?",
        )
        .bind(status.as_str())
        .bind(report)
        .bind(error)
        .bind(now())
        .bind(id)
        .execute(self.pool())
        .await?;
        Ok(())
    }
}
