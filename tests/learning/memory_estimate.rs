//! Measures the peak memory of training runs and compares it with the admission estimate
//! (`safedice::algo::memory`), whose unit test keeps the numbers measured here.
//!
//! `cargo test --test learning memory_estimate -- --ignored --nocapture` runs every case in a fresh
//! child process (this binary again, so one case's allocations never count for another): the
//! child reads the datasets' canonical bytes from files and decodes them as a worker does, builds
//! the trainer, runs steps of every phase with a checkpoint after each, exports the policy, and
//! reports its peak resident size (VmHWM) above the size it started with. The datasets are
//! random, in the shapes each case names.

use std::path::Path;
use std::process::Command;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::algo::memory::{estimate_job_memory, DataShape};
use safedice::algo::{build_trainer, resolve_config, Algorithm, TrainingData};
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};
use serde_json::{json, Value};

const CASE_VAR: &str = "SAFEDICE_MEMORY_CASE";
const DIR_VAR: &str = "SAFEDICE_MEMORY_DIR";
/// The child's test, by its full name in the test binary (tests/learning).
const CHILD_TEST: &str = "memory_estimate::child_measure";

struct Case {
    name: &'static str,
    algorithm: Algorithm,
    config: Value,
    /// (transitions, episode length) of D^U and D^N.
    unlabeled: (usize, usize),
    non_preferred: (usize, usize),
    obs_dim: usize,
    action_space: ActionSpace,
}

fn continuous(dim: usize) -> ActionSpace {
    ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] }
}

/// Every phase runs (two steps each): pretraining phases and iterations of 2.
fn short(mut config: Value) -> Value {
    let object = config.as_object_mut().unwrap();
    object.insert("iterations".into(), json!(2));
    object.insert("seed".into(), json!(0));
    config
}

fn cases() -> Vec<Case> {
    let safedice = |batch: usize, hidden: Value| {
        short(json!({"batch_size": batch, "hidden_sizes": hidden, "discriminator_iterations": 2}))
    };
    vec![
        Case {
            name: "safedice defaults (B 512, [256,256]), 100k x 17-dim obs",
            algorithm: Algorithm::Safedice,
            config: safedice(512, json!([256, 256])),
            unlabeled: (100_000, 500),
            non_preferred: (10_000, 500),
            obs_dim: 17,
            action_space: continuous(6),
        },
        Case {
            name: "safedice B 65536, [256,256], 100k x 17-dim obs",
            algorithm: Algorithm::Safedice,
            config: safedice(65_536, json!([256, 256])),
            unlabeled: (100_000, 500),
            non_preferred: (10_000, 500),
            obs_dim: 17,
            action_space: continuous(6),
        },
        Case {
            name: "safedice B 4096, [1024,1024,1024], 50k x 64-dim obs",
            algorithm: Algorithm::Safedice,
            config: safedice(4096, json!([1024, 1024, 1024])),
            unlabeled: (50_000, 1000),
            non_preferred: (5_000, 1000),
            obs_dim: 64,
            action_space: continuous(8),
        },
        Case {
            name: "safedice B 512, [256,256], 1M x 64-dim obs",
            algorithm: Algorithm::Safedice,
            config: safedice(512, json!([256, 256])),
            unlabeled: (1_000_000, 1000),
            non_preferred: (100_000, 1000),
            obs_dim: 64,
            action_space: continuous(8),
        },
        Case {
            name: "safedice absorbing, discrete 16, B 8192, 200k x 32-dim obs",
            algorithm: Algorithm::Safedice,
            config: {
                let mut c = safedice(8192, json!([256, 256]));
                c["terminal_handling"] = json!("absorbing");
                c
            },
            unlabeled: (200_000, 50),
            non_preferred: (20_000, 50),
            obs_dim: 32,
            action_space: ActionSpace::Discrete { n: 16 },
        },
        Case {
            name: "bc B 65536, [256,256], 100k x 17-dim obs",
            algorithm: Algorithm::Bc,
            config: short(json!({"batch_size": 65_536, "hidden_sizes": [256, 256]})),
            unlabeled: (100_000, 500),
            non_preferred: (10_000, 500),
            obs_dim: 17,
            action_space: continuous(6),
        },
        Case {
            name: "dwbc B 16384, [256,256], 100k x 17-dim obs",
            algorithm: Algorithm::Dwbc,
            config: short(json!({"batch_size": 16_384, "hidden_sizes": [256, 256]})),
            unlabeled: (100_000, 500),
            non_preferred: (10_000, 500),
            obs_dim: 17,
            action_space: continuous(6),
        },
        Case {
            name: "ppl 256 pairs x 200-step segments, B 4096, [256,256]",
            algorithm: Algorithm::Ppl,
            config: short(json!({"batch_size": 4096, "hidden_sizes": [256, 256],
                "reward_model_iterations": 2, "pairs_per_batch": 256, "segment_length": 200})),
            unlabeled: (100_000, 200),
            non_preferred: (10_000, 200),
            obs_dim: 17,
            action_space: continuous(6),
        },
        Case {
            name: "dexperts discrete 16, B 16384, [256,256]",
            algorithm: Algorithm::Dexperts,
            config: short(json!({"batch_size": 16_384, "hidden_sizes": [256, 256]})),
            unlabeled: (100_000, 500),
            non_preferred: (10_000, 500),
            obs_dim: 17,
            action_space: ActionSpace::Discrete { n: 16 },
        },
    ]
}

/// A random dataset of `transitions` rows in episodes of `episode` steps (the last one
/// terminal).
fn random_dataset(
    transitions: usize,
    episode: usize,
    obs_dim: usize,
    space: &ActionSpace,
    seed: u64,
) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut uniform =
        |count: usize| -> Vec<f32> { (0..count).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let observations = uniform(transitions * obs_dim);
    let next_observations = uniform(transitions * obs_dim);
    let rewards = uniform(transitions);
    let costs = uniform(transitions);
    let actions = match space {
        ActionSpace::Continuous { dim, .. } => Actions::Continuous(uniform(transitions * dim)),
        ActionSpace::Discrete { n } => {
            Actions::Discrete((0..transitions).map(|i| (i * 7 % n) as u32).collect())
        }
    };
    Dataset::new(DatasetParts {
        obs_dim,
        action_space: space.clone(),
        observations,
        actions,
        next_observations,
        terminals: (0..transitions).map(|i| i % episode == episode - 1).collect(),
        episode_ids: (0..transitions).map(|i| (i / episode) as u32).collect(),
        rewards: Some(rewards),
        costs: Some(costs),
    })
    .expect("a valid dataset")
}

fn shape(rows: (usize, usize), case: &Case) -> DataShape {
    DataShape {
        transitions: rows.0 as u64,
        obs_dim: case.obs_dim as u64,
        action_space: case.action_space.clone(),
        longest_episode: rows.1 as u64,
    }
}

/// A line of /proc/self/status in bytes (Linux).
fn status_bytes(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("procfs");
    let line = status.lines().find(|l| l.starts_with(field)).expect("status field");
    let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib * 1024
}

/// The child: one case's run, its peak reported on stdout.
fn measure(case: &Case, dir: &Path) -> u64 {
    let baseline = status_bytes("VmRSS:");
    let load = |name: &str| {
        let bytes = std::fs::read(dir.join(name)).unwrap();
        std::sync::Arc::new(safedice::data::decode_canonical(&bytes).unwrap())
    };
    let data =
        TrainingData { unlabeled: load("u.canonical"), non_preferred: Some(load("n.canonical")) };
    let config = resolve_config(case.algorithm, &case.config).expect("config");
    let mut trainer = build_trainer(&config, &data, None).expect("trainer");
    let mut phase = trainer.progress().phase;
    let mut step = 0;
    while !trainer.is_finished() {
        trainer.step(step % 2 == 0).expect("step");
        step += 1;
        if trainer.progress().phase != phase || trainer.is_finished() {
            phase = trainer.progress().phase;
            drop(trainer.checkpoint().expect("checkpoint"));
        }
    }
    drop(trainer.export_policy().expect("export"));
    status_bytes("VmHWM:") - baseline
}

#[test]
#[ignore = "measures memory in child processes; run with --ignored --nocapture"]
fn child_measure() {
    let (Ok(index), Ok(dir)) = (std::env::var(CASE_VAR), std::env::var(DIR_VAR)) else { return };
    let case = &cases()[index.parse::<usize>().unwrap()];
    println!("PEAK_BYTES {}", measure(case, Path::new(&dir)));
}

#[test]
#[ignore = "trains every case in a child process (minutes); run with --ignored --nocapture"]
fn estimates_bound_measured_peaks() {
    let mib = |bytes: u64| bytes as f64 / (1 << 20) as f64;
    let mut rows = Vec::new();
    for (index, case) in cases().iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        for (name, (rows, episode), seed) in
            [("u.canonical", case.unlabeled, 1), ("n.canonical", case.non_preferred, 2)]
        {
            let dataset = random_dataset(rows, episode, case.obs_dim, &case.action_space, seed);
            std::fs::write(dir.path().join(name), safedice::data::encode_canonical(&dataset))
                .unwrap();
        }
        let output = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", CHILD_TEST, "--ignored", "--nocapture", "--test-threads", "1"])
            .env(CASE_VAR, index.to_string())
            .env(DIR_VAR, dir.path())
            .output()
            .expect("run the child");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(
            output.status.success(),
            "{}: {stdout}{}",
            case.name,
            String::from_utf8_lossy(&output.stderr)
        );
        let measured: u64 = stdout
            .split("PEAK_BYTES ")
            .nth(1)
            .and_then(|rest| rest.split_whitespace().next())
            .unwrap_or_else(|| panic!("{}: the child reported no peak: {stdout}", case.name))
            .parse()
            .unwrap();
        let config = resolve_config(case.algorithm, &case.config).unwrap();
        let estimate = estimate_job_memory(
            &config,
            &shape(case.unlabeled, case),
            Some(&shape(case.non_preferred, case)),
        );
        let ratio = estimate.total as f64 / measured as f64;
        let row = format!(
            "| {} | {:.0} | {:.0} (data {:.0}, networks {:.0}, step {:.0}) | {ratio:.2} |",
            case.name,
            mib(measured),
            mib(estimate.total),
            mib(estimate.data),
            mib(estimate.networks),
            mib(estimate.step)
        );
        println!("{row}");
        rows.push((row, ratio));
    }
    println!("| case | measured MiB | estimate MiB | estimate / measured |");
    for (row, _) in &rows {
        println!("{row}");
    }
    for (row, ratio) in rows {
        assert!((1.0..=2.5).contains(&ratio), "estimate out of bounds: {row}");
    }
}
