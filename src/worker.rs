//! `safedice worker`: a process that claims and trains jobs and runs evaluations from the shared
//! queue, without the HTTP API. Any number of them (and of `safedice serve` nodes) share one
//! database; see `jobs::fleet` for how they share it safely.

use std::time::Duration;

use tokio_util::sync::CancellationToken;

use crate::config::WorkerConfig;
use crate::domain::RetryBackoff;
use crate::jobs::{JobRunner, WorkerOptions};
use crate::store::Store;

/// Runs the workers until `shutdown` is cancelled, then lets each checkpoint its job and hand it
/// back to the queue.
pub async fn run(config: WorkerConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    let store = Store::connect(&config.data_dir, config.database_url.as_deref()).await?;
    let options = WorkerOptions::new(
        usize::from(config.concurrency),
        Duration::from_secs(config.lease_seconds),
        config.min_free_disk,
    )
    .with_retry_backoff(RetryBackoff::new(Duration::from_secs(config.retry_backoff_secs)))
    .with_job_threads(crate::algo::job_threads(
        config.job_threads,
        usize::from(config.concurrency),
    ));
    tracing::info!(
        worker_id = %options.worker_id,
        database = store.backend().as_str(),
        concurrency = config.concurrency,
        "safedice worker starting"
    );
    let jobs = JobRunner::new(store.clone(), options, shutdown.clone());
    jobs.start(false).await?;
    shutdown.cancelled().await;
    jobs.stopped().await;
    store.close().await;
    tracing::info!("safedice worker stopped");
    Ok(())
}
