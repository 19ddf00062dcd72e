//! Named models: their versions (each a policy), aliases and the history of every alias move.
//!
//! Every change of a model bumps its `revision` in the same transaction, so a serving process
//! that remembers the revision it loaded knows whether to look again; on PostgreSQL the
//! transaction also notifies [`MODELS_CHANNEL`] with the model's name, delivered on commit, so
//! the other API nodes of a fleet look at once rather than at their next poll.

use sqlx::{Any, Transaction};

pub use super::model_aliases::MODELS_CHANNEL;
use super::model_aliases::{
    bump, model_not_found, version_not_found, TargetColumns, TARGET_COLUMNS,
};
use super::{parse_time, Listing, PageQuery, Store, StoreError};
use crate::domain::job::JobStatus;
use crate::domain::model::{
    AliasName, AliasRecord, AliasTarget, ModelName, ModelRecord, ModelRoutes, ModelVersionRecord,
    MoveNote,
};

/// A new model's fields.
#[derive(Clone, Debug)]
pub struct NewModel<'a> {
    pub name: &'a str,
    pub description: &'a str,
    pub tags: &'a [String],
}

/// A new version's fields.
#[derive(Clone, Debug)]
pub struct NewVersion<'a> {
    pub model: &'a ModelName,
    pub policy_id: &'a str,
    pub description: &'a str,
    /// `api`, or `job <id>`.
    pub source: &'a str,
    /// An alias to move to the new version in the same transaction.
    pub alias: Option<(&'a AliasName, &'a MoveNote)>,
}

#[derive(sqlx::FromRow)]
struct ModelRow {
    name: String,
    description: String,
    tags: String,
    created_at: String,
    updated_at: String,
    latest_version: Option<i64>,
    version_count: i64,
}

const MODEL_COLUMNS: &str = "name, description, tags, created_at, updated_at, \
     (SELECT MAX(version) FROM model_versions WHERE model = models.name) AS latest_version, \
     (SELECT COUNT(*) FROM model_versions WHERE model = models.name) AS version_count";

#[derive(sqlx::FromRow)]
struct AliasRow {
    alias: String,
    #[sqlx(flatten)]
    target: TargetColumns,
    updated_at: String,
}

#[derive(sqlx::FromRow)]
struct VersionRow {
    model: String,
    version: i64,
    policy_id: String,
    job_id: String,
    job_name: Option<String>,
    algorithm: String,
    description: String,
    source: String,
    created_at: String,
}

const VERSION_COLUMNS: &str = "model, version, model_versions.policy_id, description, source, \
     model_versions.created_at, p.job_id, p.algorithm, \
     (SELECT name FROM jobs WHERE jobs.id = p.job_id) AS job_name";
/// The versions with their policies (every version has one: a policy in use is never deleted).
const VERSIONS: &str = "model_versions JOIN policies AS p ON p.id = model_versions.policy_id";

impl AliasRow {
    fn into_record(self, model: &str) -> Result<AliasRecord, StoreError> {
        Ok(AliasRecord {
            target: self.target.target(),
            updated_at: parse_time(&format!("alias {model}@{}", self.alias), &self.updated_at)?,
            alias: self.alias,
        })
    }
}

impl TryFrom<VersionRow> for ModelVersionRecord {
    type Error = StoreError;

    fn try_from(row: VersionRow) -> Result<Self, StoreError> {
        let owner = format!("model {} version {}", row.model, row.version);
        Ok(ModelVersionRecord {
            created_at: parse_time(&owner, &row.created_at)?,
            version: row.version as u32,
            policy_id: row.policy_id.into(),
            job_id: row.job_id,
            job_name: row.job_name,
            algorithm: row.algorithm,
            description: row.description,
            source: row.source,
            model: row.model,
        })
    }
}

impl Store {
    /// Creates a model; `model_exists` (409) when the name is taken.
    pub async fn create_model(&self, model: &NewModel<'_>) -> Result<ModelRecord, StoreError> {
        let tags = serde_json::Value::from(model.tags.to_vec()).to_string();
        let mut tx = self.begin_write().await?;
        let now = super::now_in(&mut tx).await?;
        // `Pilot` beside `pilot` would read as one model and answer as two.
        let same: Option<String> =
            sqlx::query_scalar("SELECT name FROM models WHERE LOWER(name) = LOWER($1)")
                .bind(model.name)
                .fetch_optional(&mut *tx)
                .await?;
        if let Some(existing) = same.filter(|existing| existing != model.name) {
            return Err(StoreError::Conflict {
                code: "model_exists",
                message: format!(
                    "a model named {existing} exists already, and names are compared without \
                     case; pick another name, or add a version to {existing}"
                ),
            });
        }
        let inserted = sqlx::query(
            "INSERT INTO models (name, description, tags, revision, created_at, updated_at) \
             VALUES ($1, $2, $3, (SELECT revision + 1 FROM model_revision_floor WHERE id = 1), \
             $4, $4) ON CONFLICT (name) DO NOTHING",
        )
        .bind(model.name)
        .bind(model.description)
        .bind(&tags)
        .bind(&now)
        .execute(&mut *tx)
        .await?;
        if inserted.rows_affected() == 0 {
            return Err(StoreError::Conflict {
                code: "model_exists",
                message: format!(
                    "a model named {} exists already; pick another name, or add a version to it",
                    model.name
                ),
            });
        }
        self.notify_model(&mut tx, model.name).await?;
        tx.commit().await?;
        self.read_model(model.name).await
    }

    pub async fn model(&self, name: &ModelName) -> Result<ModelRecord, StoreError> {
        self.read_model(name.as_str()).await
    }

    /// [`Store::model`] by a name this store wrote (checked when the model was created).
    pub(super) async fn read_model(&self, name: &str) -> Result<ModelRecord, StoreError> {
        let row: ModelRow =
            sqlx::query_as(&format!("SELECT {MODEL_COLUMNS} FROM models WHERE name = $1"))
                .bind(name)
                .fetch_optional(self.pool())
                .await?
                .ok_or_else(|| model_not_found(name))?;
        self.model_record(row).await
    }

    async fn model_record(&self, row: ModelRow) -> Result<ModelRecord, StoreError> {
        let owner = format!("model {}", row.name);
        let tags = serde_json::from_str(&row.tags)
            .map_err(|e| StoreError::Corrupt(owner.clone(), format!("stored tags: {e}")))?;
        let aliases = self.aliases(&row.name).await?;
        Ok(ModelRecord {
            description: row.description,
            tags,
            latest_version: row.latest_version.map(|v| v as u32),
            version_count: row.version_count as u64,
            aliases,
            created_at: parse_time(&owner, &row.created_at)?,
            updated_at: parse_time(&owner, &row.updated_at)?,
            name: row.name,
        })
    }

    async fn aliases(&self, model: &str) -> Result<Vec<AliasRecord>, StoreError> {
        let rows: Vec<AliasRow> = sqlx::query_as(&format!(
            "SELECT alias, {TARGET_COLUMNS}, updated_at FROM model_aliases WHERE model = $1 \
             ORDER BY alias"
        ))
        .bind(model)
        .fetch_all(self.pool())
        .await?;
        rows.into_iter().map(|row| row.into_record(model)).collect()
    }

    /// A page of models, newest first; and the total.
    pub async fn list_models(
        &self,
        page: &PageQuery,
    ) -> Result<(Vec<ModelRecord>, u64), StoreError> {
        let (rows, total) = Listing::Models.page::<ModelRow>(self, MODEL_COLUMNS, page).await?;
        let mut records = Vec::with_capacity(rows.len());
        for row in rows {
            records.push(self.model_record(row).await?);
        }
        Ok((records, total))
    }

    /// Changes a model's description and/or tags.
    pub async fn update_model(
        &self,
        name: &ModelName,
        description: Option<&str>,
        tags: Option<&[String]>,
    ) -> Result<ModelRecord, StoreError> {
        let tags = tags.map(|tags| serde_json::Value::from(tags.to_vec()).to_string());
        let updated = sqlx::query(
            "UPDATE models SET description = COALESCE($2, description), tags = COALESCE($3, tags), \
             updated_at = $4 WHERE name = $1",
        )
        .bind(name.as_str())
        .bind(description)
        .bind(tags)
        .bind(self.db_now().await?)
        .execute(self.pool())
        .await?;
        if updated.rows_affected() == 0 {
            return Err(model_not_found(name.as_str()));
        }
        self.read_model(name.as_str()).await
    }

    /// Deletes a model with its versions and history (never the policies). Refused (409
    /// `model_in_use`) while an alias points at one of its versions (agents may be using it)
    /// or a queued or running job will register into it.
    pub async fn delete_model(&self, name: &ModelName) -> Result<(), StoreError> {
        let name = name.as_str();
        let mut tx = self.begin_write().await?;
        lock_model(&mut tx, self, name).await?;
        let aliases: Vec<String> =
            sqlx::query_scalar("SELECT alias FROM model_aliases WHERE model = $1 ORDER BY alias")
                .bind(name)
                .fetch_all(&mut *tx)
                .await?;
        let jobs: Vec<String> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE register_model = $1 AND status IN ($2, $3) ORDER BY id",
        )
        .bind(name)
        .bind(JobStatus::Queued.as_str())
        .bind(JobStatus::Running.as_str())
        .fetch_all(&mut *tx)
        .await?;
        if !aliases.is_empty() || !jobs.is_empty() {
            let mut uses = Vec::new();
            if !aliases.is_empty() {
                uses.push(format!(
                    "alias(es) {} may be serving agents (delete them first: DELETE \
                     /v1/models/{name}/aliases/{{alias}})",
                    aliases.join(", ")
                ));
            }
            if !jobs.is_empty() {
                uses.push(format!("job(s) {} will register into it", jobs.join(", ")));
            }
            return Err(StoreError::Conflict {
                code: "model_in_use",
                message: format!("model {name} is in use: {}", uses.join("; ")),
            });
        }
        // A model created under this name later starts above this one's revision, so every
        // serving process sees it as newer than the table it may still hold of this one.
        sqlx::query(
            "UPDATE model_revision_floor SET revision = \
             (SELECT revision FROM models WHERE name = $1) \
             WHERE id = 1 AND revision < (SELECT revision FROM models WHERE name = $1)",
        )
        .bind(name)
        .execute(&mut *tx)
        .await?;
        let tables = ["shadow_comparisons", "model_alias_moves", "model_aliases", "model_versions"];
        for table in tables.into_iter().chain(["models"]) {
            let column = if table == "models" { "name" } else { "model" };
            sqlx::query(&format!("DELETE FROM {table} WHERE {column} = $1"))
                .bind(name)
                .execute(&mut *tx)
                .await?;
        }
        self.notify_model(&mut tx, name).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Registers a policy as the model's next version (numbers never repeat, and concurrent
    /// registrations get consecutive ones: the model's row is the lock); moves `alias` to it if
    /// given.
    pub async fn register_version(
        &self,
        version: &NewVersion<'_>,
    ) -> Result<ModelVersionRecord, StoreError> {
        let mut tx = self.begin_write().await?;
        let number = register_in(&mut tx, self, version).await?;
        tx.commit().await?;
        self.model_version(version.model, number).await
    }

    pub async fn model_version(
        &self,
        model: &ModelName,
        version: u32,
    ) -> Result<ModelVersionRecord, StoreError> {
        let row: VersionRow = sqlx::query_as(&format!(
            "SELECT {VERSION_COLUMNS} FROM {VERSIONS} WHERE model = $1 AND version = $2"
        ))
        .bind(model.as_str())
        .bind(i64::from(version))
        .fetch_optional(self.pool())
        .await?
        .ok_or_else(|| version_not_found(model.as_str(), version))?;
        row.try_into()
    }

    /// A model's versions, newest first (`limit` after skipping `offset`); and how many it has.
    pub async fn model_versions(
        &self,
        model: &ModelName,
        limit: u32,
        offset: u64,
    ) -> Result<(Vec<ModelVersionRecord>, u64), StoreError> {
        let model = model.as_str();
        self.read_model(model).await?;
        let rows: Vec<VersionRow> = sqlx::query_as(&format!(
            "SELECT {VERSION_COLUMNS} FROM {VERSIONS} WHERE model = $1 \
             ORDER BY version DESC LIMIT $2 OFFSET $3"
        ))
        .bind(model)
        .bind(i64::from(limit))
        .bind(offset as i64)
        .fetch_all(self.pool())
        .await?;
        let total: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM model_versions WHERE model = $1")
            .bind(model)
            .fetch_one(self.pool())
            .await?;
        let records = rows.into_iter().map(TryInto::try_into).collect::<Result<_, _>>()?;
        Ok((records, total as u64))
    }

    /// Deletes a version no alias points at (its number is never handed out again).
    pub async fn delete_model_version(
        &self,
        model: &ModelName,
        version: u32,
    ) -> Result<(), StoreError> {
        let model = model.as_str();
        let mut tx = self.begin_write().await?;
        bump(&mut tx, model).await?;
        let aliases: Vec<String> = sqlx::query_scalar(
            "SELECT alias FROM model_aliases WHERE model = $1 \
             AND (version = $2 OR canary_version = $2 OR shadow_version = $2) ORDER BY alias",
        )
        .bind(model)
        .bind(i64::from(version))
        .fetch_all(&mut *tx)
        .await?;
        if !aliases.is_empty() {
            return Err(StoreError::Conflict {
                code: "version_in_use",
                message: format!(
                    "{model} version {version} is served by alias(es) {}; point them elsewhere \
                     first",
                    aliases.join(", ")
                ),
            });
        }
        let deleted = sqlx::query("DELETE FROM model_versions WHERE model = $1 AND version = $2")
            .bind(model)
            .bind(i64::from(version))
            .execute(&mut *tx)
            .await?;
        if deleted.rows_affected() == 0 {
            return Err(version_not_found(model, version));
        }
        self.notify_model(&mut tx, model).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Every model's revision: what a serving process compares with what it loaded.
    pub async fn model_revisions(&self) -> Result<Vec<(String, u64)>, StoreError> {
        let rows: Vec<(String, i64)> =
            sqlx::query_as("SELECT name, revision FROM models").fetch_all(self.pool()).await?;
        Ok(rows.into_iter().map(|(name, revision)| (name, revision as u64)).collect())
    }

    /// What serving needs of a model (None: there is no such model), read in one transaction
    /// so the versions and aliases are of one revision.
    pub async fn model_routes(&self, name: &str) -> Result<Option<ModelRoutes>, StoreError> {
        let mut tx = self.pool().begin().await?;
        let row: Option<(i64, String)> =
            sqlx::query_as("SELECT revision, created_at FROM models WHERE name = $1")
                .bind(name)
                .fetch_optional(&mut *tx)
                .await?;
        let Some((revision, created_at)) = row else { return Ok(None) };
        let versions: Vec<(i64, String)> = sqlx::query_as(
            "SELECT version, policy_id FROM model_versions WHERE model = $1 ORDER BY version",
        )
        .bind(name)
        .fetch_all(&mut *tx)
        .await?;
        let aliases: Vec<AliasRow> = sqlx::query_as(&format!(
            "SELECT alias, {TARGET_COLUMNS}, updated_at FROM model_aliases WHERE model = $1 \
             ORDER BY alias"
        ))
        .bind(name)
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Some(ModelRoutes {
            name: name.to_owned(),
            created_at,
            revision: revision as u64,
            versions: versions.into_iter().map(|(v, policy)| (v as u32, policy.into())).collect(),
            aliases: aliases.into_iter().map(|row| (row.alias, row.target.target())).collect(),
        }))
    }
}

/// The model versions that point at a policy, as `name version n`.
pub(super) async fn versions_of_policy(
    tx: &mut Transaction<'_, Any>,
    policy_id: &str,
) -> Result<Vec<String>, sqlx::Error> {
    let rows: Vec<(String, i64)> = sqlx::query_as(
        "SELECT model, version FROM model_versions WHERE policy_id = $1 ORDER BY model, version",
    )
    .bind(policy_id)
    .fetch_all(&mut **tx)
    .await?;
    Ok(rows.into_iter().map(|(model, v)| format!("{model} version {v}")).collect())
}

async fn lock_model(
    tx: &mut Transaction<'_, Any>,
    store: &Store,
    model: &str,
) -> Result<(), StoreError> {
    let found: Option<String> = sqlx::query_scalar(&format!(
        "SELECT name FROM models WHERE name = $1{}",
        store.backend().lock_row()
    ))
    .bind(model)
    .fetch_optional(&mut **tx)
    .await?;
    found.map(|_| ()).ok_or_else(|| model_not_found(model))
}

/// Registers a version inside the caller's transaction (also a job's completion); returns its
/// number.
pub(super) async fn register_in(
    tx: &mut Transaction<'_, Any>,
    store: &Store,
    version: &NewVersion<'_>,
) -> Result<u32, StoreError> {
    let number: Option<i64> = sqlx::query_scalar(
        "UPDATE models SET last_version = last_version + 1, revision = revision + 1, \
         updated_at = $2 WHERE name = $1 RETURNING last_version",
    )
    .bind(version.model.as_str())
    .bind(super::now_in(tx).await?)
    .fetch_optional(&mut **tx)
    .await?;
    let number = number.ok_or_else(|| model_not_found(version.model.as_str()))?;
    let policy: Option<String> = sqlx::query_scalar(&format!(
        "SELECT id FROM policies WHERE id = $1{}",
        store.backend().share_row()
    ))
    .bind(version.policy_id)
    .fetch_optional(&mut **tx)
    .await?;
    if policy.is_none() {
        return Err(StoreError::NotFound { kind: "policy", id: version.policy_id.to_owned() });
    }
    sqlx::query(
        "INSERT INTO model_versions (model, version, policy_id, description, source, created_at) \
         VALUES ($1, $2, $3, $4, $5, $6)",
    )
    .bind(version.model.as_str())
    .bind(number)
    .bind(version.policy_id)
    .bind(version.description)
    .bind(version.source)
    .bind(super::now_in(tx).await?)
    .execute(&mut **tx)
    .await?;
    let number = number as u32;
    if let Some((alias, note)) = version.alias {
        let target = AliasTarget { version: number, canary: None, shadow: None };
        super::model_aliases::set_alias_in(
            tx,
            store,
            version.model.as_str(),
            alias.as_str(),
            Some(&target),
            note,
        )
        .await?;
    } else {
        store.notify_model(tx, version.model.as_str()).await?;
    }
    Ok(number)
}
