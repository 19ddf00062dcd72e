//! Whether Eq. 10's weights remove non-preferred rows at all, measured on held-out D^N.
//!
//! Give D^U's rows the weights `w = e^r / mean_U e^r` of their (scaled) Eq. 10 reward `r`, so
//! that the weights average 1 over D^U. Under the mixture `d^U = α* d^N + (1 − α*) d^P`, the
//! weighted D^U's non-preferred share is `E_U[w · 1{non-preferred}] = α* · E_{d^N}[w]`: the
//! weighting keeps the fraction `E_{d^N}[w]` of the non-preferred share, and D^N's own rows
//! estimate it without a label of D^U. A weighting that removes them keeps close to 0; one that
//! is noise (a discriminator that cannot tell the sets apart, sharpened by the standardisation)
//! keeps 1 in expectation and only spends data. Unlike the AUC of D^N against D^U, whose
//! distance from ½ shrinks by `1 − α*` as D^U fills with non-preferred episodes, the kept share
//! falls toward 0 however large α* is, when the weighting works.
//!
//! Held-out D^N rows come in few long episodes, whose rows move together, so the interval
//! counts episodes: the mean's variance `s²/n` is multiplied by Kish's design effect
//! `1 + (m̄ − 1)ρ`, `ρ` the intra-episode correlation of the weights over the episodes of both
//! sets (one estimate, as for the AUC: held-out D^N can be a single episode). D^U's weights
//! are normalised on every row it has, and their sampling error is left out beside D^N's.

use super::mixture::{
    intra_episode_correlation, row_weighted_episode_length, sample_variance, Z_AUC,
};

/// The share of D^N's mass that a weighting of D^U keeps (`E_{d^N}[w]`, with `E_U[w] = 1`),
/// with the upper end of its two-sided interval at level `1 − δ` (z of 0.95, as the AUC's).
#[derive(Clone, Debug, PartialEq)]
pub struct KeptShare {
    pub value: f64,
    pub upper: f64,
    /// Kish's design effect of the held-out D^N rows: how many rows count as one draw.
    pub design_effect: f64,
}

/// The rows of one set with the rewards Eq. 10 gives them and the episode each row is from.
#[derive(Clone, Copy, Debug)]
pub struct Rewarded<'a> {
    pub rewards: &'a [f64],
    pub episodes: &'a [u32],
}

/// [`KeptShare`] of the weights `e^r` normalised over `unlabeled`, read on `labeled` (held-out
/// D^N), each weight mixed with `uniform_share` as the policy step mixes it
/// (`policy_uniform_share`: `(1 − m) w + m`). The interval is `[value, ∞)` with fewer than two
/// labeled rows. None when either set is empty or its episode list does not match.
pub fn kept_share(labeled: Rewarded, unlabeled: Rewarded, uniform_share: f64) -> Option<KeptShare> {
    let mismatched = labeled.rewards.len() != labeled.episodes.len()
        || unlabeled.rewards.len() != unlabeled.episodes.len();
    if labeled.rewards.is_empty() || unlabeled.rewards.is_empty() || mismatched {
        return None;
    }
    // exp(r − top) for stability, `top` D^U's highest reward, so the normalisation over D^U is
    // at least 1/n_U: a D^N row far above every row of D^U gives an infinite share (which the
    // test reads as "cannot be shown to remove"), never 0/0. The normalisation removes `top`.
    let top = unlabeled.rewards.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b));
    let raw_u: Vec<f64> = unlabeled.rewards.iter().map(|r| (r - top).exp()).collect();
    let norm = raw_u.iter().sum::<f64>() / raw_u.len() as f64;
    let weight = |e: f64| (1.0 - uniform_share) * e / norm + uniform_share;
    let w_u: Vec<f64> = raw_u.into_iter().map(weight).collect();
    let w_n: Vec<f64> = labeled.rewards.iter().map(|r| weight((r - top).exp())).collect();
    let n = w_n.len() as f64;
    let value = w_n.iter().sum::<f64>() / n;
    let (s_n, s_u) = (sample_variance(&w_n, value), sample_variance(&w_u, 1.0));
    let correlation = intra_episode_correlation(&[
        (&w_n, labeled.episodes, value, s_n),
        (&w_u, unlabeled.episodes, 1.0, s_u),
    ]);
    let design_effect = 1.0 + (row_weighted_episode_length(labeled.episodes) - 1.0) * correlation;
    let upper = if w_n.len() < 2 {
        f64::INFINITY
    } else {
        value + Z_AUC * (design_effect * s_n / n).sqrt()
    };
    Some(KeptShare { value, upper, design_effect })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Episodes of `len` rows; every row's reward is its episode's level plus noise.
    fn episodes(
        rng: &mut ChaCha8Rng,
        count: u32,
        len: u32,
        level: impl Fn(&mut ChaCha8Rng) -> f64,
    ) -> (Vec<f64>, Vec<u32>) {
        let (mut rewards, mut ids) = (Vec::new(), Vec::new());
        for e in 0..count {
            let base = level(rng);
            for _ in 0..len {
                rewards.push(base + 0.1 * rng.random::<f64>());
                ids.push(e);
            }
        }
        (rewards, ids)
    }

    /// A mixture of two kinds of episode, reward 0 (preferred) and −5 (non-preferred), share
    /// 0.6 non-preferred; D^N is non-preferred episodes. With `w = e^r / mean_U e^r`, D^N's
    /// weight is `e^{−5} / (0.4 + 0.6 e^{−5})` ≈ 0.0167 in closed form (up to the noise).
    #[test]
    fn a_weighting_that_separates_keeps_the_closed_form_share() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (u, u_ids) =
            episodes(&mut rng, 500, 20, |r| if r.random::<f64>() < 0.6 { -5.0 } else { 0.0 });
        let (n, n_ids) = episodes(&mut rng, 3, 20, |_| -5.0);
        let kept = kept_share(
            Rewarded { rewards: &n, episodes: &n_ids },
            Rewarded { rewards: &u, episodes: &u_ids },
            0.0,
        )
        .unwrap();
        let expected = (-5f64).exp() / (0.4 + 0.6 * (-5f64).exp());
        assert!((kept.value - expected).abs() < 0.15 * expected, "{kept:?} vs {expected}");
        assert!(kept.upper < 0.05, "{kept:?}");
        // The same rows give the same bits (the metric is part of a run's record).
        let again = kept_share(
            Rewarded { rewards: &n, episodes: &n_ids },
            Rewarded { rewards: &u, episodes: &u_ids },
            0.0,
        );
        assert_eq!(again.as_ref(), Some(&kept));
        assert_eq!(again.unwrap().design_effect.to_bits(), kept.design_effect.to_bits());
        // The uniform share m maps the kept share to (1 − m) k + m.
        let mixed = kept_share(
            Rewarded { rewards: &n, episodes: &n_ids },
            Rewarded { rewards: &u, episodes: &u_ids },
            0.2,
        )
        .unwrap();
        assert!((mixed.value - (0.8 * kept.value + 0.2)).abs() < 1e-12);
    }

    /// Rewards that are noise, the same law for both sets, with rows that share their episode's
    /// draw: the kept share is 1 in expectation, and the interval's upper end, counting
    /// episodes, reaches 1 in 157 of 200 draws (nominal 95% one-sided; three labeled episodes
    /// leave the variance itself uncertain), counting rows in 114.
    #[test]
    fn noise_weights_cannot_be_shown_to_remove_anything() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let level = |r: &mut ChaCha8Rng| 2.0 * r.random::<f64>() - 1.0;
        let (mut covered, mut covered_by_rows) = (0, 0);
        for _ in 0..200 {
            let (u, u_ids) = episodes(&mut rng, 200, 50, level);
            let (n, n_ids) = episodes(&mut rng, 3, 50, level);
            let kept = kept_share(
                Rewarded { rewards: &n, episodes: &n_ids },
                Rewarded { rewards: &u, episodes: &u_ids },
                0.0,
            )
            .unwrap();
            assert!(kept.design_effect > 10.0, "rows of an episode move together: {kept:?}");
            covered += usize::from(kept.upper >= 1.0);
            let rows_upper = kept.value + (kept.upper - kept.value) / kept.design_effect.sqrt();
            covered_by_rows += usize::from(rows_upper >= 1.0);
        }
        assert!(covered >= 150, "episodes counted: {covered} of 200 reach 1");
        assert!(covered_by_rows < 140, "rows counted: {covered_by_rows} of 200 reach 1");
    }

    /// A held-out D^N row whose reward lies far above every row of D^U (hundreds of nats, as
    /// a large `reward_scale` over a narrow standardisation can give): an infinite share, not
    /// NaN, so the test cannot read it as a weighting that removes D^N.
    #[test]
    fn a_d_n_row_far_above_d_u_keeps_an_infinite_share() {
        let u = [0.0, -1.0, -2.0];
        let ids = [0, 0, 1];
        let far = kept_share(
            Rewarded { rewards: &[900.0, 0.0], episodes: &[0, 0] },
            Rewarded { rewards: &u, episodes: &ids },
            0.0,
        )
        .unwrap();
        assert_eq!(far.value, f64::INFINITY, "{far:?}");
        assert!(far.upper.is_nan() || far.upper >= 1.0, "{far:?}");
    }

    #[test]
    fn one_row_has_no_interval_and_empty_sets_no_estimate() {
        let u = [0.0, 1.0, -1.0];
        let ids = [0, 0, 1];
        let one = kept_share(
            Rewarded { rewards: &[0.5], episodes: &[0] },
            Rewarded { rewards: &u, episodes: &ids },
            0.0,
        )
        .unwrap();
        assert_eq!(one.upper, f64::INFINITY);
        let empty = Rewarded { rewards: &[], episodes: &[] };
        assert!(kept_share(empty, Rewarded { rewards: &u, episodes: &ids }, 0.0).is_none());
        let short = Rewarded { rewards: &[0.5, 0.1], episodes: &[0] };
        assert!(kept_share(short, Rewarded { rewards: &u, episodes: &ids }, 0.0).is_none());
    }
}
