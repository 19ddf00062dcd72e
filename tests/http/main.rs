//! The service through the real server: every HTTP resource, the job runner's crash recovery
//! (the `safedice serve` binary killed and restarted) and `safedice demo`. One binary because
//! these tests share what they need, the server harness (`support::app`) and the job helpers
//! (`support::jobs`), and nothing process-wide: each test runs its own server on its own port and
//! data directory, and what measures memory or is killed runs in a child process.
//!
//! Every test runs on both stores: on SQLite in this process, then on PostgreSQL in a child
//! process of this binary that `on_postgres` starts (`SAFEDICE_TEST_DATABASE` picks one store).

/// The store every test server of this binary uses (`SAFEDICE_TEST_DATABASE` overrides it).
const TEST_DATABASE: &str = "sqlite";

#[path = "../support"]
mod support {
    pub mod app;
    pub mod jobs;
    pub mod postgres;
    pub mod server_log;
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
mod experiments;
mod grpc;
mod hardening;
mod jobs;
mod lifecycle;
mod models;
mod on_postgres;
mod openapi;
mod ops;
mod resources;
mod restart;
mod safety;
mod shadow;
mod ui;
mod vocabulary;
