//! `safedice bench --suite tabular`: the paper's tabular check (Appendix G, Figures 14-15) on
//! six-rooms. Every algorithm trains on the same one-hot data with the same code as everywhere
//! else; each learned policy is then solved exactly ([`crate::envs::six_rooms::exact_outcome`]:
//! the state distribution propagated through the slip dynamics, no sampling), giving the
//! expected visits of every cell (the state marginals the paper shades), the expected cost and
//! the probability of reaching the goal. DWBC and DExperts are shown at several values of their
//! hyperparameter, as the paper does, to show how much they depend on it.

use std::fmt::Write as _;
use std::sync::Arc;

use serde::Serialize;

use crate::algo::{self, Algorithm, Policy, TrainingData};
use crate::envs::six_rooms::{self, ExactOutcome};
use crate::envs::{self, DatagenSpec};

/// One trained policy's exact outcome.
#[derive(Clone, Debug, Serialize)]
pub struct TabularRow {
    pub label: String,
    pub algorithm: Algorithm,
    pub config: serde_json::Value,
    pub expected_cost: f64,
    pub goal_probability: f64,
    /// Share of the expected visits that fall on cost cells.
    pub cost_share_of_visits: f64,
    /// SafeDICE: alpha-hat and its interval (the `bbe` estimator), against [`true_share`].
    pub alpha_hat: Option<f64>,
    pub alpha_hat_interval: Option<(f64, f64)>,
    pub visits: Vec<f64>,
}

/// A trained policy solved exactly, with the alpha-hat its run used.
pub struct Solved {
    pub outcome: ExactOutcome,
    pub alpha_hat: Option<f64>,
    pub alpha_hat_interval: Option<(f64, f64)>,
}

/// The non-preferred share of the transitions of [`data`]'s D^U: the α* alpha-hat estimates.
pub fn true_share(seed: u64) -> anyhow::Result<f64> {
    let g = envs::generate(&spec(seed))?;
    let ids = &g.manifest.unlabeled_non_preferred_episode_ids;
    let rows = g.unlabeled.episode_ids();
    Ok(rows.iter().filter(|e| ids.contains(e)).count() as f64 / rows.len() as f64)
}

/// The rows: BC, SafeDICE (service defaults and the paper preset), PPL, DWBC at η ∈ {0.2, 0.5, 0.8}, DExperts at
/// α ∈ {0.2, 0.5, 0.8}.
pub fn rows() -> Vec<(String, Algorithm, serde_json::Value)> {
    let mut rows = vec![
        ("BC".to_string(), Algorithm::Bc, serde_json::json!({})),
        ("SafeDICE".to_string(), Algorithm::Safedice, serde_json::json!({})),
        (
            "SafeDICE (paper preset)".to_string(),
            Algorithm::Safedice,
            serde_json::json!({ "preset": "paper" }),
        ),
        ("PPL".to_string(), Algorithm::Ppl, serde_json::json!({})),
    ];
    for x in [0.2, 0.5, 0.8] {
        rows.push((format!("DWBC (η = {x})"), Algorithm::Dwbc, serde_json::json!({ "eta": x })));
    }
    for x in [0.2, 0.5, 0.8] {
        rows.push((
            format!("DExperts (α = {x})"),
            Algorithm::Dexperts,
            serde_json::json!({ "alpha": x }),
        ));
    }
    rows
}

/// The six-rooms data of the check: 100 preferred + 100 non-preferred episodes in D^U, 20
/// labeled non-preferred ones.
pub fn data(seed: u64) -> anyhow::Result<TrainingData> {
    let g = envs::generate(&spec(seed))?;
    Ok(TrainingData {
        unlabeled: Arc::new(g.unlabeled),
        non_preferred: g.labeled_non_preferred.map(Arc::new),
    })
}

fn spec(seed: u64) -> DatagenSpec {
    DatagenSpec {
        env: six_rooms::NAME.into(),
        preferred: 100,
        non_preferred: 100,
        labeled: 20,
        seed,
    }
}

/// Trains `algorithm` with `extra` config on `data` and solves its policy exactly.
pub fn solve(
    algorithm: Algorithm,
    extra: &serde_json::Value,
    data: &TrainingData,
    iterations: u64,
    seed: u64,
) -> anyhow::Result<Solved> {
    let mut config = serde_json::json!({
        "seed": seed, "iterations": iterations, "batch_size": 256, "hidden_sizes": [64, 64],
    });
    if let (Some(c), Some(e)) = (config.as_object_mut(), extra.as_object()) {
        c.extend(e.clone());
    }
    let resolved =
        algo::resolve_config(algorithm, &config).map_err(|e| anyhow::anyhow!(e.message))?;
    let mut trainer = algo::build_trainer(&resolved, data, None)?;
    let (mut lower, mut upper) = (None, None);
    while !trainer.is_finished() {
        // Steps record until alpha-hat exists: the one that ends the discriminator phase carries
        // its interval (recording draws no random numbers, so the run is the same).
        let record = trainer.alpha_hat().is_none();
        for (name, value) in trainer.step(record)? {
            match name {
                "alpha_hat_lower" => lower = Some(value),
                "alpha_hat_upper" => upper = Some(value),
                _ => {}
            }
        }
    }
    let artifact = trainer.export_policy()?;
    let policy = Policy::load(&artifact.spec, &artifact.weights)?;
    let n = data.unlabeled.obs_dim();
    let mut one_hot = vec![0.0f32; n * n];
    for i in 0..n {
        one_hot[i * n + i] = 1.0;
    }
    let probs = policy.action_probabilities(&one_hot).expect("six-rooms is discrete");
    let width = probs.len() / n;
    let outcome = six_rooms::exact_outcome(|i| {
        let mut p = [0.0; 4];
        for (a, slot) in p.iter_mut().enumerate().take(width) {
            *slot = f64::from(probs[i * width + a]);
        }
        p
    });
    let alpha_hat_interval = lower.zip(upper);
    Ok(Solved { outcome, alpha_hat: trainer.alpha_hat(), alpha_hat_interval })
}

/// Every row of [`rows`] on the data of `seed`.
pub fn run(iterations: u64, seed: u64) -> anyhow::Result<Vec<TabularRow>> {
    let data = data(seed)?;
    let costly = cost_cells();
    rows()
        .into_iter()
        .map(|(label, algorithm, extra)| {
            let solved = solve(algorithm, &extra, &data, iterations, seed)?;
            let out = solved.outcome;
            let total: f64 = out.visits.iter().sum();
            let on_cost: f64 =
                out.visits.iter().zip(&costly).filter(|(_, &c)| c).map(|(v, _)| v).sum();
            Ok(TabularRow {
                label,
                algorithm,
                config: extra,
                expected_cost: out.expected_cost,
                goal_probability: out.goal_probability,
                cost_share_of_visits: on_cost / total.max(1e-12),
                alpha_hat: solved.alpha_hat,
                alpha_hat_interval: solved.alpha_hat_interval,
                visits: out.visits,
            })
        })
        .collect()
}

/// Whether each free cell (observation index order) costs.
fn cost_cells() -> Vec<bool> {
    let probe = six_rooms::exact_outcome(|_| [0.25; 4]).visits.len();
    (0..probe).map(six_rooms::is_cost_index).collect()
}

/// The report: a table and one shaded grid per row.
pub fn markdown(
    rows: &[TabularRow],
    command: &str,
    iterations: u64,
    seed: u64,
    true_share: f64,
) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Tabular check (paper Appendix G): where each algorithm's state distribution goes on six-rooms\n");
    let _ = writeln!(md, "- Command: `{command}`");
    let _ = writeln!(md, "- Data (seed {seed}): D^U = 100 preferred (top rooms) + 100 non-preferred (bottom rooms, cost 1 per step) episodes, D^N = 20 labeled non-preferred; {iterations} iterations, 64-64 networks, batch 256, service defaults otherwise");
    let _ = writeln!(md, "- Each policy is solved exactly: its action probabilities at every cell propagated through the 10% slip dynamics for the 100-step horizon\n");
    let _ = writeln!(md, "- True non-preferred share of D^U's transitions (what alpha-hat estimates): {true_share:.4}\n");
    let _ = writeln!(md, "| policy | expected cost | P(goal) | share of visits on cost cells | alpha-hat [90% interval] |");
    let _ = writeln!(md, "|---|---|---|---|---|");
    for r in rows {
        let alpha = match (r.alpha_hat, r.alpha_hat_interval) {
            (Some(a), Some((l, u))) => format!("{a:.3} [{l:.3}, {u:.3}]"),
            (Some(a), None) => format!("{a:.4} (the paper's minimum)"),
            _ => "–".to_string(),
        };
        let _ = writeln!(
            md,
            "| {} | {:.2} | {:.3} | {:.3} | {} |",
            r.label, r.expected_cost, r.goal_probability, r.cost_share_of_visits, alpha
        );
    }
    let _ = writeln!(md, "\nExpected visits per cell, shaded ` .:-=+*#%@` from none to the most visited cell; the start is top left, the goal bottom right, the bottom-left and bottom-middle rooms cost.\n");
    for r in rows {
        let _ = writeln!(md, "{}\n\n```text\n{}```\n", r.label, six_rooms::shade(&r.visits));
    }
    md
}

/// `safedice bench --suite tabular`.
pub fn run_cli(
    iterations: u64,
    seed: u64,
    out: &std::path::Path,
    command: &str,
) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let rows = run(iterations, seed)?;
    std::fs::create_dir_all(out)?;
    let md = out.join("tabular.md");
    std::fs::write(&md, markdown(&rows, command, iterations, seed, true_share(seed)?))?;
    let json = out.join("tabular.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&rows)?)?;
    for r in &rows {
        println!(
            "{:<22} expected cost {:>6.2}  P(goal) {:.3}",
            r.label, r.expected_cost, r.goal_probability
        );
    }
    Ok(vec![md, json])
}
