//! Running the migrations, and tests of those that rewrite a table, on a database as the
//! release before them left it.

use std::time::Duration;

use sqlx::sqlite::SqliteConnectOptions;
use sqlx::Connection;

/// Runs the pending SQLite migrations on a connection of their own with foreign keys off: a
/// migration that rebuilds a table (SQLite's documented way to change a constraint: create,
/// copy, drop, rename) must not cascade the drop to the rows that reference it, and the pragma
/// cannot be turned off inside the transaction sqlx runs each migration in. The references are
/// checked once the migrations ran.
pub(super) async fn sqlite(options: &SqliteConnectOptions) -> anyhow::Result<()> {
    let options = options
        .clone()
        .foreign_keys(false)
        .journal_mode(sqlx::sqlite::SqliteJournalMode::Wal)
        .busy_timeout(Duration::from_secs(15));
    let mut conn = sqlx::ConnectOptions::connect(&options).await?;
    sqlx::migrate!("./migrations/sqlite").run(&mut conn).await?;
    let dangling: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM pragma_foreign_key_check")
        .fetch_one(&mut conn)
        .await?;
    conn.close().await?;
    anyhow::ensure!(dangling == 0, "{dangling} rows reference rows that do not exist");
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::borrow::Cow;

    use sqlx::sqlite::SqliteConnectOptions;
    use sqlx::{ConnectOptions, Connection, SqliteConnection};

    use crate::domain::JobStatus;
    use crate::store::{Store, DATABASE_FILE};

    /// A SQLite database migrated up to (not including) the first migration whose name contains
    /// `before`.
    async fn database_before(dir: &std::path::Path, before: &str) -> SqliteConnection {
        let options = SqliteConnectOptions::new()
            .filename(dir.join(DATABASE_FILE))
            .create_if_missing(true)
            .foreign_keys(true);
        let mut conn = options.connect().await.unwrap();
        let mut migrator = sqlx::migrate!("./migrations/sqlite");
        let at = migrator.migrations.iter().position(|m| m.description.contains(before)).unwrap();
        migrator.migrations = Cow::Owned(migrator.migrations[..at].to_vec());
        migrator.run(&mut conn).await.unwrap();
        conn
    }

    async fn count(store: &Store, sql: &str) -> i64 {
        sqlx::query_scalar(sql).fetch_one(store.pool()).await.unwrap()
    }

    /// The rebuild that lets `jobs.status` say `discarded` (SQLite cannot alter a CHECK): every job
    /// keeps its columns, none of the rows that reference a job is lost (dropping the old table
    /// must not cascade), the indexes and foreign keys hold on the new table, and a job that had
    /// ended out of attempts reads `discarded`.
    #[tokio::test]
    async fn the_discarded_rebuild_keeps_every_job_and_every_row_that_references_one() {
        let dir = tempfile::tempdir().unwrap();
        let mut conn = database_before(dir.path(), "discarded").await;
        let gave_up = "gave up after 3 attempts (3 ended with the worker gone); the last: gone";
        for (id, status, error) in [
            ("j-gave-up", "failed", Some(gave_up)),
            ("j-diverged", "failed", Some("training diverged at step 4")),
            ("j-done", "succeeded", None),
        ] {
            sqlx::query(
                "INSERT INTO jobs (id, algorithm, status, unlabeled_dataset_id, created_at, \
                 updated_at, error, name, tags, attempt, max_attempts) \
                 VALUES ($1, 'bc', $2, 'ds-1', 't0', 't1', $3, $1, '[\"a\"]', 3, 3)",
            )
            .bind(id)
            .bind(status)
            .bind(error)
            .execute(&mut conn)
            .await
            .unwrap();
            for seq in 0..2 {
                sqlx::query(
                    "INSERT INTO job_logs (job_id, seq, time, level, worker, message) \
                     VALUES ($1, $2, 't', 'info', 'w1', 'line')",
                )
                .bind(id)
                .bind(seq)
                .execute(&mut conn)
                .await
                .unwrap();
            }
        }
        conn.close().await.unwrap();

        let store = Store::open(dir.path()).await.unwrap();
        let rows: Vec<(String, String, Option<String>, i64, String)> =
            sqlx::query_as("SELECT id, status, error, attempt, tags FROM jobs ORDER BY id")
                .fetch_all(store.pool())
                .await
                .unwrap();
        let row = |id: &str, status: JobStatus, error: Option<&str>| {
            (
                id.to_owned(),
                status.as_str().to_owned(),
                error.map(str::to_owned),
                3,
                "[\"a\"]".into(),
            )
        };
        let failure = Some("training diverged at step 4");
        assert_eq!(
            rows,
            [
                row("j-diverged", JobStatus::Failed, failure),
                row("j-done", JobStatus::Succeeded, None),
                row("j-gave-up", JobStatus::Discarded, Some(gave_up)),
            ]
        );
        assert_eq!(count(&store, "SELECT COUNT(*) FROM job_logs").await, 6, "nothing cascaded");
        let indexes =
            "SELECT COUNT(*) FROM sqlite_master WHERE type = 'index' AND tbl_name = 'jobs' \
                       AND name LIKE 'jobs_by_%'";
        assert_eq!(count(&store, indexes).await, 5);
        assert_eq!(count(&store, "PRAGMA foreign_keys").await, 1, "on again for every connection");
        assert_eq!(count(&store, "SELECT COUNT(*) FROM pragma_foreign_key_check").await, 0);
        // The children's references now point at the rebuilt table: deleting a job cascades.
        sqlx::query("DELETE FROM jobs WHERE id = 'j-done'").execute(store.pool()).await.unwrap();
        assert_eq!(count(&store, "SELECT COUNT(*) FROM job_logs").await, 4);
        // And the constraint takes the new word and still refuses others.
        let set = |status: &'static str| {
            sqlx::query("UPDATE jobs SET status = $1 WHERE id = 'j-diverged'")
                .bind(status)
                .execute(store.pool())
        };
        assert!(set(JobStatus::Discarded.as_str()).await.is_ok());
        assert!(set("lost").await.is_err());
    }
}
