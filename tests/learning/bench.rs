//! A tiny benchmark run in-process (the CI smoke test of `safedice bench`): every algorithm on
//! six-rooms with small networks and few iterations. Checks the report's shape and that every
//! number in it is finite, not the algorithms' quality (that is bench/results.md's job).

use clap::Parser;
use safedice::algo::Algorithm;
use safedice::bench::{self, BenchArgs, BenchConfig, DataSize, Variant};

fn tiny_config() -> BenchConfig {
    let mut config = BenchConfig::quick();
    config.envs = vec!["six-rooms".to_string()];
    config.seeds = 2;
    config.iterations = 20;
    config.data = DataSize { preferred: 6, non_preferred: 6, labeled: 3 };
    config.eval_episodes = 10;
    config.record_every = 5;
    config.overrides.insert("batch_size".into(), 32.into());
    config.overrides.insert("hidden_sizes".into(), serde_json::json!([16, 16]));
    config
}

#[test]
fn tiny_bench_reports_every_algorithm_with_finite_numbers() {
    let config = tiny_config();
    let results = bench::run(&config).unwrap();
    assert_eq!(results.runs.len(), Algorithm::ALL.len() * 2);
    let summary = bench::summarize(&results);
    let env = &summary.envs[0];
    assert_eq!(env.env, "six-rooms");
    assert_eq!(
        env.rows.iter().map(|r| r.algorithm).collect::<Vec<_>>(),
        Algorithm::ALL.to_vec(),
        "one row per algorithm, in order"
    );
    for row in &env.rows {
        assert_eq!(row.seeds, 2);
        for stat in [
            row.normalized_return,
            row.average_cost,
            row.cost_violation_ratio,
            row.cvar_50,
            row.cvar_20,
            row.cvar_10,
            row.cvar_5,
            row.normalized_cost,
        ] {
            assert!(stat.mean.is_finite() && stat.se.is_finite(), "{row:?}");
        }
        assert!((0.0..=1.0).contains(&row.cost_violation_ratio.mean));
        // CVaR over a smaller worst share can only be higher.
        assert!(row.cvar_5.mean >= row.cvar_50.mean - 1e-9, "{row:?}");
        assert_eq!(row.alpha_hat.is_some(), row.algorithm == Algorithm::Safedice);
    }
    let alpha = results.runs[0].alpha.as_ref().expect("SafeDICE runs first in config order");
    assert!(alpha.alpha_hat.is_finite() && alpha.min_ratio.is_finite(), "{alpha:?}");
    assert!(env.safedice_vs_bc.as_ref().is_some_and(|c| c.cost_ratio.is_finite()));

    let dir = tempfile::tempdir().unwrap();
    bench::write_outputs(&results, &summary, dir.path(), "safedice bench (test)").unwrap();
    let md = std::fs::read_to_string(dir.path().join("results.md")).unwrap();
    assert!(md.contains("Command: `safedice bench (test)`"));
    // The CPU is named (speed ratios change between machines).
    let machine = md.lines().find_map(|l| l.strip_prefix("- Machine: ")).expect("a machine line");
    assert!(machine.contains("cores") && !machine.starts_with('?'), "{machine}");
    for name in ["SafeDICE", "BC", "DWBC", "PPL", "DExperts"] {
        let rows = md.lines().filter(|l| l.starts_with(&format!("| {name} |"))).count();
        assert_eq!(rows, 1, "one table row for {name}\n{md}");
    }
    assert!(!md.contains("NaN") && !md.contains("inf"), "{md}");
    let svg = std::fs::read_to_string(dir.path().join("six-rooms.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    assert_eq!(svg.matches(r#"<g class="point""#).count(), Algorithm::ALL.len(), "a point each");
    assert_eq!(svg.matches(r#"<g class="error-bars""#).count(), Algorithm::ALL.len());
    for algorithm in Algorithm::ALL {
        let color = safedice::charts::algorithm_color(algorithm);
        assert!(svg.contains(&format!(r#"fill="{color}""#)), "{algorithm:?} in its accent colour");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("results.json")).unwrap()).unwrap();
    assert_eq!(json["results"]["runs"].as_array().unwrap().len(), 10);
}

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    bench: BenchArgs,
}

fn parse(args: &[&str]) -> Result<BenchConfig, String> {
    let cli = Cli::try_parse_from(std::iter::once("bench").chain(args.iter().copied()))
        .map_err(|e| e.to_string())?;
    cli.bench.to_config().map_err(|e| e.to_string())
}

#[test]
fn arguments_select_envs_algorithms_and_modes() {
    let full = parse(&[]).unwrap();
    assert_eq!(full.envs, ["six-rooms", "point-goal", "cartpole-slider"]);
    assert_eq!((full.iterations, full.seeds, full.eval_episodes), (1_000_000, 5, 500));
    assert_eq!(full.data, DataSize::PAPER);
    let quick = parse(&["--quick", "--envs", "point-goal", "--algorithms", "safedice,bc"]).unwrap();
    assert_eq!(quick.envs, ["point-goal"]);
    assert_eq!(quick.algorithms, [Algorithm::Safedice, Algorithm::Bc]);
    assert_eq!(quick.data, DataSize::QUICK);
    assert_eq!(
        quick.training_config(Algorithm::Bc, Variant::Standard, 0)["batch_size"],
        256,
        "quick runs small networks"
    );
    assert!(
        full.training_config(Algorithm::Bc, Variant::Standard, 0).get("batch_size").is_none(),
        "full runs the service's"
    );
    let custom = parse(&["--quick", "--iterations", "7", "--hidden-sizes", "8,8"]).unwrap();
    assert_eq!(custom.iterations, 7);
    assert_eq!(
        custom.training_config(Algorithm::Bc, Variant::Standard, 3)["hidden_sizes"],
        serde_json::json!([8, 8])
    );
    assert_eq!(custom.training_config(Algorithm::Bc, Variant::Standard, 3)["seed"], 3);

    let err = parse(&["--envs", "walker"]).unwrap_err();
    assert!(err.contains("unknown environment `walker`"), "{err}");
    let err = parse(&["--algorithms", "safedice,sac"]).unwrap_err();
    assert!(err.contains("unknown algorithm `sac`"), "{err}");
    assert!(parse(&["--seed-count", "0"]).unwrap_err().contains("--seed-count"));
    // The former spellings stay accepted.
    assert!(parse(&["--seeds", "0"]).unwrap_err().contains("--seed-count"));
    assert!(parse(&["--threads", "0"]).unwrap_err().contains("--parallel"));
    assert!(parse(&["--labeled", "0"]).unwrap_err().contains("--labeled"));
    assert!(parse(&["--algorithms", "bc", "--labeled", "0"]).is_ok(), "BC needs no D^N");
    assert!(!full.ablations && !quick.ablations, "ablation rows only on request");
    assert!(parse(&["--quick", "--ablations"]).unwrap().ablations);
    let err = parse(&["--algorithms", "bc", "--labeled", "0", "--ablations"]).unwrap_err();
    assert!(err.contains("--ablations"), "SafeDICE's ablations need D^N: {err}");

    // SafeDICE's ablation rows come with SafeDICE; BC (preferred only) with any algorithm.
    let bc_only = parse(&["--quick", "--algorithms", "bc", "--ablations"]).unwrap();
    let rows: Vec<_> = bc_only.rows().into_iter().map(|(a, v)| v.label(a)).collect();
    assert_eq!(rows, ["BC", "BC (preferred only)"]);
    // A --config key reaches the algorithms that have it, and only those.
    let gp = parse(&["--algorithms", "safedice", "--ablations", "--config", r#"{"nu_gp": 0.5}"#])
        .unwrap();
    assert_eq!(gp.training_config(Algorithm::Safedice, Variant::Standard, 0)["nu_gp"], 0.5);
    assert!(gp.training_config(Algorithm::Bc, Variant::Standard, 0).get("nu_gp").is_none());
    let err = parse(&["--algorithms", "safedice", "--config", r#"{"eta": 0.3}"#]).unwrap_err();
    assert!(err.contains("`eta` belongs to none of the selected algorithms"), "{err}");
}

/// A run's results with what differs between two invocations of the same trainings (their
/// times, the wall clock, the commit) left out.
fn trained(results: &bench::BenchResults) -> Vec<serde_json::Value> {
    let mut runs = serde_json::to_value(&results.runs).unwrap();
    for run in runs.as_array_mut().unwrap() {
        let run = run.as_object_mut().unwrap();
        run.remove("train_seconds");
        run.remove("eval_seconds");
    }
    runs.as_array().unwrap().clone()
}

#[test]
fn a_run_cut_short_resumes_to_the_results_of_one_that_never_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("runs.jsonl");
    let mut config = tiny_config();
    config.algorithms = vec![Algorithm::Safedice, Algorithm::Bc];
    config.runs_log = Some(log.clone());
    let whole = bench::run(&config).unwrap();
    assert_eq!((whole.runs.len(), whole.resumed_runs), (4, 0));
    let recorded = std::fs::read_to_string(dir.path().join("bench-config.json")).unwrap();
    assert!(recorded.contains("\"iterations\": 20") && !recorded.contains("threads"), "{recorded}");

    // Cut short after two trainings, the third one's line half written.
    let lines: Vec<String> =
        std::fs::read_to_string(&log).unwrap().lines().map(String::from).collect();
    assert_eq!(lines.len(), 4, "one line per training");
    let cut = format!("{}\n{}\n{}", lines[0], lines[1], &lines[2][..lines[2].len() / 2]);
    std::fs::write(&log, cut).unwrap();

    let resumed_config = BenchConfig { resume: true, threads: 1, ..config.clone() };
    let resumed = bench::run(&resumed_config).unwrap();
    assert_eq!(resumed.resumed_runs, 2);
    assert_eq!(trained(&resumed), trained(&whole), "the same trainings, the same numbers");
    let summary = bench::summarize(&resumed);
    bench::write_outputs(&resumed, &summary, dir.path(), "safedice bench --resume").unwrap();
    let md = std::fs::read_to_string(dir.path().join("results.md")).unwrap();
    assert!(md.contains("resumed: 2 of the 4 trainings kept"), "{md}");
    let again = bench::run(&resumed_config).unwrap();
    assert_eq!(
        (again.resumed_runs, trained(&again)),
        (4, trained(&whole)),
        "the log is whole again"
    );

    // A resume may add seeds: the kept trainings stay, the new seed's are trained.
    let more_seeds = BenchConfig { resume: true, seeds: 3, ..config.clone() };
    let grown = bench::run(&more_seeds).unwrap();
    assert_eq!((grown.resumed_runs, grown.runs.len()), (4, 6));
    let mut kept_sorted: Vec<_> =
        trained(&grown).into_iter().filter(|run| run["seed"].as_u64() < Some(2)).collect();
    let mut whole_sorted = trained(&whole);
    let key = |run: &serde_json::Value| format!("{}{}", run["algorithm"], run["seed"]);
    kept_sorted.sort_by_key(key);
    whole_sorted.sort_by_key(key);
    assert_eq!(kept_sorted, whole_sorted, "the kept seeds are the first run's trainings");
    // ... and may not drop any: their trainings are in the log.
    let fewer_seeds = BenchConfig { resume: true, seeds: 1, ..config };
    let refused = bench::run(&fewer_seeds).unwrap_err().to_string();
    assert!(refused.contains("differs in seeds"), "{refused}");
}
