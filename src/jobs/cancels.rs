//! The cancel flags of the jobs this process runs: set by a cancel request (from this process's
//! API or another process's notification), read by the job's worker between steps.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

#[derive(Default)]
pub(super) struct CancelFlags {
    flags: Mutex<HashMap<String, Arc<AtomicBool>>>,
}

impl CancelFlags {
    /// A fresh flag for a job this process starts running.
    pub(super) fn register(&self, job_id: &str) -> Arc<AtomicBool> {
        let flag = Arc::new(AtomicBool::new(false));
        self.lock().insert(job_id.to_owned(), flag.clone());
        flag
    }

    /// The job's run ended here.
    pub(super) fn forget(&self, job_id: &str) {
        self.lock().remove(job_id);
    }

    /// Sets the job's flag; false when this process runs no such job.
    pub(super) fn raise(&self, job_id: &str) -> bool {
        match self.lock().get(job_id) {
            Some(flag) => {
                flag.store(true, Ordering::Relaxed);
                true
            }
            None => false,
        }
    }

    /// Whether this process runs the job now.
    pub(super) fn runs(&self, job_id: &str) -> bool {
        self.lock().contains_key(job_id)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<AtomicBool>>> {
        self.flags.lock().expect("cancel flags lock")
    }
}
