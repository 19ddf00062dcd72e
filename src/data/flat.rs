//! The flat array layout of the offline-RL ecosystem (D4RL / DSRL / OmniSafe), shared by the NPZ
//! and HDF5 readers: `observations` (N×d), `actions` (N×k floats or N integers),
//! `terminals` (N), optional `next_observations` (N×d), `timeouts` (N), `rewards` (N),
//! `costs` (N), `init_obs` (M×d). Episodes end at `terminals | timeouts` (and at the end of the
//! file). OmniSafe's short names (`obs`, `action`, `next_obs`, `done`, `reward`, `cost`) are
//! accepted too.
//!
//! Without `next_observations` (D4RL's own files, d3rlpy's layout) each transition's next
//! observation is the next row's in its episode; the last transition of an episode that is not
//! terminal (a timeout) has no successor in the file and is dropped, as D4RL's
//! `qlearning_dataset` does, and the dataset says so in its warnings.
//!
//! Optional keys this service writes so that a round trip is exact (other tools ignore them):
//! `episode_ids` (N integers; when present they define the episodes and every terminal/timeout
//! must end one), `action_low` / `action_high` (k floats, the continuous box) and `action_n`
//! (the number of discrete actions). `init_obs` is validated (M×d, finite) but the initial-state
//! set is always the first observation of each episode.

use super::error::ParseError;
use super::model::{ActionSpace, Actions, Dataset, DatasetParts};
use super::rows::MAX_DISCRETE_ACTIONS;

/// One array read from a container, converted to one of three element kinds.
pub struct Array {
    pub shape: Vec<usize>,
    pub data: ArrayData,
}

pub enum ArrayData {
    /// Any float dtype, converted to f32 (checked finite after conversion).
    Float(Vec<f32>),
    /// Any integer dtype.
    Int(Vec<i64>),
    Bool(Vec<bool>),
}

/// Bounds the decoded size of a compressed container relative to its size on disk, so that a
/// small archive cannot expand into an unbounded allocation (a zip / gzip bomb). Generous for
/// real data: a column of all-false terminals compresses ~1000x, but it is small next to the
/// observations.
pub struct DecodeBudget {
    left: u64,
}

impl DecodeBudget {
    const PER_FILE_BYTE: u64 = 64;
    const ALLOWANCE: u64 = 256 << 20;

    pub fn for_file(path: &std::path::Path) -> Result<DecodeBudget, ParseError> {
        let bytes = std::fs::metadata(path).map_err(|e| ParseError::io("reading the upload", e))?;
        Ok(DecodeBudget {
            left: bytes.len().saturating_mul(Self::PER_FILE_BYTE).saturating_add(Self::ALLOWANCE),
        })
    }

    /// Refuses an entry whose declared (uncompressed) size alone is beyond what is left, before
    /// anything of it is read.
    pub fn check_declared(&self, key: &str, declared_bytes: u64) -> Result<(), ParseError> {
        if declared_bytes > self.left {
            return Err(ParseError::invalid(format!(
                "key `{key}` declares {declared_bytes} bytes uncompressed, far more than the \
                 file's size suggests; refusing (corrupt or malicious file)"
            )));
        }
        Ok(())
    }

    /// Reserves `count` elements of `element_bytes` for `key`, or refuses.
    pub fn take(&mut self, key: &str, count: u64, element_bytes: u64) -> Result<(), ParseError> {
        let bytes = count.saturating_mul(element_bytes);
        if bytes > self.left {
            return Err(ParseError::invalid(format!(
                "key `{key}` would decode to {bytes} bytes, far more than the file's size \
                 suggests; refusing (corrupt or malicious file)"
            )));
        }
        self.left -= bytes;
        Ok(())
    }
}

/// A container of named arrays (an NPZ archive, an HDF5 file).
pub trait ArraySource {
    /// `Ok(None)` when the key is absent.
    fn read(&mut self, key: &str) -> Result<Option<Array>, ParseError>;
}

const OBSERVATIONS: &[&str] = &["observations", "obs"];
const ACTIONS: &[&str] = &["actions", "action"];
const NEXT_OBSERVATIONS: &[&str] = &["next_observations", "next_obs"];
const TERMINALS: &[&str] = &["terminals", "terminal", "dones", "done"];

/// Reads the first present key of `names`.
fn read_any(
    source: &mut impl ArraySource,
    names: &[&'static str],
) -> Result<Option<(&'static str, Array)>, ParseError> {
    for &name in names {
        if let Some(array) = source.read(name)? {
            return Ok(Some((name, array)));
        }
    }
    Ok(None)
}

fn require(
    source: &mut impl ArraySource,
    names: &[&'static str],
    what: &str,
) -> Result<(&'static str, Array), ParseError> {
    read_any(source, names)?
        .ok_or_else(|| ParseError::invalid(format!("missing required key `{}` ({what})", names[0])))
}

pub fn assemble(source: &mut impl ArraySource) -> Result<Dataset, ParseError> {
    let (key, obs) = require(source, OBSERVATIONS, "N×d observations")?;
    let (n, obs_dim, observations) = float_matrix(key, obs)?;
    if n == 0 {
        return Err(ParseError::empty(format!(
            "`{key}` has no rows: the file holds no transitions"
        )));
    }
    let next_observations = match read_any(source, NEXT_OBSERVATIONS)? {
        Some((key, next)) => Some(float_matrix_like(key, next, n, obs_dim)?),
        None => None,
    };
    let (key, actions) = require(source, ACTIONS, "N×k floats or N integers")?;
    let (actions, action_dim) = action_column(key, actions, n)?;
    let (key, terminals) = require(source, TERMINALS, "N flags")?;
    let terminals = flag_column(key, terminals, n)?;
    let timeouts = match source.read("timeouts")? {
        Some(array) => Some(flag_column("timeouts", array, n)?),
        None => None,
    };
    let rewards = optional_scalars(source, &["rewards", "reward"], n)?;
    let costs = optional_scalars(source, &["costs", "cost"], n)?;
    if let Some(init) = source.read("init_obs")? {
        let (_, dim, _) = float_matrix("init_obs", init)?;
        if dim != obs_dim {
            return Err(ParseError::invalid(format!(
                "key `init_obs` has {dim} columns but observations have {obs_dim}"
            )));
        }
    }
    let (episode_ids, ends_marked) = match source.read("episode_ids")? {
        Some(ids) => (given_episode_ids(ids, n, &terminals, timeouts.as_deref())?, true),
        None => {
            let marked = terminals.iter().chain(timeouts.iter().flatten()).any(|&end| end);
            (split_episodes(&terminals, timeouts.as_deref()), marked)
        }
    };
    let action_space = action_space(source, &actions, action_dim)?;
    let derive = next_observations.is_none();
    let parts = DatasetParts {
        obs_dim,
        action_space,
        next_observations: next_observations.unwrap_or_default(),
        observations,
        actions,
        terminals,
        episode_ids,
        rewards,
        costs,
    };
    let mut warnings = Vec::new();
    if !ends_marked && n > 1 {
        warnings.push(format!(
            "no transition is marked terminal or timeout and there are no `episode_ids`, so \
             the {n} transitions are read as one episode; if the file holds several, mark where \
             each ends"
        ));
    }
    let parts = if derive {
        let (parts, dropped) = derive_next_observations(parts)?;
        warnings.push(derived_warning(n, dropped));
        parts
    } else {
        parts
    };
    let dataset = Dataset::new(parts)?;
    Ok(warnings.into_iter().fold(dataset, Dataset::with_warning))
}

fn derived_warning(n: usize, dropped: usize) -> String {
    let derived = "no `next_observations`: each transition's next observation is the next row's \
         observation in its episode (a terminal transition's is its own, never used)";
    match dropped {
        0 => derived.to_owned(),
        d => format!(
            "{derived}; {d} of the {n} transitions end an episode without being terminal (a \
             timeout, or the end of the file), so their next observation is not in the file: \
             they were dropped"
        ),
    }
}

/// Fills `next_observations` from the next row of the same episode. The last transition of an
/// episode gets its own observation when it is terminal (its successor is never bootstrapped
/// from), and is dropped when it is not: a timeout's successor state is not in the file, and
/// any made-up value would be trained on. Returns the columns and how many rows were dropped.
fn derive_next_observations(parts: DatasetParts) -> Result<(DatasetParts, usize), ParseError> {
    let n = parts.terminals.len();
    let d = parts.obs_dim;
    let ids = &parts.episode_ids;
    let ends_episode = |i: usize| i + 1 == n || ids[i + 1] != ids[i];
    let keep: Vec<bool> = (0..n).map(|i| !ends_episode(i) || parts.terminals[i]).collect();
    let kept = keep.iter().filter(|&&k| k).count();
    if kept == 0 {
        return Err(ParseError::empty(
            "no `next_observations`, and every transition ends an episode without being \
             terminal, so no transition's next observation is in the file",
        ));
    }
    let mut next = Vec::with_capacity(kept * d);
    for i in (0..n).filter(|&i| keep[i]) {
        let from = if ends_episode(i) { i } else { i + 1 };
        next.extend_from_slice(&parts.observations[from * d..(from + 1) * d]);
    }
    let rows = |values: Vec<f32>, width: usize| -> Vec<f32> {
        let chunks = values.chunks_exact(width.max(1)).zip(&keep);
        chunks.filter(|(_, &k)| k).flat_map(|(row, _)| row.iter().copied()).collect()
    };
    let flags =
        |values: Vec<bool>| values.into_iter().zip(&keep).filter(|(_, &k)| k).map(|(v, _)| v);
    let actions = match parts.actions {
        Actions::Continuous(values) => {
            Actions::Continuous(rows(values, parts.action_space.width()))
        }
        Actions::Discrete(values) => Actions::Discrete(
            values.into_iter().zip(&keep).filter(|(_, &k)| k).map(|(v, _)| v).collect(),
        ),
    };
    let episode_ids = parts.episode_ids.iter().zip(&keep).filter(|(_, &k)| k).map(|(&v, _)| v);
    let parts = DatasetParts {
        observations: rows(parts.observations, d),
        next_observations: next,
        actions,
        terminals: flags(parts.terminals).collect(),
        episode_ids: episode_ids.collect(),
        rewards: parts.rewards.map(|r| rows(r, 1)),
        costs: parts.costs.map(|c| rows(c, 1)),
        ..parts
    };
    Ok((parts, n - kept))
}

/// A finite float matrix N×d (a 1-D array is N×1).
fn float_matrix(key: &str, array: Array) -> Result<(usize, usize, Vec<f32>), ParseError> {
    let (n, d) = match array.shape[..] {
        [n] => (n, 1),
        [n, d] => (n, d),
        ref other => {
            return Err(ParseError::invalid(format!(
                "key `{key}` has shape {other:?}; expected (N, d)"
            )))
        }
    };
    let values = match array.data {
        ArrayData::Float(v) => v,
        ArrayData::Int(_) | ArrayData::Bool(_) => {
            return Err(ParseError::invalid(format!(
                "key `{key}` has an integer/bool dtype; expected float32 or float64"
            )))
        }
    };
    check_finite(key, &values, d)?;
    if d == 0 && n > 0 {
        return Err(ParseError::invalid(format!("key `{key}` has zero columns")));
    }
    Ok((n, d, values))
}

fn float_matrix_like(key: &str, array: Array, n: usize, d: usize) -> Result<Vec<f32>, ParseError> {
    let (rows, cols, values) = float_matrix(key, array)?;
    if (rows, cols) != (n, d) {
        return Err(ParseError::invalid(format!(
            "key `{key}` has shape ({rows}, {cols}) but observations have ({n}, {d})"
        )));
    }
    Ok(values)
}

fn check_finite(key: &str, values: &[f32], width: usize) -> Result<(), ParseError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(ParseError::invalid(format!(
            "key `{key}`: row {} holds {}, not a finite number (NaN and Inf are rejected)",
            i / width.max(1),
            values[i]
        ))),
    }
}

/// Floats are continuous actions (N×k or N), integers discrete ones (N or N×1).
/// Returns the column and its width (1 for discrete).
fn action_column(key: &str, array: Array, n: usize) -> Result<(Actions, usize), ParseError> {
    let rows = array.shape.first().copied().unwrap_or(0);
    if rows != n {
        return Err(ParseError::invalid(format!(
            "key `{key}` has {rows} rows but observations have {n}"
        )));
    }
    match array.data {
        ArrayData::Float(_) => {
            let (_, dim, values) = float_matrix(key, array)?;
            Ok((Actions::Continuous(values), dim))
        }
        ArrayData::Int(values) => {
            if !matches!(array.shape[..], [_] | [_, 1]) {
                return Err(ParseError::invalid(format!(
                    "key `{key}` holds integers of shape {:?}: discrete actions must be one \
                     index per row (N or N×1); store continuous actions as floats (mixed \
                     discrete and continuous actions are not allowed)",
                    array.shape
                )));
            }
            let bad = values.iter().position(|&a| a < 0 || a as u64 >= MAX_DISCRETE_ACTIONS);
            if let Some(i) = bad {
                return Err(ParseError::invalid(format!(
                    "key `{key}`: row {i} holds discrete action {}, outside 0..{MAX_DISCRETE_ACTIONS}",
                    values[i]
                )));
            }
            Ok((Actions::Discrete(values.into_iter().map(|a| a as u32).collect()), 1))
        }
        ArrayData::Bool(_) => Err(ParseError::invalid(format!(
            "key `{key}` has a bool dtype; expected floats (continuous) or integers (discrete)"
        ))),
    }
}

/// A length-N flag column from bool, integer or float storage (values must be 0 or 1).
fn flag_column(key: &str, array: Array, n: usize) -> Result<Vec<bool>, ParseError> {
    if !matches!(array.shape[..], [rows] | [rows, 1] if rows == n) {
        return Err(ParseError::invalid(format!(
            "key `{key}` has shape {:?}; expected ({n},) like the observations",
            array.shape
        )));
    }
    let not_flag = |i: usize, v: String| {
        ParseError::invalid(format!("key `{key}`: row {i} holds {v}; flags must be 0 or 1"))
    };
    match array.data {
        ArrayData::Bool(v) => Ok(v),
        ArrayData::Int(v) => v
            .iter()
            .enumerate()
            .map(
                |(i, &x)| {
                    if x == 0 || x == 1 {
                        Ok(x == 1)
                    } else {
                        Err(not_flag(i, x.to_string()))
                    }
                },
            )
            .collect(),
        ArrayData::Float(v) => {
            v.iter()
                .enumerate()
                .map(|(i, &x)| {
                    if x == 0.0 || x == 1.0 {
                        Ok(x == 1.0)
                    } else {
                        Err(not_flag(i, x.to_string()))
                    }
                })
                .collect()
        }
    }
}

fn optional_scalars(
    source: &mut impl ArraySource,
    names: &[&'static str],
    n: usize,
) -> Result<Option<Vec<f32>>, ParseError> {
    let Some((key, array)) = read_any(source, names)? else { return Ok(None) };
    let (rows, cols, values) = float_matrix(key, array)?;
    if (rows, cols) != (n, 1) {
        return Err(ParseError::invalid(format!(
            "key `{key}` has shape ({rows}, {cols}); expected ({n},) like the observations"
        )));
    }
    Ok(Some(values))
}

/// Episode ids 0, 1, ... split after every terminal or timeout.
fn split_episodes(terminals: &[bool], timeouts: Option<&[bool]>) -> Vec<u32> {
    let mut ids = Vec::with_capacity(terminals.len());
    let mut id = 0u32;
    for (i, &terminal) in terminals.iter().enumerate() {
        ids.push(id);
        if terminal || timeouts.is_some_and(|t| t[i]) {
            id += 1;
        }
    }
    ids
}

/// Explicit `episode_ids`: contiguity is checked by `Dataset::new`; here every terminal or
/// timeout must end its episode.
fn given_episode_ids(
    array: Array,
    n: usize,
    terminals: &[bool],
    timeouts: Option<&[bool]>,
) -> Result<Vec<u32>, ParseError> {
    let ids = match array.data {
        ArrayData::Int(v) if matches!(array.shape[..], [rows] if rows == n) => v,
        _ => {
            return Err(ParseError::invalid(format!(
                "key `episode_ids` must hold {n} integers (one per transition)"
            )))
        }
    };
    if let Some(i) = ids.iter().position(|&id| u32::try_from(id).is_err()) {
        return Err(ParseError::invalid(format!(
            "key `episode_ids`: row {i} holds {}, not an id in 0..{}",
            ids[i],
            u32::MAX
        )));
    }
    for i in 0..n.saturating_sub(1) {
        let ends = terminals[i] || timeouts.is_some_and(|t| t[i]);
        if ends && ids[i] == ids[i + 1] {
            return Err(ParseError::invalid(format!(
                "key `episode_ids`: row {i} is terminal or a timeout but episode {} continues \
                 at row {}",
                ids[i],
                i + 1
            )));
        }
    }
    Ok(ids.into_iter().map(|id| id as u32).collect())
}

/// The box from `action_low`/`action_high`, the count from `action_n`, else inferred.
fn action_space(
    source: &mut impl ArraySource,
    actions: &Actions,
    dim: usize,
) -> Result<ActionSpace, ParseError> {
    match actions {
        Actions::Continuous(values) => {
            let low = source.read("action_low")?;
            let high = source.read("action_high")?;
            match (low, high) {
                (None, None) => Ok(ActionSpace::infer_continuous(values, dim)),
                (Some(low), Some(high)) => {
                    let (_, _, low) = float_matrix("action_low", low)?;
                    let (_, _, high) = float_matrix("action_high", high)?;
                    let ordered = low.iter().zip(&high).all(|(l, h)| l < h);
                    if low.len() != dim || high.len() != dim || !ordered {
                        return Err(ParseError::invalid(format!(
                            "keys `action_low` / `action_high` must each hold {dim} values (the \
                             action width) with low < high"
                        )));
                    }
                    Ok(ActionSpace::Continuous { dim, low, high })
                }
                _ => {
                    Err(ParseError::invalid("give both `action_low` and `action_high`, or neither"))
                }
            }
        }
        Actions::Discrete(values) => {
            let seen = values.iter().max().map_or(1, |&m| m as usize + 1);
            match source.read("action_n")? {
                None => Ok(ActionSpace::Discrete { n: seen }),
                Some(Array { data: ArrayData::Int(v), .. }) if v.len() == 1 => {
                    let n = v[0];
                    if n < seen as i64 || n as u64 > MAX_DISCRETE_ACTIONS {
                        return Err(ParseError::invalid(format!(
                            "key `action_n` is {n} but actions go up to {}",
                            seen - 1
                        )));
                    }
                    Ok(ActionSpace::Discrete { n: n as usize })
                }
                Some(_) => Err(ParseError::invalid("key `action_n` must be one integer")),
            }
        }
    }
}
