//! The cancel flags of the jobs this process runs: set by a cancel request (from this process's
//! API or another process's notification), read by the job's worker between steps.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use crate::domain::JobId;

#[derive(Default)]
pub(super) struct CancelFlags {
    flags: Mutex<HashMap<JobId, Arc<AtomicBool>>>,
}

impl CancelFlags {
    /// A fresh flag for a job this process starts running.
    pub(super) fn register(&self, job_id: &JobId) -> Arc<AtomicBool> {
        let flag = Arc::new(AtomicBool::new(false));
        self.lock().insert(job_id.clone(), flag.clone());
        flag
    }

    /// The job's run ended here.
    pub(super) fn forget(&self, job_id: &JobId) {
        self.lock().remove(job_id);
    }

    /// Sets the job's flag; false when this process runs no such job.
    pub(super) fn raise(&self, job_id: &JobId) -> bool {
        match self.lock().get(job_id) {
            Some(flag) => {
                flag.store(true, Ordering::Relaxed);
                true
            }
            None => false,
        }
    }

    /// Whether this process runs the job now.
    pub(super) fn runs(&self, job_id: &JobId) -> bool {
        self.lock().contains_key(job_id)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<JobId, Arc<AtomicBool>>> {
        self.flags.lock().expect("cancel flags lock")
    }
}
