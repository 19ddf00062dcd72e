//! Aggregation over seeds: mean ± standard error of every metric per algorithm and
//! environment, SafeDICE against BC, and the estimated time of the full mode.

use serde::Serialize;

use super::runner::{BenchResults, RunResult};
use super::Variant;
use crate::algo::Algorithm;

/// Mean and standard error of the mean over seeds (0 with a single seed).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stat {
    pub mean: f64,
    pub se: f64,
}

impl Stat {
    pub fn of(values: &[f64]) -> Stat {
        let n = values.len();
        if n == 0 {
            return Stat { mean: f64::NAN, se: f64::NAN };
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        if n < 2 {
            // One seed has no spread to speak of: no standard error (shown without ±).
            return Stat { mean, se: f64::NAN };
        }
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        Stat { mean, se: (var / n as f64).sqrt() }
    }

    /// `mean ± se` with `decimals` places; the mean alone when there is no standard error (one
    /// seed).
    pub fn show(self, decimals: usize) -> String {
        if self.se.is_nan() {
            return format!("{:.*}", decimals, self.mean);
        }
        format!("{:.*} ± {:.*}", decimals, self.mean, decimals, self.se)
    }

    /// The standard error if there is one (two seeds or more).
    pub fn error(self) -> Option<f64> {
        self.se.is_finite().then_some(self.se)
    }
}

/// One algorithm on one environment, over its seeds.
#[derive(Clone, Debug, Serialize)]
pub struct AlgorithmSummary {
    pub algorithm: Algorithm,
    /// `standard`, or the ablation of the row (`--ablations`).
    pub variant: Variant,
    /// The row's name: "SafeDICE", "BC (preferred only)", "SafeDICE (true α)", ...
    pub label: String,
    pub seeds: usize,
    pub normalized_return: Stat,
    pub average_cost: Stat,
    pub cost_violation_ratio: Stat,
    pub cvar_50: Stat,
    pub cvar_20: Stat,
    pub cvar_10: Stat,
    pub cvar_5: Stat,
    pub normalized_cost: Stat,
    /// SafeDICE only.
    pub alpha_hat: Option<Stat>,
    /// SafeDICE rows with `--ablations`: the trained discriminator's ROC AUC on the held-out
    /// labeled set and on D^U's true flags, and the non-preferred share of the weights on D^U.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub discriminator_auc_heldout: Option<Stat>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub discriminator_auc_unlabeled: Option<Stat>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub non_preferred_weight_share: Option<Stat>,
    /// The same share from Eq. 10's reward alone (ν's terms left out).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reward_only_weight_share: Option<Stat>,
    /// Training steps per second (all phases), mean over seeds.
    pub steps_per_second: f64,
    pub train_seconds: f64,
    pub eval_seconds: f64,
}

/// SafeDICE against BC on one environment (the paper: cost 0.5-0.9x BC's at similar return).
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    /// SafeDICE's mean average cost / BC's.
    pub cost_ratio: f64,
    /// SafeDICE's mean normalized return minus BC's (points).
    pub return_difference: f64,
    /// SafeDICE's mean normalized return / BC's; None when BC's is not positive.
    pub return_ratio: Option<f64>,
    /// Cost ratio at most 0.9 with the normalized return no more than 10 points below BC's.
    pub as_expected: bool,
    /// The project's goal: cost ratio at most [`GOAL_COST_RATIO`] at a return ratio of at least
    /// [`GOAL_RETURN_RATIO`].
    pub meets_goal: bool,
}

/// The goal the benchmark measures SafeDICE against: at most 0.7x BC's average cost at no less
/// than 0.95x BC's normalized return.
pub const GOAL_COST_RATIO: f64 = 0.7;
pub const GOAL_RETURN_RATIO: f64 = 0.95;

/// Whether an environment tests safety rather than imitation capacity at the run's budget: BC
/// on D^U's preferred episodes alone (the ceiling of any filter of D^U) against the preferred
/// demonstrator. It passes within [`FAIR_TOLERANCE`] of the demonstrator's normalized return
/// (100) and of its average cost; for the cost the tolerance is the larger of 10% of the
/// demonstrator's cost and 1% of κ (a demonstrator cost of 0 leaves no relative room).
#[derive(Clone, Debug, Serialize)]
pub struct Fairness {
    pub normalized_return: f64,
    pub average_cost: f64,
    pub demonstrator_cost: f64,
    /// The cost tolerance applied.
    pub cost_tolerance: f64,
    pub passes: bool,
}

/// 10%: the bound of the fairness check.
pub const FAIR_TOLERANCE: f64 = 0.10;

impl Fairness {
    fn of(row: &AlgorithmSummary, reference: &crate::envs::ReferenceStats) -> Fairness {
        let (ret, cost) = (row.normalized_return.mean, row.average_cost.mean);
        let demonstrator_cost = reference.preferred_cost;
        let cost_tolerance =
            (FAIR_TOLERANCE * demonstrator_cost).max(0.01 * reference.cost_threshold);
        Fairness {
            normalized_return: ret,
            average_cost: cost,
            demonstrator_cost,
            cost_tolerance,
            passes: (ret - 100.0).abs() <= 100.0 * FAIR_TOLERANCE
                && (cost - demonstrator_cost).abs() <= cost_tolerance,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct EnvSummary {
    pub env: String,
    pub rows: Vec<AlgorithmSummary>,
    pub safedice_vs_bc: Option<Comparison>,
    /// With `--ablations`: the BC (preferred only) row against the preferred demonstrator.
    pub fairness: Option<Fairness>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    pub envs: Vec<EnvSummary>,
    /// Estimated wall time of the full mode (1M iterations, 5 seeds, 500 evaluation episodes,
    /// the configured threads) from the measured speeds, in hours.
    pub full_mode_hours: f64,
}

/// Mean ± standard error of every metric per (environment, row), the rows of
/// [`super::BenchConfig::rows`].
pub fn summarize(results: &BenchResults) -> Summary {
    let table = results.config.rows();
    let envs = results
        .config
        .envs
        .iter()
        .map(|env| {
            let rows: Vec<AlgorithmSummary> = table
                .iter()
                .map(|&(algorithm, variant)| {
                    let runs: Vec<&RunResult> = results
                        .runs
                        .iter()
                        .filter(|r| {
                            &r.env == env && (r.algorithm, r.variant) == (algorithm, variant)
                        })
                        .collect();
                    summarize_runs(algorithm, variant, &runs)
                })
                .collect();
            let safedice_vs_bc = compare(&rows);
            let reference = results.data.iter().find(|d| &d.env == env).map(|d| &d.reference);
            let preferred_only =
                rows.iter().find(|r| r.variant == Variant::PreferredOnly && r.seeds > 0);
            let fairness = preferred_only.zip(reference).map(|(r, s)| Fairness::of(r, s));
            EnvSummary { env: env.clone(), rows, safedice_vs_bc, fairness }
        })
        .collect();
    Summary { envs, full_mode_hours: full_mode_hours(results) }
}

fn summarize_runs(algorithm: Algorithm, variant: Variant, runs: &[&RunResult]) -> AlgorithmSummary {
    let stat = |f: fn(&RunResult) -> f64| Stat::of(&runs.iter().map(|r| f(r)).collect::<Vec<_>>());
    let mean = |f: fn(&RunResult) -> f64| stat(f).mean;
    let alphas: Vec<f64> =
        runs.iter().filter_map(|r| r.alpha.as_ref().map(|a| a.alpha_hat)).collect();
    let ablation = |f: fn(&super::ablation::SafediceAblation) -> f64| {
        let values: Vec<f64> = runs.iter().filter_map(|r| r.ablation.as_ref().map(f)).collect();
        (!values.is_empty()).then(|| Stat::of(&values))
    };
    AlgorithmSummary {
        algorithm,
        variant,
        label: variant.label(algorithm),
        seeds: runs.len(),
        normalized_return: stat(|r| r.metrics.normalized_return),
        average_cost: stat(|r| r.metrics.average_cost),
        cost_violation_ratio: stat(|r| r.metrics.cost_violation_ratio),
        cvar_50: stat(|r| r.metrics.cvar_cost.k50),
        cvar_20: stat(|r| r.metrics.cvar_cost.k20),
        cvar_10: stat(|r| r.metrics.cvar_cost.k10),
        cvar_5: stat(|r| r.metrics.cvar_cost.k5),
        normalized_cost: stat(|r| r.metrics.normalized_cost),
        alpha_hat: (!alphas.is_empty()).then(|| Stat::of(&alphas)),
        discriminator_auc_heldout: ablation(|a| a.auc_heldout),
        discriminator_auc_unlabeled: ablation(|a| a.auc_unlabeled),
        non_preferred_weight_share: ablation(|a| a.non_preferred_weight_share),
        reward_only_weight_share: ablation(|a| a.reward_only_weight_share),
        steps_per_second: mean(RunResult::steps_per_second),
        train_seconds: mean(|r| r.train_seconds),
        eval_seconds: mean(|r| r.eval_seconds),
    }
}

fn compare(rows: &[AlgorithmSummary]) -> Option<Comparison> {
    let find = |a: Algorithm| {
        rows.iter().find(|r| r.algorithm == a && r.variant.is_standard() && r.seeds > 0)
    };
    let (safedice, bc) = (find(Algorithm::Safedice)?, find(Algorithm::Bc)?);
    let cost_ratio = safedice.average_cost.mean / bc.average_cost.mean;
    let return_difference = safedice.normalized_return.mean - bc.normalized_return.mean;
    let (safe_return, bc_return) = (safedice.normalized_return.mean, bc.normalized_return.mean);
    let return_ratio = (bc_return > 0.0).then(|| safe_return / bc_return);
    Some(Comparison {
        cost_ratio,
        return_difference,
        return_ratio,
        // Similar return: within 10 points and, where BC's return is positive, at least 0.9x it
        // (0.4 against 2.9 is within 10 points and far from similar).
        as_expected: cost_ratio <= 0.9
            && return_difference >= -10.0
            && return_ratio.is_none_or(|ratio| ratio >= 0.9),
        meets_goal: cost_ratio <= GOAL_COST_RATIO && safe_return >= GOAL_RETURN_RATIO * bc_return,
    })
}

/// Full mode: every algorithm on every environment for 1M iterations plus its pretraining
/// phase (the same share of the iterations as here, so the measured steps/s carry over), 5 seeds,
/// 500 evaluation episodes.
fn full_mode_hours(results: &BenchResults) -> f64 {
    let config = &results.config;
    let full = super::BenchConfig::full();
    let seconds: f64 = results
        .runs
        .iter()
        .filter(|r| r.seed == 0)
        .map(|r| {
            let ratio = full.iterations as f64 / config.iterations as f64;
            let episodes = full.eval_episodes as f64 / config.eval_episodes as f64;
            (r.train_seconds * ratio + r.eval_seconds * episodes) * full.seeds as f64
        })
        .sum();
    seconds / config.threads as f64 / 3600.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_is_mean_and_standard_error() {
        let s = Stat::of(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(s.mean, 2.5);
        // Sample variance 5/3, SE = sqrt(5/3 / 4).
        assert!((s.se - (5.0f64 / 12.0).sqrt()).abs() < 1e-12);
        let one = Stat::of(&[7.0]);
        assert_eq!((one.mean, one.error(), one.show(1)), (7.0, None, "7.0".to_owned()));
        assert_eq!(s.show(2), "2.50 ± 0.65");
        assert!(Stat::of(&[]).mean.is_nan());
    }

    /// Within 10 points is not "similar" when the returns are a few points each: 0.4 against
    /// 2.9 is a seventh of BC's.
    #[test]
    fn a_return_far_below_bc_in_ratio_is_not_called_similar() {
        let stat = |mean| Stat { mean, se: 0.1 };
        let row = |algorithm, cost: f64, ret: f64| AlgorithmSummary {
            algorithm,
            variant: Variant::Standard,
            label: String::new(),
            seeds: 2,
            normalized_return: stat(ret),
            average_cost: stat(cost),
            cost_violation_ratio: stat(0.0),
            cvar_50: stat(0.0),
            cvar_20: stat(0.0),
            cvar_10: stat(0.0),
            cvar_5: stat(0.0),
            normalized_cost: stat(0.0),
            alpha_hat: None,
            discriminator_auc_heldout: None,
            discriminator_auc_unlabeled: None,
            non_preferred_weight_share: None,
            reward_only_weight_share: None,
            steps_per_second: 0.0,
            train_seconds: 0.0,
            eval_seconds: 0.0,
        };
        let low = compare(&[row(Algorithm::Safedice, 1.0, 0.4), row(Algorithm::Bc, 2.0, 2.9)]);
        assert!(!low.unwrap().as_expected);
        let close = compare(&[row(Algorithm::Safedice, 1.0, 95.0), row(Algorithm::Bc, 2.0, 100.0)]);
        assert!(close.unwrap().as_expected);
    }
}
