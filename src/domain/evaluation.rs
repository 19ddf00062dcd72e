//! A policy evaluation: its lifecycle and its stored record.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::protocol::RecordedRuntime;
use super::{EvalProtocol, EvalRuntime, EvalSpec, EvaluationId, PolicyId};
use crate::envs::metrics::{compute_metrics, MAX_EPISODES};
use crate::envs::{EvalReport, ReferenceStats};

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

    /// The status as an SQL string literal (`'queued'`), for the store's SQL text: so the store
    /// spells no status by hand, and the schema's CHECK constraint pins the same words.
    pub fn sql(self) -> String {
        format!("'{}'", self.as_str())
    }

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

/// Where an evaluation's episodes ran.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum EvaluationSource {
    /// Queued and run by a worker on a built-in environment.
    Builtin,
    /// Rolled out by the user in their own simulator and recorded with its per-episode returns
    /// and costs; the service computed the metrics.
    External,
}

impl EvaluationSource {
    pub fn as_str(self) -> &'static str {
        match self {
            EvaluationSource::Builtin => "builtin",
            EvaluationSource::External => "external",
        }
    }
}

impl std::str::FromStr for EvaluationSource {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        [EvaluationSource::Builtin, EvaluationSource::External]
            .into_iter()
            .find(|source| source.as_str() == s)
            .ok_or_else(|| format!("unknown evaluation source {s:?}"))
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
    pub source: EvaluationSource,
    /// How the policy acted: `Builtin` for the service's own evaluations.
    pub runtime: EvalRuntime,
    /// The metrics, once succeeded.
    pub report: Option<EvalReport>,
    /// Why it failed.
    pub error: Option<String>,
    /// The job's step (every phase counts) at which its worker ran it, for the evaluation a job
    /// with an `eval` block records at the end of training; None for one run after training.
    pub training_step: Option<u64>,
    pub created_at: DateTime<Utc>,
    pub started_at: Option<DateTime<Utc>>,
    pub finished_at: Option<DateTime<Utc>>,
}

impl EvaluationRecord {
    /// The protocol its numbers are comparable under.
    pub fn protocol(&self) -> EvalProtocol {
        EvalProtocol::new(&self.spec, self.runtime)
    }
}

/// An evaluation run in the user's own simulator, as recorded: each episode's undiscounted
/// return and cost, and the demonstrators' mean return and cost on that simulator (the
/// normalisation of the paper's metrics). The service computes the metrics with the same code
/// as its own evaluations.
#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExternalEvaluation {
    /// The simulator and task, 1-200 characters, e.g. `dm_control/walker-walk+joint_velocity`.
    #[schema(example = "dm_control/walker-walk+joint_velocity")]
    pub env: String,
    /// Each episode's return (sum of rewards), 1 to 100,000 episodes.
    pub returns: Vec<f64>,
    /// Each episode's cost (sum of per-step costs, at least 0), one per return.
    pub costs: Vec<f64>,
    /// Each episode's length in steps (optional; gives `mean_episode_length`).
    pub lengths: Option<Vec<u64>>,
    /// The demonstrators' means on this simulator.
    pub reference: ExternalReference,
    /// The seed the episodes were run with (recorded, not used). Default 0.
    #[serde(default, deserialize_with = "super::deserialize_seed")]
    #[schema(maximum = 9223372036854775807_u64)]
    pub seed: u64,
    /// Whether the policy acted deterministically (part of the evaluation's protocol: results
    /// are compared only between evaluations that agree on it). Default false.
    #[serde(default)]
    pub deterministic: bool,
    /// How the policy acted in the simulator: `act` (the served policy answered each step),
    /// `onnx` (its ONNX export ran locally) or `other`. Part of the protocol; absent: recorded
    /// as `unspecified`.
    pub runtime: Option<RecordedRuntime>,
}

/// An external evaluation checked: what it is stored under, how the policy ran, its report.
#[derive(Debug)]
pub struct RecordedEvaluation {
    pub spec: EvalSpec,
    pub runtime: EvalRuntime,
    pub report: EvalReport,
}

/// Mean episode return and cost of the preferred and non-preferred demonstrators: the
/// normalized return is 100 · mean return / `preferred_return`, the cost threshold κ is the
/// midpoint of the two costs.
#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExternalReference {
    pub preferred_return: f64,
    pub preferred_cost: f64,
    pub non_preferred_return: f64,
    pub non_preferred_cost: f64,
    /// Demonstrator episodes behind the means (recorded). Default 0: not said.
    #[serde(default)]
    pub episodes: usize,
}

impl ExternalEvaluation {
    /// The spec it is stored under, its runtime and its report, or what is wrong with it.
    pub fn into_report(self) -> Result<RecordedEvaluation, String> {
        let env = self.env.trim();
        if env.is_empty() || env.chars().count() > 200 || env.chars().any(char::is_control) {
            return Err("env must be 1-200 characters without control characters".into());
        }
        let n = self.returns.len();
        if !(1..=MAX_EPISODES).contains(&n) {
            return Err(format!("returns must hold 1 to {MAX_EPISODES} episodes, got {n}"));
        }
        if self.costs.len() != n {
            return Err(format!(
                "costs must hold one value per return ({n}), got {}",
                self.costs.len()
            ));
        }
        if let Some(lengths) = self.lengths.as_ref().filter(|l| l.len() != n) {
            return Err(format!(
                "lengths must hold one value per return ({n}), got {}",
                lengths.len()
            ));
        }
        check_values("returns", &self.returns, false)?;
        check_values("costs", &self.costs, true)?;
        let r = &self.reference;
        let means =
            [r.preferred_return, r.preferred_cost, r.non_preferred_return, r.non_preferred_cost];
        if means.iter().any(|v| !v.is_finite())
            || r.preferred_cost < 0.0
            || r.non_preferred_cost < 0.0
        {
            return Err("reference: every mean must be finite, and costs at least 0".into());
        }
        if r.preferred_return == 0.0 {
            return Err(
                "reference.preferred_return must not be 0 (it normalises the return)".into()
            );
        }
        if r.preferred_cost + r.non_preferred_cost <= 0.0 {
            return Err("reference: the demonstrators' costs must not both be 0 (their midpoint is the cost threshold)".into());
        }
        let reference = ReferenceStats {
            env: env.to_owned(),
            episodes: r.episodes,
            seed: self.seed,
            preferred_return: r.preferred_return,
            preferred_cost: r.preferred_cost,
            non_preferred_return: r.non_preferred_return,
            non_preferred_cost: r.non_preferred_cost,
            cost_threshold: (r.preferred_cost + r.non_preferred_cost) / 2.0,
        };
        let metrics = compute_metrics(&self.returns, &self.costs, &reference);
        check_metrics_finite(&metrics)?;
        let mean_episode_length = self
            .lengths
            .as_ref()
            .map_or(0.0, |lengths| lengths.iter().map(|&l| l as f64).sum::<f64>() / n as f64);
        let spec = EvalSpec {
            env: env.to_owned(),
            episodes: n,
            seed: self.seed,
            deterministic: self.deterministic,
        };
        let report = EvalReport {
            env: env.to_owned(),
            episodes: n,
            seed: self.seed,
            deterministic: self.deterministic,
            metrics,
            mean_episode_length,
            reference,
        };
        let runtime = self.runtime.map_or(EvalRuntime::Unspecified, EvalRuntime::from);
        Ok(RecordedEvaluation { spec, runtime, report })
    }
}

/// Finite inputs can still give a metric beyond f64 (a deviation above 1.8e308, a return
/// normalised by a reference near 0): refused, naming the metric and what it is computed from,
/// rather than stored as a report no reader could decode.
fn check_metrics_finite(metrics: &crate::envs::Metrics) -> Result<(), String> {
    let Some((name, _)) = metrics.named_values().into_iter().find(|(_, v)| !v.is_finite()) else {
        return Ok(());
    };
    let name = name.trim_start_matches("eval/");
    let from = match name {
        "normalized_return" => "returns and reference.preferred_return",
        "normalized_cost" => "costs and the reference's costs",
        n if n.contains("return") => "returns",
        _ => "costs",
    };
    Err(format!(
        "metrics.{name} would not be a finite number: {from} are too large (or the reference \
         too small) for a 64-bit float"
    ))
}

/// Every value finite (and, for costs, at least 0), else the first that is not.
fn check_values(name: &str, values: &[f64], non_negative: bool) -> Result<(), String> {
    match values.iter().position(|v| !v.is_finite() || (non_negative && *v < 0.0)) {
        None => Ok(()),
        Some(i) if non_negative => Err(format!("{name}[{i}] must be a finite number at least 0")),
        Some(i) => Err(format!("{name}[{i}] must be a finite number")),
    }
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

#[cfg(test)]
mod external_tests {
    use super::*;

    fn body(returns: Vec<f64>, costs: Vec<f64>) -> ExternalEvaluation {
        let reference = serde_json::json!({"preferred_return": 100.0, "preferred_cost": 2.0,
            "non_preferred_return": 100.0, "non_preferred_cost": 10.0});
        serde_json::from_value(serde_json::json!({"env": " sim/walk ", "returns": returns,
            "costs": costs, "lengths": [10, 20, 30, 40], "reference": reference}))
        .unwrap()
    }

    /// The metrics of recorded episodes, by hand: normalized return 100 · mean / R_P, κ the
    /// midpoint of the demonstrators' costs, the violation share, CVaR 10% the worst episode.
    #[test]
    fn recorded_episodes_get_the_papers_metrics_against_their_reference() {
        let RecordedEvaluation { spec, runtime, report } =
            body(vec![50.0, 70.0, 90.0, 110.0], vec![0.0, 4.0, 7.0, 13.0]).into_report().unwrap();
        assert_eq!((spec.env.as_str(), spec.episodes), ("sim/walk", 4));
        assert_eq!(runtime, EvalRuntime::Unspecified);
        let m = &report.metrics;
        assert_eq!((m.normalized_return, m.average_cost, m.cost_threshold), (80.0, 6.0, 6.0));
        assert_eq!((m.cost_violation_ratio, m.cvar_cost.k10, m.cvar_cost.k50), (0.5, 13.0, 10.0));
        assert_eq!(report.mean_episode_length, 25.0);
    }

    #[test]
    fn bad_recordings_are_refused_with_the_field_named() {
        let refused = |e: ExternalEvaluation| e.into_report().unwrap_err();
        let four = || vec![1.0; 4];
        assert!(refused(body(vec![], vec![])).starts_with("returns must hold 1 to 100000"));
        assert!(refused(body(four(), vec![1.0; 3])).starts_with("costs must hold one value"));
        assert_eq!(
            refused(body(four(), vec![1.0, -1.0, 1.0, 1.0])),
            "costs[1] must be a finite number at least 0"
        );
        let mut nan = body(four(), four());
        nan.returns[2] = f64::NAN;
        assert_eq!(refused(nan), "returns[2] must be a finite number");
        let mut zero = body(four(), four());
        zero.reference.preferred_return = 0.0;
        assert!(refused(zero).contains("preferred_return must not be 0"));
        let mut blank = body(four(), four());
        blank.env = "  ".into();
        assert!(refused(blank).starts_with("env must be"));
        // Finite inputs whose metrics would not be.
        let two = |returns: Vec<f64>, costs: Vec<f64>| ExternalEvaluation {
            lengths: None,
            ..body(returns, costs)
        };
        assert!(refused(two(vec![1.7e308, -1.7e308], vec![1.0; 2]))
            .starts_with("metrics.return_std would not be a finite number: returns"));
        let mut tiny = two(vec![1e10], vec![1.0]);
        tiny.reference.preferred_return = 1e-308;
        assert!(refused(tiny).starts_with(
            "metrics.normalized_return would not be a finite number: returns and reference"
        ));
        // Far apart, yet every metric finite: stored with the closed forms.
        let report = two(vec![1e200, -1e200], vec![0.0, 1e300]).into_report().unwrap().report;
        assert_eq!(report.metrics.average_return, 0.0);
        assert!((report.metrics.return_std / (2f64.sqrt() * 1e200) - 1.0).abs() < 1e-12);
        assert_eq!(report.metrics.cvar_cost.k5, 1e300);
    }
}
