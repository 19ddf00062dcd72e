//! What the store's unit tests share: a SQLite store holding one small dataset.

use super::{NewDataset, Store};
use crate::data::{self, ActionSpace, Actions, Dataset, DatasetParts, Format};

/// A SQLite store in a temp dir with one two-step dataset: (its dir, the store, the dataset id).
pub(super) async fn store_with_a_dataset() -> (tempfile::TempDir, Store, String) {
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
    (dir, store, record.id.into_string())
}
