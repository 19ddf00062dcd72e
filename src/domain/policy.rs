//! A trained policy as stored (its weights are read separately, only when needed).

use chrono::{DateTime, Utc};

use super::{JobId, PolicyId};
use crate::algo::{Algorithm, PolicySpec};
use crate::data::ActionSpace;

/// A policy: what trained it, its spec, and the job's last metrics.
#[derive(Clone, Debug, PartialEq)]
pub struct PolicyRecord {
    pub id: PolicyId,
    /// The job that trained it.
    pub job_id: JobId,
    pub algorithm: Algorithm,
    pub obs_dim: usize,
    pub action_space: ActionSpace,
    /// Everything besides the weights needed to rebuild the policy.
    pub spec: PolicySpec,
    /// The last recorded value of each metric of the job.
    pub final_metrics: serde_json::Map<String, serde_json::Value>,
    /// SafeDICE's alpha-hat.
    pub alpha_hat: Option<f64>,
    pub created_at: DateTime<Utc>,
    /// The name people gave its job (read with the policy: a rename shows at once).
    pub job_name: Option<String>,
}
