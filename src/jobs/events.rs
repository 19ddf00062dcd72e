//! What watchers of jobs learn: progress and status changes, to this process's event streams
//! and, for the jobs this process runs, to the other processes of a fleet (which follow them,
//! [`super::fleet::follow_jobs`]).

use std::collections::HashMap;
use std::sync::Mutex;

use tokio::sync::{broadcast, Notify};

use super::announcements::{announce, Announcement};
use crate::domain::{JobId, JobProgress, JobStatus};
use crate::store::Store;

/// Something a watcher of a job wants to know.
#[derive(Clone, Debug)]
pub enum JobEvent {
    /// A running job advanced.
    Progress { job_id: JobId, progress: JobProgress },
    /// A job changed status (`running`, `queued` again on shutdown, or a final status).
    Status { job_id: JobId, status: JobStatus },
    /// A finished job was deleted: its streams end.
    Deleted { job_id: JobId },
}

impl JobEvent {
    pub fn job_id(&self) -> &JobId {
        match self {
            JobEvent::Progress { job_id, .. }
            | JobEvent::Status { job_id, .. }
            | JobEvent::Deleted { job_id } => job_id,
        }
    }
}

/// Events buffered per subscriber; a slow event stream skips ahead rather than blocking workers.
const EVENT_BUFFER: usize = 1024;

/// This process's event streams, and what it last published of jobs other processes run.
pub(super) struct JobEvents {
    sender: broadcast::Sender<JobEvent>,
    pub(super) followed: Followed,
}

impl JobEvents {
    pub(super) fn new() -> Self {
        JobEvents { sender: broadcast::channel(EVENT_BUFFER).0, followed: Followed::default() }
    }

    pub(super) fn subscribe(&self) -> broadcast::Receiver<JobEvent> {
        self.sender.subscribe()
    }

    /// Whether anyone in this process watches.
    pub(super) fn watched(&self) -> bool {
        self.sender.receiver_count() > 0
    }

    /// An event of a job this process runs (or changed through its API): to its own streams
    /// and, on PostgreSQL, to the API nodes that follow it.
    pub(super) fn publish(&self, store: &Store, event: JobEvent) {
        announce(store, Announcement::Changed(event.job_id().to_string()));
        self.publish_here(event);
    }

    /// An event to this process's streams only.
    pub(super) fn publish_here(&self, event: JobEvent) {
        // No subscriber is fine: nobody is watching.
        let _ = self.sender.send(event);
    }
}

/// What the follower last published per job: (status, step, updated_at).
#[derive(Default)]
pub(super) struct Followed {
    pub(super) seen: Mutex<HashMap<String, (JobStatus, u64, String)>>,
    pub(super) changed: Notify,
}
