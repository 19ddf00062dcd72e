//! The canonical binary form an accepted upload is stored in once and never re-parsed: a
//! safetensors file of the columns whose metadata carries a format tag, a version and the
//! dataset's scalars as JSON. Exact round trip (f32 bits preserved), and decoding is a bounds-
//! checked copy per column.
//!
//! Layout (version 1), tensors by name:
//! `observations` F32 [N, d], `next_observations` F32 [N, d], `actions` F32 [N, k] or U32 [N],
//! `terminals` U8 [N] (0/1), `episode_ids` U32 [N], optional `rewards` / `costs` F32 [N].
//! Metadata: `format` = "safedice-dataset", `version` = "1", `obs_dim`, `action_space` (JSON).

use std::borrow::Cow;
use std::collections::HashMap;

use safetensors::tensor::{Dtype, TensorInfo, TensorView};
use safetensors::SafeTensors;

use super::error::ParseError;
use super::model::{ActionSpace, Actions, Dataset, DatasetParts};
use super::preview::EpisodeColumns;

/// One tensor to write: name, dtype, shape, little-endian bytes.
type Column<'a> = (&'static str, Dtype, Vec<usize>, Cow<'a, [u8]>);

const FORMAT_TAG: &str = "safedice-dataset";
const VERSION: &str = "1";

/// Encodes a dataset into the canonical form.
pub fn encode_canonical(d: &Dataset) -> Vec<u8> {
    let n = d.len();
    let terminals: Vec<u8> = d.terminals().iter().map(|&t| t as u8).collect();
    let mut tensors: Vec<Column> = vec![
        ("observations", Dtype::F32, vec![n, d.obs_dim()], f32_bytes(d.observations())),
        ("next_observations", Dtype::F32, vec![n, d.obs_dim()], f32_bytes(d.next_observations())),
        ("terminals", Dtype::U8, vec![n], Cow::Borrowed(&terminals)),
        ("episode_ids", Dtype::U32, vec![n], u32_bytes(d.episode_ids())),
    ];
    match d.actions() {
        Actions::Continuous(a) => {
            tensors.push(("actions", Dtype::F32, vec![n, d.action_space().width()], f32_bytes(a)))
        }
        Actions::Discrete(a) => tensors.push(("actions", Dtype::U32, vec![n], u32_bytes(a))),
    }
    for (name, column) in [("rewards", d.rewards()), ("costs", d.costs())] {
        if let Some(values) = column {
            tensors.push((name, Dtype::F32, vec![n], f32_bytes(values)));
        }
    }
    let views = tensors.iter().map(|(name, dtype, shape, bytes)| {
        let view = TensorView::new(*dtype, shape.clone(), bytes)
            .expect("column lengths agree with their shapes in a checked dataset");
        (*name, view)
    });
    let metadata = HashMap::from([
        ("format".to_string(), FORMAT_TAG.to_string()),
        ("version".to_string(), VERSION.to_string()),
        ("obs_dim".to_string(), d.obs_dim().to_string()),
        (
            "action_space".to_string(),
            serde_json::to_string(d.action_space()).expect("action space serialises"),
        ),
    ]);
    safetensors::serialize(views, Some(metadata)).expect("safetensors header fits")
}

/// Decodes the canonical form; [`Dataset::new`] checks the columns again (storage may have
/// been damaged).
pub fn decode_canonical(bytes: &[u8]) -> Result<Dataset, ParseError> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| corrupt(format!("unreadable ({e})")))?;
    let scalars = Scalars::of(header.metadata().as_ref())?;
    let tensors =
        SafeTensors::deserialize(bytes).map_err(|e| corrupt(format!("unreadable ({e})")))?;
    decode_columns(&scalars, |name, dtype| match tensors.tensor(name) {
        Ok(view) if view.dtype() == dtype => Ok(Some(Cow::Borrowed(view.data()))),
        Ok(view) => Err(corrupt(format!("`{name}` has dtype {:?}", view.dtype()))),
        Err(_) => Ok(None),
    })
}

fn corrupt(what: String) -> ParseError {
    ParseError::corrupt_canonical(format!("canonical dataset: {what}"))
}

/// The dataset's scalars, from the metadata.
struct Scalars {
    obs_dim: usize,
    action_space: ActionSpace,
}

impl Scalars {
    fn of(meta: Option<&HashMap<String, String>>) -> Result<Scalars, ParseError> {
        let empty = HashMap::new();
        let meta = meta.unwrap_or(&empty);
        let field =
            |key: &str| meta.get(key).ok_or_else(|| corrupt(format!("no `{key}` metadata")));
        if field("format")? != FORMAT_TAG {
            return Err(corrupt("not a safedice dataset".into()));
        }
        let version = field("version")?;
        if version != VERSION {
            return Err(corrupt(format!("version {version}, this build reads {VERSION}")));
        }
        let obs_dim = field("obs_dim")?.parse().map_err(|_| corrupt("bad obs_dim".into()))?;
        let action_space = serde_json::from_str(field("action_space")?)
            .map_err(|e| corrupt(format!("bad action_space ({e})")))?;
        Ok(Scalars { obs_dim, action_space })
    }
}

/// A dataset from its columns' bytes, as `column(name, dtype)` finds them (None: absent),
/// asked for one at a time: each column's bytes are converted and dropped before the next is
/// asked for, so a caller that reads them from storage holds one column's bytes at most.
fn decode_columns<'a>(
    scalars: &Scalars,
    mut column: impl FnMut(&str, Dtype) -> Result<Option<Cow<'a, [u8]>>, ParseError>,
) -> Result<Dataset, ParseError> {
    let mut required = |name: &str, dtype: Dtype| {
        column(name, dtype)?.ok_or_else(|| corrupt(format!("no `{name}` column")))
    };
    let actions = match scalars.action_space {
        ActionSpace::Continuous { .. } => {
            Actions::Continuous(f32s(&required("actions", Dtype::F32)?))
        }
        ActionSpace::Discrete { .. } => Actions::Discrete(u32s(&required("actions", Dtype::U32)?)),
    };
    let terminals = required("terminals", Dtype::U8)?;
    if terminals.iter().any(|&t| t > 1) {
        return Err(corrupt("`terminals` holds a value other than 0/1".into()));
    }
    let terminals = terminals.iter().map(|&t| t == 1).collect();
    let observations = f32s(&required("observations", Dtype::F32)?);
    let next_observations = f32s(&required("next_observations", Dtype::F32)?);
    let episode_ids = u32s(&required("episode_ids", Dtype::U32)?);
    let rewards = column("rewards", Dtype::F32)?.map(|bytes| f32s(&bytes));
    let costs = column("costs", Dtype::F32)?.map(|bytes| f32s(&bytes));
    Dataset::new(DatasetParts {
        obs_dim: scalars.obs_dim,
        action_space: scalars.action_space.clone(),
        observations,
        actions,
        next_observations,
        terminals,
        episode_ids,
        rewards,
        costs,
    })
    .map_err(|e| corrupt(e.to_string()))
}

/// Bytes of the length prefix of a canonical file (safetensors: a little-endian u64).
pub const CANONICAL_PREFIX_BYTES: usize = 8;

/// A canonical file's header, read without its columns: where each column's bytes lie, so the
/// first rows of a large dataset can be read alone (a preview) instead of the whole file.
pub struct CanonicalHeader {
    scalars: Scalars,
    /// Offset of the first column byte in the file.
    data_start: u64,
    columns: HashMap<String, TensorInfo>,
}

/// Length of the JSON header that follows the prefix, from the prefix's 8 bytes.
pub fn canonical_header_len(prefix: [u8; CANONICAL_PREFIX_BYTES]) -> Result<usize, ParseError> {
    let n = u64::from_le_bytes(prefix);
    // safetensors' own bound on a header (100 MB); ours hold a few hundred bytes.
    usize::try_from(n)
        .ok()
        .filter(|&n| n <= 100_000_000)
        .ok_or_else(|| corrupt(format!("header of {n} bytes")))
}

impl CanonicalHeader {
    /// Parses the JSON header (the `header_len` bytes after the prefix) of a file of
    /// `file_len` bytes, checking that every column lies inside it.
    pub fn parse(header: &[u8], file_len: u64) -> Result<CanonicalHeader, ParseError> {
        let metadata: safetensors::tensor::Metadata = serde_json::from_slice(header)
            .map_err(|e| corrupt(format!("unreadable header ({e})")))?;
        let scalars = Scalars::of(metadata.metadata().as_ref())?;
        let data_start = (CANONICAL_PREFIX_BYTES + header.len()) as u64;
        let columns: HashMap<_, _> =
            metadata.tensors().into_iter().map(|(name, info)| (name, info.clone())).collect();
        if columns.values().any(|info| {
            let (begin, end) = info.data_offsets;
            begin > end || data_start.saturating_add(end as u64) > file_len
        }) {
            return Err(corrupt("a column lies outside the file".into()));
        }
        Ok(CanonicalHeader { scalars, data_start, columns })
    }

    /// Transitions in the dataset.
    pub fn rows(&self) -> usize {
        self.columns.get("episode_ids").and_then(|info| info.shape.first().copied()).unwrap_or(0)
    }

    /// The file's byte range holding rows `0..rows` of column `name`, if it has that column.
    pub fn prefix_range(&self, name: &str, rows: usize) -> Option<std::ops::Range<u64>> {
        let info = self.columns.get(name)?;
        let (begin, end) = info.data_offsets;
        let row_bytes = info.shape.iter().skip(1).product::<usize>() * info.dtype.bitsize() / 8;
        let total_rows = info.shape.first().copied().unwrap_or(0);
        let len = (rows.min(total_rows) * row_bytes).min(end - begin);
        let start = self.data_start + begin as u64;
        Some(start..start + len as u64)
    }

    /// Each column's byte range for rows `0..rows`.
    pub fn prefix_ranges(&self, rows: usize) -> Vec<(String, std::ops::Range<u64>)> {
        let mut ranges: Vec<_> = self
            .columns
            .keys()
            .map(|name| {
                (name.clone(), self.prefix_range(name, rows).expect("a column of the header"))
            })
            .collect();
        ranges.sort_by_key(|(_, range)| range.start);
        ranges
    }

    /// The byte ranges of rows `0..rows` of the columns an episode summary reads (terminals,
    /// rewards and costs; the caller has the episode ids).
    pub fn episode_column_ranges(&self, rows: usize) -> Vec<(String, std::ops::Range<u64>)> {
        ["terminals", "rewards", "costs"]
            .into_iter()
            .filter_map(|name| Some((name.to_owned(), self.prefix_range(name, rows)?)))
            .collect()
    }

    /// The episode columns from the episode ids and the bytes over
    /// [`Self::episode_column_ranges`] (every column as long as the ids).
    pub fn decode_episode_columns(
        &self,
        episode_ids: &[u8],
        columns: &HashMap<String, Vec<u8>>,
    ) -> Result<EpisodeColumns, ParseError> {
        let episode_ids = u32s(episode_ids);
        let n = episode_ids.len();
        let terminals =
            columns.get("terminals").ok_or_else(|| corrupt("no `terminals` column".into()))?;
        if terminals.len() != n || terminals.iter().any(|&t| t > 1) {
            return Err(corrupt("`terminals` does not match the episode ids".into()));
        }
        let floats = |name: &str| -> Result<Option<Vec<f32>>, ParseError> {
            match columns.get(name).map(|bytes| f32s(bytes)) {
                Some(values) if values.len() != n => {
                    Err(corrupt(format!("`{name}` does not match the episode ids")))
                }
                found => Ok(found),
            }
        };
        Ok(EpisodeColumns {
            terminals: terminals.iter().map(|&t| t == 1).collect(),
            rewards: floats("rewards")?,
            costs: floats("costs")?,
            episode_ids,
        })
    }

    /// A dataset of the first rows from each column's bytes over its [`Self::prefix_ranges`].
    pub fn decode_prefix(&self, columns: &HashMap<String, Vec<u8>>) -> Result<Dataset, ParseError> {
        decode_columns(&self.scalars, |name, dtype| {
            match (self.columns.get(name), columns.get(name)) {
                (Some(info), Some(_)) if info.dtype != dtype => {
                    Err(corrupt(format!("`{name}` has dtype {:?}", info.dtype)))
                }
                (Some(_), Some(bytes)) => Ok(Some(Cow::Borrowed(bytes.as_slice()))),
                _ => Ok(None),
            }
        })
    }

    /// The whole dataset, each column read with `read` (its byte range in the file) and
    /// converted before the next is read: memory holds the decoded dataset and one column's
    /// bytes, not the file and the dataset.
    pub fn decode_by_column(
        &self,
        mut read: impl FnMut(std::ops::Range<u64>) -> Result<Vec<u8>, ParseError>,
    ) -> Result<Dataset, ParseError> {
        let rows = self.rows();
        decode_columns(&self.scalars, |name, dtype| match self.columns.get(name) {
            Some(info) if info.dtype != dtype => {
                Err(corrupt(format!("`{name}` has dtype {:?}", info.dtype)))
            }
            Some(_) => {
                let range = self.prefix_range(name, rows).expect("a column of the header");
                Ok(Some(Cow::Owned(read(range)?)))
            }
            None => Ok(None),
        })
    }
}

/// Rows to read for a preview of `rows` transitions and `episodes` episodes, from the
/// `episode_ids` column (little-endian u32 bytes): enough for both, never past the end, and at
/// least one (a dataset is never empty).
pub fn preview_rows(episode_ids: &[u8], rows: usize, episodes: usize) -> usize {
    let ids = u32s(episode_ids);
    let mut ended = 0;
    let mut end = ids.len();
    for i in 1..ids.len() {
        if ids[i] != ids[i - 1] {
            ended += 1;
            if ended == episodes {
                end = i;
                break;
            }
        }
    }
    if episodes == 0 {
        end = 0;
    }
    rows.max(end).max(1).min(ids.len())
}

// Columns as little-endian bytes: a borrow on little-endian machines, a copy elsewhere. Decoding
// copies (tensor data in the buffer need not be 4-byte aligned).

fn f32_bytes(values: &[f32]) -> Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        Cow::Borrowed(bytemuck::cast_slice(values))
    } else {
        Cow::Owned(values.iter().flat_map(|v| v.to_le_bytes()).collect())
    }
}

fn u32_bytes(values: &[u32]) -> Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        Cow::Borrowed(bytemuck::cast_slice(values))
    } else {
        Cow::Owned(values.iter().flat_map(|v| v.to_le_bytes()).collect())
    }
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect()
}

fn u32s(bytes: &[u8]) -> Vec<u32> {
    bytes.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes"))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::preview;

    /// Episodes of lengths 1, 2, 3, … (ids not in order), 5-wide observations, with rewards
    /// and costs; continuous or discrete actions.
    fn episodes_of_growing_length(episodes: usize, discrete: bool) -> Dataset {
        let lengths: Vec<usize> = (1..=episodes).collect();
        let n: usize = lengths.iter().sum();
        let episode_ids = lengths
            .iter()
            .enumerate()
            .flat_map(|(e, &len)| std::iter::repeat_n((e as u32 * 7919) % 1000, len))
            .collect();
        let ends: Vec<usize> = lengths
            .iter()
            .scan(0, |at, len| {
                *at += len;
                Some(*at - 1)
            })
            .collect();
        let (action_space, actions) = if discrete {
            (
                ActionSpace::Discrete { n: 3 },
                Actions::Discrete((0..n as u32).map(|i| i % 3).collect()),
            )
        } else {
            let a: Vec<f32> = (0..n * 2).map(|i| (i % 11) as f32 * 0.1 - 0.5).collect();
            (ActionSpace::infer_continuous(&a, 2), Actions::Continuous(a))
        };
        Dataset::new(DatasetParts {
            obs_dim: 5,
            action_space,
            observations: (0..n * 5).map(|i| i as f32 * 0.01).collect(),
            actions,
            next_observations: (0..n * 5).map(|i| i as f32 * 0.01 + 0.05).collect(),
            terminals: (0..n).map(|i| ends.contains(&i) && i % 2 == 0).collect(),
            episode_ids,
            rewards: Some((0..n).map(|i| (i % 5) as f32).collect()),
            costs: Some((0..n).map(|i| (i % 3 == 0) as u8 as f32).collect()),
        })
        .unwrap()
    }

    /// The preview of the prefix read from byte ranges, and the bytes read.
    fn preview_from_ranges(
        bytes: &[u8],
        rows: usize,
        episodes: usize,
    ) -> (preview::DatasetPreview, usize) {
        let mut read = 0;
        let mut take = |range: std::ops::Range<u64>| {
            read += (range.end - range.start) as usize;
            bytes[range.start as usize..range.end as usize].to_vec()
        };
        let prefix: [u8; CANONICAL_PREFIX_BYTES] = take(0..8).try_into().unwrap();
        let header_len = canonical_header_len(prefix).unwrap() as u64;
        let header = CanonicalHeader::parse(&take(8..8 + header_len), bytes.len() as u64).unwrap();
        let ids = take(header.prefix_range("episode_ids", header.rows()).unwrap());
        let summarised = preview_rows(&ids, rows, episodes);
        let head_rows = rows.clamp(1, header.rows());
        let head =
            header.prefix_ranges(head_rows).into_iter().map(|(name, r)| (name, take(r))).collect();
        let head = header.decode_prefix(&head).unwrap();
        let columns: HashMap<_, _> = header
            .episode_column_ranges(summarised)
            .into_iter()
            .map(|(name, r)| (name, take(r)))
            .collect();
        let columns = header.decode_episode_columns(&ids[..summarised * 4], &columns).unwrap();
        (preview::preview_parts(&head, rows, &columns, episodes), read)
    }

    #[test]
    fn a_preview_from_the_first_rows_equals_the_preview_of_the_whole_dataset() {
        for discrete in [false, true] {
            let d = episodes_of_growing_length(40, discrete);
            let bytes = encode_canonical(&d);
            for (rows, episodes) in
                [(0, 0), (10, 0), (0, 5), (3, 5), (100, 1), (0, 1000), (100, 39), (820, 40)]
            {
                let (from_ranges, _) = preview_from_ranges(&bytes, rows, episodes);
                assert_eq!(
                    from_ranges,
                    preview::preview(&d, rows, episodes),
                    "{rows} rows, {episodes} episodes"
                );
            }
        }
    }

    #[test]
    fn a_preview_of_every_episode_reads_no_observation_beyond_the_rows_shown() {
        let d = episodes_of_growing_length(400, false);
        let bytes = encode_canonical(&d);
        let (shown, read) = preview_from_ranges(&bytes, 10, 1000);
        assert_eq!(shown, preview::preview(&d, 10, 1000));
        // Ids (4), terminal (1), reward (4), cost (4) per transition, and 10 whole rows.
        assert!(read < 13 * d.len() + 2000 + 10 * 57, "read {read} of {} bytes", bytes.len());
    }

    #[test]
    fn a_preview_reads_the_rows_it_shows_and_the_episode_ids_not_the_whole_file() {
        let d = episodes_of_growing_length(400, false); // 80,200 transitions
        let bytes = encode_canonical(&d);
        let (shown, read) = preview_from_ranges(&bytes, 10, 20);
        assert_eq!((shown.transitions.len(), shown.episodes.len()), (10, 20));
        // The first 20 episodes hold 210 rows; the ids are 4 bytes per transition.
        // Beyond the ids: the header, 10 rows of 57 bytes (observations and next ones 20 each,
        // actions 8, terminal 1, reward 4, cost 4) and the 210 rows of the first 20 episodes'
        // terminals, rewards and costs.
        let beyond_ids = read - 4 * d.len();
        assert!(beyond_ids < 2000 + 10 * 57 + 210 * 9, "read {beyond_ids} bytes beyond the ids");
        assert!(read * 10 < bytes.len(), "read {read} of {} bytes", bytes.len());
    }

    #[test]
    fn a_dataset_decoded_column_by_column_is_the_one_encoded() {
        for discrete in [false, true] {
            let d = episodes_of_growing_length(30, discrete);
            let bytes = encode_canonical(&d);
            let prefix: [u8; CANONICAL_PREFIX_BYTES] = bytes[..8].try_into().unwrap();
            let header_len = canonical_header_len(prefix).unwrap();
            let header =
                CanonicalHeader::parse(&bytes[8..8 + header_len], bytes.len() as u64).unwrap();
            let mut largest = 0;
            let decoded = header
                .decode_by_column(|r| {
                    largest = largest.max(r.end - r.start);
                    Ok(bytes[r.start as usize..r.end as usize].to_vec())
                })
                .unwrap();
            assert_eq!(decoded, d);
            assert_eq!(decoded, decode_canonical(&bytes).unwrap());
            // One observation column at a time, never the file.
            assert!(largest as usize <= d.len() * 5 * 4, "{largest}");
        }
    }
}
