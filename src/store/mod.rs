//! All SQL and artefact storage, over one of two databases:
//!
//! - **SQLite** (the default, no `--database-url`): one data directory holds everything.
//!
//!   ```text
//!   <data-dir>/safedice.sqlite   SQLite database (WAL mode; -wal/-shm files beside it)
//!   <data-dir>/datasets/<id>.canonical   each accepted dataset, once, in the canonical form
//!   <data-dir>/tmp/              uploads in flight; emptied at start-up
//!   ```
//!
//!   Dataset bytes live in files rather than SQLite blobs because uploads may reach
//!   `--max-upload-bytes` (1 GiB by default) and SQLite caps a blob at 1 GB; a row is only
//!   inserted once its file is durably in place, and files without a row are removed at
//!   start-up.
//! - **PostgreSQL** (`--database-url postgres://…`): every byte a worker on another machine needs
//!   is in the database (dataset bytes in chunks, [`datasets`]); the data directory only holds
//!   uploads in flight, so API nodes and workers share nothing but the database.
//!
//! One store, one set of queries: both backends are reached through sqlx's `Any` driver, the
//! SQL is the dialect both speak (`$N` parameters, `RETURNING`, `ON CONFLICT`), and the few
//! places where they differ (how a writing transaction begins, row locks, the clock) are the
//! fragments of [`Backend`]. Each backend has its own migrations folder.

pub mod attempts;
pub mod datasets;
pub mod evaluations;
pub mod experiments;
pub mod job_metrics;
pub mod job_runs;
pub mod jobs;
pub mod leases;
mod listing;
pub mod logs;
mod migrate;
pub mod model_aliases;
pub mod models;
mod notifications;
pub mod policies;
pub mod shadows;
pub mod storage;
#[cfg(test)]
mod test_support;

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use sqlx::any::{AnyConnectOptions, AnyPoolOptions};
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{Any, AnyPool, Connection, Transaction};

pub use datasets::{DeleteOutcome, NewDataset};
pub use leases::{Lease, Leased};
pub use listing::{Listing, PageQuery};

pub use storage::StorageProblem;

const DATABASE_FILE: &str = "safedice.sqlite";
const DATASETS_DIR: &str = "datasets";
const TMP_DIR: &str = "tmp";

/// How long a request waits for a free pooled connection before it is answered 503.
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(10);

/// SQLite's primary result codes we tell apart (extended codes carry them in the low byte).
const SQLITE_BUSY: i32 = 5;
const SQLITE_LOCKED: i32 = 6;
/// Every PostgreSQL session ends a transaction left idle for 5 s. The store's transactions send
/// their statements back to back (milliseconds), so only a stalled process leaves one open: a
/// worker stopped (SIGSTOP, a VM paused) inside a transaction would otherwise keep its row locks
/// for as long as its connection lives, and the claim's `SKIP LOCKED` would skip its job forever
/// instead of taking it over when the lease expires.
const POSTGRES_SESSION: &str = "SET idle_in_transaction_session_timeout = 5000";

/// PostgreSQL's SQLSTATEs of "try again": serialization failure, deadlock, lock not available,
/// the server starting up or shutting down, the session ended for a transaction left idle
/// ([`POSTGRES_SESSION`]).
const POSTGRES_RETRY: [&str; 6] = ["40001", "40P01", "55P03", "57P03", "57P01", "25P03"];

/// A failure of the store that callers may want to tell apart.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{kind} {id} does not exist")]
    NotFound { kind: &'static str, id: String },
    #[error("stored data for {0} is damaged: {1}")]
    Corrupt(String, String),
    /// The worker's lease on a job or evaluation was taken over by another worker (it expired):
    /// the write was refused and nothing of it is stored.
    #[error("the lease on {0} was taken over by another worker")]
    LeaseLost(String),
    /// The change conflicts with what is stored (a name taken, a resource still in use); `code`
    /// is the API's error code for it.
    #[error("{message}")]
    Conflict { code: &'static str, message: String },
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

    /// The database itself cannot be reached (its connection lost, the server shutting down or
    /// not accepting connections): a kind of busy that says more to an operator.
    pub fn is_unreachable(&self) -> bool {
        matches!(self, StoreError::Database(e) if is_unreachable(e))
    }
}

/// An I/O error on the database's socket, or PostgreSQL's connection exceptions (class 08) and
/// its administrator or crash shutdowns (57P01-57P03).
pub fn is_unreachable(e: &sqlx::Error) -> bool {
    matches!(e, sqlx::Error::Io(_))
        || postgres_code(e).is_some_and(|code| code.starts_with("08") || code.starts_with("57P0"))
}

/// SQLite's primary result code of a database error (the low byte of the extended code sqlx
/// reports); None for other databases' errors.
fn sqlite_code(e: &sqlx::Error) -> Option<i32> {
    let sqlx::Error::Database(db) = e else { return None };
    db.try_downcast_ref::<sqlx::sqlite::SqliteError>()?;
    db.code()?.parse::<i32>().ok().map(|code| code & 0xff)
}

/// PostgreSQL's SQLSTATE of a database error; None for other databases' errors.
fn postgres_code(e: &sqlx::Error) -> Option<String> {
    let sqlx::Error::Database(db) = e else { return None };
    let pg = db.try_downcast_ref::<sqlx::postgres::PgDatabaseError>()?;
    Some(pg.code().to_owned())
}

/// SQLITE_BUSY / SQLITE_LOCKED (every extended variant), PostgreSQL's "try again" states, no
/// pooled connection in time, or the connection to the database lost (an I/O error on its socket,
/// PostgreSQL's connection exceptions, class 08): the database may take the same call later,
/// and nothing is wrong with what was asked.
pub fn is_busy(e: &sqlx::Error) -> bool {
    matches!(e, sqlx::Error::PoolTimedOut | sqlx::Error::Io(_))
        || matches!(sqlite_code(e), Some(SQLITE_BUSY | SQLITE_LOCKED))
        || postgres_code(e)
            .is_some_and(|code| POSTGRES_RETRY.contains(&code.as_str()) || code.starts_with("08"))
}

/// Which database the store talks to, and the SQL that differs between them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

impl Backend {
    pub fn as_str(self) -> &'static str {
        match self {
            Backend::Sqlite => "sqlite",
            Backend::Postgres => "postgres",
        }
    }

    /// How a transaction that writes begins. SQLite: `BEGIN IMMEDIATE` takes the write lock up
    /// front (see [`Store::begin_write`]); PostgreSQL locks rows, so a plain `BEGIN` and the
    /// row locks of [`Backend::lock_row`] where a transaction reads and then writes.
    fn begin_write(self) -> &'static str {
        match self {
            Backend::Sqlite => "BEGIN IMMEDIATE",
            Backend::Postgres => "BEGIN",
        }
    }

    /// Appended to a `SELECT` whose rows the transaction then changes (or whose absence it
    /// relies on): SQLite's write lock already serialises such transactions.
    pub(crate) fn lock_row(self) -> &'static str {
        match self {
            Backend::Sqlite => "",
            Backend::Postgres => " FOR UPDATE",
        }
    }

    /// Appended to a `SELECT` whose rows must not change until the transaction ends.
    pub(crate) fn share_row(self) -> &'static str {
        match self {
            Backend::Sqlite => "",
            Backend::Postgres => " FOR SHARE",
        }
    }

    /// Appended to the sub-select of a claim: concurrent claimers skip the rows another one is
    /// taking instead of waiting for it (SQLite runs one claim at a time anyway).
    pub(crate) fn skip_locked(self) -> &'static str {
        match self {
            Backend::Sqlite => "",
            Backend::Postgres => " FOR UPDATE SKIP LOCKED",
        }
    }

    /// The database's clock in milliseconds since the Unix epoch, as an SQL expression: leases
    /// compare times from one clock, whichever machine a worker runs on.
    pub(crate) fn now_ms(self) -> &'static str {
        match self {
            Backend::Sqlite => "CAST((julianday('now') - 2440587.5) * 86400000.0 AS INTEGER)",
            Backend::Postgres => "CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)",
        }
    }
}

impl Store {
    /// The current time as stored, on the database's clock (see [`now_in`]), asked on the pool:
    /// for writes that are one statement and hold no transaction.
    pub(crate) async fn db_now(&self) -> Result<String, sqlx::Error> {
        match self.backend {
            Backend::Sqlite => Ok(process_now()),
            Backend::Postgres => {
                Ok(stamp(sqlx::query_scalar(PG_NOW_MS).fetch_one(self.pool()).await?))
            }
        }
    }
}

/// The current time as stored (RFC 3339, UTC, milliseconds) on the database's clock, read on
/// `conn` (a write transaction asks on its own connection rather than take a second one from
/// the pool). On PostgreSQL the server's clock, so every process of a fleet stamps every stored
/// time from one clock (the follower's "changed since" compares `updated_at` stamps across
/// processes, and a log line, attempt or alias move written by one worker orders against
/// another's); on SQLite this machine's, which every process sharing the file shares. Every
/// stored time comes from here or [`Store::db_now`]: the process clock is private to this module.
pub(crate) async fn now_in(conn: &mut sqlx::AnyConnection) -> Result<String, sqlx::Error> {
    if on_postgres(conn) {
        Ok(stamp(sqlx::query_scalar(PG_NOW_MS).fetch_one(conn).await?))
    } else {
        Ok(process_now())
    }
}

/// How far the database's clock runs ahead of this process's, read on `conn`: times sampled
/// before they are written (a run's metrics, stored in batches) move onto the database's clock
/// by it, so they order against the stamps of [`now_in`]. Zero on SQLite, whose clock is this
/// machine's.
pub(crate) async fn clock_offset_in(
    conn: &mut sqlx::AnyConnection,
) -> Result<chrono::TimeDelta, sqlx::Error> {
    if !on_postgres(conn) {
        return Ok(chrono::TimeDelta::zero());
    }
    let before = chrono::Utc::now().timestamp_millis();
    let database: i64 = sqlx::query_scalar(PG_NOW_MS).fetch_one(conn).await?;
    let after = chrono::Utc::now().timestamp_millis();
    // The server read its clock somewhere within the round trip: its middle is the best guess.
    Ok(chrono::TimeDelta::milliseconds(database - (before + after) / 2))
}

fn on_postgres(conn: &sqlx::AnyConnection) -> bool {
    conn.backend_name() == <sqlx::Postgres as sqlx::Database>::NAME
}

/// PostgreSQL's clock in milliseconds since the Unix epoch.
const PG_NOW_MS: &str = "SELECT CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)";

/// This process's clock, as stored: SQLite's stamps (see [`now_in`]).
fn process_now() -> String {
    stamp(chrono::Utc::now().timestamp_millis())
}

/// A clock reading in milliseconds as stored: RFC 3339, UTC, milliseconds (text that sorts in
/// time order). Never the same twice in one process: a reading in the millisecond of the last
/// one gets the next millisecond, so rows made one after another (two evaluations recorded in a
/// burst) list in the order they were made, on either clock; lists break ties by id only
/// between processes.
fn stamp(clock_ms: i64) -> String {
    use std::sync::atomic::{AtomicI64, Ordering};
    static LAST_MS: AtomicI64 = AtomicI64::new(i64::MIN);
    let previous = LAST_MS
        .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |last| Some(clock_ms.max(last + 1)))
        .expect("the update always succeeds");
    let ms = clock_ms.max(previous + 1);
    chrono::DateTime::from_timestamp_millis(ms)
        .unwrap_or_else(chrono::Utc::now)
        .to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
}

/// A stored time back in its typed form (RFC 3339; rows written before the store wrote
/// milliseconds carry nanoseconds and `+00:00`, which parse alike).
fn parse_time(owner: &str, text: &str) -> Result<chrono::DateTime<chrono::Utc>, StoreError> {
    chrono::DateTime::parse_from_rfc3339(text)
        .map(|t| t.with_timezone(&chrono::Utc))
        .map_err(|e| StoreError::Corrupt(owner.to_owned(), format!("stored time {text:?}: {e}")))
}

fn parse_optional_time(
    owner: &str,
    text: Option<&str>,
) -> Result<Option<chrono::DateTime<chrono::Utc>>, StoreError> {
    text.map(|t| parse_time(owner, t)).transpose()
}

/// An optional float as bound to SQL, to be read back with `CAST($n AS DOUBLE PRECISION)`.
/// sqlx's `Any` driver (0.8) binds a NULL `f64` as a single-precision NULL, which PostgreSQL
/// refuses for a double column ("incorrect binary data format in bind parameter"); as text, NULL
/// and every value (Rust writes the shortest form that reads back to the same bits) arrive
/// exactly on both backends.
fn optional_real(value: Option<f64>) -> Option<String> {
    value.map(|v| v.to_string())
}

/// `$first, $first+1, …` for `count` parameters (bulk inserts build their statements with it).
fn placeholders(first: usize, count: usize) -> String {
    (first..first + count).map(|n| format!("${n}")).collect::<Vec<_>>().join(", ")
}

/// The database pool and the data directory; cheap to clone.
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
    data_dir: PathBuf,
    /// PostgreSQL's URL (for the notification listener's own connection); None on SQLite.
    database_url: Option<std::sync::Arc<str>>,
}

/// Never the URL: it may carry a password.
impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store")
            .field("backend", &self.backend)
            .field("data_dir", &self.data_dir)
            .finish_non_exhaustive()
    }
}

/// How the pool hands out and takes back connections.
fn pool_options() -> AnyPoolOptions {
    AnyPoolOptions::new().acquire_timeout(ACQUIRE_TIMEOUT).after_release(|conn, _| {
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

/// The settings every SQLite connection gets. NORMAL synchronous is durable across application
/// crashes in WAL mode; only an OS crash or power loss can drop the last commits.
///
/// The busy timeout (15 s) is how long a statement waits for another connection's write lock
/// before SQLite gives up with SQLITE_BUSY. Writes hold the lock for milliseconds, but SQLite's
/// busy handler polls with back-off (up to 100 ms between tries) and is not fair, so under a
/// burst of writers one can wait far longer than the others; 15 s rides out such bursts and
/// still answers (503 `database_busy`) well before the 30 s request timeout.
const SQLITE_PRAGMAS: [&str; 4] = [
    "PRAGMA journal_mode = WAL",
    "PRAGMA synchronous = NORMAL",
    "PRAGMA foreign_keys = ON",
    "PRAGMA busy_timeout = 15000",
];

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

    /// Opens the store: SQLite in `data_dir` when `database_url` is None, else the PostgreSQL
    /// database it names (`data_dir` then only holds uploads in flight). Creates what is missing
    /// and runs the pending migrations. Safe while a server runs on the same store (tests and
    /// tools use it to inspect it); only the server calls [`Store::remove_leftovers`].
    pub async fn connect(data_dir: &Path, database_url: Option<&str>) -> anyhow::Result<Store> {
        match database_url {
            None => Store::open(data_dir).await,
            Some(url) => Store::open_postgres(data_dir, url).await,
        }
    }

    /// Opens (creating on first start) the SQLite store in `data_dir`.
    pub async fn open(data_dir: &Path) -> anyhow::Result<Store> {
        Store::open_sqlite(data_dir, 8).await
    }

    async fn open_sqlite(data_dir: &Path, max_connections: u32) -> anyhow::Result<Store> {
        for dir in [data_dir.to_path_buf(), data_dir.join(DATASETS_DIR), data_dir.join(TMP_DIR)] {
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create data directory {}", dir.display()))?;
        }
        sqlx::any::install_default_drivers();
        let database = data_dir.join(DATABASE_FILE);
        let sqlite = SqliteConnectOptions::new().filename(&database).create_if_missing(true);
        let options: AnyConnectOptions =
            sqlx::ConnectOptions::to_url_lossy(&sqlite).as_str().parse()?;
        let pool = pool_options()
            .max_connections(max_connections)
            .after_connect(|conn, _| {
                Box::pin(async move {
                    for pragma in SQLITE_PRAGMAS {
                        sqlx::query(pragma).execute(&mut *conn).await?;
                    }
                    Ok(())
                })
            })
            .connect_with(options)
            .await
            .with_context(|| format!("cannot open the database {}", database.display()))?;
        migrate::sqlite(&sqlite)
            .await
            .with_context(|| format!("cannot migrate the database {}", database.display()))?;
        Ok(Store {
            pool,
            backend: Backend::Sqlite,
            data_dir: data_dir.to_path_buf(),
            database_url: None,
        })
    }

    async fn open_postgres(data_dir: &Path, url: &str) -> anyhow::Result<Store> {
        anyhow::ensure!(
            url.starts_with("postgres://") || url.starts_with("postgresql://"),
            "--database-url must be a postgres:// (or postgresql://) URL; leave it out to use \
             SQLite in --data-dir"
        );
        for dir in [data_dir.to_path_buf(), data_dir.join(TMP_DIR)] {
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create data directory {}", dir.display()))?;
        }
        sqlx::any::install_default_drivers();
        let pool = pool_options()
            .max_connections(16)
            .after_connect(|conn, _| {
                Box::pin(async move {
                    sqlx::query(POSTGRES_SESSION).execute(&mut *conn).await.map(drop)
                })
            })
            .connect(url)
            .await
            .with_context(|| format!("cannot connect to the database {}", redact_url(url)))?;
        sqlx::migrate!("./migrations/postgres")
            .run(&pool)
            .await
            .with_context(|| format!("cannot migrate the database {}", redact_url(url)))?;
        Ok(Store {
            pool,
            backend: Backend::Postgres,
            data_dir: data_dir.to_path_buf(),
            database_url: Some(url.into()),
        })
    }

    pub fn pool(&self) -> &AnyPool {
        &self.pool
    }

    /// Whether a new connection to the database can be made within 2 s (always, for SQLite):
    /// to its pool a PostgreSQL server that is down looks busy (no connection in time).
    pub async fn database_reachable(&self) -> bool {
        use sqlx::{ConnectOptions, Connection};
        let options = self.pool.connect_options();
        let connected = async { options.connect().await?.close().await };
        self.backend == Backend::Sqlite
            || tokio::time::timeout(Duration::from_secs(2), connected)
                .await
                .is_ok_and(|c| c.is_ok())
    }

    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// PostgreSQL's URL; None on SQLite.
    pub fn database_url(&self) -> Option<&str> {
        self.database_url.as_deref()
    }

    /// Begins a transaction that writes. On SQLite, `BEGIN IMMEDIATE` takes the write lock up
    /// front (waiting up to the busy timeout for it). A plain (deferred) `BEGIN` only takes a
    /// read snapshot, and its first write then has to upgrade it: if another connection
    /// committed in between, SQLite cannot upgrade the stale snapshot and fails at once with
    /// SQLITE_BUSY ("database is locked") without waiting, which clients saw as 500s under
    /// concurrent writes. Every transaction that writes, and above all one that reads and then
    /// writes, starts here (on PostgreSQL it locks the rows it reads, [`Backend::lock_row`]).
    pub async fn begin_write(&self) -> Result<Transaction<'static, Any>, sqlx::Error> {
        self.pool.begin_with(self.backend.begin_write()).await
    }

    /// Begins a write transaction for deleting row `id` of `table` and locks the row: the
    /// transaction and the row's `column` (e.g. its status), or None if there is no such row.
    pub(crate) async fn begin_delete(
        &self,
        table: &str,
        column: &str,
        id: &str,
    ) -> Result<Option<(Transaction<'static, Any>, String)>, sqlx::Error> {
        let mut tx = self.begin_write().await?;
        let value: Option<String> = sqlx::query_scalar(&format!(
            "SELECT {column} FROM {table} WHERE id = $1{}",
            self.backend.lock_row()
        ))
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?;
        Ok(value.map(|v| (tx, v)))
    }

    /// Whether row `id` of a list's table exists (the anchor of a keyset page).
    pub async fn page_anchor_exists(&self, list: Listing, id: &str) -> Result<bool, StoreError> {
        let found: Option<String> = sqlx::query_scalar(&format!(
            "SELECT {key} FROM {} WHERE {key} = $1",
            list.table(),
            key = list.key()
        ))
        .bind(id)
        .fetch_optional(self.pool())
        .await?;
        Ok(found.is_some())
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

    /// Removes temp uploads and (SQLite) dataset files without a database row: what a crash
    /// between writing a file and committing its row (or between deleting a row and its file)
    /// leaves. Call it at start-up, before serving: it would also remove uploads in flight.
    pub async fn remove_leftovers(&self) -> anyhow::Result<()> {
        for entry in std::fs::read_dir(self.tmp_dir())? {
            let path = entry?.path();
            tracing::info!(path = %path.display(), "removing an interrupted upload");
            remove_path(&path)?;
        }
        if self.backend != Backend::Sqlite {
            return Ok(());
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

/// A database URL without its password, for messages and logs.
pub fn redact_url(url: &str) -> String {
    match url.split_once("://").and_then(|(scheme, rest)| {
        let (credentials, host) = rest.rsplit_once('@')?;
        let user = credentials.split(':').next().unwrap_or("");
        Some(format!("{scheme}://{user}:***@{host}"))
    }) {
        Some(redacted) => redacted,
        None => url.to_owned(),
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
    use std::str::FromStr;

    use sqlx::sqlite::SqliteJournalMode;
    use sqlx::SqliteConnection;

    use super::*;

    /// Lists order rows by `created_at`, then by (random) id: times taken one after another,
    /// even within one millisecond, must sort in the order they were taken.
    #[test]
    fn stored_times_taken_in_turn_sort_in_that_order() {
        let times: Vec<String> = (0..5_000).map(|_| process_now()).collect();
        assert!(times.windows(2).all(|pair| pair[0] < pair[1]));
        assert!(parse_time("t", &times[0]).is_ok());
    }

    #[test]
    fn database_urls_lose_their_password_in_messages() {
        assert_eq!(redact_url("postgres://app:s3cret@db:5432/x"), "postgres://app:***@db:5432/x");
        assert_eq!(redact_url("postgres://db/x"), "postgres://db/x");
    }

    /// A write transaction that SQLite rolls back by itself (here: the database file reaches its
    /// page limit, as a full disk does) must not leave its pooled connection unusable.
    #[tokio::test]
    async fn a_transaction_sqlite_rolled_back_does_not_poison_the_pool() {
        let dir = tempfile::tempdir().unwrap();
        // One connection, so the size limit below holds for every statement of the test.
        let store = Store::open_sqlite(dir.path(), 1).await.unwrap();
        sqlx::query("PRAGMA max_page_count = 64").execute(store.pool()).await.unwrap();
        sqlx::query("CREATE TABLE t (data BLOB)").execute(store.pool()).await.unwrap();
        let mut tx = store.begin_write().await.unwrap();
        sqlx::query("INSERT INTO t VALUES (x'00')").execute(&mut *tx).await.unwrap();
        let full = sqlx::query("INSERT INTO t VALUES ($1)")
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
