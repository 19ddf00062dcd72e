//! The training queue and worker pool, and the background policy evaluator ([`evaluations`]).
//!
//! Jobs wait in the `jobs` table (status `queued`), so the queue survives restarts and is shared
//! by every process on the same database ([`fleet`]): `safedice serve` with `--workers N`, and
//! any number of `safedice worker` processes. Each worker task claims the next job with a lease
//! ([`Store::claim_next_job`]) and drives its [`crate::algo::Trainer`] step by step on a
//! blocking thread ([`worker`]), so training never stalls the HTTP side; a heartbeat keeps the
//! lease alive, and every write for the job carries the lease token. Between steps the worker
//! checks for a cancel request and for shutdown, records metrics every `log_every` steps, saves
//! a checkpoint every `checkpoint_every` steps, evaluates the policy when the job has an `eval`
//! block ([`EvalOptions`]), and publishes progress ([`JobEvent`]) for the event streams. A job
//! whose worker died (its lease expired) is claimed again by any worker and resumes from its
//! last checkpoint.
//!
//! A run whose write the store cannot take (a full disk, SQLITE_FULL, a lock held past the busy
//! timeout) is not the job's fault: the job goes back to the queue, to resume from its last
//! checkpoint, and every worker pauses claiming until the data directory takes writes and has
//! `--min-free-disk` free again (at least [`STORAGE_RETRY`], doubling while runs keep failing so,
//! up to [`STORAGE_RETRY_MAX`]), rather than failing job after job for good.

mod announcements;
mod cancels;
pub mod evaluations;
mod events;
pub mod experiments;
pub mod fleet;
pub mod results;
mod storage_gate;
pub mod submit;
mod training;
mod worker;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{broadcast, Notify};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::domain::{DatasetId, JobId};
pub use crate::domain::{EvalOptions, EvalSpec, JobProgress, RunnerOptions};
use crate::store::Store;
use announcements::Announcement;
use cancels::CancelFlags;
pub use evaluations::{evaluate_policy, Evaluator};
pub use events::JobEvent;
use events::JobEvents;
pub use fleet::WorkerOptions;
use storage_gate::StorageGate;
pub use submit::{submit, JobRequest, SubmitError, SubmitLimits};

/// Handle to the worker pool; cheap to clone.
#[derive(Clone)]
pub struct JobRunner {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    options: WorkerOptions,
    shutdown: CancellationToken,
    /// The workers and the fleet's tasks, awaited at shutdown.
    tasks: Mutex<Vec<JoinHandle<()>>>,
    /// Woken when a job is queued.
    wake: Notify,
    /// Runs policy evaluations beside the training workers.
    evaluator: Evaluator,
    events: JobEvents,
    /// Of the jobs this process is running, checked by their worker every step.
    cancels: CancelFlags,
    /// Closed while the store cannot take writes: workers wait at it before claiming.
    storage: StorageGate,
}

impl JobRunner {
    /// A pool of `options.workers` workers (not started) that stops when `shutdown` is
    /// cancelled; with 0 workers it trains nothing and runs no evaluations (an API-only node).
    pub fn new(store: Store, options: WorkerOptions, shutdown: CancellationToken) -> Self {
        JobRunner {
            inner: Arc::new(Inner {
                evaluator: Evaluator::new(store.clone(), options.clone(), shutdown.clone()),
                store,
                options,
                shutdown,
                tasks: Mutex::new(Vec::new()),
                wake: Notify::new(),
                events: JobEvents::new(),
                cancels: CancelFlags::default(),
                storage: StorageGate::default(),
            }),
        }
    }

    /// Registers this process's workers, starts them and the evaluator (none with 0 workers),
    /// and, when `follow` is set (an API node), the task that brings the progress of jobs run
    /// by other processes to this process's event streams.
    pub async fn start(&self, follow: bool) -> anyhow::Result<()> {
        let workers = self.inner.options.workers;
        let mut tasks = Vec::new();
        if workers > 0 {
            // Process-wide: every worker of this process shares the one setting.
            crate::algo::set_job_thread_cap(self.inner.options.job_threads);
            fleet::register(self).await?;
            tasks.push(tokio::spawn(fleet::registry_heartbeat(self.clone())));
            self.inner.evaluator.start();
            for index in 0..workers {
                tasks.push(tokio::spawn(worker::run_worker(self.clone(), index)));
            }
        }
        if follow {
            tasks.push(tokio::spawn(fleet::follow_jobs(self.clone())));
        }
        if self.inner.store.database_url().is_some() {
            tasks.push(tokio::spawn(fleet::listen(self.clone())));
        }
        self.inner.tasks.lock().expect("runner lock").extend(tasks);
        tracing::info!(
            workers,
            job_threads = self.inner.options.job_threads,
            worker_id = %self.inner.options.worker_id,
            lease_seconds = self.inner.options.lease.as_secs(),
            gemm_kernels = crate::algo::fused_mlp::gemm_kernels(),
            "job workers started"
        );
        Ok(())
    }

    /// Waits for the workers to finish after shutdown was requested (each checkpoints its job
    /// and hands it back to the queue), then removes this process from the worker registry.
    pub async fn stopped(&self) {
        self.inner.evaluator.stopped().await;
        let tasks = std::mem::take(&mut *self.inner.tasks.lock().expect("runner lock"));
        for task in tasks {
            if let Err(e) = task.await {
                tracing::error!(error = %e, "a job worker panicked");
            }
        }
        if self.inner.options.workers > 0 {
            if let Err(e) = self.inner.store.remove_worker(&self.inner.options.worker_id).await {
                tracing::warn!(error = %e, "cannot remove this worker from the registry");
            }
        }
    }

    /// This process's worker identity and lease settings.
    pub fn options(&self) -> &WorkerOptions {
        &self.inner.options
    }

    /// Tells an idle worker that a job was queued (and, on PostgreSQL, every other process).
    pub fn wake(&self) {
        self.inner.wake.notify_one();
        announcements::announce(&self.inner.store, Announcement::JobQueued);
    }

    /// Stops a job this process is running at its next step; a job another process runs
    /// learns of its cancel request at its next progress write (about twice a second), or at
    /// once through a PostgreSQL notification.
    pub fn cancel_running(&self, job_id: &JobId) {
        if !self.inner.cancels.raise(job_id) {
            announcements::announce(&self.inner.store, Announcement::Cancel(job_id.to_string()));
        }
    }

    /// Progress and status changes of every job, from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<JobEvent> {
        self.inner.events.subscribe()
    }

    /// The background policy evaluator.
    pub fn evaluator(&self) -> &Evaluator {
        &self.inner.evaluator
    }

    pub fn store(&self) -> &Store {
        &self.inner.store
    }

    /// Tells the event streams of a change the API made itself: a queued job cancelled, or a
    /// finished job deleted (no worker publishes either).
    pub fn publish_api_change(&self, event: JobEvent) {
        self.publish(event);
    }

    /// Publishes an event of a job this process runs (see [`JobEvents::publish`]).
    fn publish(&self, event: JobEvent) {
        self.inner.events.publish(&self.inner.store, event);
    }

    /// Waits at the storage gate (at once while it is open).
    async fn wait_for_storage(&self) {
        let (store, shutdown) = (&self.inner.store, &self.inner.shutdown);
        self.inner.storage.wait(store, self.inner.options.min_free_disk, shutdown).await;
    }

    /// Puts a job whose run stopped on a failed write back in the queue. That write may fail
    /// too while the disk is full: it is retried until it goes through, the lease is lost, or
    /// shutdown begins (a job left `running` is claimed again once its lease expires). False
    /// when another worker had taken the job over meanwhile.
    async fn release_when_possible(
        &self,
        lease: &crate::store::Lease<JobId>,
        reason: &str,
    ) -> bool {
        let mut delay = STORAGE_RETRY;
        loop {
            match self.store().release_job(lease, reason).await {
                Ok(()) => return true,
                Err(crate::store::StoreError::LeaseLost(_)) => return false,
                Err(e) => {
                    tracing::warn!(error = %e, "cannot hand the job back to the queue yet");
                    if sleep_unless_shutdown(&self.inner.shutdown, delay).await {
                        return true;
                    }
                    delay = (delay * 2).min(STORAGE_RETRY_MAX);
                }
            }
        }
    }
}

/// The shortest pause of training after a run failed to write (doubled while runs keep failing).
pub const STORAGE_RETRY: Duration = Duration::from_secs(5);
/// The longest.
pub const STORAGE_RETRY_MAX: Duration = Duration::from_secs(300);

/// Sleeps `duration`; true if shutdown began first.
async fn sleep_unless_shutdown(shutdown: &CancellationToken, duration: Duration) -> bool {
    tokio::select! {
        () = shutdown.cancelled() => true,
        () = tokio::time::sleep(duration) => false,
    }
}

/// How long an idle queue loop (a training worker, the evaluator) sleeps before looking at its
/// queue again without being woken: covers work queued by another process on the same database
/// (on PostgreSQL a notification wakes it at once) and leases that expired meanwhile.
const IDLE_POLL: Duration = Duration::from_secs(2);
/// Back-off of a queue loop after a database error while claiming.
const ERROR_BACKOFF: Duration = Duration::from_secs(1);

/// An idle queue loop's wait: until `wake` fires, shutdown begins, or [`IDLE_POLL`] passes.
async fn wait_for_work(wake: &Notify, shutdown: &CancellationToken) {
    tokio::select! {
        () = wake.notified() => {}
        () = shutdown.cancelled() => {}
        () = tokio::time::sleep(IDLE_POLL) => {}
    }
}

/// A queue loop's wait after a failed claim: [`ERROR_BACKOFF`], or until shutdown begins.
async fn back_off(shutdown: &CancellationToken) {
    tokio::select! {
        () = shutdown.cancelled() => {}
        () = tokio::time::sleep(ERROR_BACKOFF) => {}
    }
}

/// Loads a job's datasets from the store.
pub async fn load_training_data(
    store: &Store,
    unlabeled: &DatasetId,
    non_preferred: Option<&DatasetId>,
) -> Result<crate::algo::TrainingData, crate::store::StoreError> {
    let unlabeled = Arc::new(store.load_dataset(unlabeled).await?);
    let non_preferred = match non_preferred {
        Some(id) => Some(Arc::new(store.load_dataset(id).await?)),
        None => None,
    };
    Ok(crate::algo::TrainingData { unlabeled, non_preferred })
}
