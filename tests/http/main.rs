//! The service through the real server: every HTTP resource, the job runner's crash recovery
//! (the `safedice serve` binary killed and restarted) and `safedice demo`. One binary because
//! these tests share what they need, the server harness (`support::app`) and the job helpers
//! (`support::jobs`), and nothing process-wide: each test runs its own server on its own port and
//! data directory, and what measures memory or is killed runs in a child process.
//!
//! `SAFEDICE_TEST_DATABASE=postgres cargo test --test http` runs the same suite on PostgreSQL
//! (one throwaway cluster for the process, a database per test; `support::postgres`).

#[path = "../support"]
mod support {
    pub mod app;
    pub mod jobs;
    pub mod postgres;
    // The jobs' datasets come from the training core's tasks; their training helpers are
    // tests/learning's.
    #[allow(dead_code)]
    pub mod tasks;
}

mod algorithms;
mod concurrency;
mod crash_resume;
mod datasets;
mod demo;
mod envs;
mod evaluations;
mod hardening;
mod jobs;
mod openapi;
mod ops;
mod resources;
mod ui;
