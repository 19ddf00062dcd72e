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

    /// Drops a deleted policy, so this process stops serving it. (Other API processes of a
    /// fleet keep their loaded copy until they restart: see docs/fleet.md.)
    pub fn forget(&self, id: &str) {
        self.loaded.write().expect("policy cache lock").remove(id);
    }
}

/// The policy's portable file: its weights with the spec and its training run (resolved
/// configuration, dataset ids) in the safetensors metadata, so the file alone rebuilds it
/// ([`Policy::from_file`]). Contains no id of the job or policy: two runs of the same training
/// give the same file.
pub async fn portable_weights(store: &Store, id: &str) -> Result<Vec<u8>, PolicyLoadError> {
    let unreadable = |message: String| PolicyLoadError::Unreadable { id: id.to_owned(), message };
    let (_, weights) = store.policy_artifact(id).await?;
    let record = store.policy(id).await?;
    let job = store.job(&record.job_id).await?;
    let training = serde_json::json!({
        "config": job.config,
        "unlabeled_dataset": job.unlabeled_dataset,
        "non_preferred_dataset": job.non_preferred_dataset,
    });
    let metadata = crate::algo::PortableMetadata { spec: record.spec, training };
    tokio::task::spawn_blocking(move || crate::algo::portable_file(&weights, &metadata))
        .await
        .map_err(|e| unreadable(e.to_string()))?
        .map_err(|e| unreadable(e.to_string()))
}

/// The policy as an ONNX model ([`crate::algo::onnx`]), its portable file's metadata kept in the
/// model's metadata properties.
pub async fn onnx_model(store: &Store, id: &str) -> Result<Vec<u8>, PolicyLoadError> {
    let unreadable = |message: String| PolicyLoadError::Unreadable { id: id.to_owned(), message };
    let file = portable_weights(store, id).await?;
    tokio::task::spawn_blocking(move || {
        let (policy, metadata) = Policy::from_portable(&file)?;
        let json = serde_json::to_string(&metadata)
            .map_err(|e| crate::algo::TrainError::Other(e.to_string()))?;
        let key = crate::algo::policy::PORTABLE_METADATA_KEY;
        crate::algo::onnx::export(policy.spec(), &file, &[(key, json)])
    })
    .await
    .map_err(|e| unreadable(e.to_string()))?
    .map_err(|e| unreadable(e.to_string()))
}
