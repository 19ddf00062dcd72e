//! Policy evaluations: a queue like the jobs' (claimed atomically, requeued after a crash) whose
//! rows end with the evaluation report or the reason it failed.

use std::time::Duration;

use sqlx::{Any, Transaction};

use super::datasets::DeleteOutcome;
use super::leases::{self, Lease};
use super::{now_in, parse_optional_time, parse_time, Listing, PageQuery, Store, StoreError};
use crate::domain::{
    EvalRuntime, EvalSpec, EvaluationId, EvaluationRecord, EvaluationSource, EvaluationStatus,
    PolicyId,
};
use crate::envs::EvalReport;

/// An evaluation row as the database returns it; [`EvaluationRecord`] is its typed form.
#[derive(sqlx::FromRow)]
struct EvaluationRow {
    id: String,
    policy_id: String,
    env: String,
    episodes: i64,
    seed: i64,
    deterministic: i64,
    status: String,
    source: String,
    /// NULL on rows older than the column: read by `source`.
    runtime: Option<String>,
    /// JSON of `envs::EvalReport`, once succeeded.
    report: Option<String>,
    error: Option<String>,
    training_step: Option<i64>,
    created_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
}

impl TryFrom<EvaluationRow> for EvaluationRecord {
    type Error = StoreError;

    fn try_from(row: EvaluationRow) -> Result<Self, StoreError> {
        let corrupt = |what: &str, e: &dyn std::fmt::Display| {
            StoreError::Corrupt(format!("evaluation {}", row.id), format!("stored {what}: {e}"))
        };
        let status = row.status.parse().map_err(|e: String| corrupt("status", &e))?;
        let source = row.source.parse().map_err(|e: String| corrupt("source", &e))?;
        let runtime = match (row.runtime.as_deref(), source) {
            (Some(runtime), _) => runtime.parse().map_err(|e: String| corrupt("runtime", &e))?,
            (None, EvaluationSource::Builtin) => EvalRuntime::Builtin,
            (None, EvaluationSource::External) => EvalRuntime::Unspecified,
        };
        // One unreadable report (older versions stored metrics that overflowed, as null) must
        // not take down every list it is in: the row reads without it, saying why.
        let (report, error) = match row.report.as_deref().map(serde_json::from_str::<EvalReport>) {
            Some(Err(e)) => {
                tracing::warn!(evaluation = %row.id, error = %e, "stored evaluation report unreadable");
                (None, Some(format!("the stored report cannot be read ({e}); record it again")))
            }
            Some(Ok(report)) => (Some(report), row.error),
            None => (None, row.error),
        };
        let owner = format!("evaluation {}", row.id);
        Ok(EvaluationRecord {
            created_at: parse_time(&owner, &row.created_at)?,
            started_at: parse_optional_time(&owner, row.started_at.as_deref())?,
            finished_at: parse_optional_time(&owner, row.finished_at.as_deref())?,
            id: row.id.into(),
            policy_id: row.policy_id.into(),
            spec: EvalSpec {
                env: row.env,
                episodes: row.episodes as usize,
                // Stored bit for bit as a signed integer (see insert_evaluation).
                seed: row.seed as u64,
                deterministic: row.deterministic != 0,
            },
            status,
            source,
            runtime,
            report,
            error,
            training_step: row.training_step.map(|step| step as u64),
        })
    }
}

/// An evaluation to queue, or one run elsewhere to record.
#[derive(Clone, Debug)]
pub struct NewEvaluation {
    pub id: EvaluationId,
    pub policy_id: PolicyId,
    pub spec: EvalSpec,
    /// An external evaluation's runtime and report: recorded as `succeeded` (None: queued for
    /// a worker).
    pub recorded: Option<(EvalRuntime, EvalReport)>,
}

const EVALUATION_COLUMNS: &str = "id, policy_id, env, episodes, seed, deterministic, status, \
     source, runtime, report, error, training_step, created_at, started_at, finished_at";

/// The ids of the queued or running evaluations among `evaluations e` joined and filtered by
/// `joined_where` (whose `$1` is `id`), inside the caller's transaction: what keeps a policy,
/// or the job that made it, from being deleted.
pub(super) async fn unfinished_evaluations(
    tx: &mut Transaction<'_, Any>,
    joined_where: &str,
    id: &str,
) -> Result<Vec<String>, sqlx::Error> {
    sqlx::query_scalar(&format!(
        "SELECT e.id FROM evaluations e {joined_where} AND e.status IN ({}, {}) ORDER BY e.id",
        EvaluationStatus::Queued.sql(),
        EvaluationStatus::Running.sql()
    ))
    .bind(id)
    .fetch_all(&mut **tx)
    .await
}

/// Records the evaluation a job's worker ran at the end of training as a succeeded built-in
/// evaluation of the job's new policy, inside the job's completion (so the policy never exists
/// without it).
pub(super) async fn insert_training_evaluation(
    tx: &mut Transaction<'_, Any>,
    policy_id: &PolicyId,
    evaluation: &TrainingEvaluation,
    now: &str,
) -> Result<(), StoreError> {
    let report = &evaluation.report;
    let json = serde_json::to_string(report)
        .map_err(|e| StoreError::Corrupt("evaluation report".into(), e.to_string()))?;
    sqlx::query(
        "INSERT INTO evaluations (id, policy_id, env, episodes, seed, deterministic, status, \
         source, runtime, report, training_step, created_at, started_at, finished_at) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $12, $12)",
    )
    .bind(EvaluationId::generate().as_str())
    .bind(policy_id.as_str())
    .bind(&report.env)
    .bind(report.episodes as i64)
    // SQL integers are signed: seeds above i64::MAX are stored bit for bit.
    .bind(report.seed as i64)
    .bind(i64::from(report.deterministic))
    .bind(EvaluationStatus::Succeeded.as_str())
    .bind(EvaluationSource::Builtin.as_str())
    .bind(EvalRuntime::Builtin.as_str())
    .bind(json)
    .bind(evaluation.step as i64)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

/// The evaluation a run took at its last step (its job's `eval` block), stored with its policy.
#[derive(Clone, Debug)]
pub struct TrainingEvaluation {
    /// The step it ran at (the run's last).
    pub step: u64,
    pub report: EvalReport,
}

impl Store {
    /// Number of evaluations in each status, every status listed.
    pub async fn evaluation_counts_by_status(
        &self,
    ) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        let statuses = EvaluationStatus::ALL.map(EvaluationStatus::as_str);
        self.counts_by_status("evaluations", &statuses).await
    }

    /// Queues an evaluation, or records an external one with its report, if the policy still
    /// exists: the check and the insert are one write transaction that keeps the policy row
    /// from changing, so a concurrent delete of the policy (or its job) either commits first
    /// (this answers `NotFound` for the policy) or waits for the evaluation and refuses.
    pub async fn insert_evaluation(
        &self,
        evaluation: &NewEvaluation,
    ) -> Result<EvaluationRecord, StoreError> {
        let mut tx = self.begin_write().await?;
        let now = now_in(&mut tx).await?;
        let (status, source, runtime, report, finished_at) = match &evaluation.recorded {
            None => (
                EvaluationStatus::Queued,
                EvaluationSource::Builtin,
                EvalRuntime::Builtin,
                None,
                None,
            ),
            Some((runtime, report)) => {
                let json = serde_json::to_string(report)
                    .map_err(|e| StoreError::Corrupt("evaluation report".into(), e.to_string()))?;
                let succeeded = EvaluationStatus::Succeeded;
                (succeeded, EvaluationSource::External, *runtime, Some(json), Some(&now))
            }
        };
        let policy: Option<String> = sqlx::query_scalar(&format!(
            "SELECT id FROM policies WHERE id = $1{}",
            self.backend.share_row()
        ))
        .bind(evaluation.policy_id.as_str())
        .fetch_optional(&mut *tx)
        .await?;
        if policy.is_none() {
            let id = evaluation.policy_id.to_string();
            return Err(StoreError::NotFound { kind: "policy", id });
        }
        sqlx::query(
            "INSERT INTO evaluations (id, policy_id, env, episodes, seed, deterministic, status, \
             source, runtime, report, created_at, started_at, finished_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $12)",
        )
        .bind(evaluation.id.as_str())
        .bind(evaluation.policy_id.as_str())
        .bind(&evaluation.spec.env)
        .bind(evaluation.spec.episodes as i64)
        // SQL integers are signed: seeds above i64::MAX are stored bit for bit.
        .bind(evaluation.spec.seed as i64)
        .bind(i64::from(evaluation.spec.deterministic))
        .bind(status.as_str())
        .bind(source.as_str())
        .bind(runtime.as_str())
        .bind(report)
        .bind(&now)
        .bind(finished_at)
        .execute(&mut *tx)
        .await?;
        let row: EvaluationRow =
            sqlx::query_as(&format!("SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE id = $1"))
                .bind(evaluation.id.as_str())
                .fetch_one(&mut *tx)
                .await?;
        tx.commit().await?;
        row.try_into()
    }

    pub async fn evaluation(&self, id: &EvaluationId) -> Result<EvaluationRecord, StoreError> {
        let id = id.as_str();
        let row: EvaluationRow =
            sqlx::query_as(&format!("SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE id = $1"))
                .bind(id)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| StoreError::NotFound { kind: "evaluation", id: id.to_owned() })?;
        row.try_into()
    }

    /// Deletes a finished evaluation (`InUse` names it while it is queued or running).
    pub async fn delete_evaluation(&self, id: &EvaluationId) -> Result<DeleteOutcome, StoreError> {
        let id = id.as_str();
        let Some((mut tx, status)) = self.begin_delete("evaluations", "status", id).await? else {
            return Ok(DeleteOutcome::NotFound);
        };
        if matches!(status.parse(), Ok(EvaluationStatus::Queued | EvaluationStatus::Running)) {
            return Ok(DeleteOutcome::InUse(vec![id.to_owned()]));
        }
        sqlx::query("DELETE FROM evaluations WHERE id = $1").bind(id).execute(&mut *tx).await?;
        tx.commit().await?;
        Ok(DeleteOutcome::Deleted)
    }

    /// A page of evaluations, newest first (only those of `policy_id` when given); and the total.
    pub async fn list_evaluations(
        &self,
        policy_id: Option<&PolicyId>,
        page: &PageQuery,
    ) -> Result<(Vec<EvaluationRecord>, u64), StoreError> {
        let policy_id = policy_id.map(PolicyId::as_str);
        let rows: Vec<EvaluationRow> = sqlx::query_as(&format!(
            "SELECT {EVALUATION_COLUMNS} FROM evaluations WHERE ($1 IS NULL OR policy_id = $1) \
             AND {} ORDER BY created_at DESC, id DESC LIMIT $2 OFFSET $3",
            Listing::Evaluations.after(4)
        ))
        .bind(policy_id)
        .bind(i64::from(page.limit))
        .bind(page.offset as i64)
        .bind(page.after.as_deref())
        .fetch_all(self.pool())
        .await?;
        let total: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM evaluations WHERE $1 IS NULL OR policy_id = $1",
        )
        .bind(policy_id)
        .fetch_one(self.pool())
        .await?;
        let records = rows.into_iter().map(EvaluationRecord::try_from).collect::<Result<_, _>>()?;
        Ok((records, total as u64))
    }

    /// Claims the oldest queued evaluation (or a running one whose worker's lease expired) for
    /// `worker` with a lease of `lease_duration`, in one statement. Evaluations are
    /// deterministic, so one run again after a takeover gives the same report.
    pub async fn claim_next_evaluation(
        &self,
        worker: &str,
        lease_duration: Duration,
    ) -> Result<Option<(EvaluationRecord, Lease<EvaluationId>)>, StoreError> {
        let claim = leases::Claim {
            claimable: leases::Claimable::QueuedOrExpired,
            set: "started_at = $1",
            order: "created_at, id",
        };
        match claim.run::<EvaluationId>(self, worker, lease_duration).await? {
            Some(lease) => Ok(Some((self.evaluation(&lease.id).await?, lease))),
            None => Ok(None),
        }
    }

    /// Puts an evaluation interrupted by a shutdown back in the queue.
    pub async fn requeue_evaluation(&self, lease: &Lease<EvaluationId>) -> Result<(), StoreError> {
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        sqlx::query(&format!(
            "UPDATE evaluations SET status = {}, started_at = NULL, lease_expires_ms = 0 \
             WHERE id = $1",
            EvaluationStatus::Queued.sql()
        ))
        .bind(lease.id.as_str())
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Ends a running evaluation: `Ok(report)` → `succeeded`, `Err(message)` → `failed`.
    pub async fn finish_evaluation(
        &self,
        lease: &Lease<EvaluationId>,
        result: Result<&EvalReport, &str>,
    ) -> Result<(), StoreError> {
        let (status, report, error) = match result.map(serde_json::to_string) {
            Ok(Ok(json)) => (EvaluationStatus::Succeeded, Some(json), None),
            Ok(Err(e)) => (EvaluationStatus::Failed, None, Some(e.to_string())),
            Err(message) => (EvaluationStatus::Failed, None, Some(message.to_owned())),
        };
        let mut tx = self.begin_write().await?;
        leases::hold(&mut tx, lease).await?;
        sqlx::query(
            "UPDATE evaluations SET status = $1, report = $2, error = $3, finished_at = $4 \
             WHERE id = $5",
        )
        .bind(status.as_str())
        .bind(report)
        .bind(error)
        .bind(now_in(&mut tx).await?)
        .bind(lease.id.as_str())
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }
}
