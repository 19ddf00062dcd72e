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
pub mod storage;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use anyhow::Context;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Connection, Sqlite, SqlitePool, Transaction};

pub use datasets::{DatasetRecord, DeleteOutcome, NewDataset};
pub use storage::StorageProblem;

const DATABASE_FILE: &str = "safedice.sqlite";
const DATASETS_DIR: &str = "datasets";
const TMP_DIR: &str = "tmp";

/// How long a statement waits for another connection's write lock before SQLite gives up with
/// SQLITE_BUSY. Writes hold the lock for milliseconds, but SQLite's busy handler polls with
/// back-off (up to 100 ms between tries) and is not fair, so under a burst of writers one can
/// wait far longer than the others; 15 s rides out such bursts and still answers (503
/// `database_busy`) well before the 30 s request timeout.
const BUSY_TIMEOUT: Duration = Duration::from_secs(15);
/// How long a request waits for a free pooled connection before it is answered 503.
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(10);

/// SQLite's primary result codes we tell apart (extended codes carry them in the low byte).
const SQLITE_BUSY: i32 = 5;
const SQLITE_LOCKED: i32 = 6;

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

impl StoreError {
    /// A lock or a connection was not available in time: nothing is wrong with the request or
    /// the data, and the same call succeeds once the other writers are through.
    pub fn is_busy(&self) -> bool {
        matches!(self, StoreError::Database(e) if is_busy(e))
    }
}

/// SQLite's primary result code of a database error (the low byte of the extended code sqlx
/// reports).
fn sqlite_code(e: &sqlx::Error) -> Option<i32> {
    let sqlx::Error::Database(db) = e else { return None };
    db.code()?.parse::<i32>().ok().map(|code| code & 0xff)
}

/// SQLITE_BUSY / SQLITE_LOCKED (every extended variant) or no pooled connection in time.
pub fn is_busy(e: &sqlx::Error) -> bool {
    matches!(e, sqlx::Error::PoolTimedOut)
        || matches!(sqlite_code(e), Some(SQLITE_BUSY | SQLITE_LOCKED))
}

/// How the pool hands out and takes back connections.
fn pool_options() -> SqlitePoolOptions {
    SqlitePoolOptions::new().acquire_timeout(ACQUIRE_TIMEOUT).after_release(|conn, _| {
        Box::pin(async move {
            // SQLite rolls a transaction back by itself on some errors (SQLITE_FULL, I/O errors,
            // out of memory). sqlx does not notice: the ROLLBACK of the dropped transaction then
            // fails, sqlx still counts the transaction as open, and the connection would refuse
            // every later BEGIN (a full disk turned into failed jobs that way). The ping lets
            // that rollback run first; a connection still counted in a transaction is closed
            // rather than reused.
            conn.ping().await?;
            Ok(!conn.is_in_transaction())
        })
    })
}

/// Current time as stored: RFC 3339, UTC, milliseconds (text that sorts in time order).
pub fn now() -> String {
    chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
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
            .busy_timeout(BUSY_TIMEOUT);
        let pool = pool_options()
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

    /// Begins a transaction that writes. `BEGIN IMMEDIATE` takes the write lock up front
    /// (waiting up to the busy timeout for it). A plain (deferred) `BEGIN` only takes a read
    /// snapshot, and its first write then has to upgrade it: if another connection committed in
    /// between, SQLite cannot upgrade the stale snapshot and fails at once with SQLITE_BUSY
    /// ("database is locked") without waiting, which clients saw as 500s under concurrent
    /// writes. Every transaction that writes, and above all one that reads and then writes,
    /// starts here.
    pub async fn begin_write(&self) -> Result<Transaction<'static, Sqlite>, sqlx::Error> {
        self.pool.begin_with("BEGIN IMMEDIATE").await
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

#[cfg(test)]
mod tests {
    use sqlx::SqliteConnection;

    use super::*;

    /// A write transaction that SQLite rolls back by itself (here: the database file reaches its
    /// page limit, as a full disk does) must not leave its pooled connection unusable.
    #[tokio::test]
    async fn a_transaction_sqlite_rolled_back_does_not_poison_the_pool() {
        let dir = tempfile::tempdir().unwrap();
        let options = SqliteConnectOptions::from_str("sqlite:")
            .unwrap()
            .filename(dir.path().join("db.sqlite"))
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal);
        // One connection, whichever the pool opens, each with a database size limit.
        let pool = pool_options()
            .max_connections(1)
            .after_connect(|conn, _| {
                Box::pin(async move {
                    sqlx::query("PRAGMA max_page_count = 16").execute(conn).await.map(|_| ())
                })
            })
            .connect_with(options)
            .await
            .unwrap();
        sqlx::query("CREATE TABLE t (data BLOB)").execute(&pool).await.unwrap();
        let store = Store { pool, data_dir: dir.path().to_path_buf() };
        let mut tx = store.begin_write().await.unwrap();
        sqlx::query("INSERT INTO t VALUES (x'00')").execute(&mut *tx).await.unwrap();
        let full = sqlx::query("INSERT INTO t VALUES (?)")
            .bind(vec![0u8; 4 << 20])
            .execute(&mut *tx)
            .await
            .unwrap_err();
        assert!(StoreError::Database(full).is_storage_full());
        drop(tx);
        let mut tx = store.begin_write().await.expect("the pool still begins transactions");
        sqlx::query("INSERT INTO t VALUES (x'01')").execute(&mut *tx).await.unwrap();
        tx.commit().await.unwrap();
        let rows: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM t").fetch_one(store.pool()).await.unwrap();
        assert_eq!(rows, 1, "only the committed row");
    }

    async fn connect(path: &Path, busy_timeout: Duration) -> SqliteConnection {
        let options = SqliteConnectOptions::from_str("sqlite:")
            .unwrap()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .busy_timeout(busy_timeout);
        SqliteConnection::connect_with(&options).await.unwrap()
    }

    /// The failure behind the 500s: a deferred transaction that read before another connection
    /// committed cannot upgrade its snapshot to write, and SQLite says SQLITE_BUSY at once
    /// whatever the busy timeout. `BEGIN IMMEDIATE` takes the lock first and cannot meet it.
    #[tokio::test]
    async fn a_stale_read_snapshot_cannot_write_and_is_classified_busy() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("db.sqlite");
        let mut reader = connect(&path, Duration::from_secs(5)).await;
        let mut writer = connect(&path, Duration::from_secs(5)).await;
        sqlx::query("CREATE TABLE t (v INTEGER)").execute(&mut writer).await.unwrap();
        sqlx::query("INSERT INTO t VALUES (1)").execute(&mut writer).await.unwrap();

        sqlx::query("BEGIN").execute(&mut reader).await.unwrap();
        let _: i64 = sqlx::query_scalar("SELECT v FROM t").fetch_one(&mut reader).await.unwrap();
        sqlx::query("UPDATE t SET v = 2").execute(&mut writer).await.unwrap();
        let stale = sqlx::query("UPDATE t SET v = 3").execute(&mut reader).await.unwrap_err();
        assert!(is_busy(&stale), "{stale}");
        assert!(StoreError::Database(stale).is_busy());
        sqlx::query("ROLLBACK").execute(&mut reader).await.unwrap();

        sqlx::query("BEGIN IMMEDIATE").execute(&mut reader).await.unwrap();
        let _: i64 = sqlx::query_scalar("SELECT v FROM t").fetch_one(&mut reader).await.unwrap();
        // The lock is taken: another writer waits (here: gives up after its timeout of 0).
        let mut impatient = connect(&path, Duration::ZERO).await;
        let waiting = sqlx::query("UPDATE t SET v = 4").execute(&mut impatient).await.unwrap_err();
        assert!(is_busy(&waiting), "{waiting}");
        sqlx::query("UPDATE t SET v = 3").execute(&mut reader).await.unwrap();
        sqlx::query("COMMIT").execute(&mut reader).await.unwrap();

        let other = sqlx::query("SELECT * FROM missing").execute(&mut reader).await.unwrap_err();
        assert!(!is_busy(&other), "{other}");
    }
}
