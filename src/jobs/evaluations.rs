//! Policy evaluations in the background (`POST /v1/policies/{id}/evaluate`).
//!
//! Evaluations wait in the `evaluations` table (status `queued`) and one evaluator task runs
//! them in order, each on a blocking thread, beside the training workers: an evaluation is
//! short next to a training run (500 episodes of the longest environment take about a second),
//! so one at a time keeps them from crowding training off the cores. Like a job, a running
//! evaluation is held by a lease: a shutdown interrupts it and puts it back in the queue, and
//! one whose worker died is claimed again once the lease expires. Both are safe because an
//! evaluation is a pure function of the policy and its spec.

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use super::announcements::{announce, Announcement};
use super::fleet::{LeaseKeeper, WorkerOptions};
use super::EvalSpec;
use crate::algo::Policy;
use crate::domain::{EvaluationId, EvaluationRecord};
use crate::envs::{self, EvalError, EvalReport};
use crate::store::{Lease, Store, StoreError};

/// Runs `spec` with `policy` and the paper's metrics. `interrupted` is asked between
/// environment steps; once it says yes the evaluation stops with [`EvalError::Policy`].
pub fn evaluate_policy(
    policy: &Policy,
    spec: &EvalSpec,
    interrupted: &dyn Fn() -> bool,
) -> Result<EvalReport, EvalError> {
    let act = |obs: &[f32], deterministic: bool, rng: &mut _| {
        if interrupted() {
            return Err("interrupted".to_string());
        }
        policy.act(obs, deterministic, rng).map_err(|e| e.to_string())
    };
    envs::evaluate(&spec.env, act, spec.episodes, spec.seed, spec.deterministic)
}

/// Handle to the evaluator; cheap to clone.
#[derive(Clone)]
pub struct Evaluator {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    options: WorkerOptions,
    wake: Notify,
    shutdown: CancellationToken,
    task: Mutex<Option<JoinHandle<()>>>,
}

impl Evaluator {
    /// An evaluator (not started) that stops when `shutdown` is cancelled.
    pub fn new(store: Store, options: WorkerOptions, shutdown: CancellationToken) -> Self {
        let inner = Inner { store, options, wake: Notify::new(), shutdown, task: Mutex::new(None) };
        Evaluator { inner: Arc::new(inner) }
    }

    /// Starts the evaluator task.
    pub fn start(&self) {
        let task = tokio::spawn(self.clone().run());
        *self.inner.task.lock().expect("evaluator lock") = Some(task);
    }

    /// Tells the evaluator (and, on PostgreSQL, the other processes') that an evaluation was
    /// queued.
    pub fn wake(&self) {
        self.wake_local();
        announce(&self.inner.store, Announcement::EvaluationQueued);
    }

    /// Tells this process's evaluator alone.
    pub(super) fn wake_local(&self) {
        self.inner.wake.notify_one();
    }

    /// Waits for the evaluator to stop after shutdown was requested.
    pub async fn stopped(&self) {
        let task = self.inner.task.lock().expect("evaluator lock").take();
        if let Some(task) = task {
            if let Err(e) = task.await {
                tracing::error!(error = %e, "the evaluator panicked");
            }
        }
    }

    async fn run(self) {
        let shutdown = self.inner.shutdown.clone();
        let options = &self.inner.options;
        while !shutdown.is_cancelled() {
            match self.inner.store.claim_next_evaluation(&options.worker_id, options.lease).await {
                Ok(Some((row, lease))) => self.run_one(row, lease).await,
                Ok(None) => super::wait_for_work(&self.inner.wake, &shutdown).await,
                Err(e) => {
                    tracing::error!(error = %e, "cannot claim an evaluation; retrying");
                    super::back_off(&shutdown).await;
                }
            }
        }
    }

    #[tracing::instrument(skip_all, fields(evaluation_id = %row.id, policy_id = %row.policy_id, env = %row.spec.env))]
    async fn run_one(&self, row: EvaluationRecord, lease: Lease<EvaluationId>) {
        let store = &self.inner.store;
        // A lost lease needs no flag here: the evaluation is short, and its result is refused.
        let lost = Arc::new(AtomicBool::new(false));
        let keeper = LeaseKeeper::start(store.clone(), lease.clone(), &self.inner.options, lost);
        let outcome = self.evaluate(&row).await;
        drop(keeper);
        let stored = match &outcome {
            Ok(report) => {
                let m = &report.metrics;
                tracing::info!(
                    normalized_return = m.normalized_return,
                    average_cost = m.average_cost,
                    "evaluation succeeded"
                );
                store.finish_evaluation(&lease, Ok(report)).await
            }
            Err(_) if self.inner.shutdown.is_cancelled() => {
                tracing::info!("evaluation interrupted by the shutdown; it goes back to the queue");
                store.requeue_evaluation(&lease).await
            }
            Err(message) => {
                tracing::warn!(error = %message, "evaluation failed");
                store.finish_evaluation(&lease, Err(message)).await
            }
        };
        if let Err(StoreError::LeaseLost(_)) = stored {
            tracing::warn!("another worker took the evaluation over; this result is dropped");
        } else if let Err(e) = stored {
            tracing::error!(error = %e, "cannot record the evaluation's outcome");
        }
    }

    /// Loads the policy and runs the evaluation on a blocking thread.
    async fn evaluate(&self, row: &EvaluationRecord) -> Result<EvalReport, String> {
        let (spec_json, weights) =
            self.inner.store.policy_artifact(&row.policy_id).await.map_err(|e| e.to_string())?;
        let spec = row.spec.clone();
        let shutdown = self.inner.shutdown.clone();
        let run = move || -> Result<EvalReport, String> {
            let policy = Policy::from_stored(&spec_json, &weights).map_err(|e| e.to_string())?;
            evaluate_policy(&policy, &spec, &|| shutdown.is_cancelled()).map_err(|e| e.to_string())
        };
        tokio::task::spawn_blocking(run)
            .await
            .unwrap_or_else(|e| Err(format!("the evaluation thread panicked: {e}")))
    }
}
