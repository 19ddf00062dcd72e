//! The OpenAPI description: generated from the handlers' annotations, served at
//! `GET /v1/openapi.json` and committed as `api/openapi.yaml` (a test fails when that file is
//! stale; `UPDATE_OPENAPI=1 cargo test --test http openapi::` or `safedice openapi` regenerates
//! it).

use std::collections::BTreeMap;
use std::sync::OnceLock;

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use utoipa::openapi::content::ContentBuilder;
use utoipa::openapi::link::{Link, LinkBuilder};
use utoipa::openapi::path::{Operation, PathItem};
use utoipa::openapi::response::ResponseBuilder;
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};
use utoipa::openapi::{OpenApi as OpenApiDoc, Ref, RefOr, SecurityRequirement};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::jobs::streams::{DeletedJob, JOB_EVENTS, LOG_EVENTS};
use super::AppState;

const SECURITY_SCHEME: &str = "bearer";

#[derive(OpenApi)]
#[openapi(
    info(
        title = "SafeDICE service",
        description = "Offline safe imitation learning (SafeDICE, NeurIPS 2023) as a service: \
            upload unlabeled and non-preferred demonstrations, train policies, query actions.\n\n\
            Every `/v1` and `/v2` route needs `Authorization: Bearer <token>` when the server \
            runs with an API token (the document a server serves at `/v1/openapi.json` says \
            whether it does). Every 4xx/5xx body is \
            `{\"error\": {\"code\": \"snake_case_code\", \"message\": \"...\"}}`.",
        license(name = "MIT"),
    ),
    tags(
        (name = "algorithms", description = "The algorithms trained, with every preset's values"),
        (name = "datasets", description = "Demonstration datasets (JSONL, CSV, NPZ, HDF5 uploads)"),
        (name = "environments", description = "Built-in benchmark environments"),
        (name = "evaluations", description = "Policies evaluated on the built-in environments \
            with the paper's metrics"),
        (name = "experiments", description = "A grid of algorithms × seeds on one pair of \
            datasets, queued as jobs; the paper's metrics per algorithm as mean ± standard error"),
        (name = "models", description = "Named models for deployment: numbered versions (each \
            a policy), aliases such as `production` with the history of every move, canaries, \
            and actions by name (`name`, `name@alias`, a version)"),
        (name = "operations", description = "Health, readiness, metrics, API description"),
    ),
    components(schemas(ErrorBody, DeletedJob)),
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

/// The operations of a path item, whichever methods it has.
fn operations(item: &mut PathItem) -> impl Iterator<Item = &mut Operation> {
    [
        &mut item.get,
        &mut item.put,
        &mut item.post,
        &mut item.delete,
        &mut item.options,
        &mut item.head,
        &mut item.patch,
        &mut item.trace,
    ]
    .into_iter()
    .flatten()
}

fn is_api_path(path: &str) -> bool {
    path == "/v2" || ["/v1/", "/v2/"].iter().any(|prefix| path.starts_with(prefix))
}

/// The Open Inference Protocol's routes answer errors in its own shape (`V2Error`).
fn is_v2_path(path: &str) -> bool {
    path == "/v2" || path.starts_with("/v2/")
}

/// Marks every operation under `/v1` and `/v2` as needing the bearer token, mirroring
/// [`super::auth::requirement`], with the 401 and 403 answers the token check gives.
pub fn secure_api_routes(doc: &mut OpenApiDoc) {
    for (path, item) in doc.paths.paths.iter_mut() {
        if !is_api_path(path) {
            continue;
        }
        let v2 = is_v2_path(path);
        for operation in operations(item) {
            operation.security =
                Some(vec![SecurityRequirement::new(SECURITY_SCHEME, Vec::<String>::new())]);
            add_error(
                operation,
                v2,
                401,
                "No bearer token, or not one of this server's (`unauthorized`)",
            );
            add_error(
                operation,
                v2,
                403,
                "The inference token on a route other than the action endpoints (`forbidden`)",
            );
        }
    }
}

/// Without an API token nothing is enforced: the document then names no security scheme, so
/// that clients generated from it send no credentials and expect no 401/403.
pub fn open_api_routes(doc: &mut OpenApiDoc) {
    if let Some(components) = doc.components.as_mut() {
        components.security_schemes.remove(SECURITY_SCHEME);
    }
}

/// Documents the answers that the shared extractors and middleware give, wherever they can
/// happen: a JSON body that does not parse (400), has the wrong content type (415), is over
/// the body limit (413) or does not fit the schema (422); a path or query that does not parse
/// (400); a write refused because the disk is full (507); and the request deadline (503).
pub fn document_shared_errors(doc: &mut OpenApiDoc) {
    for (path, item) in doc.paths.paths.iter_mut() {
        let (api, v2) = (is_api_path(path), is_v2_path(path));
        for operation in operations(item) {
            let takes_json = operation.request_body.as_ref().is_some_and(|body| {
                body.content.keys().any(|content_type| content_type == "application/json")
            });
            if takes_json {
                add_error(operation, v2, 400, "The body is not valid JSON (`bad_request`)");
                add_error(operation, v2, 413, "The body exceeds 2 MiB (`payload_too_large`)");
                // The inference protocol reads its body whatever content type is declared.
                if !v2 {
                    add_error(
                        operation,
                        v2,
                        415,
                        "The body is not sent as `application/json` (`unsupported_media_type`)",
                    );
                }
                add_error(
                    operation,
                    v2,
                    422,
                    "The body does not fit the schema: a missing or unknown field, a value of \
                     the wrong type or out of range (`invalid_body`)",
                );
            }
            let has_params = operation.parameters.as_ref().is_some_and(|p| !p.is_empty());
            if has_params {
                add_error(
                    operation,
                    v2,
                    400,
                    "A path or query parameter does not parse or is out of range \
                     (`bad_request`, `invalid_pagination`, ...)",
                );
            }
            if api {
                add_error(
                    operation,
                    v2,
                    503,
                    "The service cannot answer now: the database stayed locked by other \
                     writes (`database_busy`; nothing was changed), cannot be reached \
                     (`database_unavailable`; nothing was changed), the request took longer \
                     than 30 s (`timeout`), the upload slots are taken (`too_many_uploads`) or the \
                     event-stream slots (`too_many_streams`); \
                     retry after `Retry-After` seconds",
                );
            }
        }
        if api {
            for write in [&mut item.post, &mut item.delete].into_iter().flatten() {
                add_error(
                    write,
                    v2,
                    507,
                    "The server's disk is full (`insufficient_storage`); nothing was stored",
                );
            }
        }
    }
}

/// Declares the events of each Server-Sent Events stream on its `text/event-stream` media type:
/// `itemSchema` (the field OpenAPI 3.2 gives a stream's items; a 3.1 reader skips it) describes
/// one event as its fields, `{event, data, id}`, each event name with the schema of its `data`
/// (a JSON text), which schemathesis checks every event it reads against. The media type has no `schema`: beside an
/// `itemSchema`, 3.2 reads it as the schema of the whole stream read as a list of events.
pub fn describe_event_streams(doc: &mut OpenApiDoc) {
    for item in doc.paths.paths.values_mut() {
        for operation in operations(item) {
            let events: &[(&str, &str)] = match operation.operation_id.as_deref() {
                Some("job_events") => &JOB_EVENTS,
                Some("job_log") => &LOG_EVENTS,
                _ => continue,
            };
            for response in operation.responses.responses.values_mut() {
                let RefOr::T(response) = response else { continue };
                if let Some(stream) = response.content.get_mut("text/event-stream") {
                    let extensions = stream.extensions.get_or_insert_with(Default::default);
                    extensions.insert("itemSchema".to_owned(), event_item_schema(events));
                    stream.schema = None;
                }
            }
        }
    }
}

/// One event of a stream whose events are `events` (name, schema of its JSON data), as its
/// fields; the `error` event (a data that could not be serialised) carries plain text.
fn event_item_schema(events: &[(&str, &str)]) -> serde_json::Value {
    let each = events.iter().map(|(event, schema)| {
        let reference = format!("#/components/schemas/{schema}");
        serde_json::json!({"properties": {
            "event": {"const": event},
            "data": {"contentMediaType": "application/json", "contentSchema": {"$ref": reference}},
        }})
    });
    let error = serde_json::json!({"properties": {"event": {"const": "error"}}});
    serde_json::json!({
        "type": "object",
        "required": ["event", "data"],
        "properties": {
            "event": {"type": "string"},
            "data": {"type": "string"},
            "id": {"type": "string"},
        },
        "oneOf": each.chain(std::iter::once(error)).collect::<Vec<_>>(),
    })
}

/// What a create answers with points at its resource's operations: OpenAPI links from each
/// `POST` that creates (a 201 or 202 answer) to the operations under the created resource's
/// path, the new path parameter taken from the answer's body (`id`, `name`, `version`) and the
/// others from the request's path. An evaluation, created under its policy, lives under
/// `/v1/evaluations/{id}`. Clients (and schemathesis's stateful phase) follow them.
pub fn link_created_resources(doc: &mut OpenApiDoc) {
    let ids: BTreeMap<(String, &'static str), String> = doc
        .paths
        .paths
        .iter()
        .flat_map(|(path, item)| {
            [
                ("get", &item.get),
                ("put", &item.put),
                ("post", &item.post),
                ("patch", &item.patch),
                ("delete", &item.delete),
            ]
            .into_iter()
            .filter_map(move |(method, op)| {
                Some(((path.clone(), method), op.as_ref()?.operation_id.clone()?))
            })
        })
        .collect();
    let created_under = |path: &str| -> Option<String> {
        match path {
            "/v1/policies/{id}/evaluate" | "/v1/policies/{id}/evaluations" => {
                Some("/v1/evaluations".to_owned())
            }
            _ if !path.ends_with('}') => Some(path.to_owned()),
            _ => None,
        }
    };
    for (path, item) in doc.paths.paths.iter_mut() {
        let (Some(post), Some(collection)) = (item.post.as_mut(), created_under(path)) else {
            continue;
        };
        let known: Vec<&str> = path_parameters(path).collect();
        let links: BTreeMap<String, RefOr<Link>> = ids
            .iter()
            .filter_map(|((target, _), operation_id)| {
                let rest = target.strip_prefix(&collection)?.strip_prefix("/{")?;
                let created = &rest[..rest.find('}')?];
                let mut link = LinkBuilder::new().operation_id(operation_id.clone());
                for name in path_parameters(target) {
                    let value = if name == created {
                        format!("$response.body#/{created}")
                    } else if known.contains(&name) && collection == *path {
                        format!("$request.path.{name}")
                    } else {
                        return None; // a parameter nothing here can fill (an alias name)
                    };
                    link = link.parameter(name, value);
                }
                let link = link.build();
                Some((operation_id.clone(), RefOr::T(link)))
            })
            .collect();
        for (status, response) in post.responses.responses.iter_mut() {
            if let (true, RefOr::T(response)) = (status == "201" || status == "202", response) {
                response.links.extend(links.clone());
            }
        }
    }
}

/// The `{parameters}` of a path template, in order.
fn path_parameters(path: &str) -> impl Iterator<Item = &str> {
    path.split('/').filter_map(|segment| segment.strip_prefix('{')?.strip_suffix('}'))
}

fn add_error(operation: &mut Operation, v2: bool, status: u16, description: &str) {
    let schema = if v2 { "V2Error" } else { "ErrorBody" };
    let responses = &mut operation.responses.responses;
    responses.entry(status.to_string()).or_insert_with(|| {
        ResponseBuilder::new()
            .description(description)
            .content(
                "application/json",
                ContentBuilder::new().schema(Some(Ref::from_schema_name(schema))).build(),
            )
            .build()
            .into()
    });
}

/// The description as YAML, as committed in `api/openapi.yaml`.
pub fn yaml() -> anyhow::Result<String> {
    Ok(spell_link_fields(super::openapi().to_yaml()?, " operation_id: ", " operationId: "))
}

/// The description as served at `/v1/openapi.json` (pretty JSON), for a server with
/// (`secured`) or without an API token.
pub fn json(secured: bool) -> String {
    let text = super::openapi_for(secured).to_pretty_json().expect("the document serializes");
    spell_link_fields(text, "\"operation_id\":", "\"operationId\":")
}

/// utoipa 5.5 writes a link's `operationId` as `operation_id` (its `Link` lacks the camelCase
/// renaming the rest of the document has). No other key of this document has that name (a
/// test checks), so the serialized text is corrected.
fn spell_link_fields(text: String, wrong: &str, right: &str) -> String {
    text.replace(wrong, right)
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(openapi_json))
}

/// This API's OpenAPI description, as this server enforces it: with an API token every
/// `/v1` and `/v2` operation carries the bearer requirement; without one, none does.
#[utoipa::path(get, path = "/v1/openapi.json", tag = "operations",
    responses((status = 200, description = "OpenAPI 3.1 document", content_type = "application/json")))]
async fn openapi_json(State(state): State<AppState>) -> Response {
    static SECURED: OnceLock<String> = OnceLock::new();
    static OPEN: OnceLock<String> = OnceLock::new();
    let secured = state.config.api_token.is_some();
    let cell = if secured { &SECURED } else { &OPEN };
    let body = cell.get_or_init(|| json(secured));
    ([(header::CONTENT_TYPE, "application/json")], body.as_str()).into_response()
}
