//! Behaviour on a gridworld whose unlabeled data is 60% demonstrations of a hazardous shortcut
//! and 40% of a safe detour, with 20 shortcut demonstrations labeled non-preferred: SafeDICE's
//! greedy policy must take the detour, BC's follows the majority through the hazards.

use crate::support::tasks::*;
use safedice::algo::Algorithm;
use serde_json::json;

fn small(extra: serde_json::Value) -> serde_json::Value {
    let mut config = json!({
        "seed": 3,
        "iterations": 1000,
        "batch_size": 256,
        "hidden_sizes": [32, 32],
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

    // Cross-fitting trains two discriminators, each for half the steps: 500 each (at 300 each
    // alpha-hat came out 0 on gemm's AVX-512 kernels and the run crossed the hazard).
    let (safedice, alpha) =
        train(Algorithm::Safedice, small(json!({"discriminator_iterations": 1000})), &data);
    let (cost, reached) = grid_rollout(&safedice);
    let alpha = alpha.unwrap();
    assert_eq!(
        (cost, reached),
        (0, true),
        "SafeDICE (alpha-hat {alpha}) should take the detour to the goal"
    );
    // The service's alpha-hat is the lower end of its interval (docs/algorithm.md): above 0,
    // since the data do separate, and below the 0.6 share of unsafe episodes in D^U.
    assert!(alpha > 0.0 && alpha < 0.6, "alpha-hat {alpha}");
}

/// Measurements behind the `service` defaults (not a check: prints a table). Run with
/// `cargo test --test learning -- --ignored --nocapture measure_defaults`; set
/// `MEASURE_ONLY=<substring>` to run only the matching "task | variant" rows and
/// `MEASURE_SEEDS=<n>` for fewer seeds (default 3).
#[test]
#[ignore]
fn measure_defaults() {
    let variants: Vec<(&str, serde_json::Value)> = vec![
        ("service (reset, std reward, GP 10, lr 1e-4)", json!({})),
        ("service + terminal none", json!({"terminal_handling": "none"})),
        ("service + terminal mask", json!({"terminal_handling": "mask"})),
        ("service + terminal absorbing", json!({"terminal_handling": "absorbing"})),
        ("service + raw reward", json!({"standardize_reward": false})),
        ("service + lr_actor 3e-4", json!({"lr_actor": 3e-4})),
        ("service + disc GP 0.1", json!({"discriminator_gp": 0.1})),
        ("preset paper (all lr 3e-4)", json!({"preset": "paper"})),
        ("preset authors-code (actor 1e-5)", json!({"preset": "authors-code"})),
    ];
    type Rollout = fn(&safedice::algo::Policy) -> (usize, bool);
    type MakeData = fn(u64) -> safedice::algo::TrainingData;
    let tasks: [(&str, MakeData, Rollout); 2] = [
        ("gridworld", grid_training_data, grid_rollout),
        ("point", point_training_data, point_rollout),
    ];
    let only = std::env::var("MEASURE_ONLY").unwrap_or_default();
    let seeds: u64 = std::env::var("MEASURE_SEEDS").map_or(3, |s| s.parse().unwrap());
    for (task, make_data, rollout) in tasks {
        for (name, extra) in &variants {
            if !format!("{task} | {name}").contains(&only) {
                continue;
            }
            let mut outcomes = Vec::new();
            for seed in 0..seeds {
                let data = make_data(seed + 10);
                let mut config = small(
                    json!({"discriminator_iterations": 500, "seed": seed, "iterations": 3000, "hidden_sizes": [64, 64]}),
                );
                config.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
                let config = safedice::algo::resolve_config(Algorithm::Safedice, &config).unwrap();
                let mut trainer = safedice::algo::build_trainer(&config, &data, None).unwrap();
                let mut failure = None;
                let mut last = Vec::new();
                while !trainer.is_finished() {
                    match trainer.step(trainer.progress().step % 100 == 99) {
                        Ok(m) if !m.is_empty() => last = m,
                        Ok(_) => {}
                        Err(e) => {
                            failure = Some(e.to_string());
                            break;
                        }
                    }
                }
                let get =
                    |k: &str| last.iter().find(|(n, _)| *n == k).map_or(f64::NAN, |(_, v)| *v);
                let outcome = match failure {
                    Some(e) => format!("diverged ({})", e.chars().take(60).collect::<String>()),
                    None => {
                        let a = trainer.export_policy().unwrap();
                        let policy = safedice::algo::Policy::load(&a.spec, &a.weights).unwrap();
                        let (cost, reached) = rollout(&policy);
                        format!(
                            "cost {cost} goal {reached} alpha {:.3} ess {:.3} nu_loss {:.3}",
                            trainer.alpha_hat().unwrap_or(f64::NAN),
                            get("ess_fraction"),
                            get("nu_loss")
                        )
                    }
                };
                outcomes.push(outcome);
            }
            println!("{task:10} | {name:45} | {}", outcomes.join(" ; "));
        }
    }
}
