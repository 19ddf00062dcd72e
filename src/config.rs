//! Configuration of `safedice serve`: every flag is also an environment variable `SAFEDICE_*`.

use std::net::SocketAddr;
use std::path::PathBuf;

use axum::http::HeaderValue;

pub const DEFAULT_BIND: &str = "127.0.0.1:8080";
pub const DEFAULT_DATA_DIR: &str = "./safedice-data";
/// 1 GiB.
pub const DEFAULT_MAX_UPLOAD_BYTES: u64 = 1 << 30;
pub const DEFAULT_MAX_CONNECTIONS: u32 = 1024;
/// A quarter of the connection slots: one address cannot take them all.
pub const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: u32 = 256;
/// `ModelStreamInfer` streams open at once: one per agent, as many as connections by default.
pub const DEFAULT_GRPC_MAX_STREAMS: u32 = 1024;
/// 4 GiB: about forty times what a default job (batch 512, two layers of 256) on a
/// 100k-transition dataset needs, so only configurations far off the defaults meet it.
pub const DEFAULT_MAX_JOB_MEMORY: u64 = 4 << 30;
/// 16 KiB/s: a 1 GiB upload may take up to 18 hours; a slower one holds an upload slot with
/// no prospect of finishing.
pub const DEFAULT_MIN_BODY_RATE: u64 = 16 << 10;
/// 1 GiB of loaded policies: thousands of default-sized ones (256-256 networks take ~0.3 MB),
/// or eight of the largest the memory estimate lets through.
pub const DEFAULT_POLICY_CACHE_BYTES: u64 = 1 << 30;
/// 1 GiB: room for one upload of the default --max-upload-bytes, and for thousands of
/// checkpoints of default-sized networks.
pub const DEFAULT_MIN_FREE_DISK: u64 = 1 << 30;
/// Long enough that a busy database or a garbage-collection pause does not lose a lease (three
/// heartbeats must fail in a row), short enough that a dead worker's job resumes within a
/// minute.
pub const DEFAULT_LEASE_SECONDS: u64 = 30;
const LEASE_SECONDS_RANGE: std::ops::RangeInclusive<u64> = 3..=3600;
pub use crate::domain::attempt::DEFAULT_MAX_ATTEMPTS;
const MAX_ATTEMPTS_RANGE: std::ops::RangeInclusive<i64> =
    1..=crate::domain::attempt::MOST_ATTEMPTS as i64;
pub const DEFAULT_RETRY_BACKOFF_SECS: u64 = crate::domain::RetryBackoff::DEFAULT_BASE.as_secs();

/// Log line format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// One JSON object per line, for log collectors.
    Json,
    /// Human-readable lines.
    Pretty,
}

/// Settings of the HTTP service. `Debug` shows whether tokens are set, never their values.
#[derive(Clone, clap::Args)]
pub struct ServeConfig {
    /// Address to listen on (IP:port; port 0 picks a free one). A non-loopback address needs
    /// --api-token, or --insecure-public to serve without one.
    #[arg(long, env = "SAFEDICE_BIND", default_value = DEFAULT_BIND)]
    pub bind: SocketAddr,

    /// Address of the Open Inference Protocol's gRPC service (IP:port; port 0 picks a free
    /// one), beside the HTTP API on --bind: Triton's inference.GRPCInferenceService, as
    /// tritonclient.grpc calls it, with the models, tokens (metadata `authorization: Bearer
    /// <token>`) and limits of /v2. Off when unset. A non-loopback address needs --api-token, as
    /// --bind does.
    #[arg(long, env = "SAFEDICE_GRPC_BIND")]
    pub grpc_bind: Option<SocketAddr>,

    /// gRPC `ModelStreamInfer` streams open at once on this server (one per agent; they can
    /// share connections, up to 200 per connection); one more is refused at once with
    /// RESOURCE_EXHAUSTED, so it can retry or fall back to unary calls.
    #[arg(long, env = "SAFEDICE_GRPC_MAX_STREAMS", default_value_t = DEFAULT_GRPC_MAX_STREAMS, value_parser = clap::value_parser!(u32).range(1..))]
    pub grpc_max_streams: u32,

    /// Directory for the SQLite database and the stored datasets (with --database-url: only
    /// uploads in flight); created on first start.
    #[arg(long, env = "SAFEDICE_DATA_DIR", default_value = DEFAULT_DATA_DIR)]
    pub data_dir: PathBuf,

    /// PostgreSQL database shared by every API node and worker, e.g.
    /// postgres://safedice:secret@db:5432/safedice. Without it the store is SQLite in
    /// --data-dir.
    #[arg(long, env = "SAFEDICE_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,

    /// Bearer token required on every /v1 and /v2 route. Without it the API is open and the
    /// server only listens on loopback.
    #[arg(long, env = "SAFEDICE_API_TOKEN", hide_env_values = true)]
    pub api_token: Option<String>,

    /// A second bearer token that may only call the action endpoints
    /// (POST /v1/policies/{id}/act and the /v2 inference protocol), for deployed agents.
    #[arg(long, env = "SAFEDICE_INFERENCE_TOKEN", hide_env_values = true)]
    pub inference_token: Option<String>,

    /// Allow a non-loopback --bind without --api-token (anyone who can reach the port can use
    /// the whole API).
    #[arg(long, env = "SAFEDICE_INSECURE_PUBLIC", value_parser = clap::builder::BoolishValueParser::new(), action = clap::ArgAction::SetTrue)]
    pub insecure_public: bool,

    /// Origin allowed to call the API from a browser (CORS), e.g. https://dash.example.com;
    /// repeat the flag (or comma-separate the variable) for several; `*` allows any origin.
    #[arg(long = "cors-origin", env = "SAFEDICE_CORS_ORIGIN", value_delimiter = ',')]
    pub cors_origins: Vec<String>,

    /// Largest accepted dataset upload in bytes; larger uploads get 413.
    #[arg(long, env = "SAFEDICE_MAX_UPLOAD_BYTES", default_value_t = DEFAULT_MAX_UPLOAD_BYTES)]
    pub max_upload_bytes: u64,

    /// Log format.
    #[arg(long, env = "SAFEDICE_LOG_FORMAT", value_enum, default_value_t = LogFormat::Pretty)]
    pub log_format: LogFormat,

    /// Client connections open at once (lowered to fit the process's open-file limit); more
    /// are answered 503 `too_many_connections` at once, so they can retry instead of hanging.
    #[arg(long, env = "SAFEDICE_MAX_CONNECTIONS", default_value_t = DEFAULT_MAX_CONNECTIONS, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_connections: u32,

    /// Client connections open at once from one IP address; more from it are answered 503
    /// `too_many_connections_from_address` at once, so one client (or a script holding idle
    /// sockets) cannot take every slot. Behind a reverse proxy every client has the proxy's
    /// address: raise it to --max-connections there.
    #[arg(long, env = "SAFEDICE_MAX_CONNECTIONS_PER_ADDRESS", default_value_t = DEFAULT_MAX_CONNECTIONS_PER_ADDRESS, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_connections_per_address: u32,

    /// Seconds a client may take to send a request's headers; also how long an idle
    /// keep-alive connection stays open.
    #[arg(long, env = "SAFEDICE_HEADER_TIMEOUT_SECS", default_value_t = 15, value_parser = clap::value_parser!(u64).range(1..))]
    pub header_timeout_secs: u64,

    /// Seconds a request body (an upload) may pause between two pieces before the request is
    /// abandoned with 408.
    #[arg(long, env = "SAFEDICE_BODY_IDLE_TIMEOUT_SECS", default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..))]
    pub body_idle_timeout_secs: u64,

    /// Seconds a response may wait on a client that reads none of it (a download read a byte a
    /// second, a stalled network) before the connection is closed: what the response held (a
    /// --max-heavy-reads slot, its memory) goes back. 0 waits for ever.
    #[arg(long, env = "SAFEDICE_SEND_STALL_TIMEOUT_SECS", default_value_t = 30)]
    pub send_stall_timeout_secs: u64,

    /// Bytes per second a request body (an upload) must average once it has been arriving for
    /// --body-idle-timeout-secs; a slower one is abandoned with 408 `request_too_slow`, so a
    /// body trickled a byte at a time cannot hold an upload slot for ever.
    #[arg(long, env = "SAFEDICE_MIN_BODY_RATE", default_value_t = DEFAULT_MIN_BODY_RATE)]
    pub min_body_rate: u64,

    /// Dataset uploads received at once; one more is answered 503 `too_many_uploads` with
    /// Retry-After. One client (an IP address, an IPv6 /64) sends at most half of them (at least
    /// one); its next is answered 503 `too_many_uploads_from_address`.
    #[arg(long, env = "SAFEDICE_MAX_CONCURRENT_UPLOADS", default_value_t = 8, value_parser = clap::value_parser!(u16).range(1..))]
    pub max_concurrent_uploads: u16,

    /// Heavy reads served at once: dataset previews and downloads, policy files and exports,
    /// each of which holds a dataset or a policy file in memory while it is built and sent; one
    /// more is answered 503 `too_many_heavy_reads` with Retry-After, so memory stays bounded
    /// by this many of them whatever the number of clients. One client (an IP address, an IPv6
    /// /64) is sent at most half of them (at least one) at once; its next is answered 503
    /// `too_many_heavy_reads_from_address`, so a slow reader leaves the rest to others.
    #[arg(long, env = "SAFEDICE_MAX_HEAVY_READS", default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..))]
    pub max_heavy_reads: u16,

    /// Event streams open at once (`/v1/jobs/{id}/events`, `/v1/jobs/{id}/logs?follow=true`);
    /// one more is answered 503 `too_many_streams` with Retry-After. Each stream also ends after
    /// 15 minutes (clients reconnect), so the slots turn over.
    #[arg(long, env = "SAFEDICE_MAX_STREAMS", default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_streams: u32,

    /// Training jobs this process runs concurrently; 0 serves the API only (jobs then run in
    /// `safedice worker` processes on the same database).
    #[arg(long, env = "SAFEDICE_WORKERS", default_value_t = 1)]
    pub workers: u16,

    /// Seconds a worker's lease on a running job lasts without a heartbeat (renewed every third
    /// of it): a job whose worker died is resumed elsewhere this long after its last heartbeat.
    #[arg(long, env = "SAFEDICE_LEASE_SECONDS", default_value_t = DEFAULT_LEASE_SECONDS, value_parser = clap::value_parser!(u64).range(LEASE_SECONDS_RANGE))]
    pub lease_seconds: u64,

    /// Attempts of a job whose worker vanishes (killed, out of memory, its machine lost) before
    /// the job fails with the history of its attempts; a job may set its own `max_attempts`.
    /// Errors that retrying cannot fix (bad data, divergence) fail a job at once.
    #[arg(long, env = "SAFEDICE_MAX_ATTEMPTS", default_value_t = DEFAULT_MAX_ATTEMPTS, value_parser = clap::value_parser!(u32).range(MAX_ATTEMPTS_RANGE))]
    pub max_attempts: u32,

    /// Seconds a job whose worker vanished waits, after its lease expired, before its next
    /// attempt; doubled per attempt (at most 600) with +-25% jitter. 0 retries at once.
    #[arg(long, env = "SAFEDICE_RETRY_BACKOFF_SECS", default_value_t = DEFAULT_RETRY_BACKOFF_SECS)]
    pub retry_backoff_secs: u64,

    /// Threads one training job computes on here, and the `threads` a job gets when its config
    /// sets none (then at most one per 128 rows of its batch). Default: the machine's cores
    /// divided by --workers, at least 1, so jobs running side by side never oversubscribe the
    /// cores. A job keeps the `threads` it was queued with (they are part of its arithmetic,
    /// like its seed); a worker runs more than its own count on its own count, to the same
    /// weights. In a fleet, give API nodes the workers' value.
    #[arg(long, env = "SAFEDICE_JOB_THREADS", value_parser = clap::value_parser!(u16).range(1..=crate::algo::MAX_JOB_THREADS as i64))]
    pub job_threads: Option<u16>,

    /// Bytes of policy weights kept loaded for /act and /v2 (least recently used dropped
    /// first, and loaded again when asked for); one policy is kept whatever its size.
    #[arg(long, env = "SAFEDICE_POLICY_CACHE_BYTES", default_value_t = DEFAULT_POLICY_CACHE_BYTES)]
    pub policy_cache_bytes: u64,

    /// Largest estimated peak memory of one training job, in bytes: POST /v1/jobs refuses (422
    /// job_too_large) a job whose configuration and datasets need more. Each worker runs one
    /// job, so training may use up to --workers times this.
    #[arg(long, env = "SAFEDICE_MAX_JOB_MEMORY", default_value_t = DEFAULT_MAX_JOB_MEMORY, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_job_memory: u64,

    /// Free space (bytes) the data directory's file system must have for /readyz to answer
    /// ready; below it /readyz answers 503 low_disk_space, and training paused by a full disk
    /// waits for it before resuming.
    #[arg(long, env = "SAFEDICE_MIN_FREE_DISK", default_value_t = DEFAULT_MIN_FREE_DISK)]
    pub min_free_disk: u64,
}

impl std::fmt::Debug for ServeConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let redacted = |token: &Option<String>| token.as_ref().map(|_| "<redacted>");
        f.debug_struct("ServeConfig")
            .field("bind", &self.bind)
            .field("grpc_bind", &self.grpc_bind)
            .field("grpc_max_streams", &self.grpc_max_streams)
            .field("data_dir", &self.data_dir)
            .field("database_url", &self.database_url.as_deref().map(crate::store::redact_url))
            .field("api_token", &redacted(&self.api_token))
            .field("inference_token", &redacted(&self.inference_token))
            .field("insecure_public", &self.insecure_public)
            .field("cors_origins", &self.cors_origins)
            .field("max_upload_bytes", &self.max_upload_bytes)
            .field("log_format", &self.log_format)
            .field("max_connections", &self.max_connections)
            .field("max_connections_per_address", &self.max_connections_per_address)
            .field("header_timeout_secs", &self.header_timeout_secs)
            .field("body_idle_timeout_secs", &self.body_idle_timeout_secs)
            .field("send_stall_timeout_secs", &self.send_stall_timeout_secs)
            .field("min_body_rate", &self.min_body_rate)
            .field("max_concurrent_uploads", &self.max_concurrent_uploads)
            .field("max_streams", &self.max_streams)
            .field("max_heavy_reads", &self.max_heavy_reads)
            .field("workers", &self.workers)
            .field("lease_seconds", &self.lease_seconds)
            .field("max_attempts", &self.max_attempts)
            .field("retry_backoff_secs", &self.retry_backoff_secs)
            .field("job_threads", &self.job_threads)
            .field("policy_cache_bytes", &self.policy_cache_bytes)
            .field("max_job_memory", &self.max_job_memory)
            .field("min_free_disk", &self.min_free_disk)
            .finish()
    }
}

/// Settings of `safedice worker`: a process that claims and trains jobs and runs evaluations,
/// without the HTTP API. `Debug` never shows the database password.
#[derive(Clone, clap::Args)]
pub struct WorkerConfig {
    /// The database the API nodes use: a postgres:// URL, or none for SQLite in --data-dir
    /// (several processes on one machine may share one SQLite data directory).
    #[arg(long, env = "SAFEDICE_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,

    /// The SQLite data directory without --database-url; with it, unused but for the free-space
    /// check.
    #[arg(long, env = "SAFEDICE_DATA_DIR", default_value = DEFAULT_DATA_DIR)]
    pub data_dir: PathBuf,

    /// Training jobs this process runs at once (the same knob as `serve --workers`;
    /// `--concurrency` is its former name).
    #[arg(long = "workers", alias = "concurrency", value_name = "N", env = "SAFEDICE_WORKERS", default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..))]
    pub concurrency: u16,

    /// Seconds a lease lasts without a heartbeat (see `safedice serve --help`).
    #[arg(long, env = "SAFEDICE_LEASE_SECONDS", default_value_t = DEFAULT_LEASE_SECONDS, value_parser = clap::value_parser!(u64).range(LEASE_SECONDS_RANGE))]
    pub lease_seconds: u64,

    /// Seconds before the next attempt of a job whose worker vanished (see `safedice serve
    /// --help`).
    #[arg(long, env = "SAFEDICE_RETRY_BACKOFF_SECS", default_value_t = DEFAULT_RETRY_BACKOFF_SECS)]
    pub retry_backoff_secs: u64,

    /// Threads one training job computes on (see `safedice serve --help`). Default: the
    /// machine's cores divided by --workers, at least 1.
    #[arg(long, env = "SAFEDICE_JOB_THREADS", value_parser = clap::value_parser!(u16).range(1..=crate::algo::MAX_JOB_THREADS as i64))]
    pub job_threads: Option<u16>,

    /// Free space (bytes) the data directory needs before training paused by a full disk
    /// resumes.
    #[arg(long, env = "SAFEDICE_MIN_FREE_DISK", default_value_t = DEFAULT_MIN_FREE_DISK)]
    pub min_free_disk: u64,

    /// Log format.
    #[arg(long, env = "SAFEDICE_LOG_FORMAT", value_enum, default_value_t = LogFormat::Pretty)]
    pub log_format: LogFormat,
}

impl std::fmt::Debug for WorkerConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerConfig")
            .field("database_url", &self.database_url.as_deref().map(crate::store::redact_url))
            .field("data_dir", &self.data_dir)
            .field("concurrency", &self.concurrency)
            .field("lease_seconds", &self.lease_seconds)
            .field("retry_backoff_secs", &self.retry_backoff_secs)
            .field("job_threads", &self.job_threads)
            .field("min_free_disk", &self.min_free_disk)
            .field("log_format", &self.log_format)
            .finish()
    }
}

/// A configuration the server refuses to start with.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConfigError {
    #[error(
        "refusing to listen on {0} without --api-token: anyone reaching that address could use \
         the whole API. Set --api-token (SAFEDICE_API_TOKEN), bind to 127.0.0.1, or pass \
         --insecure-public if the network is trusted"
    )]
    PublicWithoutToken(SocketAddr),
    #[error(
        "--inference-token needs --api-token: without an API token every route is open anyway"
    )]
    InferenceTokenWithoutApiToken,
    #[error("{0} must not be empty or blank")]
    EmptyToken(&'static str),
    #[error(
        "--cors-origin {0:?} is not a valid origin (expected e.g. https://dash.example.com or *)"
    )]
    BadCorsOrigin(String),
}

impl ServeConfig {
    /// The defaults of every flag, for a given data directory (used by tests and embedders).
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        ServeConfig {
            bind: DEFAULT_BIND.parse().expect("default bind address parses"),
            grpc_bind: None,
            grpc_max_streams: DEFAULT_GRPC_MAX_STREAMS,
            data_dir: data_dir.into(),
            database_url: None,
            api_token: None,
            inference_token: None,
            insecure_public: false,
            cors_origins: Vec::new(),
            max_upload_bytes: DEFAULT_MAX_UPLOAD_BYTES,
            log_format: LogFormat::Pretty,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
            header_timeout_secs: 15,
            body_idle_timeout_secs: 30,
            send_stall_timeout_secs: 30,
            min_body_rate: DEFAULT_MIN_BODY_RATE,
            max_concurrent_uploads: 8,
            max_streams: 256,
            max_heavy_reads: 4,
            workers: 1,
            lease_seconds: DEFAULT_LEASE_SECONDS,
            max_attempts: DEFAULT_MAX_ATTEMPTS,
            retry_backoff_secs: DEFAULT_RETRY_BACKOFF_SECS,
            job_threads: None,
            policy_cache_bytes: DEFAULT_POLICY_CACHE_BYTES,
            max_job_memory: DEFAULT_MAX_JOB_MEMORY,
            min_free_disk: DEFAULT_MIN_FREE_DISK,
        }
    }

    /// `--job-threads`, or the machine's cores shared between the workers.
    pub fn job_threads(&self) -> usize {
        crate::algo::job_threads(self.job_threads, usize::from(self.workers))
    }

    /// Checks the combinations that would expose the API or cannot work.
    pub fn validate(&self) -> Result<(), ConfigError> {
        // A token of spaces is as good as none, and a stray newline from `$(cat token)` would
        // never match what a client sends.
        let blank = |token: &Option<String>| token.as_deref().is_some_and(|t| t.trim().is_empty());
        if blank(&self.api_token) {
            return Err(ConfigError::EmptyToken("--api-token"));
        }
        if blank(&self.inference_token) {
            return Err(ConfigError::EmptyToken("--inference-token"));
        }
        if self.inference_token.is_some() && self.api_token.is_none() {
            return Err(ConfigError::InferenceTokenWithoutApiToken);
        }
        for bind in std::iter::once(self.bind).chain(self.grpc_bind) {
            if !bind.ip().is_loopback() && self.api_token.is_none() && !self.insecure_public {
                return Err(ConfigError::PublicWithoutToken(bind));
            }
        }
        self.cors_origin_values()?;
        Ok(())
    }

    /// The CORS origins as header values; `None` inside means any origin (`*`).
    pub fn cors_origin_values(&self) -> Result<Vec<Option<HeaderValue>>, ConfigError> {
        self.cors_origins
            .iter()
            .map(|origin| {
                if origin == "*" {
                    return Ok(None);
                }
                let looks_like_origin = (origin.starts_with("http://")
                    || origin.starts_with("https://"))
                    && !origin.trim_end_matches('/').contains(|c: char| c.is_whitespace());
                match HeaderValue::from_str(origin.trim_end_matches('/')) {
                    Ok(value) if looks_like_origin => Ok(Some(value)),
                    _ => Err(ConfigError::BadCorsOrigin(origin.clone())),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(bind: &str) -> ServeConfig {
        ServeConfig { bind: bind.parse().unwrap(), ..ServeConfig::new("unused") }
    }

    #[test]
    fn public_bind_needs_a_token_or_the_explicit_opt_out() {
        assert_eq!(config("127.0.0.1:0").validate(), Ok(()));
        assert_eq!(config("[::1]:0").validate(), Ok(()));
        let public = config("0.0.0.0:8080");
        assert_eq!(public.validate(), Err(ConfigError::PublicWithoutToken(public.bind)));
        let with_token = ServeConfig { api_token: Some("s3cret".into()), ..public.clone() };
        assert_eq!(with_token.validate(), Ok(()));
        let opted_out = ServeConfig { insecure_public: true, ..public };
        assert_eq!(opted_out.validate(), Ok(()));
        // The gRPC listener by the same rule.
        let grpc = ServeConfig {
            grpc_bind: Some("0.0.0.0:8081".parse().unwrap()),
            ..config("127.0.0.1:0")
        };
        assert_eq!(grpc.validate(), Err(ConfigError::PublicWithoutToken(grpc.grpc_bind.unwrap())));
        let grpc_with_token = ServeConfig { api_token: Some("s3cret".into()), ..grpc };
        assert_eq!(grpc_with_token.validate(), Ok(()));
    }

    #[test]
    fn inference_token_alone_and_empty_tokens_are_refused() {
        let c = ServeConfig { inference_token: Some("agent".into()), ..config("127.0.0.1:0") };
        assert_eq!(c.validate(), Err(ConfigError::InferenceTokenWithoutApiToken));
        let c = ServeConfig { api_token: Some(String::new()), ..config("127.0.0.1:0") };
        assert_eq!(c.validate(), Err(ConfigError::EmptyToken("--api-token")));
        let c = ServeConfig { api_token: Some(" \t\n".into()), ..config("127.0.0.1:0") };
        assert_eq!(c.validate(), Err(ConfigError::EmptyToken("--api-token")));
        let c = ServeConfig {
            api_token: Some("s3cret".into()),
            inference_token: Some("   ".into()),
            ..config("127.0.0.1:0")
        };
        assert_eq!(c.validate(), Err(ConfigError::EmptyToken("--inference-token")));
    }

    #[test]
    fn debug_output_hides_tokens() {
        let c = ServeConfig { api_token: Some("s3cret-value".into()), ..config("127.0.0.1:0") };
        let shown = format!("{c:?}");
        assert!(!shown.contains("s3cret-value") && shown.contains("<redacted>"), "{shown}");
    }

    #[test]
    fn cors_origins_are_checked() {
        let mut c = config("127.0.0.1:0");
        c.cors_origins = vec!["https://dash.example.com/".into(), "*".into()];
        let values = c.cors_origin_values().unwrap();
        assert_eq!(values[0].as_ref().unwrap(), "https://dash.example.com");
        assert!(values[1].is_none());
        c.cors_origins = vec!["dash.example.com".into()];
        assert_eq!(c.validate(), Err(ConfigError::BadCorsOrigin("dash.example.com".into())));
    }
}
