//! Shadow versions (docs/shadow.md): for a share of an alias's requests, another version acts on
//! the same observations off the response path, and its actions are compared with the ones
//! returned. The answer never waits for it: the request hands a copy of its observations to a
//! bounded queue and goes on; one thread of its own runs the shadows, so they take at most one
//! core and never a runtime worker; a full queue skips the comparison (counted) rather than
//! growing. Counts are summed per minute here and added to the store every [`FLUSH`], where the
//! nodes of a fleet add to the same rows.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use chrono::{DateTime, DurationRound, TimeDelta, Utc};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tokio_util::sync::CancellationToken;

use crate::algo::Policy;
use crate::data::Actions;
use crate::domain::shadow::{ComparisonCounts, ComparisonKey};
use crate::store::shadows::ComparisonDelta;
use crate::store::{Store, StoreError};

/// Comparisons waiting for the shadow thread; one more is skipped.
pub const QUEUE: usize = 1024;
/// Observation values the queued comparisons may hold in all (64 MiB of f32): the queue is
/// bounded by size as well as by count, since one request may carry 16,384 rows.
pub const QUEUE_VALUES: u64 = 16 << 20;
/// How often this process adds its counts to the store.
pub const FLUSH: Duration = Duration::from_secs(5);

/// One request's comparison to run: the observations as production saw them, the actions it
/// returned, and how it acted (a sampled request's seed is shared, so both versions draw the same
/// noise and the difference is the policies').
pub struct Comparison {
    pub key: ComparisonKey,
    pub shadow: Arc<Policy>,
    pub production: Arc<Policy>,
    pub observations: Vec<f32>,
    pub production_actions: Actions,
    pub deterministic: bool,
    pub seed: u64,
}

/// A comparison as queued: the minute its request was answered in.
struct Queued {
    comparison: Comparison,
    minute: DateTime<Utc>,
}

/// Counts per comparison and minute, not yet in the store.
type Pending = HashMap<(ComparisonKey, DateTime<Utc>), ComparisonCounts>;

/// What the shadow thread shares with the requests and the flushes.
struct Shared {
    pending: Mutex<Pending>,
    /// Comparisons queued so far, and finished so far (both only grow): a read waits until the
    /// second reaches what the first was when it started.
    submitted: AtomicU64,
    finished: AtomicU64,
    /// Observation values held by the queue now.
    queued_values: AtomicU64,
    /// Requests drawn for a shadow since the process started, by what became of them.
    compared: AtomicU64,
    skipped: AtomicU64,
    failed: AtomicU64,
}

/// What `/metrics` says of this process's shadows.
pub struct ShadowUsage {
    /// Comparisons queued and not finished.
    pub queued: u64,
    /// Requests drawn for a shadow since start: compared, skipped, failed.
    pub compared: u64,
    pub skipped: u64,
    pub failed: u64,
}

/// The shadow thread's queue and this process's counts.
pub struct Shadows {
    queue: SyncSender<Queued>,
    shared: Arc<Shared>,
    /// One flush at a time: a read's flush must not find the counts taken by another flush
    /// that has not committed them yet.
    flushing: tokio::sync::Mutex<()>,
    store: Store,
}

impl Shadows {
    /// Starts the shadow thread (it ends when the last `Shadows` is dropped).
    pub fn start(store: Store) -> Arc<Self> {
        let (queue, received) = sync_channel(QUEUE);
        let shared = Arc::new(Shared {
            pending: Mutex::new(Pending::new()),
            submitted: AtomicU64::new(0),
            finished: AtomicU64::new(0),
            queued_values: AtomicU64::new(0),
            compared: AtomicU64::new(0),
            skipped: AtomicU64::new(0),
            failed: AtomicU64::new(0),
        });
        let on_thread = shared.clone();
        std::thread::Builder::new()
            .name("safedice-shadow".into())
            .spawn(move || run_comparisons(received, &on_thread))
            .expect("cannot start the shadow thread");
        Arc::new(Shadows { queue, shared, flushing: tokio::sync::Mutex::new(()), store })
    }

    /// Queues a comparison; a full queue (by count or by size) counts it as skipped.
    pub fn submit(&self, comparison: Comparison) {
        let values = comparison.observations.len() as u64;
        let held = self.shared.queued_values.fetch_add(values, Ordering::SeqCst);
        if held + values > QUEUE_VALUES && held > 0 {
            self.shared.queued_values.fetch_sub(values, Ordering::SeqCst);
            return self.skip(comparison.key);
        }
        let queued = Queued { comparison, minute: this_minute() };
        self.shared.submitted.fetch_add(1, Ordering::SeqCst);
        if let Err(TrySendError::Full(q) | TrySendError::Disconnected(q)) =
            self.queue.try_send(queued)
        {
            self.shared.queued_values.fetch_sub(values, Ordering::SeqCst);
            self.shared.finished.fetch_add(1, Ordering::SeqCst);
            self.skip(q.comparison.key);
        }
    }

    /// Counts a request drawn for the shadow that could not be compared (its queue full, or its
    /// policy not loaded on this process).
    pub fn skip(&self, key: ComparisonKey) {
        self.shared.skipped.fetch_add(1, Ordering::Relaxed);
        let counts = ComparisonCounts { requests: 1, skipped: 1, ..Default::default() };
        add_at(&self.shared.pending, key, this_minute(), &counts);
    }

    /// For `/metrics`.
    pub fn usage(&self) -> ShadowUsage {
        let load = |v: &AtomicU64| v.load(Ordering::Relaxed);
        let (submitted, finished) = (load(&self.shared.submitted), load(&self.shared.finished));
        ShadowUsage {
            queued: submitted.saturating_sub(finished),
            compared: load(&self.shared.compared),
            skipped: load(&self.shared.skipped),
            failed: load(&self.shared.failed),
        }
    }

    /// Adds this process's counts to the store; on failure they stay for the next flush.
    pub async fn flush(&self) -> Result<(), StoreError> {
        let _one_at_a_time = self.flushing.lock().await;
        let taken = std::mem::take(&mut *self.shared.pending.lock().expect("shadow counts lock"));
        let mut deltas: Vec<ComparisonDelta> = taken
            .iter()
            .map(|((key, minute), counts)| ComparisonDelta { key, minute: *minute, counts })
            .collect();
        // Every node writes the rows in the same order, so two nodes' flushes of the same rows
        // cannot deadlock on PostgreSQL.
        deltas.sort_by(|a, b| (a.key, a.minute).cmp(&(b.key, b.minute)));
        let added = self.store.add_shadow_counts(&deltas).await;
        if added.is_err() {
            for ((key, minute), counts) in taken {
                add_at(&self.shared.pending, key, minute, &counts);
            }
        }
        added
    }

    /// Waits (up to `wait`) for the comparisons queued before it was called to finish, then
    /// flushes: what a reader of the series asks for, so it sees every request this process
    /// answered before it asked.
    pub async fn settle(&self, wait: Duration) -> Result<(), StoreError> {
        let deadline = Instant::now() + wait;
        let target = self.shared.submitted.load(Ordering::SeqCst);
        while self.shared.finished.load(Ordering::SeqCst) < target && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        self.flush().await
    }

    /// Flushes every [`FLUSH`] until shutdown, then once more.
    pub fn watch(self: Arc<Self>, shutdown: CancellationToken) {
        tokio::spawn(async move {
            loop {
                let stop = tokio::select! {
                    () = shutdown.cancelled() => true,
                    () = tokio::time::sleep(FLUSH) => false,
                };
                let flushed = if stop {
                    self.settle(Duration::from_secs(1)).await
                } else {
                    self.flush().await
                };
                if let Err(e) = flushed {
                    tracing::warn!(error = %e, "cannot store the shadows' comparisons; kept for the next try");
                }
                if stop {
                    return;
                }
            }
        });
    }
}

fn this_minute() -> DateTime<Utc> {
    Utc::now().duration_trunc(TimeDelta::minutes(1)).expect("a minute divides time")
}

/// The shadow thread: each comparison in turn. A panic in one (a policy's bug) counts it as
/// failed and the thread goes on.
fn run_comparisons(received: Receiver<Queued>, shared: &Shared) {
    for Queued { comparison, minute } in received {
        let (key, values) = (comparison.key.clone(), comparison.observations.len() as u64);
        let counts = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| compare(comparison)))
            .unwrap_or_else(|_| ComparisonCounts { requests: 1, failed: 1, ..Default::default() });
        let outcome = if counts.failed > 0 { &shared.failed } else { &shared.compared };
        outcome.fetch_add(1, Ordering::Relaxed);
        add_at(&shared.pending, key, minute, &counts);
        shared.queued_values.fetch_sub(values, Ordering::SeqCst);
        shared.finished.fetch_add(1, Ordering::SeqCst);
    }
}

fn add_at(
    pending: &Mutex<Pending>,
    key: ComparisonKey,
    minute: DateTime<Utc>,
    counts: &ComparisonCounts,
) {
    let mut pending = pending.lock().expect("shadow counts lock");
    pending.entry((key, minute)).or_default().merge(counts);
}

/// Runs the shadow on the request's observations and compares its actions with production's.
fn compare(c: Comparison) -> ComparisonCounts {
    let started = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(c.seed);
    let mut counts = ComparisonCounts { requests: 1, ..Default::default() };
    let acted = c.shadow.act(&c.observations, c.deterministic, &mut rng);
    let rows = c.observations.len() / c.production.spec().obs_dim.max(1);
    let compared = acted.ok().and_then(|shadow| {
        let differences = differences(&c.production_actions, &shadow, rows)?;
        Some((shadow, differences))
    });
    let Some((shadow_actions, differences)) = compared else {
        counts.failed = 1;
        counts.shadow_ns = started.elapsed().as_nanos() as u64;
        return counts;
    };
    counts.merge(&differences);
    if let Some(scores) = c.shadow.safety_scores(&c.observations, &shadow_actions) {
        counts.shadow_log_ratio_sum = sum(&scores.non_preferred_log_ratio);
        counts.shadow_log_ratio_n = scores.non_preferred_log_ratio.len() as u64;
        counts.out_of_support_sum = sum(&scores.out_of_support);
        counts.out_of_support_n = scores.out_of_support.len() as u64;
    }
    if let Some(scores) = c.production.safety_scores(&c.observations, &c.production_actions) {
        counts.production_log_ratio_sum = sum(&scores.non_preferred_log_ratio);
        counts.production_log_ratio_n = scores.non_preferred_log_ratio.len() as u64;
    }
    counts.shadow_ns = started.elapsed().as_nanos() as u64;
    counts
}

fn sum(values: &[f32]) -> f64 {
    values.iter().map(|&v| f64::from(v)).sum()
}

/// Per observation: disagreement of discrete actions; L2 and largest absolute difference of
/// continuous ones. None when the two answers do not have the same shape.
pub fn differences(
    production: &Actions,
    shadow: &Actions,
    rows: usize,
) -> Option<ComparisonCounts> {
    let mut counts = ComparisonCounts { observations: rows as u64, ..Default::default() };
    match (production, shadow) {
        (Actions::Discrete(a), Actions::Discrete(b)) if a.len() == rows && b.len() == rows => {
            counts.disagreements = a.iter().zip(b).filter(|(x, y)| x != y).count() as u64;
        }
        (Actions::Continuous(a), Actions::Continuous(b))
            if a.len() == b.len() && rows > 0 && a.len() % rows == 0 =>
        {
            let width = a.len() / rows;
            for (x, y) in a.chunks(width).zip(b.chunks(width)) {
                let gaps = x.iter().zip(y).map(|(p, q)| f64::from(p - q).abs());
                let (squares, largest) =
                    gaps.fold((0.0, 0.0f64), |(s, m), gap| (s + gap * gap, m.max(gap)));
                let l2 = f64::sqrt(squares);
                counts.l2_sum += l2;
                counts.l2_max = counts.l2_max.max(l2);
                counts.max_abs_sum += largest;
                counts.max_abs_max = counts.max_abs_max.max(largest);
            }
        }
        _ => return None,
    }
    Some(counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continuous_differences_are_l2_and_max_abs_per_observation() {
        // Rows (3, 4) apart (L2 5, max-abs 4) and identical: sums 5 / 4, maxima 5 / 4.
        let a = Actions::Continuous(vec![0.0, 0.0, 1.0, 1.0]);
        let b = Actions::Continuous(vec![3.0, -4.0, 1.0, 1.0]);
        let d = differences(&a, &b, 2).expect("same shape");
        assert_eq!(d.observations, 2);
        assert!((d.l2_sum - 5.0).abs() < 1e-9 && (d.l2_max - 5.0).abs() < 1e-9, "{d:?}");
        assert!((d.max_abs_sum - 4.0).abs() < 1e-9 && (d.max_abs_max - 4.0).abs() < 1e-9);
        assert_eq!(d.disagreements, 0);
    }

    #[test]
    fn discrete_differences_count_disagreements() {
        let d =
            differences(&Actions::Discrete(vec![0, 1, 2]), &Actions::Discrete(vec![0, 2, 1]), 3)
                .expect("same shape");
        assert_eq!((d.observations, d.disagreements, d.l2_sum), (3, 2, 0.0));
    }

    #[test]
    fn answers_of_another_shape_do_not_compare() {
        let a = Actions::Continuous(vec![0.0, 0.0]);
        assert!(differences(&a, &Actions::Discrete(vec![0, 0]), 2).is_none());
        assert!(differences(&a, &Actions::Continuous(vec![0.0; 4]), 2).is_none());
    }
}
