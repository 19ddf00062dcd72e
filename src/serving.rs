//! Trained policies kept loaded for serving actions (`/act` and the KServe v2 routes): each is
//! read from the store and decoded once, then shared by every request.

use std::collections::HashMap;
use std::sync::{Arc, RwLock};

use crate::algo::Policy;
use crate::store::{Store, StoreError};

/// Why a policy could not be served.
#[derive(Debug, thiserror::Error)]
pub enum PolicyLoadError {
    /// The policy does not exist (`NotFound`), or the store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The stored artefact does not decode.
    #[error("policy {id}: {message}")]
    Unreadable { id: String, message: String },
}

/// Policies loaded once from the store and shared by every request.
pub struct PolicyCache {
    store: Store,
    loaded: RwLock<HashMap<String, Arc<Policy>>>,
}

impl PolicyCache {
    pub fn new(store: Store) -> Self {
        PolicyCache { store, loaded: RwLock::new(HashMap::new()) }
    }

    /// The policy `id`, loading it on first use.
    pub async fn get(&self, id: &str) -> Result<Arc<Policy>, PolicyLoadError> {
        if let Some(policy) = self.loaded.read().expect("policy cache lock").get(id) {
            return Ok(policy.clone());
        }
        let (spec, weights) = self.store.policy_artifact(id).await?;
        let unreadable =
            |message: String| PolicyLoadError::Unreadable { id: id.to_owned(), message };
        let decoded = tokio::task::spawn_blocking(move || Policy::from_stored(&spec, &weights))
            .await
            .map_err(|e| unreadable(format!("decoding panicked: {e}")))?;
        let policy = decoded.map_err(|e| unreadable(e.to_string()))?;
        let mut loaded = self.loaded.write().expect("policy cache lock");
        // Two first requests may both load it; every later one shares the first stored.
        Ok(loaded.entry(id.to_owned()).or_insert_with(|| Arc::new(policy)).clone())
    }
}
