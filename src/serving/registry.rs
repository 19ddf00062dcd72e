//! Serving by name: which policy answers `name`, `name@alias` or a version of a named model.
//!
//! Each process keeps a routing table per model, built from the store ([`Store::model_routes`])
//! and swapped whole: the policies of the latest version and of every alias (its canary and
//! shadow too) are loaded first (a policy that does not load keeps the old table serving), and
//! only then does the new table replace the old one. Tables hold policy ids, not policies: a request takes its
//! policy from the [`PolicyCache`] by id, so every model and alias over one policy shares one
//! copy, counted in `--policy-cache-bytes`, and a policy evicted from the cache is loaded again
//! when next asked for rather than pinned by a table. Requests in flight keep the policy they
//! resolved (an `Arc`) while the table changes under them: moving an alias loses no request.
//!
//! The table follows the store: this process refreshes a model at once after changing it
//! ([`ModelRegistry::refresh_model`]); changes made elsewhere (another API node, a worker
//! registering a job's policy) arrive by PostgreSQL notification within milliseconds, and by a
//! poll of every model's revision each [`POLL`] on either store.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use super::shadow::Shadows;
use super::{PolicyCache, PolicyLoadError};
use crate::algo::Policy;
use crate::domain::model::{AliasTarget, ModelName, ModelRef, ModelRoutes, Selector, BASIS_POINTS};
use crate::domain::PolicyId;
use crate::store::models::MODELS_CHANNEL;
use crate::store::{Store, StoreError};

/// How often every model's revision is compared with the loaded one (the fallback when no
/// notification arrives, and the only way on SQLite).
pub const POLL: Duration = Duration::from_secs(1);

/// How often a request for a model, alias or version this process does not know may look for
/// it in the store.
const MISS_RECHECK: Duration = Duration::from_millis(250);

/// Request counts and time of one version on this process (the Open Inference Protocol's
/// statistics extension).
#[derive(Debug, Default)]
pub struct VersionStats {
    pub success: AtomicU64,
    pub success_ns: AtomicU64,
    pub fail: AtomicU64,
    pub fail_ns: AtomicU64,
    /// Milliseconds since the Unix epoch of the last request (0: none yet).
    pub last_inference_ms: AtomicU64,
    /// The safety scores this version answered.
    pub safety: super::tally::SafetyTally,
}

impl VersionStats {
    /// Counts one request that took `elapsed`.
    pub fn record(&self, ok: bool, elapsed: Duration) {
        let (count, ns) =
            if ok { (&self.success, &self.success_ns) } else { (&self.fail, &self.fail_ns) };
        count.fetch_add(1, Ordering::Relaxed);
        ns.fetch_add(elapsed.as_nanos() as u64, Ordering::Relaxed);
        let now = chrono::Utc::now().timestamp_millis().max(0) as u64;
        self.last_inference_ms.store(now, Ordering::Relaxed);
    }
}

/// A version ready to answer: its policy loaded.
#[derive(Clone)]
pub struct Target {
    pub version: u32,
    pub policy_id: PolicyId,
    pub policy: Arc<Policy>,
    pub stats: Arc<VersionStats>,
}

/// A version in a routing table: its policy by id (the cache holds the policy).
#[derive(Clone)]
struct Route {
    version: u32,
    policy_id: PolicyId,
    stats: Arc<VersionStats>,
}

struct AliasRoute {
    main: Route,
    canary: Option<(Route, u32)>,
    /// The shadow's version and its share of requests, in basis points.
    shadow: Option<(Route, u32)>,
}

/// One model's routing table, of one revision.
struct Deployed {
    revision: u64,
    /// The model's creation stamp ([`ModelRoutes::created_at`]), for its shadows' counts.
    created_at: String,
    latest: Option<Route>,
    aliases: HashMap<String, AliasRoute>,
    versions: BTreeMap<u32, PolicyId>,
}

/// What answers a request: the model's name and the version chosen, with its policy; and the
/// alias's shadow when this request was drawn for it.
pub struct Answer {
    pub model: String,
    pub target: Target,
    pub shadow: Option<ShadowDraw>,
}

/// A request drawn for an alias's shadow.
pub struct ShadowDraw {
    /// Which incarnation of the model drew it ([`crate::domain::shadow::ComparisonKey::model_created`]).
    pub model_created: String,
    pub alias: String,
    pub version: u32,
    /// Its policy, when the cache holds it (a shadow never loads one on the request's time:
    /// without it the comparison is skipped and counted).
    pub policy: Option<Arc<Policy>>,
    pub shadows: Arc<Shadows>,
}

impl Answer {
    /// Runs `work` for this version and counts it, success or failure and its time, in the
    /// version's statistics (what the statistics extension reports, whichever route or RPC).
    pub async fn timed<T, E>(
        &self,
        work: impl std::future::Future<Output = Result<T, E>>,
    ) -> Result<T, E> {
        let started = Instant::now();
        let result = work.await;
        self.target.stats.record(result.is_ok(), started.elapsed());
        result
    }
}

/// Why a name resolves to nothing.
#[derive(Debug, thiserror::Error)]
pub enum ResolveError {
    /// No such model, alias or version (the message says which).
    #[error("{0}")]
    NotFound(String),
    /// The model was unloaded from this process (`POST /v2/repository/models/{name}/unload`).
    #[error("model {0} is unloaded on this server; load it again with POST /v2/repository/models/{0}/load")]
    Unloaded(String),
    #[error(transparent)]
    Load(#[from] PolicyLoadError),
}

impl From<StoreError> for ResolveError {
    fn from(e: StoreError) -> Self {
        ResolveError::Load(e.into())
    }
}

/// A model as the repository index lists it.
pub struct IndexEntry {
    pub name: String,
    /// `READY` or `UNAVAILABLE`.
    pub state: &'static str,
    /// Why it is not ready (empty when it is).
    pub reason: String,
    pub latest_version: Option<u32>,
}

/// The routing tables of this process.
pub struct ModelRegistry {
    store: Store,
    policies: Arc<PolicyCache>,
    tables: RwLock<HashMap<String, Arc<Deployed>>>,
    shadows: Arc<Shadows>,
    /// Shadow policies being loaded again in the background after the cache dropped them.
    reloading: Arc<Mutex<HashSet<PolicyId>>>,
    unloaded: Mutex<HashSet<String>>,
    stats: Mutex<HashMap<(String, u32), Arc<VersionStats>>>,
    /// When a request last made this process look in the store for a name it did not know.
    miss_checked: Mutex<HashMap<String, Instant>>,
}

impl ModelRegistry {
    pub fn new(store: Store, policies: Arc<PolicyCache>, shadows: Arc<Shadows>) -> Self {
        ModelRegistry {
            store,
            policies,
            tables: RwLock::new(HashMap::new()),
            shadows,
            reloading: Arc::new(Mutex::new(HashSet::new())),
            unloaded: Mutex::new(HashSet::new()),
            stats: Mutex::new(HashMap::new()),
            miss_checked: Mutex::new(HashMap::new()),
        }
    }

    fn table(&self, model: &str) -> Option<Arc<Deployed>> {
        self.tables.read().expect("model tables lock").get(model).cloned()
    }

    fn is_unloaded(&self, model: &str) -> bool {
        self.unloaded.lock().expect("unloaded lock").contains(model)
    }

    /// The statistics of a version on this process, created on first use.
    pub fn stats(&self, model: &str, version: u32) -> Arc<VersionStats> {
        let mut stats = self.stats.lock().expect("stats lock");
        stats.entry((model.to_owned(), version)).or_default().clone()
    }

    /// The version that answers `reference`; `key` (a client's request key) picks between an
    /// alias's version and its canary the same way every time, on every node.
    pub async fn resolve(
        &self,
        reference: &ModelRef,
        key: Option<&str>,
    ) -> Result<Answer, ResolveError> {
        let model = reference.model.as_str();
        if self.is_unloaded(model) {
            return Err(ResolveError::Unloaded(model.to_owned()));
        }
        match self.resolve_loaded(reference, key).await {
            // An alias or version made on another node a moment ago, before its notification
            // arrived: one look at the store (at most every MISS_RECHECK per model, so requests
            // for names that do not exist cannot turn into a query each).
            Err(ResolveError::NotFound(_)) if self.may_recheck(model) => {
                self.refresh_model(model).await?;
                self.resolve_loaded(reference, key).await
            }
            answered => answered,
        }
    }

    fn may_recheck(&self, model: &str) -> bool {
        let mut checked = self.miss_checked.lock().expect("miss lock");
        let now = Instant::now();
        match checked.get(model) {
            Some(at) if now.duration_since(*at) < MISS_RECHECK => false,
            _ => {
                if checked.len() > 10_000 {
                    checked.clear();
                }
                checked.insert(model.to_owned(), now);
                true
            }
        }
    }

    async fn resolve_loaded(
        &self,
        reference: &ModelRef,
        key: Option<&str>,
    ) -> Result<Answer, ResolveError> {
        let model = reference.model.as_str();
        let table = self
            .table(model)
            .ok_or_else(|| ResolveError::NotFound(format!("model {model} does not exist")))?;
        let mut shadow = None;
        let route = match &reference.selector {
            Selector::Latest => table.latest.clone().ok_or_else(|| {
                ResolveError::NotFound(format!("model {model} has no version yet"))
            })?,
            Selector::Alias(alias) => {
                let route = table.aliases.get(alias.as_str()).ok_or_else(|| {
                    ResolveError::NotFound(format!("model {model} has no alias {alias}"))
                })?;
                let picked = pick(route, key).clone();
                shadow = self.draw_shadow(&table, alias.as_str(), route, &picked);
                picked
            }
            Selector::Version(version) => {
                let policy_id = table.versions.get(version).ok_or_else(|| {
                    ResolveError::NotFound(format!("model {model} has no version {version}"))
                })?;
                self.route(model, *version, policy_id)
            }
        };
        Ok(Answer { model: model.to_owned(), target: self.target(route).await?, shadow })
    }

    /// The alias's shadow for this request, for its share of requests (drawn at random, apart
    /// from the canary's key) unless the shadow's version is the one answering.
    fn draw_shadow(
        &self,
        table: &Deployed,
        alias: &str,
        route: &AliasRoute,
        answering: &Route,
    ) -> Option<ShadowDraw> {
        let (shadow, basis_points) = route.shadow.as_ref()?;
        if shadow.version == answering.version
            || rand::random_range(0..BASIS_POINTS) >= *basis_points
        {
            return None;
        }
        let policy = self.policies.get_loaded(&shadow.policy_id);
        if policy.is_none() {
            self.reload_in_background(&shadow.policy_id);
        }
        Some(ShadowDraw {
            model_created: table.created_at.clone(),
            alias: alias.to_owned(),
            version: shadow.version,
            policy,
            shadows: self.shadows.clone(),
        })
    }

    /// Loads a shadow's policy the cache dropped, off every request's time (once at a time per
    /// policy), so the shadow's comparisons resume rather than stay skipped.
    fn reload_in_background(&self, id: &PolicyId) {
        if !self.reloading.lock().expect("reloading lock").insert(id.clone()) {
            return;
        }
        let (policies, reloading, id) = (self.policies.clone(), self.reloading.clone(), id.clone());
        tokio::spawn(async move {
            if let Err(e) = policies.get(&id).await {
                tracing::warn!(policy = %id, error = %e, "cannot load a shadow's policy again");
            }
            reloading.lock().expect("reloading lock").remove(&id);
        });
    }

    /// The shadows' runner of this process.
    pub fn shadows(&self) -> &Arc<Shadows> {
        &self.shadows
    }

    /// A table's version with its policy, from the cache (loaded again if it was evicted).
    async fn target(&self, route: Route) -> Result<Target, ResolveError> {
        let policy = self.policies.get(&route.policy_id).await?;
        Ok(Target {
            version: route.version,
            policy_id: route.policy_id,
            policy,
            stats: route.stats,
        })
    }

    fn route(&self, model: &str, version: u32, policy_id: &PolicyId) -> Route {
        Route { version, policy_id: policy_id.clone(), stats: self.stats(model, version) }
    }

    /// Reads the model from the store and, if it changed, loads the policies its new table needs
    /// and swaps the table in (or drops it: the model was deleted). A policy that fails to load
    /// leaves the old table serving, and the error is returned (the next poll tries again).
    pub async fn refresh_model(&self, name: &str) -> Result<(), ResolveError> {
        if self.is_unloaded(name) {
            return Ok(());
        }
        let Some(routes) = self.store.model_routes(name).await? else {
            self.tables.write().expect("model tables lock").remove(name);
            return Ok(());
        };
        if self.table(name).is_some_and(|t| t.revision >= routes.revision) {
            return Ok(());
        }
        let table = Arc::new(self.build(&routes).await?);
        let mut tables = self.tables.write().expect("model tables lock");
        // Two refreshes may race; the newer revision stays.
        if tables.get(name).is_none_or(|t| t.revision < table.revision) {
            tables.insert(name.to_owned(), table);
        }
        Ok(())
    }

    /// The table of `routes`, once every policy it routes to has loaded (through the cache,
    /// which keeps them as its budget allows).
    async fn build(&self, routes: &ModelRoutes) -> Result<Deployed, ResolveError> {
        let versions: BTreeMap<u32, PolicyId> = routes.versions.iter().cloned().collect();
        let model = &routes.name;
        let latest = versions.last_key_value().map(|(&v, id)| self.route(model, v, id));
        let mut aliases = HashMap::new();
        for (alias, AliasTarget { version, canary, shadow }) in &routes.aliases {
            let main = self.route_of(model, &versions, *version)?;
            let canary = match canary {
                Some(c) => Some((self.route_of(model, &versions, c.version)?, c.basis_points)),
                None => None,
            };
            let shadow = match shadow {
                Some(s) => Some((self.route_of(model, &versions, s.version)?, s.basis_points)),
                None => None,
            };
            aliases.insert(alias.clone(), AliasRoute { main, canary, shadow });
        }
        let routed = latest.iter().chain(aliases.values().flat_map(|route| {
            let others = [&route.canary, &route.shadow];
            std::iter::once(&route.main).chain(others.into_iter().flatten().map(|(r, _)| r))
        }));
        let policies: BTreeSet<&PolicyId> = routed.map(|route| &route.policy_id).collect();
        for policy_id in policies {
            self.policies.get(policy_id).await?;
        }
        Ok(Deployed {
            revision: routes.revision,
            created_at: routes.created_at.clone(),
            latest,
            aliases,
            versions,
        })
    }

    fn route_of(
        &self,
        model: &str,
        versions: &BTreeMap<u32, PolicyId>,
        version: u32,
    ) -> Result<Route, ResolveError> {
        let policy_id = versions.get(&version).ok_or_else(|| {
            ResolveError::NotFound(format!("model {model} has no version {version}"))
        })?;
        Ok(self.route(model, version, policy_id))
    }

    /// Brings every table up to its model's revision in the store; drops deleted models.
    pub async fn refresh_all(&self) -> Result<(), ResolveError> {
        let revisions = self.store.model_revisions().await?;
        let stored: HashSet<&str> = revisions.iter().map(|(name, _)| name.as_str()).collect();
        self.tables
            .write()
            .expect("model tables lock")
            .retain(|name, _| stored.contains(name.as_str()));
        for (name, revision) in &revisions {
            let current = self.table(name).map(|t| t.revision);
            if current != Some(*revision) {
                if let Err(e) = self.refresh_model(name).await {
                    tracing::error!(model = %name, error = %e, "cannot load the model's new versions; the previous ones keep serving");
                }
            }
        }
        Ok(())
    }

    /// Follows the store's changes until shutdown: a poll every [`POLL`], and on PostgreSQL the
    /// notifications of [`MODELS_CHANNEL`].
    pub fn watch(self: Arc<Self>, shutdown: CancellationToken) {
        let poller = self.clone();
        let stop = shutdown.clone();
        tokio::spawn(async move {
            loop {
                if let Err(e) = poller.refresh_all().await {
                    tracing::warn!(error = %e, "cannot read the models' revisions");
                }
                tokio::select! {
                    () = stop.cancelled() => return,
                    () = tokio::time::sleep(POLL) => {}
                }
            }
        });
        if self.store.database_url().is_some() {
            tokio::spawn(listen(self, shutdown));
        }
    }

    /// Every model: whether it is ready here.
    pub async fn index(&self) -> Result<Vec<IndexEntry>, StoreError> {
        let revisions = self.store.model_revisions().await?;
        let mut entries = Vec::with_capacity(revisions.len());
        for (name, _) in revisions {
            let table = self.table(&name);
            let latest_version = table.as_ref().and_then(|t| t.versions.keys().last().copied());
            let (state, reason) = if self.is_unloaded(&name) {
                ("UNAVAILABLE", "unloaded".to_owned())
            } else {
                match &table {
                    Some(t) if t.latest.is_some() => ("READY", String::new()),
                    Some(_) => ("UNAVAILABLE", "no version registered".to_owned()),
                    None => ("UNAVAILABLE", "not loaded yet".to_owned()),
                }
            };
            entries.push(IndexEntry { name, state, reason, latest_version });
        }
        Ok(entries)
    }

    /// Loads a model on this process (again after an unload) and waits until it is ready.
    pub async fn load_model(&self, name: &ModelName) -> Result<(), ResolveError> {
        let name = name.as_str();
        self.unloaded.lock().expect("unloaded lock").remove(name);
        self.refresh_model(name).await?;
        if self.table(name).is_none() {
            return Err(ResolveError::NotFound(format!("model {name} does not exist")));
        }
        Ok(())
    }

    /// Stops serving a model on this process (its policies are released once the requests in
    /// flight finish). Other processes of a fleet keep serving it.
    pub async fn unload_model(&self, name: &ModelName) -> Result<(), ResolveError> {
        self.store.model(name).await?;
        self.unloaded.lock().expect("unloaded lock").insert(name.to_string());
        self.tables.write().expect("model tables lock").remove(name.as_str());
        Ok(())
    }

    /// Whether `name` is a stored model (not found otherwise), loaded here or not.
    pub async fn check_exists(&self, name: &ModelName) -> Result<(), ResolveError> {
        self.store.model(name).await?;
        Ok(())
    }

    /// The version numbers of a loaded model, in order.
    pub fn versions(&self, model: &str) -> Vec<u32> {
        self.table(model).map(|t| t.versions.keys().copied().collect()).unwrap_or_default()
    }

    /// The statistics of every version of `model` requested on this process, by version.
    pub fn model_stats(&self, model: &str) -> Vec<(u32, Arc<VersionStats>)> {
        let stats = self.stats.lock().expect("stats lock");
        let mut found: Vec<_> = stats
            .iter()
            .filter(|((name, _), _)| name == model)
            .map(|((_, version), s)| (*version, s.clone()))
            .collect();
        found.sort_by_key(|(version, _)| *version);
        found
    }

    /// The revision this process serves of `model` (None: not loaded).
    pub fn revision(&self, model: &str) -> Option<u64> {
        self.table(model).map(|t| t.revision)
    }
}

/// The alias's version, or its canary's for `basis_points` of every 10,000 request keys (or of
/// random draws when the client sends no key).
fn pick<'a>(route: &'a AliasRoute, key: Option<&str>) -> &'a Route {
    let Some((canary, basis_points)) = &route.canary else { return &route.main };
    let draw = match key {
        Some(key) => (fnv1a(key.as_bytes()) % u64::from(BASIS_POINTS)) as u32,
        None => rand::random_range(0..BASIS_POINTS),
    };
    if draw < *basis_points {
        canary
    } else {
        &route.main
    }
}

/// FNV-1a, 64 bits: a hash that is the same in every process and every build, so a request key
/// goes to the same version on every node of a fleet.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |hash, &b| {
        (hash ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Refreshes a model as soon as another process's change of it is notified, until shutdown (the
/// poll covers what a lost connection misses).
async fn listen(registry: Arc<ModelRegistry>, shutdown: CancellationToken) {
    let store = registry.store.clone();
    let refresh = |model: String| {
        let registry = registry.clone();
        async move {
            if let Err(e) = registry.refresh_model(&model).await {
                tracing::error!(%model, error = %e, "cannot load the model's new versions; the previous ones keep serving");
            }
        }
    };
    store.listen(MODELS_CHANNEL, &shutdown, POLL, refresh).await;
}

#[cfg(test)]
mod tests {
    use super::fnv1a;

    #[test]
    fn the_request_key_hash_is_fnv1a() {
        // FNV-1a's published test vectors: the split must not change between builds.
        assert_eq!(fnv1a(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a(b"foobar"), 0x8594_4171_f739_67e8);
    }
}
