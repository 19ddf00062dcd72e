//! `/v1/models`: named models and their numbered versions (each a policy, immutable). Their
//! aliases and history are [`super::model_aliases`]; serving by name is [`super::model_serving`].

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::model_aliases::{CanaryShare, ShadowShare};
use super::model_names::{check_text, invalid_name, model_name, note, refresh};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::domain::labels::{check_tag, TagSchema, MAX_TAGS};
use crate::domain::model::{
    self, AliasRecord, ModelRecord, ModelVersionRecord, MAX_DESCRIPTION_CHARS,
};
use crate::domain::{rfc3339, PolicyId};
use crate::store::models::{NewModel, NewVersion};
use crate::store::{Listing, StoreError};

/// `POST /v1/models` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateModel {
    /// 1-64 characters from ASCII letters, digits and `- _ .`, starting with a letter or a
    /// digit, and not of the form of a policy id (a UUID).
    #[schema(min_length = 1, max_length = 64, pattern = "^[A-Za-z0-9][A-Za-z0-9._-]*$")]
    pub name: String,
    /// Free text, at most 10,000 characters.
    #[serde(default)]
    #[schema(
        pattern = r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 10000
    )]
    pub description: String,
    /// Up to 32 tags of 1-64 characters from letters, digits and `- _ . : / =`.
    #[serde(default)]
    #[schema(value_type = Vec<TagSchema>)]
    pub tags: Vec<String>,
}

/// `PATCH /v1/models/{name}` body: the fields present replace the stored ones.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct UpdateModel {
    #[schema(
        pattern = r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 10000
    )]
    pub description: Option<String>,
    #[schema(value_type = Option<Vec<TagSchema>>)]
    pub tags: Option<Vec<String>>,
}

/// A named model.
#[derive(Debug, Serialize, ToSchema)]
pub struct Model {
    pub name: String,
    pub description: String,
    pub tags: Vec<String>,
    /// The highest version number (what `/v1/models/{name}/act` serves); absent: no version.
    pub latest_version: Option<u32>,
    pub version_count: u64,
    pub aliases: Vec<Alias>,
    pub created_at: String,
    pub updated_at: String,
}

/// An alias and where it points.
#[derive(Debug, Serialize, ToSchema)]
pub struct Alias {
    pub alias: String,
    pub version: u32,
    /// Another version answering a share of the alias's requests.
    pub canary: Option<CanaryShare>,
    /// Another version run beside the alias's answer on a share of its requests and compared
    /// with it, never returned (`GET /v1/models/{name}/shadow`).
    pub shadow: Option<ShadowShare>,
    pub updated_at: String,
}

impl From<AliasRecord> for Alias {
    fn from(a: AliasRecord) -> Self {
        Alias {
            alias: a.alias,
            version: a.target.version,
            canary: a.target.canary.map(Into::into),
            shadow: a.target.shadow.map(Into::into),
            updated_at: rfc3339(&a.updated_at),
        }
    }
}

impl From<ModelRecord> for Model {
    fn from(m: ModelRecord) -> Self {
        Model {
            name: m.name,
            description: m.description,
            tags: m.tags,
            latest_version: m.latest_version,
            version_count: m.version_count,
            aliases: m.aliases.into_iter().map(Into::into).collect(),
            created_at: rfc3339(&m.created_at),
            updated_at: rfc3339(&m.updated_at),
        }
    }
}

/// `POST /v1/models/{name}/versions` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateVersion {
    /// The trained policy this version serves.
    pub policy_id: String,
    #[serde(default)]
    #[schema(
        pattern = r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 10000
    )]
    pub description: String,
    /// An alias to move to the new version at once (e.g. `staging`).
    #[schema(
        pattern = r"^(?:[A-Za-z][A-Za-z0-9._-]*|[0-9]+[A-Za-z._-][A-Za-z0-9._-]*)$",
        max_length = 64
    )]
    pub alias: Option<String>,
    /// Who registers it, for the alias's history (default `api`).
    #[schema(
        pattern = r"^[^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*[^\s\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069][^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 200
    )]
    pub actor: Option<String>,
}

/// A version of a model.
#[derive(Debug, Serialize, ToSchema)]
pub struct ModelVersion {
    pub model: String,
    pub version: u32,
    pub policy_id: String,
    /// The job that trained the policy (its metrics, evaluations and configuration).
    pub job_id: String,
    /// That job's name (absent: none).
    pub job_name: Option<String>,
    /// The algorithm that trained the policy.
    pub algorithm: String,
    pub description: String,
    /// `api`, or `job <id>` for a job's `register`.
    pub source: String,
    pub created_at: String,
    /// Where the policy is: its resource, with the paper's metrics one link further.
    pub policy_url: String,
}

impl From<ModelVersionRecord> for ModelVersion {
    fn from(v: ModelVersionRecord) -> Self {
        ModelVersion {
            policy_url: format!("/v1/policies/{}", v.policy_id.as_str()),
            model: v.model,
            version: v.version,
            policy_id: v.policy_id.into_string(),
            job_id: v.job_id,
            job_name: v.job_name,
            algorithm: v.algorithm,
            description: v.description,
            source: v.source,
            created_at: rfc3339(&v.created_at),
        }
    }
}

/// `?limit=&offset=` of a model's versions.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct VersionParams {
    /// 1-500 (default 50).
    #[param(minimum = 1, maximum = 500)]
    pub limit: Option<u32>,
    #[param(minimum = 0, maximum = 9223372036854775807_i64)]
    pub offset: Option<u64>,
}

/// A model's versions, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct VersionList {
    pub items: Vec<ModelVersion>,
    pub total: u64,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_model, list_models))
        .routes(routes!(get_model, update_model, delete_model))
        .routes(routes!(create_version, list_versions))
        .routes(routes!(get_version, delete_version))
}

fn check_tags(tags: &[String]) -> Result<(), ApiError> {
    if tags.len() > MAX_TAGS {
        return Err(ApiError::unprocessable(
            "invalid_model",
            format!("tags: at most {MAX_TAGS} tags, got {}", tags.len()),
        ));
    }
    tags.iter()
        .try_for_each(|t| check_tag(t))
        .map_err(|e| ApiError::unprocessable("invalid_model", e))
}

/// Create a model: a name agents address and versions are registered under.
#[utoipa::path(post, path = "/v1/models", tag = "models", request_body = CreateModel,
    responses(
        (status = 201, body = Model, headers(("location" = String))),
        (status = 409, description = "The name is taken, or differs from a model's only by case \
            (`model_exists`)", body = ErrorBody),
        (status = 422, description = "A name that breaks the rule (`invalid_name`, the message \
            states it), bad tags or description (`invalid_model`)", body = ErrorBody),
    ))]
async fn create_model(
    State(state): State<AppState>,
    Json(request): Json<CreateModel>,
) -> Result<impl IntoResponse, ApiError> {
    model::ModelName::parse(&request.name).map_err(invalid_name)?;
    check_text("description", &request.description, MAX_DESCRIPTION_CHARS)?;
    check_tags(&request.tags)?;
    let new =
        NewModel { name: &request.name, description: &request.description, tags: &request.tags };
    let record = state.store.create_model(&new).await?;
    tracing::info!(model = %record.name, "model created");
    let location = format!("/v1/models/{}", record.name);
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(Model::from(record))))
}

/// List models, newest first.
#[utoipa::path(get, path = "/v1/models", tag = "models", params(PageParams),
    responses((status = 200, body = Page<Model>), (status = 400, body = ErrorBody),
        (status = 404, description = "A `page_token` that is not an item of this list \
            (`page_token_not_found`)", body = ErrorBody)))]
async fn list_models(
    State(state): State<AppState>,
    Query(page): Query<PageParams>,
) -> Result<Json<Page<Model>>, ApiError> {
    let page = page.resolve(&state.store, Listing::Models).await?;
    let (records, total) = state.store.list_models(&page).await?;
    let items = records.into_iter().map(Model::from).collect();
    Ok(Json(Page::new(items, total, page, |m: &Model| &m.name)))
}

/// A model with its aliases.
#[utoipa::path(get, path = "/v1/models/{name}", tag = "models", params(("name" = String, Path)),
    responses((status = 200, body = Model), (status = 404, body = ErrorBody)))]
async fn get_model(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<Model>, ApiError> {
    let name = model_name(&name)?;
    Ok(Json(state.store.model(&name).await?.into()))
}

/// Change a model's description or tags.
#[utoipa::path(patch, path = "/v1/models/{name}", tag = "models", params(("name" = String, Path)),
    request_body = UpdateModel,
    responses((status = 200, body = Model), (status = 404, body = ErrorBody),
        (status = 422, body = ErrorBody)))]
async fn update_model(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Json(request): Json<UpdateModel>,
) -> Result<Json<Model>, ApiError> {
    let name = model_name(&name)?;
    if let Some(description) = &request.description {
        check_text("description", description, MAX_DESCRIPTION_CHARS)?;
    }
    if let Some(tags) = &request.tags {
        check_tags(tags)?;
    }
    let record = state
        .store
        .update_model(&name, request.description.as_deref(), request.tags.as_deref())
        .await?;
    Ok(Json(record.into()))
}

/// Delete a model with its versions and history (the policies stay). Refused while an alias
/// points at one of its versions or a queued or running job will register into it.
#[utoipa::path(delete, path = "/v1/models/{name}", tag = "models", params(("name" = String, Path)),
    responses((status = 204, description = "Deleted"), (status = 404, body = ErrorBody),
        (status = 409, description = "An alias or a job uses it (`model_in_use`)",
         body = ErrorBody)))]
async fn delete_model(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<StatusCode, ApiError> {
    let model = model_name(&name)?;
    state.store.delete_model(&model).await?;
    refresh(&state, &model).await;
    tracing::info!(model = %name, "model deleted");
    Ok(StatusCode::NO_CONTENT)
}

/// Register a policy as the model's next version (numbered 1, 2, … in the order registrations
/// commit; a number is never reused), optionally moving an alias to it.
#[utoipa::path(post, path = "/v1/models/{name}/versions", tag = "models",
    params(("name" = String, Path)), request_body = CreateVersion,
    responses(
        (status = 201, body = ModelVersion, headers(("location" = String))),
        (status = 404, description = "No such model", body = ErrorBody),
        (status = 422, description = "A bad alias name (`invalid_name`) or text \
            (`invalid_model`), or a `policy_id` that names no policy (`unknown_policy`)",
            body = ErrorBody),
    ))]
async fn create_version(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Json(request): Json<CreateVersion>,
) -> Result<impl IntoResponse, ApiError> {
    let name = model_name(&name)?;
    check_text("description", &request.description, MAX_DESCRIPTION_CHARS)?;
    // The body names the policy: one that does not exist makes the body wrong (422); 404 is
    // for the model the path names.
    let unknown_policy = || {
        let message = format!("policy_id: no policy {:?}", request.policy_id);
        ApiError::unprocessable("unknown_policy", message)
    };
    match state.store.policy(&PolicyId::from(request.policy_id.clone())).await {
        Err(StoreError::NotFound { .. }) => return Err(unknown_policy()),
        found => drop(found?),
    }
    let alias = match &request.alias {
        Some(alias) => Some(model::AliasName::parse(alias).map_err(invalid_name)?),
        None => None,
    };
    if alias.is_some() {
        // The alias must not resolve to a policy that cannot load: load it first.
        state.serving.policies.get(&PolicyId::from(request.policy_id.clone())).await?;
    }
    let note = note(request.actor, Some("registered with the alias".into()), None)?;
    let version = NewVersion {
        model: &name,
        policy_id: &request.policy_id,
        description: &request.description,
        source: "api",
        alias: alias.as_ref().map(|alias| (alias, &note)),
    };
    let record = match state.store.register_version(&version).await {
        // Deleted since the check above.
        Err(StoreError::NotFound { kind: "policy", .. }) => return Err(unknown_policy()),
        registered => registered?,
    };
    refresh(&state, &name).await;
    tracing::info!(model = %name, version = record.version, policy_id = %record.policy_id.as_str(), "model version registered");
    let location = format!("/v1/models/{name}/versions/{}", record.version);
    Ok((StatusCode::CREATED, [(header::LOCATION, location)], Json(ModelVersion::from(record))))
}

/// A model's versions, newest first.
#[utoipa::path(get, path = "/v1/models/{name}/versions", tag = "models",
    params(("name" = String, Path), VersionParams),
    responses((status = 200, body = VersionList), (status = 400, body = ErrorBody),
        (status = 404, body = ErrorBody)))]
async fn list_versions(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(params): Query<VersionParams>,
) -> Result<Json<VersionList>, ApiError> {
    let name = model_name(&name)?;
    let limit = params.limit.unwrap_or(50);
    if !(1..=500).contains(&limit) {
        return Err(ApiError::bad_request(
            "invalid_pagination",
            format!("limit must be between 1 and 500, got {limit}"),
        ));
    }
    let offset = params.offset.unwrap_or(0);
    if offset > i64::MAX as u64 {
        return Err(ApiError::bad_request(
            "invalid_pagination",
            format!("offset must be between 0 and {}, got {offset}", i64::MAX),
        ));
    }
    let (records, total) = state.store.model_versions(&name, limit, offset).await?;
    Ok(Json(VersionList { items: records.into_iter().map(Into::into).collect(), total }))
}

/// `{name, version}` of a version's routes.
#[derive(Debug, Deserialize)]
struct VersionPath {
    name: String,
    version: u32,
}

/// One version of a model.
#[utoipa::path(get, path = "/v1/models/{name}/versions/{version}", tag = "models",
    params(("name" = String, Path), ("version" = u32, Path)),
    responses((status = 200, body = ModelVersion), (status = 404, body = ErrorBody)))]
async fn get_version(
    State(state): State<AppState>,
    Path(path): Path<VersionPath>,
) -> Result<Json<ModelVersion>, ApiError> {
    let name = model_name(&path.name)?;
    Ok(Json(state.store.model_version(&name, path.version).await?.into()))
}

/// Delete a version no alias points at (its number is not handed out again; the policy stays).
#[utoipa::path(delete, path = "/v1/models/{name}/versions/{version}", tag = "models",
    params(("name" = String, Path), ("version" = u32, Path)),
    responses((status = 204, description = "Deleted"), (status = 404, body = ErrorBody),
        (status = 409, description = "An alias points at it, or at it as its canary or \
            shadow (`version_in_use`)",
         body = ErrorBody)))]
async fn delete_version(
    State(state): State<AppState>,
    Path(path): Path<VersionPath>,
) -> Result<StatusCode, ApiError> {
    let model = model_name(&path.name)?;
    state.store.delete_model_version(&model, path.version).await?;
    refresh(&state, &model).await;
    Ok(StatusCode::NO_CONTENT)
}
