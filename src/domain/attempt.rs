//! A job's attempts: each claim by a worker, how it ended, and when a job whose worker died is
//! tried again.

use std::time::Duration;

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// How one claim of a job by a worker ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum AttemptOutcome {
    /// The worker still holds the job's lease.
    Running,
    Succeeded,
    /// The run stopped on an error that retrying cannot fix (bad data, divergence): the job
    /// failed with it, no further attempt.
    Failed,
    Cancelled,
    /// Handed back to the queue (shutdown, or a store that could not take the run's writes):
    /// not the job's fault, so it does not count as an attempt.
    Released,
    /// The worker stopped renewing its lease (killed, out of memory, crashed, its machine or
    /// database connection lost): another attempt follows after a backoff, until the job's
    /// `max_attempts`.
    Crashed,
    /// The worker came back after its lease had expired (paused, cut off from the database)
    /// and stopped without writing: the job had already been handed on.
    LeaseLost,
}

impl AttemptOutcome {
    pub const ALL: [AttemptOutcome; 7] = [
        AttemptOutcome::Running,
        AttemptOutcome::Succeeded,
        AttemptOutcome::Failed,
        AttemptOutcome::Cancelled,
        AttemptOutcome::Released,
        AttemptOutcome::Crashed,
        AttemptOutcome::LeaseLost,
    ];

    /// The outcome as stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            AttemptOutcome::Running => "running",
            AttemptOutcome::Succeeded => "succeeded",
            AttemptOutcome::Failed => "failed",
            AttemptOutcome::Cancelled => "cancelled",
            AttemptOutcome::Released => "released",
            AttemptOutcome::Crashed => "crashed",
            AttemptOutcome::LeaseLost => "lease_lost",
        }
    }
}

impl std::str::FromStr for AttemptOutcome {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        AttemptOutcome::ALL
            .into_iter()
            .find(|outcome| outcome.as_str() == s)
            .ok_or_else(|| format!("unknown attempt outcome {s:?}"))
    }
}

/// Attempts of a job whose workers keep vanishing (killed, out of memory) before it fails for
/// good: enough to ride out a machine lost or a worker restarted, few enough that a job that
/// kills every worker it lands on stops doing so within minutes.
pub const DEFAULT_MAX_ATTEMPTS: u32 = 3;
/// The most attempts a job or the server may allow.
pub const MOST_ATTEMPTS: u32 = 100;

/// One claim of a job by a worker, as stored and shown.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct JobAttempt {
    /// Which attempt this was (1 for the first); a claim handed back on shutdown shares its
    /// number with the claim that resumes it.
    pub attempt: u32,
    /// The worker that claimed the job.
    pub worker: String,
    pub started_at: DateTime<Utc>,
    pub ended_at: Option<DateTime<Utc>>,
    pub outcome: AttemptOutcome,
    /// What ended it, for every outcome but `running` and `succeeded`.
    pub message: Option<String>,
}

/// How long a job whose worker died waits before its next attempt: exponential in the attempts
/// made, with jitter so that jobs of one crashed worker do not all land on the next at once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RetryBackoff {
    /// The wait after the first attempt (before jitter); zero retries at once.
    pub base: Duration,
    /// No wait is longer (before jitter).
    pub max: Duration,
}

impl RetryBackoff {
    /// The wait before a job's second attempt: on top of the lease, so a worker restarting on
    /// the same machine has its memory back before the job returns.
    pub const DEFAULT_BASE: Duration = Duration::from_secs(10);
    pub const DEFAULT_MAX: Duration = Duration::from_secs(600);

    pub fn new(base: Duration) -> Self {
        RetryBackoff { base, max: RetryBackoff::DEFAULT_MAX.max(base) }
    }

    /// The wait after `attempts` attempts ended in a crash: base · 2^(attempts−1), at most
    /// `max`, scaled by `jitter` in [0, 1) to between 0.75 and 1.25 of that.
    pub fn delay(&self, attempts: u32, jitter: f64) -> Duration {
        let doublings = attempts.saturating_sub(1).min(30);
        let exponential = self.base.saturating_mul(1 << doublings).min(self.max);
        exponential.mul_f64(0.75 + 0.5 * jitter.clamp(0.0, 1.0))
    }
}

/// What a worker process said of its memory at a heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemorySample {
    /// The process's resident memory.
    pub rss_bytes: u64,
    /// Memory the process could still take: the machine's available memory, or less under a
    /// cgroup limit.
    pub available_bytes: u64,
}

impl MemorySample {
    /// Whether the process had used most of what it could: a process that then vanished was
    /// most likely killed for memory.
    pub fn nearly_exhausted(&self) -> bool {
        let total = self.rss_bytes.saturating_add(self.available_bytes);
        total > 0 && self.rss_bytes as f64 >= 0.8 * total as f64
    }
}

/// Why an attempt ended when its worker stopped renewing the lease, with what the worker last
/// said of its memory.
pub fn crash_message(worker: &str, step: u64, memory: Option<MemorySample>) -> String {
    let gib = |bytes: u64| bytes as f64 / f64::from(1u32 << 30);
    let memory = match memory {
        Some(m) if m.nearly_exhausted() => format!(
            "; at its last heartbeat it used {:.2} GiB of memory with {:.2} GiB left: most likely \
             killed for want of memory (the kernel's out-of-memory killer)",
            gib(m.rss_bytes),
            gib(m.available_bytes)
        ),
        Some(m) => format!(
            "; at its last heartbeat it used {:.2} GiB of memory with {:.2} GiB left",
            gib(m.rss_bytes),
            gib(m.available_bytes)
        ),
        None => String::new(),
    };
    format!(
        "worker {worker} stopped renewing its lease at step {step} (killed, e.g. by the \
         out-of-memory killer, crashed, or cut off from the database){memory}"
    )
}

/// The error of a job that failed because every attempt's worker vanished.
pub fn gave_up_message(attempts: u32, crashes: u32, last: &str) -> String {
    format!(
        "gave up after {attempts} attempts ({crashes} ended with the worker gone); the last: \
         {last}. If the workers ran out of memory, lower batch_size or hidden_sizes, or run \
         the job on a worker with more memory"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outcomes_round_trip_through_their_stored_names_and_serde() {
        for outcome in AttemptOutcome::ALL {
            assert_eq!(outcome.as_str().parse::<AttemptOutcome>(), Ok(outcome));
            let json = serde_json::to_value(outcome).unwrap();
            assert_eq!(json, serde_json::Value::String(outcome.as_str().into()));
        }
        assert!("lost".parse::<AttemptOutcome>().is_err());
    }

    #[test]
    fn the_backoff_doubles_per_attempt_within_its_jitter_and_stops_at_the_cap() {
        let backoff = RetryBackoff::new(Duration::from_secs(10));
        assert_eq!(backoff.delay(1, 0.5), Duration::from_secs(10));
        assert_eq!(backoff.delay(2, 0.5), Duration::from_secs(20));
        assert_eq!(backoff.delay(3, 0.0), Duration::from_secs(30)); // 40 · 0.75
        assert_eq!(backoff.delay(3, 1.0), Duration::from_secs(50)); // 40 · 1.25
        assert_eq!(backoff.delay(40, 0.5), Duration::from_secs(600));
        assert_eq!(RetryBackoff::new(Duration::ZERO).delay(5, 0.9), Duration::ZERO);
    }

    #[test]
    fn a_worker_that_vanished_near_its_memory_limit_is_said_to_have_run_out_of_memory() {
        let gib = 1u64 << 30;
        let full = MemorySample { rss_bytes: 9 * gib, available_bytes: gib / 2 };
        let roomy = MemorySample { rss_bytes: gib, available_bytes: 8 * gib };
        assert!(full.nearly_exhausted() && !roomy.nearly_exhausted());
        let oom = crash_message("w1", 40, Some(full));
        assert!(oom.contains("9.00 GiB of memory with 0.50 GiB left: most likely killed"), "{oom}");
        let plain = crash_message("w1", 40, Some(roomy));
        assert!(plain.contains("1.00 GiB of memory with 8.00 GiB left") && !plain.contains("most"));
        assert!(crash_message("w1", 40, None).contains("out-of-memory killer"));
        let end = gave_up_message(3, 3, &oom);
        assert!(
            end.starts_with("gave up after 3 attempts (3 ended with the worker gone)"),
            "{end}"
        );
    }
}
