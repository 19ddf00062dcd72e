//! `safedice datagen` end to end: the binary writes files that the upload parsers accept and
//! that hold exactly the generated data, plus a manifest that describes them.

use std::path::Path;
use std::process::Command;

use safedice::data::{parse_file, Format};
use safedice::envs::{generate, DatagenSpec};

fn datagen(env: &str, format: &str, out: &Path) {
    let status = Command::new(env!("CARGO_BIN_EXE_safedice"))
        .args(["datagen", "--env", env, "--preferred", "5", "--non-preferred", "4"])
        .args(["--labeled", "3", "--seed", "2", "--format", format, "--out"])
        .arg(out)
        .status()
        .unwrap();
    assert!(status.success());
}

fn spec(env: &str) -> DatagenSpec {
    DatagenSpec { env: env.into(), preferred: 5, non_preferred: 4, labeled: 3, seed: 2 }
}

#[test]
fn npz_files_round_trip_to_the_generated_sets() {
    let dir = tempfile::tempdir().unwrap();
    for env in ["six-rooms", "point-goal", "cartpole-slider"] {
        let out = dir.path().join(env);
        datagen(env, "npz", &out);
        let expected = generate(&spec(env)).unwrap();
        let (format, unlabeled) = parse_file(&out.join("unlabeled.npz"), "unlabeled.npz").unwrap();
        assert_eq!(format, Format::Npz);
        assert_eq!(unlabeled, expected.unlabeled, "{env}");
        let (_, labeled) = parse_file(&out.join("non_preferred.npz"), "non_preferred.npz").unwrap();
        assert_eq!(Some(labeled), expected.labeled_non_preferred, "{env}");

        let manifest: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("manifest.json")).unwrap()).unwrap();
        assert_eq!(manifest["spec"]["env"], env);
        assert_eq!(manifest["spec"]["seed"], 2);
        assert_eq!(manifest["unlabeled_preferred"]["episodes"], 5);
        assert_eq!(manifest["unlabeled_non_preferred"]["episodes"], 4);
        assert_eq!(manifest["labeled_non_preferred"]["episodes"], 3);
        assert_eq!(manifest["unlabeled_non_preferred_episode_ids"].as_array().unwrap().len(), 4);
        assert_eq!(
            manifest["files"],
            serde_json::json!(["unlabeled.npz", "non_preferred.npz", "manifest.json"])
        );
        let threshold = manifest["reference"]["cost_threshold"].as_f64().unwrap();
        assert!(threshold > manifest["reference"]["preferred_cost"].as_f64().unwrap());
    }
}

#[test]
fn jsonl_files_parse_back_to_the_same_transitions() {
    let dir = tempfile::tempdir().unwrap();
    datagen("point-goal", "jsonl", dir.path());
    let expected = generate(&spec("point-goal")).unwrap();
    let (format, unlabeled) =
        parse_file(&dir.path().join("unlabeled.jsonl"), "unlabeled.jsonl").unwrap();
    assert_eq!(format, Format::Jsonl);
    assert_eq!(unlabeled, expected.unlabeled);
}

#[test]
fn unknown_env_and_empty_unlabeled_set_fail_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_safedice"))
            .args(["datagen", "--out"])
            .arg(dir.path())
            .args(args)
            .output()
            .unwrap()
    };
    let out = run(&["--env", "walker"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("invalid value 'walker' for '--env <ENV>'"), "{stderr}");
    assert!(
        stderr.contains("[possible values: six-rooms, point-goal, cartpole-slider]"),
        "{stderr}"
    );
    let out = run(&["--env", "six-rooms", "--preferred", "0", "--non-preferred", "0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("at least one episode"));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "nothing written");
}
