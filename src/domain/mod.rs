//! The service's vocabulary, shared by every layer that stores, runs or serves work: typed ids,
//! the lifecycles of jobs and evaluations, and the records the store hands out (datasets, jobs,
//! evaluations, policies, metrics, log lines, workers). No SQL, no HTTP:
//! the store turns rows into these types once, and everything above works with them.

pub mod attempt;
pub mod dataset;
pub mod evaluation;
pub mod experiment;
pub mod ids;
pub mod integral;
pub mod job;
pub mod labels;
pub mod model;
pub mod options;
pub mod policy;
pub mod progress;
pub mod protocol;
pub mod shadow;
pub mod telemetry;

pub use attempt::{AttemptOutcome, JobAttempt, RetryBackoff};
pub use dataset::DatasetRecord;
pub use evaluation::{EvaluationRecord, EvaluationSource, EvaluationStatus};
pub use ids::{DatasetId, EvaluationId, ExperimentId, JobId, PolicyId};
pub use job::{JobRecord, JobStatus, NewJob};
pub use labels::JobLabels;
pub use options::{EvalOptions, EvalSpec, RunnerOptions};
pub use policy::PolicyRecord;
pub use progress::JobProgress;
pub use protocol::{EvalProtocol, EvalRuntime};
pub use telemetry::{LogLevel, LogRecord, MetricRecord, WorkerRecord};

/// What a dataset is for, as its uploader said.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, utoipa::ToSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum DatasetRole {
    /// D^U: demonstrations of mixed quality.
    Unlabeled,
    /// D^N: demonstrations known to be non-preferred (unsafe).
    NonPreferred,
}

impl DatasetRole {
    pub fn as_str(self) -> &'static str {
        match self {
            DatasetRole::Unlabeled => "unlabeled",
            DatasetRole::NonPreferred => "non_preferred",
        }
    }

    pub fn parse(text: &str) -> Option<DatasetRole> {
        [DatasetRole::Unlabeled, DatasetRole::NonPreferred].into_iter().find(|r| r.as_str() == text)
    }
}

pub use crate::algo::MAX_SEED;

/// Deserializes a seed, refusing one above [`MAX_SEED`] with a message that says why.
pub fn deserialize_seed<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    let seed = integral::unsigned(d)?;
    if seed > MAX_SEED {
        return Err(serde::de::Error::custom(format!(
            "seed {seed} is above {MAX_SEED}, the largest 64-bit signed integer (seeds are int64)"
        )));
    }
    Ok(seed)
}

/// [`deserialize_seed`] for an optional seed.
pub fn deserialize_optional_seed<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<u64>, D::Error> {
    #[derive(serde::Deserialize)]
    struct Seed(#[serde(deserialize_with = "deserialize_seed")] u64);
    Ok(<Option<Seed> as serde::Deserialize>::deserialize(d)?.map(|Seed(s)| s))
}

/// A time as the API shows it: RFC 3339, UTC, milliseconds (`2026-01-31T12:00:00.000Z`).
pub fn rfc3339(time: &chrono::DateTime<chrono::Utc>) -> String {
    time.to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
}
