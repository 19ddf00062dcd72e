//! The aliases of named models: moves (set, delete) inside a transaction that bumps the model's
//! revision, and the history of every move.

use sqlx::{Any, Transaction};

use super::{parse_time, Store, StoreError};
use crate::domain::model::{
    AliasMove, AliasName, AliasTarget, Canary, ModelName, MoveNote, Shadow,
};

/// The PostgreSQL notification channel of model changes; the payload is the model's name.
pub const MODELS_CHANNEL: &str = "safedice_models";

#[derive(sqlx::FromRow)]
struct MoveRow {
    seq: i64,
    alias: String,
    from_version: Option<i64>,
    from_canary_version: Option<i64>,
    from_canary_basis_points: Option<i64>,
    to_version: Option<i64>,
    to_canary_version: Option<i64>,
    to_canary_basis_points: Option<i64>,
    from_shadow_version: Option<i64>,
    from_shadow_basis_points: Option<i64>,
    to_shadow_version: Option<i64>,
    to_shadow_basis_points: Option<i64>,
    actor: String,
    reason: Option<String>,
    moved_at: String,
}

impl MoveRow {
    fn into_move(self, model: &str) -> Result<AliasMove, StoreError> {
        let to = self.to_version.map(|version| AliasTarget {
            version: version as u32,
            canary: canary(self.to_canary_version, self.to_canary_basis_points),
            shadow: shadow(self.to_shadow_version, self.to_shadow_basis_points),
        });
        Ok(AliasMove {
            moved_at: parse_time(&format!("model {model} move {}", self.seq), &self.moved_at)?,
            seq: self.seq as u64,
            alias: self.alias,
            from: self.from_version.map(|version| AliasTarget {
                version: version as u32,
                canary: canary(self.from_canary_version, self.from_canary_basis_points),
                shadow: shadow(self.from_shadow_version, self.from_shadow_basis_points),
            }),
            to,
            actor: self.actor,
            reason: self.reason,
        })
    }
}

impl Store {
    /// Tells the fleet's other processes that `model` changed, on commit (PostgreSQL's NOTIFY is
    /// transactional); nothing on SQLite, whose processes poll.
    pub(super) async fn notify_model(
        &self,
        tx: &mut Transaction<'_, Any>,
        model: &str,
    ) -> Result<(), sqlx::Error> {
        if self.backend() == super::Backend::Postgres {
            sqlx::query("SELECT CAST(pg_notify($1, $2) AS TEXT)")
                .bind(MODELS_CHANNEL)
                .bind(model)
                .execute(&mut **tx)
                .await?;
        }
        Ok(())
    }
    /// Points `alias` at `target` (creating it), recording the move.
    pub async fn set_alias(
        &self,
        model: &ModelName,
        alias: &AliasName,
        target: &AliasTarget,
        note: &MoveNote,
    ) -> Result<AliasMove, StoreError> {
        let (model, alias) = (model.as_str(), alias.as_str());
        let mut tx = self.begin_write().await?;
        let seq = set_alias_in(&mut tx, self, model, alias, Some(target), note).await?;
        tx.commit().await?;
        self.alias_move(model, seq).await
    }

    /// Deletes `alias` (a name as asked: one that is no valid alias name names none), recording
    /// the move; NotFound if the model has no such alias.
    pub async fn delete_alias(
        &self,
        model: &ModelName,
        alias: &str,
        note: &MoveNote,
    ) -> Result<AliasMove, StoreError> {
        let model = model.as_str();
        let mut tx = self.begin_write().await?;
        let seq = set_alias_in(&mut tx, self, model, alias, None, note).await?;
        tx.commit().await?;
        self.alias_move(model, seq).await
    }

    async fn alias_move(&self, model: &str, seq: u64) -> Result<AliasMove, StoreError> {
        let row: MoveRow = sqlx::query_as(&format!(
            "SELECT {MOVE_COLUMNS} FROM model_alias_moves WHERE model = $1 AND seq = $2"
        ))
        .bind(model)
        .bind(seq as i64)
        .fetch_one(self.pool())
        .await?;
        row.into_move(model)
    }

    /// The moves of a model's aliases (of `alias` only, when given, as asked), newest first.
    pub async fn alias_history(
        &self,
        model: &ModelName,
        alias: Option<&str>,
        limit: u32,
    ) -> Result<Vec<AliasMove>, StoreError> {
        let model = model.as_str();
        self.read_model(model).await?;
        let rows: Vec<MoveRow> = sqlx::query_as(&format!(
            "SELECT {MOVE_COLUMNS} FROM model_alias_moves WHERE model = $1 \
             AND ($2 IS NULL OR alias = $2) ORDER BY seq DESC LIMIT $3"
        ))
        .bind(model)
        .bind(alias)
        .bind(i64::from(limit))
        .fetch_all(self.pool())
        .await?;
        rows.into_iter().map(|row| row.into_move(model)).collect()
    }
}

const MOVE_COLUMNS: &str = "seq, alias, from_version, from_canary_version, \
     from_canary_basis_points, to_version, to_canary_version, to_canary_basis_points, \
     from_shadow_version, from_shadow_basis_points, to_shadow_version, to_shadow_basis_points, \
     actor, reason, moved_at";

/// Where an alias points, as `model_aliases` keeps it.
#[derive(sqlx::FromRow)]
pub(super) struct TargetColumns {
    pub version: i64,
    pub canary_version: Option<i64>,
    pub canary_basis_points: Option<i64>,
    pub shadow_version: Option<i64>,
    pub shadow_basis_points: Option<i64>,
}

/// The columns of [`TargetColumns`] in a `SELECT`.
pub(super) const TARGET_COLUMNS: &str =
    "version, canary_version, canary_basis_points, shadow_version, shadow_basis_points";

impl TargetColumns {
    pub fn target(&self) -> AliasTarget {
        AliasTarget {
            version: self.version as u32,
            canary: canary(self.canary_version, self.canary_basis_points),
            shadow: shadow(self.shadow_version, self.shadow_basis_points),
        }
    }
}

/// Points `alias` at `target` (None: deletes it) inside the caller's transaction and records the
/// move; returns the move's `seq`.
/// A new alias whose name differs from an existing one's only by case (`Prod` beside `prod`)
/// would read as the same alias and answer another version: refused, naming the one to move.
async fn refuse_other_case(
    tx: &mut Transaction<'_, Any>,
    model: &str,
    alias: &str,
) -> Result<(), StoreError> {
    let existing: Option<String> = sqlx::query_scalar(
        "SELECT alias FROM model_aliases WHERE model = $1 AND LOWER(alias) = LOWER($2)",
    )
    .bind(model)
    .bind(alias)
    .fetch_optional(&mut **tx)
    .await?;
    match existing {
        Some(existing) => Err(StoreError::Conflict {
            code: "alias_exists",
            message: format!(
                "{model}@{existing} exists already, and aliases are compared without case: \
                 move {model}@{existing} instead, or pick another name"
            ),
        }),
        None => Ok(()),
    }
}

pub(super) async fn set_alias_in(
    tx: &mut Transaction<'_, Any>,
    store: &Store,
    model: &str,
    alias: &str,
    target: Option<&AliasTarget>,
    note: &MoveNote,
) -> Result<u64, StoreError> {
    let seq = bump(tx, model).await?;
    let from: Option<TargetColumns> = sqlx::query_as(&format!(
        "SELECT {TARGET_COLUMNS} FROM model_aliases WHERE model = $1 AND alias = $2"
    ))
    .bind(model)
    .bind(alias)
    .fetch_optional(&mut **tx)
    .await?;
    let from = from.map(|row| row.target());
    if let Some(expected) = note.expected_version {
        let current = from.as_ref().map(|t| t.version);
        if current != Some(expected) {
            let now =
                current.map_or("does not exist".to_owned(), |v| format!("points at version {v}"));
            return Err(StoreError::Conflict {
                code: "alias_moved",
                message: format!(
                    "{model}@{alias} {now}, not version {expected} as expected: someone moved \
                     it meanwhile; read it again (GET /v1/models/{model}) and decide"
                ),
            });
        }
    }
    if target.is_some() && from.is_none() {
        refuse_other_case(tx, model, alias).await?;
    }
    let now = super::now_in(tx).await?;
    match target {
        Some(target) => {
            for version in target.versions() {
                check_version(tx, model, version).await?;
            }
            sqlx::query(
                "INSERT INTO model_aliases (model, alias, version, canary_version, \
                     canary_basis_points, shadow_version, shadow_basis_points, updated_at) \
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8) \
                 ON CONFLICT (model, alias) DO UPDATE SET version = excluded.version, \
                     canary_version = excluded.canary_version, \
                     canary_basis_points = excluded.canary_basis_points, \
                     shadow_version = excluded.shadow_version, \
                     shadow_basis_points = excluded.shadow_basis_points, \
                     updated_at = excluded.updated_at",
            )
            .bind(model)
            .bind(alias)
            .bind(i64::from(target.version))
            .bind(target.canary.map(|c| i64::from(c.version)))
            .bind(target.canary.map(|c| i64::from(c.basis_points)))
            .bind(target.shadow.map(|c| i64::from(c.version)))
            .bind(target.shadow.map(|c| i64::from(c.basis_points)))
            .bind(&now)
            .execute(&mut **tx)
            .await?;
        }
        None => {
            if from.is_none() {
                return Err(StoreError::NotFound { kind: "alias", id: format!("{model}@{alias}") });
            }
            sqlx::query("DELETE FROM model_aliases WHERE model = $1 AND alias = $2")
                .bind(model)
                .bind(alias)
                .execute(&mut **tx)
                .await?;
        }
    }
    sqlx::query(
        "INSERT INTO model_alias_moves (model, seq, alias, from_version, from_canary_version, \
             from_canary_basis_points, to_version, to_canary_version, to_canary_basis_points, \
             from_shadow_version, from_shadow_basis_points, to_shadow_version, \
             to_shadow_basis_points, actor, reason, moved_at) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16)",
    )
    .bind(model)
    .bind(seq as i64)
    .bind(alias)
    .bind(from.as_ref().map(|t| i64::from(t.version)))
    .bind(from.as_ref().and_then(|t| t.canary).map(|c| i64::from(c.version)))
    .bind(from.as_ref().and_then(|t| t.canary).map(|c| i64::from(c.basis_points)))
    .bind(target.map(|t| i64::from(t.version)))
    .bind(target.and_then(|t| t.canary).map(|c| i64::from(c.version)))
    .bind(target.and_then(|t| t.canary).map(|c| i64::from(c.basis_points)))
    .bind(from.as_ref().and_then(|t| t.shadow).map(|c| i64::from(c.version)))
    .bind(from.as_ref().and_then(|t| t.shadow).map(|c| i64::from(c.basis_points)))
    .bind(target.and_then(|t| t.shadow).map(|c| i64::from(c.version)))
    .bind(target.and_then(|t| t.shadow).map(|c| i64::from(c.basis_points)))
    .bind(&note.actor)
    .bind(note.reason.as_deref())
    .bind(&now)
    .execute(&mut **tx)
    .await?;
    store.notify_model(tx, model).await?;
    Ok(seq)
}

async fn check_version(
    tx: &mut Transaction<'_, Any>,
    model: &str,
    version: u32,
) -> Result<(), StoreError> {
    let found: Option<i64> =
        sqlx::query_scalar("SELECT version FROM model_versions WHERE model = $1 AND version = $2")
            .bind(model)
            .bind(i64::from(version))
            .fetch_optional(&mut **tx)
            .await?;
    found.map(|_| ()).ok_or_else(|| version_not_found(model, version))
}

pub(super) fn canary(version: Option<i64>, basis_points: Option<i64>) -> Option<Canary> {
    Some(Canary { version: version? as u32, basis_points: basis_points? as u32 })
}

fn shadow(version: Option<i64>, basis_points: Option<i64>) -> Option<Shadow> {
    Some(Shadow { version: version? as u32, basis_points: basis_points? as u32 })
}

pub(super) fn model_not_found(name: &str) -> StoreError {
    StoreError::NotFound { kind: "model", id: name.to_owned() }
}

pub(super) fn version_not_found(model: &str, version: u32) -> StoreError {
    StoreError::NotFound { kind: "model version", id: format!("{model} version {version}") }
}

/// Bumps the model's revision (locking its row until the transaction ends) and returns the new
/// revision; NotFound if there is no such model.
pub(super) async fn bump(tx: &mut Transaction<'_, Any>, model: &str) -> Result<u64, StoreError> {
    let revision: Option<i64> = sqlx::query_scalar(
        "UPDATE models SET revision = revision + 1, updated_at = $2 WHERE name = $1 \
         RETURNING revision",
    )
    .bind(model)
    .bind(super::now_in(tx).await?)
    .fetch_optional(&mut **tx)
    .await?;
    revision.map(|r| r as u64).ok_or_else(|| model_not_found(model))
}
