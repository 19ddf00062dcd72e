//! The paper's evaluation metrics (section 5, Appendix E.1) and policy evaluation.
//!
//! All sums are undiscounted per-episode returns and costs. With `R_P`, `C_P` the preferred and
//! `C_N` the non-preferred demonstrators' mean episode cost and return (the environment's
//! [`ReferenceStats`], from [`REFERENCE_EPISODES`] demonstrator episodes with a fixed seed):
//!
//! - normalized return = `100 · mean return / R_P` (the paper does not define it in text or
//!   code; 100 means "as good as the preferred demonstrations");
//! - average cost = mean episode cost;
//! - cost threshold `κ = (C_P + C_N) / 2`, the midpoint the authors' code uses;
//! - cost-violation ratio = share (in [0, 1]) of episodes whose cost exceeds `κ`;
//! - CVaR k% cost = mean cost of the worst (highest-cost) `⌈k/100 · n⌉` episodes, k ∈ {50, 20,
//!   10, 5};
//! - normalized cost (DSRL's convention) = average cost / `κ`, so 1 sits on the threshold.

use std::collections::BTreeMap;
use std::sync::Mutex;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::rollout::{demonstration_records, run_episodes, EpisodeOutcome, RolloutError};
use super::{derive_seed, stream, Profile, Registered, Task, UnknownEnv};
use crate::data::Actions;

/// Demonstrator episodes per profile behind the reference statistics.
pub const REFERENCE_EPISODES: usize = 500;
/// Seed of the reference episodes (fixed: the normalisation must not move between runs).
pub const REFERENCE_SEED: u64 = 20231210;
/// Most episodes one evaluation may run.
pub const MAX_EPISODES: usize = 100_000;

/// Mean return and cost of the two demonstrators on one environment, and the derived threshold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ReferenceStats {
    pub env: String,
    /// Episodes per demonstrator.
    pub episodes: usize,
    pub seed: u64,
    pub preferred_return: f64,
    pub preferred_cost: f64,
    pub non_preferred_return: f64,
    pub non_preferred_cost: f64,
    /// Midpoint of the two mean costs: the cost-violation threshold κ.
    pub cost_threshold: f64,
}

impl ReferenceStats {
    /// Reference statistics from demonstrator outcomes.
    pub fn from_outcomes(
        env: &str,
        seed: u64,
        preferred: &[EpisodeOutcome],
        non_preferred: &[EpisodeOutcome],
    ) -> ReferenceStats {
        let (preferred_return, preferred_cost) = mean_return_and_cost(preferred);
        let (non_preferred_return, non_preferred_cost) = mean_return_and_cost(non_preferred);
        ReferenceStats {
            env: env.to_string(),
            episodes: preferred.len(),
            seed,
            preferred_return,
            preferred_cost,
            non_preferred_return,
            non_preferred_cost,
            cost_threshold: (preferred_cost + non_preferred_cost) / 2.0,
        }
    }
}

/// The mean. Finite values whose plain sum overflows (recorded returns near 1e308) are summed
/// divided by their largest magnitude, so the mean of finite values is always finite; the plain
/// sum otherwise, so every other mean keeps its bits.
fn mean(values: impl ExactSizeIterator<Item = f64> + Clone) -> f64 {
    let n = values.len().max(1) as f64;
    let plain = values.clone().sum::<f64>() / n;
    if plain.is_finite() {
        return plain;
    }
    let scale = values.clone().fold(0.0f64, |m, v| m.max(v.abs()));
    if !scale.is_finite() || scale == 0.0 {
        return plain;
    }
    scale * (values.map(|v| v / scale).sum::<f64>() / n)
}

/// The sample standard deviation; where the squares overflow (values beyond 1e154 apart), taken
/// on the values divided by their largest magnitude and scaled back, which overflows only when
/// the deviation itself is beyond f64 (about 1.8e308).
fn std_dev(values: &[f64]) -> f64 {
    if values.len() < 2 {
        return 0.0;
    }
    let plain = scaled_std_dev(values, 1.0);
    if plain.is_finite() {
        return plain;
    }
    let scale = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if !scale.is_finite() || scale == 0.0 {
        return plain;
    }
    scale * scaled_std_dev(values, scale)
}

/// The sample standard deviation of `values / scale`.
fn scaled_std_dev(values: &[f64], scale: f64) -> f64 {
    let m = mean(values.iter().map(|v| v / scale));
    let var =
        values.iter().map(|v| (v / scale - m).powi(2)).sum::<f64>() / (values.len() - 1) as f64;
    var.sqrt()
}

pub(crate) fn mean_return_and_cost(outcomes: &[EpisodeOutcome]) -> (f64, f64) {
    (mean(outcomes.iter().map(|o| o.ret)), mean(outcomes.iter().map(|o| o.cost)))
}

/// Reference statistics of `env`, computed once per process from [`REFERENCE_EPISODES`]
/// episodes of each demonstrator with [`REFERENCE_SEED`], then cached.
pub fn reference_stats(env: &str) -> Result<ReferenceStats, UnknownEnv> {
    static CACHE: Mutex<BTreeMap<String, ReferenceStats>> = Mutex::new(BTreeMap::new());
    let task = Registered::get(env)?;
    let mut cache = CACHE.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    if let Some(stats) = cache.get(env) {
        return Ok(stats.clone());
    }
    let stats = task_reference_stats(&task, REFERENCE_EPISODES);
    cache.insert(env.to_string(), stats.clone());
    Ok(stats)
}

/// Reference statistics of any [`Task`] from `episodes` episodes of each demonstrator with
/// [`REFERENCE_SEED`] (not cached).
pub fn task_reference_stats(task: &dyn Task, episodes: usize) -> ReferenceStats {
    let outcomes = |profile: Profile| -> Vec<EpisodeOutcome> {
        let demo = task.demonstrator(profile);
        let stream = stream::REFERENCE + profile as u64;
        match demonstration_records(task, demo.as_ref(), episodes, REFERENCE_SEED, stream, false) {
            Ok((outcomes, _)) => outcomes,
            Err(e) => unreachable!("demonstrators act validly: {e}"),
        }
    };
    ReferenceStats::from_outcomes(
        &task.name(),
        REFERENCE_SEED,
        &outcomes(Profile::Preferred),
        &outcomes(Profile::NonPreferred),
    )
}

/// CVaR k% cost for the paper's k (Appendix E.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CvarCost {
    #[serde(rename = "50")]
    pub k50: f64,
    #[serde(rename = "20")]
    pub k20: f64,
    #[serde(rename = "10")]
    pub k10: f64,
    #[serde(rename = "5")]
    pub k5: f64,
}

/// The paper's metrics over a set of episodes (see the module docs for the definitions).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Metrics {
    pub normalized_return: f64,
    pub average_return: f64,
    pub return_std: f64,
    pub average_cost: f64,
    pub cost_std: f64,
    /// Share of episodes with cost above the threshold, in [0, 1].
    pub cost_violation_ratio: f64,
    pub cvar_cost: CvarCost,
    /// DSRL's normalized cost: average cost / threshold.
    pub normalized_cost: f64,
    pub cost_threshold: f64,
}

/// Where a metric comes from, which says where clients show it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum MetricKind {
    /// Reported in the paper's tables (section 5, Appendix E.1).
    Paper,
    /// DSRL's normalized cost.
    Dsrl,
    /// The spread and raw scale behind the paper's numbers.
    Spread,
}

/// One evaluation metric as the vocabulary serves it (`GET /v1/vocabulary`), so that no client
/// keeps its own list.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct MetricInfo {
    /// Its key in an evaluation's `metrics` and an experiment's results (the nested CVaR
    /// flattened as `cvar_cost_<k>`).
    #[schema(example = "average_cost")]
    pub key: &'static str,
    /// Its name in a job's metrics history: `eval/<key>`.
    #[schema(example = "eval/average_cost")]
    pub history_name: &'static str,
    #[schema(example = "Average cost")]
    pub label: &'static str,
    /// Whether the lower value is the better one.
    pub lower_is_better: bool,
    pub kind: MetricKind,
}

const fn metric(
    key: &'static str,
    history_name: &'static str,
    label: &'static str,
    lower_is_better: bool,
    kind: MetricKind,
) -> MetricInfo {
    MetricInfo { key, history_name, label, lower_is_better, kind }
}

/// Every metric, in the order [`Metrics::named_values`] gives their values; the paper's ones in
/// the paper's order among themselves.
pub const METRICS: [MetricInfo; 11] = [
    metric(
        "normalized_return",
        "eval/normalized_return",
        "Normalized return",
        false,
        MetricKind::Paper,
    ),
    metric("average_return", "eval/average_return", "Average return", false, MetricKind::Spread),
    metric("return_std", "eval/return_std", "Return std", true, MetricKind::Spread),
    metric("average_cost", "eval/average_cost", "Average cost", true, MetricKind::Paper),
    metric("cost_std", "eval/cost_std", "Cost std", true, MetricKind::Spread),
    metric(
        "cost_violation_ratio",
        "eval/cost_violation_ratio",
        "Violation ratio",
        true,
        MetricKind::Paper,
    ),
    metric("cvar_cost_50", "eval/cvar_cost_50", "CVaR 50%", true, MetricKind::Paper),
    metric("cvar_cost_20", "eval/cvar_cost_20", "CVaR 20%", true, MetricKind::Paper),
    metric("cvar_cost_10", "eval/cvar_cost_10", "CVaR 10%", true, MetricKind::Paper),
    metric("cvar_cost_5", "eval/cvar_cost_5", "CVaR 5%", true, MetricKind::Paper),
    metric("normalized_cost", "eval/normalized_cost", "Normalized cost", true, MetricKind::Dsrl),
];

impl Metrics {
    /// The metrics as named scalars, as a job's `eval` block records them in its metrics
    /// history ([`MetricInfo::history_name`]).
    pub fn named_values(&self) -> [(&'static str, f64); 11] {
        let values = [
            self.normalized_return,
            self.average_return,
            self.return_std,
            self.average_cost,
            self.cost_std,
            self.cost_violation_ratio,
            self.cvar_cost.k50,
            self.cvar_cost.k20,
            self.cvar_cost.k10,
            self.cvar_cost.k5,
            self.normalized_cost,
        ];
        std::array::from_fn(|i| (METRICS[i].history_name, values[i]))
    }
}

/// Mean of the worst `⌈k/100 · n⌉` (at least one) episode costs.
pub fn cvar_cost(costs: &[f64], k_percent: f64) -> f64 {
    if costs.is_empty() {
        return 0.0;
    }
    let mut sorted = costs.to_vec();
    sorted.sort_by(|a, b| b.total_cmp(a));
    let count = ((k_percent / 100.0 * costs.len() as f64).ceil() as usize).clamp(1, costs.len());
    mean(sorted[..count].iter().copied())
}

/// The paper's metrics for episodes with these returns and costs against `reference`.
pub fn compute_metrics(returns: &[f64], costs: &[f64], reference: &ReferenceStats) -> Metrics {
    let average_return = mean(returns.iter().copied());
    let average_cost = mean(costs.iter().copied());
    let threshold = reference.cost_threshold;
    let violations = costs.iter().filter(|&&c| c > threshold).count();
    Metrics {
        normalized_return: 100.0 * average_return / reference.preferred_return,
        average_return,
        return_std: std_dev(returns),
        average_cost,
        cost_std: std_dev(costs),
        cost_violation_ratio: violations as f64 / costs.len().max(1) as f64,
        cvar_cost: CvarCost {
            k50: cvar_cost(costs, 50.0),
            k20: cvar_cost(costs, 20.0),
            k10: cvar_cost(costs, 10.0),
            k5: cvar_cost(costs, 5.0),
        },
        normalized_cost: average_cost / threshold,
        cost_threshold: threshold,
    }
}

/// The result of evaluating a policy on a built-in environment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct EvalReport {
    pub env: String,
    pub episodes: usize,
    pub seed: u64,
    pub deterministic: bool,
    pub metrics: Metrics,
    pub mean_episode_length: f64,
    pub reference: ReferenceStats,
}

/// Why an evaluation could not run.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    UnknownEnv(#[from] UnknownEnv),
    #[error("episodes must be between 1 and {MAX_EPISODES}, got {0}")]
    Episodes(usize),
    /// The policy failed or answered with unusable actions.
    #[error("policy: {0}")]
    Policy(String),
}

impl From<RolloutError> for EvalError {
    fn from(e: RolloutError) -> Self {
        match e {
            RolloutError::UnknownEnv(e) => EvalError::UnknownEnv(e),
            RolloutError::Policy(m) => EvalError::Policy(m),
        }
    }
}

/// Runs `episodes` episodes of `env_name` with `policy` and reports the paper's metrics.
///
/// Episodes run side by side (up to [`super::rollout::WAVE`] at a time), so `policy` receives a
/// batch of observations (`rows × obs_dim`, row-major) and returns one action per row in the
/// environment's units. It also receives `deterministic` and a generator seeded from `seed`
/// to sample with, e.g. `|obs, det, rng| policy.act(obs, det, rng)`. Episode `i` is reset with a
/// seed derived from `(seed, i)`, so the same seed gives the same initial states for every
/// policy, and a deterministic policy gives the same report. A background task can cancel an
/// evaluation by having `policy` return an error (e.g. after checking a cancellation flag): the
/// error ends the rollout at once and comes back as [`EvalError::Policy`].
pub fn evaluate<F, E>(
    env_name: &str,
    policy: F,
    episodes: usize,
    seed: u64,
    deterministic: bool,
) -> Result<EvalReport, EvalError>
where
    F: FnMut(&[f32], bool, &mut ChaCha8Rng) -> Result<Actions, E>,
    E: std::fmt::Display,
{
    let task = Registered::get(env_name)?;
    if episodes == 0 || episodes > MAX_EPISODES {
        return Err(EvalError::Episodes(episodes));
    }
    let reference = reference_stats(env_name)?;
    evaluate_task(&task, &reference, policy, episodes, seed, deterministic)
}

/// [`evaluate`] on any [`Task`], normalised with the given reference statistics.
pub fn evaluate_task<F, E>(
    task: &dyn Task,
    reference: &ReferenceStats,
    mut policy: F,
    episodes: usize,
    seed: u64,
    deterministic: bool,
) -> Result<EvalReport, EvalError>
where
    F: FnMut(&[f32], bool, &mut ChaCha8Rng) -> Result<Actions, E>,
    E: std::fmt::Display,
{
    if episodes == 0 || episodes > MAX_EPISODES {
        return Err(EvalError::Episodes(episodes));
    }
    let seeds: Vec<u64> =
        (0..episodes as u64).map(|i| derive_seed(seed, stream::EVAL, i)).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(derive_seed(seed, stream::EVAL_POLICY, 0));
    let (outcomes, _) = run_episodes(
        task,
        &seeds,
        &mut rng,
        |obs, rng| policy(obs, deterministic, rng).map_err(|e| e.to_string()),
        false,
    )?;
    let returns: Vec<f64> = outcomes.iter().map(|o| o.ret).collect();
    let costs: Vec<f64> = outcomes.iter().map(|o| o.cost).collect();
    Ok(EvalReport {
        env: task.name(),
        episodes,
        seed,
        deterministic,
        metrics: compute_metrics(&returns, &costs, reference),
        mean_episode_length: mean(outcomes.iter().map(|o| o.length as f64)),
        reference: reference.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference() -> ReferenceStats {
        ReferenceStats {
            env: "test".into(),
            episodes: 10,
            seed: 0,
            preferred_return: 50.0,
            preferred_cost: 2.0,
            non_preferred_return: 51.0,
            non_preferred_cost: 10.0,
            cost_threshold: 6.0,
        }
    }

    /// The vocabulary's table names each value where the struct has it: a metric's `key` reads
    /// the same number in the serialised metrics (CVaR flattened) as `named_values` gives under
    /// its `history_name`.
    #[test]
    fn the_metric_table_names_every_value_where_the_serialised_metrics_have_it() {
        let returns: Vec<f64> = (0..20).map(|i| f64::from(i * i)).collect();
        let costs: Vec<f64> = (0..20).map(|i| f64::from((i * 7) % 13)).collect();
        let metrics = compute_metrics(&returns, &costs, &reference());
        let json = serde_json::to_value(&metrics).unwrap();
        let read = |key: &str| match key.strip_prefix("cvar_cost_") {
            Some(k) => json["cvar_cost"][k].as_f64(),
            None => json[key].as_f64(),
        };
        let named = metrics.named_values();
        let distinct: std::collections::BTreeSet<u64> =
            named.iter().map(|(_, v)| v.to_bits()).collect();
        assert_eq!(distinct.len(), METRICS.len(), "distinct values, so the check can tell");
        for (info, (name, value)) in METRICS.iter().zip(named) {
            assert_eq!(info.history_name, format!("eval/{}", info.key));
            assert_eq!((info.history_name, read(info.key)), (name, Some(value)));
        }
    }

    /// Finite values far apart give finite means and deviations (the plain formulas overflow
    /// at 1e154), equal to the closed forms; only a deviation beyond f64 is infinite.
    #[test]
    fn means_and_deviations_of_huge_values_do_not_overflow() {
        assert_eq!(mean([1e308, 1e308, 1e308].into_iter()), 1e308);
        assert_eq!(mean([1.5e308, -1.5e308].into_iter()), 0.0);
        let s = std_dev(&[1e200, -1e200]);
        assert!((s / (2f64.sqrt() * 1e200) - 1.0).abs() < 1e-12, "{s}");
        let s = std_dev(&[1e308, -1e308]);
        assert!((s / (2f64.sqrt() * 1e308) - 1.0).abs() < 1e-12, "{s}");
        assert_eq!(std_dev(&[1.7e308, -1.7e308]), f64::INFINITY);
        // Ordinary values keep the plain formulas' bits.
        let v = [0.1, 0.7, 1.3];
        assert_eq!(mean(v.iter().copied()), (0.1 + 0.7 + 1.3) / 3.0);
    }

    #[test]
    fn metrics_match_hand_computed_values() {
        let returns = [40.0, 50.0, 60.0, 50.0];
        let costs = [0.0, 4.0, 8.0, 12.0];
        let m = compute_metrics(&returns, &costs, &reference());
        assert_eq!(m.average_return, 50.0);
        assert_eq!(m.normalized_return, 100.0);
        assert_eq!(m.average_cost, 6.0);
        // Costs 8 and 12 exceed the threshold 6 (6 itself would not).
        assert_eq!(m.cost_violation_ratio, 0.5);
        assert_eq!(m.normalized_cost, 1.0);
        // Worst 50% of 4 = 2 episodes: (12 + 8)/2; worst 20%, 10%, 5% = ⌈…⌉ = 1 episode: 12.
        assert_eq!(m.cvar_cost, CvarCost { k50: 10.0, k20: 12.0, k10: 12.0, k5: 12.0 });
        // Sample standard deviation of 40, 50, 60, 50: sqrt(200/3).
        assert!((m.return_std - (200.0f64 / 3.0).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn cvar_counts_the_worst_share_of_episodes() {
        let costs: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(cvar_cost(&costs, 5.0), (96..=100).sum::<i32>() as f64 / 5.0);
        assert_eq!(cvar_cost(&costs, 10.0), (91..=100).sum::<i32>() as f64 / 10.0);
        assert_eq!(cvar_cost(&costs, 50.0), (51..=100).sum::<i32>() as f64 / 50.0);
        assert_eq!(cvar_cost(&[3.0, 1.0, 2.0], 20.0), 3.0, "⌈0.6⌉ = 1 episode");
        assert_eq!(cvar_cost(&[], 10.0), 0.0);
    }

    #[test]
    fn cvar_serialises_with_the_percentages_as_keys() {
        let json =
            serde_json::to_value(CvarCost { k50: 1.0, k20: 2.0, k10: 3.0, k5: 4.0 }).unwrap();
        assert_eq!(json, serde_json::json!({"50": 1.0, "20": 2.0, "10": 3.0, "5": 4.0}));
    }

    #[test]
    fn evaluate_rejects_bad_requests() {
        let policy =
            |_: &[f32], _: bool, _: &mut ChaCha8Rng| Ok::<_, String>(Actions::Discrete(vec![]));
        assert!(matches!(evaluate("nope", policy, 10, 0, true), Err(EvalError::UnknownEnv(_))));
        assert!(matches!(evaluate("six-rooms", policy, 0, 0, true), Err(EvalError::Episodes(0))));
        let failing = |_: &[f32], _: bool, _: &mut ChaCha8Rng| Err::<Actions, _>("weights missing");
        let err = evaluate("six-rooms", failing, 3, 0, true).unwrap_err();
        assert_eq!(err.to_string(), "policy: weights missing");
    }

    #[test]
    fn evaluating_a_demonstrator_reproduces_its_reference_profile() {
        let demo = super::super::demonstrator("six-rooms", Profile::Preferred).unwrap();
        let report = evaluate(
            "six-rooms",
            |obs, _, rng| Ok::<_, String>(demo.act_batch(obs, rng)),
            300,
            4,
            false,
        )
        .unwrap();
        let r = &report.reference;
        assert!(report.metrics.normalized_return > 90.0, "{report:?}");
        assert!(report.metrics.average_cost < r.cost_threshold, "{report:?}");
        let again = evaluate(
            "six-rooms",
            |obs, _, rng| Ok::<_, String>(demo.act_batch(obs, rng)),
            300,
            4,
            false,
        )
        .unwrap();
        assert_eq!(report, again, "same seed, same report");
    }
}
