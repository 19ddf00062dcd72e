//! The one error type of the upload path: a stable API code plus a message that names the
//! offending line / row / key and says how to fix it (the HTTP layer answers 422 with both).

use super::model::ModelError;

/// A rejected upload. `code` is a stable snake_case API error code; `message` names the line /
/// row / key and says how to fix it, at most [`crate::text::MAX_MESSAGE_BYTES`] long however
/// much of the input it quotes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct ParseError {
    pub code: &'static str,
    pub message: String,
}

impl ParseError {
    fn new(code: &'static str, message: impl Into<String>) -> Self {
        ParseError { code, message: crate::text::bounded_message(message.into()) }
    }

    /// The data is readable but wrong: ragged, non-finite, inconsistent, truncated, ...
    pub const INVALID: &'static str = "invalid_dataset";
    /// Neither the file name nor the content identify a supported format.
    pub const UNKNOWN_FORMAT: &'static str = "unknown_format";
    /// The file holds no transitions at all.
    pub const EMPTY: &'static str = "empty_dataset";
    /// A recognised format whose support is not compiled into this build (HDF5).
    pub const UNSUPPORTED_FORMAT: &'static str = "unsupported_format";
    /// A stored canonical file that does not decode (storage corruption, never user input).
    pub const CORRUPT_CANONICAL: &'static str = "corrupt_canonical";

    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(Self::INVALID, message)
    }

    pub fn unknown_format(message: impl Into<String>) -> Self {
        Self::new(Self::UNKNOWN_FORMAT, message)
    }

    pub fn empty(message: impl Into<String>) -> Self {
        Self::new(Self::EMPTY, message)
    }

    pub fn unsupported_format(message: impl Into<String>) -> Self {
        Self::new(Self::UNSUPPORTED_FORMAT, message)
    }

    pub fn corrupt_canonical(message: impl Into<String>) -> Self {
        Self::new(Self::CORRUPT_CANONICAL, message)
    }

    /// An I/O failure while reading the (already stored) upload: the service's problem, but
    /// reported with the same shape.
    pub fn io(context: &str, err: std::io::Error) -> Self {
        ParseError::invalid(format!("{context}: {err}"))
    }
}

impl From<ModelError> for ParseError {
    /// Column-level inconsistencies found by [`super::Dataset::new`] when a parser builds the
    /// columns; parsers catch most of these earlier with line numbers, this is the safety net.
    fn from(err: ModelError) -> Self {
        match err {
            ModelError::Empty => ParseError::empty("the file holds no transitions"),
            other => ParseError::invalid(other.to_string()),
        }
    }
}
