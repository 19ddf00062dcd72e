//! HDF5 uploads, read in pure Rust in every build, from files h5py wrote
//! (tests/fixtures/make_hdf5_fixture.py): DSRL's layout, D4RL's (no `next_observations`,
//! chunked gzip with shuffle, `infos/` and `metadata/` groups), integer columns of several
//! widths; and corrupt files refused with a message, never a panic.

use std::path::{Path, PathBuf};

use safedice::data::{parse_file, ActionSpace, Actions, Format};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

/// DSRL's layout: gzip-compressed datasets, h5py's bool enum, float64 observations.
#[test]
fn a_dsrl_file_written_by_h5py_parses_column_for_column() {
    let (format, d) = parse_file(&fixture("dsrl_like.hdf5"), "dsrl_like.hdf5").unwrap();
    assert_eq!(format, Format::Hdf5);
    let obs: Vec<f32> = (0..12).map(|x| x as f32 / 2.0).collect();
    assert_eq!(d.observations(), obs);
    assert_eq!(d.next_observations(), obs.iter().map(|x| x + 0.5).collect::<Vec<_>>());
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.5, -0.5, 0.25, 1.0]));
    assert_eq!(d.terminals(), [false, true, false, false]);
    assert_eq!(d.episode_ids(), [0, 0, 1, 1]);
    assert_eq!(d.rewards(), Some(&[1., 2., 3., 4.][..]));
    assert_eq!(d.costs(), Some(&[0., 1., 1., 0.][..]));
    assert_eq!(d.warnings(), [] as [String; 0]);
}

/// D4RL's layout: the next observation is the next row's within an episode; the transitions
/// that end an episode at a timeout (row 7) or at the end of the file (row 9) have none in the
/// file and are dropped; the terminal one (row 3) keeps its own. The groups are left unread,
/// and both facts are reported.
#[test]
fn a_d4rl_file_without_next_observations_derives_them_and_says_what_it_dropped() {
    let (format, d) = parse_file(&fixture("d4rl_like.hdf5"), "hopper.hdf5").unwrap();
    assert_eq!(format, Format::Hdf5);
    let row = |i: usize| [3 * i, 3 * i + 1, 3 * i + 2].map(|v| v as f32);
    let kept = [0, 1, 2, 3, 4, 5, 6, 8];
    assert_eq!(d.observations(), kept.iter().flat_map(|&i| row(i)).collect::<Vec<_>>());
    let successors = [1, 2, 3, 3, 5, 6, 7, 9];
    assert_eq!(d.next_observations(), successors.iter().flat_map(|&i| row(i)).collect::<Vec<_>>());
    assert_eq!(d.episode_ids(), [0, 0, 0, 0, 1, 1, 1, 2]);
    assert_eq!(d.terminals(), [false, false, false, true, false, false, false, false]);
    assert_eq!(d.rewards(), Some(&[0., 1., 2., 3., 4., 5., 6., 8.][..]));
    let Actions::Continuous(actions) = d.actions() else { panic!("continuous actions") };
    let all: Vec<f32> = (0..20).map(|i| -1.0 + 2.0 * i as f32 / 19.0).collect();
    let expected: Vec<f32> = kept.iter().flat_map(|&i| [all[2 * i], all[2 * i + 1]]).collect();
    for (a, b) in actions.iter().zip(&expected) {
        assert!((a - b).abs() < 1e-6, "{actions:?}");
    }
    let warnings = d.warnings().join("\n");
    assert!(warnings.contains("2 of the 10 transitions end an episode without being terminal"));
    assert!(warnings.contains("groups `infos/`, `metadata/` were not read"), "{warnings}");
}

/// Integer actions (int64) are discrete, uint8 flags and int16 episode ids read as integers.
#[test]
fn integer_columns_of_any_width_are_read() {
    let (_, d) = parse_file(&fixture("discrete_like.hdf5"), "discrete_like.h5").unwrap();
    assert_eq!(d.actions(), &Actions::Discrete(vec![0, 2, 1, 2]));
    assert_eq!(d.action_space(), &ActionSpace::Discrete { n: 3 });
    assert_eq!(d.terminals(), [false, true, false, true]);
    assert_eq!(d.episode_ids(), [0, 0, 1, 1]);
    assert!(d.warnings()[0].starts_with("no `next_observations`"), "{:?}", d.warnings());
}

/// Truncated, scrambled and random files: an `invalid_dataset` naming the problem, no panic.
#[test]
fn corrupt_files_are_refused_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture("d4rl_like.hdf5")).unwrap();
    let mut cases = vec![("truncated", bytes[..bytes.len() / 2].to_vec())];
    let mut scrambled = bytes.clone();
    for (i, b) in scrambled.iter_mut().enumerate().skip(600).step_by(7).take(400) {
        *b ^= (i as u8).wrapping_mul(31) | 1;
    }
    cases.push(("scrambled", scrambled));
    let mut random: Vec<u8> = b"\x89HDF\r\n\x1a\n".to_vec();
    random.extend((0..4096u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8));
    cases.push(("random", random));
    for (name, content) in cases {
        let path = dir.path().join(format!("{name}.hdf5"));
        std::fs::write(&path, content).unwrap();
        match parse_file(&path, &format!("{name}.hdf5")) {
            Err(err) => assert_eq!(err.code, "invalid_dataset", "{name}: {}", err.message),
            // A scramble may miss every byte that matters; what it reads must still be a dataset.
            Ok((_, d)) => assert!(name == "scrambled" && !d.is_empty(), "{name} parsed"),
        }
    }
}
