//! Cross-fitting of the discriminator (`cross_fit`): Eq. 10 reads `c(s, a)` on every row of
//! D^U, and a discriminator scores the D^U rows it trained on (label "unlabeled") lower than
//! rows it never saw, non-preferred ones included: their reward is not low enough, and the
//! weights keep them. Here D^U's episodes go in two folds; the discriminator's step budget is
//! split in two halves, the first trains on fold 0 against D^N and scores fold 1, the second
//! (initialised afresh) trains on fold 1 and scores fold 0. Every row of D^U is then scored by a
//! discriminator that never trained on its episode, and Best Bin Estimation reads all of D^U
//! rather than a held-out fifth. Each half keeps its own early-stopping rule, measured on the
//! other fold; with `calibrate_discriminator` each half's logit is recalibrated on its own
//! held-out scores (Platt scaling) before the two are pooled, so both speak one scale.
//! docs/algorithm.md, "Cross-fitting", says what the development split showed.

use std::collections::HashMap;

use candle_core::Tensor;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::folds::FoldScores;
use super::mixture::{best_bin_estimate, platt_scaling, roc_auc, HeldOut};
use super::trainer::{logits_of, snapshot, SafediceTrainer};
use super::weighting::UnlabeledScores;
use crate::algo::discriminator_stop::EarlyStop;
use crate::algo::mlp::Mlp;
use crate::algo::optim::Adam;
use crate::algo::safety::{Member, Recalibration};
use crate::algo::TrainError;
use crate::data::Dataset;

impl SafediceTrainer {
    /// The step that ends the first half of the discriminator's budget (cross-fitting only).
    pub(super) fn first_half_end(&self) -> Option<u64> {
        self.cross_fit.as_ref().map(|_| self.cfg.discriminator_iterations / 2)
    }

    /// `step` counted from the start of the discriminator that trains at it: the early-stopping
    /// rule of each half counts its own steps.
    pub(super) fn steps_into_half(&self, step: u64) -> u64 {
        match self.first_half_end() {
            Some(half) if step > half => step - half,
            _ => step,
        }
    }

    /// The held-out rows of D^U and the stopping rule for the half that trains after `step`.
    pub(super) fn enter_half(&mut self, step: u64) {
        let (Some(half_end), Some(cf)) = (self.first_half_end(), self.cross_fit.as_ref()) else {
            return;
        };
        let budget = self.cfg.discriminator_iterations;
        let (half, steps) = if step < half_end { (0, half_end) } else { (1, budget - half_end) };
        let (holdout, labeled) = (cf.holdout(half), cf.labeled_holdout(half));
        if let Some(v) = self.disc_stop.as_mut() {
            v.u = holdout;
            if let Some(labeled) = labeled {
                v.n = labeled;
            }
            v.rule = EarlyStop::new(steps);
            v.best.clear();
        }
    }

    /// The first half is done: keep its (best) discriminator's scores on fold 1 and on D^N's
    /// held-out rows, then start the second half's discriminator from fresh weights and a fresh
    /// optimiser.
    pub(super) fn end_first_half(&mut self) -> Result<(), TrainError> {
        let Some(v) = self.disc_stop.as_ref() else { return Ok(()) };
        if !v.best.is_empty() {
            self.disc.load(&v.best)?;
        }
        let trained = snapshot(&self.disc)?;
        let Some(cf) = self.cross_fit.as_ref() else { return Ok(()) };
        let u = self.score_rows(&self.run.u, &cf.folds[1])?;
        let labeled = cf.labeled_rows_scored(0, &v.n.validation);
        let n = self.score_rows(self.run.non_preferred(), &labeled)?;
        tracing::info!(
            best_step = v.rule.best_step,
            heldout_loss = v.rule.best_loss,
            "SafeDICE discriminator, cross-fitting: first half done, fold 1 scored"
        );
        let seed = self.run.config.seed() ^ 0x5afe_d1ce_0000_00d1;
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
            cf.first = Some(FoldScores { u, n, weights: trained });
        }
        self.enter_half(self.cfg.discriminator_iterations);
        Ok(())
    }

    /// With cross-fitting, once both halves are done: every row of D^U's logit from the
    /// discriminator that did not train on it (each recalibrated on its own held-out scores
    /// with `calibrate_discriminator`), and Best Bin Estimation and the AUC on them.
    /// D^N's held-out rows are shared out between the two discriminators in the proportion
    /// their folds have in D^U, so the labeled scores come from the same mixture of the two
    /// score functions as D^U's; with `cross_fit_labeled` each discriminator scores its other
    /// fold of D^N, every row of it, and the two are pooled as they are (each fold about half
    /// of its set). None without cross-fitting.
    pub(super) fn cross_fitted(&self) -> Result<Option<UnlabeledScores>, TrainError> {
        let (Some(cf), Some(v)) = (self.cross_fit.as_ref(), self.disc_stop.as_ref()) else {
            return Ok(None);
        };
        let Some(first) = cf.first.as_ref() else { return Ok(None) };
        let second_u = self.score_rows(&self.run.u, &cf.folds[0])?;
        let second_n_rows = cf.labeled_rows_scored(1, &v.n.validation);
        let second_n = self.score_rows(self.run.non_preferred(), &second_n_rows)?;
        let fit = |n: &[f32], u: &[f32]| self.recalibration(n, u);
        let (first_fit, second_fit) = (fit(&first.n, &first.u), fit(&second_n, &second_u));
        let apply = |(scale, shift): (f64, f64), c: f32| (scale * c as f64 + shift) as f32;
        let mut logits = vec![0f32; self.run.u.len];
        for (&row, &c) in cf.folds[1].iter().zip(&first.u) {
            logits[row as usize] = apply(first_fit, c);
        }
        for (&row, &c) in cf.folds[0].iter().zip(&second_u) {
            logits[row as usize] = apply(second_fit, c);
        }
        let scores_n: Vec<f32> = match cf.labeled_folds {
            Some(_) => {
                let first_n = first.n.iter().map(|&c| apply(first_fit, c));
                first_n.chain(second_n.iter().map(|&c| apply(second_fit, c))).collect()
            }
            None => {
                let share_first = cf.folds[1].len() as f64 / self.run.u.len.max(1) as f64;
                let from_first = (share_first * first.n.len() as f64).round() as usize;
                (0..first.n.len())
                    .map(|i| match i < from_first {
                        true => apply(first_fit, first.n[i]),
                        false => apply(second_fit, second_n[i]),
                    })
                    .collect()
            }
        };
        let heldout = match (best_bin_estimate(&scores_n, &logits), roc_auc(&scores_n, &logits)) {
            (Some(alpha), Some(auc)) => {
                // The safety head's own discriminator is the second half's: its own fit
                // ([`Self::first_half_member`] gives the first's).
                let calibration = self.cfg.calibrate_discriminator.then_some(second_fit);
                Some(HeldOut { alpha, auc, calibration })
            }
            _ => None,
        };
        Ok(Some(UnlabeledScores { logits, heldout, calibrated: true }))
    }

    /// With `calibrate_discriminator`, the Platt fit of a discriminator's logits on held-out
    /// rows of D^N and D^U; `1, 0` without.
    fn recalibration(&self, n: &[f32], u: &[f32]) -> (f64, f64) {
        match self.cfg.calibrate_discriminator {
            true => platt_scaling(n, u),
            false => (1.0, 0.0),
        }
    }

    /// The first half's discriminator as the safety head's second member, recalibrated as
    /// [`Self::cross_fitted`] read it; None without cross-fitting, before the first half is done,
    /// or from a checkpoint written before its weights were kept.
    pub(super) fn first_half_member(&self) -> Option<Member> {
        let first = self.cross_fit.as_ref()?.first.as_ref()?;
        if first.weights.is_empty() {
            return None;
        }
        let (logit_scale, logit_shift) = self.recalibration(&first.n, &first.u);
        let recalibration = Recalibration { logit_scale, logit_shift };
        Some(Member { weights: first.weights.clone(), recalibration })
    }

    /// The first half's discriminator's logits on every row of `data` (raw, as
    /// [`Self::discriminator_logits`] gives the second's); None where
    /// [`Self::first_half_member`] is.
    pub fn first_half_discriminator_logits(
        &self,
        data: &Dataset,
    ) -> Result<Option<Vec<f32>>, TrainError> {
        let Some(member) = self.first_half_member() else { return Ok(None) };
        let mut unused = ChaCha8Rng::seed_from_u64(0);
        let net =
            Mlp::new("discriminator", self.disc.dims(), false, &self.run.device, &mut unused)?;
        net.load(&member.weights)?;
        let columns = self.columns_of(data)?;
        let every_row: Vec<u32> = (0..columns.len as u32).collect();
        Ok(Some(logits_of(&net, &columns, &every_row)?))
    }
}
