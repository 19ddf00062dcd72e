//! Cross-fitting of the discriminator (`cross_fit`): Eq. 10 reads `c(s, a)` on every row of
//! D^U, and a discriminator scores the D^U rows it trained on (label "unlabeled") lower than
//! rows it never saw, non-preferred ones included: their reward is not low enough, and the
//! weights keep them. Here D^U's episodes go in `cross_fit_folds` folds (two by default) and the
//! discriminator's step budget in as many parts: part `p` trains a discriminator (initialised
//! afresh) on every fold but one against D^N and scores the fold it left out
//! ([`super::folds`] says which). Every row of D^U is then scored by a discriminator that never
//! trained on its episode, and Best Bin Estimation reads all of D^U rather than a held-out
//! fifth. Each part keeps its own early-stopping rule, measured on the fold it scores; with
//! `calibrate_discriminator` each part's logit is recalibrated on its own held-out scores (Platt
//! scaling) before they are pooled, so all speak one scale. docs/algorithm.md, "Cross-fitting",
//! says what the development split showed.

use std::collections::HashMap;

use candle_core::Tensor;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::bin_by_episode::bin_ratio_by_episode;
use super::folds::{whole_episode_folds, FoldScores};
use super::heldout::HeldOut;
use super::mixture::{best_bin_estimate, platt_scaling, EpisodesOf};
use super::pooling::pool_by_episode;
use super::trainer::{logits_of, snapshot, SafediceTrainer};
use super::weighting::{episodes_of, UnlabeledScores};
use crate::algo::discriminator_stop::EarlyStop;
use crate::algo::mlp::Mlp;
use crate::algo::optim::Adam;
use crate::algo::safety::{Member, Recalibration};
use crate::algo::TrainError;
use crate::data::Dataset;

impl SafediceTrainer {
    /// The steps part `part` of the discriminator's budget starts after and ends at.
    fn part_bounds(&self, part: usize, parts: usize) -> (u64, u64) {
        let budget = self.cfg.discriminator_iterations;
        let at = |p: usize| (p as u64 * budget) / parts as u64;
        (at(part), at(part + 1))
    }

    /// The part that trains after `step` steps are done (cross-fitting only).
    fn part_after(&self, step: u64) -> Option<usize> {
        let parts = self.cross_fit.as_ref()?.parts();
        let ended = (0..parts - 1).filter(|&p| self.part_bounds(p, parts).1 <= step).count();
        Some(ended)
    }

    /// After a resume: the checkpoint must hold a finished part for every part its step has
    /// passed, or the next part would score a fold it trained on.
    pub(super) fn check_finished_parts(&self) -> Result<(), TrainError> {
        let (Some(cf), Some(part)) = (self.cross_fit.as_ref(), self.part_after(self.run.step))
        else {
            return Ok(());
        };
        if cf.done.len() != part {
            return Err(TrainError::Other(format!(
                "checkpoint at step {} holds {} finished cross-fitting parts where {part} are done",
                self.run.step,
                cf.done.len()
            )));
        }
        Ok(())
    }

    /// Whether `step` ends a part that another follows (cross-fitting only).
    pub(super) fn ends_a_part(&self, step: u64) -> bool {
        let Some(parts) = self.cross_fit.as_ref().map(|cf| cf.parts()) else { return false };
        (0..parts - 1).any(|p| self.part_bounds(p, parts).1 == step)
    }

    /// `step` counted from the start of the discriminator that trains at it: the early-stopping
    /// rule of each part counts its own steps.
    pub(super) fn steps_into_part(&self, step: u64) -> u64 {
        match (self.part_after(step.saturating_sub(1)), self.cross_fit.as_ref()) {
            (Some(part), Some(cf)) => step - self.part_bounds(part, cf.parts()).0,
            _ => step,
        }
    }

    /// The held-out rows and the stopping rule for the part that trains after `step`.
    pub(super) fn enter_part(&mut self, step: u64) {
        let (Some(part), Some(cf)) = (self.part_after(step), self.cross_fit.as_ref()) else {
            return;
        };
        let (start, end) = self.part_bounds(part, cf.parts());
        let (holdout, labeled) = (cf.holdout(part), cf.labeled_holdout(part));
        if let Some(v) = self.disc_stop.as_mut() {
            v.u = holdout;
            if let Some(labeled) = labeled {
                v.n = labeled;
            }
            v.rule = EarlyStop::new(end - start);
            v.best.clear();
        }
    }

    /// A part other than the last is done: keep its (best) discriminator's scores on the fold
    /// of D^U and the rows of D^N it scores, then start the next part's discriminator from
    /// fresh weights and a fresh optimiser.
    pub(super) fn end_part(&mut self) -> Result<(), TrainError> {
        let (Some(v), Some(cf)) = (self.disc_stop.as_ref(), self.cross_fit.as_ref()) else {
            return Ok(());
        };
        if !v.best.is_empty() {
            self.disc.load(&v.best)?;
        }
        let part = cf.done.len();
        debug_assert_eq!(Some(part), self.part_after(self.run.step.saturating_sub(1)));
        let trained = snapshot(&self.disc)?;
        let u = self.score_rows(&self.run.u, cf.rows_scored(part))?;
        let n = self
            .score_rows(self.run.non_preferred(), &cf.labeled_rows_scored(part, &v.n.validation))?;
        tracing::info!(
            part,
            best_step = v.rule.best_step,
            heldout_loss = v.rule.best_loss,
            "SafeDICE discriminator, cross-fitting: a part done, its fold scored"
        );
        // The first part's stream is the one two-fold runs have always used.
        let seed = self.run.config.seed() ^ 0x5afe_d1ce_0000_00d1 ^ ((part as u64) << 16);
        let dims = self.disc.dims().to_vec();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let fresh = Mlp::new("discriminator", &dims, false, &self.run.device, &mut rng)?;
        let weights: HashMap<String, Tensor> = fresh
            .named_vars()
            .into_iter()
            .map(|(name, var)| (name, var.as_tensor().clone()))
            .collect();
        self.disc.load(&weights)?;
        self.disc_opt = Adam::new(self.disc.named_vars(), self.cfg.lr_discriminator)?;
        if let Some(cf) = self.cross_fit.as_mut() {
            cf.done.push(FoldScores { u, n, weights: trained });
        }
        self.enter_part(self.run.step);
        Ok(())
    }

    /// With cross-fitting, once every part is done: every row of D^U's logit from the
    /// discriminator that did not train on it (each recalibrated on its own held-out scores
    /// with `calibrate_discriminator`), and Best Bin Estimation and the AUC on them.
    /// Without D^N in folds, D^N's held-out rows are shared out between the discriminators in
    /// the proportion their folds have in D^U, so the labeled scores come from the same mixture
    /// of score functions as D^U's; with D^N in folds each discriminator scores its fold of D^N,
    /// every row of it, and they are pooled as they are (the folds' shares of D^N and of D^U
    /// agree roughly: both are cut evenly by episode, with their own draws). None without
    /// cross-fitting.
    pub(super) fn cross_fitted(&self) -> Result<Option<UnlabeledScores>, TrainError> {
        let (Some(cf), Some(v)) = (self.cross_fit.as_ref(), self.disc_stop.as_ref()) else {
            return Ok(None);
        };
        let last = cf.parts() - 1;
        if cf.done.len() != last {
            return Ok(None);
        }
        let own_u = self.score_rows(&self.run.u, cf.rows_scored(last))?;
        let own_n_rows = cf.labeled_rows_scored(last, &v.n.validation);
        let own_n = self.score_rows(self.run.non_preferred(), &own_n_rows)?;
        let scores: Vec<(&[f32], &[f32])> = (cf.done.iter().map(|d| (&d.u[..], &d.n[..])))
            .chain(std::iter::once((&own_u[..], &own_n[..])))
            .collect();
        let fits: Vec<(f64, f64)> = scores.iter().map(|&(u, n)| self.recalibration(n, u)).collect();
        let apply = |(scale, shift): (f64, f64), c: f32| (scale * c as f64 + shift) as f32;
        let mut logits = vec![0f32; self.run.u.len];
        for (part, (&(u, _), &fit)) in scores.iter().zip(&fits).enumerate() {
            for (&row, &c) in cf.rows_scored(part).iter().zip(u) {
                logits[row as usize] = apply(fit, c);
            }
        }
        let scores_n: Vec<f32> = match cf.labeled_folds {
            Some(_) => (scores.iter().zip(&fits))
                .flat_map(|(&(_, n), &fit)| n.iter().map(move |&c| apply(fit, c)))
                .collect(),
            None => {
                let rows_n = own_n.len();
                let mut from = vec![last; rows_n];
                let mut scored_before = 0usize;
                for part in 0..last {
                    let start = self.share_of(scored_before, rows_n);
                    scored_before += cf.rows_scored(part).len();
                    let end = self.share_of(scored_before, rows_n);
                    from[start..end].fill(part);
                }
                (0..rows_n).map(|i| apply(fits[from[i]], scores[from[i]].1[i])).collect()
            }
        };
        let labeled_rows: Vec<u32> = match cf.labeled_folds {
            Some(_) => (0..=last).flat_map(|part| cf.labeled_rows_scored(part, &[])).collect(),
            None => own_n_rows,
        };
        let episodes_n = episodes_of(&self.run.non_preferred().episode_ids, &labeled_rows);
        let pooled = (self.pooling_applies())
            .then(|| self.pooled_by_episode(&scores_n, &episodes_n, &logits));
        let (pooled_n, pooled_u) = pooled.unzip();
        let episodes = EpisodesOf { labeled: &episodes_n, mixture: &self.run.u.episode_ids };
        let auc = self.heldout_auc(&scores_n, &logits, episodes);
        let heldout = match (best_bin_estimate(&scores_n, &logits), auc) {
            (Some(alpha), Some(auc)) => {
                // The safety head's own discriminator is the last part's: its own fit
                // ([`Self::finished_part_members`] gives the others').
                let calibration = self.cfg.calibrate_discriminator.then_some(fits[last]);
                let alpha_by_episode =
                    bin_ratio_by_episode(&scores_n, &logits, alpha.threshold, episodes);
                let eq10_n = pooled_n;
                Some(HeldOut {
                    alpha,
                    auc,
                    calibration,
                    scores_n,
                    episodes_n,
                    alpha_by_episode,
                    eq10_n,
                })
            }
            _ => None,
        };
        Ok(Some(UnlabeledScores { logits, heldout, calibrated: true, eq10_logits: pooled_u }))
    }

    /// `pool_scores_by_episode`, where D^U's folds hold whole episodes: with fewer episodes the
    /// folds cut rows, so an episode's mean would read scores of discriminators that trained on
    /// its other rows, and a single episode would give every row the same score.
    fn pooling_applies(&self) -> bool {
        if !self.cfg.pool_scores_by_episode {
            return false;
        }
        let mut episodes = self.run.u.episode_ids.clone();
        episodes.sort_unstable();
        episodes.dedup();
        let applies = whole_episode_folds(self.cfg.cross_fit_folds as usize, episodes.len());
        if !applies {
            tracing::warn!(
                episodes = episodes.len(),
                "SafeDICE: D^U has too few episodes to pool the discriminator's scores by episode; Eq. 10 reads each row's own logit"
            );
        }
        applies
    }

    /// `pool_scores_by_episode`: held-out D^N's and D^U's scores replaced by their episodes'
    /// means, then recalibrated on those means (with `calibrate_discriminator`) so that Eq. 10
    /// reads the log-ratio of the means' densities ([`super::pooling`]). Returns D^N's and D^U's.
    fn pooled_by_episode(
        &self,
        scores_n: &[f32],
        episodes_n: &[u32],
        logits_u: &[f32],
    ) -> (Vec<f32>, Vec<f32>) {
        let (mut n, mut u) = (scores_n.to_vec(), logits_u.to_vec());
        pool_by_episode(&mut n, episodes_n);
        pool_by_episode(&mut u, &self.run.u.episode_ids);
        let (scale, shift) = self.recalibration(&n, &u);
        for c in n.iter_mut().chain(u.iter_mut()) {
            *c = (scale * *c as f64 + shift) as f32;
        }
        tracing::info!(scale, shift, "SafeDICE scores pooled by episode and recalibrated");
        (n, u)
    }

    /// How many of D^N's `rows_n` held-out rows go to the parts that score the first
    /// `scored_rows` rows of D^U (in part order).
    fn share_of(&self, scored_rows: usize, rows_n: usize) -> usize {
        let share = scored_rows as f64 / self.run.u.len.max(1) as f64;
        ((share * rows_n as f64).round() as usize).min(rows_n)
    }

    /// With `calibrate_discriminator`, the Platt fit of a discriminator's logits on held-out
    /// rows of D^N and D^U; `1, 0` without.
    fn recalibration(&self, n: &[f32], u: &[f32]) -> (f64, f64) {
        match self.cfg.calibrate_discriminator {
            true => platt_scaling(n, u),
            false => (1.0, 0.0),
        }
    }

    /// The finished parts' discriminators as the safety head's further members, each
    /// recalibrated as [`Self::cross_fitted`] read it; none without cross-fitting, before a part
    /// is done, or from a checkpoint written before their weights were kept.
    pub(super) fn finished_part_members(&self) -> Vec<Member> {
        let Some(cf) = self.cross_fit.as_ref() else { return Vec::new() };
        (cf.done.iter().filter(|d| !d.weights.is_empty()))
            .map(|d| {
                let (logit_scale, logit_shift) = self.recalibration(&d.n, &d.u);
                let recalibration = Recalibration { logit_scale, logit_shift };
                Member { weights: d.weights.clone(), recalibration }
            })
            .collect()
    }

    /// The finished parts' discriminators' logits on every row of `data` (raw, as
    /// [`Self::discriminator_logits`] gives the last part's), in the order of
    /// [`Self::finished_part_members`]; empty where that is.
    pub fn finished_part_discriminator_logits(
        &self,
        data: &Dataset,
    ) -> Result<Vec<Vec<f32>>, TrainError> {
        let members = self.finished_part_members();
        if members.is_empty() {
            return Ok(Vec::new());
        }
        let mut unused = ChaCha8Rng::seed_from_u64(0);
        let net =
            Mlp::new("discriminator", self.disc.dims(), false, &self.run.device, &mut unused)?;
        let columns = self.columns_of(data)?;
        let every_row: Vec<u32> = (0..columns.len as u32).collect();
        let mut out = Vec::with_capacity(members.len());
        for member in &members {
            net.load(&member.weights)?;
            out.push(logits_of(&net, &columns, &every_row)?);
        }
        Ok(out)
    }
}
