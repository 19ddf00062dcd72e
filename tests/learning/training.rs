//! The training interface end to end on tiny tasks, for every algorithm and both action kinds:
//! determinism, checkpoint/resume equality, artefact round trip, data and checkpoint errors,
//! the non-finite guard, and alpha-hat against a discriminator trained on data with a known
//! answer.

use std::sync::Arc;

use crate::support::tasks::*;
use safedice::algo::{self, Algorithm, Policy, TrainError, Trainer, TrainingData};
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};
use serde_json::{json, Value};

fn tiny(algorithm: Algorithm, seed: u64) -> Value {
    let mut c = json!({"seed": seed, "iterations": 12, "batch_size": 32, "hidden_sizes": [16, 16]});
    let phase = match algorithm {
        Algorithm::Safedice => Some("discriminator_iterations"),
        Algorithm::Ppl => Some("reward_model_iterations"),
        _ => None,
    };
    if let Some(key) = phase {
        c[key] = json!(6);
    }
    c
}

fn build(
    config: &Value,
    algorithm: Algorithm,
    data: &TrainingData,
    checkpoint: Option<&[u8]>,
) -> Box<dyn Trainer> {
    let config = algo::resolve_config(algorithm, config).unwrap();
    algo::build_trainer(&config, data, checkpoint).unwrap()
}

fn run_to_end(t: &mut Box<dyn Trainer>) {
    while !t.is_finished() {
        let metrics = t.step(true).unwrap();
        assert!(!metrics.is_empty());
        assert!(metrics.iter().all(|(_, v)| v.is_finite()), "{metrics:?}");
    }
}

fn weights(t: &dyn Trainer) -> Vec<u8> {
    t.export_policy().unwrap().weights
}

fn datasets() -> [(&'static str, TrainingData); 2] {
    [("gridworld", grid_training_data(5)), ("point", point_training_data(5))]
}

#[test]
fn same_seed_gives_bitwise_identical_weights_and_resume_continues_the_same_run() {
    for (task, data) in datasets() {
        for algorithm in Algorithm::ALL {
            let config = tiny(algorithm, 11);
            let mut reference = build(&config, algorithm, &data, None);
            run_to_end(&mut reference);
            let expected = weights(reference.as_ref());

            let mut again = build(&config, algorithm, &data, None);
            run_to_end(&mut again);
            assert_eq!(
                weights(again.as_ref()),
                expected,
                "{algorithm} on {task}: same seed, other weights"
            );

            let mut other = build(&tiny(algorithm, 12), algorithm, &data, None);
            run_to_end(&mut other);
            assert_ne!(weights(other.as_ref()), expected, "{algorithm} on {task}: seed ignored");

            // Stop in the pretraining phase, exactly at its end, and in the main phase.
            let total = reference.progress().total;
            for stop in [3, 6, total - 2] {
                let mut first = build(&config, algorithm, &data, None);
                for _ in 0..stop {
                    first.step(false).unwrap();
                }
                let bytes = first.checkpoint().unwrap();
                drop(first);
                let mut resumed = build(&config, algorithm, &data, Some(&bytes));
                assert_eq!(resumed.progress().step, stop);
                run_to_end(&mut resumed);
                assert_eq!(
                    weights(resumed.as_ref()),
                    expected,
                    "{algorithm} on {task}: resumed at step {stop}, other weights"
                );
                assert_eq!(resumed.alpha_hat(), reference.alpha_hat());
            }
        }
    }
}

/// A job's `threads` are part of its arithmetic, like its seed: at 2 threads a run gives the
/// same weights again, resumed mid-run too, and on a worker that runs them on one thread
/// (`--job-threads 1`: its shards in turn), for every algorithm.
#[test]
fn two_threads_give_the_same_weights_again_resumed_and_on_one_thread() {
    let data = point_training_data(5);
    for algorithm in Algorithm::ALL {
        let mut config = tiny(algorithm, 11);
        config["threads"] = json!(2);
        let mut reference = build(&config, algorithm, &data, None);
        run_to_end(&mut reference);
        let expected = weights(reference.as_ref());

        let mut again = build(&config, algorithm, &data, None);
        run_to_end(&mut again);
        assert_eq!(weights(again.as_ref()), expected, "{algorithm}: 2 threads, other weights");

        let stop = reference.progress().total - 2;
        let mut first = build(&config, algorithm, &data, None);
        for _ in 0..stop {
            first.step(false).unwrap();
        }
        let bytes = first.checkpoint().unwrap();
        drop(first);
        // The cap is read when a run is built; other tests' runs only lose speed meanwhile.
        algo::set_job_thread_cap(1);
        let mut resumed = build(&config, algorithm, &data, Some(&bytes));
        algo::set_job_thread_cap(algo::available_cores());
        run_to_end(&mut resumed);
        assert_eq!(
            weights(resumed.as_ref()),
            expected,
            "{algorithm}: resumed at step {stop} on one thread, other weights"
        );
    }
}

#[test]
fn exported_policies_load_and_act_in_the_dataset_units() {
    for (task, data) in datasets() {
        for algorithm in Algorithm::ALL {
            let mut t = build(&tiny(algorithm, 1), algorithm, &data, None);
            run_to_end(&mut t);
            let artifact = t.export_policy().unwrap();
            assert_eq!(artifact.spec.algorithm, algorithm);
            let spec_json = serde_json::to_value(&artifact.spec).unwrap();
            let policy =
                Policy::load(&serde_json::from_value(spec_json).unwrap(), &artifact.weights)
                    .unwrap();
            let obs = &data.unlabeled.observations()[..3 * data.unlabeled.obs_dim()];
            let mut rng = rand::SeedableRng::seed_from_u64(0);
            match (policy.act(obs, false, &mut rng).unwrap(), data.unlabeled.action_space()) {
                (Actions::Discrete(a), ActionSpace::Discrete { n }) => {
                    assert_eq!(a.len(), 3);
                    assert!(a.iter().all(|&x| (x as usize) < *n), "{algorithm} on {task}");
                }
                (Actions::Continuous(a), ActionSpace::Continuous { dim, low, high }) => {
                    assert_eq!(a.len(), 3 * dim);
                    assert!(a
                        .iter()
                        .enumerate()
                        .all(|(i, &x)| x >= low[i % dim] && x <= high[i % dim]));
                }
                _ => panic!("{algorithm} on {task}: action kind changed"),
            }
        }
    }
}

#[test]
fn progress_reports_phases_and_total_steps() {
    let data = grid_training_data(2);
    // Six discriminator steps cannot tell D^N from D^U on held-out rows; without the uniform
    // fallback the main loop's own metrics are reported (the fallback has its own tests).
    let mut config = tiny(Algorithm::Safedice, 0);
    config["uniform_fallback"] = false.into();
    let mut t = build(&config, Algorithm::Safedice, &data, None);
    assert_eq!(
        (t.progress().step, t.progress().total, t.progress().phase),
        (0, 18, "discriminator")
    );
    assert_eq!(t.alpha_hat(), None);
    for _ in 0..5 {
        t.step(false).unwrap();
    }
    let metrics = t.step(true).unwrap();
    let names: Vec<&str> = metrics.iter().map(|(n, _)| *n).collect();
    assert!(names.contains(&"alpha_hat") && names.contains(&"alpha_hat_argmin_row"), "{names:?}");
    assert_eq!(t.progress().phase, "policy");
    assert!(t.alpha_hat().is_some());
    let metrics = t.step(true).unwrap();
    for name in ["nu_loss", "policy_loss", "ess_fraction", "weight_max_share", "weight_degenerate"]
    {
        assert!(
            metrics.iter().any(|(n, v)| *n == name && v.is_finite()),
            "{name} missing in {metrics:?}"
        );
    }
    while !t.is_finished() {
        t.step(false).unwrap();
    }
    assert!(matches!(t.step(false), Err(TrainError::Other(_))));
}

/// Four (s, a) pairs with d^N = [0, .2, .4, .4] and d^U = 0.7 d^P + 0.3 d^N: min d^U/d^N over
/// D^U is exactly 0.3 (pairs 2 and 3). A discriminator trained without penalty should find it
/// with the paper's minimum (`min`; BBE's own tests are in `algo::safedice::mixture`).
#[test]
fn alpha_hat_matches_the_known_mixture_ratio() {
    fn pairs(counts: [usize; 4]) -> Dataset {
        let mut obs = Vec::new();
        let mut episode_ids = Vec::new();
        for (pair, &count) in counts.iter().enumerate() {
            for _ in 0..count {
                let mut row = vec![0.0f32; 4];
                row[pair] = 1.0;
                obs.extend(row);
                episode_ids.push(episode_ids.len() as u32);
            }
        }
        let n = episode_ids.len();
        Dataset::new(DatasetParts {
            obs_dim: 4,
            action_space: ActionSpace::Discrete { n: 2 },
            next_observations: obs.clone(),
            observations: obs,
            actions: Actions::Discrete(vec![0; n]),
            terminals: vec![false; n],
            episode_ids,
            rewards: None,
            costs: None,
        })
        .unwrap()
    }
    let data = TrainingData {
        unlabeled: Arc::new(pairs([350, 410, 120, 120])),
        non_preferred: Some(Arc::new(pairs([0, 100, 200, 200]))),
    };
    let config = json!({
        "seed": 4, "iterations": 1, "discriminator_iterations": 1500, "batch_size": 256,
        "hidden_sizes": [32, 32], "discriminator_gp": 0.0, "lr_discriminator": 1e-3,
        "normalize_observations": false, "alpha_hat_estimator": "min",
    });
    let mut t = build(&config, Algorithm::Safedice, &data, None);
    let mut argmin_row = f64::NAN;
    for _ in 0..1500 {
        for (name, value) in t.step(true).unwrap() {
            if name == "alpha_hat_argmin_row" {
                argmin_row = value;
            }
        }
    }
    let alpha = t.alpha_hat().unwrap();
    assert!((alpha - 0.3).abs() < 0.03, "alpha-hat {alpha}, expected 0.3");
    assert!(argmin_row >= 760.0, "the minimum must come from pairs 2 or 3, got row {argmin_row}");
}

#[test]
fn non_finite_losses_stop_the_run_with_a_clear_error() {
    let mut parts = grid_dataset(3, 3, 0).into_parts();
    parts.observations.iter_mut().for_each(|x| *x *= 3e38);
    let data = Dataset::new(parts).unwrap();
    let data = TrainingData {
        unlabeled: Arc::new(data),
        non_preferred: Some(Arc::new(grid_dataset(0, 2, 1))),
    };
    let mut config = tiny(Algorithm::Safedice, 0);
    config["normalize_observations"] = json!(false);
    let mut t = build(&config, Algorithm::Safedice, &data, None);
    match t.step(false) {
        Err(TrainError::Diverged { step, message }) => {
            assert_eq!(step, 0);
            assert!(message.contains("discriminator loss (Eq. 9)"), "{message}");
        }
        other => panic!("expected Diverged, got {:?}", other.map(|_| ())),
    }
}

#[test]
fn data_and_checkpoint_mismatches_are_rejected() {
    let grid = grid_training_data(0);
    let config = algo::resolve_config(Algorithm::Safedice, &tiny(Algorithm::Safedice, 0)).unwrap();
    let without_n = TrainingData { unlabeled: grid.unlabeled.clone(), non_preferred: None };
    assert_eq!(algo::check_data(&config, &without_n).unwrap_err().key, "non_preferred");
    let bc = algo::resolve_config(Algorithm::Bc, &json!({})).unwrap();
    assert!(algo::check_data(&bc, &without_n).is_ok());
    let mixed = TrainingData {
        unlabeled: grid.unlabeled.clone(),
        non_preferred: point_training_data(0).non_preferred,
    };
    assert_eq!(algo::check_data(&config, &mixed).unwrap_err().key, "non_preferred");

    let mut t = algo::build_trainer(&config, &grid, None).unwrap();
    t.step(false).unwrap();
    let bytes = t.checkpoint().unwrap();
    let other_seed =
        algo::resolve_config(Algorithm::Safedice, &tiny(Algorithm::Safedice, 1)).unwrap();
    assert!(matches!(
        algo::build_trainer(&other_seed, &grid, Some(&bytes)),
        Err(TrainError::BadCheckpoint(_))
    ));
    let other_data = grid_training_data(1);
    assert!(matches!(
        algo::build_trainer(&config, &other_data, Some(&bytes)),
        Err(TrainError::BadCheckpoint(_))
    ));
    assert!(matches!(
        algo::build_trainer(&config, &grid, Some(b"garbage")),
        Err(TrainError::BadCheckpoint(_))
    ));
}
