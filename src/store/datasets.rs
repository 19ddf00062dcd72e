//! Dataset rows and their canonical files.

use std::io::Write;
use std::path::{Path, PathBuf};

use chrono::{DateTime, Utc};
use sha2::{Digest, Sha256};
use sqlx::types::Json;

use super::{Store, StoreError};
use crate::data::{self, ActionSpace, Dataset, DatasetStats, Format};

const CANONICAL_EXTENSION: &str = "canonical";
const COLUMNS: &str = "id, name, description, format, transitions, episodes, obs_dim, \
     action_space, stats, sha256, bytes, canonical_sha256, canonical_bytes, created_at";

/// What is known about an accepted upload before it is stored.
#[derive(Debug, Clone)]
pub struct NewDataset {
    pub name: String,
    pub description: Option<String>,
    pub format: Format,
    pub transitions: usize,
    pub episodes: usize,
    pub obs_dim: usize,
    pub action_space: ActionSpace,
    pub stats: DatasetStats,
    /// SHA-256 of the uploaded file, hex.
    pub sha256: String,
    /// Size of the uploaded file.
    pub bytes: u64,
}

impl NewDataset {
    /// Describes a parsed upload.
    pub fn describe(
        dataset: &Dataset,
        format: Format,
        name: String,
        description: Option<String>,
        upload_sha256: String,
        upload_bytes: u64,
    ) -> Self {
        NewDataset {
            name,
            description,
            format,
            transitions: dataset.len(),
            episodes: dataset.episodes(),
            obs_dim: dataset.obs_dim(),
            action_space: dataset.action_space().clone(),
            stats: data::stats(dataset),
            sha256: upload_sha256,
            bytes: upload_bytes,
        }
    }
}

/// A stored dataset's description.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetRecord {
    pub id: String,
    pub name: String,
    pub description: Option<String>,
    pub format: Format,
    pub transitions: u64,
    pub episodes: u64,
    pub obs_dim: u64,
    pub action_space: ActionSpace,
    pub stats: DatasetStats,
    pub sha256: String,
    pub bytes: u64,
    pub created_at: DateTime<Utc>,
    canonical_sha256: String,
    canonical_bytes: u64,
}

#[derive(sqlx::FromRow)]
struct DatasetRow {
    id: String,
    name: String,
    description: Option<String>,
    format: String,
    transitions: i64,
    episodes: i64,
    obs_dim: i64,
    action_space: Json<ActionSpace>,
    stats: Json<DatasetStats>,
    sha256: String,
    bytes: i64,
    canonical_sha256: String,
    canonical_bytes: i64,
    created_at: DateTime<Utc>,
}

impl TryFrom<DatasetRow> for DatasetRecord {
    type Error = StoreError;

    fn try_from(row: DatasetRow) -> Result<Self, StoreError> {
        let format: Format = row
            .format
            .parse()
            .map_err(|e: data::ParseError| StoreError::Corrupt(row.id.clone(), e.message))?;
        Ok(DatasetRecord {
            id: row.id,
            name: row.name,
            description: row.description,
            format,
            transitions: row.transitions as u64,
            episodes: row.episodes as u64,
            obs_dim: row.obs_dim as u64,
            action_space: row.action_space.0,
            stats: row.stats.0,
            sha256: row.sha256,
            bytes: row.bytes as u64,
            created_at: row.created_at,
            canonical_sha256: row.canonical_sha256,
            canonical_bytes: row.canonical_bytes as u64,
        })
    }
}

/// The result of a delete request.
#[derive(Debug, PartialEq, Eq)]
pub enum DeleteOutcome {
    Deleted,
    NotFound,
    /// Queued or running jobs (their ids) still need the dataset.
    InUse(Vec<String>),
}

/// The dataset id a canonical file belongs to, from its name `<id>.canonical`.
pub(super) fn id_of_canonical_file(path: &Path) -> Option<&str> {
    let is_canonical = path.extension().is_some_and(|e| e == CANONICAL_EXTENSION);
    is_canonical.then(|| path.file_stem()?.to_str()).flatten()
}

fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Writes `bytes` to `path` so that `path` either does not exist or holds all of them, even
/// after a crash: a temp file in the same directory, flushed, renamed, directory synced.
fn write_atomically(dir: &Path, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut file = tempfile::Builder::new().prefix(".").suffix(".partial").tempfile_in(dir)?;
    file.write_all(bytes)?;
    file.as_file().sync_all()?;
    file.persist(path).map_err(|e| e.error)?;
    std::fs::File::open(dir)?.sync_all()
}

impl Store {
    fn canonical_path(&self, id: &str) -> PathBuf {
        self.datasets_dir().join(format!("{id}.{CANONICAL_EXTENSION}"))
    }

    /// Stores an accepted upload: its canonical bytes as a file, then its row. Either both
    /// exist afterwards or neither does.
    pub async fn create_dataset(
        &self,
        new: NewDataset,
        canonical: Vec<u8>,
    ) -> Result<DatasetRecord, StoreError> {
        let id = crate::domain::DatasetId::generate().into_string();
        let path = self.canonical_path(&id);
        let dir = self.datasets_dir();
        let canonical_bytes = canonical.len() as u64;
        let write_path = path.clone();
        let canonical_sha256 = tokio::task::spawn_blocking(move || {
            write_atomically(&dir, &write_path, &canonical).map(|()| sha256_hex(&canonical))
        })
        .await
        .map_err(std::io::Error::other)??;

        let inserted = sqlx::query(
            "INSERT INTO datasets (id, name, description, format, transitions, episodes, obs_dim, \
             action_space, stats, sha256, bytes, canonical_sha256, canonical_bytes, created_at) \
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(&id)
        .bind(&new.name)
        .bind(&new.description)
        .bind(new.format.as_str())
        .bind(new.transitions as i64)
        .bind(new.episodes as i64)
        .bind(new.obs_dim as i64)
        .bind(Json(&new.action_space))
        .bind(Json(&new.stats))
        .bind(&new.sha256)
        .bind(new.bytes as i64)
        .bind(&canonical_sha256)
        .bind(canonical_bytes as i64)
        .bind(Utc::now())
        .execute(self.pool())
        .await;
        if let Err(e) = inserted {
            let _ = tokio::fs::remove_file(&path).await;
            return Err(e.into());
        }
        self.dataset(&id)
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.clone() })
    }

    /// One dataset's description.
    pub async fn dataset(&self, id: &str) -> Result<Option<DatasetRecord>, StoreError> {
        let row: Option<DatasetRow> =
            sqlx::query_as(&format!("SELECT {COLUMNS} FROM datasets WHERE id = ?"))
                .bind(id)
                .fetch_optional(self.pool())
                .await?;
        row.map(DatasetRecord::try_from).transpose()
    }

    /// A page of datasets, newest first, and the total count.
    pub async fn datasets(
        &self,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<DatasetRecord>, u64), StoreError> {
        let rows: Vec<DatasetRow> = sqlx::query_as(&format!(
            "SELECT {COLUMNS} FROM datasets ORDER BY rowid DESC LIMIT ? OFFSET ?"
        ))
        .bind(limit as i64)
        .bind(offset as i64)
        .fetch_all(self.pool())
        .await?;
        let (total,): (i64,) =
            sqlx::query_as("SELECT COUNT(*) FROM datasets").fetch_one(self.pool()).await?;
        let records = rows.into_iter().map(DatasetRecord::try_from).collect::<Result<_, _>>()?;
        Ok((records, total as u64))
    }

    pub(super) async fn dataset_ids(&self) -> Result<Vec<String>, sqlx::Error> {
        sqlx::query_scalar("SELECT id FROM datasets").fetch_all(self.pool()).await
    }

    /// Deletes a dataset unless a queued or running job uses it. The check and the delete are
    /// one write transaction (the write lock taken up front), so a job queued concurrently
    /// either commits first and is seen here, or sees the dataset gone (see
    /// [`Store::insert_job`]); and the answer describes the state the delete saw, not one read
    /// after it.
    pub async fn delete_dataset(&self, id: &str) -> Result<DeleteOutcome, StoreError> {
        let mut tx = self.begin_write().await?;
        let exists: bool =
            sqlx::query_scalar("SELECT EXISTS (SELECT 1 FROM datasets WHERE id = ?)")
                .bind(id)
                .fetch_one(&mut *tx)
                .await?;
        if !exists {
            return Ok(DeleteOutcome::NotFound);
        }
        let jobs: Vec<String> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE status IN ('queued', 'running') \
             AND (unlabeled_dataset_id = ?1 OR non_preferred_dataset_id = ?1) ORDER BY id",
        )
        .bind(id)
        .fetch_all(&mut *tx)
        .await?;
        if !jobs.is_empty() {
            return Ok(DeleteOutcome::InUse(jobs));
        }
        sqlx::query("DELETE FROM datasets WHERE id = ?").bind(id).execute(&mut *tx).await?;
        tx.commit().await?;
        match tokio::fs::remove_file(self.canonical_path(id)).await {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            // The row is gone; the next start-up removes the orphaned file.
            Err(e) => tracing::warn!(dataset = id, error = %e, "cannot remove dataset file"),
        }
        Ok(DeleteOutcome::Deleted)
    }

    /// Loads a stored dataset for training, checking the file against the hash recorded at
    /// upload time.
    pub async fn load_dataset(&self, id: &str) -> Result<Dataset, StoreError> {
        let record = self
            .dataset(id)
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.to_owned() })?;
        let path = self.canonical_path(id);
        let read_path = path.clone();
        let read = tokio::task::spawn_blocking(move || std::fs::read(read_path))
            .await
            .map_err(std::io::Error::other)?;
        let bytes = match read {
            Ok(bytes) => bytes,
            // Deleted between reading its row and its file: as if it had never been found. A
            // file missing under a row that is still there is damage, not a race.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(match self.dataset(id).await? {
                    None => StoreError::NotFound { kind: "dataset", id: id.to_owned() },
                    Some(_) => {
                        StoreError::Corrupt(id.to_owned(), format!("{} is missing", path.display()))
                    }
                });
            }
            Err(e) => return Err(e.into()),
        };
        let id = id.to_owned();
        tokio::task::spawn_blocking(move || {
            if bytes.len() as u64 != record.canonical_bytes
                || sha256_hex(&bytes) != record.canonical_sha256
            {
                return Err(StoreError::Corrupt(id, format!("{} changed on disk", path.display())));
            }
            data::decode_canonical(&bytes).map_err(|e| StoreError::Corrupt(id, e.to_string()))
        })
        .await
        .map_err(std::io::Error::other)?
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::{Actions, DatasetParts};

    async fn store_with_a_dataset() -> (tempfile::TempDir, Store, String) {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).await.unwrap();
        let dataset = Dataset::new(DatasetParts {
            obs_dim: 1,
            action_space: ActionSpace::Discrete { n: 2 },
            observations: vec![0.0, 1.0],
            actions: Actions::Discrete(vec![0, 1]),
            next_observations: vec![1.0, 2.0],
            terminals: vec![false, true],
            episode_ids: vec![0, 0],
            rewards: None,
            costs: None,
        })
        .unwrap();
        let new = NewDataset::describe(&dataset, Format::Jsonl, "d".into(), None, "0".into(), 1);
        let record = store.create_dataset(new, data::encode_canonical(&dataset)).await.unwrap();
        (dir, store, record.id)
    }

    /// A missing file is only "not found" when the row went with it (a concurrent delete); a
    /// file missing under a row that is still there is damage, reported as such.
    #[tokio::test]
    async fn a_missing_file_under_an_existing_row_is_corrupt() {
        let (_dir, store, id) = store_with_a_dataset().await;
        std::fs::remove_file(store.canonical_path(&id)).unwrap();
        assert!(matches!(store.load_dataset(&id).await, Err(StoreError::Corrupt(..))));
    }
}
