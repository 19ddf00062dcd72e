//! The pause of training while the store cannot take writes. A run that ended on a failed write
//! (a full disk, SQLITE_FULL, a lock held past the busy timeout) closes the gate; every worker
//! of this process then waits at it before claiming, for a back-off that doubles while runs
//! keep failing so, and until the data directory takes writes and has `--min-free-disk` free.

use std::sync::atomic::{AtomicU32, Ordering};

use tokio_util::sync::CancellationToken;

use super::{sleep_unless_shutdown, STORAGE_RETRY, STORAGE_RETRY_MAX};
use crate::store::Store;

#[derive(Default)]
pub(super) struct StorageGate {
    /// Runs in a row that ended because the store could not take their writes.
    failures: AtomicU32,
}

impl StorageGate {
    /// A run ended because the store could not take its writes.
    pub(super) fn close(&self) {
        self.failures.fetch_add(1, Ordering::Relaxed);
    }

    /// A run's writes went through.
    pub(super) fn open(&self) {
        self.failures.store(0, Ordering::Relaxed);
    }

    /// While closed: waits the back-off, then until the data directory takes writes and has
    /// `min_free_disk` bytes free (or shutdown begins). Returns at once while open.
    pub(super) async fn wait(
        &self,
        store: &Store,
        min_free_disk: u64,
        shutdown: &CancellationToken,
    ) {
        let failures = self.failures.load(Ordering::Relaxed);
        if failures == 0 {
            return;
        }
        let pause =
            STORAGE_RETRY.saturating_mul(1 << (failures - 1).min(16)).min(STORAGE_RETRY_MAX);
        tracing::warn!(
            seconds = pause.as_secs(),
            "training paused: the store could not take writes"
        );
        if sleep_unless_shutdown(shutdown, pause).await {
            return;
        }
        loop {
            match store.check_storage(min_free_disk).await {
                Ok(()) => {
                    tracing::info!("the data directory takes writes again; training resumes");
                    return;
                }
                Err(problem) => {
                    tracing::warn!(%problem, "training stays paused");
                    if sleep_unless_shutdown(shutdown, STORAGE_RETRY).await {
                        return;
                    }
                }
            }
        }
    }
}
