//! A policy evaluation: its lifecycle and its stored record.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::{EvalSpec, EvaluationId, PolicyId};
use crate::envs::EvalReport;

/// An evaluation's lifecycle: `queued` → `running` → `succeeded` | `failed` (a running one goes
/// back to `queued` when the server shuts down and runs again at the next start).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum EvaluationStatus {
    Queued,
    Running,
    Succeeded,
    Failed,
}

impl EvaluationStatus {
    /// Every status, in lifecycle order.
    pub const ALL: [EvaluationStatus; 4] = [
        EvaluationStatus::Queued,
        EvaluationStatus::Running,
        EvaluationStatus::Succeeded,
        EvaluationStatus::Failed,
    ];

    /// The status as stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            EvaluationStatus::Queued => "queued",
            EvaluationStatus::Running => "running",
            EvaluationStatus::Succeeded => "succeeded",
            EvaluationStatus::Failed => "failed",
        }
    }
}

impl std::str::FromStr for EvaluationStatus {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        EvaluationStatus::ALL
            .into_iter()
            .find(|status| status.as_str() == s)
            .ok_or_else(|| format!("unknown evaluation status {s:?}"))
    }
}

/// An evaluation as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct EvaluationRecord {
    pub id: EvaluationId,
    pub policy_id: PolicyId,
    /// Environment, episodes, seed and whether actions are deterministic.
    pub spec: EvalSpec,
    pub status: EvaluationStatus,
    /// The metrics, once succeeded.
    pub report: Option<EvalReport>,
    /// Why it failed.
    pub error: Option<String>,
    pub created_at: DateTime<Utc>,
    pub started_at: Option<DateTime<Utc>>,
    pub finished_at: Option<DateTime<Utc>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statuses_round_trip_through_their_stored_names() {
        for status in EvaluationStatus::ALL {
            assert_eq!(status.as_str().parse::<EvaluationStatus>(), Ok(status));
            assert_eq!(serde_json::to_value(status).unwrap().as_str(), Some(status.as_str()));
        }
    }
}
