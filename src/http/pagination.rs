//! Pagination shared by every list endpoint, newest first: `?limit=&page_token=` (keyset: a
//! page does not shift when items are added meanwhile) or `?limit=&offset=`, and a page object
//! that says where the next page starts.

use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::error::ApiError;
use crate::store::{Listing, PageQuery, Store};

pub const DEFAULT_LIMIT: u32 = 50;
pub const MAX_LIMIT: u32 = 500;
/// i64::MAX, the largest offset SQL can take.
pub const MAX_OFFSET: u64 = i64::MAX as u64;

/// `?limit=50&offset=0`: at most `limit` items (1..=500, default 50), skipping `offset`.
#[derive(Debug, Clone, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PageParams {
    /// Items per page, 1 to 500 (default 50).
    #[param(minimum = 1, maximum = 500, default = 50)]
    pub limit: Option<u32>,
    /// Items to skip (default 0), at most 2^63 - 1; with `page_token`, counted after its item.
    #[param(minimum = 0, maximum = 9223372036854775807_i64, default = 0)]
    pub offset: Option<u64>,
    /// The previous page's `next_page_token`: the page after it, unaffected by items added
    /// since (an `offset` shifts when new items arrive).
    #[param(min_length = 1, max_length = 64)]
    pub page_token: Option<String>,
}

/// A validated page request.
pub type PageRequest = PageQuery;

impl PageParams {
    pub fn validate(self) -> Result<PageRequest, ApiError> {
        let limit = self.limit.unwrap_or(DEFAULT_LIMIT);
        if !(1..=MAX_LIMIT).contains(&limit) {
            return Err(ApiError::bad_request(
                "invalid_pagination",
                format!("limit must be between 1 and {MAX_LIMIT}, got {limit}"),
            ));
        }
        let offset = self.offset.unwrap_or(0);
        // The database counts in i64: a larger offset would wrap to the first page.
        if offset > MAX_OFFSET {
            return Err(ApiError::bad_request(
                "invalid_pagination",
                format!("offset must be between 0 and {MAX_OFFSET}, got {offset}"),
            ));
        }
        let after = self.page_token;
        if let Some(token) = &after {
            let chars = token.chars().count();
            if !(1..=64).contains(&chars) {
                return Err(ApiError::bad_request(
                    "invalid_pagination",
                    format!(
                        "page_token must be 1 to 64 characters (a next_page_token), got {chars}"
                    ),
                ));
            }
        }
        Ok(PageRequest { limit, offset, after })
    }

    /// Validates the request and checks that a page token's item still exists in `list`.
    pub async fn resolve(self, store: &Store, list: Listing) -> Result<PageRequest, ApiError> {
        let page = self.validate()?;
        if let Some(token) = &page.after {
            if !store.page_anchor_exists(list, token).await? {
                return Err(ApiError::Rejected {
                    status: axum::http::StatusCode::NOT_FOUND,
                    code: "page_token_not_found",
                    message: format!(
                        "page_token {token:?} is not an item of this list (deleted since, or not \
                         a next_page_token): start again from the first page"
                    ),
                });
            }
        }
        Ok(page)
    }
}

/// One page of a list, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct Page<T> {
    pub items: Vec<T>,
    /// Number of items across all pages.
    pub total: u64,
    pub limit: u32,
    pub offset: u64,
    /// The `offset` of the next page, absent on the last page and with `page_token`.
    pub next_offset: Option<u64>,
    /// Pass as `page_token` for the next page; absent when this page is not full (the last).
    pub next_page_token: Option<String>,
}

impl<T> Page<T> {
    /// A page of `items`; `id` gives an item's id (the next page's token).
    pub fn new(items: Vec<T>, total: u64, request: PageRequest, id: impl Fn(&T) -> &str) -> Self {
        let end = request.offset.saturating_add(items.len() as u64);
        let next_offset = (end < total && request.after.is_none()).then_some(end);
        let full = items.len() == request.limit as usize;
        let next_page_token = items.last().filter(|_| full).map(|last| id(last).to_owned());
        Page {
            items,
            total,
            limit: request.limit,
            offset: request.offset,
            next_offset,
            next_page_token,
        }
    }
}
