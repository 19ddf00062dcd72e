//! Room to write: whether the data directory takes writes and has free space left (readiness,
//! and the job runner's wait after a full disk), and whether an error means the disk is full.

use std::io::Write;
use std::path::{Path, PathBuf};

use super::{postgres_code, sqlite_code, Backend, Store, StoreError};

/// SQLite's primary result code for "database or disk is full".
const SQLITE_FULL: i32 = 13;
/// PostgreSQL's SQLSTATE disk_full.
const POSTGRES_DISK_FULL: &str = "53100";

impl StoreError {
    /// The disk (or the database's size limit) is full: the write failed, nothing of it was
    /// stored, and it succeeds once space is freed.
    pub fn is_storage_full(&self) -> bool {
        match self {
            StoreError::Database(e) => is_storage_full(e),
            StoreError::Io(e) => is_io_storage_full(e),
            _ => false,
        }
    }
}

/// SQLITE_FULL (the file system refused to grow the database or its WAL, SQLite's VFS turns
/// ENOSPC into it, or the database reached `max_page_count`), PostgreSQL's disk_full, or an I/O
/// error of a full disk.
pub fn is_storage_full(e: &sqlx::Error) -> bool {
    match e {
        sqlx::Error::Io(io) => is_io_storage_full(io),
        other => {
            sqlite_code(other) == Some(SQLITE_FULL)
                || postgres_code(other).is_some_and(|code| code == POSTGRES_DISK_FULL)
        }
    }
}

/// ENOSPC (`StorageFull`) or EDQUOT (`QuotaExceeded`): the file system, or the user's quota on
/// it, has no room for the write.
pub fn is_io_storage_full(e: &std::io::Error) -> bool {
    matches!(e.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded)
}

/// Why the data directory cannot take the service's writes now.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StorageProblem {
    /// A file cannot be created and written in one of the directories the service writes to
    /// (read-only mount, permissions, a directory replaced by a file, a full disk).
    #[error("the data directory cannot be written ({dir}: {error})")]
    Unwritable {
        /// The directory, relative to the data directory (`.`, `datasets`, `tmp`): clients of
        /// the unauthenticated /readyz see this, not the server's paths.
        dir: String,
        error: String,
    },
    /// The file system holding the data directory has less room than required.
    #[error(
        "the data directory's file system has {free} bytes available, below the {required} \
         bytes required (--min-free-disk)"
    )]
    LowSpace { free: u64, required: u64 },
}

impl Store {
    /// Checks that a file can be created and written in each directory the service writes to,
    /// and that the data directory's file system has at least `min_free` bytes available to
    /// this process. Cheap (three one-byte files, created and removed, and one `statvfs`), so
    /// readiness probes can call it every time.
    pub async fn check_storage(&self, min_free: u64) -> Result<(), StorageProblem> {
        let data_dir = self.data_dir.clone();
        // On PostgreSQL the data directory only takes uploads in flight.
        let dirs: &'static [&'static str] = match self.backend {
            Backend::Sqlite => &[".", super::DATASETS_DIR, super::TMP_DIR],
            Backend::Postgres => &[".", super::TMP_DIR],
        };
        tokio::task::spawn_blocking(move || check_storage(&data_dir, dirs, min_free))
            .await
            .unwrap_or_else(|e| {
                Err(StorageProblem::Unwritable { dir: ".".into(), error: e.to_string() })
            })
    }
}

/// Free space first: a full disk also fails the write probe, and "low disk space" says more
/// than "No space left on device" about a directory.
fn check_storage(data_dir: &Path, dirs: &[&str], min_free: u64) -> Result<(), StorageProblem> {
    let free = available_bytes(data_dir)
        .map_err(|e| StorageProblem::Unwritable { dir: ".".into(), error: without_path(&e) })?;
    if free < min_free {
        return Err(StorageProblem::LowSpace { free, required: min_free });
    }
    for &sub in dirs {
        let dir: PathBuf = data_dir.join(sub);
        probe_write(&dir).map_err(|e| {
            tracing::warn!(dir = %dir.display(), error = %e, "the data directory cannot be written");
            StorageProblem::Unwritable { dir: sub.to_owned(), error: without_path(&e) }
        })?;
    }
    Ok(())
}

/// The system's description of an I/O error, without the path some errors carry (tempfile
/// adds it): the unauthenticated /readyz must not show the server's paths (the log has them).
fn without_path(e: &std::io::Error) -> String {
    match e.raw_os_error() {
        Some(code) => std::io::Error::from_raw_os_error(code).to_string(),
        None => e.kind().to_string(),
    }
}

/// Creates, writes and removes a one-byte file in `dir`. Without a sync: file systems reserve
/// the space at `write` (a full disk fails it with ENOSPC), and a probe that waited for the
/// disk would make readiness slow when the disk is busy.
fn probe_write(dir: &Path) -> std::io::Result<()> {
    let mut probe = tempfile::Builder::new().prefix(".write-probe-").tempfile_in(dir)?;
    probe.write_all(b"x")?;
    probe.flush()?;
    probe.close()
}

/// Bytes available to an unprivileged process on the file system of `dir` (`f_bavail`: the
/// blocks reserved for root do not count, the service should not live on them).
#[cfg(unix)]
fn available_bytes(dir: &Path) -> std::io::Result<u64> {
    let stats = rustix::fs::statvfs(dir)?;
    Ok(stats.f_bavail.saturating_mul(stats.f_frsize))
}

#[cfg(not(unix))]
fn available_bytes(_dir: &Path) -> std::io::Result<u64> {
    Ok(u64::MAX)
}

#[cfg(test)]
mod tests {
    use std::str::FromStr;

    use sqlx::sqlite::SqliteConnectOptions;
    use sqlx::{Connection, SqliteConnection};

    use super::*;

    /// A real ENOSPC: Linux's /dev/full fails every write with it.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_write_to_a_full_device_is_storage_full() {
        let mut full = std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap();
        let e = full.write_all(b"checkpoint").and_then(|()| full.flush()).unwrap_err();
        assert_eq!(e.raw_os_error(), Some(rustix::io::Errno::NOSPC.raw_os_error()));
        assert!(is_io_storage_full(&e));
        assert!(StoreError::Io(e).is_storage_full());
        let quota = std::io::Error::from_raw_os_error(rustix::io::Errno::DQUOT.raw_os_error());
        assert!(is_io_storage_full(&quota));
        let other = std::io::Error::from_raw_os_error(rustix::io::Errno::ACCESS.raw_os_error());
        assert!(!is_io_storage_full(&other) && !StoreError::Io(other).is_storage_full());
    }

    /// A real SQLITE_FULL from a real database file: `max_page_count` caps the file's size, and
    /// SQLite answers a write past it exactly as it answers a full disk.
    #[tokio::test]
    async fn a_database_past_its_page_limit_is_storage_full() {
        let dir = tempfile::tempdir().unwrap();
        let options = SqliteConnectOptions::from_str("sqlite:")
            .unwrap()
            .filename(dir.path().join("db.sqlite"))
            .create_if_missing(true);
        let mut db = SqliteConnection::connect_with(&options).await.unwrap();
        sqlx::query("CREATE TABLE checkpoints (data BLOB)").execute(&mut db).await.unwrap();
        sqlx::query("PRAGMA max_page_count = 8").execute(&mut db).await.unwrap();
        let full = sqlx::query("INSERT INTO checkpoints VALUES ($1)")
            .bind(vec![0u8; 1 << 20])
            .execute(&mut db)
            .await
            .unwrap_err();
        assert!(full.to_string().contains("database or disk is full"), "{full}");
        assert!(is_storage_full(&full));
        assert!(!super::super::is_busy(&full));
        assert!(StoreError::Database(full).is_storage_full());
        let other =
            sqlx::query("INSERT INTO missing VALUES (1)").execute(&mut db).await.unwrap_err();
        assert!(!is_storage_full(&other));
    }
}
