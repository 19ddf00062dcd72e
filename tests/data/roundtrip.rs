//! Writers and the canonical form: `parse(write(d)) == d` for every upload format and
//! `decode(encode(d)) == d`, over random datasets (seeded) with awkward float values; and the
//! episode statistics against hand-computed values.

use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::data::{
    decode_canonical, encode_canonical, parse_file, stats, write_csv, write_jsonl, write_npz,
    ActionSpace, Actions, Dataset, DatasetParts, Format, Summary,
};

/// A random valid dataset in the shape a parser returns (action space as inferred).
fn random_dataset(seed: u64, discrete: bool) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let obs_dim = rng.random_range(1..5);
    let act_dim = rng.random_range(1..4);
    let episodes = rng.random_range(1..5);
    let mut d = DatasetParts {
        obs_dim,
        action_space: ActionSpace::Discrete { n: 1 },
        observations: Vec::new(),
        actions: Actions::Discrete(Vec::new()),
        next_observations: Vec::new(),
        terminals: Vec::new(),
        episode_ids: Vec::new(),
        rewards: rng.random_bool(0.5).then(Vec::new),
        costs: rng.random_bool(0.5).then(Vec::new),
    };
    let (mut continuous, mut indices) = (Vec::new(), Vec::new());
    let mut id: u32 = rng.random_range(0..1000);
    for _ in 0..episodes {
        id += rng.random_range(1..50);
        let len = rng.random_range(1..8);
        let terminal_end = rng.random_bool(0.5);
        for t in 0..len {
            d.observations.extend((0..obs_dim).map(|_| awkward(&mut rng)));
            d.next_observations.extend((0..obs_dim).map(|_| awkward(&mut rng)));
            continuous.extend((0..act_dim).map(|_| awkward(&mut rng)));
            indices.push(rng.random_range(0..6u32));
            d.terminals.push(terminal_end && t == len - 1);
            d.episode_ids.push(id);
            if let Some(r) = &mut d.rewards {
                r.push(awkward(&mut rng));
            }
            if let Some(c) = &mut d.costs {
                c.push(awkward(&mut rng));
            }
        }
    }
    if discrete {
        d.action_space = ActionSpace::Discrete { n: *indices.iter().max().unwrap() as usize + 1 };
        d.actions = Actions::Discrete(indices);
    } else {
        d.action_space = ActionSpace::infer_continuous(&continuous, act_dim);
        d.actions = Actions::Continuous(continuous);
    }
    Dataset::new(d).unwrap()
}

/// Finite f32 values that stress decimal round trips: arbitrary bit patterns, subnormals,
/// extremes, negative zero, integers.
fn awkward(rng: &mut impl Rng) -> f32 {
    match rng.random_range(0..6) {
        0 => loop {
            let v = f32::from_bits(rng.random());
            if v.is_finite() {
                break v;
            }
        },
        1 => f32::from_bits(rng.random_range(1..0x0080_0000)), // subnormal
        2 => [f32::MAX, f32::MIN, f32::MIN_POSITIVE, -0.0, f32::EPSILON][rng.random_range(0..5)],
        3 => rng.random_range(-1000..1000) as f32,
        _ => rng.random_range(-1.0f32..1.0),
    }
}

fn round_trip(
    d: &Dataset,
    name: &str,
    write: fn(&Dataset, &Path) -> std::io::Result<()>,
) -> (Format, Dataset) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    write(d, &path).unwrap();
    parse_file(&path, name).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// Bitwise equality (so -0.0 vs 0.0 would be caught, which `==` on f32 would miss).
fn assert_identical(a: &Dataset, b: &Dataset, what: &str) {
    assert_eq!(a, b, "{what}");
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(a.observations()), bits(b.observations()), "{what}: observations");
    assert_eq!(
        bits(a.next_observations()),
        bits(b.next_observations()),
        "{what}: next_observations"
    );
    if let (Actions::Continuous(x), Actions::Continuous(y)) = (a.actions(), b.actions()) {
        assert_eq!(bits(x), bits(y), "{what}: actions");
    }
    for (x, y) in [(a.rewards(), b.rewards()), (a.costs(), b.costs())] {
        assert_eq!(x.map(bits), y.map(bits), "{what}: rewards/costs");
    }
}

#[test]
fn every_writer_round_trips_exactly() {
    for seed in 0..40 {
        for discrete in [false, true] {
            let d = random_dataset(seed, discrete);
            let what = format!("seed {seed}, discrete {discrete}");
            let (f, back) = round_trip(&d, "d.jsonl", write_jsonl);
            assert_eq!(f, Format::Jsonl);
            assert_identical(&d, &back, &format!("jsonl {what}"));
            let (f, back) = round_trip(&d, "d.csv", write_csv);
            assert_eq!(f, Format::Csv);
            assert_identical(&d, &back, &format!("csv {what}"));
            let (f, back) = round_trip(&d, "d.npz", write_npz);
            assert_eq!(f, Format::Npz);
            assert_identical(&d, &back, &format!("npz {what}"));
            assert_identical(&d, &decode_canonical(&encode_canonical(&d)).unwrap(), &what);
        }
    }
}

#[test]
fn npz_keeps_a_declared_action_space_that_inference_would_change() {
    let mut parts = random_dataset(7, true).into_parts();
    parts.action_space = ActionSpace::Discrete { n: 9 };
    let d = Dataset::new(parts).unwrap();
    assert_eq!(round_trip(&d, "d.npz", write_npz).1, d);
    let mut parts = random_dataset(7, false).into_parts();
    let dim = parts.action_space.width();
    parts.actions = Actions::Continuous(vec![0.0; parts.terminals.len() * dim]);
    parts.action_space =
        ActionSpace::Continuous { dim, low: vec![-2.0; dim], high: vec![3.0; dim] };
    let d = Dataset::new(parts).unwrap();
    assert_eq!(round_trip(&d, "d.npz", write_npz).1, d);
}

#[test]
fn npz_written_timeouts_reproduce_the_episodes_without_episode_ids() {
    // Tools that ignore our `episode_ids` key split at terminals | timeouts: same episodes.
    let d = random_dataset(3, false);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.npz");
    write_npz(&d, &path).unwrap();
    let mut archive = npyz::npz::NpzArchive::open(&path).unwrap();
    let read_flags = |a: &mut npyz::npz::NpzArchive<_>, k: &str| -> Vec<bool> {
        a.by_name(k).unwrap().unwrap().into_vec().unwrap()
    };
    let terminals = read_flags(&mut archive, "terminals");
    let timeouts = read_flags(&mut archive, "timeouts");
    let ends: Vec<usize> =
        (0..d.len()).filter(|&i| terminals[i] || timeouts[i]).map(|i| i + 1).collect();
    let expected: Vec<usize> = d.episode_ranges().iter().map(|r| r.end).collect();
    assert_eq!(ends, expected);
}

#[test]
fn canonical_form_is_versioned_and_rejects_damage() {
    let d = random_dataset(11, false);
    let bytes = encode_canonical(&d);
    let err = decode_canonical(&bytes[..bytes.len() - 1]).unwrap_err();
    assert_eq!(err.code, "corrupt_canonical");
    let err = decode_canonical(b"not a dataset").unwrap_err();
    assert_eq!(err.code, "corrupt_canonical");
    // A safetensors file that is not ours.
    let other = safetensors::serialize(
        [(
            "x",
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![1], &[0; 4])
                .unwrap(),
        )],
        None,
    )
    .unwrap();
    let err = decode_canonical(&other).unwrap_err();
    assert!(err.message.contains("format"), "{}", err.message);
}

#[test]
fn stats_sum_rewards_and_costs_per_episode() {
    let d = Dataset::new(DatasetParts {
        obs_dim: 1,
        action_space: ActionSpace::Discrete { n: 2 },
        observations: vec![0.0; 5],
        actions: Actions::Discrete(vec![0, 1, 0, 1, 0]),
        next_observations: vec![0.0; 5],
        terminals: vec![false, true, false, false, false],
        episode_ids: vec![4, 4, 9, 9, 9],
        rewards: Some(vec![1.0, 2.0, 0.5, 0.5, 1.0]),
        costs: None,
    })
    .unwrap();
    let s = stats(&d);
    assert_eq!((s.transitions, s.episodes, s.terminal_episodes), (5, 2, 1));
    assert_eq!(s.episode_length, Summary { count: 2, mean: 2.5, std: 0.5, min: 2.0, max: 3.0 });
    // Episode returns 3 and 2: mean 2.5, population std 0.5.
    assert_eq!(
        s.episode_return,
        Some(Summary { count: 2, mean: 2.5, std: 0.5, min: 2.0, max: 3.0 })
    );
    assert_eq!(s.episode_cost, None);
    let json = serde_json::to_value(&s).unwrap();
    assert_eq!(json["episode_return"]["mean"], 2.5);
    assert!(json["episode_cost"].is_null());
}

#[test]
fn json_decimal_form_of_every_sampled_f32_parses_back_to_the_same_bits() {
    // The JSONL reader parses numbers through serde_json (decimal -> f64 -> f32); the writer
    // prints the shortest f32 decimal. Double rounding must never change a value.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..200_000 {
        let v = f32::from_bits(rng.random());
        if !v.is_finite() {
            continue;
        }
        let text = serde_json::to_string(&v).unwrap();
        let back: f32 = serde_json::from_str(&text).unwrap();
        assert_eq!(v.to_bits(), back.to_bits(), "{v:e} written as {text}");
    }
}
