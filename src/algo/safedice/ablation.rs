//! Ablation hooks of the benchmark (`bench --ablations`): replacements for what Algorithm 1
//! estimates, and the oracle discriminator they are measured with. A user's config cannot
//! reach them.

/// Probability floor of the oracle discriminator ([`oracle_logits`]) on preferred rows:
/// `σ(c) = 1e-6` instead of 0, so their logit stays finite (`ln(1e-6 / (1 − 1e-6))` ≈ −13.8).
pub const ORACLE_PROB_FLOOR: f64 = 1e-6;

/// The optimal discriminator of Eq. 9, `c* = d^N / (d^U + d^N)`, as logits
/// `log(d^N / d^U)`, for a D^U whose rows are known to come from the non-preferred (`true`) or
/// the preferred (`false`) policy, with the two policies taken to share no state-action pair.
/// With α the non-preferred share of the rows, `d^U = α d^N` on non-preferred rows, so
/// `c* = 1/(1 + α)` and the logit is `−ln α`; `d^N = 0` on preferred rows, so `c* = 0`,
/// floored at [`ORACLE_PROB_FLOOR`].
///
/// Why not the labels themselves (`σ(c)` = 1 on non-preferred rows): Eq. 10 divides by
/// `1 − c*`, and Eq. 15's `min (1/c* − 1)` would be 0, so alpha-hat would be 0 and the reward 0
/// everywhere, i.e. no filtering at all. With these logits Eq. 15 returns α itself (minus its
/// 1e-5 margin), and Eq. 10 gives `−ln(1 − α̂)` on preferred rows and
/// `ln(1 − α̂/α) − ln(1 − α̂)` (≈ ln(1e-5/α), finite thanks to the margin) on non-preferred
/// ones. Without non-preferred rows every logit is the floor and the reward is constant.
/// A diagnostic of how well SafeDICE does with a perfect discriminator: a learner never has
/// these labels.
pub fn oracle_logits(non_preferred: &[bool]) -> Vec<f32> {
    let share =
        non_preferred.iter().filter(|&&np| np).count() as f64 / non_preferred.len().max(1) as f64;
    let floor = (ORACLE_PROB_FLOOR / (1.0 - ORACLE_PROB_FLOOR)).ln() as f32;
    let on_non_preferred = -(share.ln()) as f32;
    non_preferred.iter().map(|&np| if np { on_non_preferred } else { floor }).collect()
}

/// Replacements for what Algorithm 1 estimates, for ablations that measure what each estimate
/// costs (the benchmark's `--ablations`). Not part of a [`ResolvedConfig`], so a user's config
/// cannot set them, and not saved in checkpoints: [`SafediceTrainer::resume`] runs without.
/// Both act where the discriminator phase ends (alpha-hat and the Eq. 10 reward are computed
/// once there), before either engine's main loop reads the reward, so the candle and the fused
/// paths see the same values. The discriminator is still trained, drawing the same random
/// numbers, so a run with overrides and one without share their minibatches.
#[derive(Clone, Debug, Default)]
pub struct SafediceOverrides {
    /// α of Eq. 10 in place of alpha-hat (Eq. 15), kept in `[0, 1 − 1e-5]`. Eq. 15 estimates
    /// the α* of `d^U = (1 − α*) d^P + α* d^N` (Appendix A, Eq. 18), where `d^U` is the
    /// distribution of D^U's transitions (the trainer samples its rows uniformly); the true
    /// value is therefore the share of D^U's **transitions** (not episodes) that are
    /// non-preferred. Rows where `1 − α e^c` falls below the floor are floored and counted
    /// (`reward_clipped_rows`), as with the quantile diagnostic. The recorded `alpha_hat` is
    /// this value; `alpha_hat_estimated` records what Eq. 15 gave.
    pub alpha: Option<f64>,
    /// Discriminator logits for every row of D^U in place of the trained discriminator's
    /// (e.g. [`oracle_logits`]); Eq. 15 (unless `alpha` is set) and Eq. 10 read these.
    pub unlabeled_logits: Option<Vec<f32>>,
}
