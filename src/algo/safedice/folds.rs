//! The data side of cross-fitting (`cross_fit`, [`super::cross_fit`]): D^U's folds (and D^N's,
//! with `cross_fit_labeled` or more than two folds), the held-out rows each part's discriminator
//! stops early on, and the finished parts' scores and weights as the checkpoint carries them.
//! Below the trainer, which holds a [`CrossFit`].
//!
//! Part `p` of `K` scores fold `(p + 1) mod K` and trains on the others: with two folds, the
//! first part trains on fold 0 and scores fold 1, the second the reverse.

use std::collections::HashMap;

use candle_core::Tensor;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::algo::discriminator_stop::{Holdout, MAX_VALIDATION_ROWS};
use crate::algo::TrainError;

/// Checkpoint names of the first part's scores (beside the early-stopping rule's weights).
const FIRST_U: &str = "cross_fit/first_u";
const FIRST_N: &str = "cross_fit/first_n";
/// Prefix of the first part's discriminator weights in the checkpoint (a safety head member).
const FIRST_WEIGHTS: &str = "cross_fit/first/";

/// The checkpoint names of finished part `part`'s D^U scores, D^N scores and weight prefix (the
/// first part's are the names a two-fold checkpoint has always used).
fn part_names(part: usize) -> (String, String, String) {
    match part {
        0 => (FIRST_U.into(), FIRST_N.into(), FIRST_WEIGHTS.into()),
        p => (
            format!("cross_fit/part{p}_u"),
            format!("cross_fit/part{p}_n"),
            format!("cross_fit/part{p}/"),
        ),
    }
}

/// D^U's folds and, for every part done, its discriminator's out-of-fold scores.
pub(super) struct CrossFit {
    /// Rows of D^U in each fold (whole episodes; rows when D^U has fewer episodes than
    /// `max(K, 4)`).
    pub(super) folds: Vec<Vec<u32>>,
    /// Rows of D^N in each fold, split the same way, with `cross_fit_labeled` or more than two
    /// folds; None otherwise (D^N's held-out fifth then serves every part).
    pub(super) labeled_folds: Option<Vec<Vec<u32>>>,
    /// The finished parts, in order.
    pub(super) done: Vec<FoldScores>,
}

/// A finished part's discriminator: its raw logits on every row of the D^U fold it scores and
/// on the D^N rows it scores (D^N's held-out rows, or its D^N fold), and its weights by variable
/// name (empty in a checkpoint written before they were kept).
pub(super) struct FoldScores {
    pub(super) u: Vec<f32>,
    pub(super) n: Vec<f32>,
    pub(super) weights: HashMap<String, Tensor>,
}

impl CrossFit {
    /// `k` folds of D^U from the run's seed (a stream of its own), and of D^N too when
    /// `labeled_episode_ids` is given (another stream); None when D^U has fewer rows than
    /// folds. D^N keeps its held-out fifth when it has fewer rows than folds.
    pub(super) fn new(
        k: usize,
        episode_ids: &[u32],
        labeled_episode_ids: Option<&[u32]>,
        seed: u64,
    ) -> Option<CrossFit> {
        let folds = folds_of(k, episode_ids, seed ^ 0x5afe_d1ce_0000_00cf)?;
        let labeled_folds =
            labeled_episode_ids.and_then(|ids| folds_of(k, ids, seed ^ 0x5afe_d1ce_0000_00ce));
        Some(CrossFit { folds, labeled_folds, done: Vec::new() })
    }

    pub(super) fn parts(&self) -> usize {
        self.folds.len()
    }

    /// The fold part `part` scores (and stops early on); it trains on the others.
    pub(super) fn scored_fold(&self, part: usize) -> usize {
        (part + 1) % self.parts()
    }

    /// The discriminator of part `part`: trains on the other folds of D^U, stops early on the
    /// one it scores (a fixed subset of it when longer than the held-out cap).
    pub(super) fn holdout(&self, part: usize) -> Holdout {
        fold_holdout(&self.folds, self.scored_fold(part))
    }

    /// With D^N in folds, the same for D^N; None without.
    pub(super) fn labeled_holdout(&self, part: usize) -> Option<Holdout> {
        let scored = self.scored_fold(part);
        self.labeled_folds.as_ref().map(|folds| fold_holdout(folds, scored))
    }

    /// The rows of D^U part `part` scores once trained: every row of its fold.
    pub(super) fn rows_scored(&self, part: usize) -> &[u32] {
        &self.folds[self.scored_fold(part)]
    }

    /// The rows of D^N part `part` scores once trained: with D^N in folds every row of its fold;
    /// otherwise `held_out`, D^N's fifth.
    pub(super) fn labeled_rows_scored(&self, part: usize, held_out: &[u32]) -> Vec<u32> {
        match &self.labeled_folds {
            Some(folds) => folds[self.scored_fold(part)].clone(),
            None => held_out.to_vec(),
        }
    }

    /// The finished parts' scores and weights as checkpoint tensors (none before the first is
    /// done).
    pub(super) fn checkpoint_tensors(&self) -> Vec<(String, Tensor)> {
        let column = |v: &[f32]| Tensor::from_slice(v, v.len(), &candle_core::Device::Cpu);
        let mut out = Vec::new();
        for (part, scores) in self.done.iter().enumerate() {
            let (u_name, n_name, prefix) = part_names(part);
            for (name, v) in [(n_name, &scores.n), (u_name, &scores.u)] {
                if let Ok(t) = column(v) {
                    out.push((name, t));
                }
            }
            out.extend(
                scores.weights.iter().map(|(name, t)| (format!("{prefix}{name}"), t.clone())),
            );
        }
        out
    }

    /// Takes the finished parts' scores and weights out of a checkpoint's tensors, leaving the
    /// rest.
    /// `labeled_held_out` is D^N's held-out fifth (what the parts score without D^N in folds).
    pub(super) fn restore(
        &mut self,
        tensors: &mut HashMap<String, Tensor>,
        labeled_held_out: &[u32],
    ) -> Result<(), TrainError> {
        for part in 0..self.parts() - 1 {
            let (u_name, n_name, prefix) = part_names(part);
            let (Some(u), Some(n)) = (tensors.remove(&u_name), tensors.remove(&n_name)) else {
                return Ok(());
            };
            let (u, n) = (u.to_vec1::<f32>()?, n.to_vec1::<f32>()?);
            let expected = self.rows_scored(part).len();
            let expected_n = self.labeled_rows_scored(part, labeled_held_out).len();
            if u.len() != expected || n.len() != expected_n {
                return Err(TrainError::Other(format!(
                    "checkpoint has {} + {} cross-fitted scores for the {expected} + {expected_n} rows of D^U and D^N part {part} scores",
                    u.len(),
                    n.len(),
                )));
            }
            let names: Vec<String> =
                tensors.keys().filter(|k| k.starts_with(&prefix)).cloned().collect();
            let weights = names
                .into_iter()
                .filter_map(|k| Some((k[prefix.len()..].to_string(), tensors.remove(&k)?)))
                .collect();
            self.done.push(FoldScores { u, n, weights });
        }
        Ok(())
    }
}

/// Whether `k` folds of a set with `episodes` episodes hold whole episodes: at least `max(k, 4)`
/// of them (below that, the folds cut rows).
pub(super) fn whole_episode_folds(k: usize, episodes: usize) -> bool {
    episodes >= k.max(4)
}

/// Rows in `k` folds of whole episodes (of rows, with fewer episodes than `max(k, 4)`), shuffled
/// by `seed`: fold `f` holds the shuffled units from `⌊f·len/k⌋` up to `⌊(f+1)·len/k⌋`, so the
/// folds' sizes differ by one unit at most. None with fewer rows than folds.
fn folds_of(k: usize, episode_ids: &[u32], seed: u64) -> Option<Vec<Vec<u32>>> {
    if episode_ids.len() < k.max(2) {
        return None;
    }
    let mut episodes: Vec<u32> = episode_ids.to_vec();
    episodes.sort_unstable();
    episodes.dedup();
    let by_row = !whole_episode_folds(k, episodes.len());
    let mut units: Vec<u32> =
        if by_row { (0..episode_ids.len() as u32).collect() } else { episodes };
    units.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let len = units.len();
    let fold_at = |i: usize| (0..k).rev().find(|&f| f * len / k <= i).unwrap_or(0);
    let fold_of: HashMap<u32, usize> =
        units.iter().enumerate().map(|(i, &unit)| (unit, fold_at(i))).collect();
    let mut folds = vec![Vec::new(); k];
    for (row, &episode) in episode_ids.iter().enumerate() {
        let unit = if by_row { row as u32 } else { episode };
        folds[fold_of[&unit]].push(row as u32);
    }
    Some(folds)
}

/// Trains on every fold but `scored`, stops early on it (a fixed subset of it when longer than
/// the held-out cap).
fn fold_holdout(folds: &[Vec<u32>], scored: usize) -> Holdout {
    let other = &folds[scored];
    let stride = other.len().div_ceil(MAX_VALIDATION_ROWS).max(1);
    let train = (0..folds.len()).filter(|&f| f != scored).flat_map(|f| folds[f].iter().copied());
    let mut train: Vec<u32> = train.collect();
    train.sort_unstable();
    Holdout { train, validation: other.iter().step_by(stride).copied().collect() }
}
