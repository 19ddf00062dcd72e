//! HDF5 uploads (DSRL's format), only with `--features hdf5`:
//! `cargo test --features hdf5 --test data hdf5::` (needs libhdf5, e.g.
//! `apt-get install libhdf5-dev`).
#![cfg(feature = "hdf5")]

use hdf5_metno as h5;
use safedice::data::{parse_file, ActionSpace, Actions, Format};

/// A DSRL-like file: float64 observations, bool terminals/timeouts (h5py's bool enum is what
/// `bool` maps to), float32 actions and costs.
fn dsrl_like(path: &std::path::Path, observations: &[f64]) {
    let file = h5::File::create(path).unwrap();
    let n = observations.len() / 2;
    let write_f64 = |name: &str, v: &[f64], shape: &[usize]| {
        file.new_dataset::<f64>().shape(shape).create(name).unwrap().write_raw(v).unwrap();
    };
    write_f64("observations", observations, &[n, 2]);
    let next: Vec<f64> = observations.iter().map(|x| x + 1.0).collect();
    write_f64("next_observations", &next, &[n, 2]);
    let actions: Vec<f32> = (0..n).map(|i| i as f32 / 10.0).collect();
    file.new_dataset::<f32>().shape([n, 1]).create("actions").unwrap().write_raw(&actions).unwrap();
    let terminals: Vec<bool> = (0..n).map(|i| i == 1).collect();
    let timeouts: Vec<bool> = (0..n).map(|i| i == n - 1).collect();
    file.new_dataset::<bool>()
        .shape([n])
        .create("terminals")
        .unwrap()
        .write_raw(&terminals)
        .unwrap();
    file.new_dataset::<bool>().shape([n]).create("timeouts").unwrap().write_raw(&timeouts).unwrap();
    let costs: Vec<f32> = (0..n).map(|i| (i % 2) as f32).collect();
    file.new_dataset::<f32>().shape([n]).create("costs").unwrap().write_raw(&costs).unwrap();
}

#[test]
fn hdf5_flat_layout_parses_like_npz() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dsrl.hdf5");
    dsrl_like(&path, &[0., 0., 1., 1., 2., 2., 3., 3.]);
    let (format, d) = parse_file(&path, "dsrl.hdf5").unwrap();
    assert_eq!(format, Format::Hdf5);
    assert_eq!(d.observations(), [0., 0., 1., 1., 2., 2., 3., 3.]);
    assert_eq!(d.next_observations()[..2], [1., 1.]);
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.0, 0.1, 0.2, 0.3]));
    assert_eq!(
        d.action_space(),
        &ActionSpace::Continuous { dim: 1, low: vec![-1.], high: vec![1.] }
    );
    assert_eq!(d.terminals(), [false, true, false, false]);
    assert_eq!(d.episode_ids(), [0, 0, 1, 1]);
    assert_eq!(d.costs(), Some(&[0., 1., 0., 1.][..]));
}

#[test]
fn hdf5_rejects_non_finite_values_and_truncation_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.h5");
    dsrl_like(&path, &[0., 0., 1., f64::NAN, 2., 2., 3., 3.]);
    let err = parse_file(&path, "bad.h5").unwrap_err();
    assert_eq!(err.code, "invalid_dataset");
    assert!(err.message.contains("`observations`: row 1"), "{}", err.message);

    dsrl_like(&path, &[0.; 8]);
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let err = parse_file(&path, "bad.h5").unwrap_err();
    assert_eq!(err.code, "invalid_dataset");
    assert!(err.message.contains("truncated or corrupt"), "{}", err.message);
}

/// tests/fixtures/make_hdf5_fixture.py: written by h5py (HDF5 2.0), gzip-compressed datasets,
/// h5py's bool enum.
#[test]
fn hdf5_written_by_h5py() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dsrl_like.hdf5");
    let (format, d) = parse_file(&path, "dsrl_like.hdf5").unwrap();
    assert_eq!(format, Format::Hdf5);
    let obs: Vec<f32> = (0..12).map(|x| x as f32 / 2.0).collect();
    assert_eq!(d.observations(), obs);
    assert_eq!(d.next_observations(), obs.iter().map(|x| x + 0.5).collect::<Vec<_>>());
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.5, -0.5, 0.25, 1.0]));
    assert_eq!(d.terminals(), [false, true, false, false]);
    assert_eq!(d.episode_ids(), [0, 0, 1, 1]);
    assert_eq!(d.rewards(), Some(&[1., 2., 3., 4.][..]));
    assert_eq!(d.costs(), Some(&[0., 1., 1., 0.][..]));
}
