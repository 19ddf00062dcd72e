//! `/v1/models/{name}/aliases/{alias}` and `/v1/models/{name}/history`: aliases moved (with a
//! canary, a shadow, or neither) and deleted, each move kept in the model's history. The model
//! and its versions are [`super::models`]; serving by name is [`super::model_serving`], the
//! shadows' series [`super::model_shadows`].

use axum::extract::State;
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::error::ErrorBody;
use super::extract::{Json, Path, Query};
use super::model_names::{invalid_name, model_name, note, refresh};
use super::{ApiError, AppState};
use crate::domain::model::{self, AliasMove, AliasTarget, Canary, Shadow, BASIS_POINTS};
use crate::domain::rfc3339;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(set_alias, delete_alias)).routes(routes!(model_history))
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
    let name = model_name(&path.name)?;
    let alias = model::AliasName::parse(&path.alias).map_err(invalid_name)?;
    // A canary of the alias's own version splits nothing: it is no canary (the schema cannot
    // say "another version", so it is not refused).
    let canary = canary_of(request.canary)?.filter(|c| c.version != request.version);
    let shadow = shadow_of(request.shadow)?.filter(|s| s.version != request.version);
    let target = AliasTarget { version: request.version, canary, shadow };
    let note = note(request.actor, request.reason, request.expected_version)?;
    // Versions that do not exist are 404 before anything else is said of them.
    preload(&state, &name, &target).await?;
    let moved = state.store.set_alias(&name, &alias, &target, &note).await?;
    refresh(&state, &name).await;
    let from = moved.from.as_ref().map(|t| t.version);
    tracing::info!(model = %path.name, alias = %path.alias, ?from, to = target.version, actor = %note.actor, "alias moved");
    Ok(Json(moved.into()))
}

/// Loads the policies of the versions an alias will point at, so that a policy that cannot be
/// served is refused before the move (and loading takes no request's time after it); a shadow
/// must act on what the alias's version acts on.
async fn preload(
    state: &AppState,
    model: &model::ModelName,
    target: &AliasTarget,
) -> Result<(), ApiError> {
    let mut answering = Vec::new();
    for version in target.versions() {
        let record = state.store.model_version(model, version).await?;
        let policy = state.serving.policies.get(&record.policy_id).await?;
        match target.shadow {
            // The shadow comes last: it is compared with whichever version answers.
            Some(shadow) if shadow.version == version => {
                for (answers, spec) in &answering {
                    check_shadow(spec, policy.spec(), *answers, version)?;
                }
            }
            _ => answering.push((version, policy.spec().clone())),
        }
    }
    Ok(())
}

/// A shadow is compared action for action: it must take the same observations and give the
/// same kind of action as each version it shadows (the alias's, and its canary's).
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
    let name = model_name(&path.name)?;
    let note = note(params.actor, params.reason, params.expected_version)?;
    state.store.delete_alias(&name, &path.alias, &note).await?;
    refresh(&state, &name).await;
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
    let name = model_name(&name)?;
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
