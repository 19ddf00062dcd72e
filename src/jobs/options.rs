//! The job-runner knobs of a job (`"runner"` beside the algorithm's `"config"`): how often the
//! worker records metrics and saves checkpoints. They change what is stored, never the trained
//! policy.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// How a job is run. Every field is optional in requests.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct RunnerOptions {
    /// Record the step's metrics (losses, alpha-hat, weight statistics) every `log_every` steps;
    /// the last step is always recorded. 1 to 1,000,000; default 100.
    #[schema(minimum = 1, maximum = 1_000_000, default = 100)]
    pub log_every: u64,
    /// Save a checkpoint (weights, optimiser state, RNG state) to the database every
    /// `checkpoint_every` steps, and on shutdown; a restarted server resumes from the last one.
    /// 1 to 100,000,000; default 5000.
    #[schema(minimum = 1, maximum = 100_000_000, default = 5000)]
    pub checkpoint_every: u64,
}

impl Default for RunnerOptions {
    fn default() -> Self {
        RunnerOptions { log_every: 100, checkpoint_every: 5000 }
    }
}

/// A runner option out of range, or an unknown one; the message names it.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct RunnerOptionsError(pub String);

impl RunnerOptions {
    /// Parses the request's `runner` object (absent or null: the defaults).
    pub fn parse(raw: Option<&serde_json::Value>) -> Result<RunnerOptions, RunnerOptionsError> {
        let options: RunnerOptions = match raw {
            None | Some(serde_json::Value::Null) => RunnerOptions::default(),
            Some(value) => serde_json::from_value(value.clone())
                .map_err(|e| RunnerOptionsError(format!("runner: {e}")))?,
        };
        in_range("log_every", options.log_every, 1_000_000)?;
        in_range("checkpoint_every", options.checkpoint_every, 100_000_000)?;
        Ok(options)
    }

    /// Whether the step that brings the run to `step_after` (1-based) records metrics.
    pub fn records(&self, step_after: u64, total: u64) -> bool {
        step_after % self.log_every == 0 || step_after == total
    }

    /// Whether to checkpoint after `step_after` steps (never after the last: the run is done).
    pub fn checkpoints(&self, step_after: u64, total: u64) -> bool {
        step_after % self.checkpoint_every == 0 && step_after < total
    }
}

fn in_range(key: &str, value: u64, high: u64) -> Result<(), RunnerOptionsError> {
    if (1..=high).contains(&value) {
        Ok(())
    } else {
        Err(RunnerOptionsError(format!("runner.{key}: must be between 1 and {high}, got {value}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_overrides_and_errors_name_the_key() {
        assert_eq!(RunnerOptions::parse(None).unwrap(), RunnerOptions::default());
        let o = RunnerOptions::parse(Some(&json!({"log_every": 5}))).unwrap();
        assert_eq!((o.log_every, o.checkpoint_every), (5, 5000));
        let e = RunnerOptions::parse(Some(&json!({"log_every": 0}))).unwrap_err();
        assert_eq!(e.0, "runner.log_every: must be between 1 and 1000000, got 0");
        let e = RunnerOptions::parse(Some(&json!({"eval_every": 3}))).unwrap_err();
        assert!(e.0.starts_with("runner: unknown field `eval_every`"), "{}", e.0);
    }

    #[test]
    fn the_last_step_is_recorded_and_never_checkpointed() {
        let o = RunnerOptions { log_every: 10, checkpoint_every: 20 };
        let recorded: Vec<u64> = (1..=45).filter(|&s| o.records(s, 45)).collect();
        assert_eq!(recorded, [10, 20, 30, 40, 45]);
        let saved: Vec<u64> = (1..=40).filter(|&s| o.checkpoints(s, 40)).collect();
        assert_eq!(saved, [20]);
    }
}
