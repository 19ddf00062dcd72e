//! Aggregation over seeds (mean ± standard error) and the written outputs: results.md (tables
//! like the paper's Tables 5-9), results.json (every run) and the SVG plots.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::runner::{BenchResults, RunResult};
use super::{plot, BASELINE_KNOBS};
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
            return Stat { mean, se: 0.0 };
        }
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        Stat { mean, se: (var / n as f64).sqrt() }
    }

    fn show(self, decimals: usize) -> String {
        format!("{:.*} ± {:.*}", decimals, self.mean, decimals, self.se)
    }
}

/// One algorithm on one environment, over its seeds.
#[derive(Clone, Debug, Serialize)]
pub struct AlgorithmSummary {
    pub algorithm: Algorithm,
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
    /// Cost ratio at most 0.9 with the normalized return no more than 10 points below BC's.
    pub as_expected: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct EnvSummary {
    pub env: String,
    pub rows: Vec<AlgorithmSummary>,
    pub safedice_vs_bc: Option<Comparison>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    pub envs: Vec<EnvSummary>,
    /// Estimated wall time of the full mode (1M iterations, 5 seeds, 500 evaluation episodes,
    /// the configured threads) from the measured speeds, in hours.
    pub full_mode_hours: f64,
}

/// Mean ± standard error of every metric per (environment, algorithm).
pub fn summarize(results: &BenchResults) -> Summary {
    let envs = results
        .config
        .envs
        .iter()
        .map(|env| {
            let rows: Vec<AlgorithmSummary> = results
                .config
                .algorithms
                .iter()
                .map(|&algorithm| {
                    let runs: Vec<&RunResult> = results
                        .runs
                        .iter()
                        .filter(|r| &r.env == env && r.algorithm == algorithm)
                        .collect();
                    summarize_runs(algorithm, &runs)
                })
                .collect();
            let safedice_vs_bc = compare(&rows);
            EnvSummary { env: env.clone(), rows, safedice_vs_bc }
        })
        .collect();
    Summary { envs, full_mode_hours: full_mode_hours(results) }
}

fn summarize_runs(algorithm: Algorithm, runs: &[&RunResult]) -> AlgorithmSummary {
    let stat = |f: fn(&RunResult) -> f64| Stat::of(&runs.iter().map(|r| f(r)).collect::<Vec<_>>());
    let mean = |f: fn(&RunResult) -> f64| stat(f).mean;
    let alphas: Vec<f64> =
        runs.iter().filter_map(|r| r.alpha.as_ref().map(|a| a.alpha_hat)).collect();
    AlgorithmSummary {
        algorithm,
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
        steps_per_second: mean(RunResult::steps_per_second),
        train_seconds: mean(|r| r.train_seconds),
        eval_seconds: mean(|r| r.eval_seconds),
    }
}

fn compare(rows: &[AlgorithmSummary]) -> Option<Comparison> {
    let find = |a: Algorithm| rows.iter().find(|r| r.algorithm == a && r.seeds > 0);
    let (safedice, bc) = (find(Algorithm::Safedice)?, find(Algorithm::Bc)?);
    let cost_ratio = safedice.average_cost.mean / bc.average_cost.mean;
    let return_difference = safedice.normalized_return.mean - bc.normalized_return.mean;
    Some(Comparison {
        cost_ratio,
        return_difference,
        as_expected: cost_ratio <= 0.9 && return_difference >= -10.0,
    })
}

/// Full mode: every algorithm on every environment for 1M iterations plus its pretraining
/// phase (same 10% share as here, so the measured steps/s carry over), 5 seeds, 500 episodes.
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

/// The SafeDICE-vs-BC table printed at the end of `safedice bench`.
pub fn console_table(summary: &Summary) -> String {
    let mut out = String::new();
    for env in &summary.envs {
        let _ = writeln!(out, "\n{}", env.env);
        let _ = writeln!(
            out,
            "  {:<9} {:>16} {:>16} {:>14} {:>16}",
            "algorithm", "norm. return", "avg cost", "violation", "alpha-hat"
        );
        for r in &env.rows {
            let alpha = r.alpha_hat.map_or("-".to_string(), |a| a.show(4));
            let _ = writeln!(
                out,
                "  {:<9} {:>16} {:>16} {:>14} {:>16}",
                r.algorithm.as_str(),
                r.normalized_return.show(1),
                r.average_cost.show(2),
                r.cost_violation_ratio.show(2),
                alpha
            );
        }
        if let Some(c) = &env.safedice_vs_bc {
            let _ = writeln!(
                out,
                "  SafeDICE/BC cost ratio {:.2}, return difference {:+.1} points",
                c.cost_ratio, c.return_difference
            );
        }
    }
    out
}

/// Writes results.md, results.json and one `<env>.svg` per environment into `dir`; returns the
/// paths written.
pub fn write_outputs(
    results: &BenchResults,
    summary: &Summary,
    dir: &Path,
    command: &str,
) -> std::io::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let mut written = Vec::new();
    for env in &summary.envs {
        let path = dir.join(format!("{}.svg", env.env));
        std::fs::write(&path, plot::cost_vs_return(env))?;
        written.push(path);
    }
    let path = dir.join("results.json");
    let json = serde_json::json!({ "results": results, "summary": summary });
    std::fs::write(&path, serde_json::to_vec_pretty(&json).map_err(std::io::Error::other)?)?;
    written.push(path);
    let path = dir.join("results.md");
    std::fs::write(&path, markdown(results, summary, command))?;
    written.push(path);
    Ok(written)
}

/// The report: run description, one table per environment, SafeDICE diagnostics, speeds.
pub fn markdown(results: &BenchResults, summary: &Summary, command: &str) -> String {
    let c = &results.config;
    let mut md = String::new();
    let _ = writeln!(md, "# Benchmark results\n");
    let _ = writeln!(md, "- Command: `{command}`");
    let _ = writeln!(md, "- Date: {} (UTC start)", results.started.format("%Y-%m-%d %H:%M"));
    let _ = writeln!(md, "- Git commit: {}", results.git_commit);
    let _ = writeln!(
        md,
        "- Training: service preset, {} policy iterations per run (+10% pretraining for SafeDICE's \
         discriminator and PPL's reward model), seeds 0..{}, {} thread(s) in parallel; {}{}",
        c.iterations,
        c.seeds,
        c.threads,
        BASELINE_KNOBS,
        if c.overrides.is_empty() {
            String::new()
        } else {
            format!("; overrides {}", serde_json::Value::Object(c.overrides.clone()))
        }
    );
    let _ = writeln!(
        md,
        "- Data (seed {}): D^U = {} preferred + {} non-preferred episodes, D^N = {} labeled \
         non-preferred episodes",
        c.data_seed, c.data.preferred, c.data.non_preferred, c.data.labeled
    );
    let _ = writeln!(
        md,
        "- Evaluation: {} episodes per policy, {} actions, evaluation seed = training seed",
        c.eval_episodes,
        if c.deterministic_eval { "deterministic" } else { "sampled" }
    );
    let _ = writeln!(
        md,
        "- Wall time: {:.1} min; full mode (1M iterations, 5 seeds, 500 episodes, {} threads) \
         estimated at {:.0} h from the speeds measured here (same networks, batch and load)",
        results.wall_seconds / 60.0,
        c.threads,
        summary.full_mode_hours
    );
    let _ = writeln!(
        md,
        "\nMetrics (src/envs/metrics.rs): normalized return = 100 · mean return / the preferred \
         demonstrator's; cost threshold κ = midpoint of the two demonstrators' mean costs; \
         violation = share of episodes with cost > κ; CVaR k% = mean cost of the worst k% \
         episodes; normalized cost = average cost / κ. Cells: mean ± standard error over seeds.\n"
    );
    for (env, data) in summary.envs.iter().zip(&results.data) {
        write_env(&mut md, env, data);
    }
    write_diagnostics(&mut md, results);
    write_speeds(&mut md, summary);
    md
}

fn write_env(md: &mut String, env: &super::report::EnvSummary, data: &super::runner::EnvData) {
    let _ = writeln!(md, "## {}\n", env.env);
    let r = &data.reference;
    let _ = writeln!(
        md,
        "Demonstrators (reference, {} episodes each): preferred return {:.2} / cost {:.2}, \
         non-preferred return {:.2} / cost {:.2}; κ = {:.2}. Generated D^U: preferred mean cost \
         {:.2}, non-preferred {:.2}; {} + {} transitions.\n",
        r.episodes,
        r.preferred_return,
        r.preferred_cost,
        r.non_preferred_return,
        r.non_preferred_cost,
        r.cost_threshold,
        data.unlabeled_preferred.mean_cost,
        data.unlabeled_non_preferred.mean_cost,
        data.unlabeled_preferred.transitions,
        data.unlabeled_non_preferred.transitions
    );
    let _ = writeln!(
        md,
        "| Algorithm | Normalized return | Average cost | Cost-violation ratio | CVaR 50% | \
         CVaR 20% | CVaR 10% | CVaR 5% | Normalized cost | alpha-hat |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|");
    for row in &env.rows {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            display_name(row.algorithm),
            row.normalized_return.show(1),
            row.average_cost.show(2),
            row.cost_violation_ratio.show(3),
            row.cvar_50.show(2),
            row.cvar_20.show(2),
            row.cvar_10.show(2),
            row.cvar_5.show(2),
            row.normalized_cost.show(3),
            row.alpha_hat.map_or("–".to_string(), |a| a.show(4)),
        );
    }
    if let Some(cmp) = &env.safedice_vs_bc {
        let _ = writeln!(
            md,
            "\nSafeDICE vs BC: cost ratio {:.2} (paper: 0.5-0.9), normalized return {:+.1} points. \
             {}",
            cmp.cost_ratio,
            cmp.return_difference,
            if cmp.as_expected {
                "As expected: clearly lower cost at similar return."
            } else {
                "NOT as expected (see the SafeDICE diagnostics below)."
            }
        );
    }
    let _ = writeln!(md, "\n![{} cost vs return]({}.svg)\n", env.env, env.env);
}

fn write_diagnostics(md: &mut String, results: &BenchResults) {
    let runs: Vec<&RunResult> = results.runs.iter().filter(|r| r.alpha.is_some()).collect();
    if runs.is_empty() {
        return;
    }
    let _ = writeln!(md, "## SafeDICE diagnostics (per run)\n");
    let _ = writeln!(
        md,
        "alpha-hat = min over D^U of (1/c − 1) minus 1e-5 (Eq. 15). `argmin episode` is the D^U \
         episode holding that minimum and whether it was generated by the non-preferred \
         demonstrator (ground truth the learner never sees). q01 is the 1% quantile of the same \
         ratio (a diagnostic, not the paper): far above the minimum means one rare sample set \
         alpha-hat. With the optimal discriminator, min (1/c − 1) = min d^U/d^N is the \
         non-preferred share α of D^U wherever the preferred demonstrator never goes, so the \
         share column is what alpha-hat would be with separable demonstrators. ESS = effective sample size of the policy weights as a fraction of the batch \
         (mean over the recorded steps / last).\n"
    );
    let _ = writeln!(
        md,
        "| Env | Seed | alpha-hat | D^U non-preferred share | min ratio | q01 ratio | argmin episode | non-preferred? | ESS mean | ESS last | clipped rewards |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|");
    for r in runs {
        let a = r.alpha.as_ref().expect("filtered");
        let share = results.data.iter().find(|d| d.env == r.env).map_or(f64::NAN, |d| {
            let n = d.unlabeled_non_preferred.transitions as f64;
            n / (n + d.unlabeled_preferred.transitions as f64)
        });
        let _ = writeln!(
            md,
            "| {} | {} | {:.4} | {:.3} | {:.4} | {:.4} | {} | {} | {:.3} | {:.3} | {} |",
            r.env,
            r.seed,
            a.alpha_hat,
            share,
            a.min_ratio,
            a.quantile_01,
            a.argmin_episode,
            if a.argmin_episode_is_non_preferred { "yes" } else { "no" },
            a.ess_fraction_mean,
            a.ess_fraction_last,
            a.reward_clipped_rows
        );
    }
    let _ = writeln!(md);
}

fn write_speeds(md: &mut String, summary: &Summary) {
    let _ = writeln!(md, "## Speed (this run; the machine was shared, so timings are noisy)\n");
    let _ = writeln!(md, "| Env | Algorithm | steps/s | train s / run | eval s / run |");
    let _ = writeln!(md, "|---|---|---|---|---|");
    for env in &summary.envs {
        for r in &env.rows {
            let _ = writeln!(
                md,
                "| {} | {} | {:.1} | {:.1} | {:.1} |",
                env.env,
                display_name(r.algorithm),
                r.steps_per_second,
                r.train_seconds,
                r.eval_seconds
            );
        }
    }
    let _ = writeln!(md);
}

/// The algorithm's name as the paper writes it.
pub fn display_name(algorithm: Algorithm) -> &'static str {
    match algorithm {
        Algorithm::Safedice => "SafeDICE",
        Algorithm::Bc => "BC",
        Algorithm::Dwbc => "DWBC",
        Algorithm::Ppl => "PPL",
        Algorithm::Dexperts => "DExperts",
    }
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
        assert_eq!(Stat::of(&[7.0]), Stat { mean: 7.0, se: 0.0 });
        assert!(Stat::of(&[]).mean.is_nan());
    }
}
