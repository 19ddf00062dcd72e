//! Behaviour on a gridworld whose unlabeled data is 60% demonstrations of a hazardous shortcut
//! and 40% of a safe detour, with 20 shortcut demonstrations labeled non-preferred: SafeDICE's
//! greedy policy must take the detour, BC's follows the majority through the hazards.

mod algo_support;

use algo_support::*;
use safedice::algo::Algorithm;
use serde_json::json;

fn small(extra: serde_json::Value) -> serde_json::Value {
    let mut config = json!({
        "seed": 3,
        "iterations": 1500,
        "batch_size": 256,
        "hidden_sizes": [64, 64],
    });
    config.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
    config
}

#[test]
fn safedice_takes_the_safe_route_and_bc_does_not() {
    let data = grid_training_data(1);
    let (bc, _) = train(Algorithm::Bc, small(json!({})), &data);
    let (bc_cost, _) = grid_rollout(&bc);
    assert!(bc_cost > 0, "BC should follow the unsafe majority");

    let (safedice, alpha) =
        train(Algorithm::Safedice, small(json!({"discriminator_iterations": 500})), &data);
    let (cost, reached) = grid_rollout(&safedice);
    let alpha = alpha.unwrap();
    assert!(alpha > 0.2 && alpha < 0.9, "alpha-hat {alpha}");
    assert_eq!(
        (cost, reached),
        (0, true),
        "SafeDICE (alpha-hat {alpha}) should take the detour to the goal"
    );
}
