//! Many processes, one queue: this process's worker identity and its row in the worker
//! registry, the lease heartbeat of each running job or evaluation, the task that brings jobs
//! run by other processes to this process's event streams, and the PostgreSQL notifications
//! that make all of it prompt (polling stays the fallback, and the only way on SQLite).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::task::JoinHandle;

use super::announcements::{Announcement, CHANNEL};
use super::events::Followed;
use super::{JobEvent, JobRunner};
use crate::domain::attempt::MemorySample;
use crate::domain::{JobId, JobRecord, JobStatus, RetryBackoff};
use crate::store::leases::{host_name, Leased};
use crate::store::{Lease, Store, StoreError};

/// How this process takes part in the shared queue.
#[derive(Clone, Debug)]
pub struct WorkerOptions {
    /// Training jobs this process runs at once (0: none, and no evaluations: an API-only node).
    pub workers: usize,
    /// How long a lease lasts without a heartbeat: a worker that stops renewing (killed, its
    /// machine lost, paused) loses its jobs to other workers this long after its last renewal.
    pub lease: Duration,
    /// Names this process in leases, logs and /metrics: `<host>-<pid>-<random>`.
    pub worker_id: String,
    /// Free space the data directory needs before paused training resumes (`--min-free-disk`).
    pub min_free_disk: u64,
    /// How long a job whose worker vanished waits before its next attempt.
    pub retry_backoff: RetryBackoff,
    /// The most threads one job computes on here (`--job-threads`).
    pub job_threads: usize,
}

impl WorkerOptions {
    pub fn new(workers: usize, lease: Duration, min_free_disk: u64) -> Self {
        let suffix = uuid::Uuid::new_v4().simple().to_string();
        let worker_id = format!("{}-{}-{}", host_name(), std::process::id(), &suffix[..6]);
        let retry_backoff = RetryBackoff::new(RetryBackoff::DEFAULT_BASE);
        let job_threads = crate::algo::job_threads(None, workers);
        WorkerOptions { workers, lease, worker_id, min_free_disk, retry_backoff, job_threads }
    }

    pub fn with_job_threads(mut self, job_threads: usize) -> Self {
        self.job_threads = job_threads.max(1);
        self
    }

    pub fn with_retry_backoff(mut self, retry_backoff: RetryBackoff) -> Self {
        self.retry_backoff = retry_backoff;
        self
    }

    /// How often leases and the registry row are renewed: three renewals fit in one lease, so
    /// one slow or failed renewal does not lose it.
    pub fn heartbeat(&self) -> Duration {
        self.lease / 3
    }
}

/// Keeps a lease alive while its run goes on (stops when dropped). Once another worker has
/// taken the lease over, it sets `on_lost` (the run's cancel flag: the run stops, and its
/// writes are refused anyway).
pub(super) struct LeaseKeeper {
    task: JoinHandle<()>,
}

impl LeaseKeeper {
    pub(super) fn start<I: Leased + Send + Sync + 'static>(
        store: Store,
        lease: Lease<I>,
        options: &WorkerOptions,
        on_lost: Arc<AtomicBool>,
    ) -> Self {
        let (duration, every) = (options.lease, options.heartbeat());
        let task = tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                match store.renew_lease(&lease, duration).await {
                    Ok(()) => {}
                    // Also once the run ended its job (the row is no longer `running`): the
                    // flag then stops nothing.
                    Err(StoreError::LeaseLost(_)) => {
                        tracing::debug!(id = %lease.id, "the lease is no longer held");
                        on_lost.store(true, Ordering::Relaxed);
                        return;
                    }
                    Err(e) => tracing::warn!(id = %lease.id, error = %e, "cannot renew the lease"),
                }
            }
        });
        LeaseKeeper { task }
    }
}

impl Drop for LeaseKeeper {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Adds this process to the worker registry (and forgets workers silent for ten leases).
pub(super) async fn register(runner: &JobRunner) -> Result<(), StoreError> {
    let options = &runner.inner.options;
    runner.store().register_worker(&options.worker_id, options.workers, options.lease * 10).await
}

/// Renews this process's registry row until shutdown.
pub(super) async fn registry_heartbeat(runner: JobRunner) {
    let options = runner.inner.options.clone();
    while !super::sleep_unless_shutdown(&runner.inner.shutdown, options.heartbeat()).await {
        let memory = memory_sample();
        if let Err(e) = runner.store().worker_heartbeat(&options.worker_id, memory).await {
            tracing::warn!(error = %e, "cannot record the worker heartbeat");
        }
    }
}

/// This process's resident memory and what it could still take: the machine's available memory,
/// or less where a cgroup (v2) limit is nearer. None off Linux.
fn memory_sample() -> Option<MemorySample> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let rss_bytes = kib_field(&status, "VmRSS:")? * 1024;
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let mut available_bytes = kib_field(&meminfo, "MemAvailable:")? * 1024;
    if let Some(cgroup_left) = cgroup_memory_left() {
        available_bytes = available_bytes.min(cgroup_left);
    }
    Some(MemorySample { rss_bytes, available_bytes })
}

/// A `Name:   1234 kB` field of a /proc file, in KiB.
fn kib_field(text: &str, name: &str) -> Option<u64> {
    let line = text.lines().find(|line| line.starts_with(name))?;
    line[name.len()..].split_whitespace().next()?.parse().ok()
}

/// `memory.max - memory.current` of this process's cgroup (v2), when it has a limit.
fn cgroup_memory_left() -> Option<u64> {
    let cgroup = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let path = cgroup.lines().find_map(|line| line.strip_prefix("0::"))?;
    let dir = std::path::Path::new("/sys/fs/cgroup").join(path.trim_start_matches('/'));
    let read = |name: &str| std::fs::read_to_string(dir.join(name)).ok();
    let max: u64 = read("memory.max")?.trim().parse().ok()?;
    let current: u64 = read("memory.current")?.trim().parse().ok()?;
    Some(max.saturating_sub(current))
}

/// Listens for the other processes' announcements (PostgreSQL) until shutdown.
pub(super) async fn listen(runner: JobRunner) {
    let shutdown = runner.inner.shutdown.clone();
    let store = runner.inner.store.clone();
    let dispatch = |payload: String| {
        dispatch(&runner, &payload);
        std::future::ready(())
    };
    store.listen(CHANNEL, &shutdown, Duration::from_secs(1), dispatch).await;
}

fn dispatch(runner: &JobRunner, payload: &str) {
    match Announcement::parse(payload) {
        Some(Announcement::JobQueued) => runner.inner.wake.notify_one(),
        Some(Announcement::EvaluationQueued) => runner.inner.evaluator.wake_local(),
        Some(Announcement::Cancel(id)) => {
            runner.inner.cancels.raise(&JobId::from(id));
        }
        Some(Announcement::Changed(_)) => runner.inner.events.followed.changed.notify_one(),
        None => tracing::debug!(payload, "unknown notification"),
    }
}

/// How often an API node looks for changes of jobs that other processes run (a PostgreSQL
/// notification makes it look at once).
const FOLLOW_POLL: Duration = Duration::from_millis(500);
/// How far back each look reaches before the newest change it has seen: rows committed late
/// (a transaction that took its time stamp before another's) or stamped by a machine whose
/// clock is behind are still seen; what was already published is not published again.
const FOLLOW_OVERLAP: chrono::TimeDelta = chrono::TimeDelta::seconds(5);

/// Publishes progress and status changes of jobs run by other processes to this process's
/// event streams, until shutdown.
pub(super) async fn follow_jobs(runner: JobRunner) {
    let shutdown = runner.inner.shutdown.clone();
    // The stamps compared are the database's (see `store::now_in`), so the start is too.
    let mut newest = match runner.store().db_now().await {
        Ok(now) => now,
        Err(e) => {
            tracing::warn!(error = %e, "cannot read the database's clock; starting from this machine's");
            crate::domain::rfc3339(&chrono::Utc::now())
        }
    };
    loop {
        tokio::select! {
            () = shutdown.cancelled() => return,
            () = runner.inner.events.followed.changed.notified() => {}
            () = tokio::time::sleep(FOLLOW_POLL) => {}
        }
        // Nobody watching: nothing to publish, and a stream opened later starts from the job
        // as stored.
        if !runner.inner.events.watched() {
            continue;
        }
        let since = overlap_before(&newest);
        match runner.store().jobs_changed_since(&since).await {
            Ok(jobs) => {
                for job in jobs {
                    newest = newest.max(crate::domain::rfc3339(&job.updated_at));
                    publish_change(&runner, job);
                }
                forget_older_than(&runner.inner.events.followed, &since);
            }
            Err(e) => tracing::warn!(error = %e, "cannot read the jobs' changes"),
        }
    }
}

fn overlap_before(time: &str) -> String {
    chrono::DateTime::parse_from_rfc3339(time)
        .map(|t| crate::domain::rfc3339(&(t.with_timezone(&chrono::Utc) - FOLLOW_OVERLAP)))
        .unwrap_or_else(|_| time.to_owned())
}

/// Publishes what changed of `job` since the follower last saw it (jobs this process runs
/// publish their own events).
fn publish_change(runner: &JobRunner, job: JobRecord) {
    if runner.inner.cancels.runs(&job.id) {
        return;
    }
    let updated_at = crate::domain::rfc3339(&job.updated_at);
    let previous = runner
        .inner
        .events
        .followed
        .seen
        .lock()
        .expect("follower lock")
        .insert(job.id.to_string(), (job.status, job.step, updated_at));
    let event = match previous {
        Some((status, step, _)) if status == job.status => {
            if job.status != JobStatus::Running || step == job.step {
                return;
            }
            JobEvent::Progress { progress: job.progress(), job_id: job.id }
        }
        _ => JobEvent::Status { job_id: job.id, status: job.status },
    };
    runner.inner.events.publish_here(event);
}

/// Keeps the follower's memory bounded: jobs unchanged since before the window are forgotten.
fn forget_older_than(followed: &Followed, since: &str) {
    followed
        .seen
        .lock()
        .expect("follower lock")
        .retain(|_, (_, _, updated_at)| updated_at.as_str() >= since);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_follower_looks_back_by_the_overlap() {
        assert_eq!(overlap_before("2026-11-23T20:00:03.250Z"), "2026-11-23T19:59:58.250Z");
    }
}
