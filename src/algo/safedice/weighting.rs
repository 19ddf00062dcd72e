//! Algorithm 1 steps 2-3 on the frozen discriminator, and what follows from them: alpha-hat
//! (Eq. 15: the paper's minimum, or Best Bin Estimation on held-out episodes with the logit
//! recalibrated, [`super::mixture`]), Eq. 10's reward on every row of D^U (its −∞ rows
//! excluded or floored), and the uniform fallback that trains as BC when the held-out data
//! cannot tell D^N from D^U. docs/algorithm.md, "2. alpha-hat" and "3. Reward", says why.

use rand::SeedableRng;

use super::bin_by_episode::{bin_ratio_by_episode, BinByEpisode};
use super::draws::FlowColumns;
use super::heldout::HeldOut;
use super::kept_share::{kept_share, KeptShare, Rewarded};
use super::mixture::{
    best_bin_estimate, platt_scaling, roc_auc, roc_auc_by_episode, Auc, EpisodesOf,
};
use super::objectives::{alpha_hat_from_logits, eq10_rewards, ALPHA_MARGIN, POLICY_LOSS};
use super::trainer::{SafediceTrainer, UniformWeights};
use crate::algo::bc::bc_loss;
use crate::algo::fused_policy::{fused_policy_step, fused_policy_update};
use crate::algo::hyperparams::{
    AlphaEstimator, AlphaHatPoint, AucInterval, BbeUnlabeledRows, TopBin,
};
use crate::algo::optim::Adam;
use crate::algo::{Algorithm, ResolvedConfig, TrainError};

/// The discriminator's logits on every row of D^U, the held-out statistics alpha-hat reads,
/// and whether the logits are recalibrated already (cross-fitted: each half on its own fit).
/// With `pool_scores_by_episode`, `eq10_logits` are what Eq. 10 reads instead of `logits`
/// (each row's episode's mean, recalibrated); alpha-hat, its bin and the fallback read `logits`.
pub(super) struct UnlabeledScores {
    pub(super) logits: Vec<f32>,
    pub(super) heldout: Option<HeldOut>,
    pub(super) calibrated: bool,
    pub(super) eq10_logits: Option<Vec<f32>>,
}

impl SafediceTrainer {
    /// Algorithm 1 step 2 and the reward of Eq. 10 over all of D^U, with the frozen discriminator.
    pub(super) fn finish_discriminator_phase(&mut self) -> Result<(), TrainError> {
        let UnlabeledScores { mut logits, heldout, calibrated, eq10_logits } =
            self.unlabeled_scores()?;
        // The bin's rows, on the scores Best Bin Estimation read (before a recalibration here).
        let in_bin: Vec<bool> = match &heldout {
            Some(h) if self.cfg.top_bin != TopBin::RowLogits => {
                logits.iter().map(|&c| c as f64 >= h.alpha.threshold).collect()
            }
            _ => Vec::new(),
        };
        let episode_ids = &self.run.u.episode_ids;
        let mut alpha = alpha_hat_from_logits(&logits, episode_ids, self.cfg.alpha_hat_quantile);
        // The paper's statistic above reads the discriminator as trained; Eq. 10 reads it
        // recalibrated (cross-fitted logits already are).
        if let Some((scale, shift)) = heldout.as_ref().and_then(|h| h.calibration) {
            if !calibrated {
                logits.iter_mut().for_each(|c| *c = (scale * *c as f64 + shift) as f32);
            }
        }
        // Pooled, Eq. 10 reads the episode's evidence; the bin above stays each row's own.
        let pooled = eq10_logits.is_some();
        if let Some(pooled_logits) = eq10_logits {
            logits = pooled_logits;
        }
        if let Some(h) = &heldout {
            let point = self.cfg.alpha_hat_point.of(h);
            alpha.value = (point - ALPHA_MARGIN).clamp(0.0, 1.0 - ALPHA_MARGIN);
        }
        // `bin_ratio_own_scale` standardises on the rows' own logits, before the bin is raised.
        let own_logits = (self.cfg.top_bin == TopBin::BinRatioOwnScale).then(|| logits.clone());
        let raised = match (self.cfg.top_bin, &heldout) {
            (TopBin::BinRatio | TopBin::BinRatioOwnScale, Some(h)) => {
                raise_to_bin_ratio(&mut logits, &in_bin, h.alpha.value)
            }
            _ => 0,
        };
        let ruled_out = if self.cfg.top_bin == TopBin::RuledOut { &in_bin[..] } else { &[] };
        let estimated = alpha.value;
        if let Some(a) = self.overrides.alpha {
            alpha.value = a.clamp(0.0, 1.0 - ALPHA_MARGIN);
        }
        let eq10 = eq10_rewards(
            &logits,
            own_logits.as_deref().unwrap_or(&[]),
            alpha.value,
            self.cfg.undefined_reward,
            self.cfg.excluded_reward_gap,
            self.cfg.standardize_reward,
            ruled_out,
        );
        let strength = self.weighting_strength(heldout.as_ref());
        let scale = self.cfg.reward_scale * strength.unwrap_or(1.0);
        let kept = heldout.as_ref().and_then(|h| {
            let logits_n = self.heldout_eq10_logits(h, calibrated);
            let ruled_out_n: Vec<bool> = match self.cfg.top_bin {
                TopBin::RuledOut => {
                    h.scores_n.iter().map(|&c| c as f64 >= h.alpha.threshold).collect()
                }
                _ => Vec::new(),
            };
            let rewards_n: Vec<f64> =
                eq10.map.rewards(&logits_n, &ruled_out_n).into_iter().map(|r| scale * r).collect();
            let rewards_u: Vec<f64> = eq10.rewards.iter().map(|r| scale * r).collect();
            kept_share(
                Rewarded { rewards: &rewards_n, episodes: &h.episodes_n },
                Rewarded { rewards: &rewards_u, episodes: &self.run.u.episode_ids },
                self.cfg.policy_uniform_share,
            )
        });
        if let Some(bad) = eq10.rewards.iter().position(|r| !r.is_finite()) {
            return Err(TrainError::Diverged {
                step: self.run.step,
                message: format!(
                    "the Eq. 10 reward of D^U row {bad} is not finite (alpha-hat {})",
                    alpha.value
                ),
            });
        }
        tracing::info!(
            alpha_hat = alpha.value,
            estimator = ?self.cfg.alpha_hat_estimator,
            argmin_row = alpha.argmin_row,
            argmin_episode = alpha.argmin_episode,
            quantile_01 = alpha.quantile_01,
            "SafeDICE alpha-hat (Eq. 15)"
        );
        self.phase_metrics = vec![
            ("alpha_hat", alpha.value),
            ("alpha_hat_min_ratio", alpha.min_ratio),
            ("alpha_hat_argmin_row", alpha.argmin_row as f64),
            ("alpha_hat_argmin_episode", alpha.argmin_episode as f64),
            ("alpha_hat_q01_diagnostic_not_paper", alpha.quantile_01),
            ("reward_mean", eq10.mean),
            ("reward_std", eq10.std),
            ("reward_clipped_rows", eq10.undefined_rows as f64),
        ];
        if let Some(h) = &heldout {
            self.phase_metrics.extend(h.metrics());
        }
        if let Some(strength) = strength {
            self.phase_metrics.push(("weighting_strength", strength));
        }
        if let Some(k) = &kept {
            self.phase_metrics.extend([
                ("weighting_kept_dn_share", k.value),
                ("weighting_kept_dn_share_upper", k.upper),
                ("weighting_kept_dn_share_design_effect", k.design_effect),
            ]);
        }
        if calibrated {
            self.phase_metrics.push(("discriminator_cross_fitted", 1.0));
            if self.cfg.pool_scores_by_episode {
                let value = f64::from(u8::from(pooled));
                self.phase_metrics.push(("discriminator_scores_pooled_by_episode", value));
            }
        }
        if !in_bin.is_empty() {
            let rows = in_bin.iter().filter(|&&flag| flag).count();
            self.phase_metrics.push(("top_bin_rows", rows as f64));
            self.phase_metrics.push(("top_bin_rows_raised", raised as f64));
        }
        if self.overrides.alpha.is_some() {
            self.phase_metrics.push(("alpha_hat_estimated", estimated));
        }
        if self.overrides.unlabeled_logits.is_some() {
            self.phase_metrics.push(("discriminator_outputs_given", 1.0));
        }
        let uninformative = if eq10.undefined_rows == logits.len() {
            Some("Eq. 10 is undefined on every row".to_string())
        } else {
            // Unstandardised, alpha-hat 0 makes Eq. 10 exactly 0 everywhere (standardised, it
            // weights by the limit as α → 0+): uniform weights, at SafeDICE's lower learning
            // rate and with ν's noise, unless the run trains as BC itself.
            (eq10.std == 0.0).then(|| {
                format!("Eq. 10's reward is the same on every row (alpha-hat {:.4}), so there is nothing to weight", alpha.value)
            })
        };
        self.decide_weighting(heldout.as_ref(), kept.as_ref(), uninformative)?;
        self.heldout = heldout;
        let rewards: Vec<f32> = eq10.rewards.iter().map(|&r| (scale * r) as f32).collect();
        self.flow = Some(FlowColumns::build(&self.run.u, rewards, &self.cfg)?);
        self.alpha = Some(alpha);
        Ok(())
    }

    /// What multiplies `reward_scale`: with `weighting_strength_from_auc`, the share of the
    /// held-out AUC's excess over ½ that its interval makes certain; `None` (nothing applied)
    /// otherwise, and where no held-out statistics exist (the paper's estimator, given logits).
    fn weighting_strength(&self, heldout: Option<&HeldOut>) -> Option<f64> {
        match heldout {
            Some(h) if self.cfg.weighting_strength_from_auc => {
                let strength = h.certain_separation();
                tracing::info!(
                    strength,
                    auc = h.auc.value,
                    auc_lower = h.auc.lower,
                    "SafeDICE weighting strength from the held-out AUC"
                );
                Some(strength)
            }
            _ => None,
        }
    }

    /// Held-out D^N's logits as Eq. 10 reads D^U's: pooled by episode where D^U's are,
    /// recalibrated (unless the scores are already), and raised to the bin's ratio in Best Bin Estimation's bin under `bin_ratio`.
    fn heldout_eq10_logits(&self, h: &HeldOut, calibrated: bool) -> Vec<f32> {
        let in_bin: Vec<bool> = h.scores_n.iter().map(|&c| c as f64 >= h.alpha.threshold).collect();
        let mut logits = h.eq10_n.clone().unwrap_or_else(|| h.scores_n.clone());
        if let (Some((scale, shift)), false) = (h.calibration, calibrated) {
            logits.iter_mut().for_each(|c| *c = (scale * *c as f64 + shift) as f32);
        }
        if matches!(self.cfg.top_bin, TopBin::BinRatio | TopBin::BinRatioOwnScale) {
            raise_to_bin_ratio(&mut logits, &in_bin, h.alpha.value);
        }
        logits
    }

    /// The discriminator's logits on every row of D^U (given ones in the oracle ablation,
    /// cross-fitted ones with `cross_fit`) and the held-out statistics.
    fn unlabeled_scores(&self) -> Result<UnlabeledScores, TrainError> {
        if let Some(given) = &self.overrides.unlabeled_logits {
            let logits = given.clone();
            return Ok(UnlabeledScores {
                logits,
                heldout: None,
                calibrated: false,
                eq10_logits: None,
            });
        }
        if let Some(cross_fitted) = self.cross_fitted()? {
            return Ok(cross_fitted);
        }
        let logits = self.score(&self.run.u)?;
        let heldout = self.heldout_statistics(&logits)?;
        Ok(UnlabeledScores { logits, heldout, calibrated: false, eq10_logits: None })
    }

    /// With the `bbe` estimator: the frozen discriminator's scores on the held-out rows of D^N
    /// and D^U, Best Bin Estimation of alpha-hat on them (or on every row of D^U, `logits_u`,
    /// for the mixture's side with `bbe_unlabeled_rows: all`) and their ROC AUC.
    fn heldout_statistics(&self, logits_u: &[f32]) -> Result<Option<HeldOut>, TrainError> {
        // Given logits (the oracle ablation) are a discriminator of their own: Eq. 15 on them.
        let given = self.overrides.unlabeled_logits.is_some();
        if self.cfg.alpha_hat_estimator != AlphaEstimator::Bbe || given {
            return Ok(None);
        }
        let Some(v) = &self.disc_stop else { return Ok(None) };
        let scores_n = self.score_rows(self.run.non_preferred(), &v.n.validation)?;
        let scores_u = self.score_rows(&self.run.u, &v.u.validation)?;
        let episodes_n = episodes_of(&self.run.non_preferred().episode_ids, &v.n.validation);
        let episodes_u = episodes_of(&self.run.u.episode_ids, &v.u.validation);
        let episodes = EpisodesOf { labeled: &episodes_n, mixture: &episodes_u };
        let (mixture, mixture_episodes) = match self.cfg.bbe_unlabeled_rows {
            BbeUnlabeledRows::HeldOut => (&scores_u[..], episodes),
            BbeUnlabeledRows::All => {
                (logits_u, EpisodesOf { mixture: &self.run.u.episode_ids, ..episodes })
            }
        };
        let (Some(alpha), Some(auc)) = (
            best_bin_estimate(&scores_n, mixture),
            self.heldout_auc(&scores_n, &scores_u, episodes),
        ) else {
            return Ok(None);
        };
        let calibration =
            self.cfg.calibrate_discriminator.then(|| platt_scaling(&scores_n, &scores_u));
        let alpha_by_episode =
            bin_ratio_by_episode(&scores_n, mixture, alpha.threshold, mixture_episodes);
        let eq10_n = None;
        Ok(Some(HeldOut {
            alpha,
            auc,
            calibration,
            scores_n,
            episodes_n,
            alpha_by_episode,
            eq10_n,
        }))
    }

    /// The held-out ROC AUC of D^N's scores against D^U's, its interval counting rows or
    /// episodes as `auc_interval` says.
    pub(super) fn heldout_auc(
        &self,
        scores_n: &[f32],
        scores_u: &[f32],
        episodes: EpisodesOf,
    ) -> Option<Auc> {
        match self.cfg.auc_interval {
            AucInterval::Rows => roc_auc(scores_n, scores_u),
            AucInterval::Episodes => roc_auc_by_episode(scores_n, scores_u, episodes),
        }
    }

    /// `uniform_fallback`: uniform weights (BC) when the held-out data cannot identify the
    /// mixture, with the reason in the metrics and the log.
    fn decide_weighting(
        &mut self,
        heldout: Option<&HeldOut>,
        kept: Option<&KeptShare>,
        uninformative_reward: Option<String>,
    ) -> Result<(), TrainError> {
        let ablation = self.overrides.alpha.is_some() || self.overrides.unlabeled_logits.is_some();
        let bbe = self.cfg.alpha_hat_estimator == AlphaEstimator::Bbe;
        if !self.cfg.uniform_fallback || !bbe || ablation {
            return Ok(());
        }
        let reason = match heldout {
            None => Some("no held-out rows to estimate alpha-hat on".to_string()),
            Some(h) => h.not_identifiable(),
        }
        .or(uninformative_reward)
        .or_else(|| kept.filter(|_| self.cfg.kept_share_test).and_then(weights_keep_dn));
        self.phase_metrics.push(("weighting_uniform", f64::from(u8::from(reason.is_some()))));
        let Some(reason) = reason else { return Ok(()) };
        tracing::warn!(reason = %reason, "weighting: uniform, {reason}; SafeDICE trains as BC");
        let fused = match self.fused {
            Some(_) => fused_policy_step(&self.run, self.policy.mlp())?,
            None => None,
        };
        self.uniform = Some(UniformWeights { reason, fused });
        Ok(())
    }

    /// The main loop's step with uniform weights: BC's loss on a batch of D^U.
    pub(super) fn uniform_step(
        &mut self,
        record: bool,
    ) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let idx = self.run.sample_u()?;
        let obs = self.run.u.obs.index_select(&idx, 0)?;
        let actions = self.run.u.actions.select(&idx)?;
        let uniform = self.uniform.as_mut().expect("uniform weighting");
        let value = match &mut uniform.fused {
            Some(fused) => fused_policy_update(
                fused,
                &self.run,
                self.policy.mlp(),
                &mut self.policy_opt,
                &obs,
                &actions,
                None,
                POLICY_LOSS,
            )?,
            None => {
                let loss = bc_loss(&self.policy, &obs, &actions)?;
                let value = self.run.checked(&loss, POLICY_LOSS.0, POLICY_LOSS.1)?;
                self.policy_opt.minimize(&loss)?;
                value
            }
        };
        self.run.step += 1;
        let mut metrics = std::mem::take(&mut self.phase_metrics);
        if record {
            metrics.extend([
                ("policy_loss", value),
                ("alpha_hat", self.alpha.as_ref().map_or(f64::NAN, |a| a.value)),
                ("ess_fraction", 1.0),
                ("weighting_uniform", 1.0),
            ]);
        }
        Ok(metrics)
    }

    /// The policy's learning rate in the uniform fallback: a BC job's of the same preset, since
    /// SafeDICE's own default is set lower for its weighted loss; an `lr_actor` the run set
    /// itself is kept.
    pub(super) fn fallback_lr_actor(&self) -> f64 {
        let common = &self.run.config.common;
        let preset = |algorithm| ResolvedConfig::preset(algorithm, common.preset).common.lr_actor;
        if common.lr_actor == preset(Algorithm::Safedice) {
            preset(Algorithm::Bc)
        } else {
            common.lr_actor
        }
    }

    /// The uniform fallback from its first step: the policy, its optimiser and the random stream
    /// start again exactly as a BC job of the same seed and config does (`RunData::new`, then
    /// `new_policy`), so the policy it ends with is BC's, bit for bit. Only the live phase end
    /// calls it; a resume restores the restarted stream and policy from the checkpoint.
    pub(super) fn restart_policy_as_bc(&mut self) -> Result<(), TrainError> {
        self.run.rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.run.config.seed());
        self.policy = self.run.new_policy("policy")?;
        self.policy_opt = Adam::new(self.policy.mlp().named_vars(), self.fallback_lr_actor())?;
        if let Some(u) = self.uniform.as_mut() {
            if u.fused.is_some() {
                u.fused = fused_policy_step(&self.run, self.policy.mlp())?;
            }
        }
        Ok(())
    }

    /// How alpha-hat was estimated, in words for the job log ([`Trainer::alpha_hat_detail`]).
    pub(super) fn describe_alpha_hat(&self) -> Option<String> {
        let alpha = self.alpha.as_ref()?;
        Some(match &self.heldout {
            Some(HeldOut { alpha: bin, auc, alpha_by_episode, .. }) => format!(
                "Best Bin Estimation on {}: {:.4} ({}), 90% interval [{:.3}, {:.3}] around the bin's ratio {:.3}{}, from the {:.0}% of held-out D^N rows scoring at least {:.3} (and {:.0}% of D^U's); held-out AUC {:.3} [{:.3}, {:.3}]; the paper's minimum over D^U would be {:.4}",
                self.scored_rows_words(), alpha.value, self.alpha_point_words(), bin.lower, bin.upper, bin.value,
                episodes_words(alpha_by_episode.as_ref()), 100.0 * bin.share_n, bin.threshold,
                100.0 * bin.share_u, auc.value, auc.lower, auc.upper, alpha.min_ratio
            ),
            None => format!(
                "the minimum of 1/c - 1 over D^U (the paper), at row {} of episode {}",
                alpha.argmin_row, alpha.argmin_episode
            ),
        })
    }

    fn scored_rows_words(&self) -> &'static str {
        match &self.cross_fit {
            Some(cf) if cf.labeled_folds.is_some() => "every row of D^U and of D^N, each scored by the discriminator that did not train on its episode (cross-fitted)",
            Some(_) => "every row of D^U, each scored by the discriminator that did not train on its episode (cross-fitted)",
            None => "held-out episodes",
        }
    }

    fn alpha_point_words(&self) -> &'static str {
        match self.cfg.alpha_hat_point {
            AlphaHatPoint::Estimate => "the bin's ratio",
            AlphaHatPoint::Lower => "the interval's lower end",
            AlphaHatPoint::EpisodesLower => "the lower end of its interval counting episodes",
        }
    }
}

/// `top_bin: bin_ratio`: on the bin's rows, the (recalibrated) logit becomes at least the bin's
/// log density ratio `ln(q_N/q_U) = −ln(ratio)`; nothing changes without D^U rows in the bin.
/// Returns how many logits rose.
fn raise_to_bin_ratio(logits: &mut [f32], in_bin: &[bool], ratio: f64) -> usize {
    if ratio <= 0.0 {
        return 0;
    }
    let bin_logit = (-ratio.ln()) as f32;
    let mut raised = 0;
    for (c, _) in logits.iter_mut().zip(in_bin).filter(|(_, &flag)| flag) {
        if *c < bin_logit {
            *c = bin_logit;
            raised += 1;
        }
    }
    raised
}

/// The bin's interval with episodes counted, for the job log: BBE's own counts rows.
fn episodes_words(by_episode: Option<&BinByEpisode>) -> String {
    by_episode.map_or_else(String::new, |b| {
        format!(" ([{:.3}, {:.3}] counting episodes)", b.lower, b.upper)
    })
}

/// Why the weighting is no better than noise, if it is not: the interval of the share of D^N's
/// mass that Eq. 10's weights keep reaches 1 (or is not a number).
fn weights_keep_dn(kept: &KeptShare) -> Option<String> {
    let shown_below_one = kept.upper < 1.0;
    (!shown_below_one).then(|| {
        format!(
            "Eq. 10's weights keep {:.3} of held-out D^N's share (upper end {:.3}, design effect {:.1}): they cannot be shown to remove non-preferred rows",
            kept.value, kept.upper, kept.design_effect
        )
    })
}

/// The episode of each of `rows` (rows of a set whose episodes are `episode_ids`).
pub(super) fn episodes_of(episode_ids: &[u32], rows: &[u32]) -> Vec<u32> {
    rows.iter().map(|&row| episode_ids[row as usize]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The kept share's test fires when its interval reaches 1, and says with what numbers.
    #[test]
    fn weights_that_may_keep_all_of_d_n_are_reported() {
        let kept = |value, upper| KeptShare { value, upper, design_effect: 40.0 };
        assert_eq!(weights_keep_dn(&kept(0.4, 0.99)), None);
        assert!(weights_keep_dn(&kept(f64::NAN, f64::NAN)).is_some(), "NaN is no evidence");
        let reason = weights_keep_dn(&kept(0.62, 1.06)).unwrap();
        assert!(reason.starts_with("Eq. 10's weights keep 0.620 of held-out D^N's share (upper end 1.060, design effect 40.0)"), "{reason}");
    }

    /// On the bin's rows the logit rises to the bin's `ln(q_N/q_U)` and never falls; off the bin,
    /// and with an empty bin (ratio 0), nothing moves. At alpha-hat the bin's ratio Eq. 10 then
    /// sits at its edge on every row of the bin.
    #[test]
    fn bin_rows_read_at_least_the_bins_density_ratio() {
        let ratio = 0.6f64;
        let mut logits = [-1.0f32, 2.0, 0.1, -3.0];
        let in_bin = [true, true, false, false];
        assert_eq!(raise_to_bin_ratio(&mut logits, &in_bin, ratio), 1);
        let bin_logit = -(ratio.ln()) as f32;
        assert_eq!(logits, [bin_logit, 2.0, 0.1, -3.0]);
        let edge = 1.0 - ratio * (logits[0] as f64).exp();
        assert!(edge.abs() < 1e-6, "1 − α e^c = {edge}");
        let mut empty = [-1.0f32, 2.0];
        assert_eq!(raise_to_bin_ratio(&mut empty, &[true, true], 0.0), 0);
        assert_eq!(empty, [-1.0, 2.0]);
    }
}
