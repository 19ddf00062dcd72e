//! The job-runner knobs of a job (`"runner"` beside the algorithm's `"config"`): how often the
//! worker records metrics and saves checkpoints; and the optional `"eval"` block, which
//! evaluates the policy on a built-in environment every N policy steps. They change what is
//! stored, never the trained policy.

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
        step_after.is_multiple_of(self.log_every) || step_after == total
    }

    /// Whether to checkpoint after `step_after` steps (never after the last: the run is done).
    pub fn checkpoints(&self, step_after: u64, total: u64) -> bool {
        step_after.is_multiple_of(self.checkpoint_every) && step_after < total
    }
}

/// Evaluation episodes unless a request says otherwise: the paper's 500.
pub const DEFAULT_EVAL_EPISODES: usize = 500;

/// One evaluation of a policy on a built-in environment with the paper's metrics: the body of
/// `POST /v1/policies/{id}/evaluate`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct EvalSpec {
    /// A built-in environment (`GET /v1/envs`) whose observation and action spaces match the
    /// policy's.
    #[schema(example = "point-goal")]
    pub env: String,
    /// Episodes to run, 1 to 100,000; default 500 (the paper's).
    #[serde(default = "default_eval_episodes")]
    #[schema(minimum = 1, maximum = 100_000, default = 500)]
    pub episodes: usize,
    /// Seed of the episodes' initial states and of sampled actions: the same seed and policy
    /// give the same metrics. Default 0.
    #[serde(default, deserialize_with = "super::deserialize_seed")]
    #[schema(maximum = 9223372036854775807_u64)]
    pub seed: u64,
    /// true: tanh of the Gaussian mean / argmax; false (default, as the paper): sampled actions.
    #[serde(default)]
    pub deterministic: bool,
}

fn default_eval_episodes() -> usize {
    DEFAULT_EVAL_EPISODES
}

/// A job's `eval` block: evaluate the policy being trained every `every` policy-learning steps
/// and at the end (without `every`: only at the end), recording the paper's metrics in the
/// job's metrics history as `eval/normalized_return`, `eval/average_cost`,
/// `eval/cost_violation_ratio`, `eval/cvar_cost_{50,20,10,5}`, ... (pretraining phases are not
/// evaluated: the policy does not move during them).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct EvalOptions {
    /// A built-in environment (`GET /v1/envs`) whose spaces match the job's datasets.
    #[schema(example = "point-goal")]
    pub env: String,
    /// Policy-learning steps between evaluations, 1 to 100,000,000; absent: the policy is
    /// evaluated once, at the end of training.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(minimum = 1, maximum = 100_000_000, example = 1000)]
    pub every: Option<u64>,
    /// Episodes per evaluation, 1 to 100,000; default 500.
    #[serde(default = "default_eval_episodes")]
    #[schema(minimum = 1, maximum = 100_000, default = 500)]
    pub episodes: usize,
    /// Seed of every evaluation (the same initial states each time, so the history compares
    /// like with like). Default 0.
    #[serde(default, deserialize_with = "super::deserialize_seed")]
    #[schema(maximum = 9223372036854775807_u64)]
    pub seed: u64,
    /// Deterministic actions instead of sampled ones (default false).
    #[serde(default)]
    pub deterministic: bool,
}

impl EvalSpec {
    /// Checks the environment exists and the episode count is in range; messages start with
    /// `prefix` (e.g. `eval.`) and name the field.
    pub fn validate(&self, prefix: &str) -> Result<(), RunnerOptionsError> {
        crate::envs::info(&self.env)
            .map_err(|e| RunnerOptionsError(format!("{prefix}env: {e}")))?;
        let max = crate::envs::metrics::MAX_EPISODES;
        if !(1..=max).contains(&self.episodes) {
            return Err(RunnerOptionsError(format!(
                "{prefix}episodes: must be between 1 and {max}, got {}",
                self.episodes
            )));
        }
        Ok(())
    }
}

impl EvalOptions {
    /// Parses and validates the request's `eval` object (absent or null: no evaluation).
    pub fn parse(
        raw: Option<&serde_json::Value>,
    ) -> Result<Option<EvalOptions>, RunnerOptionsError> {
        let options: EvalOptions = match raw {
            None | Some(serde_json::Value::Null) => return Ok(None),
            Some(value) => serde_json::from_value(value.clone())
                .map_err(|e| RunnerOptionsError(format!("eval: {e}")))?,
        };
        if let Some(every) = options.every.filter(|every| !(1..=100_000_000).contains(every)) {
            return Err(RunnerOptionsError(format!(
                "eval.every: must be between 1 and 100000000, got {every}"
            )));
        }
        options.spec().validate("eval.")?;
        Ok(Some(options))
    }

    /// The evaluation each due step runs.
    pub fn spec(&self) -> EvalSpec {
        EvalSpec {
            env: self.env.clone(),
            episodes: self.episodes,
            seed: self.seed,
            deterministic: self.deterministic,
        }
    }

    /// Whether to evaluate after `step_after` steps (1-based, every phase counted) of a run of
    /// `total` steps whose first `pretraining` steps train no policy: every `every` policy
    /// steps, and after the last step (the only one without `every`).
    pub fn due(&self, step_after: u64, pretraining: u64, total: u64) -> bool {
        step_after == total
            || self.every.is_some_and(|every| {
                step_after > pretraining && (step_after - pretraining).is_multiple_of(every)
            })
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
    fn eval_blocks_parse_with_defaults_and_name_the_bad_field() {
        assert_eq!(EvalOptions::parse(None).unwrap(), None);
        let o =
            EvalOptions::parse(Some(&json!({"env": "six-rooms", "every": 50}))).unwrap().unwrap();
        assert_eq!((o.every, o.episodes, o.seed, o.deterministic), (Some(50), 500, 0, false));
        // Without `every`: only at the end, and the block says so by leaving it out.
        let end = EvalOptions::parse(Some(&json!({"env": "six-rooms"}))).unwrap().unwrap();
        assert_eq!(end.every, None);
        assert!(serde_json::to_value(&end).unwrap().get("every").is_none());
        let bad = |v| EvalOptions::parse(Some(&v)).unwrap_err().0;
        assert_eq!(
            bad(json!({"env": "walker", "every": 5})),
            "eval.env: unknown environment `walker` (known: six-rooms, point-goal, cartpole-slider)"
        );
        assert_eq!(
            bad(json!({"env": "six-rooms", "every": 0})),
            "eval.every: must be between 1 and 100000000, got 0"
        );
        assert_eq!(
            bad(json!({"env": "six-rooms", "every": 5, "episodes": 0})),
            "eval.episodes: must be between 1 and 100000, got 0"
        );
        assert!(bad(json!({"every": 5})).starts_with("eval: missing field `env`"));
    }

    #[test]
    fn evaluations_follow_the_policy_phase_and_end_the_run() {
        let o = EvalOptions {
            env: "six-rooms".into(),
            every: Some(10),
            episodes: 5,
            seed: 0,
            deterministic: false,
        };
        // 15 pretraining steps, then 32 policy steps.
        let due: Vec<u64> = (1..=47).filter(|&s| o.due(s, 15, 47)).collect();
        assert_eq!(due, [25, 35, 45, 47]);
        let at_end = EvalOptions { every: None, ..o };
        let due: Vec<u64> = (1..=47).filter(|&s| at_end.due(s, 15, 47)).collect();
        assert_eq!(due, [47]);
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
