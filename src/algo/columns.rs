//! Training tensors built once from a [`Dataset`]: column tensors on the device, minibatches by
//! `index_select` with indices drawn from the run's seeded RNG (uniform, with replacement).

use candle_core::{DType, Device, Result, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::data::{ActionSpace, Actions, Dataset};

/// Dataset actions are clipped to `[-1 + ε, 1 − ε]` before `atanh` (they often sit exactly on
/// ±1), and ε keeps the Jacobian term `log(1 − a² + ε)` finite.
pub const ACTION_EPS: f64 = 1e-6;

/// Observation standardisation `(o − mean) / std`, from D^U's statistics (std + 1e-3, as in
/// DemoDICE). Stored in the policy artefact.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObsNormalizer {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

impl ObsNormalizer {
    pub fn from_dataset(d: &Dataset) -> ObsNormalizer {
        let dim = d.obs_dim();
        let n = d.len().max(1) as f64;
        let mut mean = vec![0f64; dim];
        for row in d.observations().chunks_exact(dim) {
            for (m, &x) in mean.iter_mut().zip(row) {
                *m += x as f64 / n;
            }
        }
        let mut var = vec![0f64; dim];
        for row in d.observations().chunks_exact(dim) {
            for ((v, &x), m) in var.iter_mut().zip(row).zip(&mean) {
                *v += (x as f64 - m).powi(2) / n;
            }
        }
        ObsNormalizer {
            mean: mean.iter().map(|&m| m as f32).collect(),
            std: var.iter().map(|&v| (v.sqrt() + 1e-3) as f32).collect(),
        }
    }

    /// Standardises row-major observations in place.
    pub fn apply(&self, values: &mut [f32]) {
        let dim = self.mean.len();
        for row in values.chunks_exact_mut(dim) {
            for ((x, m), s) in row.iter_mut().zip(&self.mean).zip(&self.std) {
                *x = (*x - m) / s;
            }
        }
    }
}

/// Maps a continuous action box to `[-1, 1]^dim` and back.
pub fn to_unit_box(a: f32, low: f32, high: f32) -> f32 {
    (2.0 * (a - low) / (high - low) - 1.0).clamp(-1.0, 1.0)
}

pub fn from_unit_box(a: f32, low: f32, high: f32) -> f32 {
    low + (a + 1.0) * 0.5 * (high - low)
}

/// The action column in the form the policy's log-likelihood needs.
#[derive(Clone)]
pub enum ActionColumn {
    /// `pretanh` = atanh of the clipped unit-box action (`N × dim`), `log_jacobian` =
    /// `Σ_j log(1 − a_j² + ε)` (`N`): both constants of the data, computed once.
    Continuous { pretanh: Tensor, log_jacobian: Tensor },
    /// Action indices (`N`, u32).
    Discrete { index: Tensor },
}

impl ActionColumn {
    pub fn select(&self, idx: &Tensor) -> Result<ActionColumn> {
        Ok(match self {
            ActionColumn::Continuous { pretanh, log_jacobian } => ActionColumn::Continuous {
                pretanh: pretanh.index_select(idx, 0)?,
                log_jacobian: log_jacobian.index_select(idx, 0)?,
            },
            ActionColumn::Discrete { index } => {
                ActionColumn::Discrete { index: index.index_select(idx, 0)? }
            }
        })
    }

    /// The rows of `a`, then those of `b` (columns of the same action space).
    pub fn cat(a: &ActionColumn, b: &ActionColumn) -> Result<ActionColumn> {
        Ok(match (a, b) {
            (
                ActionColumn::Continuous { pretanh: p, log_jacobian: j },
                ActionColumn::Continuous { pretanh: q, log_jacobian: k },
            ) => ActionColumn::Continuous {
                pretanh: Tensor::cat(&[p, q], 0)?,
                log_jacobian: Tensor::cat(&[j, k], 0)?,
            },
            (ActionColumn::Discrete { index: i }, ActionColumn::Discrete { index: k }) => {
                ActionColumn::Discrete { index: Tensor::cat(&[i, k], 0)? }
            }
            _ => candle_core::bail!("cannot stack continuous and discrete actions"),
        })
    }
}

/// One dataset as training tensors.
pub struct Columns {
    pub len: usize,
    pub obs_dim: usize,
    /// `N × obs_dim`, standardised when the run normalises observations.
    pub obs: Tensor,
    pub next_obs: Tensor,
    /// The action as a network input (`N × input_width`): the unit-box action, or a one-hot.
    pub action_input: Tensor,
    pub actions: ActionColumn,
    /// Host copies the samplers and terminal handling need.
    pub terminals: Vec<bool>,
    pub episode_ids: Vec<u32>,
    /// First row of every episode (the initial-state set p0).
    pub episode_starts: Vec<u32>,
    /// For each row, the first row of its episode.
    pub start_of_row: Vec<u32>,
}

impl Columns {
    /// `space` is the unlabeled dataset's action space: every dataset of a run is rescaled with
    /// its box.
    pub fn new(
        d: &Dataset,
        space: &ActionSpace,
        normalizer: Option<&ObsNormalizer>,
        device: &Device,
    ) -> Result<Columns> {
        let n = d.len();
        let dim = d.obs_dim();
        let mut obs = d.observations().to_vec();
        let mut next_obs = d.next_observations().to_vec();
        if let Some(norm) = normalizer {
            norm.apply(&mut obs);
            norm.apply(&mut next_obs);
        }
        let (action_input, actions) = action_tensors(d.actions(), space, n, device)?;
        let mut start_of_row = Vec::with_capacity(n);
        let ranges = d.episode_ranges();
        for r in &ranges {
            start_of_row.extend(std::iter::repeat_n(r.start as u32, r.len()));
        }
        Ok(Columns {
            len: n,
            obs_dim: dim,
            obs: Tensor::from_vec(obs, (n, dim), device)?,
            next_obs: Tensor::from_vec(next_obs, (n, dim), device)?,
            action_input,
            actions,
            terminals: d.terminals().to_vec(),
            episode_ids: d.episode_ids().to_vec(),
            episode_starts: ranges.iter().map(|r| r.start as u32).collect(),
            start_of_row,
        })
    }

    /// `batch` row indices uniform over the dataset, with replacement.
    pub fn sample(&self, rng: &mut ChaCha8Rng, batch: usize) -> Result<Tensor> {
        sample_indices(rng, self.len, batch, self.obs.device())
    }

    /// `batch` episode-start rows (samples of p0), with replacement.
    pub fn sample_initial(&self, rng: &mut ChaCha8Rng, batch: usize) -> Result<Tensor> {
        let picks: Vec<u32> = (0..batch)
            .map(|_| self.episode_starts[rng.random_range(0..self.episode_starts.len())])
            .collect();
        Tensor::from_vec(picks, batch, self.obs.device())
    }

    /// `[obs | action_input]` rows: the input of (s, a) networks.
    pub fn state_action(&self, idx: &Tensor) -> Result<Tensor> {
        Tensor::cat(&[self.obs.index_select(idx, 0)?, self.action_input.index_select(idx, 0)?], 1)
    }

    /// Half-open row ranges of the episodes.
    pub fn episode_ranges(&self) -> Vec<std::ops::Range<usize>> {
        let mut out: Vec<_> =
            self.episode_starts.windows(2).map(|w| w[0] as usize..w[1] as usize).collect();
        if let Some(&last) = self.episode_starts.last() {
            out.push(last as usize..self.len);
        }
        out
    }
}

/// `batch` indices uniform in `0..n`, with replacement, as a u32 tensor.
pub fn sample_indices(
    rng: &mut ChaCha8Rng,
    n: usize,
    batch: usize,
    device: &Device,
) -> Result<Tensor> {
    let picks: Vec<u32> = (0..batch).map(|_| rng.random_range(0..n as u32)).collect();
    Tensor::from_vec(picks, batch, device)
}

/// `rows × 1` uniform values in [0, 1) (interpolation coefficients).
pub fn uniform_column(rng: &mut ChaCha8Rng, rows: usize, device: &Device) -> Result<Tensor> {
    let u: Vec<f32> = (0..rows).map(|_| rng.random::<f32>()).collect();
    Tensor::from_vec(u, (rows, 1), device)
}

fn action_tensors(
    actions: &Actions,
    space: &ActionSpace,
    n: usize,
    device: &Device,
) -> Result<(Tensor, ActionColumn)> {
    match (actions, space) {
        (Actions::Continuous(a), ActionSpace::Continuous { dim, low, high }) => {
            let unit: Vec<f32> = a
                .chunks_exact(*dim)
                .flat_map(|row| {
                    row.iter().enumerate().map(|(j, &x)| to_unit_box(x, low[j], high[j]))
                })
                .collect();
            let clipped: Vec<f64> = unit
                .iter()
                .map(|&x| (x as f64).clamp(-1.0 + ACTION_EPS, 1.0 - ACTION_EPS))
                .collect();
            let pretanh: Vec<f32> = clipped.iter().map(|x| x.atanh() as f32).collect();
            let log_jacobian: Vec<f32> = clipped
                .chunks_exact(*dim)
                .map(|row| row.iter().map(|x| (1.0 - x * x + ACTION_EPS).ln()).sum::<f64>() as f32)
                .collect();
            Ok((
                Tensor::from_vec(unit, (n, *dim), device)?,
                ActionColumn::Continuous {
                    pretanh: Tensor::from_vec(pretanh, (n, *dim), device)?,
                    log_jacobian: Tensor::from_vec(log_jacobian, n, device)?,
                },
            ))
        }
        (Actions::Discrete(a), ActionSpace::Discrete { n: count }) => {
            let index = Tensor::from_vec(a.clone(), n, device)?;
            let one_hot = one_hot(a, *count, device)?;
            Ok((one_hot, ActionColumn::Discrete { index }))
        }
        _ => candle_core::bail!("action column does not match the action space"),
    }
}

pub fn one_hot(actions: &[u32], count: usize, device: &Device) -> Result<Tensor> {
    let mut values = vec![0f32; actions.len() * count];
    for (i, &a) in actions.iter().enumerate() {
        values[i * count + a as usize] = 1.0;
    }
    Tensor::from_vec(values, (actions.len(), count), device)
}

/// A short digest of a dataset's columns, so a checkpoint can refuse other data.
pub fn fingerprint(d: &Dataset) -> String {
    let mut h = Sha256::new();
    h.update((d.obs_dim() as u64).to_le_bytes());
    for v in [d.observations(), d.next_observations()] {
        for x in v.iter() {
            h.update(x.to_le_bytes());
        }
    }
    match d.actions() {
        Actions::Continuous(a) => a.iter().for_each(|x| h.update(x.to_le_bytes())),
        Actions::Discrete(a) => a.iter().for_each(|x| h.update(x.to_le_bytes())),
    }
    h.update(d.terminals().iter().map(|&t| t as u8).collect::<Vec<_>>());
    d.episode_ids().iter().for_each(|x| h.update(x.to_le_bytes()));
    hex::encode(&h.finalize()[..16])
}

/// Converts host `f32` values to a `rows × 1` tensor (e.g. a per-row reward column).
pub fn column(values: Vec<f32>, device: &Device) -> Result<Tensor> {
    let n = values.len();
    Tensor::from_vec(values, (n, 1), device)?.to_dtype(DType::F32)
}
