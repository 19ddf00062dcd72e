//! Trained policies: the artefact (spec JSON + safetensors weights) and what the API lists.

use sqlx::{Any, Transaction};

use super::datasets::DeleteOutcome;
use super::{parse_time, Listing, PageQuery, Store, StoreError};
use crate::algo::PolicyArtifact;
use crate::domain::{JobId, PolicyId, PolicyRecord};

/// A policy row as the database returns it (everything but the weights); [`PolicyRecord`] is its typed
/// form.
#[derive(sqlx::FromRow)]
struct PolicyRow {
    id: String,
    job_id: String,
    algorithm: String,
    obs_dim: i64,
    action_space: String,
    spec: String,
    final_metrics: String,
    alpha_hat: Option<f64>,
    created_at: String,
    job_name: Option<String>,
}

impl TryFrom<PolicyRow> for PolicyRecord {
    type Error = StoreError;

    fn try_from(row: PolicyRow) -> Result<Self, StoreError> {
        let corrupt = |what: &str, e: serde_json::Error| {
            StoreError::Corrupt(format!("policy {}", row.id), format!("stored {what}: {e}"))
        };
        let algorithm = serde_json::from_value(row.algorithm.clone().into())
            .map_err(|e| corrupt("algorithm", e))?;
        let action_space =
            serde_json::from_str(&row.action_space).map_err(|e| corrupt("action space", e))?;
        let spec = serde_json::from_str(&row.spec).map_err(|e| corrupt("spec", e))?;
        let final_metrics =
            serde_json::from_str(&row.final_metrics).map_err(|e| corrupt("final metrics", e))?;
        let created_at = parse_time(&format!("policy {}", row.id), &row.created_at)?;
        Ok(PolicyRecord {
            id: row.id.into(),
            job_id: row.job_id.into(),
            algorithm,
            obs_dim: row.obs_dim as usize,
            action_space,
            spec,
            final_metrics,
            alpha_hat: row.alpha_hat,
            created_at,
            job_name: row.job_name,
        })
    }
}

/// What a succeeded job stores.
#[derive(Clone, Debug)]
pub struct NewPolicy<'a> {
    pub id: &'a PolicyId,
    pub job_id: &'a JobId,
    /// The spec (algorithm, spaces, decoder) and the weights.
    pub artifact: &'a PolicyArtifact,
    /// The last stored value of each of the job's metrics.
    pub final_metrics: &'a [(String, f64)],
    pub alpha_hat: Option<f64>,
}

const POLICY_COLUMNS: &str =
    "id, job_id, algorithm, obs_dim, action_space, spec, final_metrics, alpha_hat, created_at, \
     (SELECT name FROM jobs WHERE jobs.id = policies.job_id) AS job_name";

/// JSON text of plain data with string keys, which serde_json cannot fail on.
fn json_text(value: &impl serde::Serialize) -> String {
    serde_json::to_string(value).expect("plain data serialises to JSON")
}

/// Inserts a policy inside the caller's transaction (the job's completion).
pub(super) async fn insert_policy(
    tx: &mut Transaction<'_, Any>,
    policy: &NewPolicy<'_>,
) -> Result<(), sqlx::Error> {
    let spec = &policy.artifact.spec;
    let final_metrics: serde_json::Map<String, serde_json::Value> =
        policy.final_metrics.iter().map(|(name, value)| (name.clone(), (*value).into())).collect();
    sqlx::query(
        "INSERT INTO policies (id, job_id, algorithm, obs_dim, action_space, spec, weights, \
             final_metrics, alpha_hat, created_at) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, CAST($9 AS DOUBLE PRECISION), $10)",
    )
    .bind(policy.id.as_str())
    .bind(policy.job_id.as_str())
    .bind(spec.algorithm.as_str())
    .bind(spec.obs_dim as i64)
    .bind(json_text(&spec.action_space))
    .bind(json_text(spec))
    .bind(&policy.artifact.weights[..])
    .bind(json_text(&final_metrics))
    .bind(super::optional_real(policy.alpha_hat))
    .bind(super::now_in(tx).await?)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

impl Store {
    pub async fn policy(&self, id: &PolicyId) -> Result<PolicyRecord, StoreError> {
        let id = id.as_str();
        let row: PolicyRow =
            sqlx::query_as(&format!("SELECT {POLICY_COLUMNS} FROM policies WHERE id = $1"))
                .bind(id)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| StoreError::NotFound { kind: "policy", id: id.to_owned() })?;
        row.try_into()
    }

    /// A page of policies, newest first (only those of `job_id` when given); and the total.
    pub async fn list_policies(
        &self,
        job_id: Option<&JobId>,
        page: &PageQuery,
    ) -> Result<(Vec<PolicyRecord>, u64), StoreError> {
        let job_id = job_id.map(JobId::as_str);
        let rows: Vec<PolicyRow> = sqlx::query_as(&format!(
            "SELECT {POLICY_COLUMNS} FROM policies WHERE ($1 IS NULL OR job_id = $1) AND {} \
             ORDER BY created_at DESC, id DESC LIMIT $2 OFFSET $3",
            Listing::Policies.after(4)
        ))
        .bind(job_id)
        .bind(i64::from(page.limit))
        .bind(page.offset as i64)
        .bind(page.after.as_deref())
        .fetch_all(self.pool())
        .await?;
        let total: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM policies WHERE $1 IS NULL OR job_id = $1")
                .bind(job_id)
                .fetch_one(self.pool())
                .await?;
        let records = rows.into_iter().map(PolicyRecord::try_from).collect::<Result<_, _>>()?;
        Ok((records, total as u64))
    }

    /// The artefact of a policy: (spec JSON, safetensors weights).
    pub async fn policy_artifact(&self, id: &PolicyId) -> Result<(String, Vec<u8>), StoreError> {
        let id = id.as_str();
        sqlx::query_as("SELECT spec, weights FROM policies WHERE id = $1")
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "policy", id: id.to_owned() })
    }

    /// Deletes a policy and its finished evaluations, unless a model version points at it or an
    /// evaluation of it is queued or running; its job stays, without a policy.
    pub async fn delete_policy(&self, id: &PolicyId) -> Result<DeleteOutcome, StoreError> {
        let id = id.as_str();
        let Some((mut tx, _)) = self.begin_delete("policies", "id", id).await? else {
            return Ok(DeleteOutcome::NotFound);
        };
        let versions = super::models::versions_of_policy(&mut tx, id).await?;
        if !versions.is_empty() {
            return Ok(DeleteOutcome::Registered(versions));
        }
        let busy =
            super::evaluations::unfinished_evaluations(&mut tx, "WHERE e.policy_id = $1", id)
                .await?;
        if !busy.is_empty() {
            return Ok(DeleteOutcome::InUse(busy));
        }
        for statement in [
            "DELETE FROM evaluations WHERE policy_id = $1",
            "UPDATE jobs SET policy_id = NULL WHERE policy_id = $1",
            "DELETE FROM policies WHERE id = $1",
        ] {
            sqlx::query(statement).bind(id).execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(DeleteOutcome::Deleted)
    }
}
