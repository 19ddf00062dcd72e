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

use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

use super::error::ParseError;
use super::model::{ActionSpace, Actions, Dataset, DatasetParts};

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
    let corrupt =
        |what: String| ParseError::corrupt_canonical(format!("canonical dataset: {what}"));
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| corrupt(format!("unreadable ({e})")))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let field = |key: &str| meta.get(key).ok_or_else(|| corrupt(format!("no `{key}` metadata")));
    if field("format")? != FORMAT_TAG {
        return Err(corrupt("not a safedice dataset".into()));
    }
    let version = field("version")?;
    if version != VERSION {
        return Err(corrupt(format!("version {version}, this build reads {VERSION}")));
    }
    let obs_dim: usize = field("obs_dim")?.parse().map_err(|_| corrupt("bad obs_dim".into()))?;
    let action_space: ActionSpace = serde_json::from_str(field("action_space")?)
        .map_err(|e| corrupt(format!("bad action_space ({e})")))?;
    let tensors =
        SafeTensors::deserialize(bytes).map_err(|e| corrupt(format!("unreadable ({e})")))?;
    let column = |name: &str, dtype: Dtype| -> Result<Option<&[u8]>, ParseError> {
        match tensors.tensor(name) {
            Ok(view) if view.dtype() == dtype => Ok(Some(view.data())),
            Ok(view) => Err(corrupt(format!("`{name}` has dtype {:?}", view.dtype()))),
            Err(_) => Ok(None),
        }
    };
    let required = |name: &str, dtype: Dtype| {
        column(name, dtype)?.ok_or_else(|| corrupt(format!("no `{name}` column")))
    };
    let actions = match action_space {
        ActionSpace::Continuous { .. } => {
            Actions::Continuous(f32s(required("actions", Dtype::F32)?))
        }
        ActionSpace::Discrete { .. } => Actions::Discrete(u32s(required("actions", Dtype::U32)?)),
    };
    let terminals = required("terminals", Dtype::U8)?;
    if terminals.iter().any(|&t| t > 1) {
        return Err(corrupt("`terminals` holds a value other than 0/1".into()));
    }
    Dataset::new(DatasetParts {
        obs_dim,
        action_space,
        observations: f32s(required("observations", Dtype::F32)?),
        actions,
        next_observations: f32s(required("next_observations", Dtype::F32)?),
        terminals: terminals.iter().map(|&t| t == 1).collect(),
        episode_ids: u32s(required("episode_ids", Dtype::U32)?),
        rewards: column("rewards", Dtype::F32)?.map(f32s),
        costs: column("costs", Dtype::F32)?.map(f32s),
    })
    .map_err(|e| corrupt(e.to_string()))
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
