//! The OpenAPI description: generated from the handlers' annotations, served at
//! `GET /v1/openapi.json` and committed as `api/openapi.yaml` (a test fails when that file is
//! stale; `UPDATE_OPENAPI=1 cargo test --test http_openapi` or `safedice openapi` regenerates it).

use std::sync::OnceLock;

use axum::http::header;
use axum::response::{IntoResponse, Response};
use utoipa::openapi::header::HeaderBuilder;
use utoipa::openapi::path::Operation;
use utoipa::openapi::schema::{ObjectBuilder, Type};
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};
use utoipa::openapi::{
    Content, OpenApi as OpenApiDoc, Ref, RefOr, ResponseBuilder, SecurityRequirement,
};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::AppState;

const SECURITY_SCHEME: &str = "bearer";

#[derive(OpenApi)]
#[openapi(
    info(
        title = "SafeDICE service",
        description = "Offline safe imitation learning (SafeDICE, NeurIPS 2023) as a service: \
            upload unlabeled and non-preferred demonstrations, train policies, query actions.\n\n\
            Every `/v1` and `/v2` route needs `Authorization: Bearer <token>` when the server \
            runs with an API token. Every 4xx/5xx body is \
            `{\"error\": {\"code\": \"snake_case_code\", \"message\": \"...\"}}`.",
        license(name = "MIT"),
    ),
    tags(
        (name = "datasets", description = "Demonstration datasets (JSONL, CSV, NPZ, HDF5 uploads)"),
        (name = "environments", description = "Built-in benchmark environments"),
        (name = "evaluations", description = "Policies evaluated on the built-in environments \
            with the paper's metrics"),
        (name = "operations", description = "Health, readiness, metrics, API description"),
    ),
    components(schemas(ErrorBody)),
)]
struct ApiDoc;

/// The document the routes' descriptions are merged into.
pub fn base() -> OpenApiDoc {
    let mut doc = ApiDoc::openapi();
    doc.info.version = env!("CARGO_PKG_VERSION").to_owned();
    let components = doc.components.get_or_insert_with(Default::default);
    components.add_security_scheme(
        SECURITY_SCHEME,
        SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)),
    );
    doc
}

/// Marks every operation under `/v1` and `/v2` as needing the bearer token, mirroring
/// [`super::auth::requirement`].
pub fn secure_api_routes(doc: &mut OpenApiDoc) {
    for (_, operation) in api_operations(doc) {
        operation.security =
            Some(vec![SecurityRequirement::new(SECURITY_SCHEME, Vec::<String>::new())]);
    }
}

/// Every operation of `operations` under `/v1` and `/v2`, mutably.
fn api_operations(doc: &mut OpenApiDoc) -> impl Iterator<Item = (&str, &mut Operation)> {
    doc.paths.paths.iter_mut().flat_map(|(path, item)| {
        let is_api = ["/v1/", "/v2/"].iter().any(|prefix| path.starts_with(prefix));
        let operations = [
            &mut item.get,
            &mut item.put,
            &mut item.post,
            &mut item.delete,
            &mut item.options,
            &mut item.head,
            &mut item.patch,
            &mut item.trace,
        ];
        operations.into_iter().flatten().filter(move |_| is_api).map(move |op| (path.as_str(), op))
    })
}

/// Documents the 503 every API operation can answer: any of them may meet a database that
/// stays locked by other writers past the busy timeout (`database_busy`, with `Retry-After`),
/// and the bounded ones time out after 30 s (`timeout`). Operations that describe their own
/// 503 keep it.
pub fn document_unavailable(doc: &mut OpenApiDoc) {
    let retry_after = HeaderBuilder::new()
        .schema(ObjectBuilder::new().schema_type(Type::Integer).minimum(Some(0)))
        .description(Some("Seconds to wait before retrying (with `database_busy`)"))
        .build();
    let response = ResponseBuilder::new()
        .description(
            "The service cannot answer now: the database stayed locked by other writes \
             (`database_busy`; nothing was changed, retry after `Retry-After` seconds), or the \
             request took longer than 30 s (`timeout`)",
        )
        .header("Retry-After", retry_after)
        .content("application/json", Content::new(Some(Ref::from_schema_name("ErrorBody"))))
        .build();
    for (_, operation) in api_operations(doc) {
        operation
            .responses
            .responses
            .entry("503".to_owned())
            .or_insert_with(|| RefOr::T(response.clone()));
    }
}

/// The operations that write to the data directory (the others only read it).
const WRITING_OPERATIONS: [&str; 5] =
    ["upload_dataset", "delete_dataset", "create_job", "cancel_job", "evaluate_policy"];

/// Documents the 507 every API operation that stores something can answer when the disk is full
/// (`storage_full`; nothing was stored). Operations that describe their own 507 keep it.
pub fn document_storage_full(doc: &mut OpenApiDoc) {
    let response = ResponseBuilder::new()
        .description(
            "The server's disk is full (`storage_full`); nothing was stored. Retry once space is \
             freed: `GET /readyz` answers 200 again then",
        )
        .content("application/json", Content::new(Some(Ref::from_schema_name("ErrorBody"))))
        .build();
    for (_, operation) in api_operations(doc) {
        if operation.operation_id.as_deref().is_some_and(|id| WRITING_OPERATIONS.contains(&id)) {
            operation
                .responses
                .responses
                .entry("507".to_owned())
                .or_insert_with(|| RefOr::T(response.clone()));
        }
    }
}

/// The description as YAML, as committed in `api/openapi.yaml`.
pub fn yaml() -> anyhow::Result<String> {
    Ok(super::openapi().to_yaml()?)
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(openapi_json))
}

/// This API's OpenAPI description.
#[utoipa::path(get, path = "/v1/openapi.json", tag = "operations",
    responses((status = 200, description = "OpenAPI 3.1 document", content_type = "application/json")))]
async fn openapi_json() -> Response {
    static DOCUMENT: OnceLock<String> = OnceLock::new();
    let body = DOCUMENT.get_or_init(|| {
        super::openapi().to_pretty_json().expect("the OpenAPI document serializes")
    });
    ([(header::CONTENT_TYPE, "application/json")], body.as_str()).into_response()
}
