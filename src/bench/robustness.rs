//! `safedice bench --suite robustness`: the defaults' proving ground. Every task of the
//! generated suite ([`crate::envs::suite`]) trains BC, BC on the preferred episodes alone (the
//! ceiling of any filter of D^U, and the fairness check), and the selected algorithms; each
//! algorithm is scored per task against BC by the share of the achievable improvement it
//! captured, `(cost_BC − cost) / (cost_BC − cost_BC-preferred)`, and by whether it is worse than
//! BC (cost above 1.05x BC's, or normalized return below 0.95x BC's). The summary gives the
//! median, the 10th percentile and the worst task of the captured share, so a default that helps
//! most tasks and breaks a few shows.
//!
//! Defaults are chosen on the `dev` split only; the `test` split is run once to report them.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::report;
use super::runner::{self, BenchResults, BenchTask};
use super::summary::{summarize, AlgorithmSummary, EnvSummary, Summary};
use super::{BenchConfig, DataSize, Variant};
use crate::algo::Algorithm;
use crate::envs::suite::{Split, TaskSpec};
use crate::envs::task_reference_stats;

/// Demonstrator episodes per profile behind a suite task's reference statistics.
pub const REFERENCE_EPISODES: usize = 200;
/// Worse than BC: average cost above this multiple of BC's (plus 1% of κ, so a BC cost of 0
/// leaves room for noise) ...
pub const WORSE_COST_RATIO: f64 = 1.05;
/// ... or normalized return below this multiple of the lower of BC's and BC-preferred-only's:
/// where the preferred demonstrations themselves hold less return than BC's mixture (the
/// non-preferred demonstrator earns more), a safe policy cannot be asked for BC's return.
pub const WORSE_RETURN_RATIO: f64 = 0.95;
/// The suite's fairness check: BC on the preferred episodes alone within 10 points of the
/// preferred demonstrator's normalized return and within the larger of 10% of its cost and
/// [`FAIR_COST_KAPPA`] κ of it. The built-in environments' check allows 1% of κ; the suite's
/// gridworlds have costs of a fraction of a step per episode, which 200 evaluation episodes
/// cannot resolve to 1% of κ.
pub const FAIR_COST_KAPPA: f64 = 0.05;

/// The suite's fairness check of one task (see [`FAIR_COST_KAPPA`]).
#[derive(Clone, Debug, Serialize)]
pub struct TaskFairness {
    pub task: String,
    pub normalized_return: f64,
    pub average_cost: f64,
    pub demonstrator_cost: f64,
    pub cost_tolerance: f64,
    pub passes: bool,
}

fn fairness(results: &BenchResults, env: &EnvSummary) -> Option<TaskFairness> {
    let ceiling = row(env, Algorithm::Bc, Variant::PreferredOnly)?;
    let reference = &results.data.iter().find(|d| d.env == env.env)?.reference;
    let (ret, cost) = (ceiling.normalized_return.mean, ceiling.average_cost.mean);
    let demonstrator_cost = reference.preferred_cost;
    let cost_tolerance = (0.1 * demonstrator_cost).max(FAIR_COST_KAPPA * reference.cost_threshold);
    Some(TaskFairness {
        task: env.env.clone(),
        normalized_return: ret,
        average_cost: cost,
        demonstrator_cost,
        cost_tolerance,
        passes: (ret - 100.0).abs() <= 10.0 && (cost - demonstrator_cost).abs() <= cost_tolerance,
    })
}

/// A task scores the captured share only where BC on the preferred episodes improves on BC by
/// at least this share of κ; elsewhere there is nothing to capture.
pub const MIN_ACHIEVABLE: f64 = 0.05;

/// The suite's default budget: small networks and runs, so both splits train every row in
/// about 2 h on 2 cores.
pub fn default_config() -> BenchConfig {
    let mut overrides = serde_json::Map::new();
    overrides.insert("batch_size".into(), 256.into());
    overrides.insert("hidden_sizes".into(), serde_json::json!([64, 64]));
    BenchConfig {
        envs: Vec::new(),
        algorithms: vec![Algorithm::Safedice, Algorithm::Bc, Algorithm::Dwbc, Algorithm::Ppl],
        seeds: 2,
        iterations: 5000,
        data: DataSize { preferred: 1, non_preferred: 1, labeled: 1 },
        data_seed: 0,
        eval_episodes: 100,
        deterministic_eval: false,
        threads: 2,
        overrides,
        record_every: 1000,
        ablations: false,
        paper_preset_row: true,
        preferred_only_row: true,
        discriminator_share: None,
        fixed_alpha: None,
        runs_log: None,
        resume: false,
    }
}

/// The tasks of `splits`, `count` per split, with their reference statistics.
pub fn tasks(splits: &[Split], count: usize, iterations: u64) -> Vec<(TaskSpec, BenchTask)> {
    splits
        .iter()
        .flat_map(|&split| TaskSpec::split(split, count))
        .map(|spec| {
            let task = spec.task();
            let reference = task_reference_stats(&task, REFERENCE_EPISODES);
            let data = DataSize {
                preferred: spec.preferred_episodes,
                non_preferred: spec.non_preferred_episodes,
                labeled: spec.labeled_episodes,
            };
            let iterations = Some(iterations * spec.iteration_scale());
            (spec, BenchTask { task: Box::new(task), reference, data, iterations })
        })
        .collect()
}

/// One algorithm row on one task, scored against BC.
#[derive(Clone, Debug, Serialize)]
pub struct TaskScore {
    pub task: String,
    pub row: String,
    pub cost: f64,
    pub normalized_return: f64,
    pub cost_ratio: f64,
    pub return_ratio: f64,
    /// None where BC is already within [`MIN_ACHIEVABLE`] of the ceiling.
    pub captured: Option<f64>,
    pub worse_than_bc: bool,
    /// Normalized return below 0.95x BC's (the rule before the preferred-only ceiling's return
    /// bounded it), reported beside `worse_than_bc`.
    pub below_bc_return: bool,
    pub alpha_hat: Option<f64>,
    pub auc_heldout: Option<f64>,
    /// alpha-hat's confidence interval, averaged over seeds (the `bbe` estimator), the true
    /// non-preferred share of D^U's episodes, and the seeds whose weighting fell back to uniform.
    pub alpha_hat_interval: Option<(f64, f64)>,
    pub true_share: f64,
    pub uniform_seeds: usize,
}

/// A row's scores over the tasks of one split.
#[derive(Clone, Debug, Serialize)]
pub struct RowSummary {
    pub split: Split,
    pub row: String,
    /// `all tasks`, or `fair tasks`: those passing the fairness check, where the ceiling is one
    /// a filter of D^U can reach.
    pub scope: &'static str,
    pub tasks: usize,
    /// Tasks with something to capture.
    pub scored: usize,
    pub captured_median: f64,
    pub captured_p10: f64,
    pub worst_task: Option<(String, f64)>,
    pub worse_than_bc: usize,
    pub worse_tasks: Vec<String>,
    /// Tasks below 0.95x BC's own return (the rule before the ceiling bounded it).
    pub below_bc_return: Vec<String>,
    /// The goal on the test split: worse than BC on no task, median ≥ 0.7, 10th percentile ≥ 0.3.
    pub meets_goal: bool,
}

fn row(env: &EnvSummary, algorithm: Algorithm, variant: Variant) -> Option<&AlgorithmSummary> {
    env.rows.iter().find(|r| r.algorithm == algorithm && r.variant == variant && r.seeds > 0)
}

/// Scores every non-BC row of every task.
pub fn score(results: &BenchResults, summary: &Summary, specs: &[TaskSpec]) -> Vec<TaskScore> {
    let mut scores = Vec::new();
    for (env, spec) in summary.envs.iter().zip(specs) {
        let kappa = results
            .data
            .iter()
            .find(|d| d.env == spec.id)
            .map_or(0.0, |d| d.reference.cost_threshold);
        let (Some(bc), Some(ceiling)) = (
            row(env, Algorithm::Bc, Variant::Standard),
            row(env, Algorithm::Bc, Variant::PreferredOnly),
        ) else {
            continue;
        };
        let achievable = bc.average_cost.mean - ceiling.average_cost.mean;
        for r in env.rows.iter().filter(|r| r.algorithm != Algorithm::Bc && r.seeds > 0) {
            let cost = r.average_cost.mean;
            let ret = r.normalized_return.mean;
            let bc_ret = bc.normalized_return.mean;
            let attainable_ret = bc_ret.min(ceiling.normalized_return.mean);
            let below_bc_return = bc_ret > 0.0 && ret < WORSE_RETURN_RATIO * bc_ret;
            let worse = cost > WORSE_COST_RATIO * bc.average_cost.mean + 0.01 * kappa
                || (attainable_ret > 0.0 && ret < WORSE_RETURN_RATIO * attainable_ret);
            scores.push(TaskScore {
                task: spec.id.clone(),
                row: r.label.clone(),
                cost,
                normalized_return: ret,
                cost_ratio: cost / bc.average_cost.mean,
                return_ratio: ret / bc_ret,
                captured: (achievable > MIN_ACHIEVABLE * kappa)
                    .then(|| (bc.average_cost.mean - cost) / achievable),
                worse_than_bc: worse,
                below_bc_return,
                alpha_hat: r.alpha_hat.map(|a| a.mean),
                auc_heldout: r.discriminator_auc_heldout.map(|a| a.mean),
                alpha_hat_interval: alpha_interval(results, &spec.id, &r.label),
                true_share: spec.mixture_share(),
                uniform_seeds: uniform_seeds(results, &spec.id, &r.label),
            });
        }
    }
    scores
}

/// The SafeDICE runs of one task and row.
fn alpha_runs<'a>(
    results: &'a BenchResults,
    task: &'a str,
    label: &'a str,
) -> impl Iterator<Item = &'a crate::bench::runner::AlphaDiagnostics> {
    results
        .runs
        .iter()
        .filter(move |r| r.env == task && r.label() == label)
        .filter_map(|r| r.alpha.as_ref())
}

/// alpha-hat's interval averaged over a row's seeds, where the estimator reports one.
fn alpha_interval(results: &BenchResults, task: &str, label: &str) -> Option<(f64, f64)> {
    let bounds: Vec<(f64, f64)> = alpha_runs(results, task, label)
        .map(|a| (a.alpha_hat_lower, a.alpha_hat_upper))
        .filter(|(l, u)| l.is_finite() && u.is_finite())
        .collect();
    let n = bounds.len() as f64;
    (n > 0.0).then(|| {
        (bounds.iter().map(|b| b.0).sum::<f64>() / n, bounds.iter().map(|b| b.1).sum::<f64>() / n)
    })
}

fn uniform_seeds(results: &BenchResults, task: &str, label: &str) -> usize {
    alpha_runs(results, task, label).filter(|a| a.weighting_uniform == 1.0).count()
}

/// Linear-interpolated quantile of sorted values (numpy's default).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Per split and row: median, 10th percentile and worst captured share, tasks worse than BC.
pub fn summarize_rows(
    scores: &[TaskScore],
    specs: &[TaskSpec],
    scope: &'static str,
) -> Vec<RowSummary> {
    let mut rows: Vec<String> = scores.iter().map(|s| s.row.clone()).collect();
    rows.dedup();
    rows.sort();
    rows.dedup();
    let mut out = Vec::new();
    for split in [Split::Dev, Split::Test] {
        let in_split = |s: &&TaskScore| specs.iter().any(|t| t.id == s.task && t.split == split);
        for row in &rows {
            let mine: Vec<&TaskScore> =
                scores.iter().filter(in_split).filter(|s| &s.row == row).collect();
            if mine.is_empty() {
                continue;
            }
            let mut captured: Vec<(f64, &str)> =
                mine.iter().filter_map(|s| s.captured.map(|c| (c, s.task.as_str()))).collect();
            captured.sort_by(|a, b| a.0.total_cmp(&b.0));
            let values: Vec<f64> = captured.iter().map(|c| c.0).collect();
            let worse: Vec<String> =
                mine.iter().filter(|s| s.worse_than_bc).map(|s| s.task.clone()).collect();
            let (median, p10) = (quantile(&values, 0.5), quantile(&values, 0.1));
            out.push(RowSummary {
                split,
                row: row.clone(),
                scope,
                tasks: mine.len(),
                scored: values.len(),
                captured_median: median,
                captured_p10: p10,
                worst_task: captured.first().map(|(c, t)| (t.to_string(), *c)),
                meets_goal: worse.is_empty() && median >= 0.7 && p10 >= 0.3,
                worse_than_bc: worse.len(),
                worse_tasks: worse,
                below_bc_return: mine
                    .iter()
                    .filter(|s| s.below_bc_return)
                    .map(|s| s.task.clone())
                    .collect(),
            });
        }
    }
    out
}

/// Which tasks a run trains on: the first `count` of each split, of the named families only
/// when `families` names any.
pub struct Selection<'a> {
    pub splits: &'a [Split],
    pub count: usize,
    pub families: Vec<&'a str>,
}

impl Selection<'_> {
    fn keeps(&self, spec: &TaskSpec) -> bool {
        self.families.is_empty() || self.families.contains(&spec.family.name())
    }
}

/// `safedice bench --suite robustness`: runs the splits, writes results.md and results.json.
pub fn run_cli(
    mut config: BenchConfig,
    selection: &Selection,
    out: &Path,
    command: &str,
) -> anyhow::Result<Vec<PathBuf>> {
    let pairs = tasks(selection.splits, selection.count, config.iterations);
    let (specs, bench_tasks): (Vec<TaskSpec>, Vec<BenchTask>) =
        pairs.into_iter().filter(|(spec, _)| selection.keeps(spec)).unzip();
    if specs.is_empty() {
        anyhow::bail!("no task of the suite matches --tasks {} and --families", selection.count);
    }
    config.envs = specs.iter().map(|s| s.id.clone()).collect();
    if !config.algorithms.contains(&Algorithm::Bc) {
        config.algorithms.push(Algorithm::Bc);
    }
    config.preferred_only_row = true;
    let results = runner::run_tasks(&config, &bench_tasks)?;
    let summary = summarize(&results);
    let scores = score(&results, &summary, &specs);
    let fair: Vec<TaskFairness> =
        summary.envs.iter().filter_map(|e| fairness(&results, e)).collect();
    let mut rows = summarize_rows(&scores, &specs, "all tasks");
    let passes = |s: &&TaskScore| fair.iter().any(|f| f.task == s.task && f.passes);
    let fair_scores: Vec<TaskScore> = scores.iter().filter(passes).cloned().collect();
    rows.extend(summarize_rows(&fair_scores, &specs, "fair tasks"));
    std::fs::create_dir_all(out)?;
    let json = out.join("results.json");
    let body = serde_json::json!({
        "tasks": specs, "results": results, "summary": summary, "scores": scores, "rows": rows,
        "fairness": fair,
    });
    std::fs::write(&json, serde_json::to_vec_pretty(&body)?)?;
    let md = out.join("results.md");
    std::fs::write(&md, markdown(&results, &summary, &specs, &scores, &rows, &fair, command))?;
    print!("{}", console(&rows));
    Ok(vec![json, md])
}

fn console(rows: &[RowSummary]) -> String {
    let mut s = String::new();
    for r in rows {
        let _ = writeln!(
            s,
            "{:<5} {:<10} {:<28} captured median {:>6.2}  p10 {:>6.2}  worst {:>6.2} ({})  worse than BC {}/{}",
            r.split.as_str(),
            r.scope,
            r.row,
            r.captured_median,
            r.captured_p10,
            r.worst_task.as_ref().map_or(f64::NAN, |w| w.1),
            r.worst_task.as_ref().map_or("-", |w| w.0.as_str()),
            r.worse_than_bc,
            r.tasks
        );
    }
    s
}

fn fmt(x: Option<f64>, decimals: usize) -> String {
    x.filter(|v| v.is_finite()).map_or("—".to_string(), |v| format!("{v:.decimals$}"))
}

fn markdown(
    results: &BenchResults,
    summary: &Summary,
    specs: &[TaskSpec],
    scores: &[TaskScore],
    rows: &[RowSummary],
    fair: &[TaskFairness],
    command: &str,
) -> String {
    let c = &results.config;
    let mut md = String::new();
    let _ = writeln!(md, "# Robustness suite\n");
    let _ = writeln!(md, "- Command: `{command}`");
    let _ = writeln!(
        md,
        "- Date: {}; commit {} (binary built from {}); machine: {}",
        results.started.format("%Y-%m-%d %H:%M UTC"),
        results.git_commit,
        results.build_commit,
        results.machine
    );
    let _ = writeln!(
        md,
        "- Training: {} base policy iterations (× 1 grids, × 2 pace, × 4 nav), {}, overrides {}; {} evaluation episodes per policy; {} thread(s)",
        c.iterations,
        report::seeds_text(c.seeds),
        serde_json::Value::Object(c.overrides.clone()),
        c.eval_episodes,
        c.threads
    );
    if let Some(alpha) = c.fixed_alpha {
        let _ = writeln!(
            md,
            "- SafeDICE's α fixed at {alpha} in place of alpha-hat (a study, not a default)"
        );
    }
    let _ = writeln!(md, "- Wall time: {}\n", report::wall_time(results));
    let _ = writeln!(
        md,
        "Captured share = (cost_BC − cost) / (cost_BC − cost_BC-preferred-only), over tasks where BC-preferred-only improves on BC by more than {MIN_ACHIEVABLE} κ. Worse than BC: cost > {WORSE_COST_RATIO}x BC's + 0.01 κ, or normalized return < {WORSE_RETURN_RATIO}x the lower of BC's and BC-preferred-only's (a safe policy is not asked for the return only the non-preferred demonstrator earns; the per-task table also marks returns below {WORSE_RETURN_RATIO}x BC's own).\n"
    );
    let _ = writeln!(md, "## Summary\n");
    let _ = writeln!(md, "Rows over all tasks, then over the tasks that pass the fairness check (below): where BC on the preferred episodes alone does not reach the preferred demonstrator, the ceiling measures imitation capacity more than safety.\n");
    let _ = writeln!(md, "| split | tasks | row | tasks (scored) | captured median | 10th pct | worst task | worse than BC | goal |");
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let worst = r.worst_task.as_ref().map_or("—".into(), |(t, v)| format!("{v:.2} ({t})"));
        let worse = if r.worse_tasks.is_empty() {
            "0".to_string()
        } else {
            format!("{} ({})", r.worse_than_bc, r.worse_tasks.join(", "))
        };
        let worse = match r.below_bc_return.len() {
            0 => worse,
            n => format!("{worse}; {n} below 0.95x BC's return ({})", r.below_bc_return.join(", ")),
        };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} ({}) | {:.2} | {:.2} | {} | {} | {} |",
            r.split.as_str(),
            r.scope,
            r.row,
            r.tasks,
            r.scored,
            r.captured_median,
            r.captured_p10,
            worst,
            worse,
            if r.meets_goal { "met" } else { "missed" }
        );
    }
    let failing: Vec<&str> = fair.iter().filter(|f| !f.passes).map(|f| f.task.as_str()).collect();
    let _ = writeln!(
        md,
        "\nFairness check (BC on the preferred episodes alone against the preferred demonstrator: return within 10 points, cost within the larger of 10% and {FAIR_COST_KAPPA} κ): passes on {} of {} tasks{}.",
        fair.len() - failing.len(),
        fair.len(),
        if failing.is_empty() { String::new() } else { format!("; fails on {}", failing.join(", ")) }
    );
    let _ = writeln!(md, "\n## Tasks\n");
    let _ = writeln!(md, "| task | parameters | D^U pref + non-pref (share) | D^N | obs noise | demonstrators: return / cost (pref, non-pref) | fairness (BC-pref: return, cost) | BC cost | BC-pref cost |");
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|");
    for (spec, env) in specs.iter().zip(&summary.envs) {
        let data = results.data.iter().find(|d| d.env == spec.id);
        let demo = data.map_or("—".into(), |d| {
            let r = &d.reference;
            format!(
                "{:.2} / {:.2}, {:.2} / {:.2}",
                r.preferred_return, r.preferred_cost, r.non_preferred_return, r.non_preferred_cost
            )
        });
        let fair = fair.iter().find(|f| f.task == spec.id).map_or("—".into(), |f| {
            format!(
                "{:.1}, {:.2}: {}",
                f.normalized_return,
                f.average_cost,
                if f.passes { "passes" } else { "FAILS" }
            )
        });
        let cost = |a, v| row(env, a, v).map(|r| r.average_cost.mean);
        let _ = writeln!(
            md,
            "| {} | {} | {} + {} ({:.2}) | {} | {:.3} | {} | {} | {} | {} |",
            spec.id,
            spec.describe(),
            spec.preferred_episodes,
            spec.non_preferred_episodes,
            spec.mixture_share(),
            spec.labeled_episodes,
            spec.obs_noise,
            demo,
            fair,
            fmt(cost(Algorithm::Bc, Variant::Standard), 2),
            fmt(cost(Algorithm::Bc, Variant::PreferredOnly), 2),
        );
    }
    let _ = writeln!(md, "\n## Scores per task\n");
    let _ = writeln!(md, "| task | row | cost | normalized return | cost / BC | return / BC | captured | worse than BC (return < 0.95x BC's) | alpha-hat [interval] (true share) | AUC held-out | uniform seeds |");
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|");
    for s in scores {
        let alpha = match (s.alpha_hat, s.alpha_hat_interval) {
            (Some(a), Some((l, u))) => format!("{a:.3} [{l:.2}, {u:.2}] ({:.2})", s.true_share),
            (Some(a), None) => format!("{a:.3} ({:.2})", s.true_share),
            _ => "–".to_string(),
        };
        let uniform =
            if s.alpha_hat.is_some() { s.uniform_seeds.to_string() } else { "–".into() };
        let _ = writeln!(
            md,
            "| {} | {} | {:.2} | {:.1} | {} | {} | {} | {} | {} | {} | {} |",
            s.task,
            s.row,
            s.cost,
            s.normalized_return,
            fmt(Some(s.cost_ratio), 2),
            fmt(Some(s.return_ratio), 2),
            fmt(s.captured, 2),
            match (s.worse_than_bc, s.below_bc_return) {
                (true, _) => "yes",
                (false, true) => "no (yes)",
                (false, false) => "no",
            },
            alpha,
            fmt(s.auc_heldout, 3),
            uniform
        );
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_like_numpy() {
        let v = [0.0, 1.0, 2.0, 3.0, 4.0];
        assert_eq!(quantile(&v, 0.5), 2.0);
        assert!((quantile(&v, 0.1) - 0.4).abs() < 1e-12);
        assert_eq!(quantile(&[7.0], 0.1), 7.0);
        assert!(quantile(&[], 0.5).is_nan());
    }

    #[test]
    fn a_family_selection_keeps_that_family_only() {
        let splits = [Split::Dev];
        let pace = Selection { splits: &splits, count: 8, families: vec!["pace"] };
        let kept: Vec<String> = TaskSpec::split(Split::Dev, 8)
            .into_iter()
            .filter(|t| pace.keeps(t))
            .map(|t| t.id)
            .collect();
        assert_eq!(kept, ["dev-03-pace", "dev-07-pace"]);
        let every = Selection { families: vec![], ..pace };
        assert!(TaskSpec::split(Split::Dev, 8).iter().all(|t| every.keeps(t)));
    }
}
