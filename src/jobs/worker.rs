//! One worker: claim a job, drive its trainer on a blocking thread, store what it produces.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::runtime::Handle;

use super::fleet::LeaseKeeper;
use super::{EvalOptions, JobEvent, JobProgress, JobRunner, RunnerOptions};
use crate::algo::{self, Policy, Trainer};
use crate::domain::{JobRecord, JobStatus, PolicyId};
use crate::store::evaluations::TrainingEvaluation;
use crate::store::jobs::{MetricRow, ProgressUpdate};
use crate::store::leases::LeaseTable;
use crate::store::logs::LogLevel;
use crate::store::now;
use crate::store::policies::NewPolicy;
use crate::store::storage::{is_io_storage_full, is_storage_full};
use crate::store::{is_busy, Lease, Store, StoreError};

/// How often a running job's progress is written and published (and pending metrics flushed).
const PROGRESS_INTERVAL: Duration = Duration::from_millis(500);

/// How a run ended, as the training thread hands it to [`run_job`]. The thread writes no end of
/// the job itself: `run_job` writes each (the policy, `cancelled`, `failed`, back to the queue)
/// and publishes it. A write after the end would be refused as if the lease were lost, and the
/// end would then be neither logged truly nor published.
#[derive(Debug)]
enum Outcome {
    /// Trained to the end: the policy to store.
    Succeeded(Box<TrainedPolicy>),
    Cancelled,
    Failed(String),
    /// Shutdown: checkpointed (or, mid-evaluation, left at its last checkpoint), to go back to
    /// the queue.
    Released,
    /// A write of the run failed because the store could not take it (full disk, SQLITE_FULL,
    /// a lock held past the busy timeout, the database connection lost): nothing is wrong with
    /// the job, so it goes back to the queue and resumes from its last checkpoint once the store
    /// takes writes again (or, if the database stays away longer than the lease, another worker
    /// takes it over).
    StoreUnavailable(String),
    /// Another worker took the job over (this worker's lease expired): nothing more is written.
    LeaseLost,
}

impl Outcome {
    /// The outcome of a run (or of writing its end) that stopped on `e`.
    fn of_error(e: &anyhow::Error) -> Outcome {
        if lease_lost(e) {
            Outcome::LeaseLost
        } else if store_unavailable(e) {
            Outcome::StoreUnavailable(format!("{e:#}"))
        } else {
            Outcome::Failed(format!("{e:#}"))
        }
    }
}

/// The policy a run trained, exported on the training thread, stored by [`run_job`].
#[derive(Debug)]
struct TrainedPolicy {
    artifact: algo::PolicyArtifact,
    alpha_hat: Option<f64>,
    /// The step training ended at.
    step: u64,
    /// The evaluation the run took at that step (its job's `eval` block), stored as an
    /// evaluation of the policy.
    evaluation: Option<TrainingEvaluation>,
}

/// What writing a run's end came to.
enum Ended {
    /// The job's end (or, after a shutdown, its return to the queue) is stored.
    Written(JobStatus),
    /// The store could not take the end's write: the job goes back to the queue.
    StoreUnavailable(String),
    LeaseLost,
}

/// Whether a run's error is a write refused because another worker holds the job now.
fn lease_lost(e: &anyhow::Error) -> bool {
    e.chain().any(|cause| matches!(cause.downcast_ref(), Some(StoreError::LeaseLost(_))))
}

/// Whether a run's error is the store failing to take a write for want of room, a lock or its
/// connection, not a fault of the job (anywhere in the error's chain of causes).
fn store_unavailable(e: &anyhow::Error) -> bool {
    e.chain().any(|cause| {
        if let Some(e) = cause.downcast_ref::<StoreError>() {
            e.is_storage_full() || e.is_busy()
        } else if let Some(e) = cause.downcast_ref::<sqlx::Error>() {
            is_storage_full(e) || is_busy(e)
        } else if let Some(e) = cause.downcast_ref::<std::io::Error>() {
            is_io_storage_full(e)
        } else {
            false
        }
    })
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
                runner.pause_for_storage();
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
async fn run_job(runner: &JobRunner, job: JobRecord, lease: Lease) {
    let id = job.id.clone();
    let cancel = runner.register_cancel_flag(&id);
    // A cancel may have been requested between the claim and the flag's registration.
    if job.cancel_requested {
        cancel.store(true, Ordering::Relaxed);
    }
    let keeper = LeaseKeeper::start(
        runner.store().clone(),
        LeaseTable::Jobs,
        lease.clone(),
        &runner.inner.options,
        cancel.clone(),
    );
    runner.publish(JobEvent::Status { job_id: id.clone(), status: JobStatus::Running });
    tracing::info!("job started");
    let log = JobLog::new(runner, &lease);
    let attempt = format!("attempt {} of {}", job.attempt, job.max_attempts);
    log.write(LogLevel::Info, &format!("claimed by worker {} ({attempt})", log.worker)).await;
    let run = TrainingRun::new(runner.clone(), Handle::current(), job, lease.clone(), cancel);
    let (outcome, metrics) = match tokio::task::spawn_blocking(move || run.drive()).await {
        Ok((Ok(outcome), metrics)) => (outcome, metrics),
        Ok((Err(e), metrics)) => (Outcome::of_error(&e), metrics),
        Err(e) => (Outcome::Failed(format!("the training thread panicked: {e}")), Vec::new()),
    };
    // While the lease is still kept alive: a slow write of the end does not lose the job.
    let ended = write_end(runner, &log, &lease, outcome, metrics).await;
    drop(keeper);
    runner.forget_cancel_flag(&id);
    if !matches!(ended, Ended::StoreUnavailable(_) | Ended::Written(JobStatus::Queued)) {
        runner.storage_recovered();
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
            runner.pause_for_storage();
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
    lease: &Lease,
    mut outcome: Outcome,
    mut metrics: Vec<MetricRow>,
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

/// Stores the trained policy with the last metrics and marks the job succeeded.
async fn store_policy(
    store: &Store,
    log: &JobLog,
    lease: &Lease,
    trained: TrainedPolicy,
    metrics: Vec<MetricRow>,
) -> anyhow::Result<()> {
    // In first: the policy's final metrics are the last values stored.
    store.insert_metrics(lease, &metrics).await?;
    let last: serde_json::Map<String, serde_json::Value> = store
        .last_metric_values(&lease.id)
        .await?
        .into_iter()
        .map(|(name, value)| (name, value.into()))
        .collect();
    let TrainedPolicy { artifact, alpha_hat, step, evaluation } = trained;
    let policy_id = PolicyId::generate();
    let policy = NewPolicy {
        id: &policy_id,
        job_id: &lease.id,
        algorithm: artifact.spec.algorithm.as_str(),
        obs_dim: artifact.spec.obs_dim,
        action_space: &serde_json::to_string(&artifact.spec.action_space)?,
        spec: &serde_json::to_string(&artifact.spec)?,
        weights: &artifact.weights,
        final_metrics: &serde_json::Value::Object(last).to_string(),
        alpha_hat,
    };
    log.write(LogLevel::Info, &format!("succeeded at step {step}: policy {policy_id}")).await;
    if let Some(register) = store.job(&lease.id).await?.register {
        let alias = register.alias.as_deref().map(|a| format!(", alias {a} moved to it"));
        let message = format!(
            "registering the policy as the next version of model {}{}",
            register.model,
            alias.unwrap_or_default()
        );
        log.write(LogLevel::Info, &message).await;
    }
    if let Some((model, version)) =
        store.finish_job_succeeded(lease, &[], &policy, step, evaluation.as_ref()).await?
    {
        tracing::info!(%model, version, %policy_id, "policy registered as a model version");
    }
    Ok(())
}

/// The end of a run whose job another worker took over: nothing more is written for the job;
/// the run's own attempt says what happened (the reaper recorded it as a crash).
async fn end_after_lease_lost(runner: &JobRunner, lease: &Lease) {
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

/// Writes a job's log lines ([`Store::append_job_log`]) as the worker holding its lease.
#[derive(Clone)]
struct JobLog {
    store: Store,
    lease: Lease,
    worker: String,
}

impl JobLog {
    fn new(runner: &JobRunner, lease: &Lease) -> Self {
        let worker = runner.inner.options.worker_id.clone();
        JobLog { store: runner.store().clone(), lease: lease.clone(), worker }
    }

    /// Appends a line; a line that cannot be stored never stops the job (a lost lease is seen
    /// by the next fenced write anyway).
    async fn write(&self, level: LogLevel, message: &str) {
        match self.store.append_job_log(&self.lease, &self.worker, level, message).await {
            Ok(()) | Err(StoreError::LeaseLost(_)) => {}
            Err(e) => tracing::warn!(error = %e, "cannot write the job's log"),
        }
    }
}

/// When a run records, checkpoints and evaluates.
struct Schedule {
    options: RunnerOptions,
    eval: Option<EvalOptions>,
    /// Steps before policy learning starts (not evaluated).
    pretraining: u64,
}

impl Schedule {
    /// The eval block if an evaluation is due after `step` steps.
    fn eval_due(&self, step: u64, total: u64) -> Option<&EvalOptions> {
        self.eval.as_ref().filter(|eval| eval.due(step, self.pretraining, total))
    }
}

/// How an evaluation during training ended.
enum EvalOutcome {
    Recorded,
    /// A cancel or shutdown stopped it; nothing was recorded.
    Interrupted,
    Failed(String),
}

/// One job's training, on a blocking thread; talks to the store through the runtime handle.
struct TrainingRun {
    runner: JobRunner,
    rt: Handle,
    job: JobRecord,
    /// Carried by every write: refused once another worker took the job over.
    lease: Lease,
    cancel: Arc<AtomicBool>,
    /// Metrics recorded since the last write.
    pending: Vec<MetricRow>,
    log: JobLog,
    /// The phase last written to the log.
    logged_phase: Option<&'static str>,
    alpha_logged: bool,
    /// The run's latest evaluation; the one at its last step is stored with the policy.
    last_evaluation: Option<TrainingEvaluation>,
}

impl TrainingRun {
    fn new(
        runner: JobRunner,
        rt: Handle,
        job: JobRecord,
        lease: Lease,
        cancel: Arc<AtomicBool>,
    ) -> Self {
        let log = JobLog::new(&runner, &lease);
        TrainingRun {
            runner,
            rt,
            job,
            lease,
            cancel,
            pending: Vec::new(),
            log,
            logged_phase: None,
            alpha_logged: false,
            last_evaluation: None,
        }
    }

    /// Trains until the run ends; hands back how, with the metrics recorded since the last
    /// write (stored with the job's end).
    fn drive(mut self) -> (anyhow::Result<Outcome>, Vec<MetricRow>) {
        let outcome = self.run();
        (outcome, std::mem::take(&mut self.pending))
    }

    fn run(&mut self) -> anyhow::Result<Outcome> {
        let config = &self.job.config;
        let schedule = Schedule {
            options: self.job.runner.clone(),
            eval: self.job.eval.clone(),
            pretraining: config.pretraining_steps(),
        };
        let store = self.runner.store().clone();
        let data = self.rt.block_on(super::load_training_data(
            &store,
            &self.job.unlabeled_dataset,
            self.job.non_preferred_dataset.as_deref(),
        ))?;
        let checkpoint = self.rt.block_on(store.checkpoint(&self.job.id))?;
        let resumed_at = checkpoint.as_ref().map_or(0, |(step, _)| *step);
        // Rows past the checkpoint are recomputed (bitwise the same) by the resumed run.
        self.rt.block_on(store.discard_metrics_after(&self.lease, resumed_at))?;
        let mut trainer =
            match algo::build_trainer(config, &data, checkpoint.as_ref().map(|(_, b)| &b[..])) {
                Ok(trainer) => trainer,
                Err(e) => return Ok(Outcome::Failed(e.to_string())),
            };
        if resumed_at > 0 {
            tracing::info!(step = resumed_at, "resuming from checkpoint");
            self.log(LogLevel::Info, format!("resuming from the checkpoint at step {resumed_at}"));
        } else {
            let (u, n) = (&self.job.unlabeled_dataset, self.job.non_preferred_dataset.as_ref());
            let n = n.map_or(String::new(), |n| format!(", non-preferred dataset {n}"));
            let total = self.job.total_steps;
            self.log(
                LogLevel::Info,
                format!("training from scratch: {total} steps, unlabeled dataset {u}{n}"),
            );
        }
        self.report_progress(trainer.as_ref(), None)?;
        self.train(trainer.as_mut(), &schedule)
    }

    fn train(&mut self, trainer: &mut dyn Trainer, schedule: &Schedule) -> anyhow::Result<Outcome> {
        let options = &schedule.options;
        let shutdown = self.runner.inner.shutdown.clone();
        let mut window = (Instant::now(), trainer.progress().step);
        while !trainer.is_finished() {
            if self.cancel.load(Ordering::Relaxed) {
                let step = trainer.progress().step;
                self.log(LogLevel::Info, format!("cancelled at step {step}"));
                return Ok(Outcome::Cancelled);
            }
            if shutdown.is_cancelled() {
                let step = trainer.progress().step;
                self.log(
                    LogLevel::Info,
                    format!("the worker shuts down: checkpoint at step {step}, back to the queue"),
                );
                self.save_checkpoint(trainer)?;
                return Ok(Outcome::Released);
            }
            let progress = trainer.progress();
            let record = options.records(progress.step + 1, progress.total);
            let scalars = match trainer.step(record) {
                Ok(scalars) => scalars,
                Err(e) => return Ok(Outcome::Failed(e.to_string())),
            };
            let step = trainer.progress().step;
            self.record(step, &scalars);
            if let Some(eval) = schedule.eval_due(step, progress.total) {
                match self.evaluate(trainer, eval, step)? {
                    EvalOutcome::Recorded => {}
                    // The loop's next turn sees the cancel flag.
                    EvalOutcome::Interrupted if !shutdown.is_cancelled() => continue,
                    // Back to the last checkpoint: the resumed run recomputes this step and its
                    // evaluation bitwise the same.
                    EvalOutcome::Interrupted => return Ok(Outcome::Released),
                    EvalOutcome::Failed(message) => return Ok(Outcome::Failed(message)),
                }
            }
            if options.checkpoints(step, progress.total) {
                self.save_checkpoint(trainer)?;
            }
            if window.0.elapsed() >= PROGRESS_INTERVAL {
                let speed = (step - window.1) as f64 / window.0.elapsed().as_secs_f64();
                self.flush_metrics()?;
                if self.report_progress(trainer, Some(speed))? {
                    self.cancel.store(true, Ordering::Relaxed);
                }
                window = (Instant::now(), step);
            }
        }
        self.log_milestones(trainer);
        let step = trainer.progress().step;
        let trained = TrainedPolicy {
            artifact: trainer.export_policy()?,
            alpha_hat: trainer.alpha_hat(),
            step,
            // The schedule evaluates at the last step, which no checkpoint precedes in another
            // run, so a run that reaches the end has taken it.
            evaluation: self.last_evaluation.take().filter(|e| e.step == step),
        };
        Ok(Outcome::Succeeded(Box::new(trained)))
    }

    /// Evaluates the current policy and records the paper's metrics at `step` (`eval/...`).
    fn evaluate(
        &mut self,
        trainer: &dyn Trainer,
        eval: &EvalOptions,
        step: u64,
    ) -> anyhow::Result<EvalOutcome> {
        let artifact = trainer.export_policy()?;
        let policy = Policy::load(&artifact.spec, &artifact.weights)?;
        let shutdown = self.runner.inner.shutdown.clone();
        let interrupted = || self.cancel.load(Ordering::Relaxed) || shutdown.is_cancelled();
        let started = Instant::now();
        match super::evaluate_policy(&policy, &eval.spec(), &interrupted) {
            Ok(report) => {
                let m = &report.metrics;
                tracing::debug!(
                    step,
                    normalized_return = m.normalized_return,
                    average_cost = m.average_cost,
                    seconds = started.elapsed().as_secs_f64(),
                    "evaluated"
                );
                self.log(
                    LogLevel::Info,
                    format!(
                        "evaluation at step {step} on {}: normalized return {:.2}, average cost \
                         {:.3} ({:.1} s)",
                        eval.env,
                        m.normalized_return,
                        m.average_cost,
                        started.elapsed().as_secs_f64()
                    ),
                );
                self.record(step, &m.named_values());
                self.last_evaluation = Some(TrainingEvaluation { step, report });
                Ok(EvalOutcome::Recorded)
            }
            Err(_) if interrupted() => Ok(EvalOutcome::Interrupted),
            Err(e) => Ok(EvalOutcome::Failed(format!("evaluation at step {step} failed: {e}"))),
        }
    }

    /// Keeps the finite scalars of a recorded step (non-finite ones end the run in the trainer).
    fn record(&mut self, step: u64, scalars: &[(&'static str, f64)]) {
        if scalars.is_empty() {
            return;
        }
        let time = now();
        self.pending.extend(scalars.iter().filter(|(_, v)| v.is_finite()).map(|(name, value)| {
            MetricRow {
                name: (*name).to_owned(),
                step: step as i64,
                value: *value,
                time: time.clone(),
            }
        }));
    }

    fn flush_metrics(&mut self) -> anyhow::Result<()> {
        let rows = std::mem::take(&mut self.pending);
        self.rt.block_on(self.runner.store().insert_metrics(&self.lease, &rows))?;
        Ok(())
    }

    fn save_checkpoint(&mut self, trainer: &dyn Trainer) -> anyhow::Result<()> {
        let bytes = trainer.checkpoint()?;
        let rows = std::mem::take(&mut self.pending);
        let step = trainer.progress().step;
        self.rt.block_on(self.runner.store().save_checkpoint(&self.lease, step, &bytes, &rows))?;
        tracing::debug!(step, bytes = bytes.len(), "checkpoint saved");
        self.log(LogLevel::Info, format!("checkpoint at step {step} ({} bytes)", bytes.len()));
        Ok(())
    }

    /// Writes a line to the job's log (from the training thread).
    fn log(&self, level: LogLevel, message: String) {
        self.rt.block_on(self.log.write(level, &message));
    }

    /// Logs the start of each phase and alpha-hat (Eq. 15) once known.
    fn log_milestones(&mut self, trainer: &dyn Trainer) {
        let p = trainer.progress();
        if self.logged_phase != Some(p.phase) {
            self.logged_phase = Some(p.phase);
            self.log(LogLevel::Info, format!("phase {} from step {}", p.phase, p.step));
        }
        if let Some(alpha) = trainer.alpha_hat().filter(|_| !self.alpha_logged) {
            self.alpha_logged = true;
            self.log(LogLevel::Info, format!("alpha-hat (Eq. 15) = {alpha:.4}"));
        }
    }

    /// Writes and publishes progress; returns whether a cancel was requested in the database.
    fn report_progress(
        &mut self,
        trainer: &dyn Trainer,
        speed: Option<f64>,
    ) -> anyhow::Result<bool> {
        self.log_milestones(trainer);
        let p = trainer.progress();
        let update = ProgressUpdate {
            step: p.step,
            phase: p.phase,
            iterations_per_second: speed,
            alpha_hat: trainer.alpha_hat(),
        };
        let cancel = self.rt.block_on(self.runner.store().update_progress(&self.lease, &update))?;
        self.runner.publish(JobEvent::Progress {
            job_id: self.job.id.clone(),
            progress: JobProgress::new(p.step, p.total, Some(p.phase.to_owned()), speed),
        });
        Ok(cancel)
    }
}

#[cfg(test)]
mod tests {
    use anyhow::Context;

    use super::*;

    #[test]
    fn a_full_disk_or_a_busy_database_anywhere_in_the_chain_is_the_store_not_the_job() {
        let full = StoreError::Io(std::io::Error::from(std::io::ErrorKind::StorageFull));
        let full = Err::<(), _>(full).context("saving the checkpoint").unwrap_err();
        assert!(store_unavailable(&full));
        let busy = anyhow::Error::from(StoreError::Database(sqlx::Error::PoolTimedOut));
        assert!(store_unavailable(&busy.context("recording progress")));
        let reset = std::io::Error::from(std::io::ErrorKind::ConnectionReset);
        let lost = anyhow::Error::from(StoreError::Database(sqlx::Error::Io(reset)));
        assert!(store_unavailable(&lost.context("saving the checkpoint")));
        let corrupt = StoreError::Corrupt("d".into(), "changed on disk".into());
        assert!(!store_unavailable(&anyhow::Error::from(corrupt)));
        assert!(!store_unavailable(&anyhow::anyhow!("the evaluation at step 10 failed")));
    }
}
