//! One worker: claim a job, run its training ([`super::training`]), write how it ended.

use std::sync::atomic::Ordering;

use super::fleet::LeaseKeeper;
use super::training::{JobLog, Outcome, TrainedPolicy, TrainingRun};
use super::{JobEvent, JobRunner};
use crate::domain::LogLevel;
use crate::domain::MetricRecord;
use crate::domain::{JobId, JobRecord, JobStatus, PolicyId};
use crate::store::job_runs::SucceededRun;
use crate::store::{Lease, Store, StoreError};

/// What writing a run's end came to.
enum Ended {
    /// The job's end (or, after a shutdown, its return to the queue) is stored.
    Written(JobStatus),
    /// The store could not take the end's write: the job goes back to the queue.
    StoreUnavailable(String),
    LeaseLost,
}

#[tracing::instrument(skip(runner))]
pub(super) async fn run_worker(runner: JobRunner, index: usize) {
    let shutdown = runner.inner.shutdown.clone();
    while !shutdown.is_cancelled() {
        runner.wait_for_storage().await;
        if shutdown.is_cancelled() {
            break;
        }
        let options = &runner.inner.options;
        reap_expired_jobs(&runner).await;
        match runner.store().claim_next_job(&options.worker_id, options.lease).await {
            Ok(Some((job, lease))) => run_job(&runner, job, lease).await,
            Ok(None) => super::wait_for_work(&runner.inner.wake, &shutdown).await,
            // A claim is a write too: on a full disk, pause like a run that could not write.
            Err(e) if e.is_storage_full() => {
                tracing::error!(error = %e, "cannot claim a job: the disk is full");
                runner.inner.storage.close();
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot claim a job; retrying");
                super::back_off(&shutdown).await;
            }
        }
    }
}

/// Hands the jobs of workers that vanished back to the queue (or fails those out of attempts),
/// and tells this process's event streams.
async fn reap_expired_jobs(runner: &JobRunner) {
    let options = &runner.inner.options;
    match runner.store().reap_expired_jobs(&options.worker_id, &options.retry_backoff).await {
        Ok(reaped) => {
            for job in reaped {
                tracing::warn!(job_id = %job.id, status = %job.status, "{}", job.message);
                runner.publish(JobEvent::Status { job_id: job.id, status: job.status });
            }
        }
        Err(e) => tracing::warn!(error = %e, "cannot look for jobs whose worker vanished"),
    }
}

#[tracing::instrument(skip_all, fields(job_id = %job.id, algorithm = %job.algorithm, claim = lease.token))]
async fn run_job(runner: &JobRunner, job: JobRecord, lease: Lease<JobId>) {
    let id = job.id.clone();
    let cancel = runner.inner.cancels.register(&id);
    // A cancel may have been requested between the claim and the flag's registration.
    if job.cancel_requested {
        cancel.store(true, Ordering::Relaxed);
    }
    let keeper = LeaseKeeper::start(
        runner.store().clone(),
        lease.clone(),
        &runner.inner.options,
        cancel.clone(),
    );
    runner.publish(JobEvent::Status { job_id: id.clone(), status: JobStatus::Running });
    tracing::info!("job started");
    let log = JobLog::new(runner, &lease);
    let attempt = format!("attempt {} of {}", job.attempt, job.max_attempts);
    log.write(LogLevel::Info, &format!("claimed by worker {} ({attempt})", log.worker)).await;
    let run = TrainingRun::new(runner.clone(), job, lease.clone(), cancel, log.clone());
    let (outcome, metrics) = match run.drive().await {
        (Ok(outcome), metrics) => (outcome, metrics),
        (Err(e), metrics) => (Outcome::of_error(&e), metrics),
    };
    // While the lease is still kept alive: a slow write of the end does not lose the job.
    let ended = write_end(runner, &log, &lease, outcome, metrics).await;
    drop(keeper);
    runner.inner.cancels.forget(&id);
    if !matches!(ended, Ended::StoreUnavailable(_) | Ended::Written(JobStatus::Queued)) {
        runner.inner.storage.open();
    }
    let status = match ended {
        Ended::LeaseLost => return end_after_lease_lost(runner, &lease).await,
        Ended::Written(status) => status,
        Ended::StoreUnavailable(message) => {
            tracing::error!(
                error = %message,
                "the store cannot take the job's writes; the job goes back to the queue and \
                 training pauses until the data directory takes writes again"
            );
            runner.inner.storage.close();
            let reason = format!("the store could not take the run's writes: {message}");
            if !runner.release_when_possible(&lease, &reason).await {
                return end_after_lease_lost(runner, &lease).await;
            }
            JobStatus::Queued
        }
    };
    tracing::info!(%status, "job stopped");
    runner.publish(JobEvent::Status { job_id: id, status });
}

/// Writes how the run ended: the one place a job's end is written. A write that fails turns
/// into the outcome its error means (a lost lease, the store unavailable, or the job failed)
/// and that is written instead.
async fn write_end(
    runner: &JobRunner,
    log: &JobLog,
    lease: &Lease<JobId>,
    mut outcome: Outcome,
    mut metrics: Vec<MetricRecord>,
) -> Ended {
    let store = runner.store();
    loop {
        let (status, written) = match outcome {
            Outcome::Succeeded(trained) => {
                let metrics = std::mem::take(&mut metrics);
                (JobStatus::Succeeded, store_policy(store, log, lease, *trained, metrics).await)
            }
            Outcome::Cancelled => {
                let metrics = std::mem::take(&mut metrics);
                let written = store.finish_job(lease, JobStatus::Cancelled, None, &metrics).await;
                (JobStatus::Cancelled, written.map_err(Into::into))
            }
            Outcome::Released => {
                let reason = "the worker shut down; the job resumes from its last checkpoint";
                (JobStatus::Queued, store.release_job(lease, reason).await.map_err(Into::into))
            }
            Outcome::Failed(message) => {
                tracing::warn!(error = %message, "job failed");
                log.write(LogLevel::Error, &format!("failed: {message}")).await;
                let status = JobStatus::Failed;
                match store.finish_job(lease, status, Some(&message), &metrics).await {
                    Ok(()) => {}
                    Err(StoreError::LeaseLost(_)) => return Ended::LeaseLost,
                    Err(e) => tracing::error!(error = %e, "cannot record the job's failure"),
                }
                return Ended::Written(status);
            }
            Outcome::StoreUnavailable(message) => return Ended::StoreUnavailable(message),
            Outcome::LeaseLost => return Ended::LeaseLost,
        };
        match written {
            Ok(()) => return Ended::Written(status),
            Err(e) => outcome = Outcome::of_error(&e),
        }
    }
}

/// Stores the last metrics and the trained policy and marks the job succeeded, in one
/// transaction.
async fn store_policy(
    store: &Store,
    log: &JobLog,
    lease: &Lease<JobId>,
    trained: TrainedPolicy,
    metrics: Vec<MetricRecord>,
) -> anyhow::Result<()> {
    let TrainedPolicy { artifact, alpha_hat, step, evaluation } = trained;
    let policy_id = PolicyId::generate();
    let run = SucceededRun {
        policy_id: &policy_id,
        artifact: &artifact,
        alpha_hat,
        step,
        evaluation: evaluation.as_ref(),
    };
    log.write(LogLevel::Info, &format!("succeeded at step {step}: policy {policy_id}")).await;
    if let Some((model, version)) =
        store.finish_job_succeeded(lease, &log.worker, &metrics, &run).await?
    {
        tracing::info!(%model, version, %policy_id, "policy registered as a model version");
    }
    Ok(())
}

/// The end of a run whose job another worker took over: nothing more is written for the job;
/// the run's own attempt says what happened (the reaper recorded it as a crash).
async fn end_after_lease_lost(runner: &JobRunner, lease: &Lease<JobId>) {
    tracing::warn!(
        "another worker took the job over after this worker's lease expired; this run stops \
         without writing anything more"
    );
    let message = format!(
        "worker {} came back after its lease had expired (paused, or cut off from the \
         database) and stopped without writing",
        runner.inner.options.worker_id
    );
    if let Err(e) = runner.store().record_lease_lost(lease, &message).await {
        tracing::warn!(error = %e, "cannot record the lost lease on the job's attempt");
    }
}
