//! The data side of cross-fitting (`cross_fit`, [`super::cross_fit`]): D^U's two folds, the
//! held-out rows each half's discriminator stops early on, and the first half's scores and
//! weights as the checkpoint carries them. Below the trainer, which holds a [`CrossFit`].

use std::collections::HashMap;

use candle_core::Tensor;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::algo::discriminator_stop::{Holdout, MAX_VALIDATION_ROWS};
use crate::algo::TrainError;

/// Checkpoint names of the first half's scores (beside the early-stopping rule's weights).
const FIRST_U: &str = "cross_fit/first_u";
const FIRST_N: &str = "cross_fit/first_n";
/// Prefix of the first half's discriminator weights in the checkpoint (the safety head's second
/// member).
const FIRST_WEIGHTS: &str = "cross_fit/first/";

/// D^U's two folds and, once the first half is done, its discriminator's out-of-fold scores.
pub(super) struct CrossFit {
    /// Rows of D^U in each fold (whole episodes; rows when D^U has fewer than four episodes).
    pub(super) folds: [Vec<u32>; 2],
    /// With `cross_fit_labeled`: rows of D^N in each fold, split the same way; None otherwise
    /// (D^N's held-out fifth then serves both halves).
    pub(super) labeled_folds: Option<[Vec<u32>; 2]>,
    pub(super) first: Option<FoldScores>,
}

/// The first half's discriminator: its raw logits on every row of fold 1 and on D^N's held-out
/// rows (every row of D^N's fold 1 with `cross_fit_labeled`), and its weights by variable name (empty in a checkpoint written before they were kept).
pub(super) struct FoldScores {
    pub(super) u: Vec<f32>,
    pub(super) n: Vec<f32>,
    pub(super) weights: HashMap<String, Tensor>,
}

impl CrossFit {
    /// Two folds of D^U from the run's seed (a stream of its own), and of D^N too when
    /// `labeled_episode_ids` is given (another stream; D^N keeps its held-out fifth when it has
    /// a single row); None with a single row in D^U.
    pub(super) fn new(
        episode_ids: &[u32],
        labeled_episode_ids: Option<&[u32]>,
        seed: u64,
    ) -> Option<CrossFit> {
        let folds = two_folds(episode_ids, seed ^ 0x5afe_d1ce_0000_00cf)?;
        let labeled_folds =
            labeled_episode_ids.and_then(|ids| two_folds(ids, seed ^ 0x5afe_d1ce_0000_00ce));
        Some(CrossFit { folds, labeled_folds, first: None })
    }

    /// The discriminator of half `half`: trains on its fold of D^U, stops early on the other
    /// (a fixed subset of it when longer than the held-out cap).
    pub(super) fn holdout(&self, half: usize) -> Holdout {
        fold_holdout(&self.folds, half)
    }

    /// With `cross_fit_labeled`, the same for D^N; None without.
    pub(super) fn labeled_holdout(&self, half: usize) -> Option<Holdout> {
        self.labeled_folds.as_ref().map(|folds| fold_holdout(folds, half))
    }

    /// The rows of D^N the discriminator of half `half` scores once trained: with
    /// `cross_fit_labeled` its other fold, every row of it; otherwise `held_out`, D^N's fifth.
    pub(super) fn labeled_rows_scored(&self, half: usize, held_out: &[u32]) -> Vec<u32> {
        match &self.labeled_folds {
            Some(folds) => folds[1 - half].clone(),
            None => held_out.to_vec(),
        }
    }

    /// The first half's scores and weights as checkpoint tensors (none before it is done).
    pub(super) fn checkpoint_tensors(&self) -> Vec<(String, Tensor)> {
        let Some(first) = &self.first else { return Vec::new() };
        let column = |v: &[f32]| Tensor::from_slice(v, v.len(), &candle_core::Device::Cpu);
        let scores = [(FIRST_N, &first.n), (FIRST_U, &first.u)]
            .into_iter()
            .filter_map(|(name, v)| Some((name.to_string(), column(v).ok()?)));
        let weights =
            first.weights.iter().map(|(name, t)| (format!("{FIRST_WEIGHTS}{name}"), t.clone()));
        scores.chain(weights).collect()
    }

    /// Takes the first half's scores and weights out of a checkpoint's tensors, leaving the rest.
    pub(super) fn restore(
        &mut self,
        tensors: &mut HashMap<String, Tensor>,
    ) -> Result<(), TrainError> {
        let (Some(u), Some(n)) = (tensors.remove(FIRST_U), tensors.remove(FIRST_N)) else {
            return Ok(());
        };
        let (u, n) = (u.to_vec1::<f32>()?, n.to_vec1::<f32>()?);
        if u.len() != self.folds[1].len() {
            return Err(TrainError::Other(format!(
                "checkpoint has {} cross-fitted scores for {} rows of fold 1",
                u.len(),
                self.folds[1].len()
            )));
        }
        let names: Vec<String> =
            tensors.keys().filter(|k| k.starts_with(FIRST_WEIGHTS)).cloned().collect();
        let weights = names
            .into_iter()
            .filter_map(|k| Some((k[FIRST_WEIGHTS.len()..].to_string(), tensors.remove(&k)?)))
            .collect();
        self.first = Some(FoldScores { u, n, weights });
        Ok(())
    }
}

/// Rows in two folds of whole episodes (of rows, with fewer than four episodes), shuffled by
/// `seed`; None with a single row.
fn two_folds(episode_ids: &[u32], seed: u64) -> Option<[Vec<u32>; 2]> {
    if episode_ids.len() < 2 {
        return None;
    }
    let mut episodes: Vec<u32> = episode_ids.to_vec();
    episodes.sort_unstable();
    episodes.dedup();
    let by_row = episodes.len() < 4;
    let mut units: Vec<u32> =
        if by_row { (0..episode_ids.len() as u32).collect() } else { episodes };
    units.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let in_first: std::collections::HashSet<u32> =
        units[..units.len() / 2].iter().copied().collect();
    let mut folds = [Vec::new(), Vec::new()];
    for (row, &episode) in episode_ids.iter().enumerate() {
        let unit = if by_row { row as u32 } else { episode };
        folds[usize::from(!in_first.contains(&unit))].push(row as u32);
    }
    Some(folds)
}

/// Half `half` trains on its fold and stops early on the other, a fixed subset of it when
/// longer than the held-out cap.
fn fold_holdout(folds: &[Vec<u32>; 2], half: usize) -> Holdout {
    let other = &folds[1 - half];
    let stride = other.len().div_ceil(MAX_VALIDATION_ROWS).max(1);
    Holdout {
        train: folds[half].clone(),
        validation: other.iter().step_by(stride).copied().collect(),
    }
}
