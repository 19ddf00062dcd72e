//! Policy evaluations: a queue like the jobs' (claimed atomically, requeued after a crash) whose
//! rows end with the evaluation report or the reason it failed.

use super::jobs::now;
use super::{Store, StoreError};

/// An evaluation as stored (the HTTP layer turns it into the API's resource).
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct EvaluationRow {
    pub id: String,
    pub policy_id: String,
    pub env: String,
    pub episodes: i64,
    pub seed: i64,
    pub deterministic: bool,
    /// `queued` → `running` → `succeeded` | `failed`.
    pub status: String,
    /// JSON of `envs::EvalReport`, once succeeded.
    pub report: Option<String>,
    pub error: Option<String>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
}

/// What `POST /v1/policies/{id}/evaluate` stores.
#[derive(Clone, Debug)]
pub struct NewEvaluation<'a> {
    pub id: &'a str,
    pub policy_id: &'a str,
    pub env: &'a str,
    pub episodes: usize,
    pub seed: u64,
    pub deterministic: bool,
}

/// Every evaluation status, in lifecycle order.
pub const EVALUATION_STATUSES: [&str; 4] = ["queued", "running", "succeeded", "failed"];

const EVALUATION_COLUMNS: &str = "id, policy_id, env, episodes, seed, deterministic, status, \
     report, error, created_at, started_at, finished_at";

impl Store {
    /// Number of evaluations in each status, every status listed.
    pub async fn evaluation_counts_by_status(
        &self,
    ) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        self.counts_by_status("evaluations", &EVALUATION_STATUSES).await
    }

    pub async fn insert_evaluation(
        &self,
        evaluation: &NewEvaluation<'_>,
    ) -> Result<EvaluationRow, StoreError> {
        sqlx::query(
            "INSERT INTO evaluations (id, policy_id, env, episodes, seed, deterministic, status, \
             created_at) VALUES (?, ?, ?, ?, ?, ?, 'queued', ?)",
        )
        .bind(evaluation.id)
        .bind(evaluation.policy_id)
        .bind(evaluation.env)
        .bind(evaluation.episodes as i64)
        // SQLite integers are signed: seeds above i64::MAX are stored bit for bit.
        .bind(evaluation.seed as i64)
        .bind(evaluation.deterministic)
        .bind(now())
        .execute(self.pool())
        .await?;
        self.evaluation(evaluation.id).await
    }

    pub async fn evaluation(&self, id: &str) -> Result<EvaluationRow, StoreError> {
        sqlx::query_as(&format!("SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE id = ?"))
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "evaluation", id: id.to_owned() })
    }

    /// A page of evaluations, newest first (only those of `policy_id` when given); and the total.
    pub async fn list_evaluations(
        &self,
        policy_id: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<EvaluationRow>, u64), StoreError> {
        let rows = sqlx::query_as(&format!(
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
        Ok((rows, total as u64))
    }

    /// Atomically moves the oldest queued evaluation to `running` and returns it.
    pub async fn claim_next_evaluation(&self) -> Result<Option<EvaluationRow>, StoreError> {
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

    /// Ends a running evaluation: `Ok(report JSON)` → `succeeded`, `Err(message)` → `failed`.
    pub async fn finish_evaluation(
        &self,
        id: &str,
        result: Result<&str, &str>,
    ) -> Result<(), StoreError> {
        let (status, report, error) = match result {
            Ok(report) => ("succeeded", Some(report), None),
            Err(message) => ("failed", None, Some(message)),
        };
        sqlx::query(
            "UPDATE evaluations SET status = ?, report = ?, error = ?, finished_at = ? \
             WHERE id = ?",
        )
        .bind(status)
        .bind(report)
        .bind(error)
        .bind(now())
        .bind(id)
        .execute(self.pool())
        .await?;
        Ok(())
    }
}
