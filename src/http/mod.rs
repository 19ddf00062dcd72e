//! The HTTP API: one module per resource, each exposing a `router()` of its routes together
//! with their OpenAPI description; this module merges them and adds the middleware.
//!
//! Request path, outermost first: request id (`x-request-id`, generated when absent) → trace
//! span → CORS → panic catcher → body idle timeout → per-route metrics → bearer auth → timeout
//! (not on uploads and streams) → handler. Connection-level limits (count, header deadline)
//! are in [`connections`].

pub mod act;
pub mod algorithms;
pub mod auth;
pub mod client_slots;
pub mod connections;
pub mod datasets;
pub mod envs;
pub mod error;
pub mod evaluations;
pub mod experiments;
pub mod extract;
pub mod health;
pub mod inference;
pub mod job_attempts;
pub mod jobs;
mod log_follower;
pub mod model_aliases;
pub mod model_names;
pub mod model_serving;
pub mod model_shadows;
pub mod models;
pub mod openapi;
pub mod outage;
pub mod pagination;
pub mod policies;
pub mod prometheus;
pub mod results;
pub mod ui;
pub mod vocabulary;

use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use axum::http::{header, HeaderName, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::Router;
use tokio_util::sync::CancellationToken;
use tower::ServiceBuilder;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::classify::ServerErrorsFailureClass;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use utoipa_axum::router::OpenApiRouter;

use crate::config::ServeConfig;
use crate::jobs::JobRunner;
pub use crate::serving::Serving;
use crate::store::Store;
pub use error::ApiError;

/// Longest a bounded request may take before it is answered with 503 `timeout`. Uploads and
/// event streams are exempt.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

pub(crate) const REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// What every handler can reach. The services in it (store, job runner, policy cache) are built
/// and started by [`crate::server`]; this layer only uses them.
///
/// One `Arc` around them all: axum clones the state for every extractor and middleware of every
/// request, and cloning the fields one by one (the store's path, a cancellation token whose clone
/// takes a lock, a handful of `Arc`s) cost a `/act` request measurably (bench/act_latency.sh:
/// 30,900 → 33,800 requests/s; `AppState` clone and drop no longer appear in the profile).
#[derive(Clone)]
pub struct AppState(Arc<Services>);

impl std::ops::Deref for AppState {
    type Target = Services;

    fn deref(&self) -> &Services {
        &self.0
    }
}

/// The services behind [`AppState`].
pub struct Services {
    pub config: Arc<ServeConfig>,
    pub store: Store,
    pub metrics: Arc<prometheus::Metrics>,
    pub tokens: Arc<auth::Tokens>,
    /// Cancelled when the server begins a graceful shutdown (long-running work stops on it).
    pub shutdown: CancellationToken,
    /// The training worker pool.
    pub jobs: JobRunner,
    /// Trained policies loaded for inference (`serving.policies`) and the named models
    /// (`serving.models`: which policy answers `name`, `name@alias` or a version).
    pub serving: Serving,
    /// One slot per upload being received (`--max-concurrent-uploads`), half of them per client.
    pub uploads: Arc<client_slots::ClientSlots>,
    /// One permit per open event stream (`--max-streams`).
    pub streams: Arc<tokio::sync::Semaphore>,
    /// One slot per heavy read being built or sent (`--max-heavy-reads`), half of them per
    /// client.
    pub heavy_reads: Arc<client_slots::ClientSlots>,
    /// Whether the database is known to be down (requests then answer fast).
    pub outage: Arc<outage::OutageWatch>,
}

impl AppState {
    pub fn new(
        config: ServeConfig,
        store: Store,
        jobs: JobRunner,
        serving: Serving,
        shutdown: CancellationToken,
    ) -> Self {
        let tokens =
            auth::Tokens::new(config.api_token.as_deref(), config.inference_token.as_deref());
        let uploads = client_slots::ClientSlots::new(usize::from(config.max_concurrent_uploads));
        let streams = tokio::sync::Semaphore::new(config.max_streams as usize);
        let heavy_reads = client_slots::ClientSlots::new(usize::from(config.max_heavy_reads));
        AppState(Arc::new(Services {
            metrics: Arc::new(prometheus::Metrics::new()),
            tokens: Arc::new(tokens),
            jobs,
            serving,
            uploads: Arc::new(uploads),
            streams: Arc::new(streams),
            heavy_reads: Arc::new(heavy_reads),
            outage: Arc::default(),
            shutdown,
            config: Arc::new(config),
            store,
        }))
    }
}

/// A 5xx answer in the log: 503 is load shed on purpose (uploads slots taken, a busy or
/// unreachable database, a timeout) and says so at WARN; every other one is an ERROR.
fn log_failure(class: ServerErrorsFailureClass, latency: Duration, _span: &tracing::Span) {
    let latency_ms = latency.as_millis();
    match class {
        ServerErrorsFailureClass::StatusCode(StatusCode::SERVICE_UNAVAILABLE) => {
            tracing::warn!(latency_ms, "answered 503: the service shed this request")
        }
        other => tracing::error!(latency_ms, classification = %other, "response failed"),
    }
}

/// Every route with its OpenAPI description, before middleware.
fn routes() -> OpenApiRouter<AppState> {
    let bounded = OpenApiRouter::new()
        .merge(health::router())
        .merge(prometheus::router())
        .merge(openapi::router())
        .merge(ui::router())
        .merge(datasets::router())
        .merge(algorithms::router())
        .merge(envs::router())
        .merge(jobs::router())
        .merge(job_attempts::router())
        .merge(policies::router())
        .merge(evaluations::router())
        .merge(experiments::router())
        .merge(results::router())
        .merge(models::router())
        .merge(model_aliases::router())
        .merge(model_serving::router())
        .merge(model_shadows::router())
        .merge(inference::router())
        .merge(vocabulary::router())
        .layer(middleware::from_fn(timeout));
    // Routes that legitimately take long: uploads of up to --max-upload-bytes, event streams.
    let long_running = OpenApiRouter::new().merge(datasets::upload_router()).merge(jobs::streams());
    OpenApiRouter::with_openapi(openapi::base()).merge(bounded).merge(long_running)
}

/// The OpenAPI description of the whole API, generated from the handlers, for a server with
/// an API token (as committed in `api/openapi.yaml`).
pub fn openapi() -> utoipa::openapi::OpenApi {
    openapi_for(true)
}

/// The description for a server with (`secured`) or without an API token.
pub fn openapi_for(secured: bool) -> utoipa::openapi::OpenApi {
    let mut doc = routes().into_openapi();
    openapi::document_shared_errors(&mut doc);
    openapi::link_created_resources(&mut doc);
    openapi::describe_event_streams(&mut doc);
    if secured {
        openapi::secure_api_routes(&mut doc);
    } else {
        openapi::open_api_routes(&mut doc);
    }
    doc
}

/// The complete application: routes, fallbacks and middleware.
pub fn app(state: AppState) -> anyhow::Result<Router> {
    let cors = cors_layer(&state.config)?;
    let body_idle = BodyPace {
        idle: Duration::from_secs(state.config.body_idle_timeout_secs),
        min_rate: state.config.min_body_rate,
    };
    let (router, _) = routes().split_for_parts();
    let router = router
        .fallback(error::route_not_found)
        .method_not_allowed_fallback(error::method_not_allowed)
        .layer(middleware::from_fn_with_state(state.clone(), auth::require_token))
        .layer(middleware::from_fn_with_state(state.clone(), outage::name_database_outages))
        .layer(middleware::from_fn(inference::binary::v2_error_shape))
        .layer(middleware::from_fn_with_state(state.clone(), prometheus::track))
        .layer(middleware::from_fn_with_state(body_idle, body_idle_timeout))
        .with_state(state);
    let trace = TraceLayer::new_for_http()
        .make_span_with(|request: &Request| {
            let request_id =
                request.headers().get(&REQUEST_ID).and_then(|v| v.to_str().ok()).unwrap_or("-");
            tracing::info_span!(
                "request",
                method = %request.method(),
                path = %request.uri().path(),
                request_id,
            )
        })
        .on_response(DefaultOnResponse::new().level(tracing::Level::INFO))
        .on_failure(log_failure);
    Ok(router.layer(
        ServiceBuilder::new()
            .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
            .layer(trace)
            .layer(PropagateRequestIdLayer::new(REQUEST_ID))
            .option_layer(cors)
            .layer(CatchPanicLayer::custom(panic_response)),
    ))
}

/// CORS for a dashboard served from another origin; none when no origin is configured.
fn cors_layer(config: &ServeConfig) -> anyhow::Result<Option<CorsLayer>> {
    let origins = config.cors_origin_values()?;
    if origins.is_empty() {
        return Ok(None);
    }
    let allow_origin = if origins.iter().any(Option::is_none) {
        AllowOrigin::any()
    } else {
        AllowOrigin::list(origins.into_iter().flatten())
    };
    Ok(Some(
        CorsLayer::new()
            .allow_origin(allow_origin)
            .allow_methods([Method::GET, Method::POST, Method::DELETE])
            .allow_headers([header::AUTHORIZATION, header::CONTENT_TYPE])
            .expose_headers([REQUEST_ID, header::LOCATION])
            .max_age(Duration::from_secs(3600)),
    ))
}

/// Bounds the time to produce a response.
async fn timeout(request: Request, next: Next) -> Response {
    match tokio::time::timeout(REQUEST_TIMEOUT, next.run(request)).await {
        Ok(response) => response,
        Err(_) => ApiError::unavailable(
            "timeout",
            format!(
                "the request took longer than {} s and was abandoned",
                REQUEST_TIMEOUT.as_secs()
            ),
        )
        .into_response(),
    }
}

/// Fails a request body that pauses longer than `limit` between two pieces (a client trickling
/// an upload would otherwise hold its connection and temp file for as long as it likes).
async fn body_idle_timeout(
    axum::extract::State(pace): axum::extract::State<BodyPace>,
    request: Request,
    next: Next,
) -> Response {
    let (parts, body) = request.into_parts();
    let body = axum::body::Body::new(tower_http::timeout::TimeoutBody::new(pace.idle, body));
    let body = connections::at_least(body, pace.idle, pace.min_rate);
    next.run(Request::from_parts(parts, body)).await
}

/// How a request body must arrive: no pause longer than `idle`, and after the first `idle`,
/// `min_rate` bytes per second on average (a body trickled a byte at a time would otherwise
/// hold an upload slot for ever without ever pausing long).
#[derive(Clone, Copy)]
struct BodyPace {
    idle: Duration,
    min_rate: u64,
}

/// A panicking handler becomes a logged 500 with the usual error body.
fn panic_response(panic: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let detail = panic
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| panic.downcast_ref::<&str>().copied())
        .unwrap_or("non-string panic payload");
    ApiError::Internal(anyhow::anyhow!("handler panicked: {detail}")).into_response()
}

pub(crate) const OCTET_STREAM: &str = "application/octet-stream";

/// A slot for one more heavy read (a dataset preview or download, a policy file or export) by
/// `client`, or 503 with Retry-After: `too_many_heavy_reads_from_address` once the client holds
/// its share (half the slots), `too_many_heavy_reads` once all are taken. Hand the slot to
/// [`attachment_holding`] so it is held until the file has been sent.
pub(crate) fn heavy_read_permit(
    state: &AppState,
    client: Option<client_slots::Client>,
) -> Result<client_slots::Slot, ApiError> {
    state.heavy_reads.try_take(client).map_err(|refusal| match refusal {
        client_slots::Refusal::ClientShare { share } => ApiError::unavailable(
            "too_many_heavy_reads_from_address",
            format!(
                "this address is being sent {share} dataset or policy files already, its share \
                 of the {} the server builds or sends at once (--max-heavy-reads); retry once \
                 one has arrived",
                state.heavy_reads.total()
            ),
        ),
        client_slots::Refusal::AllTaken => ApiError::unavailable(
            "too_many_heavy_reads",
            format!(
                "{} dataset or policy files are being built or sent already (--max-heavy-reads); \
                 retry shortly",
                state.heavy_reads.total()
            ),
        ),
    })
}

/// Bytes of a streamed body written ahead of the client's reading.
const STREAMED_BODY_PIPE_BYTES: usize = 256 * 1024;

/// A body that `write` writes on a blocking thread as the client reads it
/// (through a pipe of [`STREAMED_BODY_PIPE_BYTES`]), so a large file is sent without a second
/// copy of it in memory. A client that goes away makes the next write fail, which ends the
/// thread; a write that fails on its own ends the body short of the Content-Length the caller
/// sets, so the client sees a broken download, never a short file that looks whole.
pub(crate) fn body_written_by(
    write: impl FnOnce(&mut dyn std::io::Write) -> Result<(), String> + Send + 'static,
) -> axum::body::Body {
    let (reader, writer) = tokio::io::duplex(STREAMED_BODY_PIPE_BYTES);
    let mut bridge = tokio_util::io::SyncIoBridge::new(writer);
    tokio::task::spawn_blocking(move || {
        let written =
            write(&mut bridge).and_then(|()| bridge.shutdown().map_err(|e| e.to_string()));
        if let Err(error) = written {
            tracing::warn!(%error, "a streamed download stopped before its end");
        }
    });
    axum::body::Body::from_stream(tokio_util::io::ReaderStream::new(reader))
}

/// [`attachment`] whose body holds `slot` until it has been sent (or the client went away):
/// a file is in memory, or on its way out of a temp file, until then.
pub(crate) fn attachment_holding(
    file_name: &str,
    content_type: &'static str,
    body: impl Into<axum::body::Body>,
    slot: client_slots::Slot,
) -> Result<axum::response::Response, ApiError> {
    use futures::StreamExt;
    let chunks = body.into().into_data_stream().map(move |chunk| {
        // The stream owns the slot: it is released when hyper drops the finished body.
        let _held = &slot;
        chunk
    });
    attachment(file_name, content_type, axum::body::Body::from_stream(chunks))
}

/// A file download: `bytes` of `content_type`, saved by browsers and `curl -OJ` as `file_name`.
pub(crate) fn attachment(
    file_name: &str,
    content_type: &'static str,
    bytes: impl Into<axum::body::Body>,
) -> Result<axum::response::Response, ApiError> {
    use axum::http::{header, HeaderValue};
    use axum::response::IntoResponse;
    let disposition = format!("attachment; filename=\"{file_name}\"");
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(content_type)),
            (
                header::CONTENT_DISPOSITION,
                HeaderValue::from_str(&disposition).map_err(anyhow::Error::from)?,
            ),
        ],
        bytes.into(),
    )
        .into_response())
}
