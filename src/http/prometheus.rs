//! `GET /metrics`: request counts and latency histograms by method, route template and status
//! (and for the gRPC service, by RPC and status code),
//! plus the training queue, the evaluations by status, and the fleet (workers, their heartbeats
//! and running jobs, leases expired and taken over), read from the database at scrape time: any
//! API node reports the whole fleet. OpenMetrics text (the Prometheus exposition format Prometheus scrapes natively).

use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::{ApiError, AppState};

const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    method: String,
    /// The route template (`/v1/datasets/{id}`), never the raw path, so ids do not explode the
    /// number of series; `unmatched` for requests no route matched.
    route: String,
    status: u16,
}

/// A gRPC call (or one message of a stream) of the Open Inference Protocol service.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct GrpcLabels {
    /// The RPC's name (`ModelInfer`, `ModelStreamInfer`...).
    method: &'static str,
    /// The gRPC status code's name (`OK`, `NOT_FOUND`...); for a stream message, the code its
    /// error would have had as a call.
    code: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StatusLabel {
    status: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WorkerLabel {
    worker: String,
}

type SecondsGauge = Gauge<f64, std::sync::atomic::AtomicU64>;

type HistogramFamily = Family<RequestLabels, Histogram, fn() -> Histogram>;

/// The service's metrics registry.
pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    latency: HistogramFamily,
    grpc_requests: Family<GrpcLabels, Counter>,
    grpc_latency: Family<GrpcLabels, Histogram, fn() -> Histogram>,
    queue_depth: Gauge,
    jobs: Family<StatusLabel, Gauge>,
    evaluations: Family<StatusLabel, Gauge>,
    fleet: FleetMetrics,
    policies_loaded: Gauge,
    policy_cache_bytes: Gauge,
    policy_bytes_outside_cache: Gauge,
    shadow_queue: Gauge,
    shadow_requests: Family<ShadowLabel, Counter>,
    slots_in_use: Family<SlotLabel, Gauge>,
    /// Two scrapes at once must not both add the same totals' growth to the counters.
    shadow_sync: std::sync::Mutex<()>,
}

/// Which limited slots: `heavy_read` (--max-heavy-reads), `upload` (--max-concurrent-uploads),
/// `stream` (--max-streams).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct SlotLabel {
    kind: &'static str,
}

/// What became of a request drawn for a shadow.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ShadowLabel {
    result: &'static str,
}

/// What /metrics says of the workers sharing the database.
#[derive(Default)]
struct FleetMetrics {
    workers: Gauge,
    heartbeat_age: Family<WorkerLabel, SecondsGauge>,
    running: Family<WorkerLabel, Gauge>,
    expired_leases: Gauge,
    takeovers: Gauge,
}

impl FleetMetrics {
    fn register(&self, registry: &mut Registry) {
        registry.register("workers", "Worker processes in the registry", self.workers.clone());
        registry.register(
            "worker_heartbeat_age_seconds",
            "Time since each registered worker's last heartbeat",
            self.heartbeat_age.clone(),
        );
        registry.register(
            "running_jobs",
            "Running jobs by the worker holding their lease",
            self.running.clone(),
        );
        registry.register(
            "expired_leases",
            "Running jobs whose worker's lease expired and that no worker has taken over yet",
            self.expired_leases.clone(),
        );
        registry.register(
            "lease_takeovers",
            "Claims, over all stored jobs, that took a job over after its worker's lease expired",
            self.takeovers.clone(),
        );
    }

    /// Reads the fleet's state; series of workers that are gone disappear.
    async fn refresh(&self, store: &crate::store::Store) -> Result<(), ApiError> {
        let workers = store.workers().await?;
        self.workers.set(workers.len() as i64);
        self.heartbeat_age.clear();
        for worker in &workers {
            let label = WorkerLabel { worker: worker.id.clone() };
            self.heartbeat_age.get_or_create(&label).set(worker.heartbeat_age.as_secs_f64());
        }
        let leases = store.lease_stats().await?;
        self.running.clear();
        for (worker, count) in leases.running_by_worker {
            self.running.get_or_create(&WorkerLabel { worker }).set(count);
        }
        self.expired_leases.set(leases.expired_jobs);
        self.takeovers.set(leases.takeovers);
        Ok(())
    }
}

fn latency_histogram() -> Histogram {
    // 1 ms to ~33 s in factors of two.
    Histogram::new(exponential_buckets(0.001, 2.0, 16))
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("safedice");
        let requests = Family::<RequestLabels, Counter>::default();
        let latency: HistogramFamily = Family::new_with_constructor(latency_histogram);
        let grpc_requests = Family::<GrpcLabels, Counter>::default();
        let grpc_latency: Family<GrpcLabels, Histogram, fn() -> Histogram> =
            Family::new_with_constructor(latency_histogram);
        registry.register(
            "grpc_requests",
            "gRPC calls answered, and messages of inference streams",
            grpc_requests.clone(),
        );
        registry.register(
            "grpc_request_duration_seconds",
            "Time from a gRPC call (or stream message) to its answer",
            grpc_latency.clone(),
        );
        let queue_depth = Gauge::default();
        let jobs = Family::<StatusLabel, Gauge>::default();
        registry.register("http_requests", "HTTP requests answered", requests.clone());
        registry.register(
            "http_request_duration_seconds",
            "Time from request to response headers",
            latency.clone(),
        );
        registry.register(
            "job_queue_depth",
            "Training jobs waiting for a worker",
            queue_depth.clone(),
        );
        registry.register("jobs", "Training jobs by status", jobs.clone());
        let evaluations = Family::<StatusLabel, Gauge>::default();
        registry.register("evaluations", "Policy evaluations by status", evaluations.clone());
        let fleet = FleetMetrics::default();
        fleet.register(&mut registry);
        let (policies_loaded, policy_cache_bytes) = (Gauge::default(), Gauge::default());
        registry.register(
            "policies_loaded",
            "Policies this process keeps loaded for /act and /v2",
            policies_loaded.clone(),
        );
        registry.register(
            "policy_cache_bytes",
            "Bytes of weights of the loaded policies (at most --policy-cache-bytes, or one policy)",
            policy_cache_bytes.clone(),
        );
        let policy_bytes_outside_cache = Gauge::default();
        registry.register(
            "policy_bytes_outside_cache",
            "Bytes of policies dropped from the cache that requests in flight still hold (shared, never a second copy)",
            policy_bytes_outside_cache.clone(),
        );
        let shadow_queue = Gauge::default();
        registry.register(
            "shadow_queue",
            "Shadow comparisons queued and not finished (docs/shadow.md)",
            shadow_queue.clone(),
        );
        let shadow_requests = Family::<ShadowLabel, Counter>::default();
        registry.register(
            "shadow_requests",
            "Requests drawn for an alias's shadow, by result: compared, skipped (queue full or \
             policy not loaded), error (the comparison gave nothing comparable)",
            shadow_requests.clone(),
        );
        let slots_in_use = Family::<SlotLabel, Gauge>::default();
        registry.register(
            "request_slots_in_use",
            "Slots held by requests in flight, by kind: heavy_read (files built or being sent, \
             --max-heavy-reads), upload (--max-concurrent-uploads), stream (event streams, \
             --max-streams)",
            slots_in_use.clone(),
        );
        Metrics {
            registry,
            slots_in_use,
            shadow_queue,
            shadow_requests,
            shadow_sync: std::sync::Mutex::new(()),
            requests,
            latency,
            grpc_requests,
            grpc_latency,
            queue_depth,
            jobs,
            evaluations,
            fleet,
            policies_loaded,
            policy_cache_bytes,
            policy_bytes_outside_cache,
        }
    }

    fn observe(&self, labels: RequestLabels, seconds: f64) {
        self.latency.get_or_create(&labels).observe(seconds);
        self.requests.get_or_create(&labels).inc();
    }

    /// Counts and times a gRPC call (or a message of a stream) by its method and status code.
    pub fn observe_grpc(&self, method: &'static str, code: &'static str, seconds: f64) {
        let labels = GrpcLabels { method, code };
        self.grpc_latency.get_or_create(&labels).observe(seconds);
        self.grpc_requests.get_or_create(&labels).inc();
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

/// Middleware: counts and times every request under its route template.
pub async fn track(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_owned(), |p| p.as_str().to_owned());
    let response = next.run(request).await;
    let labels = RequestLabels { method, route, status: response.status().as_u16() };
    state.metrics.observe(labels, started.elapsed().as_secs_f64());
    response
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(metrics))
}

/// Prometheus metrics.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "operations",
    responses(
        (status = 200, description = "OpenMetrics text", body = String,
         content_type = "application/openmetrics-text"),
        (status = 500, description = "The database could not be read", body = super::error::ErrorBody),
    )
)]
async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let counts = state.store.job_counts_by_status().await?;
    for (status, count) in counts {
        state.metrics.jobs.get_or_create(&StatusLabel { status }).set(count);
        if status == crate::domain::JobStatus::Queued.as_str() {
            state.metrics.queue_depth.set(count);
        }
    }
    for (status, count) in state.store.evaluation_counts_by_status().await? {
        state.metrics.evaluations.get_or_create(&StatusLabel { status }).set(count);
    }
    state.metrics.fleet.refresh(&state.store).await?;
    let usage = state.serving.policies.usage();
    let gauge = |bytes: u64| i64::try_from(bytes).unwrap_or(i64::MAX);
    state.metrics.policies_loaded.set(usage.loaded as i64);
    state.metrics.policy_cache_bytes.set(gauge(usage.bytes));
    state.metrics.policy_bytes_outside_cache.set(gauge(usage.held_outside));
    let streams_in_use = state.config.max_streams as usize - state.streams.available_permits();
    for (kind, in_use) in [
        ("heavy_read", state.heavy_reads.in_use()),
        ("upload", state.uploads.in_use()),
        ("stream", streams_in_use),
    ] {
        state.metrics.slots_in_use.get_or_create(&SlotLabel { kind }).set(in_use as i64);
    }
    let shadows = state.serving.models.shadows().usage();
    state.metrics.shadow_queue.set(gauge(shadows.queued));
    let _one_scrape = state.metrics.shadow_sync.lock().expect("shadow metrics lock");
    for (result, total) in
        [("compared", shadows.compared), ("skipped", shadows.skipped), ("error", shadows.failed)]
    {
        let counter = state.metrics.shadow_requests.get_or_create(&ShadowLabel { result });
        counter.inc_by(total.saturating_sub(counter.get()));
    }
    let mut body = String::new();
    prometheus_client::encoding::text::encode(&mut body, &state.metrics.registry)
        .map_err(|e| ApiError::Internal(e.into()))?;
    Ok(([(header::CONTENT_TYPE, CONTENT_TYPE)], body).into_response())
}
