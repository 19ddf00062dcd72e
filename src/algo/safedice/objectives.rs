//! The paper's equations for SafeDICE, each once, as candle tensor code (the losses) or plain
//! arithmetic (alpha-hat and the reward): Eq. 9 (discriminator), Eq. 10 (reward from the
//! discriminator), Eq. 15 (alpha-hat), Eq. 36 (ν) and Eq. 37 (policy). The reference trainer
//! ([`super::trainer`]) differentiates the losses with candle autograd; the fused engine
//! ([`super::fused`]) is checked against them in its tests.

use candle_core::Tensor;

use crate::algo::hyperparams::UndefinedReward;
use crate::algo::losses::{neg_log_one_minus_sigmoid, neg_log_sigmoid, weighted_nll};

/// Alpha-hat's margin below the minimum and its cap, as in the authors' code.
pub(crate) const ALPHA_MARGIN: f64 = 1e-5;
/// Added to the mean of the masked policy weights before dividing by it (a batch of
/// absorbing-state rows only has no weight left to renormalise); shared with the fused engine.
pub(crate) const MASK_RENORM_EPS: f64 = 1e-12;
/// Floor of `1 − α e^c` inside Eq. 10's log; reached only with the quantile diagnostic.
const REWARD_LOG_FLOOR: f64 = 1e-8;
/// Names and hints of the non-finite guard, shared by the candle and the fused paths.
pub(crate) const DISC_LOSS: (&str, &str) =
    ("the discriminator loss (Eq. 9)", "Try a lower lr_discriminator.");
pub(crate) const NU_LOSS: (&str, &str) = (
    "the nu loss (Eq. 36)",
    "Episodes that end in terminal states make Eq. 36 unbounded below: try terminal_handling \"reset\", standardize_reward true, or a lower lr_nu (the authors' code uses 1e-4).",
);
pub(crate) const POLICY_LOSS: (&str, &str) = (
    "the policy loss (Eq. 37)",
    "Try a lower lr_actor, or check the weight statistics (ess_fraction) for degeneracy.",
);

/// Eq. 9's loss for a batch of discriminator logits: `−mean log σ(c_N) − mean log(1 − σ(c_U))`
/// (σ(c) is the probability that (s, a) is non-preferred).
pub fn discriminator_loss(logits_n: &Tensor, logits_u: &Tensor) -> candle_core::Result<Tensor> {
    neg_log_sigmoid(logits_n)?.mean_all()? + neg_log_one_minus_sigmoid(logits_u)?.mean_all()?
}

/// Eq. 36: `log E_{D^U}[exp A] + (1 − γ) E_{p0}[ν(s0)]`, with `A = r + γ' ν(s') − ν(s)` already
/// formed (γ' per row, see [`TerminalHandling`]). The log-mean-exp is computed stably.
pub fn nu_loss(
    advantages: &Tensor,
    nu_initial: &Tensor,
    gamma: f64,
) -> candle_core::Result<Tensor> {
    let b = advantages.dim(0)? as f64;
    let log_mean_exp = (advantages.log_sum_exp(0)? - b.ln())?;
    log_mean_exp + (nu_initial.mean_all()? * (1.0 - gamma))?
}

/// Eq. 37: `−mean(w̃ log π) / mean(w̃)` with self-normalised, detached weights (optionally
/// masked: absorbing-state rows have no action).
pub fn policy_loss(log_prob: &Tensor, weights: &Tensor) -> candle_core::Result<Tensor> {
    weighted_nll(log_prob, weights)
}

/// Eq. 37's weights `w` (mean 1 over the batch) with a share `m` spread evenly over the rows:
/// `(1 − m) w + m`, still of mean 1 (the `policy_uniform_share` knob). The fused engine calls
/// it per row; the candle trainer applies the same map as `affine(1 − m, m)`.
pub fn with_uniform_share(w: f32, share: f32) -> f32 {
    (1.0 - share) * w + share
}

/// Eq. 10 written with the discriminator logit `c` (σ(c) = c* of the paper):
/// `log((1 − (1+α)σ) / ((1−α)(1−σ))) = log(1 − α e^c) − log(1 − α)`, exact and free of the
/// cancellations of the sigmoid form. Returns the reward and whether `1 − α e^c` had to be
/// floored (impossible with the paper's alpha-hat, which makes it positive on all of D^U).
pub fn reward_from_logit(c: f64, alpha: f64) -> (f64, bool) {
    let inside = 1.0 - alpha * c.exp();
    let clipped = inside < REWARD_LOG_FLOOR;
    ((inside.max(REWARD_LOG_FLOOR)).ln() - (1.0 - alpha).ln(), clipped)
}

/// Eq. 10 on every row of D^U, with the option's treatment of undefined rows and the optional
/// standardisation.
#[derive(Clone, Debug, PartialEq)]
pub struct Eq10Rewards {
    pub rewards: Vec<f64>,
    /// Mean and standard deviation of the raw reward over the rows it is defined on (all rows,
    /// floored, with [`UndefinedReward::Floor`]); of the rows' own logits' rewards where
    /// `scale_from` gives those.
    pub mean: f64,
    pub std: f64,
    /// Rows where `1 − α e^c` fell below the floor: floored, or excluded.
    pub undefined_rows: usize,
    /// The map from a logit to its reward that made `rewards`, to read other rows (held-out
    /// D^N) exactly as D^U's were read.
    pub map: Eq10Map,
}

/// Eq. 10 at one alpha with one treatment of its undefined rows and one standardisation: what
/// [`eq10_rewards`] fixed from D^U's rows, applied to any logit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Eq10Map {
    alpha: f64,
    standardize: bool,
    exclude: bool,
    mean: f64,
    std: f64,
    /// The reward of an excluded row: `gap` below the lowest defined reward of D^U.
    excluded: f64,
}

impl Eq10Map {
    /// Eq. 10's reward of each logit, read as D^U's rows were (`ruled_out` as in
    /// [`eq10_rewards`]).
    pub fn rewards(&self, logits: &[f32], ruled_out: &[bool]) -> Vec<f64> {
        let raw = raw_eq10(logits, self.alpha, self.standardize, ruled_out);
        raw.into_iter().map(|row| self.reward(row)).collect()
    }

    fn reward(&self, (raw, undefined): (f64, bool)) -> f64 {
        if self.exclude && undefined {
            self.excluded
        } else {
            self.scale(raw)
        }
    }

    fn scale(&self, raw: f64) -> f64 {
        if self.standardize {
            (raw - self.mean) / (self.std + 1e-8)
        } else {
            raw
        }
    }
}

/// Eq. 10 for every logit of D^U at `alpha`; with [`UndefinedReward::Exclude`] the rows where
/// Eq. 10 is −∞ stay out of the standardisation and sit `gap` below the lowest defined reward
/// ([`super::config::EXCLUDED_REWARD_GAP`] by default).
///
/// At `alpha` 0 Eq. 10 is 0 on every row, yet its standardisation has a limit as α → 0+:
/// `log(1 − α e^c) − log(1 − α) = −α (e^c − 1) + O(α²)`, whose standardisation is that of
/// `−e^c`. With `standardize`, alpha-hat 0 weights by that limit ([`eq10_limit_at_zero`]), so
/// alpha-hat 0 and 1e-6 train alike instead of one of them falling off a cliff to BC.
///
/// `ruled_out` flags rows to treat as undefined whatever their logit (`rule_out_top_bin`:
/// the rows in Best Bin Estimation's bin, where `d^P = 0` up to the estimator's error); empty,
/// none.
///
/// `scale_from`, when not empty, holds each row's own logit where `logits` holds what Eq. 10
/// reads (`top_bin: bin_ratio_own_scale`, which raises the bin's rows only): the
/// standardisation's mean and deviation then come from the own logits' rewards, so raising the
/// bin lowers the bin's rewards and moves no other row's, as it does without the
/// standardisation.
pub fn eq10_rewards(
    logits: &[f32],
    scale_from: &[f32],
    alpha: f64,
    undefined: UndefinedReward,
    gap: f64,
    standardize: bool,
    ruled_out: &[bool],
) -> Eq10Rewards {
    let raw = raw_eq10(logits, alpha, standardize, ruled_out);
    let own = (!scale_from.is_empty()).then(|| raw_eq10(scale_from, alpha, standardize, ruled_out));
    let undefined_rows = raw.iter().filter(|r| r.1).count();
    let exclude = undefined == UndefinedReward::Exclude;
    let defined = |rows: &[(f64, bool)]| -> Vec<f64> {
        rows.iter().filter(|r| !(exclude && r.1)).map(|r| r.0).collect()
    };
    let (mean, std) = mean_std(&defined(own.as_deref().unwrap_or(&raw)));
    let mut map = Eq10Map { alpha, standardize, exclude, mean, std, excluded: 0.0 };
    let lowest = defined(&raw).into_iter().map(|r| map.scale(r)).fold(f64::INFINITY, f64::min);
    if lowest.is_finite() {
        map.excluded = lowest - gap;
    }
    let rewards = raw.into_iter().map(|row| map.reward(row)).collect();
    Eq10Rewards { rewards, mean, std, undefined_rows, map }
}

/// Eq. 10 (or its limit at α = 0, standardised) on every logit, with whether the row is
/// undefined: past Eq. 10's edge, or flagged in `ruled_out`.
fn raw_eq10(logits: &[f32], alpha: f64, standardize: bool, ruled_out: &[bool]) -> Vec<(f64, bool)> {
    let mut raw: Vec<(f64, bool)> = if alpha == 0.0 && standardize {
        logits.iter().map(|&c| (eq10_limit_at_zero(c as f64), false)).collect()
    } else {
        logits.iter().map(|&c| reward_from_logit(c as f64, alpha)).collect()
    };
    for (row, _) in raw.iter_mut().zip(ruled_out).filter(|(_, &flag)| flag) {
        *row = ((REWARD_LOG_FLOOR).ln() - (1.0 - alpha).ln(), true);
    }
    raw
}

/// Eq. 10's shape as α → 0+, up to the factor α and a constant, which a standardisation
/// removes: `−e^c`.
pub fn eq10_limit_at_zero(c: f64) -> f64 {
    -c.exp()
}

fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// alpha-hat (Eq. 15, Algorithm 1 step 2) and where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct AlphaHat {
    /// The α used: the statistic below minus 1e-5, kept in [0, 1 − 1e-5].
    pub value: f64,
    /// `min over D^U of (1/c(s,a) − 1) = min e^{−logit}` (the paper's statistic).
    pub min_ratio: f64,
    /// Row of D^U (and its episode id) where that minimum is reached.
    pub argmin_row: usize,
    pub argmin_episode: u32,
    /// The 1% quantile of the same ratio: a diagnostic only, NOT the paper. Far above
    /// `min_ratio` means one rare sample sets alpha-hat.
    pub quantile_01: f64,
}

/// alpha-hat from the discriminator logits of every row of D^U. `quantile = 0` is the paper's
/// minimum; `quantile > 0` replaces it by that quantile (diagnostic option, not the paper).
pub fn alpha_hat_from_logits(logits: &[f32], episode_ids: &[u32], quantile: f64) -> AlphaHat {
    assert!(!logits.is_empty(), "D^U is never empty");
    let (argmin_row, max_logit) = logits
        .iter()
        .enumerate()
        .fold((0, f32::NEG_INFINITY), |best, (i, &c)| if c > best.1 { (i, c) } else { best });
    let mut ratios: Vec<f64> = logits.iter().map(|&c| (-(c as f64)).exp()).collect();
    ratios.sort_by(f64::total_cmp);
    let at =
        |q: f64| ratios[((q * (ratios.len() - 1) as f64).round() as usize).min(ratios.len() - 1)];
    let min_ratio = (-(max_logit as f64)).exp();
    let statistic = if quantile > 0.0 { at(quantile) } else { min_ratio };
    AlphaHat {
        value: (statistic - ALPHA_MARGIN).clamp(0.0, 1.0 - ALPHA_MARGIN),
        min_ratio,
        argmin_row,
        argmin_episode: episode_ids[argmin_row],
        quantile_01: at(0.01),
    }
}

#[cfg(test)]
mod tests {
    use super::super::config::EXCLUDED_REWARD_GAP;
    use super::*;

    /// With the optimal discriminator c* = d^N/(d^U + d^N), i.e. logit log(d^N/d^U), alpha-hat
    /// is min d^U/d^N (Eq. 15) minus the margin, found at the row that attains it.
    #[test]
    fn alpha_hat_of_a_known_discriminator() {
        let d_u = [0.30f64, 0.25, 0.15, 0.30];
        let d_n = [0.05f64, 0.10, 0.60, 0.25];
        let logits: Vec<f32> = d_u.iter().zip(&d_n).map(|(u, n)| (n / u).ln() as f32).collect();
        let a = alpha_hat_from_logits(&logits, &[4, 4, 9, 9], 0.0);
        assert!((a.min_ratio - 0.25).abs() < 1e-6, "{a:?}");
        assert!((a.value - (0.25 - ALPHA_MARGIN)).abs() < 1e-6);
        assert_eq!((a.argmin_row, a.argmin_episode), (2, 9));
        // Eq. 10 is then finite on every row (Appendix A.3) and most negative at the argmin.
        let rewards: Vec<f64> = logits
            .iter()
            .map(|&c| reward_from_logit(c as f64, a.value))
            .map(|(r, clipped)| {
                assert!(!clipped);
                r
            })
            .collect();
        assert!(rewards.iter().all(|r| r.is_finite()));
        let worst =
            rewards
                .iter()
                .enumerate()
                .fold((0, f64::INFINITY), |b, (i, &r)| if r < b.1 { (i, r) } else { b });
        assert_eq!(worst.0, 2);
    }

    /// Eq. 10 in its logit form equals the paper's sigmoid form.
    #[test]
    fn reward_logit_form_equals_eq_10() {
        for (c, alpha) in [(-2.0f64, 0.3), (0.5, 0.1), (1.2, 0.2), (-0.3, 0.6)] {
            let sigma = 1.0 / (1.0 + (-c).exp());
            let paper = ((1.0 - (1.0 + alpha) * sigma) / ((1.0 - alpha) * (1.0 - sigma))).ln();
            let (ours, clipped) = reward_from_logit(c, alpha);
            assert!(!clipped);
            assert!((ours - paper).abs() < 1e-10, "c={c}: {ours} vs {paper}");
        }
        assert!(reward_from_logit(3.0, 0.5).1, "1 − α e^c < 0 is floored and reported");
    }

    /// Eq. 10 on every row's own logit (no `scale_from`), no row flagged.
    fn plain(
        logits: &[f32],
        alpha: f64,
        undefined: UndefinedReward,
        gap: f64,
        standardize: bool,
    ) -> Eq10Rewards {
        eq10_rewards(logits, &[], alpha, undefined, gap, standardize, &[])
    }

    /// Undefined rows: floored, they join the statistics (the old behaviour); excluded, they
    /// sit 30 below the lowest defined reward and the standardisation ignores them.
    #[test]
    fn eq10_rewards_floor_or_exclude_undefined_rows() {
        let alpha = 0.5f64;
        // e^c = 1/α on the last row: 1 − α e^c = 0, Eq. 10 is −∞ there.
        let logits = [0.0f32, -1.0, (1.0 / alpha).ln() as f32 + 0.1];
        let floored = plain(&logits, alpha, UndefinedReward::Floor, EXCLUDED_REWARD_GAP, false);
        assert_eq!(floored.undefined_rows, 1);
        assert!((floored.rewards[2] - (1e-8f64.ln() - 0.5f64.ln())).abs() < 1e-9);
        let excluded = plain(&logits, alpha, UndefinedReward::Exclude, EXCLUDED_REWARD_GAP, true);
        assert_eq!(excluded.undefined_rows, 1);
        let defined = [reward_from_logit(0.0, alpha).0, reward_from_logit(-1.0, alpha).0];
        let mean = (defined[0] + defined[1]) / 2.0;
        assert!((excluded.mean - mean).abs() < 1e-12);
        let (r0, r1) = (excluded.rewards[0], excluded.rewards[1]);
        assert!((r0 + r1).abs() < 1e-9 && (r0.abs() - 1.0).abs() < 1e-6, "{excluded:?}");
        assert!((excluded.rewards[2] - (r0.min(r1) - EXCLUDED_REWARD_GAP)).abs() < 1e-9);
        // A smaller gap moves the excluded row only; the defined rows keep their rewards.
        let near = plain(&logits, alpha, UndefinedReward::Exclude, 2.0, true);
        assert_eq!(&near.rewards[..2], &excluded.rewards[..2]);
        assert!((near.rewards[2] - (r0.min(r1) - 2.0)).abs() < 1e-9, "{near:?}");
    }

    /// Rows flagged as ruled out (`rule_out_top_bin`) are undefined whatever their logit: the
    /// same as a row past Eq. 10's edge, excluded or floored, and out of the statistics; at
    /// α = 0 (the limit) too.
    #[test]
    fn flagged_rows_are_ruled_out_like_rows_past_eq10s_edge() {
        let alpha = 0.5f64;
        let logits = [0.0f32, -1.0, -2.0];
        let flags = [false, true, false];
        for standardize in [false, true] {
            let flagged = eq10_rewards(
                &logits,
                &[],
                alpha,
                UndefinedReward::Exclude,
                30.0,
                standardize,
                &flags,
            );
            let past_edge = [logits[0], (1.0 / alpha).ln() as f32 + 0.1, logits[2]];
            let beyond = plain(&past_edge, alpha, UndefinedReward::Exclude, 30.0, standardize);
            assert_eq!(flagged, beyond, "standardize {standardize}");
            assert_eq!(flagged.undefined_rows, 1);
        }
        let floored =
            eq10_rewards(&logits, &[], alpha, UndefinedReward::Floor, 30.0, false, &flags);
        assert!((floored.rewards[1] - (1e-8f64.ln() - 0.5f64.ln())).abs() < 1e-9, "{floored:?}");
        let limit = eq10_rewards(&logits, &[], 0.0, UndefinedReward::Exclude, 30.0, true, &flags);
        assert_eq!(limit.undefined_rows, 1);
        assert!((limit.rewards[1] - (limit.rewards[0].min(limit.rewards[2]) - 30.0)).abs() < 1e-9);
    }

    /// `scale_from` (`top_bin: bin_ratio_own_scale`): the rows whose logit was not raised keep
    /// the rewards of their own logits exactly, standardised or not and at α = 0 too, while the
    /// raised row's reward falls; the statistics are those of the own logits.
    #[test]
    fn raising_a_row_moves_no_other_rows_reward_on_the_own_scale() {
        let own = [-2.0f32, -1.0, 0.0, 0.5, 1.0];
        let mut raised = own;
        raised[4] = 2.2; // e^2.2 ≈ 9: at α = 0.1 still under Eq. 10's edge
        for (alpha, standardize) in [(0.1, true), (0.1, false), (0.0, true)] {
            let rewards = |logits: &[f32], scale_from: &[f32]| {
                let gap = EXCLUDED_REWARD_GAP;
                eq10_rewards(
                    logits,
                    scale_from,
                    alpha,
                    UndefinedReward::Exclude,
                    gap,
                    standardize,
                    &[],
                )
            };
            let before = rewards(&own, &[]);
            let after = rewards(&raised, &own);
            assert_eq!(&after.rewards[..4], &before.rewards[..4], "α {alpha}, {standardize}");
            assert_eq!((after.mean, after.std), (before.mean, before.std));
            assert!(after.rewards[4] < before.rewards[4] - 1.0, "{after:?} vs {before:?}");
            // In the statistics (`bin_ratio`), the raised row moves the others.
            let counted = rewards(&raised, &[]);
            if standardize {
                assert!((counted.rewards[0] - before.rewards[0]).abs() > 0.1, "{counted:?}");
            }
        }
        // Raised past the edge: excluded, below every other row, and the others still unmoved.
        raised[4] = 3.0;
        let own_scale = eq10_rewards(&raised, &own, 0.1, UndefinedReward::Exclude, 30.0, true, &[]);
        let before = plain(&own, 0.1, UndefinedReward::Exclude, 30.0, true);
        assert_eq!(own_scale.undefined_rows, 1);
        assert_eq!(&own_scale.rewards[..4], &before.rewards[..4]);
        let lowest = own_scale.rewards[..4].iter().copied().fold(f64::INFINITY, f64::min);
        assert!((own_scale.rewards[4] - (lowest - 30.0)).abs() < 1e-9, "{own_scale:?}");
    }

    /// Standardised, Eq. 10 at α = 0 is its limit as α → 0+: the rewards at α = 1e-3 and 1e-4
    /// approach it, their distance shrinking with α (an error of order α e^c; much below 1e-6
    /// the standardisation's 1e-8 floor on the deviation starts to damp them);
    /// unstandardised it stays 0 on every row.
    #[test]
    fn standardised_eq10_is_continuous_at_alpha_zero() {
        let logits = [-3.0f32, -0.5, 0.0, 0.7, 1.5, 2.5];
        let exclude =
            |alpha: f64| plain(&logits, alpha, UndefinedReward::Exclude, EXCLUDED_REWARD_GAP, true);
        let at = |alpha: f64| exclude(alpha).rewards;
        let limit = at(0.0);
        let distance = |alpha: f64| {
            at(alpha).iter().zip(&limit).map(|(r, l)| (r - l).abs()).fold(0.0, f64::max)
        };
        assert!(distance(1e-4) < 1e-2, "{:?} vs {limit:?}", at(1e-4));
        assert!(distance(1e-4) < distance(1e-3) / 5.0, "{} {}", distance(1e-4), distance(1e-3));
        let mean = limit.iter().sum::<f64>() / limit.len() as f64;
        assert!(mean.abs() < 1e-12 && limit.windows(2).all(|w| w[0] > w[1]), "{limit:?}");
        let raw = plain(&logits, 0.0, UndefinedReward::Exclude, EXCLUDED_REWARD_GAP, false);
        assert!(raw.rewards.iter().all(|&r| r == 0.0) && raw.std == 0.0, "{raw:?}");
    }

    #[test]
    fn nu_loss_is_log_mean_exp_plus_initial_term() {
        let dev = candle_core::Device::Cpu;
        let a = Tensor::new(&[0.5f32, -1.0, 2.0, 100.0], &dev).unwrap();
        let nu0 = Tensor::new(&[1.0f32, 3.0], &dev).unwrap();
        let got = crate::algo::losses::scalar(&nu_loss(&a, &nu0, 0.99).unwrap()).unwrap();
        let lme = 100.0 + ((0.5f64 - 100.0).exp() + (-101f64).exp() + (-98f64).exp() + 1.0).ln()
            - 4f64.ln();
        assert!((got - (lme + 0.01 * 2.0)).abs() < 1e-4, "{got} vs {}", lme + 0.02);
    }
}
