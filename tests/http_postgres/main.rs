//! The HTTP suite of `tests/http` on the PostgreSQL store: the same test files, each server on a
//! fresh database of this process's throwaway cluster (`support::postgres`) instead of a SQLite
//! file. Left out: `crash_resume` (it kills `safedice serve` on a SQLite data directory; the
//! PostgreSQL takeover is `tests/fleet`), `demo` (its own in-process SQLite service) and
//! `openapi` (the same for both stores).
//!
//! Without PostgreSQL's binaries these tests say so loudly and run on SQLite; CI sets
//! `SAFEDICE_REQUIRE_POSTGRES=1`, which makes that a failure.

/// The store every test server of this binary uses (`SAFEDICE_TEST_DATABASE` overrides it).
const TEST_DATABASE: &str = "postgres";

#[path = "../support"]
mod support {
    pub mod app;
    pub mod jobs;
    pub mod postgres;
    pub mod server_log;
    #[allow(dead_code)]
    pub mod tasks;
}

#[path = "../http/algorithms.rs"]
mod algorithms;
#[path = "../http/concurrency.rs"]
mod concurrency;
#[path = "../http/datasets.rs"]
mod datasets;
#[path = "../http/envs.rs"]
mod envs;
#[path = "../http/evaluations.rs"]
mod evaluations;
#[path = "../http/experiments.rs"]
mod experiments;
#[path = "../http/hardening.rs"]
mod hardening;
#[path = "../http/jobs.rs"]
mod jobs;
#[path = "../http/lifecycle.rs"]
mod lifecycle;
#[path = "../http/models.rs"]
mod models;
#[path = "../http/ops.rs"]
mod ops;
#[path = "../http/resources.rs"]
mod resources;
#[path = "../http/restart.rs"]
mod restart;
#[path = "../http/ui.rs"]
mod ui;

/// Every file of `tests/http` runs here too unless it is named as left out above: a new file
/// registered only in `tests/http/main.rs` fails this test instead of silently never running on
/// PostgreSQL.
#[test]
fn every_http_test_file_runs_on_postgres_too() {
    const LEFT_OUT: [&str; 4] = ["main.rs", "crash_resume.rs", "demo.rs", "openapi.rs"];
    let registered = include_str!("main.rs");
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/http");
    let mut missing: Vec<String> = std::fs::read_dir(dir)
        .expect("tests/http")
        .map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| name.ends_with(".rs") && !LEFT_OUT.contains(&name.as_str()))
        .filter(|name| !registered.contains(&format!("#[path = \"../http/{name}\"]")))
        .collect();
    missing.sort();
    assert!(missing.is_empty(), "add to tests/http_postgres/main.rs (or to LEFT_OUT): {missing:?}");
}
