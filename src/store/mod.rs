//! All SQL and artefact storage. One data directory holds everything the service keeps:
//!
//! ```text
//! <data-dir>/safedice.sqlite   SQLite database (WAL mode; -wal/-shm files beside it)
//! <data-dir>/datasets/<id>.canonical   each accepted dataset, once, in the canonical form
//! <data-dir>/tmp/              uploads in flight; emptied at start-up
//! ```
//!
//! Dataset bytes live in files rather than SQLite blobs because uploads may reach
//! `--max-upload-bytes` (1 GiB by default) and SQLite caps a blob at 1 GB; a row is only inserted
//! once its file is durably in place, and files without a row are removed at start-up.

pub mod datasets;
pub mod evaluations;
pub mod jobs;
pub mod policies;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use anyhow::Context;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::SqlitePool;

pub use datasets::{DatasetRecord, DeleteOutcome, NewDataset};

const DATABASE_FILE: &str = "safedice.sqlite";
const DATASETS_DIR: &str = "datasets";
const TMP_DIR: &str = "tmp";

/// A failure of the store that callers may want to tell apart.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{kind} {id} does not exist")]
    NotFound { kind: &'static str, id: String },
    #[error("stored data for {0} is damaged: {1}")]
    Corrupt(String, String),
    #[error(transparent)]
    Database(#[from] sqlx::Error),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// errno of "no space left on device" and "disk quota exceeded" (Linux).
const ENOSPC: i32 = 28;
const EDQUOT: i32 = 122;
/// SQLite's primary result code SQLITE_FULL ("database or disk is full").
const SQLITE_FULL: i64 = 13;

impl StoreError {
    /// Whether the failure is the disk (or quota) being full: the request was fine and may
    /// succeed once space is freed, so it is neither the caller's fault nor a bug.
    pub fn is_storage_full(&self) -> bool {
        match self {
            StoreError::Io(e) => io_is_storage_full(e),
            StoreError::Database(e) => sqlx_is_storage_full(e),
            _ => false,
        }
    }
}

/// An I/O error that means the file system (or the user's quota) is full.
pub fn io_is_storage_full(e: &std::io::Error) -> bool {
    e.kind() == std::io::ErrorKind::StorageFull
        || e.kind() == std::io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(ENOSPC | EDQUOT))
}

/// A database error that means the disk is full (SQLITE_FULL, or an I/O error saying so).
pub fn sqlx_is_storage_full(e: &sqlx::Error) -> bool {
    match e {
        sqlx::Error::Database(db) => {
            // Extended result codes keep the primary code in their low byte.
            let primary = db.code().and_then(|c| c.parse::<i64>().ok()).map(|c| c & 0xff);
            primary == Some(SQLITE_FULL)
        }
        sqlx::Error::Io(io) => io_is_storage_full(io),
        _ => false,
    }
}

/// The database pool and the data directory; cheap to clone.
#[derive(Clone, Debug)]
pub struct Store {
    pool: SqlitePool,
    data_dir: PathBuf,
}

impl Store {
    /// Number of rows of `table` in each of `statuses`, every status listed (zero when there are
    /// none). `table` is one of ours, never user input.
    async fn counts_by_status(
        &self,
        table: &str,
        statuses: &[&'static str],
    ) -> Result<Vec<(&'static str, i64)>, sqlx::Error> {
        let rows: Vec<(String, i64)> =
            sqlx::query_as(&format!("SELECT status, COUNT(*) FROM {table} GROUP BY status"))
                .fetch_all(self.pool())
                .await?;
        Ok(statuses
            .iter()
            .map(|&status| {
                let count = rows.iter().find(|(s, _)| s == status).map_or(0, |(_, n)| *n);
                (status, count)
            })
            .collect())
    }

    /// Opens (creating on first start) the data directory and its database and runs the pending
    /// migrations. Safe while a server runs on the same directory (tests and tools use it to
    /// inspect the store); only the server calls [`Store::remove_leftovers`].
    pub async fn open(data_dir: &Path) -> anyhow::Result<Store> {
        for dir in [data_dir.to_path_buf(), data_dir.join(DATASETS_DIR), data_dir.join(TMP_DIR)] {
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create data directory {}", dir.display()))?;
        }
        let database = data_dir.join(DATABASE_FILE);
        let options = SqliteConnectOptions::from_str("sqlite:")?
            .filename(&database)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // NORMAL is durable across application crashes in WAL mode; only an OS crash or
            // power loss can drop the last commits.
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(5));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(options)
            .await
            .with_context(|| format!("cannot open the database {}", database.display()))?;
        sqlx::migrate!("./migrations")
            .run(&pool)
            .await
            .with_context(|| format!("cannot migrate the database {}", database.display()))?;
        Ok(Store { pool, data_dir: data_dir.to_path_buf() })
    }

    pub fn pool(&self) -> &SqlitePool {
        &self.pool
    }

    pub fn data_dir(&self) -> &Path {
        &self.data_dir
    }

    /// Where uploads are streamed before they are parsed (same file system as the datasets, so
    /// nothing crosses devices).
    pub fn tmp_dir(&self) -> PathBuf {
        self.data_dir.join(TMP_DIR)
    }

    fn datasets_dir(&self) -> PathBuf {
        self.data_dir.join(DATASETS_DIR)
    }

    /// Whether the database answers a query (readiness).
    pub async fn ping(&self) -> Result<(), sqlx::Error> {
        sqlx::query("SELECT 1").execute(&self.pool).await.map(|_| ())
    }

    /// Closes the pool, checkpointing the WAL.
    pub async fn close(&self) {
        self.pool.close().await;
    }

    /// Removes temp uploads and dataset files without a database row: what a crash between
    /// writing a file and committing its row (or between deleting a row and its file) leaves.
    /// Call it at start-up, before serving: it would also remove uploads in flight.
    pub async fn remove_leftovers(&self) -> anyhow::Result<()> {
        for entry in std::fs::read_dir(self.tmp_dir())? {
            let path = entry?.path();
            tracing::info!(path = %path.display(), "removing an interrupted upload");
            remove_path(&path)?;
        }
        let known: std::collections::HashSet<String> =
            self.dataset_ids().await?.into_iter().collect();
        for entry in std::fs::read_dir(self.datasets_dir())? {
            let path = entry?.path();
            let is_known =
                datasets::id_of_canonical_file(&path).is_some_and(|id| known.contains(id));
            if !is_known {
                tracing::warn!(path = %path.display(), "removing a dataset file without a row");
                remove_path(&path)?;
            }
        }
        Ok(())
    }
}

fn remove_path(path: &Path) -> std::io::Result<()> {
    if path.is_dir() {
        std::fs::remove_dir_all(path)
    } else {
        std::fs::remove_file(path)
    }
}
