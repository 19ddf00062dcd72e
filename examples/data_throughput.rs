//! Parser / canonical-form throughput and peak memory on a Walker-sized dataset: a benchmark
//! that prints its numbers (timings depend on the machine and its load), not a test:
//!
//! `cargo run --release --example data_throughput`
//!
//! Peak RSS is read from /proc/self/status (VmHWM) after resetting it through
//! /proc/self/clear_refs, so each figure is the peak while that one parse ran (Linux only).

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::data::{
    decode_canonical, encode_canonical, parse_file, write_csv, write_jsonl, write_npz, ActionSpace,
    Actions, Dataset, DatasetParts,
};

type Writer = fn(&Dataset, &std::path::Path) -> std::io::Result<()>;

const TRANSITIONS: usize = 200_000;
const OBS_DIM: usize = 17;
const ACT_DIM: usize = 6;
const EPISODE_LEN: usize = 1000;

fn walker_sized() -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut normal =
        |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-3.0f32..3.0)).collect() };
    let actions: Vec<f32> = normal(TRANSITIONS * ACT_DIM).iter().map(|a| a / 3.0).collect();
    Dataset::new(DatasetParts {
        obs_dim: OBS_DIM,
        action_space: ActionSpace::infer_continuous(&actions, ACT_DIM),
        observations: normal(TRANSITIONS * OBS_DIM),
        actions: Actions::Continuous(actions),
        next_observations: normal(TRANSITIONS * OBS_DIM),
        terminals: (0..TRANSITIONS).map(|i| i % EPISODE_LEN == EPISODE_LEN - 1).collect(),
        episode_ids: (0..TRANSITIONS).map(|i| (i / EPISODE_LEN) as u32).collect(),
        rewards: Some(normal(TRANSITIONS)),
        costs: Some(normal(TRANSITIONS)),
    })
    .unwrap()
}

fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(f64::NAN);
    kib / 1024.0
}

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let d = walker_sized();
    let column_mib =
        (d.observations().len() * 2 + d.len() * (ACT_DIM + 4)) as f64 * 4.0 / 1048576.0;
    println!("{} transitions, obs {OBS_DIM}, act {ACT_DIM}: columns {column_mib:.1} MiB", d.len());
    let writers: [(&str, Writer); 3] =
        [("d.jsonl", write_jsonl), ("d.csv", write_csv), ("d.npz", write_npz)];
    for (name, write) in writers {
        let path = dir.path().join(name);
        let t = Instant::now();
        write(&d, &path).unwrap();
        let write_s = t.elapsed().as_secs_f64();
        let mib = std::fs::metadata(&path).unwrap().len() as f64 / 1048576.0;
        reset_peak_rss();
        let base = peak_rss_mib();
        let t = Instant::now();
        let (_, parsed) = parse_file(&path, name).unwrap();
        let parse_s = t.elapsed().as_secs_f64();
        let peak = peak_rss_mib() - base;
        assert_eq!(parsed, d);
        drop(parsed);
        println!(
            "{name:8} {mib:7.1} MiB  write {write_s:6.2}s  parse {parse_s:6.2}s \
             ({:6.1} MiB/s)  parse peak RSS above baseline {peak:6.1} MiB",
            mib / parse_s
        );
    }
    let t = Instant::now();
    let bytes = encode_canonical(&d);
    let encode_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let back = decode_canonical(&bytes).unwrap();
    let decode_s = t.elapsed().as_secs_f64();
    assert_eq!(back, d);
    let mib = bytes.len() as f64 / 1048576.0;
    println!(
        "canonical {mib:6.1} MiB  encode {encode_s:.3}s ({:.0} MiB/s)  decode {decode_s:.3}s \
         ({:.0} MiB/s)",
        mib / encode_s,
        mib / decode_s
    );
}
