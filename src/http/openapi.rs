//! The OpenAPI description: generated from the handlers' annotations, served at
//! `GET /v1/openapi.json` and committed as `api/openapi.yaml` (a test fails when that file is
//! stale; `UPDATE_OPENAPI=1 cargo test --test http_openapi` or `safedice openapi` regenerates it).

use std::sync::OnceLock;

use axum::http::header;
use axum::response::{IntoResponse, Response};
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};
use utoipa::openapi::{OpenApi as OpenApiDoc, SecurityRequirement};
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
    for (path, item) in doc.paths.paths.iter_mut() {
        let is_api = ["/v1/", "/v2/"].iter().any(|prefix| path.starts_with(prefix));
        if !is_api {
            continue;
        }
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
        for operation in operations.into_iter().flatten() {
            operation.security =
                Some(vec![SecurityRequirement::new(SECURITY_SCHEME, Vec::<String>::new())]);
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
