//! Dataset rows and their canonical bytes: a file per dataset in the data directory on SQLite,
//! chunks in the `dataset_chunks` table on PostgreSQL (see the module docs of [`super`]).

use std::io::Write;
use std::path::{Path, PathBuf};

use futures::TryStreamExt;
use sha2::{Digest, Sha256};
use sqlx::{Any, Transaction};

use super::{now_in, parse_time, Backend, Listing, PageQuery, Store, StoreError};
use crate::data::{self, ActionSpace, Dataset, DatasetStats, Format};
use crate::domain::{DatasetId, DatasetRecord, DatasetRole, JobStatus};

const CANONICAL_EXTENSION: &str = "canonical";
const COLUMNS: &str = "id, name, description, format, transitions, episodes, obs_dim, \
     action_space, stats, sha256, bytes, canonical_sha256, canonical_bytes, created_at, role";

/// What is known about an accepted upload before it is stored.
#[derive(Debug, Clone)]
pub struct NewDataset {
    pub name: String,
    pub description: Option<String>,
    /// What the uploader said the dataset is for.
    pub role: Option<DatasetRole>,
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
            role: None,
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

#[derive(sqlx::FromRow)]
struct DatasetRow {
    id: String,
    name: String,
    description: Option<String>,
    format: String,
    transitions: i64,
    episodes: i64,
    obs_dim: i64,
    action_space: String,
    stats: String,
    sha256: String,
    bytes: i64,
    canonical_sha256: String,
    canonical_bytes: i64,
    created_at: String,
    role: Option<String>,
}

impl TryFrom<DatasetRow> for DatasetRecord {
    type Error = StoreError;

    fn try_from(row: DatasetRow) -> Result<Self, StoreError> {
        let format: Format = row
            .format
            .parse()
            .map_err(|e: data::ParseError| StoreError::Corrupt(row.id.clone(), e.message))?;
        let json = |what: &str, e: serde_json::Error| {
            StoreError::Corrupt(row.id.clone(), format!("stored {what}: {e}"))
        };
        let action_space =
            serde_json::from_str(&row.action_space).map_err(|e| json("action space", e))?;
        let stats = serde_json::from_str(&row.stats).map_err(|e| json("stats", e))?;
        let created_at = parse_time(&row.id, &row.created_at)?;
        let role = match row.role.as_deref() {
            Some(text) => Some(DatasetRole::parse(text).ok_or_else(|| {
                StoreError::Corrupt(row.id.clone(), format!("stored role {text:?}"))
            })?),
            None => None,
        };
        Ok(DatasetRecord {
            id: DatasetId::from(row.id),
            name: row.name,
            description: row.description,
            role,
            format,
            transitions: row.transitions as u64,
            episodes: row.episodes as u64,
            obs_dim: row.obs_dim as u64,
            action_space,
            stats,
            sha256: row.sha256,
            bytes: row.bytes as u64,
            created_at,
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
    /// Queued or running work (ids) still needs it: jobs of a dataset, evaluations of a
    /// policy, the evaluation itself.
    InUse(Vec<String>),
    /// Model versions (`name version n`) point at it: a policy that may be deployed.
    Registered(Vec<String>),
}

/// The dataset id a canonical file belongs to, from its name `<id>.canonical`.
pub(super) fn id_of_canonical_file(path: &Path) -> Option<&str> {
    let is_canonical = path.extension().is_some_and(|e| e == CANONICAL_EXTENSION);
    is_canonical.then(|| path.file_stem()?.to_str()).flatten()
}

/// The JSON of a stored description (plain data: serialising cannot fail).
fn to_json(value: &impl serde::Serialize) -> String {
    serde_json::to_string(value).expect("dataset descriptions serialise to JSON")
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

/// Bytes per row of `dataset_chunks`: large enough that a 1 GiB dataset is 256 rows, small
/// enough that a row never holds much memory on either side of the connection.
const CHUNK_BYTES: usize = 4 << 20;

impl Store {
    fn canonical_path(&self, id: &str) -> PathBuf {
        self.datasets_dir().join(format!("{id}.{CANONICAL_EXTENSION}"))
    }

    /// Stores an accepted upload: its canonical bytes and its row. Either both exist afterwards
    /// or neither does (SQLite: the file is durably in place before the row is inserted;
    /// PostgreSQL: row and chunks are one transaction).
    pub async fn create_dataset(
        &self,
        new: NewDataset,
        canonical: Vec<u8>,
    ) -> Result<DatasetRecord, StoreError> {
        let id = crate::domain::DatasetId::generate().into_string();
        match self.backend {
            Backend::Sqlite => self.create_dataset_file(&id, &new, canonical).await?,
            Backend::Postgres => {
                let hashed = canonical_sha256(canonical).await?;
                let mut tx = self.begin_write().await?;
                insert_dataset_row(&mut tx, &id, &new, &hashed).await?;
                for (seq, chunk) in hashed.bytes.chunks(CHUNK_BYTES).enumerate() {
                    sqlx::query(
                        "INSERT INTO dataset_chunks (dataset_id, seq, data) VALUES ($1, $2, $3)",
                    )
                    .bind(&id)
                    .bind(seq as i64)
                    .bind(chunk)
                    .execute(&mut *tx)
                    .await?;
                }
                tx.commit().await?;
            }
        }
        self.dataset(&DatasetId::from(id.clone()))
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.clone() })
    }

    async fn create_dataset_file(
        &self,
        id: &str,
        new: &NewDataset,
        canonical: Vec<u8>,
    ) -> Result<(), StoreError> {
        let path = self.canonical_path(id);
        let dir = self.datasets_dir();
        let write_path = path.clone();
        let hashed = tokio::task::spawn_blocking(move || {
            write_atomically(&dir, &write_path, &canonical).map(|()| Hashed::of(canonical))
        })
        .await
        .map_err(std::io::Error::other)??;
        let mut tx = self.begin_write().await?;
        let inserted = insert_dataset_row(&mut tx, id, new, &hashed).await;
        let committed = match inserted {
            Ok(()) => tx.commit().await.map_err(StoreError::from),
            Err(e) => Err(e),
        };
        if let Err(e) = committed {
            let _ = tokio::fs::remove_file(&path).await;
            return Err(e);
        }
        Ok(())
    }

    /// One dataset's description.
    pub async fn dataset(&self, id: &DatasetId) -> Result<Option<DatasetRecord>, StoreError> {
        let id = id.as_str();
        let row: Option<DatasetRow> =
            sqlx::query_as(&format!("SELECT {COLUMNS} FROM datasets WHERE id = $1"))
                .bind(id)
                .fetch_optional(self.pool())
                .await?;
        row.map(DatasetRecord::try_from).transpose()
    }

    /// A page of datasets, newest first, and the total count.
    pub async fn datasets(
        &self,
        page: &PageQuery,
    ) -> Result<(Vec<DatasetRecord>, u64), StoreError> {
        let (rows, total) = Listing::Datasets.page::<DatasetRow>(self, COLUMNS, page).await?;
        let records = rows.into_iter().map(DatasetRecord::try_from).collect::<Result<_, _>>()?;
        Ok((records, total))
    }

    pub(super) async fn dataset_ids(&self) -> Result<Vec<String>, sqlx::Error> {
        sqlx::query_scalar("SELECT id FROM datasets").fetch_all(self.pool()).await
    }

    /// Deletes a dataset unless a queued or running job uses it. The check and the delete are
    /// one write transaction (the dataset's row locked first), so a job queued concurrently
    /// either commits first and is seen here, or sees the dataset gone (see
    /// [`Store::insert_job`]); and the answer describes the state the delete saw, not one read
    /// after it.
    pub async fn delete_dataset(&self, id: &DatasetId) -> Result<DeleteOutcome, StoreError> {
        let id = id.as_str();
        let Some((mut tx, _)) = self.begin_delete("datasets", "id", id).await? else {
            return Ok(DeleteOutcome::NotFound);
        };
        let jobs: Vec<String> = sqlx::query_scalar(&format!(
            "SELECT id FROM jobs WHERE status IN ({}, {}) \
             AND (unlabeled_dataset_id = $1 OR non_preferred_dataset_id = $1) ORDER BY id",
            JobStatus::Queued.sql(),
            JobStatus::Running.sql()
        ))
        .bind(id)
        .fetch_all(&mut *tx)
        .await?;
        if !jobs.is_empty() {
            return Ok(DeleteOutcome::InUse(jobs));
        }
        // On PostgreSQL the chunks go with the row (ON DELETE CASCADE).
        sqlx::query("DELETE FROM datasets WHERE id = $1").bind(id).execute(&mut *tx).await?;
        tx.commit().await?;
        if self.backend == Backend::Sqlite {
            match tokio::fs::remove_file(self.canonical_path(id)).await {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                // The row is gone; the next start-up removes the orphaned file.
                Err(e) => tracing::warn!(dataset = id, error = %e, "cannot remove dataset file"),
            }
        }
        Ok(DeleteOutcome::Deleted)
    }

    /// Loads a stored dataset for training, checking its bytes against the hash recorded at
    /// upload time.
    pub async fn load_dataset(&self, id: &DatasetId) -> Result<Dataset, StoreError> {
        let record = self
            .dataset(id)
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.to_string() })?;
        let id = id.as_str();
        self.verify_canonical(id, &record).await?;
        let header = self.canonical_header(id, record.canonical_bytes).await?;
        // Column by column on a blocking thread: memory holds the decoded dataset and one
        // column's bytes, never the whole file beside it.
        let (store, owned_id, runtime) =
            (self.clone(), id.to_owned(), tokio::runtime::Handle::current());
        let decoded = tokio::task::spawn_blocking(move || {
            let mut failed = None;
            let decoded = header.decode_by_column(|range| {
                runtime.block_on(store.read_canonical_range(&owned_id, range)).map_err(|e| {
                    let message = e.to_string();
                    failed = Some(e);
                    data::ParseError::corrupt_canonical(message)
                })
            });
            match (decoded, failed) {
                (_, Some(read_error)) => Err(read_error),
                (decoded, None) => {
                    decoded.map_err(|e| StoreError::Corrupt(owned_id, e.to_string()))
                }
            }
        });
        decoded.await.map_err(std::io::Error::other)?
    }

    /// Checks that the stored file is the one uploaded (its length and SHA-256), reading it in
    /// pieces: a file or chunks changed since upload are `Corrupt`.
    async fn verify_canonical(&self, id: &str, record: &DatasetRecord) -> Result<(), StoreError> {
        let mut hasher = Sha256::new();
        let mut length = 0u64;
        let place = match self.backend {
            Backend::Sqlite => {
                let path = self.canonical_path(id);
                let hashing = path.clone();
                let hashed = tokio::task::spawn_blocking(move || {
                    use std::io::Read;
                    let mut file = std::fs::File::open(&hashing)?;
                    let mut piece = vec![0; CHUNK_BYTES];
                    loop {
                        let n = file.read(&mut piece)?;
                        if n == 0 {
                            return Ok::<_, std::io::Error>((hasher, length));
                        }
                        hasher.update(&piece[..n]);
                        length += n as u64;
                    }
                });
                match hashed.await.map_err(std::io::Error::other)? {
                    Ok(done) => (hasher, length) = done,
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        return Err(self.missing_file(id, &path).await);
                    }
                    Err(e) => return Err(e.into()),
                }
                path.display().to_string()
            }
            Backend::Postgres => {
                let mut chunks = sqlx::query_scalar::<_, Vec<u8>>(
                    "SELECT data FROM dataset_chunks WHERE dataset_id = $1 ORDER BY seq",
                )
                .bind(id)
                .fetch(self.pool());
                while let Some(chunk) = chunks.try_next().await? {
                    hasher.update(&chunk);
                    length += chunk.len() as u64;
                }
                "its stored chunks".to_owned()
            }
        };
        let sha256 = format!("{:x}", hasher.finalize());
        if length != record.canonical_bytes || sha256 != record.canonical_sha256 {
            return Err(StoreError::Corrupt(
                id.to_owned(),
                format!("{place} changed since upload"),
            ));
        }
        Ok(())
    }

    /// A dataset's file not found: deleted between reading its row and its file (as if never
    /// found), or, under a row that is still there, damage.
    async fn missing_file(&self, id: &str, path: &Path) -> StoreError {
        match self.dataset(&DatasetId::from(id.to_owned())).await {
            Ok(None) => StoreError::NotFound { kind: "dataset", id: id.to_owned() },
            Ok(Some(_)) => {
                StoreError::Corrupt(id.to_owned(), format!("{} is missing", path.display()))
            }
            Err(e) => e,
        }
    }

    /// A preview of a stored dataset's first `rows` transitions and `episodes` episodes, read
    /// from the file's ranges alone: its header, the `episode_ids` column, the first rows of
    /// every column, and the terminals, rewards and costs of the episodes summarised. Memory
    /// grows with the rows shown and 13 bytes a transition, not with the observations. The
    /// whole file's checksum is left to full loads.
    pub async fn preview_dataset(
        &self,
        id: &DatasetId,
        rows: usize,
        episodes: usize,
    ) -> Result<data::DatasetPreview, StoreError> {
        let record = self
            .dataset(id)
            .await?
            .ok_or_else(|| StoreError::NotFound { kind: "dataset", id: id.to_string() })?;
        let id = id.as_str();
        let corrupt = |e: data::ParseError| StoreError::Corrupt(id.to_owned(), e.to_string());
        let header = self.canonical_header(id, record.canonical_bytes).await?;
        let ids = match header.prefix_range("episode_ids", header.rows()) {
            Some(range) => self.read_canonical_range(id, range).await?,
            None => Vec::new(),
        };
        let summarised = data::preview_rows(&ids, rows, episodes);
        let head_rows = rows.clamp(1, header.rows().max(1));
        let head = self.read_ranges(id, header.prefix_ranges(head_rows)).await?;
        let head = header.decode_prefix(&head).map_err(corrupt)?;
        let columns = self.read_ranges(id, header.episode_column_ranges(summarised)).await?;
        let ids = &ids[..(summarised * 4).min(ids.len())];
        let columns = header.decode_episode_columns(ids, &columns).map_err(corrupt)?;
        Ok(data::preview_parts(&head, rows, &columns, episodes))
    }

    /// The header of a dataset's canonical file (where each column lies), read alone.
    async fn canonical_header(
        &self,
        id: &str,
        file_len: u64,
    ) -> Result<data::CanonicalHeader, StoreError> {
        let corrupt = |e: data::ParseError| StoreError::Corrupt(id.to_owned(), e.to_string());
        let prefix_len = data::CANONICAL_PREFIX_BYTES as u64;
        let prefix = self.read_canonical_range(id, 0..prefix_len).await?;
        let prefix = prefix.try_into().map_err(|_| {
            StoreError::Corrupt(id.to_owned(), "shorter than its header's length".into())
        })?;
        let header_len = data::canonical_header_len(prefix).map_err(corrupt)? as u64;
        let header = self.read_canonical_range(id, prefix_len..prefix_len + header_len).await?;
        data::CanonicalHeader::parse(&header, file_len).map_err(corrupt)
    }

    async fn read_ranges(
        &self,
        id: &str,
        ranges: Vec<(String, std::ops::Range<u64>)>,
    ) -> Result<std::collections::HashMap<String, Vec<u8>>, StoreError> {
        let mut columns = std::collections::HashMap::new();
        for (name, range) in ranges {
            columns.insert(name, self.read_canonical_range(id, range).await?);
        }
        Ok(columns)
    }

    /// Bytes `range` of a dataset's canonical file: a positional read of the file (SQLite), or
    /// the stored chunks that cover it (PostgreSQL).
    async fn read_canonical_range(
        &self,
        id: &str,
        range: std::ops::Range<u64>,
    ) -> Result<Vec<u8>, StoreError> {
        let len = usize::try_from(range.end - range.start).map_err(std::io::Error::other)?;
        match self.backend {
            Backend::Sqlite => {
                let path = self.canonical_path(id);
                let read = tokio::task::spawn_blocking(move || {
                    use std::os::unix::fs::FileExt;
                    let mut bytes = vec![0; len];
                    std::fs::File::open(&path)?.read_exact_at(&mut bytes, range.start)?;
                    Ok::<_, std::io::Error>(bytes)
                });
                Ok(read.await.map_err(std::io::Error::other)??)
            }
            Backend::Postgres => {
                let chunk = CHUNK_BYTES as u64;
                let (first, last) = (range.start / chunk, range.end.saturating_sub(1) / chunk);
                let mut covering = sqlx::query_scalar::<_, Vec<u8>>(
                    "SELECT data FROM dataset_chunks WHERE dataset_id = $1 AND seq >= $2 \
                     AND seq <= $3 ORDER BY seq",
                )
                .bind(id)
                .bind(first as i64)
                .bind(last as i64)
                .fetch(self.pool());
                let mut bytes = Vec::with_capacity(len);
                let mut at = first * chunk;
                while let Some(data) = covering.try_next().await? {
                    let from = range.start.saturating_sub(at) as usize;
                    let to = ((range.end - at) as usize).min(data.len());
                    bytes.extend_from_slice(&data[from.min(to)..to]);
                    at += chunk;
                }
                if bytes.len() != len {
                    let why = format!("its stored chunks end before byte {}", range.end);
                    return Err(StoreError::Corrupt(id.to_owned(), why));
                }
                Ok(bytes)
            }
        }
    }
}

/// Canonical bytes with their SHA-256.
struct Hashed {
    bytes: Vec<u8>,
    sha256: String,
}

impl Hashed {
    fn of(bytes: Vec<u8>) -> Self {
        let sha256 = sha256_hex(&bytes);
        Hashed { bytes, sha256 }
    }
}

async fn canonical_sha256(canonical: Vec<u8>) -> Result<Hashed, StoreError> {
    Ok(tokio::task::spawn_blocking(move || Hashed::of(canonical))
        .await
        .map_err(std::io::Error::other)?)
}

async fn insert_dataset_row(
    tx: &mut Transaction<'_, Any>,
    id: &str,
    new: &NewDataset,
    hashed: &Hashed,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO datasets (id, name, description, format, transitions, episodes, obs_dim, \
         action_space, stats, sha256, bytes, canonical_sha256, canonical_bytes, created_at, role) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15)",
    )
    .bind(id)
    .bind(&new.name)
    .bind(&new.description)
    .bind(new.format.as_str())
    .bind(new.transitions as i64)
    .bind(new.episodes as i64)
    .bind(new.obs_dim as i64)
    .bind(to_json(&new.action_space))
    .bind(to_json(&new.stats))
    .bind(&new.sha256)
    .bind(new.bytes as i64)
    .bind(&hashed.sha256)
    .bind(hashed.bytes.len() as i64)
    .bind(now_in(tx).await?)
    .bind(new.role.map(DatasetRole::as_str))
    .execute(&mut **tx)
    .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::test_support::store_with_a_dataset;

    /// A missing file is only "not found" when the row went with it (a concurrent delete); a
    /// file missing under a row that is still there is damage, reported as such.
    #[tokio::test]
    async fn a_missing_file_under_an_existing_row_is_corrupt() {
        let (_dir, store, id) = store_with_a_dataset().await;
        std::fs::remove_file(store.canonical_path(&id)).unwrap();
        assert!(matches!(
            store.load_dataset(&DatasetId::from(id.clone())).await,
            Err(StoreError::Corrupt(..))
        ));
    }
}
