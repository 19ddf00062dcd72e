//! `safedice bench --ablations`: rows that tell which stage of SafeDICE limits an environment,
//! built from the ground truth only the data generator knows (which episode of D^U came from
//! which demonstrator). Nothing here reaches the service: the truth flags live in the
//! benchmark's prepared data, and the trainer takes them through
//! [`crate::algo::safedice::SafediceOverrides`], which a user's config cannot set.
//!
//! Per environment and seed:
//! - **BC (preferred only)**: BC on the preferred episodes of D^U alone, the ceiling any filter
//!   of D^U can reach;
//! - **SafeDICE (true α)**: alpha-hat (Eq. 15) replaced by the true non-preferred share of D^U's
//!   transitions (the α* of `d^U = (1 − α*) d^P + α* d^N`, Appendix A Eq. 18);
//! - **SafeDICE (oracle labels)**: the discriminator's outputs on D^U replaced by the optimal
//!   discriminator for the true labels ([`crate::algo::safedice::oracle_logits`]), which also
//!   makes Eq. 15 return the true share;
//! - for every SafeDICE run (the plain one included): the trained discriminator's ROC AUC
//!   ([`roc_auc`]) on a held-out labeled set and on D^U's true flags, and the share of Eq. 37's
//!   batch-normalised weights on non-preferred transitions of D^U at the end of training.
//!
//! All SafeDICE variants of one seed train the same discriminator (same seed, same draws), so
//! their AUCs agree; the rows differ only in what Eq. 10 and Eq. 15 read.

use serde::{Deserialize, Serialize};

use crate::algo::Algorithm;
use crate::data::{Actions, Dataset, DatasetParts};

/// What a benchmark row trains: an algorithm as the service runs it, or an ablation.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Variant {
    /// The algorithm on the benchmark's data, as the service trains it.
    #[default]
    Standard,
    /// BC on the preferred episodes of D^U only.
    PreferredOnly,
    /// SafeDICE with α set to the true non-preferred share of D^U's transitions.
    TrueAlpha,
    /// SafeDICE with the optimal discriminator of the true labels.
    OracleLabels,
    /// The algorithm under the `paper` preset instead of the service defaults (the robustness
    /// suite reports both).
    PaperPreset,
}

impl Variant {
    /// The ablation rows, in table order, with the algorithm each one trains.
    pub const ABLATIONS: [(Algorithm, Variant); 3] = [
        (Algorithm::Bc, Variant::PreferredOnly),
        (Algorithm::Safedice, Variant::TrueAlpha),
        (Algorithm::Safedice, Variant::OracleLabels),
    ];

    /// The row's name in results.md and on the console.
    pub fn label(self, algorithm: Algorithm) -> String {
        match self {
            Variant::Standard => algorithm.display_name().to_string(),
            Variant::PreferredOnly => format!("{} (preferred only)", algorithm.display_name()),
            Variant::TrueAlpha => format!("{} (true α)", algorithm.display_name()),
            Variant::OracleLabels => format!("{} (oracle labels)", algorithm.display_name()),
            Variant::PaperPreset => format!("{} (paper preset)", algorithm.display_name()),
        }
    }

    pub fn is_standard(&self) -> bool {
        *self == Variant::Standard
    }
}

/// The held-out labeled set of the AUC: `max(labeled, 10)` preferred and as many non-preferred
/// episodes, generated with the seed `derive_seed(data seed, HELDOUT_STREAM, 0)`, so its
/// episodes are fresh (neither D^U's nor D^N's).
pub const HELDOUT_STREAM: u64 = 201;
pub const HELDOUT_MIN_EPISODES: usize = 10;
/// Seed of the row order [`batch_weight_share`] cuts into batches.
pub const WEIGHT_SHARE_SEED: u64 = 0;

/// The discriminator's ranking quality and where the SafeDICE weights went, for one run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SafediceAblation {
    /// ROC AUC of the trained discriminator's logit as a score of "non-preferred" on the
    /// held-out labeled set (fresh preferred vs non-preferred transitions).
    #[serde(deserialize_with = "super::resume::nan_if_null")]
    pub auc_heldout: f64,
    /// The same on D^U's transitions against their true flags (in-sample: the discriminator
    /// was trained on D^U as its negative class).
    #[serde(deserialize_with = "super::resume::nan_if_null")]
    pub auc_unlabeled: f64,
    /// Share of Eq. 37's batch-normalised weights as the policy step reads them (current ν, all
    /// of D^U in batches of the run's size, with its `policy_uniform_share`,
    /// [`batch_weight_share`]) on the non-preferred transitions at the end of
    /// training: the true share α means no filtering, 0 a perfect filter.
    #[serde(deserialize_with = "super::resume::nan_if_null")]
    pub non_preferred_weight_share: f64,
    /// The same share from Eq. 10's reward alone, `exp(r)` per batch with ν's terms
    /// `γ' ν(s') − ν(s)` left out: what the weights would be before the ν step moved them. Far
    /// below `non_preferred_weight_share` means ν gives the non-preferred rows back their weight.
    #[serde(deserialize_with = "super::resume::nan_if_null")]
    pub reward_only_weight_share: f64,
}

/// Exact ROC AUC of `scores` for the classes `positive`: the Mann-Whitney U statistic over all
/// (positive, negative) pairs, a pair counting 1 when the positive scores higher and 1/2 on a
/// tie, divided by the number of pairs. Sorting once makes it O(n log n): walking the groups of
/// equal scores upwards, each positive in a group beats every negative below the group and ties
/// with the group's negatives. None when a class is empty. NaN scores sort above every number
/// (`f32::total_cmp`); callers pass finite scores.
pub fn roc_auc(scores: &[f32], positive: &[bool]) -> Option<f64> {
    assert_eq!(scores.len(), positive.len(), "one class flag per score");
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    // Twice U, in integers: 2 · (wins + ties/2).
    let (mut twice_u, mut negatives_below) = (0u128, 0u128);
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        let (mut pos, mut neg) = (0u128, 0u128);
        while j < order.len() && scores[order[j]].total_cmp(&scores[order[i]]).is_eq() {
            if positive[order[j]] {
                pos += 1;
            } else {
                neg += 1;
            }
            j += 1;
        }
        twice_u += pos * (2 * negatives_below + neg);
        negatives_below += neg;
        i = j;
    }
    let positives = positive.iter().filter(|&&p| p).count() as u128;
    let pairs = positives * negatives_below;
    (pairs > 0).then(|| twice_u as f64 / (2 * pairs) as f64)
}

/// Per-row flags from per-episode ones: row `i` is flagged when its episode id is in `ids`.
pub fn row_flags(data: &Dataset, ids: &[u32]) -> Vec<bool> {
    let ids: std::collections::HashSet<u32> = ids.iter().copied().collect();
    data.episode_ids().iter().map(|id| ids.contains(id)).collect()
}

/// The rows of `data` where `keep` holds, as a dataset (whole episodes when `keep` is constant
/// over each episode, as [`row_flags`] makes it); None when nothing is kept.
pub fn select_rows(data: &Dataset, keep: &[bool]) -> Option<Dataset> {
    assert_eq!(keep.len(), data.len());
    let rows: Vec<usize> = (0..data.len()).filter(|&i| keep[i]).collect();
    if rows.is_empty() {
        return None;
    }
    let dim = data.obs_dim();
    let gather = |values: &[f32], width: usize| -> Vec<f32> {
        rows.iter().flat_map(|&i| &values[i * width..(i + 1) * width]).copied().collect()
    };
    let actions = match data.actions() {
        Actions::Discrete(a) => Actions::Discrete(rows.iter().map(|&i| a[i]).collect()),
        Actions::Continuous(a) => Actions::Continuous(gather(a, a.len() / data.len())),
    };
    let parts = DatasetParts {
        obs_dim: dim,
        action_space: data.action_space().clone(),
        observations: gather(data.observations(), dim),
        actions,
        next_observations: gather(data.next_observations(), dim),
        terminals: rows.iter().map(|&i| data.terminals()[i]).collect(),
        episode_ids: rows.iter().map(|&i| data.episode_ids()[i]).collect(),
        rewards: data.rewards().map(|r| gather(r, 1)),
        costs: data.costs().map(|c| gather(c, 1)),
    };
    Some(Dataset::new(parts).expect("whole episodes of a valid dataset"))
}

/// Share of the total `weights` on the flagged rows.
pub fn weight_share(weights: &[f64], flagged: &[bool]) -> f64 {
    let total: f64 = weights.iter().sum();
    let on: f64 = weights.iter().zip(flagged).filter(|(_, &f)| f).map(|(w, _)| w).sum();
    on / total
}

/// The share of Eq. 37's weights on the flagged rows as the policy step sees them: the rows in
/// a fixed random order (`seed`), cut into batches of `batch`, each batch's weights
/// `exp(A)` self-normalised within the batch (stably, from the log-weights `log_weights`), the
/// batches' shares averaged by size. A share over the whole dataset at once can be ruled by a
/// few rows whose `A` lies hundreds of nats above the rest (ν far outside the states the
/// minibatches usually hold) while no minibatch gives them that role. `uniform_share` mixes
/// the batch's weights as the policy step does (`policy_uniform_share`: `(1 − m) w + m`).
pub fn batch_weight_share(
    log_weights: &[f64],
    flagged: &[bool],
    batch: usize,
    seed: u64,
    uniform_share: f64,
) -> f64 {
    use rand::seq::SliceRandom;
    use rand::SeedableRng;
    assert_eq!(log_weights.len(), flagged.len(), "one flag per row");
    let mut order: Vec<usize> = (0..log_weights.len()).collect();
    order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    let mut total = 0.0;
    for rows in order.chunks(batch.max(1)) {
        let max = rows.iter().map(|&i| log_weights[i]).fold(f64::NEG_INFINITY, f64::max);
        let exp: Vec<f64> = rows.iter().map(|&i| (log_weights[i] - max).exp()).collect();
        let mean = exp.iter().sum::<f64>() / exp.len() as f64;
        let weights: Vec<f64> =
            exp.iter().map(|e| (1.0 - uniform_share) * e / mean + uniform_share).collect();
        let flags: Vec<bool> = rows.iter().map(|&i| flagged[i]).collect();
        total += weight_share(&weights, &flags) * rows.len() as f64;
    }
    total / log_weights.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Pairs by hand: positives {0.9, 0.5, 0.5}, negatives {0.5, 0.2}. Wins: 0.9 beats both (2),
    /// each 0.5 beats 0.2 (2) and ties 0.5 (2 halves): U = 4 + 1 = 5 of 6 pairs.
    #[test]
    fn auc_of_a_hand_computed_case() {
        let scores = [0.9, 0.5, 0.5, 0.5, 0.2];
        let positive = [true, true, true, false, false];
        assert_eq!(roc_auc(&scores, &positive), Some(5.0 / 6.0));
        assert_eq!(roc_auc(&[1.0, 2.0], &[false, true]), Some(1.0));
        assert_eq!(roc_auc(&[1.0, 2.0], &[true, false]), Some(0.0));
        assert_eq!(roc_auc(&[3.0, 3.0, 3.0], &[true, false, true]), Some(0.5));
        assert_eq!(roc_auc(&[1.0, 2.0], &[true, true]), None, "no negatives");
        assert_eq!(roc_auc(&[], &[]), None);
    }

    fn brute_force(scores: &[f32], positive: &[bool]) -> Option<f64> {
        let mut twice_u = 0u64;
        let mut pairs = 0u64;
        for (i, &p) in positive.iter().enumerate() {
            for (j, &q) in positive.iter().enumerate() {
                if p && !q {
                    pairs += 1;
                    twice_u += match scores[i].partial_cmp(&scores[j]).unwrap() {
                        std::cmp::Ordering::Greater => 2,
                        std::cmp::Ordering::Equal => 1,
                        std::cmp::Ordering::Less => 0,
                    };
                }
            }
        }
        (pairs > 0).then(|| twice_u as f64 / (2 * pairs) as f64)
    }

    proptest! {
        /// Against the pairwise count on random data, with many ties (scores on a coarse grid).
        #[test]
        fn auc_equals_the_pairwise_count(
            rows in proptest::collection::vec((0i32..8, any::<bool>()), 0..60)
        ) {
            let scores: Vec<f32> = rows.iter().map(|&(s, _)| s as f32 * 0.25 - 1.0).collect();
            let positive: Vec<bool> = rows.iter().map(|&(_, p)| p).collect();
            prop_assert_eq!(roc_auc(&scores, &positive), brute_force(&scores, &positive));
        }
    }

    /// `bench` with `--ablations` on one environment, tiny networks and a few iterations: the
    /// extra rows reach the summary, results.json and results.md, the true-α row uses the true
    /// share, the oracle row's Eq. 15 recovers it, `--fixed-alpha` sets the standard row's α,
    /// and every SafeDICE row reports the same discriminator AUCs (one discriminator per seed).
    #[test]
    fn tiny_bench_with_ablations_writes_the_extra_rows() {
        use crate::bench::{self, BenchConfig, DataSize};
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            bench: bench::BenchArgs,
        }
        let parse = |args: &[&str]| {
            let cli = <Cli as clap::Parser>::try_parse_from(args.iter().copied()).unwrap();
            cli.bench.to_config()
        };
        assert!(parse(&["bench", "--quick", "--ablations"]).unwrap().ablations);
        assert!(!parse(&["bench", "--quick"]).unwrap().ablations);
        assert!(parse(&["bench", "--ablations", "--preferred", "0"]).is_err());
        assert_eq!(
            parse(&["bench", "--quick", "--fixed-alpha", "0.25"]).unwrap().fixed_alpha,
            Some(0.25)
        );
        assert!(parse(&["bench", "--quick", "--fixed-alpha", "1"]).is_err());

        let mut config = BenchConfig::quick();
        config.envs = vec!["six-rooms".to_string()];
        config.algorithms = vec![Algorithm::Safedice, Algorithm::Bc];
        config.seeds = 1;
        config.iterations = 30;
        config.data = DataSize { preferred: 6, non_preferred: 6, labeled: 3 };
        config.eval_episodes = 5;
        config.record_every = 10;
        config.threads = 1;
        config.ablations = true;
        // A study's fixed α replaces alpha-hat in the standard row only.
        config.fixed_alpha = Some(0.25);
        config.overrides.insert("batch_size".into(), 32.into());
        config.overrides.insert("hidden_sizes".into(), serde_json::json!([16, 16]));
        let results = bench::run(&config).unwrap();
        let summary = bench::summarize(&results);
        let labels: Vec<&str> = summary.envs[0].rows.iter().map(|r| r.label.as_str()).collect();
        assert_eq!(
            labels,
            [
                "SafeDICE",
                "BC",
                "BC (preferred only)",
                "SafeDICE (true α)",
                "SafeDICE (oracle labels)"
            ]
        );
        let truth = results.data[0].ablation.as_ref().expect("ground truth with --ablations");
        assert!(truth.true_alpha > 0.0 && truth.true_alpha < 1.0, "{truth:?}");
        let run = |v: Variant| results.runs.iter().find(|r| r.variant == v).unwrap();
        let alpha = |v: Variant| run(v).alpha.as_ref().unwrap().alpha_hat;
        assert_eq!(alpha(Variant::TrueAlpha), truth.true_alpha);
        assert_eq!(alpha(Variant::Standard), 0.25);
        assert!((alpha(Variant::OracleLabels) - (truth.true_alpha - 1e-5)).abs() < 1e-6);
        assert!(
            run(Variant::PreferredOnly).alpha.is_none()
                && run(Variant::PreferredOnly).ablation.is_none()
        );
        let aucs: Vec<(f64, f64)> = results
            .runs
            .iter()
            .filter(|r| r.algorithm == Algorithm::Safedice)
            .map(|r| r.ablation.as_ref().map(|a| (a.auc_heldout, a.auc_unlabeled)).unwrap())
            .collect();
        assert_eq!(aucs.len(), 3);
        assert!(aucs.iter().all(|&a| a == aucs[0]), "one discriminator per seed: {aucs:?}");
        assert!((0.0..=1.0).contains(&aucs[0].0) && (0.0..=1.0).contains(&aucs[0].1));
        let share =
            run(Variant::OracleLabels).ablation.as_ref().unwrap().non_preferred_weight_share;
        assert!((0.0..=1.0).contains(&share), "{share}");

        let dir = tempfile::tempdir().unwrap();
        bench::write_outputs(&results, &summary, dir.path(), "safedice bench (test)").unwrap();
        let md = std::fs::read_to_string(dir.path().join("results.md")).unwrap();
        for label in labels {
            let rows = md.lines().filter(|l| l.starts_with(&format!("| {label} |"))).count();
            assert_eq!(rows, 1, "one table row for {label}\n{md}");
            let speeds = md.lines().filter(|l| l.starts_with(&format!("| six-rooms | {label} |")));
            assert!(speeds.count() >= 1, "{label} in the speed table\n{md}");
        }
        assert!(md.contains("## Ablations"), "{md}");
        assert!(md.contains("| six-rooms | SafeDICE (oracle labels) | "), "{md}");
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("results.json")).unwrap())
                .unwrap();
        assert_eq!(json["results"]["config"]["ablations"], true);
        let runs = json["results"]["runs"].as_array().unwrap();
        let variants: Vec<&str> = runs.iter().map(|r| r["variant"].as_str().unwrap()).collect();
        assert_eq!(
            variants,
            ["standard", "standard", "preferred_only", "true_alpha", "oracle_labels"]
        );
        assert!(runs[4]["ablation"]["auc_heldout"].is_number());
        let rows = json["summary"]["envs"][0]["rows"].as_array().unwrap();
        assert_eq!(rows[4]["label"], "SafeDICE (oracle labels)");
        assert!(rows[4]["discriminator_auc_unlabeled"]["mean"].is_number());
        assert!(json["results"]["data"][0]["ablation"]["true_alpha"].is_number());
        let svg = std::fs::read_to_string(dir.path().join("six-rooms.svg")).unwrap();
        assert_eq!(svg.matches(r#"<g class="point""#).count(), 2, "ablations stay off the plot");
    }

    #[test]
    fn selected_rows_keep_whole_episodes_and_every_column() {
        let spec = crate::envs::DatagenSpec {
            env: "point-goal".into(),
            preferred: 3,
            non_preferred: 2,
            labeled: 0,
            seed: 4,
        };
        let g = crate::envs::generate(&spec).unwrap();
        let flags = row_flags(&g.unlabeled, &g.manifest.unlabeled_non_preferred_episode_ids);
        let keep: Vec<bool> = flags.iter().map(|f| !f).collect();
        let preferred = select_rows(&g.unlabeled, &keep).unwrap();
        assert_eq!(preferred.episodes(), 3);
        assert_eq!(preferred.len(), g.manifest.unlabeled_preferred.transitions);
        let first = keep.iter().position(|&k| k).unwrap();
        assert_eq!(preferred.obs(0), g.unlabeled.obs(first));
        assert_eq!(preferred.next_obs(0), g.unlabeled.next_obs(first));
        let cost: f64 = preferred.costs().unwrap().iter().map(|&c| c as f64).sum();
        let expected = g.manifest.unlabeled_preferred.mean_cost * 3.0;
        assert!((cost - expected).abs() < 1e-6, "{cost} vs {expected}");
        assert!(select_rows(&g.unlabeled, &vec![false; g.unlabeled.len()]).is_none());
        assert_eq!(weight_share(&[1.0, 3.0], &[false, true]), 0.75);
    }

    /// One batch is the plain share; a row 1000 nats above the rest rules only its own batch
    /// (a whole-dataset share would be 1 or 0 with it), and f64 stays finite.
    #[test]
    fn batch_weight_share_normalises_each_batch() {
        let flags = [false, true, false, true];
        let logs = [0.0, 3f64.ln(), 0.0, 3f64.ln()];
        assert!((batch_weight_share(&logs, &flags, 4, 0, 0.0) - 0.75).abs() < 1e-12);
        assert!((batch_weight_share(&logs, &flags, 1, 0, 0.0) - 0.5).abs() < 1e-12);
        let mut logs = vec![0.0; 8];
        let mut flags = vec![false; 8];
        logs[0] = 1000.0;
        flags[1..].iter_mut().for_each(|f| *f = true);
        // Batches of one: the share is the flagged fraction of rows, 7/8.
        assert!((batch_weight_share(&logs, &flags, 1, 3, 0.0) - 7.0 / 8.0).abs() < 1e-12);
        // Batches of four: the batch holding row 0 gives 0, the other 1: mean 1/2.
        assert!((batch_weight_share(&logs, &flags, 4, 3, 0.0) - 0.5).abs() < 1e-12);
        // A uniform share m moves each batch's share toward its flagged fraction:
        // (1 − m) · 1/2 + m · 7/8.
        let mixed = batch_weight_share(&logs, &flags, 4, 3, 0.2);
        assert!((mixed - (0.8 * 0.5 + 0.2 * 7.0 / 8.0)).abs() < 1e-12, "{mixed}");
    }
}
