//! JSONL: one transition per line,
//! `{"episode": 3, "obs": [..], "action": [..] | 2, "next_obs": [..], "terminal": false,
//!   "reward": 1.0, "cost": 0.0}`; `next_obs`, `terminal`, `reward`, `cost` optional.
//! Streamed line by line: memory is the columns plus one line.

use std::fmt;
use std::io::BufRead;

use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::Deserialize;

use super::error::ParseError;
use super::model::Dataset;
use super::rows::{Row, RowAction, RowAssembler};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonRow {
    episode: u32,
    obs: Vec<f32>,
    action: JsonAction,
    #[serde(default)]
    next_obs: Option<Vec<f32>>,
    #[serde(default, deserialize_with = "flag")]
    terminal: Option<bool>,
    #[serde(default)]
    reward: Option<f32>,
    #[serde(default)]
    cost: Option<f32>,
}

/// An integer is a discrete action, a list a continuous one; anything else is explained.
enum JsonAction {
    Continuous(Vec<f32>),
    Discrete(u64),
}

impl<'de> Deserialize<'de> for JsonAction {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct ActionVisitor;
        impl<'de> Visitor<'de> for ActionVisitor {
            type Value = JsonAction;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a list of numbers (continuous) or a non-negative integer (discrete)")
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<JsonAction, E> {
                Ok(JsonAction::Discrete(v))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<JsonAction, E> {
                Err(E::custom(format!("discrete action {v} is negative; actions are 0..n")))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<JsonAction, E> {
                Err(E::custom(format!(
                    "action {v} is a bare number that is not an integer; write a continuous \
                     action as a list ([{v}]) or a discrete one as an integer"
                )))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<JsonAction, A::Error> {
                let mut values = Vec::with_capacity(seq.size_hint().unwrap_or(8));
                while let Some(v) = seq.next_element::<f32>()? {
                    values.push(v);
                }
                Ok(JsonAction::Continuous(values))
            }
        }
        deserializer.deserialize_any(ActionVisitor)
    }
}

/// `terminal` as written by JSON tools and by numpy-minded ones: `true`/`false`, `0`/`1`.
fn flag<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<bool>, D::Error> {
    struct FlagVisitor;
    impl<'de> Visitor<'de> for FlagVisitor {
        type Value = Option<bool>;
        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("true, false, 0 or 1")
        }
        fn visit_bool<E: de::Error>(self, v: bool) -> Result<Option<bool>, E> {
            Ok(Some(v))
        }
        fn visit_u64<E: de::Error>(self, v: u64) -> Result<Option<bool>, E> {
            match v {
                0 | 1 => Ok(Some(v == 1)),
                _ => Err(E::custom(format!("`terminal` is {v}; expected true, false, 0 or 1"))),
            }
        }
        fn visit_f64<E: de::Error>(self, v: f64) -> Result<Option<bool>, E> {
            match v {
                0.0 => Ok(Some(false)),
                1.0 => Ok(Some(true)),
                _ => Err(E::custom(format!("`terminal` is {v}; expected true, false, 0 or 1"))),
            }
        }
        fn visit_unit<E: de::Error>(self) -> Result<Option<bool>, E> {
            Ok(None)
        }
    }
    deserializer.deserialize_any(FlagVisitor)
}

/// Parses a JSONL stream (the file is read once, line by line).
pub fn parse(reader: impl BufRead) -> Result<Dataset, ParseError> {
    let mut reader = reader;
    let mut rows = RowAssembler::new();
    let mut line = Vec::with_capacity(4096);
    let mut number = 0;
    loop {
        line.clear();
        let read = reader
            .read_until(b'\n', &mut line)
            .map_err(|e| ParseError::io(&format!("line {}", number + 1), e))?;
        if read == 0 {
            break;
        }
        number += 1;
        let text = strip_bom(number, &line);
        if text.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        let row: JsonRow =
            serde_path_to_error::deserialize(&mut serde_json::Deserializer::from_slice(text))
                .map_err(|e| json_error(number, text, e))?;
        let action = match &row.action {
            JsonAction::Continuous(a) => RowAction::Continuous(a),
            JsonAction::Discrete(a) => RowAction::Discrete(*a),
        };
        rows.push(
            number,
            Row {
                episode: row.episode,
                obs: &row.obs,
                action,
                next_obs: row.next_obs.as_deref(),
                terminal: row.terminal.unwrap_or(false),
                reward: row.reward,
                cost: row.cost,
            },
        )?;
    }
    rows.finish()
}

fn strip_bom(number: usize, line: &[u8]) -> &[u8] {
    match line.strip_prefix(b"\xEF\xBB\xBF".as_slice()) {
        Some(rest) if number == 1 => rest,
        _ => line,
    }
}

/// serde_json's message without its "at line 1 column N" (we parse one line at a time), with
/// our line number, the field it was in (`obs`[1]: a number beyond f32's range is refused
/// there), and a hint for the most common cause, Python's `NaN` / `Infinity` tokens.
fn json_error(
    number: usize,
    text: &[u8],
    err: serde_path_to_error::Error<serde_json::Error>,
) -> ParseError {
    let field = field_of(err.path());
    let err = err.into_inner();
    let full = err.to_string();
    let suffix = format!(" at line {} column {}", err.line(), err.column());
    let message = full.strip_suffix(&suffix).unwrap_or(&full);
    let text = String::from_utf8_lossy(text);
    let hint = if ["NaN", "Infinity"].iter().any(|t| text.contains(t)) {
        " (NaN and Infinity are not valid JSON and non-finite values are rejected)"
    } else if !text.trim_start().starts_with('{') {
        " (each line must be one JSON object)"
    } else {
        ""
    };
    ParseError::invalid(format!("line {number}, column {}: {field}{message}{hint}", err.column()))
}

/// "`obs`[1]: " for the path `obs[1]`; nothing where serde_json failed outside a field.
fn field_of(path: &serde_path_to_error::Path) -> String {
    let path = path.to_string();
    if path.is_empty() || path == "." {
        return String::new();
    }
    let split = path.find('[').unwrap_or(path.len());
    format!("`{}`{}: ", &path[..split], &path[split..])
}
