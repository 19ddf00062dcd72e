//! `/v1/models`: named models, their numbered versions (each a policy, immutable) and their
//! aliases with the history of every move. Serving by name is [`super::model_serving`].

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::pagination::{Page, PageParams};
use super::{ApiError, AppState};
use crate::domain::labels::{check_tag, TagSchema, MAX_TAGS};
use crate::domain::model::{
    self, AliasMove, AliasRecord, AliasTarget, Canary, ModelRecord, ModelVersionRecord, MoveNote,
    Shadow, BASIS_POINTS, MAX_ACTOR_CHARS, MAX_DESCRIPTION_CHARS,
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

/// A shadow: `version` acts on `sample` of the alias's requests off the response path, and its
/// actions are compared with the ones returned.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ShadowShare {
    pub version: u32,
    /// The share of requests shadowed, 0.0001-1 (kept in steps of 0.0001).
    #[schema(minimum = 0.0001, maximum = 1.0)]
    pub sample: f64,
}

impl From<Shadow> for ShadowShare {
    fn from(s: Shadow) -> Self {
        ShadowShare {
            version: s.version,
            sample: f64::from(s.basis_points) / f64::from(BASIS_POINTS),
        }
    }
}

/// A canary: `version` answers `weight` of the requests (the same requests every time when
/// clients send an `x-safedice-request-key`).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CanaryShare {
    pub version: u32,
    /// The share of requests, 0.0001-0.9999 (kept in steps of 0.0001).
    #[schema(minimum = 0.0001, maximum = 0.9999)]
    pub weight: f64,
}

impl From<Canary> for CanaryShare {
    fn from(c: Canary) -> Self {
        CanaryShare {
            version: c.version,
            weight: f64::from(c.basis_points) / f64::from(BASIS_POINTS),
        }
    }
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

/// `PUT /v1/models/{name}/aliases/{alias}` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SetAlias {
    /// The version the alias answers from.
    pub version: u32,
    /// Another version answering a share of the requests (absent, or the alias's own version:
    /// none).
    pub canary: Option<CanaryShare>,
    /// Another version to run beside the alias's answer on a share of its requests and compare
    /// with it (absent, or the alias's own version: none). It must take the same observations
    /// and give the same kind of action (422 `invalid_shadow` otherwise). A move without it
    /// ends the shadow.
    pub shadow: Option<ShadowShare>,
    /// Who moves it, for the history (default `api`), at most 200 characters.
    #[schema(
        pattern = r"^[^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*[^\s\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069][^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 200
    )]
    pub actor: Option<String>,
    /// Why, for the history.
    #[schema(
        pattern = r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 200
    )]
    pub reason: Option<String>,
    /// Move only if the alias points at this version now (409 `alias_moved` otherwise): a
    /// client that read the alias does not undo a move made meanwhile.
    pub expected_version: Option<u32>,
}

/// `?actor=&reason=&expected_version=` of an alias's delete.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MoveParams {
    /// Who deletes it, for the history (default `api`).
    #[param(
        pattern = r"^[^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*[^\s\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069][^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 200
    )]
    pub actor: Option<String>,
    #[param(
        pattern = r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$",
        max_length = 200
    )]
    pub reason: Option<String>,
    /// Delete only if the alias points at this version now (409 `alias_moved` otherwise).
    pub expected_version: Option<u32>,
}

/// One move of an alias.
#[derive(Debug, Serialize, ToSchema)]
pub struct AliasMoveResource {
    /// Increases with every change of the model.
    pub seq: u64,
    pub alias: String,
    /// Where it pointed before (absent: it was created).
    pub from_version: Option<u32>,
    /// The canary it had before: a rollback restores `from_version` with this canary.
    pub from_canary: Option<CanaryShare>,
    /// Where it points after (absent: it was deleted).
    pub to_version: Option<u32>,
    pub canary: Option<CanaryShare>,
    /// The shadow it had before.
    pub from_shadow: Option<ShadowShare>,
    /// The shadow it has after.
    pub shadow: Option<ShadowShare>,
    pub actor: String,
    pub reason: Option<String>,
    pub moved_at: String,
}

impl From<AliasMove> for AliasMoveResource {
    fn from(m: AliasMove) -> Self {
        AliasMoveResource {
            seq: m.seq,
            alias: m.alias,
            from_version: m.from.as_ref().map(|t| t.version),
            from_canary: m.from.as_ref().and_then(|t| t.canary).map(Into::into),
            from_shadow: m.from.and_then(|t| t.shadow).map(Into::into),
            to_version: m.to.as_ref().map(|t| t.version),
            canary: m.to.as_ref().and_then(|t| t.canary).map(Into::into),
            shadow: m.to.and_then(|t| t.shadow).map(Into::into),
            actor: m.actor,
            reason: m.reason,
            moved_at: rfc3339(&m.moved_at),
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

/// `?alias=&limit=` of a model's history.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct HistoryParams {
    /// Only this alias's moves.
    pub alias: Option<String>,
    /// 1-1000 (default 100).
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<u32>,
}

/// A model's alias moves, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct History {
    pub items: Vec<AliasMoveResource>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_model, list_models))
        .routes(routes!(get_model, update_model, delete_model))
        .routes(routes!(create_version, list_versions))
        .routes(routes!(get_version, delete_version))
        .routes(routes!(set_alias, delete_alias))
        .routes(routes!(model_history))
}

fn invalid_name(message: String) -> ApiError {
    ApiError::unprocessable("invalid_name", message)
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

fn check_text(field: &str, text: &str, max: usize) -> Result<(), ApiError> {
    model::check_text(field, text, max).map_err(|e| ApiError::unprocessable("invalid_model", e))
}

/// A model name from the path: anything else than a model's name is 404 (a name that breaks
/// the rules cannot exist), except that `name@alias` says where to use it.
fn model_name(name: &str) -> Result<(), ApiError> {
    model::check_model_name(name)
        .map_err(|rule| ApiError::NotFound(format!("model {name:?} does not exist ({rule})")))
}

fn note(
    actor: Option<String>,
    reason: Option<String>,
    expected_version: Option<u32>,
) -> Result<MoveNote, ApiError> {
    let actor = actor.unwrap_or_else(|| "api".into());
    check_text("actor", &actor, MAX_ACTOR_CHARS)?;
    if actor.trim().is_empty() {
        return Err(ApiError::unprocessable("invalid_model", "actor: must not be empty"));
    }
    if let Some(reason) = &reason {
        check_text("reason", reason, MAX_ACTOR_CHARS)?;
    }
    Ok(MoveNote { actor, reason, expected_version })
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
    model::check_model_name(&request.name).map_err(invalid_name)?;
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
    model_name(&name)?;
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
    model_name(&name)?;
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
    model_name(&name)?;
    state.store.delete_model(&name).await?;
    refresh(&state, &name).await;
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
    model_name(&name)?;
    check_text("description", &request.description, MAX_DESCRIPTION_CHARS)?;
    // The body names the policy: one that does not exist makes the body wrong (422); 404 is
    // for the model the path names.
    let unknown_policy = || {
        let message = format!("policy_id: no policy {:?}", request.policy_id);
        ApiError::unprocessable("unknown_policy", message)
    };
    match state.store.policy(&PolicyId::from(request.policy_id.as_str())).await {
        Err(StoreError::NotFound { .. }) => return Err(unknown_policy()),
        found => drop(found?),
    }
    if let Some(alias) = &request.alias {
        model::check_alias_name(alias).map_err(invalid_name)?;
        // The alias must not resolve to a policy that cannot load: load it first.
        state.serving.policies.get(&request.policy_id).await?;
    }
    let note = note(request.actor, Some("registered with the alias".into()), None)?;
    let version = NewVersion {
        model: &name,
        policy_id: &request.policy_id,
        description: &request.description,
        source: "api",
        alias: request.alias.as_deref().map(|alias| (alias, &note)),
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
    model_name(&name)?;
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
    model_name(&path.name)?;
    Ok(Json(state.store.model_version(&path.name, path.version).await?.into()))
}

/// Delete a version no alias points at (its number is not handed out again; the policy stays).
#[utoipa::path(delete, path = "/v1/models/{name}/versions/{version}", tag = "models",
    params(("name" = String, Path), ("version" = u32, Path)),
    responses((status = 204, description = "Deleted"), (status = 404, body = ErrorBody),
        (status = 409, description = "An alias points at it (`version_in_use`)",
         body = ErrorBody)))]
async fn delete_version(
    State(state): State<AppState>,
    Path(path): Path<VersionPath>,
) -> Result<StatusCode, ApiError> {
    model_name(&path.name)?;
    state.store.delete_model_version(&path.name, path.version).await?;
    refresh(&state, &path.name).await;
    Ok(StatusCode::NO_CONTENT)
}

/// `{name, alias}` of an alias's routes.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Path)]
struct AliasPath {
    name: String,
    /// An alias's name: 1-64 characters from ASCII letters, digits and `- _ .`, starting with a
    /// letter or digit, not all digits, not `latest`.
    #[param(
        pattern = r"^(?:[A-Za-z][A-Za-z0-9._-]*|[0-9]+[A-Za-z._-][A-Za-z0-9._-]*)$",
        max_length = 64
    )]
    alias: String,
}

fn canary_of(share: Option<CanaryShare>) -> Result<Option<Canary>, ApiError> {
    let Some(share) = share else { return Ok(None) };
    let basis_points = (share.weight * f64::from(BASIS_POINTS)).round();
    if !(1.0..f64::from(BASIS_POINTS)).contains(&basis_points) {
        return Err(ApiError::unprocessable(
            "invalid_canary",
            format!(
                "canary.weight must be between 0.0001 and 0.9999 (a share of the requests), got {}",
                share.weight
            ),
        ));
    }
    Ok(Some(Canary { version: share.version, basis_points: basis_points as u32 }))
}

fn shadow_of(share: Option<ShadowShare>) -> Result<Option<Shadow>, ApiError> {
    let Some(share) = share else { return Ok(None) };
    let basis_points = (share.sample * f64::from(BASIS_POINTS)).round();
    if !(1.0..=f64::from(BASIS_POINTS)).contains(&basis_points) {
        return Err(ApiError::unprocessable(
            "invalid_shadow",
            format!(
                "shadow.sample must be between 0.0001 and 1 (a share of the requests), got {}",
                share.sample
            ),
        ));
    }
    Ok(Some(Shadow { version: share.version, basis_points: basis_points as u32 }))
}

/// Point an alias at a version (creating the alias), optionally with a canary version for a
/// share of the requests. The versions' policies are loaded before the move commits, and this
/// server answers from the new version as soon as the call returns; the other API nodes of a
/// fleet follow within about a second. Every move is kept in the model's history.
#[utoipa::path(put, path = "/v1/models/{name}/aliases/{alias}", tag = "models",
    params(AliasPath), request_body = SetAlias,
    responses(
        (status = 200, body = AliasMoveResource),
        (status = 404, description = "No such model or version", body = ErrorBody),
        (status = 409, description = "The alias is not at `expected_version` (`alias_moved`), \
            or a new alias's name differs from an existing one's only by case (`alias_exists`)",
         body = ErrorBody),
        (status = 422, description = "A bad alias name (`invalid_name`), canary \
            (`invalid_canary`), shadow (`invalid_shadow`: its share, or a version that takes \
            other observations or gives another kind of action) or actor (`invalid_model`)",
         body = ErrorBody),
    ))]
async fn set_alias(
    State(state): State<AppState>,
    Path(path): Path<AliasPath>,
    Json(request): Json<SetAlias>,
) -> Result<Json<AliasMoveResource>, ApiError> {
    model_name(&path.name)?;
    model::check_alias_name(&path.alias).map_err(invalid_name)?;
    // A canary of the alias's own version splits nothing: it is no canary (the schema cannot
    // say "another version", so it is not refused).
    let canary = canary_of(request.canary)?.filter(|c| c.version != request.version);
    let shadow = shadow_of(request.shadow)?.filter(|s| s.version != request.version);
    let target = AliasTarget { version: request.version, canary, shadow };
    let note = note(request.actor, request.reason, request.expected_version)?;
    // Versions that do not exist are 404 before anything else is said of them.
    preload(&state, &path.name, &target).await?;
    let moved = state.store.set_alias(&path.name, &path.alias, &target, &note).await?;
    refresh(&state, &path.name).await;
    let from = moved.from.as_ref().map(|t| t.version);
    tracing::info!(model = %path.name, alias = %path.alias, ?from, to = target.version, actor = %note.actor, "alias moved");
    Ok(Json(moved.into()))
}

/// Loads the policies of the versions an alias will point at, so that a policy that cannot be
/// served is refused before the move (and loading takes no request's time after it); a shadow
/// must act on what the alias's version acts on.
async fn preload(state: &AppState, model: &str, target: &AliasTarget) -> Result<(), ApiError> {
    let mut main = None;
    for version in target.versions() {
        let record = state.store.model_version(model, version).await?;
        let policy = state.serving.policies.get(record.policy_id.as_str()).await?;
        main.get_or_insert_with(|| policy.clone());
        if target.shadow.is_some_and(|s| s.version == version) {
            let main = main.as_ref().expect("the alias's version comes first");
            check_shadow(main.spec(), policy.spec(), target.version, version)?;
        }
    }
    Ok(())
}

/// A shadow is compared action for action: it must take the same observations and give the
/// same kind of action as the version it shadows.
fn check_shadow(
    main: &crate::algo::PolicySpec,
    shadow: &crate::algo::PolicySpec,
    version: u32,
    shadow_version: u32,
) -> Result<(), ApiError> {
    let (kind, shadow_kind) = (action_kind(&main.action_space), action_kind(&shadow.action_space));
    if main.obs_dim == shadow.obs_dim && kind == shadow_kind {
        return Ok(());
    }
    Err(ApiError::unprocessable(
        "invalid_shadow",
        format!(
            "version {shadow_version} takes {} observation values and gives {}; version \
             {version} takes {} and gives {}: a shadow must act on the same observations, with \
             the same kind of action, to be compared",
            shadow.obs_dim, shadow_kind, main.obs_dim, kind
        ),
    ))
}

/// The kind of action a policy gives (its box's bounds aside: actions in other units still
/// compare).
fn action_kind(space: &crate::data::ActionSpace) -> String {
    match space {
        crate::data::ActionSpace::Continuous { dim, .. } => format!("{dim}-dimensional actions"),
        crate::data::ActionSpace::Discrete { n } => format!("one of {n} discrete actions"),
    }
}

/// Delete an alias (recorded in the history); agents addressing it get 404 from then on.
#[utoipa::path(delete, path = "/v1/models/{name}/aliases/{alias}", tag = "models",
    params(AliasPath, MoveParams),
    responses((status = 204, description = "Deleted"), (status = 404, body = ErrorBody),
        (status = 422, description = "A bad actor or reason (`invalid_model`)", body = ErrorBody),
        (status = 409, description = "The alias is not at `expected_version` (`alias_moved`)",
         body = ErrorBody)))]
async fn delete_alias(
    State(state): State<AppState>,
    Path(path): Path<AliasPath>,
    Query(params): Query<MoveParams>,
) -> Result<StatusCode, ApiError> {
    model_name(&path.name)?;
    let note = note(params.actor, params.reason, params.expected_version)?;
    state.store.delete_alias(&path.name, &path.alias, &note).await?;
    refresh(&state, &path.name).await;
    Ok(StatusCode::NO_CONTENT)
}

/// Every move of the model's aliases (who, when, from, to), newest first: a rollback is a move
/// back to an earlier `to_version`.
#[utoipa::path(get, path = "/v1/models/{name}/history", tag = "models",
    params(("name" = String, Path), HistoryParams),
    responses((status = 200, body = History), (status = 400, body = ErrorBody),
        (status = 404, body = ErrorBody)))]
async fn model_history(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(params): Query<HistoryParams>,
) -> Result<Json<History>, ApiError> {
    model_name(&name)?;
    let limit = params.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::bad_request(
            "invalid_pagination",
            format!("limit must be between 1 and 1000, got {limit}"),
        ));
    }
    let moves = state.store.alias_history(&name, params.alias.as_deref(), limit).await?;
    Ok(Json(History { items: moves.into_iter().map(Into::into).collect() }))
}

/// This server serves the change at once (the others of a fleet follow by notification or
/// poll). A failure to load leaves the previous table serving and is retried by the poll.
async fn refresh(state: &AppState, model: &str) {
    if let Err(e) = state.serving.models.refresh_model(model).await {
        tracing::error!(%model, error = %e, "cannot load the model's new versions yet; the previous ones keep serving");
    }
}
