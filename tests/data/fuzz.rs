//! Damaged uploads never panic the parser: seeded random truncations, byte flips and insertions
//! of valid files in every format either parse into a dataset (consistent: `Dataset::new` built
//! it) or are rejected with a `ParseError` (same for the canonical form). Plus the decode budget
//! that stops an archive whose arrays claim far more data than the file could hold.

use std::io::Write;
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::data::{
    decode_canonical, encode_canonical, parse_file, write_csv, write_jsonl, write_npz, ActionSpace,
    Actions, Dataset, DatasetParts,
};

type Writer = fn(&Dataset, &Path) -> std::io::Result<()>;

fn small_dataset(discrete: bool) -> Dataset {
    let n = 12;
    Dataset::new(DatasetParts {
        obs_dim: 3,
        action_space: if discrete {
            ActionSpace::Discrete { n: 4 }
        } else {
            ActionSpace::infer_continuous(&[0.5; 24], 2)
        },
        observations: (0..n * 3).map(|x| x as f32 * 0.37).collect(),
        actions: if discrete {
            Actions::Discrete((0..n as u32).map(|i| i % 4).collect())
        } else {
            Actions::Continuous(vec![0.5; n * 2])
        },
        next_observations: (0..n * 3).map(|x| x as f32 * 0.37 + 1.0).collect(),
        terminals: (0..n).map(|i| i == 5 || i == n - 1).collect(),
        episode_ids: (0..n).map(|i| if i < 6 { 2 } else { 9 }).collect(),
        rewards: Some(vec![1.0; n]),
        costs: Some((0..n).map(|i| (i % 2) as f32).collect()),
    })
    .unwrap()
}

fn mutate(rng: &mut impl Rng, bytes: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    match rng.random_range(0..4) {
        0 => out.truncate(rng.random_range(0..bytes.len())),
        1 => {
            for _ in 0..rng.random_range(1..4) {
                let i = rng.random_range(0..out.len());
                out[i] ^= 1 << rng.random_range(0..8);
            }
        }
        2 => {
            let i = rng.random_range(0..out.len());
            const SYNTAX: &[u8] = b"0,.-e9{}[]\n\"x ";
            out.insert(i, SYNTAX[rng.random_range(0..SYNTAX.len())]);
        }
        _ => {
            let i = rng.random_range(0..out.len());
            out[i] = rng.random();
        }
    }
    out
}

#[test]
fn damaged_files_are_rejected_or_valid_never_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let writers: [(&str, Writer); 3] =
        [("d.jsonl", write_jsonl), ("d.csv", write_csv), ("d.npz", write_npz)];
    for discrete in [false, true] {
        let d = small_dataset(discrete);
        for (name, write) in writers {
            let path = dir.path().join(name);
            write(&d, &path).unwrap();
            let original = std::fs::read(&path).unwrap();
            for _ in 0..100 {
                let damaged = mutate(&mut rng, &original);
                std::fs::File::create(&path).unwrap().write_all(&damaged).unwrap();
                // Whatever parses is consistent: a Dataset is only built by Dataset::new.
                if let Ok((_, parsed)) = parse_file(&path, name) {
                    assert!(!parsed.is_empty());
                }
            }
        }
        let canonical = encode_canonical(&d);
        for _ in 0..300 {
            if let Ok(decoded) = decode_canonical(&mutate(&mut rng, &canonical)) {
                assert!(!decoded.is_empty());
            }
        }
    }
}

/// An NPZ whose `observations` header claims 10^9 × 64 float64 values in a tiny file.
#[test]
fn arrays_claiming_more_data_than_the_file_can_hold_are_refused_before_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.npz");
    let mut header =
        "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000, 64), }".to_string();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((header.len() as u16).to_le_bytes());
    npy.extend(header.as_bytes());
    let mut zip = npyz::zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
    zip.start_file("observations.npy", npyz::zip::write::FileOptions::default()).unwrap();
    zip.write_all(&npy).unwrap();
    zip.finish().unwrap();
    let err = parse_file(&path, "bomb.npz").unwrap_err();
    assert_eq!(err.code, "invalid_dataset");
    assert!(
        err.message.contains("`observations` would decode to 512000000000 bytes"),
        "{}",
        err.message
    );
}
