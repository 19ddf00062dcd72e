//! Trained policies: the artefact (spec JSON + safetensors weights) and what the API lists.

use sqlx::{Sqlite, Transaction};

use super::{Store, StoreError};

/// A policy as listed (everything but the weights).
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct PolicyRow {
    pub id: String,
    pub job_id: String,
    pub algorithm: String,
    pub obs_dim: i64,
    /// JSON of the action space.
    pub action_space: String,
    /// JSON of `algo::PolicySpec`.
    pub spec: String,
    /// JSON object: the last recorded value of each metric of the job.
    pub final_metrics: String,
    pub alpha_hat: Option<f64>,
    pub created_at: String,
}

/// What a succeeded job stores.
#[derive(Clone, Debug)]
pub struct NewPolicy<'a> {
    pub id: &'a str,
    pub job_id: &'a str,
    pub algorithm: &'a str,
    pub obs_dim: usize,
    pub action_space: &'a str,
    pub spec: &'a str,
    pub weights: &'a [u8],
    pub final_metrics: &'a str,
    pub alpha_hat: Option<f64>,
}

const POLICY_COLUMNS: &str =
    "id, job_id, algorithm, obs_dim, action_space, spec, final_metrics, alpha_hat, created_at";

/// Inserts a policy inside the caller's transaction (the job's completion).
pub(super) async fn insert_policy(
    tx: &mut Transaction<'_, Sqlite>,
    policy: &NewPolicy<'_>,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO policies (id, job_id, algorithm, obs_dim, action_space, spec, weights, \
             final_metrics, alpha_hat, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
    )
    .bind(policy.id)
    .bind(policy.job_id)
    .bind(policy.algorithm)
    .bind(policy.obs_dim as i64)
    .bind(policy.action_space)
    .bind(policy.spec)
    .bind(policy.weights)
    .bind(policy.final_metrics)
    .bind(policy.alpha_hat)
    .bind(super::now())
    .execute(&mut **tx)
    .await?;
    Ok(())
}

impl Store {
    pub async fn policy(&self, id: &str) -> Result<PolicyRow, StoreError> {
        sqlx::query_as(&format!("SELECT {POLICY_COLUMNS} FROM policies WHERE id = ?"))
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "policy", id: id.to_owned() })
    }

    /// A page of policies, newest first (only those of `job_id` when given); and the total.
    pub async fn list_policies(
        &self,
        job_id: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<PolicyRow>, u64), StoreError> {
        let rows = sqlx::query_as(&format!(
            "SELECT {POLICY_COLUMNS} FROM policies WHERE (?1 IS NULL OR job_id = ?1) \
             ORDER BY created_at DESC, id DESC LIMIT ?2 OFFSET ?3"
        ))
        .bind(job_id)
        .bind(i64::from(limit))
        .bind(offset as i64)
        .fetch_all(self.pool())
        .await?;
        let total: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM policies WHERE ?1 IS NULL OR job_id = ?1")
                .bind(job_id)
                .fetch_one(self.pool())
                .await?;
        Ok((rows, total as u64))
    }

    /// The artefact of a policy: (spec JSON, safetensors weights).
    pub async fn policy_artifact(&self, id: &str) -> Result<(String, Vec<u8>), StoreError> {
        sqlx::query_as("SELECT spec, weights FROM policies WHERE id = ?")
            .bind(id)
            .fetch_optional(self.pool())
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "policy", id: id.to_owned() })
    }
}
