//! Datasets: the in-memory model, the upload parsers and their validation, the canonical stored
//! form, statistics and writers.
//!
//! Upload formats (detected from the file name and the content, see [`parse_file`]):
//! - JSONL, one transition per line ([`jsonl`] module docs),
//! - CSV with a header ([`csv_table`] module docs),
//! - NPZ in the D4RL/DSRL/OmniSafe flat layout ([`flat`] module docs),
//! - HDF5 with the same keys as top-level datasets ([`hdf5`] module docs).
//!
//! Every rejection is a [`ParseError`] whose message names the line / row / key.

mod canonical;
mod csv_table;
mod error;
mod flat;
mod hdf5;
mod jsonl;
pub mod model;
mod npz;
mod preview;
mod rows;
mod stats;
mod writers;

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use serde::{Deserialize, Serialize};

pub use canonical::{
    canonical_header_len, decode_canonical, encode_canonical, preview_rows, CanonicalHeader,
    CANONICAL_PREFIX_BYTES,
};
pub use error::ParseError;
pub use model::{ActionSpace, Actions, Dataset, DatasetParts, ModelError};
pub use preview::{
    preview, preview_parts, DatasetPreview, EpisodeColumns, EpisodeSummary, TransitionRow,
};
pub use rows::MAX_DISCRETE_ACTIONS;
pub use stats::{disagreements, stats, DatasetStats, Summary};
pub use writers::{write_csv, write_jsonl, write_npz};

/// An upload format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Jsonl,
    Csv,
    Npz,
    Hdf5,
}

impl Format {
    pub fn as_str(self) -> &'static str {
        match self {
            Format::Jsonl => "jsonl",
            Format::Csv => "csv",
            Format::Npz => "npz",
            Format::Hdf5 => "hdf5",
        }
    }

    /// The format a file extension names, if any.
    fn from_file_name(file_name: &str) -> Option<Format> {
        let lower = file_name.to_ascii_lowercase();
        let ext = lower.rsplit_once('.').map(|(_, ext)| ext)?;
        match ext {
            "jsonl" | "ndjson" | "json" => Some(Format::Jsonl),
            "csv" => Some(Format::Csv),
            "npz" => Some(Format::Npz),
            "h5" | "hdf5" | "hdf" => Some(Format::Hdf5),
            _ => None,
        }
    }
}

impl std::str::FromStr for Format {
    type Err = ParseError;

    /// The inverse of [`Format::as_str`] (for reading a stored format back).
    fn from_str(s: &str) -> Result<Format, ParseError> {
        [Format::Jsonl, Format::Csv, Format::Npz, Format::Hdf5]
            .into_iter()
            .find(|f| f.as_str() == s)
            .ok_or_else(|| ParseError::unknown_format(format!("unknown format `{s}`")))
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

const ZIP_MAGIC: &[u8] = b"PK\x03\x04";
const EMPTY_ZIP_MAGIC: &[u8] = b"PK\x05\x06";
const HDF5_MAGIC: &[u8] = b"\x89HDF\r\n\x1a\n";
const GZIP_MAGIC: &[u8] = b"\x1f\x8b";
const SUPPORTED: &str = "supported formats: .jsonl, .csv, .npz, .h5/.hdf5";

/// Detects the format from the file name and the content, parses, validates and returns the
/// dataset. Works from a file on disk (uploads are streamed to a temp file first); text formats
/// are streamed, binary ones decoded column by column.
pub fn parse_file(path: &Path, file_name: &str) -> Result<(Format, Dataset), ParseError> {
    let format = detect(path, file_name)?;
    let open = || File::open(path).map_err(|e| ParseError::io("opening the upload", e));
    let dataset = match format {
        Format::Jsonl => jsonl::parse(BufReader::with_capacity(1 << 16, open()?))?,
        Format::Csv => csv_table::parse(BufReader::with_capacity(1 << 16, open()?))?,
        Format::Npz => npz::parse(path)?,
        Format::Hdf5 => hdf5::parse(path)?,
    };
    Ok((format, dataset))
}

/// Content decides for binary formats (magic bytes); the name decides between text formats and
/// must not contradict the content.
fn detect(path: &Path, file_name: &str) -> Result<Format, ParseError> {
    let mut head = Vec::with_capacity(512);
    File::open(path)
        .and_then(|f| f.take(512).read_to_end(&mut head))
        .map_err(|e| ParseError::io("reading the upload", e))?;
    let named = Format::from_file_name(file_name);
    let text = head.strip_prefix(b"\xEF\xBB\xBF".as_slice()).unwrap_or(&head);
    let first = text.iter().find(|b| !b.is_ascii_whitespace()).copied();
    if first.is_none() {
        return Err(ParseError::empty(format!("`{file_name}` is empty: it holds no transitions")));
    }
    let by_content = if head.starts_with(ZIP_MAGIC) || head.starts_with(EMPTY_ZIP_MAGIC) {
        Some(Format::Npz)
    } else if head.starts_with(HDF5_MAGIC) {
        Some(Format::Hdf5)
    } else if head.starts_with(GZIP_MAGIC) {
        return Err(ParseError::unknown_format(format!(
            "`{file_name}` is gzip-compressed; decompress it first ({SUPPORTED})"
        )));
    } else if first == Some(b'{') {
        Some(Format::Jsonl)
    } else {
        None
    };
    match (named, by_content) {
        (Some(n), Some(c)) if n == c => Ok(n),
        (Some(Format::Npz), _) => Err(ParseError::invalid(format!(
            "`{file_name}` is named .npz but is not a zip archive (truncated or not an NPZ); \
             write it with numpy.savez"
        ))),
        (Some(Format::Hdf5), _) => Err(ParseError::invalid(format!(
            "`{file_name}` is named as HDF5 but lacks the HDF5 signature (truncated or not HDF5)"
        ))),
        (_, Some(c @ (Format::Npz | Format::Hdf5))) => Ok(c),
        (Some(Format::Jsonl), _) => {
            if first == Some(b'[') {
                Err(ParseError::invalid(format!(
                    "`{file_name}` holds a JSON array; write one JSON object per line (JSONL)"
                )))
            } else {
                Err(ParseError::invalid(format!(
                    "line 1 of `{file_name}`: expected a JSON object (one transition per line)"
                )))
            }
        }
        (Some(Format::Csv), Some(Format::Jsonl)) => Err(ParseError::invalid(format!(
            "`{file_name}` is named .csv but holds JSON objects; rename it to .jsonl"
        ))),
        (Some(Format::Csv), _) => Ok(Format::Csv),
        (None, Some(Format::Jsonl)) => Ok(Format::Jsonl),
        (None, _) if looks_like_csv_header(text) => Ok(Format::Csv),
        (None, _) => Err(ParseError::unknown_format(format!(
            "cannot tell the format of `{file_name}` from its name or content; {SUPPORTED}"
        ))),
    }
}

/// A first line with comma-separated names including `episode` and an `obs_` column.
fn looks_like_csv_header(text: &[u8]) -> bool {
    let line = text.split(|&b| b == b'\n').next().unwrap_or_default();
    let line = String::from_utf8_lossy(line);
    let names: Vec<&str> = line.split(',').map(|s| s.trim().trim_matches('"')).collect();
    names.contains(&"episode") && names.iter().any(|n| n.starts_with("obs_"))
}
