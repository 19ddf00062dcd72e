//! The safety head a SafeDICE policy carries (`safedice::algo::safety`), on a built-in
//! environment: its log-ratio separates held-out non-preferred state-actions from preferred ones,
//! its support score separates the data's states from states far off them, and the policy file
//! gives the same scores as the trainer's discriminator.

use std::sync::Arc;

use safedice::algo::safedice::SafediceTrainer;
use safedice::algo::{self, Algorithm, Policy, Trainer, TrainingData};
use safedice::data::{Actions, Dataset};
use safedice::envs::{generate, DatagenSpec, Generated};
use serde_json::json;

/// The bound on the log-ratio's AUC (held-out non-preferred state-actions against preferred
/// ones). Measured at these seeds: six-rooms 0.98, cartpole-slider 0.92 (point-goal 0.63, where
/// the two demonstrators share most states and actions: docs/safety-scores.md); the bound leaves room
/// for other builds' floating point without letting a head that does not separate pass.
const MIN_AUC: f64 = 0.85;

fn generated(env: &str, seed: u64) -> Generated {
    let spec = DatagenSpec { env: env.into(), preferred: 40, non_preferred: 40, labeled: 20, seed };
    generate(&spec).unwrap()
}

/// Rows (observations, actions) of `data` whose episode is (or, with `keep` false, is not) in
/// `episodes`.
fn rows(data: &Dataset, episodes: &[u32], keep: bool) -> (Vec<f32>, Actions) {
    let obs_dim = data.obs_dim();
    let chosen: Vec<usize> =
        (0..data.len()).filter(|&r| episodes.contains(&data.episode_ids()[r]) == keep).collect();
    let obs = chosen
        .iter()
        .flat_map(|&r| data.observations()[r * obs_dim..(r + 1) * obs_dim].to_vec())
        .collect();
    let actions = match data.actions() {
        Actions::Continuous(values) => {
            let width = values.len() / data.len();
            Actions::Continuous(
                chosen.iter().flat_map(|&r| values[r * width..(r + 1) * width].to_vec()).collect(),
            )
        }
        Actions::Discrete(picks) => Actions::Discrete(chosen.iter().map(|&r| picks[r]).collect()),
    };
    (obs, actions)
}

/// P(score of a positive > score of a negative), ties counted half.
fn auc(positives: &[f32], negatives: &[f32]) -> f64 {
    let mut wins = 0.0;
    for p in positives {
        for n in negatives {
            wins += if p > n {
                1.0
            } else if p == n {
                0.5
            } else {
                0.0
            };
        }
    }
    wins / (positives.len() * negatives.len()) as f64
}

fn median(mut values: Vec<f32>) -> f32 {
    values.sort_by(f32::total_cmp);
    values[values.len() / 2]
}

#[test]
fn the_safety_head_separates_unsafe_state_actions_and_states_off_the_data_on_six_rooms() {
    check_safety_head("six-rooms");
}

#[test]
fn the_safety_head_separates_unsafe_state_actions_and_states_off_the_data_on_cartpole_slider() {
    check_safety_head("cartpole-slider");
}

fn check_safety_head(env: &str) {
    let train = generated(env, 7);
    let data = TrainingData {
        unlabeled: Arc::new(train.unlabeled.clone()),
        non_preferred: train.labeled_non_preferred.clone().map(Arc::new),
    };
    let config = json!({"seed": 1, "iterations": 6100, "discriminator_iterations": 6000,
                        "hidden_sizes": [64, 64], "batch_size": 256});
    let config = algo::resolve_config(Algorithm::Safedice, &config).unwrap();
    let mut trainer = SafediceTrainer::new(&config, &data).unwrap();
    while !trainer.is_finished() {
        trainer.step(false).unwrap();
    }
    let artifact = trainer.export_policy().unwrap();
    let safety = artifact.spec.safety.clone().expect("a SafeDICE policy carries a safety head");
    let policy = Policy::load(&artifact.spec, &artifact.weights).unwrap();

    // Held-out data of the same task: its labeled non-preferred episodes against the preferred
    // episodes of its unlabeled set.
    let test = generated(env, 8);
    let labeled = test.labeled_non_preferred.as_ref().unwrap();
    let (n_obs, n_act) = rows(labeled, &[], false);
    let unsafe_ids = &test.manifest.unlabeled_non_preferred_episode_ids;
    let (p_obs, p_act) = rows(&test.unlabeled, unsafe_ids, false);
    let score = |obs: &[f32], act: &Actions| policy.safety_scores(obs, act).expect("answers");
    let on_unsafe = score(&n_obs, &n_act);
    let on_safe = score(&p_obs, &p_act);
    let separation = auc(&on_unsafe.non_preferred_log_ratio, &on_safe.non_preferred_log_ratio);
    println!(
        "{env}: AUC {separation:.3} of the log-ratio (held-out D^N vs preferred; heldout AUC in \
         training {:?}); median out_of_support {:.2} on held-out states",
        safety.heldout_auc,
        median(on_safe.out_of_support.clone())
    );
    assert!(separation >= MIN_AUC, "{env}: AUC {separation}");

    // States of the data are on its support; the same states moved 10 standard deviations
    // away in every dimension are not.
    assert!(median(on_safe.out_of_support.clone()) <= 1.0, "{:?}", &on_safe.out_of_support[..8]);
    // One standard deviation of the support's space, in the observations' own units.
    let policy_std = artifact.spec.observation_normalization.as_ref().map(|n| n.std.clone());
    let std: Vec<f32> = (safety.support_normalization.std.iter().enumerate())
        .map(|(j, s)| s * policy_std.as_ref().map_or(1.0, |p| p[j]))
        .collect();
    let far: Vec<f32> =
        p_obs.iter().enumerate().map(|(i, x)| x + 10.0 * std[i % std.len()]).collect();
    let off = score(&far, &p_act);
    assert!(off.out_of_support.iter().all(|&s| s > 2.0), "{:?}", &off.out_of_support[..8]);

    // The policy file's head is the trainer's discriminators (cross-fitting's parts), each
    // read through its recalibration, averaged.
    let own = trainer.discriminator_logits(labeled).unwrap();
    let parts = trainer.finished_part_discriminator_logits(labeled).unwrap();
    assert_eq!(parts.len(), safety.more_discriminators.len(), "{safety:?}");
    let calibrated = |c: f32, scale: f64, shift: f64| scale * f64::from(c) + shift;
    let want: Vec<f64> = (0..own.len())
        .map(|i| {
            let last = calibrated(own[i], safety.logit_scale, safety.logit_shift);
            let others = (parts.iter().zip(&safety.more_discriminators))
                .map(|(logits, r)| calibrated(logits[i], r.logit_scale, r.logit_shift));
            (last + others.sum::<f64>()) / (1 + parts.len()) as f64
        })
        .collect();
    let recorded = policy.safety_scores(&n_obs, labeled.actions()).unwrap();
    for (got, want) in recorded.non_preferred_log_ratio.iter().zip(&want) {
        assert!((f64::from(*got) - want).abs() <= 1e-4 * want.abs().max(1.0), "{got} vs {want}");
    }

    // Other algorithms carry no head.
    let bc = algo::resolve_config(Algorithm::Bc, &json!({"iterations": 2})).unwrap();
    let mut bc = algo::build_trainer(&bc, &data, None).unwrap();
    bc.step(false).unwrap();
    let bc = bc.export_policy().unwrap();
    assert!(bc.spec.safety.is_none());
    let bc = Policy::load(&bc.spec, &bc.weights).unwrap();
    assert!(bc.safety_scores(&n_obs, labeled.actions()).is_none());
}
