//! What the frozen discriminator's scores on held-out rows say, gathered for the weighting
//! stage: Best Bin Estimation's alpha-hat ([`super::mixture`]), the held-out AUC, the bin
//! counted by episode ([`super::bin_by_episode`]) and the recalibration; the uniform fallback's
//! test of identifiability reads them here.

use super::bin_by_episode::BinByEpisode;
use super::mixture::{Auc, MixtureEstimate};
use crate::algo::hyperparams::AlphaHatPoint;

/// Held-out statistics of the frozen discriminator (the `bbe` estimator).
pub struct HeldOut {
    pub alpha: MixtureEstimate,
    pub auc: Auc,
    /// `calibrate_discriminator`: Eq. 10 reads `scale · c + shift` (Platt scaling on these rows).
    pub calibration: Option<(f64, f64)>,
    /// The held-out D^N rows' scores as Best Bin Estimation read them, and their episodes: the
    /// kept share ([`super::kept_share`]) reads Eq. 10 on them.
    pub scores_n: Vec<f32>,
    pub episodes_n: Vec<u32>,
    /// The bin's ratio with episodes counted ([`super::bin_by_episode`]): reported, and
    /// alpha-hat's lower end with `alpha_hat_point: episodes_lower`.
    pub alpha_by_episode: Option<BinByEpisode>,
    /// With `pool_scores_by_episode`, the held-out D^N rows' logits as Eq. 10 reads them (their
    /// episodes' means, recalibrated); `scores_n` stays what Best Bin Estimation read.
    pub eq10_n: Option<Vec<f32>>,
}

impl AlphaHatPoint {
    /// The point of Best Bin Estimation's interval that alpha-hat takes (before its margin).
    pub fn of(self, heldout: &HeldOut) -> f64 {
        let bin = &heldout.alpha;
        match self {
            AlphaHatPoint::Estimate => bin.value,
            AlphaHatPoint::Lower => bin.lower,
            AlphaHatPoint::EpisodesLower => {
                heldout.alpha_by_episode.as_ref().map_or(bin.lower, |b| b.lower)
            }
        }
    }
}

impl HeldOut {
    /// Why D^N and D^U cannot be told apart on held-out rows, if they cannot: the AUC's interval
    /// covers 0.5, or alpha-hat's covers 1 (every row of D^U could be non-preferred).
    pub fn not_identifiable(&self) -> Option<String> {
        let (auc, a) = (&self.auc, &self.alpha);
        if auc.lower <= 0.5 {
            return Some(format!(
                "held-out AUC {:.3} [{:.3}, {:.3}] does not exclude 0.5",
                auc.value, auc.lower, auc.upper
            ));
        }
        (a.upper >= 1.0).then(|| {
            format!(
                "alpha-hat {:.3} [{:.3}, {:.3}] does not exclude 1 (held-out AUC {:.3})",
                a.value, a.lower, a.upper, auc.value
            )
        })
    }

    /// The share of the AUC's excess over ½ that its interval's lower end keeps: 1 where the
    /// separation is certain, 0 where the interval reaches ½ or the AUC is not above it.
    pub fn certain_separation(&self) -> f64 {
        let excess = self.auc.value - 0.5;
        if excess > 0.0 {
            ((self.auc.lower - 0.5) / excess).clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    pub fn metrics(&self) -> Vec<(&'static str, f64)> {
        let (a, auc) = (&self.alpha, &self.auc);
        let mut metrics = vec![
            ("alpha_hat_bin_ratio", a.value),
            ("alpha_hat_lower", a.lower),
            ("alpha_hat_upper", a.upper),
            ("alpha_hat_bin_threshold", a.threshold),
            ("alpha_hat_bin_share_dn", a.share_n),
            ("alpha_hat_bin_share_du", a.share_u),
            ("alpha_hat_rows_dn", a.rows_n as f64),
            ("alpha_hat_rows_du", a.rows_u as f64),
            ("discriminator_heldout_auc", auc.value),
            ("discriminator_heldout_auc_lower", auc.lower),
            ("discriminator_heldout_auc_upper", auc.upper),
        ];
        if let Some(b) = &self.alpha_by_episode {
            metrics.extend([
                ("alpha_hat_episodes_lower", b.lower),
                ("alpha_hat_episodes_upper", b.upper),
                ("alpha_hat_episodes_design_effect_dn", b.design_effect_labeled),
                ("alpha_hat_episodes_design_effect_du", b.design_effect_mixture),
            ]);
        }
        if let Some(d) = &auc.episodes {
            metrics.extend([
                ("discriminator_heldout_auc_episode_correlation", d.correlation),
                ("discriminator_heldout_auc_design_effect_dn", d.design_effect_labeled),
                ("discriminator_heldout_auc_design_effect_du", d.design_effect_mixture),
            ]);
        }
        if let Some((scale, shift)) = self.calibration {
            metrics.extend([
                ("discriminator_calibration_scale", scale),
                ("discriminator_calibration_shift", shift),
            ]);
        }
        metrics
    }
}
