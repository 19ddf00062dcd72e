//! The safety head a SafeDICE policy carries for serving: two scores for every action a
//! deployed agent receives, so that it can hand control to a safe controller.
//!
//! - `non_preferred_log_ratio`: the frozen discriminator `c(s, a)` of Eq. 9 on the returned
//!   action, recalibrated as Eq. 10 reads it. Trained on balanced minibatches of D^N and D^U,
//!   `σ(c)` estimates `d^N / (d^N + d^U)`, so `c` estimates `log d^N(s,a) / d^U(s,a)`: above 0,
//!   the pair looks more like the non-preferred demonstrations than like the unlabeled data.
//!   A cross-fitted run (`cross_fit`) trained two discriminators, each on half of D^U's
//!   episodes; the head keeps both and answers the mean of their recalibrated logits, which
//!   reads all of D^U as the one discriminator of other runs does.
//! - `out_of_support`: how far the observation is from the states of D^U: the distance to the
//!   nearest of up to [`SUPPORT_ROWS`] reference states of D^U (standardised per dimension),
//!   divided by the [`SUPPORT_QUANTILE`] quantile of that distance over other rows of D^U. Up to
//!   1 is as close as 99% of the training states are; above 1, farther; the discriminator and the
//!   policy were never trained there and both scores lose their meaning.
//!
//! docs/safety-scores.md says how to read them and what they cost.

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use super::columns::{to_unit_box, ObsNormalizer};
use super::fused_mlp::{FusedMlp, Workspace};
use super::mlp::Mlp;
use super::TrainError;
use crate::data::{ActionSpace, Actions};

/// The two scores' names, in this order, wherever they are answered (`/act`, the inference
/// protocol's outputs, the ONNX export's outputs).
pub const SCORE_NAMES: [&str; 2] = ["non_preferred_log_ratio", "out_of_support"];
/// The discriminator's tensors in the policy file (`discriminator.{layer}.weight|bias`); the
/// k-th of [`SafetySpec::more_discriminators`] is `discriminator_{k}.*`, k from 1.
pub const DISCRIMINATOR: &str = "discriminator";
/// The reference states of D^U (`rows × obs_dim`, standardised), in the policy file.
pub const SUPPORT_TENSOR: &str = "support.observations";
/// At most this many reference states: a nearest-neighbour search over them costs
/// `SUPPORT_ROWS × obs_dim` multiply-adds per observation.
pub const SUPPORT_ROWS: usize = 1024;
/// The quantile of D^U's own nearest-neighbour distances that `out_of_support` divides by.
pub const SUPPORT_QUANTILE: f64 = 0.99;
/// The smallest reference distance (in standard deviations): data with repeated states (a grid)
/// has nearest-neighbour distances of 0, and a ratio to 0 would say nothing.
pub const MIN_REFERENCE_DISTANCE: f32 = 0.1;

/// What the policy file says of its safety head (the tensors are [`DISCRIMINATOR`]`.*` and
/// [`SUPPORT_TENSOR`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SafetySpec {
    /// Hidden widths of the discriminator (ReLU; input `[observation | action]` with the
    /// observation normalised as the policy's and the action in the unit box or one-hot).
    pub discriminator_hidden_sizes: Vec<usize>,
    /// The recalibration `scale · c + shift` Eq. 10 read the logit with (`1, 0` when none).
    pub logit_scale: f64,
    pub logit_shift: f64,
    /// Further discriminators of the same shape (cross-fitting's finished parts), each with its own
    /// recalibration; the log-ratio is the mean of every member's recalibrated logit. Empty (and
    /// absent from the JSON) with one discriminator.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub more_discriminators: Vec<Recalibration>,
    /// The discriminator's ROC AUC on held-out episodes, when the run measured it: near 0.5 the
    /// log-ratio carries no information.
    pub heldout_auc: Option<f64>,
    /// Standardisation of the (policy-normalised) observations before distances are taken.
    pub support_normalization: ObsNormalizer,
    /// Rows of [`SUPPORT_TENSOR`].
    pub support_rows: usize,
    /// The divisor of `out_of_support`: the [`SUPPORT_QUANTILE`] quantile of the distance from
    /// held-out D^U rows to their nearest reference state, at least [`MIN_REFERENCE_DISTANCE`].
    pub support_reference_distance: f32,
}

/// A discriminator's recalibration `scale · c + shift`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Recalibration {
    pub logit_scale: f64,
    pub logit_shift: f64,
}

impl Recalibration {
    /// No recalibration (`1, 0`).
    pub const NONE: Recalibration = Recalibration { logit_scale: 1.0, logit_shift: 0.0 };
}

/// The name prefix of the `k`-th discriminator's tensors (0: the spec's own).
pub fn discriminator_prefix(k: usize) -> String {
    match k {
        0 => DISCRIMINATOR.to_owned(),
        k => format!("{DISCRIMINATOR}_{k}"),
    }
}

/// One discriminator of a head being built: its weights by variable name (as a
/// [`DISCRIMINATOR`] network names them) and its recalibration.
pub struct Member {
    pub weights: HashMap<String, Tensor>,
    pub recalibration: Recalibration,
}

/// Both scores for each of `B` rows.
#[derive(Clone, Debug, PartialEq)]
pub struct SafetyScores {
    pub non_preferred_log_ratio: Vec<f32>,
    pub out_of_support: Vec<f32>,
}

/// The safety head of a loaded policy.
pub struct SafetyHead {
    spec: SafetySpec,
    /// Each member with its recalibration, the spec's own first.
    discriminators: Vec<(FusedMlp, Recalibration)>,
    /// The reference states, standardised ([`Support`]).
    support: Support,
}

impl SafetyHead {
    /// The head from the policy file's tensors.
    pub fn load(
        spec: &SafetySpec,
        obs_dim: usize,
        space: &ActionSpace,
        tensors: &HashMap<String, Tensor>,
    ) -> Result<SafetyHead, TrainError> {
        let own = Recalibration { logit_scale: spec.logit_scale, logit_shift: spec.logit_shift };
        let recalibrations = std::iter::once(own).chain(spec.more_discriminators.iter().copied());
        let discriminators = recalibrations
            .enumerate()
            .map(|(k, recalibration)| {
                let prefix = discriminator_prefix(k);
                let net =
                    discriminator_net(&prefix, obs_dim, space, &spec.discriminator_hidden_sizes)?;
                net.load(tensors)?;
                Ok((net.to_fused()?, recalibration))
            })
            .collect::<Result<_, TrainError>>()?;
        let support = tensors
            .get(SUPPORT_TENSOR)
            .ok_or_else(|| TrainError::Other(format!("the policy file lacks `{SUPPORT_TENSOR}`")))?
            .flatten_all()?
            .to_vec1::<f32>()?;
        if support.len() != spec.support_rows * obs_dim
            || spec.support_normalization.mean.len() != obs_dim
        {
            return Err(TrainError::Other(format!(
                "`{SUPPORT_TENSOR}` holds {} values, not {} rows of {obs_dim}",
                support.len(),
                spec.support_rows
            )));
        }
        let support = Support::new(&support, obs_dim);
        Ok(SafetyHead { spec: spec.clone(), discriminators, support })
    }

    /// The scores of `actions` (in the dataset's units) at `observations` (`B × obs_dim`,
    /// already normalised as the policy normalises them).
    pub fn scores(
        &self,
        observations: &[f32],
        actions: &Actions,
        space: &ActionSpace,
    ) -> SafetyScores {
        let obs_dim = self.spec.support_normalization.mean.len();
        let rows = observations.len() / obs_dim.max(1);
        SafetyScores {
            non_preferred_log_ratio: self.log_ratios(observations, actions, space, rows),
            out_of_support: self.support_scores(observations, rows),
        }
    }

    fn log_ratios(
        &self,
        observations: &[f32],
        actions: &Actions,
        space: &ActionSpace,
        rows: usize,
    ) -> Vec<f32> {
        let shape = self.discriminators[0].0.shape();
        let mut ws = Workspace::for_inference(shape, rows);
        let input = ws.input_mut();
        let obs_dim = observations.len() / rows.max(1);
        let width = shape.input();
        for (r, row) in input.chunks_exact_mut(width).take(rows).enumerate() {
            row[..obs_dim].copy_from_slice(&observations[r * obs_dim..(r + 1) * obs_dim]);
            encode_action(actions, space, r, &mut row[obs_dim..]);
        }
        let mut sum = vec![0f32; rows];
        for (net, recalibration) in &self.discriminators {
            net.forward(&mut ws, rows);
            // In f32 and in member order, as the ONNX export's Mul, Add and Sum compute it.
            let scale = recalibration.logit_scale as f32;
            let shift = recalibration.logit_shift as f32;
            for (total, &c) in sum.iter_mut().zip(&ws.output()[..rows]) {
                *total += scale * c + shift;
            }
        }
        match self.discriminators.len() {
            1 => sum,
            members => sum.into_iter().map(|total| total / members as f32).collect(),
        }
    }

    fn support_scores(&self, observations: &[f32], rows: usize) -> Vec<f32> {
        let mut z = observations[..rows * self.support_dim()].to_vec();
        self.spec.support_normalization.apply(&mut z);
        let mut squares = Vec::new();
        z.chunks_exact(self.support_dim())
            .map(|row| {
                let distance = self.support.nearest_distance(row, &mut squares);
                distance / self.spec.support_reference_distance
            })
            .collect()
    }

    fn support_dim(&self) -> usize {
        self.spec.support_normalization.mean.len()
    }
}

/// The discriminator as SafeDICE builds it (`run.new_critic`), its variables named under
/// `prefix`: no bias on the output layer.
fn discriminator_net(
    prefix: &str,
    obs_dim: usize,
    space: &ActionSpace,
    hidden: &[usize],
) -> Result<Mlp, TrainError> {
    let dims: Vec<usize> = std::iter::once(obs_dim + space.input_width())
        .chain(hidden.iter().copied())
        .chain(std::iter::once(1))
        .collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    Ok(Mlp::new(prefix, &dims, false, &Device::Cpu, &mut rng)?)
}

/// Row `r`'s action as the discriminator's input: the unit-box action, or a one-hot.
fn encode_action(actions: &Actions, space: &ActionSpace, r: usize, out: &mut [f32]) {
    match (actions, space) {
        (Actions::Continuous(values), ActionSpace::Continuous { dim, low, high }) => {
            for j in 0..*dim {
                out[j] = to_unit_box(values[r * dim + j], low[j], high[j]);
            }
        }
        (Actions::Discrete(picks), ActionSpace::Discrete { .. }) => {
            out.iter_mut().for_each(|x| *x = 0.0);
            out[picks[r] as usize] = 1.0;
        }
        _ => unreachable!("a policy's actions match its action space"),
    }
}

/// Reference states stored by column (`obs_dim × rows`): the distances to all of them are then
/// `obs_dim` passes over contiguous memory, which the compiler vectorises, where a reference
/// row at a time is a horizontal sum per row (about 2.5x slower: `examples/safety_score_cost.rs`).
/// The sum over dimensions still runs in order, so the distances are those of a row at a time,
/// bit for bit.
struct Support {
    columns: Vec<f32>,
    rows: usize,
}

impl Support {
    /// From row-major `rows × dim` values.
    fn new(values: &[f32], dim: usize) -> Support {
        let rows = values.len() / dim.max(1);
        let columns = (0..dim).flat_map(|j| (0..rows).map(move |r| values[r * dim + j])).collect();
        Support { columns, rows }
    }

    /// Euclidean distance from `row` to the nearest reference state (infinite when there is
    /// none); `squares` is scratch space.
    fn nearest_distance(&self, row: &[f32], squares: &mut Vec<f32>) -> f32 {
        squares.clear();
        squares.resize(self.rows, 0.0);
        for (column, &x) in self.columns.chunks_exact(self.rows.max(1)).zip(row) {
            for (square, &reference) in squares.iter_mut().zip(column) {
                let difference = reference - x;
                *square += difference * difference;
            }
        }
        squares.iter().copied().fold(f32::INFINITY, f32::min).sqrt()
    }
}

/// Builds the safety head of a trained SafeDICE run: its spec and the tensors to add to the
/// policy file. `members`: the discriminators, at least one, the first the spec's own.
/// `observations`: D^U's observations as the run fed them to its networks (`N × obs_dim`,
/// normalised when the run normalises). No random draws: the reference states are evenly spaced
/// rows and the held-out ones the rows halfway between, so exporting a policy never changes what
/// the run trains.
pub fn build(
    members: &[Member],
    hidden: &[usize],
    heldout_auc: Option<f64>,
    observations: &[f32],
    obs_dim: usize,
) -> Result<(SafetySpec, Vec<(String, Tensor)>), TrainError> {
    let n = observations.len() / obs_dim.max(1);
    let mut standardised = observations[..n * obs_dim].to_vec();
    let normalization = standardisation(&standardised, obs_dim);
    normalization.apply(&mut standardised);
    let (reference_rows, heldout_rows) = split_rows(n);
    let row = |i: usize| &standardised[i * obs_dim..(i + 1) * obs_dim];
    let support: Vec<f32> = reference_rows.iter().flat_map(|&i| row(i).to_vec()).collect();
    let reference = Support::new(&support, obs_dim);
    let mut squares = Vec::new();
    let mut distances: Vec<f32> =
        (heldout_rows.iter()).map(|&i| reference.nearest_distance(row(i), &mut squares)).collect();
    distances.sort_by(f32::total_cmp);
    let quantile = distances
        .get(((distances.len() as f64 - 1.0) * SUPPORT_QUANTILE).round() as usize)
        .copied()
        .unwrap_or(0.0);
    let (own, more) = members
        .split_first()
        .ok_or_else(|| TrainError::Other("a safety head needs a discriminator".into()))?;
    let spec = SafetySpec {
        discriminator_hidden_sizes: hidden.to_vec(),
        logit_scale: own.recalibration.logit_scale,
        logit_shift: own.recalibration.logit_shift,
        more_discriminators: more.iter().map(|m| m.recalibration).collect(),
        heldout_auc,
        support_normalization: normalization,
        support_rows: reference_rows.len(),
        support_reference_distance: quantile.max(MIN_REFERENCE_DISTANCE),
    };
    let mut tensors = Vec::new();
    for (k, member) in members.iter().enumerate() {
        let prefix = discriminator_prefix(k);
        for (name, tensor) in &member.weights {
            let name = match name.strip_prefix(DISCRIMINATOR) {
                Some(layer) => format!("{prefix}{layer}"),
                None => {
                    return Err(TrainError::Other(format!("`{name}` is not a discriminator's")))
                }
            };
            tensors.push((name, tensor.to_device(&Device::Cpu)?));
        }
    }
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let rows = reference_rows.len();
    tensors.push((
        SUPPORT_TENSOR.to_owned(),
        Tensor::from_vec(support, (rows, obs_dim), &Device::Cpu)?,
    ));
    Ok((spec, tensors))
}

/// Per-dimension mean and standard deviation (+1e-3, as the policy's normalisation) of rows.
fn standardisation(values: &[f32], dim: usize) -> ObsNormalizer {
    let n = (values.len() / dim.max(1)).max(1) as f64;
    let mut mean = vec![0f64; dim];
    let mut square = vec![0f64; dim];
    for row in values.chunks_exact(dim.max(1)) {
        for (j, &x) in row.iter().enumerate() {
            mean[j] += x as f64 / n;
            square[j] += (x as f64) * (x as f64) / n;
        }
    }
    let std = mean.iter().zip(&square).map(|(m, s)| ((s - m * m).max(0.0).sqrt() + 1e-3) as f32);
    ObsNormalizer { mean: mean.iter().map(|&m| m as f32).collect(), std: std.collect() }
}

/// Up to [`SUPPORT_ROWS`] evenly spaced reference rows of `0..n`, and the rows halfway between
/// consecutive ones (none when the references are every row).
fn split_rows(n: usize) -> (Vec<usize>, Vec<usize>) {
    let count = n.min(SUPPORT_ROWS);
    if count == 0 {
        return (Vec::new(), Vec::new());
    }
    let at = |k: usize| k * n / count;
    let reference: Vec<usize> = (0..count).map(at).collect();
    let heldout = (0..count)
        .map(|k| (at(k) + if k + 1 < count { at(k + 1) } else { n }) / 2)
        .filter(|i| reference.binary_search(i).is_err())
        .collect();
    (reference, heldout)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_and_heldout_rows_interleave_without_overlap() {
        let (reference, heldout) = split_rows(10_000);
        assert_eq!(reference.len(), SUPPORT_ROWS);
        assert_eq!(heldout.len(), SUPPORT_ROWS);
        assert!(heldout.iter().all(|i| reference.binary_search(i).is_err() && *i < 10_000));
        let (reference, heldout) = split_rows(300);
        assert_eq!(reference, (0..300).collect::<Vec<_>>());
        assert!(heldout.is_empty());
        assert_eq!(split_rows(0), (vec![], vec![]));
    }

    #[test]
    fn nearest_distance_is_the_closed_form_minimum() {
        let reference = Support::new(&[0.0, 0.0, 3.0, 4.0, -1.0, 1.0], 2);
        let mut scratch = Vec::new();
        let mut nearest = |row: [f32; 2]| reference.nearest_distance(&row, &mut scratch);
        assert_eq!(nearest([3.0, 4.0]), 0.0);
        assert!((nearest([6.0, 8.0]) - 5.0).abs() < 1e-6);
        assert!((nearest([-1.0, 2.0]) - 1.0).abs() < 1e-6);
        assert_eq!(Support::new(&[], 2).nearest_distance(&[1.0, 1.0], &mut scratch), f32::INFINITY);
    }
}
