//! The robustness suite at CI size (`safedice bench --suite robustness`): one task of every
//! family, every row, a tiny budget. Checks the plumbing (every task trained and scored, the
//! report written) and determinism (the same run twice gives the same numbers), not the numbers
//! themselves: the full run is a benchmark (bench/robustness/).

use safedice::algo::Algorithm;
use safedice::bench::robustness;
use safedice::envs::suite::Split;

fn tiny() -> safedice::bench::BenchConfig {
    let mut config = robustness::default_config();
    config.seeds = 1;
    config.iterations = 30;
    config.eval_episodes = 4;
    config.record_every = 10;
    config.overrides.insert("batch_size".into(), 32.into());
    config.overrides.insert("hidden_sizes".into(), serde_json::json!([16, 16]));
    config.overrides.insert("discriminator_early_stopping".into(), true.into());
    config
}

fn first_four() -> robustness::Selection<'static> {
    robustness::Selection { splits: &[Split::Dev], count: 4, families: vec![] }
}

#[test]
fn ci_sized_suite_trains_scores_and_reports_every_task_deterministically() {
    let dir = tempfile::tempdir().unwrap();
    let written =
        robustness::run_cli(tiny(), &first_four(), dir.path(), "safedice bench (test)").unwrap();
    assert_eq!(written.len(), 2);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("results.json")).unwrap()).unwrap();
    let tasks = json["tasks"].as_array().unwrap();
    let families: Vec<&str> =
        tasks.iter().map(|t| t["family"]["family"].as_str().unwrap()).collect();
    assert_eq!(families, ["grid", "grid", "nav", "pace"], "one task of each family");
    // Rows: SafeDICE, SafeDICE (paper preset), DWBC, PPL, scored against BC on every task.
    let scores = json["scores"].as_array().unwrap();
    assert_eq!(scores.len(), 4 * 4, "{scores:?}");
    let runs = json["results"]["runs"].as_array().unwrap();
    // 4 algorithms + the paper row + BC (preferred only), one seed, four tasks.
    assert_eq!(runs.len(), 4 * 6);
    for s in scores {
        assert!(s["cost"].as_f64().unwrap().is_finite(), "{s}");
        assert!(s["worse_than_bc"].is_boolean());
    }
    let rows = json["rows"].as_array().unwrap();
    assert!(rows.iter().all(|r| r["split"] == "dev" && r["tasks"] == 4), "{rows:?}");
    let md = std::fs::read_to_string(dir.path().join("results.md")).unwrap();
    assert!(md.contains("- Command: `safedice bench (test)`"), "{md}");
    for id in ["dev-00-grid", "dev-01-grid-continuing", "dev-02-nav", "dev-03-pace"] {
        assert!(md.contains(&format!("| {id} |")), "{id} in the task table\n{md}");
    }

    // Determinism: the same configuration again gives the same metrics for every run.
    let again = tempfile::tempdir().unwrap();
    robustness::run_cli(tiny(), &first_four(), again.path(), "again").unwrap();
    let json2: serde_json::Value =
        serde_json::from_slice(&std::fs::read(again.path().join("results.json")).unwrap()).unwrap();
    let key = |r: &serde_json::Value| {
        (
            r["env"].to_string(),
            r["algorithm"].to_string(),
            r["variant"].to_string(),
            r["seed"].to_string(),
        )
    };
    let metrics = |j: &serde_json::Value| {
        let mut v: Vec<_> = j["results"]["runs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| (key(r), r["metrics"].to_string()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(metrics(&json), metrics(&json2));
    assert!(runs.iter().any(|r| r["algorithm"] == serde_json::json!(Algorithm::Safedice)));
}

/// The paper's tabular check (Appendix G) pinned: on six-rooms, solved exactly, SafeDICE with
/// the service defaults leaves the cost rooms that BC (which follows the unlabeled mixture)
/// enters, as the paper's figure shows, and still reaches the goal; its alpha-hat's interval
/// holds the true non-preferred share (bench/robustness/tabular.md).
#[test]
fn tabular_check_safedice_avoids_the_cost_rooms_bc_enters() {
    use safedice::bench::tabular;
    let data = tabular::data(0).unwrap();
    let defaults = serde_json::json!({});
    let bc = tabular::solve(Algorithm::Bc, &defaults, &data, 4000, 0).unwrap().outcome;
    let safedice = tabular::solve(Algorithm::Safedice, &defaults, &data, 4000, 0).unwrap();
    assert!(
        bc.expected_cost > 3.0,
        "BC follows the mixture into the cost rooms: {}",
        bc.expected_cost
    );
    let cost = safedice.outcome.expected_cost;
    assert!(cost < 0.2 * bc.expected_cost, "SafeDICE {cost} against BC {}", bc.expected_cost);
    assert!(safedice.outcome.goal_probability > 0.9, "{}", safedice.outcome.goal_probability);
    let truth = tabular::true_share(0).unwrap();
    let (lower, upper) = safedice.alpha_hat_interval.expect("bbe reports an interval");
    assert!(lower <= truth && truth <= upper, "true share {truth} outside [{lower}, {upper}]");
}
