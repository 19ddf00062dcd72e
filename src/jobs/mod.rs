//! The training queue and worker pool, and the background policy evaluator ([`evaluations`]).
//!
//! Jobs wait in the `jobs` table (status `queued`), so the queue survives restarts. Each of
//! `--workers` worker tasks claims the next job atomically ([`Store::claim_next_job`]) and drives
//! its [`crate::algo::Trainer`] step by step on a blocking thread ([`worker`]), so training never
//! stalls the HTTP side. Between steps the worker checks for a cancel request and for shutdown,
//! records metrics every `log_every` steps, saves a checkpoint every `checkpoint_every` steps,
//! evaluates the policy when the job has an `eval` block ([`EvalOptions`]), and publishes
//! progress ([`JobEvent`]) for the event streams. At start-up, jobs a dead process
//! left `running` go back to the queue first and resume from their last checkpoint.

pub mod evaluations;
pub mod options;
pub mod progress;
mod worker;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{broadcast, Notify};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::store::Store;
pub use evaluations::{evaluate_policy, Evaluator};
pub use options::{EvalOptions, EvalSpec, RunnerOptions};
pub use progress::JobProgress;

/// Something a watcher of a job wants to know.
#[derive(Clone, Debug)]
pub enum JobEvent {
    /// A running job advanced.
    Progress { job_id: String, progress: JobProgress },
    /// A job changed status (`running`, `queued` again on shutdown, or a final status).
    Status { job_id: String, status: String },
}

impl JobEvent {
    pub fn job_id(&self) -> &str {
        match self {
            JobEvent::Progress { job_id, .. } | JobEvent::Status { job_id, .. } => job_id,
        }
    }
}

/// Handle to the worker pool; cheap to clone.
#[derive(Clone)]
pub struct JobRunner {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    workers: usize,
    /// Woken when a job is queued.
    wake: Notify,
    events: broadcast::Sender<JobEvent>,
    /// Cancel flags of the jobs this process is running, checked by their worker every step.
    cancels: Mutex<HashMap<String, Arc<AtomicBool>>>,
    shutdown: CancellationToken,
    tasks: Mutex<Vec<JoinHandle<()>>>,
    /// Runs policy evaluations beside the training workers.
    evaluator: Evaluator,
}

/// Events buffered per subscriber; a slow event stream skips ahead rather than blocking workers.
const EVENT_BUFFER: usize = 1024;

impl JobRunner {
    /// A pool of `workers` workers (not started) that stops when `shutdown` is cancelled.
    pub fn new(store: Store, workers: usize, shutdown: CancellationToken) -> Self {
        let (events, _) = broadcast::channel(EVENT_BUFFER);
        JobRunner {
            inner: Arc::new(Inner {
                workers: workers.max(1),
                wake: Notify::new(),
                events,
                cancels: Mutex::new(HashMap::new()),
                evaluator: Evaluator::new(store.clone(), shutdown.clone()),
                store,
                shutdown,
                tasks: Mutex::new(Vec::new()),
            }),
        }
    }

    /// Requeues jobs interrupted by a previous process, then starts the workers and the
    /// evaluator.
    pub async fn start(&self) -> anyhow::Result<()> {
        self.inner.evaluator.start().await?;
        let requeued = self.inner.store.requeue_interrupted_jobs().await?;
        if requeued > 0 {
            tracing::info!(jobs = requeued, "resuming jobs interrupted by the last shutdown");
        }
        let mut tasks = self.inner.tasks.lock().expect("runner lock");
        for index in 0..self.inner.workers {
            tasks.push(tokio::spawn(worker::run_worker(self.clone(), index)));
        }
        tracing::info!(workers = self.inner.workers, "job workers started");
        Ok(())
    }

    /// Waits for the workers to finish after shutdown was requested (each checkpoints its job
    /// and hands it back to the queue).
    pub async fn stopped(&self) {
        self.inner.evaluator.stopped().await;
        let tasks = std::mem::take(&mut *self.inner.tasks.lock().expect("runner lock"));
        for task in tasks {
            if let Err(e) = task.await {
                tracing::error!(error = %e, "a job worker panicked");
            }
        }
    }

    /// Tells an idle worker that a job was queued.
    pub fn wake(&self) {
        self.inner.wake.notify_one();
    }

    /// Stops a job this process is running at its next step (no-op for other jobs).
    pub fn cancel_running(&self, job_id: &str) {
        if let Some(flag) = self.inner.cancels.lock().expect("runner lock").get(job_id) {
            flag.store(true, Ordering::Relaxed);
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

    fn publish(&self, event: JobEvent) {
        // No subscriber is fine: nobody is watching.
        let _ = self.inner.events.send(event);
    }

    fn register_cancel_flag(&self, job_id: &str) -> Arc<AtomicBool> {
        let flag = Arc::new(AtomicBool::new(false));
        self.inner.cancels.lock().expect("runner lock").insert(job_id.to_owned(), flag.clone());
        flag
    }

    fn forget_cancel_flag(&self, job_id: &str) {
        self.inner.cancels.lock().expect("runner lock").remove(job_id);
    }
}

/// How long an idle queue loop (a training worker, the evaluator) sleeps before looking at its
/// queue again without being woken: covers work queued by another process on the same database.
const IDLE_POLL: Duration = Duration::from_secs(5);
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
    unlabeled: &str,
    non_preferred: Option<&str>,
) -> Result<crate::algo::TrainingData, crate::store::StoreError> {
    let unlabeled = Arc::new(store.load_dataset(unlabeled).await?);
    let non_preferred = match non_preferred {
        Some(id) => Some(Arc::new(store.load_dataset(id).await?)),
        None => None,
    };
    Ok(crate::algo::TrainingData { unlabeled, non_preferred })
}
