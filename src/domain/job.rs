//! A training job: its lifecycle and its stored record.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::{DatasetId, EvalOptions, JobId, JobLabels, JobProgress, PolicyId, RunnerOptions};
use crate::algo::{Algorithm, ResolvedConfig};

/// A job's lifecycle: `queued` → `running` → `succeeded` | `failed` | `cancelled` | `discarded`
/// (a running job goes back to `queued` when the server shuts down, or when its worker vanished
/// and it has attempts left, and resumes from its checkpoint).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    /// The training reported an error (bad data, a diverged loss, a failure of the code).
    Failed,
    Cancelled,
    /// Its workers vanished `max_attempts` times (killed, out of memory, the machine gone) before
    /// it ended: the job was given up, not failed by its own code.
    Discarded,
}

impl JobStatus {
    /// Every status, in lifecycle order.
    pub const ALL: [JobStatus; 6] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Cancelled,
        JobStatus::Discarded,
    ];

    /// The status as an SQL string literal (`'queued'`), for the store's SQL text: so the store
    /// spells no status by hand, and the schema's CHECK constraint pins the same words.
    pub fn sql(self) -> String {
        format!("'{}'", self.as_str())
    }

    /// The status as stored and shown (`queued`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
            JobStatus::Discarded => "discarded",
        }
    }

    /// A final status: the job never runs again.
    pub fn is_final(self) -> bool {
        !matches!(self, JobStatus::Queued | JobStatus::Running)
    }

    /// The job ended with what it was for (its policy stored): the one final status a client
    /// that waits for a job treats as success.
    pub fn is_success(self) -> bool {
        matches!(self, JobStatus::Succeeded)
    }

    /// What the status means, as the vocabulary serves it to clients.
    pub fn meaning(self) -> &'static str {
        match self {
            JobStatus::Queued => {
                "waiting for a worker (or for its retry time after a worker vanished)"
            }
            JobStatus::Running => "a worker holds its lease and trains it",
            JobStatus::Succeeded => "trained; its policy is stored",
            JobStatus::Failed => "the training reported an error; `error` says which",
            JobStatus::Cancelled => "cancelled by a user before it ended",
            JobStatus::Discarded => {
                "given up after its workers vanished max_attempts times; `error` has the history"
            }
        }
    }
}

impl std::fmt::Display for JobStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for JobStatus {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        JobStatus::ALL
            .into_iter()
            .find(|status| status.as_str() == s)
            .ok_or_else(|| format!("unknown job status {s:?}"))
    }
}

/// A job as stored: what was asked for, where it is, and what came of it.
#[derive(Clone, Debug, PartialEq)]
pub struct JobRecord {
    pub id: JobId,
    pub algorithm: Algorithm,
    pub status: JobStatus,
    pub unlabeled_dataset: DatasetId,
    pub non_preferred_dataset: Option<DatasetId>,
    /// Every knob of the algorithm with its value.
    pub config: ResolvedConfig,
    pub runner: RunnerOptions,
    pub eval: Option<EvalOptions>,
    /// Name, tags and notes.
    pub labels: JobLabels,
    /// Steps done, every phase counted.
    pub step: u64,
    pub total_steps: u64,
    pub phase: Option<String>,
    /// The recent speed the worker last reported (kept only while the job runs).
    pub iterations_per_second: Option<f64>,
    /// SafeDICE's alpha-hat once computed.
    pub alpha_hat: Option<f64>,
    pub policy_id: Option<PolicyId>,
    pub error: Option<String>,
    pub cancel_requested: bool,
    /// The worker that holds (or last held) the job's lease.
    pub worker: Option<String>,
    /// Attempts started (a run handed back on shutdown gives its attempt back).
    pub attempt: u32,
    /// Attempts before the job fails for good when its workers keep vanishing.
    pub max_attempts: u32,
    /// A job queued again after its worker vanished: not claimed before this time.
    pub retry_at: Option<DateTime<Utc>>,
    /// A running job whose worker stopped renewing its lease at this time and that no worker
    /// has taken over yet (waiting for a worker).
    pub lease_expired_at: Option<DateTime<Utc>>,
    /// The model its policy becomes a version of when it succeeds.
    pub register: Option<super::model::Registration>,
    /// The experiment whose grid it belongs to, and its arm's label there.
    pub experiment: Option<(String, String)>,
    pub created_at: DateTime<Utc>,
    pub updated_at: DateTime<Utc>,
    pub started_at: Option<DateTime<Utc>>,
    pub finished_at: Option<DateTime<Utc>>,
}

impl JobRecord {
    /// The job's progress; a speed only while it runs.
    pub fn progress(&self) -> JobProgress {
        let speed = self.iterations_per_second.filter(|_| self.status == JobStatus::Running);
        JobProgress::new(self.step, self.total_steps, self.phase.clone(), speed)
    }
}

/// A job to queue: its datasets, resolved configuration and options.
#[derive(Clone, Debug)]
pub struct NewJob {
    pub id: JobId,
    pub unlabeled_dataset: DatasetId,
    pub non_preferred_dataset: Option<DatasetId>,
    pub config: ResolvedConfig,
    pub runner: RunnerOptions,
    pub eval: Option<EvalOptions>,
    pub labels: JobLabels,
    /// Attempts before the job fails for good when its workers keep vanishing.
    pub max_attempts: u32,
    /// The model its policy becomes a version of when it succeeds.
    pub register: Option<super::model::Registration>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statuses_round_trip_through_their_stored_names_and_serde() {
        for status in JobStatus::ALL {
            assert_eq!(status.as_str().parse::<JobStatus>(), Ok(status));
            let json = serde_json::to_value(status).unwrap();
            assert_eq!(json, serde_json::Value::String(status.as_str().into()));
        }
        assert!("done".parse::<JobStatus>().is_err());
        let finals: Vec<_> = JobStatus::ALL.into_iter().filter(|s| s.is_final()).collect();
        assert_eq!(
            finals,
            [JobStatus::Succeeded, JobStatus::Failed, JobStatus::Cancelled, JobStatus::Discarded]
        );
    }
}
