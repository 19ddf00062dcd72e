//! Pages of the tables the API lists: newest first, by offset or after a row (keyset paging),
//! and the one query that reads a whole table's page and its total.

use sqlx::any::AnyRow;
use sqlx::FromRow;

use super::{Store, StoreError};

/// Which page of a list (newest first: `created_at DESC, id DESC`): `limit` rows after
/// skipping `offset`, or after the row `after` (keyset paging: pages do not shift when rows are
/// added meanwhile).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PageQuery {
    pub limit: u32,
    pub offset: u64,
    pub after: Option<String>,
}

/// The tables the API lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Listing {
    Datasets,
    Jobs,
    Policies,
    Evaluations,
    Models,
    Experiments,
}

impl Listing {
    pub(super) fn table(self) -> &'static str {
        match self {
            Listing::Datasets => "datasets",
            Listing::Jobs => "jobs",
            Listing::Policies => "policies",
            Listing::Evaluations => "evaluations",
            Listing::Models => "models",
            Listing::Experiments => "experiments",
        }
    }

    /// The column that names a row (models are named, everything else has an id).
    pub(super) fn key(self) -> &'static str {
        match self {
            Listing::Models => "name",
            _ => "id",
        }
    }

    /// The keyset condition with the anchor id bound at `$n`: rows listed after the anchor.
    pub(super) fn after(self, n: usize) -> String {
        format!(
            "(${n} IS NULL OR (created_at, {key}) < \
             (SELECT created_at, {key} FROM {} WHERE {key} = ${n}))",
            self.table(),
            key = self.key()
        )
    }
}

impl Listing {
    /// A page of the whole table (`columns` selected, newest first) as `R` rows, and the
    /// table's row count.
    pub(super) async fn page<R>(
        self,
        store: &Store,
        columns: &str,
        page: &PageQuery,
    ) -> Result<(Vec<R>, u64), StoreError>
    where
        R: for<'r> FromRow<'r, AnyRow> + Send + Unpin,
    {
        let (table, key) = (self.table(), self.key());
        let rows: Vec<R> = sqlx::query_as(&format!(
            "SELECT {columns} FROM {table} WHERE {} ORDER BY created_at DESC, {key} DESC \
             LIMIT $1 OFFSET $2",
            self.after(3)
        ))
        .bind(i64::from(page.limit))
        .bind(page.offset as i64)
        .bind(page.after.as_deref())
        .fetch_all(store.pool())
        .await?;
        let total: i64 = sqlx::query_scalar(&format!("SELECT COUNT(*) FROM {table}"))
            .fetch_one(store.pool())
            .await?;
        Ok((rows, total as u64))
    }
}
