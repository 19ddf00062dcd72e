//! Policy evaluations in the background (`POST /v1/policies/{id}/evaluate`).
//!
//! Evaluations wait in the `evaluations` table (status `queued`) and one evaluator task runs
//! them in order, each on a blocking thread, beside the training workers: an evaluation is
//! short next to a training run (500 episodes of the longest environment take about a second),
//! so one at a time keeps them from crowding training off the cores. A shutdown interrupts the
//! running one and puts it back in the queue; at start-up, evaluations a dead process left
//! `running` are queued again. Both are safe because an evaluation is a pure function of the
//! policy and its spec.

use std::sync::{Arc, Mutex};

use tokio::sync::Notify;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use super::EvalSpec;
use crate::algo::Policy;
use crate::domain::EvaluationRecord;
use crate::envs::{self, EvalError, EvalReport};
use crate::store::Store;

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
    wake: Notify,
    shutdown: CancellationToken,
    task: Mutex<Option<JoinHandle<()>>>,
}

impl Evaluator {
    /// An evaluator (not started) that stops when `shutdown` is cancelled.
    pub fn new(store: Store, shutdown: CancellationToken) -> Self {
        Evaluator {
            inner: Arc::new(Inner { store, wake: Notify::new(), shutdown, task: Mutex::new(None) }),
        }
    }

    /// Requeues evaluations interrupted by a previous process, then starts the evaluator task.
    pub async fn start(&self) -> anyhow::Result<()> {
        let requeued = self.inner.store.requeue_evaluations(None).await?;
        if requeued > 0 {
            tracing::info!(
                evaluations = requeued,
                "rerunning evaluations interrupted by the last shutdown"
            );
        }
        let task = tokio::spawn(self.clone().run());
        *self.inner.task.lock().expect("evaluator lock") = Some(task);
        Ok(())
    }

    /// Tells the evaluator that an evaluation was queued.
    pub fn wake(&self) {
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
        while !shutdown.is_cancelled() {
            match self.inner.store.claim_next_evaluation().await {
                Ok(Some(row)) => self.run_one(row).await,
                Ok(None) => super::wait_for_work(&self.inner.wake, &shutdown).await,
                Err(e) => {
                    tracing::error!(error = %e, "cannot claim an evaluation; retrying");
                    super::back_off(&shutdown).await;
                }
            }
        }
    }

    #[tracing::instrument(skip_all, fields(evaluation_id = %row.id, policy_id = %row.policy_id, env = %row.spec.env))]
    async fn run_one(&self, row: EvaluationRecord) {
        let store = &self.inner.store;
        let outcome = self.evaluate(&row).await;
        let stored = match &outcome {
            Ok(report) => {
                let m = &report.metrics;
                tracing::info!(
                    normalized_return = m.normalized_return,
                    average_cost = m.average_cost,
                    "evaluation succeeded"
                );
                store.finish_evaluation(&row.id, Ok(report)).await
            }
            Err(_) if self.inner.shutdown.is_cancelled() => {
                tracing::info!(
                    "evaluation interrupted by the shutdown; it reruns at the next start"
                );
                store.requeue_evaluations(Some(&row.id)).await.map(drop)
            }
            Err(message) => {
                tracing::warn!(error = %message, "evaluation failed");
                store.finish_evaluation(&row.id, Err(message)).await
            }
        };
        if let Err(e) = stored {
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
