//! Offset pagination shared by every list endpoint: `?limit=&offset=`, newest first, and a
//! page object that says where the next page starts.

use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::error::ApiError;

pub const DEFAULT_LIMIT: u32 = 50;
pub const MAX_LIMIT: u32 = 500;
/// i64::MAX, the largest offset SQL can take.
pub const MAX_OFFSET: u64 = i64::MAX as u64;

/// `?limit=50&offset=0`: at most `limit` items (1..=500, default 50), skipping `offset`.
#[derive(Debug, Clone, Copy, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PageParams {
    /// Items per page, 1 to 500 (default 50).
    #[param(minimum = 1, maximum = 500, default = 50)]
    pub limit: Option<u32>,
    /// Items to skip (default 0), at most 2^63 - 1.
    #[param(minimum = 0, maximum = 9223372036854775807_i64, default = 0)]
    pub offset: Option<u64>,
}

/// A validated page request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PageRequest {
    pub limit: u32,
    pub offset: u64,
}

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
        Ok(PageRequest { limit, offset })
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
    /// The `offset` of the next page, absent on the last page.
    pub next_offset: Option<u64>,
}

impl<T> Page<T> {
    pub fn new(items: Vec<T>, total: u64, request: PageRequest) -> Self {
        let end = request.offset.saturating_add(items.len() as u64);
        let next_offset = (end < total).then_some(end);
        Page { items, total, limit: request.limit, offset: request.offset, next_offset }
    }
}
