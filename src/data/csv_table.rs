//! CSV with a header: `episode, obs_0..obs_{d-1}, act_0..act_{k-1}` (or `action` for a discrete
//! action), optional `next_obs_0..next_obs_{d-1}`, `terminal`, `reward`, `cost`. Columns may come
//! in any order; unknown or duplicated columns are rejected. Streamed record by record.

use std::collections::HashMap;
use std::io::Read;

use super::error::ParseError;
use super::model::Dataset;
use super::rows::{Row, RowAction, RowAssembler};

/// Where each field lives in a record.
struct Columns {
    episode: usize,
    obs: Vec<usize>,
    action: ActionColumns,
    next_obs: Option<Vec<usize>>,
    terminal: Option<usize>,
    reward: Option<usize>,
    cost: Option<usize>,
}

enum ActionColumns {
    Continuous(Vec<usize>),
    Discrete(usize),
}

pub fn parse(reader: impl Read) -> Result<Dataset, ParseError> {
    let mut csv = ::csv::ReaderBuilder::new().trim(::csv::Trim::All).from_reader(reader);
    let header = csv.byte_headers().map_err(csv_error)?.clone();
    if header.is_empty() || header.iter().all(|h| h.is_empty()) {
        return Err(ParseError::empty("the CSV file is empty (no header line)"));
    }
    let columns = Columns::from_header(&header)?;
    let mut rows = RowAssembler::new();
    let mut record = ::csv::ByteRecord::new();
    let (mut obs, mut action, mut next_obs) = (Vec::new(), Vec::new(), Vec::new());
    while csv.read_byte_record(&mut record).map_err(csv_error)? {
        let line = record.position().map_or(0, |p| p.line() as usize);
        let field = |i: usize| Field { line, name: &header[i], text: &record[i] };
        read_floats(&columns.obs, &field, &mut obs)?;
        let row_action = match &columns.action {
            ActionColumns::Continuous(cols) => {
                read_floats(cols, &field, &mut action)?;
                RowAction::Continuous(&action)
            }
            ActionColumns::Discrete(col) => RowAction::Discrete(field(*col).index()?),
        };
        let has_next = match &columns.next_obs {
            Some(cols) => read_optional_floats(cols, &field, &mut next_obs)?,
            None => false,
        };
        let optional_float = |col: Option<usize>| -> Result<Option<f32>, ParseError> {
            match col.map(field) {
                Some(f) if !f.text.is_empty() => f.float().map(Some),
                _ => Ok(None),
            }
        };
        let terminal = match columns.terminal.map(field) {
            Some(f) if !f.text.is_empty() => f.flag()?,
            _ => false,
        };
        rows.push(
            line,
            Row {
                episode: field(columns.episode).episode()?,
                obs: &obs,
                action: row_action,
                next_obs: has_next.then_some(next_obs.as_slice()),
                terminal,
                reward: optional_float(columns.reward)?,
                cost: optional_float(columns.cost)?,
            },
        )?;
    }
    rows.finish()
}

impl Columns {
    fn from_header(header: &::csv::ByteRecord) -> Result<Columns, ParseError> {
        let mut named: HashMap<String, usize> = HashMap::new();
        let mut obs = HashMap::new();
        let mut act = HashMap::new();
        let mut next = HashMap::new();
        for (i, raw) in header.iter().enumerate() {
            let name = std::str::from_utf8(raw)
                .map_err(|_| ParseError::invalid(format!("header column {} is not UTF-8", i + 1)))?
                .trim_start_matches('\u{feff}')
                .to_string();
            let indexed = [("next_obs_", &mut next), ("obs_", &mut obs), ("act_", &mut act)]
                .into_iter()
                .find_map(|(prefix, map)| {
                    name.strip_prefix(prefix)
                        .and_then(|s| s.parse::<usize>().ok())
                        .map(|j| (map, j))
                });
            let duplicate = match indexed {
                Some((map, j)) => map.insert(j, i).is_some(),
                None => match name.as_str() {
                    "episode" | "action" | "terminal" | "reward" | "cost" => {
                        named.insert(name.clone(), i).is_some()
                    }
                    _ => {
                        let hint = if name.is_empty() || name.starts_with("Unnamed") {
                            " (a pandas index column? write the file with index=False)"
                        } else {
                            ""
                        };
                        return Err(ParseError::invalid(format!(
                            "header: unknown column `{name}`{hint}; expected episode, obs_0.., \
                             act_0.. or action, and optionally next_obs_0.., terminal, reward, \
                             cost"
                        )));
                    }
                },
            };
            if duplicate {
                return Err(ParseError::invalid(format!("header: column `{name}` appears twice")));
            }
        }
        let episode = *named.get("episode").ok_or_else(|| {
            ParseError::invalid("header: missing the `episode` column (the episode id of each row)")
        })?;
        let obs = numbered(obs, "obs_")?;
        if obs.is_empty() {
            return Err(ParseError::invalid("header: no observation columns obs_0, obs_1, ..."));
        }
        let act = numbered(act, "act_")?;
        let action = match (named.get("action"), act.is_empty()) {
            (Some(&col), true) => ActionColumns::Discrete(col),
            (None, false) => ActionColumns::Continuous(act),
            (Some(_), false) => {
                return Err(ParseError::invalid(
                    "header: both `action` (discrete) and act_* (continuous) columns; mixed \
                     discrete and continuous actions are not allowed, keep one kind",
                ))
            }
            (None, true) => {
                return Err(ParseError::invalid(
                    "header: no action columns; use act_0, act_1, ... for a continuous action \
                     or `action` for a discrete one",
                ))
            }
        };
        let next = numbered(next, "next_obs_")?;
        let next_obs = match next.len() {
            0 => None,
            n if n == obs.len() => Some(next),
            n => {
                return Err(ParseError::invalid(format!(
                    "header: {n} next_obs_* columns but {} obs_* columns; they must match",
                    obs.len()
                )))
            }
        };
        Ok(Columns {
            episode,
            obs,
            action,
            next_obs,
            terminal: named.get("terminal").copied(),
            reward: named.get("reward").copied(),
            cost: named.get("cost").copied(),
        })
    }
}

/// Column indices of `prefix0..prefix{n-1}`, which must be numbered without gaps.
fn numbered(map: HashMap<usize, usize>, prefix: &str) -> Result<Vec<usize>, ParseError> {
    (0..map.len())
        .map(|j| {
            map.get(&j).copied().ok_or_else(|| {
                ParseError::invalid(format!(
                    "header: column `{prefix}{j}` is missing; {prefix}* columns must be numbered \
                     0..{} without gaps",
                    map.len()
                ))
            })
        })
        .collect()
}

/// One cell with what an error message needs.
struct Field<'a> {
    line: usize,
    name: &'a [u8],
    text: &'a [u8],
}

impl Field<'_> {
    fn error(&self, what: &str) -> ParseError {
        ParseError::invalid(format!(
            "line {}, column `{}`: {what}",
            self.line,
            String::from_utf8_lossy(self.name)
        ))
    }

    fn str(&self) -> Result<&str, ParseError> {
        std::str::from_utf8(self.text).map_err(|_| self.error("not UTF-8 text"))
    }

    fn float(&self) -> Result<f32, ParseError> {
        let text = self.str()?;
        let value: f32 =
            text.parse().map_err(|_| self.error(&format!("`{text}` is not a number")))?;
        if !value.is_finite() {
            return Err(self.error(&format!("`{text}` is not a finite number (NaN/Inf rejected)")));
        }
        Ok(value)
    }

    /// A non-negative integer; `3.0` is accepted too, since pandas writes integer columns that
    /// way once they held a missing value.
    fn integer(&self, what: &str) -> Result<u64, ParseError> {
        let text = self.str()?;
        let integral_float = || {
            text.parse::<f64>()
                .ok()
                .filter(|v| v.fract() == 0.0 && *v >= 0.0 && *v < 2f64.powi(53))
                .map(|v| v as u64)
        };
        text.parse()
            .ok()
            .or_else(integral_float)
            .ok_or_else(|| self.error(&format!("`{text}` is not {what}")))
    }

    fn index(&self) -> Result<u64, ParseError> {
        self.integer(
            "a non-negative integer (a discrete action; use act_0.. columns for continuous ones)",
        )
    }

    fn episode(&self) -> Result<u32, ParseError> {
        let id = self.integer("a non-negative integer episode id")?;
        u32::try_from(id).map_err(|_| self.error(&format!("episode id {id} exceeds {}", u32::MAX)))
    }

    fn flag(&self) -> Result<bool, ParseError> {
        match self.str()?.to_ascii_lowercase().as_str() {
            "1" | "1.0" | "true" => Ok(true),
            "0" | "0.0" | "false" => Ok(false),
            other => Err(self.error(&format!("`{other}` is not a flag (true/false/1/0)"))),
        }
    }
}

fn read_floats<'a>(
    cols: &[usize],
    field: &impl Fn(usize) -> Field<'a>,
    out: &mut Vec<f32>,
) -> Result<(), ParseError> {
    out.clear();
    for &c in cols {
        let f = field(c);
        if f.text.is_empty() {
            return Err(f.error("empty cell"));
        }
        out.push(f.float()?);
    }
    Ok(())
}

/// `next_obs_*`: all cells empty means "take it from the next row"; some empty is an error.
fn read_optional_floats<'a>(
    cols: &[usize],
    field: &impl Fn(usize) -> Field<'a>,
    out: &mut Vec<f32>,
) -> Result<bool, ParseError> {
    if cols.iter().all(|&c| field(c).text.is_empty()) {
        return Ok(false);
    }
    read_floats(cols, field, out)?;
    Ok(true)
}

fn csv_error(err: ::csv::Error) -> ParseError {
    let line = err.position().map(|p| p.line());
    let message = match err.kind() {
        ::csv::ErrorKind::UnequalLengths { expected_len, len, .. } => {
            format!("has {len} fields but the header has {expected_len} (ragged rows are rejected)")
        }
        ::csv::ErrorKind::Utf8 { .. } => "is not UTF-8 text".to_string(),
        _ => err.to_string(),
    };
    match line {
        Some(line) => ParseError::invalid(format!("line {line}: {message}")),
        None => ParseError::invalid(format!("CSV: {message}")),
    }
}
