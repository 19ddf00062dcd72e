//! Trained policies kept loaded for serving actions (`/act`, the KServe v2 routes, gRPC): each
//! is read from the store and decoded once, then shared by every request. [`registry`] resolves
//! named models (`name`, `name@alias`, a version) to them; [`act`] is the act path every
//! transport shares, [`inference`] the Open Inference Protocol's decisions, whichever transport
//! carries it.

pub mod act;
pub mod inference;
pub mod registry;
pub mod shadow;
pub mod tally;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock, RwLockWriteGuard, Weak};

use crate::algo::Policy;
use crate::domain::PolicyId;
use crate::store::{Store, StoreError};

/// What serves trained policies: the policy cache and the named models' routing tables.
#[derive(Clone)]
pub struct Serving {
    pub policies: Arc<PolicyCache>,
    pub models: Arc<registry::ModelRegistry>,
}

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

/// Policies loaded once from the store and shared by every request, at most `budget` bytes of
/// them: past it the least recently used are dropped (and loaded again if asked for), so one
/// token that can act on every policy cannot hold them all in memory. A dropped policy that a
/// request in flight still holds is handed out again rather than loaded a second time: there is
/// never more than one copy of a policy in the process.
pub struct PolicyCache {
    store: Store,
    slots: RwLock<Slots>,
}

/// What the cache holds, behind one lock so that a load's insert and a forget are ordered.
struct Slots {
    loaded: Lru<Arc<Policy>>,
    /// Every policy loaded, weakly, with its bytes: one dropped from `loaded` but still held by
    /// a request is found here and shared, not loaded again.
    alive: HashMap<String, (Weak<Policy>, u64)>,
    /// The loads under way, per policy. A load reads the store and decodes outside the lock, so
    /// a delete (store, then [`PolicyCache::forget`]) can land in between; the forget marks the
    /// loads it overtook, and those insert nothing and answer as if the policy were already
    /// gone. Only in-flight loads are tracked, so the map stays as small as the traffic.
    loading: HashMap<String, Loading>,
}

#[derive(Default)]
struct Loading {
    /// Requests loading this policy now.
    loads: usize,
    /// A forget ran while they were loading.
    forgotten: bool,
}

/// One request's load of a policy, registered in [`Slots::loading`]; dropping it (the load
/// finished, failed, or the request went away mid-load) deregisters it.
struct LoadTicket<'a> {
    cache: &'a PolicyCache,
    id: &'a str,
}

impl Drop for LoadTicket<'_> {
    fn drop(&mut self) {
        let mut slots = self.cache.write();
        if let Some(loading) = slots.loading.get_mut(self.id) {
            loading.loads -= 1;
            if loading.loads == 0 {
                slots.loading.remove(self.id);
            }
        }
    }
}

impl PolicyCache {
    /// A cache of at most `budget` bytes of policy weights (one policy is kept whatever its
    /// size).
    pub fn new(store: Store, budget: u64) -> Self {
        let slots =
            Slots { loaded: Lru::new(budget), alive: HashMap::new(), loading: HashMap::new() };
        PolicyCache { store, slots: RwLock::new(slots) }
    }

    /// For /metrics: the policies the cache holds and their bytes, and the bytes of the ones
    /// it dropped that requests in flight still hold.
    pub fn usage(&self) -> CacheUsage {
        let slots = self.slots.read().expect("policy cache lock");
        let outside = slots
            .alive
            .iter()
            .filter(|(id, (policy, _))| policy.strong_count() > 0 && !slots.loaded.contains(id))
            .map(|(_, (_, bytes))| bytes)
            .sum();
        CacheUsage {
            loaded: slots.loaded.len(),
            bytes: slots.loaded.bytes(),
            held_outside: outside,
        }
    }

    fn write(&self) -> RwLockWriteGuard<'_, Slots> {
        self.slots.write().expect("policy cache lock")
    }

    /// The policy `id`, loading it on first use. A load that a [`PolicyCache::forget`] of the
    /// same policy overtook answers `NotFound`, like every request after the delete.
    pub async fn get(&self, id: &PolicyId) -> Result<Arc<Policy>, PolicyLoadError> {
        let id = id.as_str();
        // The common case, a loaded policy, takes the shared lock only.
        if let Some(policy) = self.slots.read().expect("policy cache lock").loaded.get(id) {
            return Ok(policy.clone());
        }
        let ticket = {
            let mut slots = self.write();
            if let Some(policy) = slots.loaded.get(id) {
                return Ok(policy.clone());
            }
            if let Some((policy, bytes)) =
                slots.alive.get(id).and_then(|(w, b)| Some((w.upgrade()?, *b)))
            {
                // Dropped from the cache but still in use: the same copy, counted again.
                return Ok(slots.loaded.insert_if_absent(id, bytes, || policy));
            }
            slots.loading.entry(id.to_owned()).or_default().loads += 1;
            LoadTicket { cache: self, id }
        };
        let (spec, weights) = self.store.policy_artifact(&PolicyId::from(id.to_owned())).await?;
        let bytes = weights.len() as u64;
        let unreadable =
            |message: String| PolicyLoadError::Unreadable { id: id.to_owned(), message };
        let decoded = tokio::task::spawn_blocking(move || Policy::from_stored(&spec, &weights))
            .await
            .map_err(|e| unreadable(format!("decoding panicked: {e}")))?;
        let policy = decoded.map_err(|e| unreadable(e.to_string()))?;
        let mut slots = self.write();
        if slots.loading.get(id).is_some_and(|loading| loading.forgotten) {
            // Deleted while this request loaded it: inserting would serve it until restart.
            return Err(StoreError::NotFound { kind: "policy", id: id.to_owned() }.into());
        }
        // Two first requests may both load it; every later one shares the first stored.
        let policy = slots.loaded.insert_if_absent(id, bytes, || Arc::new(policy));
        slots.alive.retain(|_, (policy, _)| policy.strong_count() > 0);
        slots.alive.insert(id.to_owned(), (Arc::downgrade(&policy), bytes));
        // The lock first: dropping the ticket takes it again. A forget from here on finds the
        // policy inserted and removes it.
        drop(slots);
        drop(ticket);
        Ok(policy)
    }

    /// The policy `id` if this process holds it now; never loads it.
    pub fn get_loaded(&self, id: &PolicyId) -> Option<Arc<Policy>> {
        let id = id.as_str();
        let slots = self.slots.read().expect("policy cache lock");
        slots.loaded.get(id).or_else(|| slots.alive.get(id).and_then(|(w, _)| w.upgrade()))
    }

    /// Drops a deleted policy, so this process stops serving it, and marks the loads of it
    /// under way so none inserts it back. Call it after the delete is committed: a load that
    /// starts later finds no policy in the store. (Other API processes of a fleet keep their
    /// loaded copy until they restart: see docs/fleet.md.)
    pub fn forget(&self, id: &PolicyId) {
        let id = id.as_str();
        let mut slots = self.write();
        slots.loaded.remove(id);
        slots.alive.remove(id);
        if let Some(loading) = slots.loading.get_mut(id) {
            loading.forgotten = true;
        }
    }
}

/// What [`PolicyCache::usage`] reports.
pub struct CacheUsage {
    /// Policies in the cache.
    pub loaded: usize,
    /// Their bytes of weights (at most the budget, or one policy).
    pub bytes: u64,
    /// Bytes of policies the cache dropped that requests in flight still hold.
    pub held_outside: u64,
}

/// The policy's portable file: its weights with the spec and its training run (resolved
/// configuration, dataset ids) in the safetensors metadata, so the file alone rebuilds it
/// ([`Policy::from_file`]). Contains no id of the job or policy: two runs of the same training
/// give the same file.
pub async fn portable_weights(store: &Store, id: &PolicyId) -> Result<Vec<u8>, PolicyLoadError> {
    let (weights, metadata) = portable_parts(store, id).await?;
    run_blocking(id.as_str(), move || crate::algo::portable_file(&weights, &metadata)).await
}

/// The stored weights and what the portable file says of them.
async fn portable_parts(
    store: &Store,
    id: &PolicyId,
) -> Result<(Vec<u8>, crate::algo::PortableMetadata), PolicyLoadError> {
    let (_, weights) = store.policy_artifact(id).await?;
    let record = store.policy(id).await?;
    let job = store.job(&record.job_id).await?;
    let training = serde_json::json!({
        "config": job.config,
        "unlabeled_dataset": job.unlabeled_dataset,
        "non_preferred_dataset": job.non_preferred_dataset,
    });
    Ok((weights, crate::algo::PortableMetadata { spec: record.spec, training }))
}

/// CPU work on a policy's bytes, off the runtime's threads; its failure names the policy.
async fn run_blocking<T: Send + 'static>(
    id: &str,
    work: impl FnOnce() -> Result<T, crate::algo::TrainError> + Send + 'static,
) -> Result<T, PolicyLoadError> {
    let unreadable = |message: String| PolicyLoadError::Unreadable { id: id.to_owned(), message };
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| unreadable(e.to_string()))?
        .map_err(|e| unreadable(e.to_string()))
}

/// The policy as an ONNX model ([`crate::algo::onnx`]), built straight from the stored weights
/// (no portable file, no loaded policy in between), with the portable file's metadata in the
/// model's metadata properties: the same model as `safedice export` of the policy file. The
/// stored weights are dropped once the model holds its copy, so an export holds one copy of
/// the weights while it is written out ([`OnnxModel::write_to`]).
///
/// [`OnnxModel::write_to`]: crate::algo::onnx::OnnxModel::write_to
pub async fn onnx_model(
    store: &Store,
    id: &PolicyId,
) -> Result<crate::algo::onnx::OnnxModel, PolicyLoadError> {
    let (weights, metadata) = portable_parts(store, id).await?;
    run_blocking(id.as_str(), move || crate::algo::onnx::build_portable(weights, &metadata)).await
}

/// Values by id with their sizes, dropped least recently used first once their sizes add up to
/// more than `budget` (the value just inserted always stays). A read marks its entry used with
/// an atomic tick, so reads share the lock.
struct Lru<V> {
    entries: HashMap<String, LruEntry<V>>,
    bytes: u64,
    budget: u64,
    clock: AtomicU64,
}

struct LruEntry<V> {
    value: V,
    bytes: u64,
    used: AtomicU64,
}

impl<V: Clone> Lru<V> {
    fn new(budget: u64) -> Self {
        Lru { entries: HashMap::new(), bytes: 0, budget, clock: AtomicU64::new(0) }
    }

    fn tick(&self) -> u64 {
        self.clock.fetch_add(1, Ordering::Relaxed)
    }

    fn get(&self, id: &str) -> Option<V> {
        let entry = self.entries.get(id)?;
        entry.used.store(self.tick(), Ordering::Relaxed);
        Some(entry.value.clone())
    }

    /// The stored value of `id`, inserting `make()` of `bytes` first if there is none (then
    /// evicting others past the budget).
    fn insert_if_absent(&mut self, id: &str, bytes: u64, make: impl FnOnce() -> V) -> V {
        if let Some(value) = self.get(id) {
            return value;
        }
        let value = make();
        let used = AtomicU64::new(self.tick());
        self.entries.insert(id.to_owned(), LruEntry { value: value.clone(), bytes, used });
        self.bytes += bytes;
        while self.bytes > self.budget && self.entries.len() > 1 {
            let oldest = self
                .entries
                .iter()
                .filter(|(key, _)| key.as_str() != id)
                .min_by_key(|(_, entry)| entry.used.load(Ordering::Relaxed))
                .map(|(key, _)| key.clone());
            match oldest {
                Some(key) => self.remove(&key),
                None => break,
            }
        }
        value
    }

    fn contains(&self, id: &str) -> bool {
        self.entries.contains_key(id)
    }

    fn remove(&mut self, id: &str) {
        if let Some(entry) = self.entries.remove(id) {
            self.bytes -= entry.bytes;
        }
    }

    fn len(&self) -> usize {
        self.entries.len()
    }

    fn bytes(&self) -> u64 {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::Lru;

    #[test]
    fn the_least_recently_used_go_first_once_the_budget_is_passed() {
        let mut lru = Lru::new(100);
        assert_eq!(lru.insert_if_absent("a", 40, || 'a'), 'a');
        lru.insert_if_absent("b", 40, || 'b');
        assert_eq!(lru.get("a"), Some('a')); // a is now more recent than b
        lru.insert_if_absent("c", 40, || 'c'); // 120 > 100: b goes
        assert_eq!((lru.get("b"), lru.len(), lru.bytes()), (None, 2, 80));
        assert_eq!(lru.insert_if_absent("a", 40, || 'x'), 'a', "present: not made again");
        // One value larger than the budget stays alone.
        lru.insert_if_absent("huge", 500, || 'h');
        assert_eq!((lru.len(), lru.bytes(), lru.get("huge")), (1, 500, Some('h')));
        lru.remove("huge");
        assert_eq!((lru.len(), lru.bytes()), (0, 0));
    }
}
