//! What a safety score adds to an action, in process: `Policy::act` alone against `Policy::act`
//! then `Policy::safety_scores`, on a SafeDICE policy of the paper's size (256-256, the
//! discriminator too) trained briefly on point-goal data (21 observations, 1,024 reference
//! states). Prints the median and 99th percentile per call for 1 and 64 observations. The
//! weights do not matter for the time: the arithmetic is the same.
//!
//!     cargo run --release --example safety_score_cost [-- --calls 20000]

use std::sync::Arc;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use safedice::algo::{self, Algorithm, Policy, TrainingData};
use safedice::envs::{generate, DatagenSpec};

fn main() -> anyhow::Result<()> {
    let mut calls = 20_000usize;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        match (flag.as_str(), args.next()) {
            ("--calls", Some(value)) => calls = value.parse()?,
            _ => anyhow::bail!("usage: safety_score_cost [--calls N]"),
        }
    }
    let spec = DatagenSpec {
        env: "point-goal".into(),
        preferred: 50,
        non_preferred: 50,
        labeled: 10,
        seed: 0,
    };
    let generated = generate(&spec)?;
    let data = TrainingData {
        unlabeled: Arc::new(generated.unlabeled.clone()),
        non_preferred: generated.labeled_non_preferred.clone().map(Arc::new),
    };
    let config = serde_json::json!({"iterations": 20, "discriminator_iterations": 10,
                                    "hidden_sizes": [256, 256]});
    let config = algo::resolve_config(Algorithm::Safedice, &config)?;
    let mut trainer = algo::build_trainer(&config, &data, None)?;
    while !trainer.is_finished() {
        trainer.step(false)?;
    }
    let artifact = trainer.export_policy()?;
    let policy = Policy::load(&artifact.spec, &artifact.weights)?;
    let obs_dim = artifact.spec.obs_dim;
    let observations = generated.unlabeled.observations();
    println!("safety_score_cost: {calls} calls each, release build, one thread");
    println!("{:>5} {:>22} {:>22}", "rows", "act p50 / p99 (µs)", "+ scores p50 / p99 (µs)");
    for rows in [1usize, 64] {
        let batch = &observations[..rows * obs_dim];
        let plain = time(calls, || {
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            policy.act(batch, true, &mut rng).map(drop)
        })?;
        let scored = time(calls, || {
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let actions = policy.act(batch, true, &mut rng)?;
            std::hint::black_box(policy.safety_scores(batch, &actions));
            Ok(())
        })?;
        println!(
            "{rows:>5} {:>10.1} / {:>9.1} {:>10.1} / {:>9.1}",
            plain.0, plain.1, scored.0, scored.1
        );
    }
    Ok(())
}

/// Median and 99th percentile of `calls` runs of `work`, in microseconds.
fn time(
    calls: usize,
    mut work: impl FnMut() -> Result<(), algo::TrainError>,
) -> anyhow::Result<(f64, f64)> {
    let mut micros = Vec::with_capacity(calls);
    for _ in 0..calls {
        let start = Instant::now();
        work()?;
        micros.push(start.elapsed().as_secs_f64() * 1e6);
    }
    micros.sort_by(f64::total_cmp);
    Ok((micros[calls / 2], micros[calls * 99 / 100]))
}
