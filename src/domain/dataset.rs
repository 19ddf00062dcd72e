//! A stored dataset as the layers above the store see it.

use chrono::{DateTime, Utc};

use super::{DatasetId, DatasetRole};
use crate::data::{ActionSpace, DatasetStats, Format};

/// A stored dataset's description.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetRecord {
    pub id: DatasetId,
    pub name: String,
    pub description: Option<String>,
    pub role: Option<DatasetRole>,
    pub format: Format,
    pub transitions: u64,
    pub episodes: u64,
    pub obs_dim: u64,
    pub action_space: ActionSpace,
    pub stats: DatasetStats,
    pub sha256: String,
    pub bytes: u64,
    pub created_at: DateTime<Utc>,
    /// Checksum and size of the store's canonical encoding of the dataset (what training
    /// loads), checked on every load.
    pub canonical_sha256: String,
    pub canonical_bytes: u64,
}
