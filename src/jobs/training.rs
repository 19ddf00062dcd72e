//! One job's training run, driven from the async side: the trainer advances in chunks of steps on
//! the blocking pool ([`on_blocking`]), and between chunks the run does its store I/O (metrics,
//! checkpoints, progress, the job's log) as ordinary `.await`s. A chunk ends after the step where
//! something is due (an evaluation, a checkpoint, a progress report) or before one when the job
//! is cancelled or the worker shuts down, so the trainer takes exactly the steps, with the same
//! `record` flags, that an uninterrupted loop would: the same seed gives the same weights however
//! the run is chunked.
//!
//! The run writes no end of the job: it hands an [`Outcome`] to `worker::run_job`, which writes
//! it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use super::{EvalOptions, JobEvent, JobProgress, JobRunner, RunnerOptions};
use crate::algo::{self, Policy, Progress, Trainer};
use crate::domain::LogLevel;
use crate::domain::MetricRecord;
use crate::domain::{JobId, JobRecord};
use crate::store::evaluations::TrainingEvaluation;
use crate::store::job_runs::ProgressUpdate;
use crate::store::storage::{is_io_storage_full, is_storage_full};
use crate::store::{is_busy, Lease, Store, StoreError};

/// How often a running job's progress is written and published (and pending metrics flushed).
const PROGRESS_INTERVAL: Duration = Duration::from_millis(500);

/// How a run ended, as [`TrainingRun::drive`] hands it to `worker::run_job`. The run writes no
/// end of the job itself: `run_job` writes each (the policy, `cancelled`, `failed`, back to the queue)
/// and publishes it. A write after the end would be refused as if the lease were lost, and the
/// end would then be neither logged truly nor published.
#[derive(Debug)]
pub(super) enum Outcome {
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
    pub(super) fn of_error(e: &anyhow::Error) -> Outcome {
        if lease_lost(e) {
            Outcome::LeaseLost
        } else if store_unavailable(e) {
            Outcome::StoreUnavailable(format!("{e:#}"))
        } else {
            Outcome::Failed(format!("{e:#}"))
        }
    }
}

/// The policy a run trained, stored by `worker::run_job`.
#[derive(Debug)]
pub(super) struct TrainedPolicy {
    pub artifact: algo::PolicyArtifact,
    pub alpha_hat: Option<f64>,
    /// The step training ended at.
    pub step: u64,
    /// The evaluation the run took at that step (its job's `eval` block), stored as an
    /// evaluation of the policy.
    pub evaluation: Option<TrainingEvaluation>,
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

/// Writes a job's log lines ([`Store::append_job_log`]) as the worker holding its lease.
#[derive(Clone)]
pub(super) struct JobLog {
    store: Store,
    lease: Lease<JobId>,
    pub(super) worker: String,
}

impl JobLog {
    pub(super) fn new(runner: &JobRunner, lease: &Lease<JobId>) -> Self {
        let worker = runner.inner.options.worker_id.clone();
        JobLog { store: runner.store().clone(), lease: lease.clone(), worker }
    }

    /// Appends a line; a line that cannot be stored never stops the job (a lost lease is seen
    /// by the next fenced write anyway).
    pub(super) async fn write(&self, level: LogLevel, message: &str) {
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

    /// Whether the run stops its chunk after `step` for an evaluation or a checkpoint.
    fn due(&self, step: u64, total: u64) -> bool {
        self.eval_due(step, total).is_some() || self.options.checkpoints(step, total)
    }
}

/// What one chunk of steps did, and why it stopped.
struct Chunk {
    /// The scalars of each recorded step, with the step count after it.
    recorded: Vec<(u64, Vec<(&'static str, f64)>)>,
    stop: Stop,
}

enum Stop {
    /// Before a step: the job was cancelled or the worker shuts down.
    Interrupted,
    /// After a step: the last one, something due at it, or the progress interval over.
    Paused,
    /// A step failed (a non-finite loss, say): the message ends the job.
    StepFailed(String),
}

/// Takes steps until one is due for the async side (see [`Stop`]), on a blocking thread.
fn advance(
    trainer: &mut dyn Trainer,
    schedule: &Schedule,
    interrupted: &dyn Fn() -> bool,
    until: Instant,
) -> Chunk {
    let mut recorded = Vec::new();
    loop {
        if interrupted() {
            return Chunk { recorded, stop: Stop::Interrupted };
        }
        let progress = trainer.progress();
        let record = schedule.options.records(progress.step + 1, progress.total);
        match trainer.step(record) {
            Ok(scalars) if !scalars.is_empty() => recorded.push((trainer.progress().step, scalars)),
            Ok(_) => {}
            Err(e) => return Chunk { recorded, stop: Stop::StepFailed(e.to_string()) },
        }
        let step = trainer.progress().step;
        if trainer.is_finished() || schedule.due(step, progress.total) || Instant::now() >= until {
            return Chunk { recorded, stop: Stop::Paused };
        }
    }
}

/// Runs `work` on the trainer on the blocking pool (training is CPU-bound and must not hold an
/// async worker thread) and hands the trainer back with the result.
async fn on_blocking<T: Send + 'static>(
    mut trainer: Box<dyn Trainer>,
    work: impl FnOnce(&mut dyn Trainer) -> T + Send + 'static,
) -> anyhow::Result<(Box<dyn Trainer>, T)> {
    let joined = tokio::task::spawn_blocking(move || {
        let out = work(trainer.as_mut());
        (trainer, out)
    })
    .await;
    joined.map_err(|e| anyhow::anyhow!("the training thread panicked: {e}"))
}

/// One job's training with everything it writes on the way.
pub(super) struct TrainingRun {
    runner: JobRunner,
    job: JobRecord,
    /// Carried by every write: refused once another worker took the job over.
    lease: Lease<JobId>,
    cancel: Arc<AtomicBool>,
    /// Metrics recorded since the last write.
    pending: Vec<MetricRecord>,
    log: JobLog,
    /// The phase last written to the log.
    logged_phase: Option<&'static str>,
    alpha_logged: bool,
    /// The run's latest evaluation; the one at its last step is stored with the policy.
    last_evaluation: Option<TrainingEvaluation>,
}

impl TrainingRun {
    pub(super) fn new(
        runner: JobRunner,
        job: JobRecord,
        lease: Lease<JobId>,
        cancel: Arc<AtomicBool>,
        log: JobLog,
    ) -> Self {
        TrainingRun {
            runner,
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
    pub(super) async fn drive(mut self) -> (anyhow::Result<Outcome>, Vec<MetricRecord>) {
        let outcome = self.run().await;
        (outcome, std::mem::take(&mut self.pending))
    }

    async fn run(&mut self) -> anyhow::Result<Outcome> {
        let config = self.job.config.clone();
        let schedule = Arc::new(Schedule {
            options: self.job.runner.clone(),
            eval: self.job.eval.clone(),
            pretraining: config.pretraining_steps(),
        });
        let store = self.runner.store().clone();
        let data = super::load_training_data(
            &store,
            &self.job.unlabeled_dataset,
            self.job.non_preferred_dataset.as_ref(),
        )
        .await?;
        let inspected = (data.unlabeled.clone(), data.non_preferred.clone());
        let checkpoint = store.checkpoint(&self.job.id).await?;
        let resumed_at = checkpoint.as_ref().map_or(0, |(step, _)| *step);
        // Rows past the checkpoint are recomputed (bitwise the same) by the resumed run.
        store.discard_metrics_after(&self.lease, resumed_at).await?;
        let built = tokio::task::spawn_blocking(move || {
            algo::build_trainer(&config, &data, checkpoint.as_ref().map(|(_, b)| &b[..]))
        })
        .await
        .map_err(|e| anyhow::anyhow!("the training thread panicked: {e}"))?;
        let trainer = match built {
            Ok(trainer) => trainer,
            Err(e) => return Ok(Outcome::Failed(e.to_string())),
        };
        let threads = threads_note(self.job.config.common.threads);
        if resumed_at > 0 {
            tracing::info!(step = resumed_at, "resuming from checkpoint");
            let message = format!("resuming from the checkpoint at step {resumed_at}, {threads}");
            self.log(LogLevel::Info, message).await;
        } else {
            let (u, n) = (&self.job.unlabeled_dataset, self.job.non_preferred_dataset.as_ref());
            let n = n.map_or(String::new(), |n| format!(", non-preferred dataset {n}"));
            let total = self.job.total_steps;
            let message = format!(
                "training from scratch: {total} steps, unlabeled dataset {u}{n}, {threads}"
            );
            self.log(LogLevel::Info, message).await;
            for warning in self.data_warnings(&inspected.0, inspected.1.as_deref()).await? {
                self.log(LogLevel::Warn, warning).await;
            }
        }
        self.report_progress(trainer.progress(), AlphaNote::of(trainer.as_ref()), None).await?;
        self.train(trainer, schedule).await
    }

    /// What the job's data gives reason to check, logged once when training starts: each
    /// dataset's upload warnings, and where D^N does not look like D^U's kind of data.
    async fn data_warnings(
        &self,
        unlabeled: &crate::data::Dataset,
        non_preferred: Option<&crate::data::Dataset>,
    ) -> anyhow::Result<Vec<String>> {
        let store = self.runner.store();
        let mut warnings = Vec::new();
        let ids =
            std::iter::once(&self.job.unlabeled_dataset).chain(&self.job.non_preferred_dataset);
        for (role, id) in ["D^U", "D^N"].into_iter().zip(ids) {
            // A dataset deleted since the job loaded it has nothing more to say.
            let Some(record) = store.dataset(id).await? else { continue };
            warnings.extend(record.stats.warnings.iter().map(|w| format!("{role} ({id}): {w}")));
        }
        if let Some(non_preferred) = non_preferred {
            warnings.extend(crate::data::disagreements(unlabeled, non_preferred));
        }
        Ok(warnings)
    }

    async fn train(
        &mut self,
        mut trainer: Box<dyn Trainer>,
        schedule: Arc<Schedule>,
    ) -> anyhow::Result<Outcome> {
        let shutdown = self.runner.inner.shutdown.clone();
        let mut window = (Instant::now(), trainer.progress().step);
        while !trainer.is_finished() {
            if self.cancel.load(Ordering::Relaxed) {
                let step = trainer.progress().step;
                self.log(LogLevel::Info, format!("cancelled at step {step}")).await;
                return Ok(Outcome::Cancelled);
            }
            if shutdown.is_cancelled() {
                let step = trainer.progress().step;
                let message =
                    format!("the worker shuts down: checkpoint at step {step}, back to the queue");
                self.log(LogLevel::Info, message).await;
                self.save_checkpoint(trainer).await?;
                return Ok(Outcome::Released);
            }
            let total = trainer.progress().total;
            let interrupted = interruption(&self.cancel, &shutdown);
            let chunk_schedule = schedule.clone();
            let until = window.0 + PROGRESS_INTERVAL;
            let chunk;
            (trainer, chunk) =
                on_blocking(trainer, move |t| advance(t, &chunk_schedule, &interrupted, until))
                    .await?;
            for (step, scalars) in &chunk.recorded {
                self.record(*step, scalars);
            }
            match chunk.stop {
                Stop::Interrupted => continue,
                Stop::StepFailed(message) => return Ok(Outcome::Failed(message)),
                Stop::Paused => {}
            }
            let step = trainer.progress().step;
            if let Some(eval) = schedule.eval_due(step, total) {
                let evaluated;
                (trainer, evaluated) = self.evaluate(trainer, eval.clone(), step).await?;
                match evaluated {
                    EvalOutcome::Recorded => {}
                    // The loop's next turn sees the cancel flag.
                    EvalOutcome::Interrupted if !shutdown.is_cancelled() => continue,
                    // Back to the last checkpoint: the resumed run recomputes this step and its
                    // evaluation bitwise the same.
                    EvalOutcome::Interrupted => return Ok(Outcome::Released),
                    EvalOutcome::Failed(message) => return Ok(Outcome::Failed(message)),
                }
            }
            if schedule.options.checkpoints(step, total) {
                trainer = self.save_checkpoint(trainer).await?;
            }
            if window.0.elapsed() >= PROGRESS_INTERVAL {
                let speed = (step - window.1) as f64 / window.0.elapsed().as_secs_f64();
                self.flush_metrics().await?;
                let (progress, alpha) = (trainer.progress(), AlphaNote::of(trainer.as_ref()));
                if self.report_progress(progress, alpha, Some(speed)).await? {
                    self.cancel.store(true, Ordering::Relaxed);
                }
                window = (Instant::now(), step);
            }
        }
        self.log_milestones(&trainer.progress(), AlphaNote::of(trainer.as_ref())).await;
        let step = trainer.progress().step;
        let (trainer, artifact) = on_blocking(trainer, |t| t.export_policy()).await?;
        let trained = TrainedPolicy {
            artifact: artifact?,
            alpha_hat: trainer.alpha_hat(),
            step,
            // The schedule evaluates at the last step, which no checkpoint precedes in another
            // run, so a run that reaches the end has taken it.
            evaluation: self.last_evaluation.take().filter(|e| e.step == step),
        };
        Ok(Outcome::Succeeded(Box::new(trained)))
    }

    /// Evaluates the current policy (on the blocking pool) and records the paper's metrics at
    /// `step` (`eval/...`).
    async fn evaluate(
        &mut self,
        trainer: Box<dyn Trainer>,
        eval: EvalOptions,
        step: u64,
    ) -> anyhow::Result<(Box<dyn Trainer>, EvalOutcome)> {
        let interrupted = interruption(&self.cancel, &self.runner.inner.shutdown);
        let spec = eval.spec();
        let started = Instant::now();
        let (trainer, result) = on_blocking(trainer, move |t| -> anyhow::Result<_> {
            let artifact = t.export_policy()?;
            let policy = Policy::load(&artifact.spec, &artifact.weights)?;
            Ok(super::evaluate_policy(&policy, &spec, &interrupted))
        })
        .await?;
        let outcome = match result? {
            Ok(report) => {
                let m = &report.metrics;
                let seconds = started.elapsed().as_secs_f64();
                tracing::debug!(
                    step,
                    normalized_return = m.normalized_return,
                    average_cost = m.average_cost,
                    seconds,
                    "evaluated"
                );
                let message = format!(
                    "evaluation at step {step} on {}: normalized return {:.2}, average cost \
                     {:.3} ({seconds:.1} s)",
                    eval.env, m.normalized_return, m.average_cost,
                );
                self.log(LogLevel::Info, message).await;
                self.record(step, &m.named_values());
                self.last_evaluation = Some(TrainingEvaluation { step, report });
                EvalOutcome::Recorded
            }
            Err(_) if self.interrupted() => EvalOutcome::Interrupted,
            Err(e) => EvalOutcome::Failed(format!("evaluation at step {step} failed: {e}")),
        };
        Ok((trainer, outcome))
    }

    fn interrupted(&self) -> bool {
        self.cancel.load(Ordering::Relaxed) || self.runner.inner.shutdown.is_cancelled()
    }

    /// Keeps the finite scalars of a recorded step (non-finite ones end the run in the trainer).
    fn record(&mut self, step: u64, scalars: &[(&'static str, f64)]) {
        if scalars.is_empty() {
            return;
        }
        let time = chrono::Utc::now();
        self.pending.extend(scalars.iter().filter(|(_, v)| v.is_finite()).map(|(name, value)| {
            MetricRecord { name: (*name).to_owned(), step, value: *value, time }
        }));
    }

    async fn flush_metrics(&mut self) -> anyhow::Result<()> {
        let rows = std::mem::take(&mut self.pending);
        self.runner.store().insert_metrics(&self.lease, &rows).await?;
        Ok(())
    }

    /// Saves a checkpoint with the metrics recorded since the last write (the trainer's state
    /// serialised on the blocking pool) and hands the trainer back.
    async fn save_checkpoint(
        &mut self,
        trainer: Box<dyn Trainer>,
    ) -> anyhow::Result<Box<dyn Trainer>> {
        let (trainer, bytes) = on_blocking(trainer, |t| t.checkpoint()).await?;
        let bytes = bytes?;
        let rows = std::mem::take(&mut self.pending);
        let step = trainer.progress().step;
        self.runner.store().save_checkpoint(&self.lease, step, &bytes, &rows).await?;
        tracing::debug!(step, bytes = bytes.len(), "checkpoint saved");
        self.log(LogLevel::Info, format!("checkpoint at step {step} ({} bytes)", bytes.len()))
            .await;
        Ok(trainer)
    }

    async fn log(&self, level: LogLevel, message: String) {
        self.log.write(level, &message).await;
    }

    /// Logs the start of each phase, and alpha-hat (Eq. 15) with how it was estimated and the
    /// weighting it led to, once known.
    async fn log_milestones(&mut self, p: &Progress, alpha: AlphaNote) {
        if self.logged_phase != Some(p.phase) {
            self.logged_phase = Some(p.phase);
            self.log(LogLevel::Info, format!("phase {} from step {}", p.phase, p.step)).await;
        }
        let Some(value) = alpha.value.filter(|_| !self.alpha_logged) else { return };
        self.alpha_logged = true;
        let detail = alpha.detail.map_or(String::new(), |d| format!(" ({d})"));
        self.log(LogLevel::Info, format!("alpha-hat (Eq. 15) = {value:.4}{detail}")).await;
        if let Some(reason) = alpha.uniform_reason {
            let message = format!("weighting: uniform, {reason}: the policy is trained as BC");
            self.log(LogLevel::Warn, message).await;
        }
    }

    /// Writes and publishes progress; returns whether a cancel was requested in the database.
    async fn report_progress(
        &mut self,
        p: Progress,
        alpha: AlphaNote,
        speed: Option<f64>,
    ) -> anyhow::Result<bool> {
        let alpha_hat = alpha.value;
        self.log_milestones(&p, alpha).await;
        let update = ProgressUpdate {
            step: p.step,
            phase: p.phase,
            iterations_per_second: speed,
            alpha_hat,
        };
        let cancel = self.runner.store().update_progress(&self.lease, &update).await?;
        self.runner.publish(JobEvent::Progress {
            job_id: self.job.id.clone(),
            progress: JobProgress::new(p.step, p.total, Some(p.phase.to_owned()), speed),
        });
        Ok(cancel)
    }
}

/// How an evaluation during training ended.
enum EvalOutcome {
    Recorded,
    /// A cancel or shutdown stopped it; nothing was recorded.
    Interrupted,
    Failed(String),
}

/// Whether the job was cancelled or the worker shuts down, readable from a blocking thread.
fn interruption(
    cancel: &Arc<AtomicBool>,
    shutdown: &CancellationToken,
) -> impl Fn() -> bool + Send + 'static {
    let (cancel, shutdown) = (cancel.clone(), shutdown.clone());
    move || cancel.load(Ordering::Relaxed) || shutdown.is_cancelled()
}

/// alpha-hat as the job log tells it: the value, how it was estimated, and the weighting.
struct AlphaNote {
    value: Option<f64>,
    detail: Option<String>,
    uniform_reason: Option<String>,
}

impl AlphaNote {
    fn of(trainer: &dyn Trainer) -> AlphaNote {
        AlphaNote {
            value: trainer.alpha_hat(),
            detail: trainer.alpha_hat_detail(),
            uniform_reason: trainer.uniform_weighting_reason(),
        }
    }
}

/// The job log's word on a job's `threads` and what this worker runs them on.
fn threads_note(threads: usize) -> String {
    let here = threads.min(algo::job_thread_cap());
    match (threads, here) {
        (1, _) => "1 thread".to_owned(),
        (t, h) if t == h => format!("{t} threads"),
        (t, h) => format!("{t} threads (run on this worker's {h}: the same weights, more slowly)"),
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
