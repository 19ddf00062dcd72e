//! The PostgreSQL run of this binary: every test of it again, each server on a fresh database of
//! a throwaway cluster (`support::postgres`) instead of a SQLite file. Started by the one test
//! below as a child process of this same binary with `SAFEDICE_TEST_DATABASE=postgres`, so a new
//! test file runs on both stores without being registered anywhere else.
//!
//! Left out of the PostgreSQL run, by module: `crash_resume` (it kills `safedice serve` on a
//! SQLite data directory; the PostgreSQL takeover is `tests/fleet`), `demo` (its own in-process
//! SQLite service) and `openapi` (the same document for both stores).
//!
//! Run one store only: `cargo test --test http` with `SAFEDICE_TEST_DATABASE=sqlite` or
//! `=postgres` (this test then does nothing; a filter such as `jobs::` works as usual).

use std::process::Command;

use crate::support::postgres;

/// Modules whose tests run on SQLite only (see the module docs).
const SQLITE_ONLY: [&str; 3] = ["crash_resume::", "demo::", "openapi::"];

/// Where the child's whole output goes; `.ci/run` prints its summary line.
const LOG: &str = concat!(env!("CARGO_TARGET_TMPDIR"), "/http-on-postgres.log");

#[test]
fn every_test_of_this_binary_again_on_postgres() {
    if std::env::var_os("SAFEDICE_TEST_DATABASE").is_some() || !postgres::available() {
        return;
    }
    let mut child = Command::new(std::env::current_exe().expect("this test binary"));
    child.env("SAFEDICE_TEST_DATABASE", "postgres").args(["--skip", "on_postgres::"]);
    for module in SQLITE_ONLY {
        child.args(["--skip", module]);
    }
    // This test holds one of the parent's threads while the child runs, so the two processes
    // together run about as many tests at once as the parent alone would.
    if std::env::var_os("RUST_TEST_THREADS").is_none() {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        child.arg(format!("--test-threads={}", (cores / 2).max(1)));
    }
    let output = child.output().expect("run this test binary on PostgreSQL");
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    std::fs::write(LOG, format!("{text}{}", String::from_utf8_lossy(&output.stderr)))
        .expect("write the PostgreSQL run's log");
    let summary = text.lines().filter(|l| l.starts_with("test result")).collect::<Vec<_>>();
    println!("PostgreSQL run: {} (log: {LOG})", summary.join("; "));
    assert!(
        output.status.success(),
        "tests failed on PostgreSQL ({}); their output:\n{}",
        output.status,
        text.find("\nfailures:").map_or(text.as_str(), |at| &text[at..])
    );
    assert!(summary.iter().any(|l| !l.contains(" 0 passed")), "no test ran on PostgreSQL");
}
