//! `/v1/datasets`: multipart uploads streamed to disk, parsed once, stored in the canonical
//! form; listing, reading and deleting their descriptions.

use std::path::Path;

use axum::body::Body;
use axum::extract::multipart::{Field, Multipart, MultipartRejection};
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use chrono::{DateTime, Utc};
use serde::Serialize;
use sha2::{Digest, Sha256};
use tempfile::NamedTempFile;
use tokio::io::AsyncWriteExt;
use tokio_util::io::ReaderStream;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::client_slots::{Refusal, RequestClient};
use super::error::ErrorBody;
use super::extract::{Json, Path as UrlPath, Query};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::data::{self, ActionSpace, DatasetStats, Format};
use crate::domain::DatasetRecord;
use crate::domain::{DatasetId, DatasetRole};
use crate::store::{DeleteOutcome, Listing, NewDataset};

/// Room for the multipart framing and the `name`/`description` fields on top of the file.
const FORM_OVERHEAD_BYTES: u64 = 64 * 1024;
/// How much of an upload found oversized while streaming is still read (and discarded) before
/// answering 413, so that clients that send the whole body before reading the response see the
/// 413 rather than a reset connection. Beyond it the connection is dropped. (An upload whose
/// Content-Length already says it is too large is answered at once, reading nothing.)
const DRAIN_BYTES: u64 = 8 * 1024 * 1024;
const MAX_NAME_CHARS: usize = 200;
const MAX_DESCRIPTION_CHARS: usize = 4000;

/// A stored dataset.
#[derive(Debug, Serialize, ToSchema)]
pub struct DatasetResource {
    #[schema(example = "0b6f4e0c-3f7e-4a57-9a43-8b1f6a9e2c11")]
    pub id: String,
    #[schema(example = "walker-unlabeled")]
    pub name: String,
    pub description: Option<String>,
    /// What the uploader said the dataset is for (the `role` form field), if anything.
    pub role: Option<DatasetRole>,
    /// The format the file was uploaded in.
    pub format: Format,
    /// Number of transitions.
    pub transitions: u64,
    pub episodes: u64,
    pub obs_dim: u64,
    pub action_space: ActionSpace,
    /// Per-episode length, return and cost statistics (return/cost when the upload had them).
    pub stats: DatasetStats,
    /// SHA-256 of the uploaded file, hex (compare with `sha256sum`).
    pub sha256: String,
    /// Size of the uploaded file.
    pub bytes: u64,
    pub created_at: DateTime<Utc>,
}

impl From<DatasetRecord> for DatasetResource {
    fn from(r: DatasetRecord) -> Self {
        DatasetResource {
            id: r.id.into_string(),
            name: r.name,
            description: r.description,
            role: r.role,
            format: r.format,
            transitions: r.transitions,
            episodes: r.episodes,
            obs_dim: r.obs_dim,
            action_space: r.action_space,
            stats: r.stats,
            sha256: r.sha256,
            bytes: r.bytes,
            created_at: r.created_at,
        }
    }
}

/// The upload form (only describes `multipart/form-data` to OpenAPI; the handler streams it).
/// Other fields are refused (400 `unknown_field`).
#[derive(ToSchema)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct UploadForm {
    /// The dataset file: JSONL, CSV, NPZ (D4RL/DSRL flat layout) or HDF5; the format is
    /// detected from the file name and the content.
    #[schema(value_type = String, format = Binary)]
    file: Vec<u8>,
    /// Display name (1-200 characters, not all blank, no control characters; surrounding
    /// space is trimmed); defaults to the file name.
    #[schema(
        min_length = 1,
        max_length = 200,
        pattern = r"^[^\x00-\x1f\x7f-\x9f]*[^\s\x00-\x1f\x7f-\x9f][^\x00-\x1f\x7f-\x9f]*$"
    )]
    name: Option<String>,
    /// Free text, up to 4000 characters.
    #[schema(max_length = 4000)]
    description: Option<String>,
    /// What the dataset is for: `unlabeled` (D^U) or `non_preferred` (D^N). Jobs refuse a
    /// dataset in the other role's place.
    role: Option<DatasetRole>,
}

/// A dataset name: 1-200 characters, no control characters, surrounding space trimmed.
#[derive(Debug, Clone, PartialEq, Eq)]
struct DatasetName(String);

impl DatasetName {
    fn parse(raw: &str) -> Result<Self, ApiError> {
        let name = raw.trim();
        let chars = name.chars().count();
        if chars == 0 || chars > MAX_NAME_CHARS || name.chars().any(char::is_control) {
            return Err(ApiError::unprocessable(
                "invalid_name",
                format!(
                    "the dataset name must be 1 to {MAX_NAME_CHARS} characters without control \
                     characters, got {chars} characters"
                ),
            ));
        }
        Ok(DatasetName(name.to_owned()))
    }
}

/// Routes with ordinary request bodies (timeouts apply).
pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_datasets))
        .routes(routes!(get_dataset, delete_dataset))
        .routes(routes!(preview_dataset))
        .routes(routes!(download_dataset))
}

/// The upload route: no timeout and no default body limit (`--max-upload-bytes` applies).
pub fn upload_router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(upload_dataset)).layer(DefaultBodyLimit::disable())
}

/// Upload a dataset.
///
/// `curl -H "Authorization: Bearer $TOKEN" -F file=@demos.jsonl -F name=walker-unlabeled
/// http://127.0.0.1:8080/v1/datasets`. The file is streamed to disk, parsed and validated once,
/// and stored in a canonical binary form; a rejected upload leaves nothing behind.
#[utoipa::path(
    post,
    path = "/v1/datasets",
    tag = "datasets",
    request_body(content = inline(UploadForm), content_type = "multipart/form-data"),
    responses(
        (status = 201, description = "Stored; `Location` names the new resource", body = DatasetResource),
        (status = 400, description = "Not a multipart form, no `file` field, unknown or repeated field (`bad_request`, `missing_file`, `unknown_field`, `duplicate_field`)", body = ErrorBody),
        (status = 408, description = "The body paused longer than --body-idle-timeout-secs (`request_timeout`) or arrived slower than --min-body-rate on average (`request_too_slow`); nothing was stored", body = ErrorBody),
        (status = 413, description = "The file exceeds --max-upload-bytes (`payload_too_large`); a declared Content-Length over the limit is answered before the body is read", body = ErrorBody),
        (status = 422, description = "The file is not a valid dataset (`invalid_dataset`, `unknown_format`, `empty_dataset`, `unsupported_format`) or the name/description is invalid (`invalid_name`, `invalid_description`); the message names the line, row or key", body = ErrorBody),
        (status = 503, description = "--max-concurrent-uploads uploads are in flight (`too_many_uploads`), or half of them from this client (`too_many_uploads_from_address`); retry after `Retry-After` seconds", body = ErrorBody),
        (status = 507, description = "The server's disk is full (`insufficient_storage`); nothing was stored", body = ErrorBody),
    )
)]
async fn upload_dataset(
    State(state): State<AppState>,
    RequestClient(client): RequestClient,
    headers: HeaderMap,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<Response, ApiError> {
    let limit = state.config.max_upload_bytes;
    if content_length(&headers).is_some_and(|len| len > limit.saturating_add(FORM_OVERHEAD_BYTES)) {
        // Declared too large: answer before reading a byte, and close the connection rather
        // than read (or make the client send) a body that will be thrown away.
        let mut response = ApiError::PayloadTooLarge { limit }.into_response();
        response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
        return Ok(response);
    }
    let mut multipart = multipart?;
    // Each upload in flight holds a connection, a temp file and a parser thread at the end.
    let _receiving = state.uploads.try_take(client).map_err(|refusal| match refusal {
        Refusal::ClientShare { share } => ApiError::unavailable(
            "too_many_uploads_from_address",
            format!(
                "this address is sending {share} uploads already, its share of the {} the server \
                 receives at once (--max-concurrent-uploads); retry once one has finished",
                state.uploads.total()
            ),
        ),
        Refusal::AllTaken => ApiError::unavailable(
            "too_many_uploads",
            format!(
                "{} uploads are being received already (--max-concurrent-uploads); retry shortly",
                state.uploads.total()
            ),
        ),
    })?;
    let upload = match receive_form(&mut multipart, &state.store.tmp_dir(), limit).await {
        Err(too_large @ ApiError::PayloadTooLarge { .. }) => {
            drain(&mut multipart).await;
            return Err(too_large);
        }
        received => received?,
    };
    let record = store_upload(&state, upload).await?;
    let location = format!("/v1/datasets/{}", record.id);
    let body = Json(DatasetResource::from(record));
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], body).into_response())
}

/// The received form: the file in a temp file (deleted when this is dropped) and its fields.
struct Upload {
    file: NamedTempFile,
    file_name: String,
    sha256: String,
    bytes: u64,
    name: Option<DatasetName>,
    description: Option<String>,
    role: Option<DatasetRole>,
}

fn content_length(headers: &HeaderMap) -> Option<u64> {
    headers.get(header::CONTENT_LENGTH)?.to_str().ok()?.parse().ok()
}

/// Reads and discards up to [`DRAIN_BYTES`] of what is left of the request.
async fn drain(multipart: &mut Multipart) {
    let mut drained = 0u64;
    while let Ok(Some(mut field)) = multipart.next_field().await {
        while let Ok(Some(chunk)) = field.chunk().await {
            drained += chunk.len() as u64;
            if drained > DRAIN_BYTES {
                return;
            }
        }
    }
}

async fn receive_form(
    multipart: &mut Multipart,
    tmp_dir: &Path,
    limit: u64,
) -> Result<Upload, ApiError> {
    let mut file = None;
    let mut name = None;
    let mut description = None;
    let mut role = None;
    while let Some(field) = multipart.next_field().await? {
        let field_name = field.name().unwrap_or_default().to_owned();
        let repeated = match field_name.as_str() {
            "file" => file.replace(receive_file(field, tmp_dir, limit).await?).is_some(),
            "name" => {
                let text = read_text(field, "name", MAX_NAME_CHARS).await?;
                name.replace(DatasetName::parse(&text)?).is_some()
            }
            "description" => {
                let text = read_text(field, "description", MAX_DESCRIPTION_CHARS).await?;
                description.replace(text).is_some()
            }
            "role" => {
                let text = read_text(field, "role", 32).await?;
                let parsed = DatasetRole::parse(text.trim()).ok_or_else(|| {
                    ApiError::unprocessable(
                        "invalid_role",
                        format!("role must be `unlabeled` or `non_preferred`, got {text:?}"),
                    )
                })?;
                role.replace(parsed).is_some()
            }
            other => {
                return Err(ApiError::bad_request(
                    "unknown_field",
                    format!(
                        "unexpected form field `{other}`; the form takes `file`, and optionally \
                         `name`, `description` and `role`"
                    ),
                ))
            }
        };
        if repeated {
            return Err(ApiError::bad_request(
                "duplicate_field",
                format!("the form has more than one `{field_name}` field; send it once"),
            ));
        }
    }
    let (file, file_name, sha256, bytes) = file.ok_or_else(|| {
        ApiError::bad_request(
            "missing_file",
            "the form has no `file` field: send the dataset as e.g. `-F file=@demos.jsonl`",
        )
    })?;
    Ok(Upload { file, file_name, sha256, bytes, name, description, role })
}

/// Streams the `file` field to a temp file in `tmp_dir`, hashing it on the way; over `limit`
/// bytes the temp file is dropped (deleted) and the answer is 413.
async fn receive_file(
    mut field: Field<'_>,
    tmp_dir: &Path,
    limit: u64,
) -> Result<(NamedTempFile, String, String, u64), ApiError> {
    let file_name = field.file_name().unwrap_or_default().to_owned();
    let temp = tempfile::Builder::new().prefix("upload-").tempfile_in(tmp_dir)?;
    let mut out = tokio::fs::File::from_std(temp.as_file().try_clone()?);
    let mut hasher = Sha256::new();
    let mut bytes = 0u64;
    while let Some(chunk) = field.chunk().await? {
        bytes += chunk.len() as u64;
        if bytes > limit {
            return Err(ApiError::PayloadTooLarge { limit });
        }
        hasher.update(&chunk);
        out.write_all(&chunk).await?;
    }
    out.flush().await?;
    Ok((temp, file_name, hex::encode(hasher.finalize()), bytes))
}

/// Reads a short text field, refusing more than `max_chars` characters.
async fn read_text(
    mut field: Field<'_>,
    field_name: &'static str,
    max_chars: usize,
) -> Result<String, ApiError> {
    let too_long = || {
        ApiError::unprocessable(
            if field_name == "name" { "invalid_name" } else { "invalid_description" },
            format!("`{field_name}` is longer than {max_chars} characters"),
        )
    };
    let mut raw = Vec::new();
    while let Some(chunk) = field.chunk().await? {
        raw.extend_from_slice(&chunk);
        // A character is at most 4 bytes in UTF-8.
        if raw.len() > max_chars * 4 {
            return Err(too_long());
        }
    }
    let text = String::from_utf8(raw).map_err(|_| {
        ApiError::unprocessable("invalid_request", format!("`{field_name}` is not valid UTF-8"))
    })?;
    if text.chars().count() > max_chars {
        return Err(too_long());
    }
    Ok(text)
}

/// Parses, validates and stores an upload; its temp file is deleted however this ends.
async fn store_upload(state: &AppState, upload: Upload) -> Result<DatasetRecord, ApiError> {
    let Upload { file, file_name, sha256, bytes, name, description, role } = upload;
    let name = match name {
        Some(name) => name,
        None => default_name(&file_name),
    };
    let parsed = tokio::task::spawn_blocking(move || {
        let (format, dataset) = data::parse_file(file.path(), &file_name)?;
        drop(file);
        let new = NewDataset {
            role,
            ..NewDataset::describe(&dataset, format, name.0, description, sha256, bytes)
        };
        Ok::<_, ApiError>((new, data::encode_canonical(&dataset)))
    })
    .await??;
    let (new, canonical) = parsed;
    Ok(state.store.create_dataset(new, canonical).await?)
}

/// The file name, or "dataset" when the upload had none, as a valid name.
fn default_name(file_name: &str) -> DatasetName {
    let truncated: String =
        file_name.chars().filter(|c| !c.is_control()).take(MAX_NAME_CHARS).collect();
    DatasetName::parse(&truncated).unwrap_or_else(|_| DatasetName("dataset".to_owned()))
}

/// List datasets, newest first.
#[utoipa::path(
    get,
    path = "/v1/datasets",
    tag = "datasets",
    params(PageParams),
    responses(
        (status = 200, description = "One page of datasets, newest first", body = Page<DatasetResource>),
        (status = 400, description = "Bad `limit`/`offset` (`invalid_pagination`, `bad_request`)", body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody),
    )
)]
async fn list_datasets(
    State(state): State<AppState>,
    Query(params): Query<PageParams>,
) -> Result<Json<Page<DatasetResource>>, ApiError> {
    let page = params.resolve(&state.store, Listing::Datasets).await?;
    let (records, total) = state.store.datasets(&page).await?;
    let items = records.into_iter().map(DatasetResource::from).collect();
    Ok(Json(Page::new(items, total, page, |d: &DatasetResource| &d.id)))
}

/// One dataset.
#[utoipa::path(
    get,
    path = "/v1/datasets/{id}",
    tag = "datasets",
    params(("id" = String, Path, description = "Dataset id")),
    responses(
        (status = 200, description = "The dataset", body = DatasetResource),
        (status = 404, description = "No such dataset (`not_found`)", body = ErrorBody),
    )
)]
async fn get_dataset(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<DatasetId>,
) -> Result<Json<DatasetResource>, ApiError> {
    let record =
        state.store.dataset(&id).await?.ok_or_else(|| ApiError::not_found("dataset", &id))?;
    Ok(Json(record.into()))
}

/// `?rows=&episodes=`
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PreviewParams {
    /// Transitions shown from the start, 0 to 100 (default 10).
    #[param(minimum = 0, maximum = 100, default = 10)]
    pub rows: Option<usize>,
    /// Episodes summarised from the start, 0 to 1000 (default 20).
    #[param(minimum = 0, maximum = 1000, default = 20)]
    pub episodes: Option<usize>,
}

/// The first transitions of a dataset and a summary (length, return, cost, ending) of its first
/// episodes, as stored.
#[utoipa::path(get, path = "/v1/datasets/{id}/preview", tag = "datasets",
    params(("id" = String, Path, description = "Dataset id"), PreviewParams),
    responses(
        (status = 200, body = data::DatasetPreview),
        (status = 400, description = "`rows` or `episodes` out of range (`invalid_preview`)",
            body = ErrorBody),
        (status = 404, description = "No such dataset (`not_found`)", body = ErrorBody),
        (status = 503, description = "--max-heavy-reads dataset or policy files are being \
            built or sent (`too_many_heavy_reads`), or half of them to this client \
            (`too_many_heavy_reads_from_address`); retry after `Retry-After` seconds", body = ErrorBody),
    ))]
async fn preview_dataset(
    State(state): State<AppState>,
    RequestClient(client): RequestClient,
    UrlPath(id): UrlPath<DatasetId>,
    Query(params): Query<PreviewParams>,
) -> Result<Json<data::DatasetPreview>, ApiError> {
    let (rows, episodes) = (params.rows.unwrap_or(10), params.episodes.unwrap_or(20));
    if rows > 100 || episodes > 1000 {
        return Err(ApiError::bad_request(
            "invalid_preview",
            format!("rows must be 0 to 100 and episodes 0 to 1000, got {rows} and {episodes}"),
        ));
    }
    // Reads 13 bytes a transition of the episodes it summarises, up to the whole dataset's.
    let _permit = super::heavy_read_permit(&state, client)?;
    Ok(Json(state.store.preview_dataset(&id, rows, episodes).await?))
}

/// The dataset as stored, as an NPZ file in the D4RL/DSRL flat layout (what
/// `numpy.load` reads, and what uploads again to the same dataset).
#[utoipa::path(get, path = "/v1/datasets/{id}/download", tag = "datasets",
    params(("id" = String, Path, description = "Dataset id")),
    responses(
        (status = 200, description = "NPZ file", content_type = "application/octet-stream",
            body = Vec<u8>),
        (status = 404, description = "No such dataset (`not_found`)", body = ErrorBody),
        (status = 503, description = "--max-heavy-reads dataset or policy files are being \
            built or sent (`too_many_heavy_reads`), or half of them to this client \
            (`too_many_heavy_reads_from_address`); retry after `Retry-After` seconds", body = ErrorBody),
    ))]
async fn download_dataset(
    State(state): State<AppState>,
    RequestClient(client): RequestClient,
    UrlPath(id): UrlPath<DatasetId>,
) -> Result<Response, ApiError> {
    let permit = super::heavy_read_permit(&state, client)?;
    let dataset = state.store.load_dataset(&id).await?;
    let tmp_dir = state.store.tmp_dir();
    // Written to a temp file and sent from it: the decoded dataset is dropped before the first
    // byte goes out, and the file is never read into memory whole.
    let (file, bytes) = tokio::task::spawn_blocking(move || {
        let file = tempfile::Builder::new().suffix(".npz").tempfile_in(&tmp_dir)?;
        data::write_npz(&dataset, file.path())?;
        // A second handle reads it after the name is gone (the temp file is unlinked when
        // `file` drops here), so nothing is left behind whatever happens to the response.
        let handle = file.reopen()?;
        let bytes = handle.metadata()?.len();
        Ok::<_, std::io::Error>((handle, bytes))
    })
    .await?
    .map_err(|e| ApiError::Internal(anyhow::anyhow!("writing the NPZ file: {e}")))?;
    let body = Body::from_stream(ReaderStream::new(tokio::fs::File::from_std(file)));
    let name = format!("dataset-{id}.npz");
    let mut response = super::attachment_holding(&name, super::OCTET_STREAM, body, permit)?;
    response.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(bytes));
    Ok(response)
}

/// Delete a dataset and its stored data.
#[utoipa::path(
    delete,
    path = "/v1/datasets/{id}",
    tag = "datasets",
    params(("id" = String, Path, description = "Dataset id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, description = "No such dataset (`not_found`)", body = ErrorBody),
        (status = 409, description = "A queued or running job uses it (`dataset_in_use`)", body = ErrorBody),
    )
)]
async fn delete_dataset(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<DatasetId>,
) -> Result<StatusCode, ApiError> {
    match state.store.delete_dataset(&id).await? {
        DeleteOutcome::Deleted => Ok(StatusCode::NO_CONTENT),
        DeleteOutcome::NotFound => Err(ApiError::not_found("dataset", &id)),
        DeleteOutcome::InUse(jobs) | DeleteOutcome::Registered(jobs) => Err(ApiError::conflict(
            "dataset_in_use",
            format!(
                "dataset {id} is used by queued or running job(s) {}; cancel them or wait for \
                 them to finish, then delete it",
                jobs.join(", ")
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_trimmed_and_bounded() {
        assert_eq!(DatasetName::parse("  walker ").unwrap(), DatasetName("walker".into()));
        assert!(DatasetName::parse("   ").is_err());
        assert!(DatasetName::parse("a\nb").is_err());
        assert!(DatasetName::parse(&"x".repeat(MAX_NAME_CHARS + 1)).is_err());
        assert_eq!(default_name(""), DatasetName("dataset".into()));
        assert_eq!(default_name("demos.jsonl"), DatasetName("demos.jsonl".into()));
    }
}
