//! The written outputs of a benchmark run: results.md (tables like the paper's Tables 5-9),
//! results.json (every run), the SVG plots and the console table. The numbers come from
//! [`super::summary`].

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::runner::{BenchResults, RunResult};
use super::summary::{EnvSummary, Summary};
use super::{plot, BASELINE_KNOBS};

/// The SafeDICE-vs-BC table printed at the end of `safedice bench`.
pub fn console_table(summary: &Summary) -> String {
    let mut out = String::new();
    for env in &summary.envs {
        let _ = writeln!(out, "\n{}", env.env);
        let _ = writeln!(
            out,
            "  {:<24} {:>16} {:>16} {:>14} {:>16}",
            "algorithm", "norm. return", "avg cost", "violation", "alpha-hat"
        );
        for r in &env.rows {
            let alpha = r.alpha_hat.map_or("-".to_string(), |a| a.show(4));
            let _ = writeln!(
                out,
                "  {:<24} {:>16} {:>16} {:>14} {:>16}",
                if r.variant.is_standard() {
                    r.algorithm.as_str().to_string()
                } else {
                    r.label.clone()
                },
                r.normalized_return.show(1),
                r.average_cost.show(2),
                r.cost_violation_ratio.show(2),
                alpha
            );
        }
        if let Some(c) = &env.safedice_vs_bc {
            let _ = writeln!(
                out,
                "  SafeDICE/BC cost ratio {:.2}, return difference {:+.1} points, goal {}",
                c.cost_ratio,
                c.return_difference,
                if c.meets_goal { "met" } else { "missed" }
            );
        }
        if let Some(f) = &env.fairness {
            let verdict = if f.passes { "passes" } else { "FAILS" };
            let _ = writeln!(out, "  fairness check (BC on preferred episodes) {verdict}");
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
    let _ = writeln!(
        md,
        "- Git commit: {} (checked out at the start); binary built from {}",
        results.git_commit, results.build_commit
    );
    let _ = writeln!(md, "- Machine: {}", results.machine);
    let _ = writeln!(
        md,
        "- Training: service preset, {} policy iterations per run (SafeDICE's discriminator \
         trained for as many steps first, PPL's reward model for 10%), {}, {} thread(s) in parallel; {}{}",
        c.iterations,
        seeds_text(c.seeds),
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
        "- Wall time: {}; full mode (1M iterations, 5 seeds, 500 episodes, {} threads) \
         estimated at {:.0} h from the speeds measured here (same networks, batch and load)",
        wall_time(results),
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
    write_ablations(&mut md, results, summary);
    write_speeds(&mut md, summary);
    md
}

fn write_env(md: &mut String, env: &EnvSummary, data: &super::runner::EnvData) {
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
            row.label,
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
             {} Goal (cost ≤ {}x BC's at ≥ {}x its normalized return{}): {}.",
            cmp.cost_ratio,
            cmp.return_difference,
            if cmp.as_expected {
                "As expected: clearly lower cost at similar return."
            } else {
                "NOT as expected (see the SafeDICE diagnostics below)."
            },
            super::summary::GOAL_COST_RATIO,
            super::summary::GOAL_RETURN_RATIO,
            cmp.return_ratio.map_or(String::new(), |r| format!("; return ratio {r:.3}")),
            if cmp.meets_goal { "met" } else { "missed" }
        );
    }
    if let Some(f) = &env.fairness {
        let _ = writeln!(
            md,
            "\nFairness check (BC on D^U's preferred episodes alone against the preferred \
             demonstrator, within 10%): normalized return {:.1} (100 ± 10), average cost {:.2} \
             ({:.2} ± {:.2}): {}.",
            f.normalized_return,
            f.average_cost,
            f.demonstrator_cost,
            f.cost_tolerance,
            if f.passes {
                "passes, the environment tests safety at this budget"
            } else {
                "FAILS, at this budget the environment tests imitation capacity"
            }
        );
    }
    let _ = writeln!(md, "\n![{} cost vs return]({}.svg)\n", env.env, env.env);
}

/// `0.512 [0.43, 0.60]`, or the value alone where the run reported no interval.
fn interval(value: f64, lower: f64, upper: f64) -> String {
    if lower.is_finite() && upper.is_finite() {
        format!("{value:.3} [{lower:.2}, {upper:.2}]")
    } else {
        format!("{value:.4}")
    }
}

fn finite(value: f64, decimals: usize) -> String {
    if value.is_finite() {
        format!("{value:.decimals$}")
    } else {
        "–".to_string()
    }
}

fn write_diagnostics(md: &mut String, results: &BenchResults) {
    let runs: Vec<&RunResult> =
        results.runs.iter().filter(|r| r.alpha.is_some() && r.variant.is_standard()).collect();
    if runs.is_empty() {
        return;
    }
    let _ = writeln!(md, "## SafeDICE diagnostics (per run)\n");
    let _ = writeln!(
        md,
        "alpha-hat: with the service defaults, Best Bin Estimation of Eq. 15's mixture proportion \
         on held-out episodes, with its 90% interval and the held-out AUC of D^N against D^U \
         (docs/algorithm.md); `uniform` = 1 when the run fell back to BC's weights. `min ratio` is \
         the paper's statistic, min over D^U of (1/c − 1). `argmin episode` is the D^U \
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
        "| Env | Seed | alpha-hat [interval] | D^U non-preferred share | held-out AUC | uniform | min ratio | q01 ratio | argmin episode | non-preferred? | ESS mean | ESS last | undefined Eq. 10 rows |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in runs {
        let a = r.alpha.as_ref().expect("filtered");
        let share = results.data.iter().find(|d| d.env == r.env).map_or(f64::NAN, |d| {
            let n = d.unlabeled_non_preferred.transitions as f64;
            n / (n + d.unlabeled_preferred.transitions as f64)
        });
        let _ = writeln!(
            md,
            "| {} | {} | {} | {:.3} | {} | {} | {:.4} | {:.4} | {} | {} | {:.3} | {:.3} | {} |",
            r.env,
            r.seed,
            interval(a.alpha_hat, a.alpha_hat_lower, a.alpha_hat_upper),
            share,
            finite(a.heldout_auc, 3),
            finite(a.weighting_uniform, 0),
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

/// The ablation rows' ground truth and the SafeDICE rows' discriminator and weight diagnostics
/// (`--ablations` only).
fn write_ablations(md: &mut String, results: &BenchResults, summary: &Summary) {
    if !results.config.ablations {
        return;
    }
    let _ = writeln!(md, "## Ablations (ground truth of the data generator)\n");
    let _ = writeln!(
        md,
        "Rows that use what only the data generator knows, to tell which stage limits an \
         environment. **BC (preferred only)**: BC on the preferred episodes of D^U alone, the \
         ceiling of any filter of D^U. **SafeDICE (true α)**: alpha-hat (Eq. 15) replaced by the \
         true non-preferred share of D^U's transitions (the α* Eq. 15 estimates). **SafeDICE \
         (oracle labels)**: the discriminator's outputs on D^U replaced by the optimal \
         discriminator of the true labels (σ(c) = 1/(1 + α*) on non-preferred rows, 1e-6 on \
         preferred ones), so Eq. 15 returns α* and Eq. 10 is as large a penalty as the margin \
         allows. AUC: ROC AUC of the trained discriminator's logit as a score of \
         \"non-preferred\", on a held-out labeled set (fresh preferred and non-preferred \
         episodes, another data seed) and on D^U's true flags; all SafeDICE rows of a seed \
         train the same discriminator. Weight share: the share of Eq. 37's weights \
         (exp(A − 1) with the final ν, self-normalised within each batch as the policy step does, \
         all of D^U in batches of the run's size) on non-preferred transitions (α* = no \
         filtering, 0 = a perfect filter). Reading: oracle labels far better than \
         SafeDICE point at the discriminator or alpha-hat (true α tells which); oracle labels \
         no better than SafeDICE point at the weighting stage (ν, Eq. 36-37) or the policy \
         fit; BC (preferred only) bounds them all.\n"
    );
    let _ = writeln!(
        md,
        "| Env | true α (transitions) | non-preferred episodes | held-out set (preferred / non-preferred transitions, seed) |"
    );
    let _ = writeln!(md, "|---|---|---|---|");
    for d in &results.data {
        if let Some(a) = &d.ablation {
            let _ = writeln!(
                md,
                "| {} | {:.4} | {:.3} | {} / {}, {} |",
                d.env,
                a.true_alpha,
                a.non_preferred_episode_share,
                a.heldout_preferred_transitions,
                a.heldout_non_preferred_transitions,
                a.heldout_seed
            );
        }
    }
    let _ = writeln!(
        md,
        "\n| Env | Row | α used | AUC held-out | AUC D^U | weight share on non-preferred | the same from Eq. 10's reward alone |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|");
    let show =
        |s: Option<super::summary::Stat>, d: usize| s.map_or("–".to_string(), |s| s.show(d));
    for env in &summary.envs {
        for row in env.rows.iter().filter(|r| r.discriminator_auc_heldout.is_some()) {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {} | {} | {} |",
                env.env,
                row.label,
                show(row.alpha_hat, 4),
                show(row.discriminator_auc_heldout, 3),
                show(row.discriminator_auc_unlabeled, 3),
                show(row.non_preferred_weight_share, 3),
                show(row.reward_only_weight_share, 3)
            );
        }
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
                env.env, r.label, r.steps_per_second, r.train_seconds, r.eval_seconds
            );
        }
    }
    let _ = writeln!(md);
}

/// "seed 0" or "seeds 0-4": the seeds a run used.
pub(super) fn seeds_text(seeds: u64) -> String {
    match seeds {
        1 => "seed 0".to_owned(),
        n => format!("seeds 0-{}", n.saturating_sub(1)),
    }
}

/// The run's wall time, and how many of its trainings an earlier invocation did (`--resume`).
pub fn wall_time(results: &BenchResults) -> String {
    let minutes = format!("{:.1} min", results.wall_seconds / 60.0);
    match results.resumed_runs {
        0 => minutes,
        kept => format!(
            "{minutes} (resumed: {kept} of the {} trainings kept from an earlier invocation's \
             runs.jsonl, whose time is not counted)",
            results.runs.len()
        ),
    }
}
