//! `GET /v1/jobs/{id}/logs?follow=true`: a job's log lines as they are written, fed by the
//! job's events instead of a timer. A follower reads the log when its job says something
//! happened (progress, a status change: relayed from other processes in a fleet), at most once
//! per [`MIN_READ_INTERVAL`], and otherwise every [`QUIET_CHECK`] (lines a worker elsewhere
//! wrote with nothing announced, a job deleted through another node). The job's status is read
//! only when something other than progress woke the follower. A follower of a queued job costs
//! two reads every 5 s and one of a running job at most one every 0.5 s, where each used to
//! poll twice every 0.5 s.

use std::collections::VecDeque;
use std::time::Duration;

use futures::Stream;
use tokio::sync::broadcast;
use tokio::time::Instant;

use crate::domain::{JobId, JobStatus, LogRecord};
use crate::jobs::JobEvent;
use crate::store::{Store, StoreError};

/// Lines read at once.
const READ_LIMIT: u32 = 1000;
/// Reads of one follower are at least this far apart (progress arrives about twice a second).
const MIN_READ_INTERVAL: Duration = Duration::from_millis(500);
/// A follower that hears nothing reads anyway after this long.
const QUIET_CHECK: Duration = Duration::from_secs(5);

/// Where a follower is.
struct Follower {
    store: Store,
    events: broadcast::Receiver<JobEvent>,
    id: JobId,
    /// The last line sent (its `seq`).
    after: i64,
    pending: VecDeque<LogRecord>,
    /// The job has ended (or is gone): once the lines written before that are sent, so is the
    /// stream.
    ended: bool,
    last_read: Option<Instant>,
}

/// The lines of job `id` after line `after`, until the job has ended and its last line was
/// sent. `events` must be subscribed before the job was read, so that no change between the
/// two is missed.
pub(super) fn follow(
    store: Store,
    events: broadcast::Receiver<JobEvent>,
    id: JobId,
    after: i64,
) -> impl Stream<Item = LogRecord> + Send + 'static {
    let follower = Follower {
        store,
        events,
        id,
        after,
        pending: VecDeque::new(),
        ended: false,
        last_read: None,
    };
    futures::stream::unfold(follower, |mut follower| async move {
        let row = follower.next_line().await?;
        follower.after = row.seq as i64;
        Some((row, follower))
    })
}

impl Follower {
    /// The next line to send; None once the job has ended and every line was sent (or the
    /// store cannot be read).
    async fn next_line(&mut self) -> Option<LogRecord> {
        loop {
            if let Some(row) = self.pending.pop_front() {
                return Some(row);
            }
            if self.last_read.is_some() && self.ended {
                return None;
            }
            // Progress says the job still runs; anything else may be its end.
            let progressed = self.last_read.is_some() && self.wait_for_news().await;
            if !progressed {
                // The status first: lines written before a final status are then all in the
                // read that follows.
                match self.store.job_status(&self.id).await {
                    Ok(status) => self.ended |= JobStatus::is_final(status),
                    Err(StoreError::NotFound { .. }) => self.ended = true,
                    Err(_) => return None,
                }
            }
            self.pending = self.store.job_log(&self.id, self.after, READ_LIMIT).await.ok()?.into();
            self.last_read = Some(Instant::now());
            // A full page: more lines may follow at once.
            if self.pending.len() == READ_LIMIT as usize {
                self.last_read = None;
            }
        }
    }

    /// Until the job announces something (or [`QUIET_CHECK`] passes), and at least
    /// [`MIN_READ_INTERVAL`] after the last read; whether it was progress (the job runs on).
    async fn wait_for_news(&mut self) -> bool {
        let quiet = tokio::time::sleep(QUIET_CHECK);
        tokio::pin!(quiet);
        let progressed = loop {
            tokio::select! {
                () = &mut quiet => break false,
                received = self.events.recv() => match received {
                    Ok(event) if *event.job_id() == self.id => {
                        break matches!(event, JobEvent::Progress { .. });
                    }
                    Ok(_) => continue,
                    // Skipped events may have been this job's.
                    Err(broadcast::error::RecvError::Lagged(_)) => break false,
                    // No runner to announce anything: the quiet check carries on alone.
                    Err(broadcast::error::RecvError::Closed) => {
                        (&mut quiet).await;
                        break false;
                    }
                },
            }
        };
        if let Some(read) = self.last_read {
            tokio::time::sleep_until(read + MIN_READ_INTERVAL).await;
        }
        progressed
    }
}
