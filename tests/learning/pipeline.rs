//! The whole offline pipeline on the six-rooms gridworld (the paper's Appendix G): generate
//! demonstrations with `datagen`, train BC and SafeDICE on them, and evaluate the trained
//! policies with `evaluate`, which queries `Policy::act` with batches of observations.
//! As in the paper's Figure 15, BC follows both routes and pays cost; SafeDICE avoids the
//! costly rooms while still reaching the goal.

use std::sync::Arc;

use rand_chacha::ChaCha8Rng;
use safedice::algo::{self, Algorithm, Policy, TrainingData};
use safedice::envs::{evaluate, generate, DatagenSpec, EvalReport};
use serde_json::json;

fn train(algorithm: Algorithm, config: serde_json::Value, data: &TrainingData) -> Policy {
    let config = algo::resolve_config(algorithm, &config).unwrap();
    let mut trainer = algo::build_trainer(&config, data, None).unwrap();
    while !trainer.is_finished() {
        trainer.step(false).unwrap();
    }
    let artifact = trainer.export_policy().unwrap();
    Policy::load(&artifact.spec, &artifact.weights).unwrap()
}

fn evaluate_policy(policy: &Policy) -> EvalReport {
    let act = |obs: &[f32], det: bool, rng: &mut ChaCha8Rng| policy.act(obs, det, rng);
    evaluate("six-rooms", act, 200, 0, true).unwrap()
}

#[test]
fn safedice_avoids_the_costly_rooms_that_bc_walks_through() {
    let spec = DatagenSpec {
        env: "six-rooms".into(),
        preferred: 80,
        non_preferred: 120,
        labeled: 20,
        seed: 0,
    };
    let generated = generate(&spec).unwrap();
    let data = TrainingData {
        unlabeled: Arc::new(generated.unlabeled),
        non_preferred: generated.labeled_non_preferred.map(Arc::new),
    };
    let common =
        json!({"seed": 1, "iterations": 1500, "batch_size": 256, "hidden_sizes": [64, 64]});
    let bc = evaluate_policy(&train(Algorithm::Bc, common.clone(), &data));
    let mut config = common;
    config["discriminator_iterations"] = json!(500);
    let safedice = evaluate_policy(&train(Algorithm::Safedice, config, &data));
    println!("BC {:?}\nSafeDICE {:?}", bc.metrics, safedice.metrics);
    assert!(bc.metrics.average_cost > 5.0, "BC follows the non-preferred majority");
    assert!(
        safedice.metrics.average_cost < 0.25 * bc.metrics.average_cost,
        "SafeDICE cost {} vs BC {}",
        safedice.metrics.average_cost,
        bc.metrics.average_cost
    );
    assert!(safedice.metrics.normalized_return > 90.0, "{:?}", safedice.metrics);
}
