//! safedice: offline safe imitation learning (SafeDICE, NeurIPS 2023) as a service.
//!
//! - [`config`]: the settings of `safedice serve`.
//! - [`server`]: starting and stopping the service.
//! - [`logging`]: the process's log output (never blocks or fails the service).
//! - [`algo`]: the learning algorithms on candle (no HTTP or SQL).
//! - [`domain`]: typed ids, job and evaluation lifecycles, the records the store hands out.
//! - [`data`]: the dataset model, upload parsers and validation.
//! - [`envs`]: built-in benchmark environments, demonstrators and evaluation metrics.
//! - [`demo`]: `safedice demo`, the whole service driven over HTTP in one command.
//! - [`bench`]: `safedice bench`, the paper's comparison on the built-in environments.
//! - [`serving`]: trained policies kept loaded for serving actions, and the act path every
//!   transport shares.
//! - [`store`]: all SQL and artefact storage.
//! - [`jobs`]: the training queue and worker pool.
//! - [`http`]: the HTTP API, one module per resource, and the dashboard at `/`.
//! - [`grpc`]: the Open Inference Protocol over gRPC (`serve --grpc-bind`).
//! - [`charts`]: server-side SVG charts for the dashboard.
//! - [`text`]: bounded messages (errors that quote client input stay short).

/// The commit this binary was built from, `+modified` when its sources differed from it
/// (build.rs; "unknown" when built outside a git checkout).
pub const BUILD_COMMIT: &str = env!("SAFEDICE_BUILD_COMMIT");

/// `safedice --version`: the package version and [`BUILD_COMMIT`].
pub const VERSION: &str =
    concat!(env!("CARGO_PKG_VERSION"), " (", env!("SAFEDICE_BUILD_COMMIT"), ")");

pub mod algo;
pub mod bench;
pub mod charts;
pub mod config;
pub mod data;
pub mod demo;
pub mod domain;
pub mod envs;
pub mod grpc;
pub mod http;
pub mod jobs;
pub mod logging;
pub mod lttb;
pub mod server;
pub mod serving;
pub mod store;
pub mod text;
pub mod worker;
