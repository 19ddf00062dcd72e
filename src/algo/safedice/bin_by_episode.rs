//! Best Bin Estimation's bin read again with episodes counted. BBE's own bound
//! ([`super::mixture::best_bin_estimate`]) counts rows, and the rows of an episode fall in the
//! bin together, so on long episodes its interval is too narrow (bench/rwrl/results.md, Cartpole
//! seed 1: the true share 0.5 above an interval of [0.305, 0.467] built from 16 held-out
//! episodes counted as 4,096 draws). The interval here is reported beside it on every `bbe` run;
//! alpha-hat reads its lower end only with `alpha_hat_point: episodes_lower`, and the bin never
//! (docs/algorithm.md, "2. alpha-hat").

use super::mixture::{
    intra_episode_correlation, row_weighted_episode_length, sample_variance, EpisodesOf, DELTA,
};

/// Two-sided normal quantile of each share's interval in [`bin_ratio_by_episode`] (95%): both
/// shares hold together with probability at least 90% (Bonferroni), the `1 − δ` of the other
/// intervals ([`DELTA`] = 0.1, checked below).
const Z_SHARE: f64 = 1.96;
const _: () = assert!(DELTA == 0.1, "Z_SHARE is the 97.5% quantile for δ = 0.1");

/// Best Bin Estimation's bin read again with episodes counted: the interval of its ratio
/// `q_U/q_N` at the threshold BBE chose (not capped at 1, as BBE's estimate is), and how many
/// rows counted as one draw on each side.
#[derive(Clone, Debug, PartialEq)]
pub struct BinByEpisode {
    pub lower: f64,
    pub upper: f64,
    /// Kish's design effect of the bin's indicator on the labeled and the mixture side.
    pub design_effect_labeled: f64,
    pub design_effect_mixture: f64,
}

/// The ratio of the shares of `mixture` and `labeled` scores at least `threshold`, with an
/// interval that counts episodes: each share's Wilson interval counts the side's rows over
/// Kish's design effect `1 + (m̄ − 1)ρ` (`ρ` the intra-episode correlation of the bin's
/// indicator, one value for both sides as in [`super::mixture::roc_auc_by_episode`]), and the
/// ratio's interval is the quotient of the two (the lower share over the upper and back;
/// unbounded above when the labeled share's interval reaches 0). At the threshold BBE chose
/// this is what the held-out episodes support; it does not account for the threshold having
/// been chosen on the same rows, so it still leans optimistic. None when a side is empty or the
/// episodes do not match the scores.
pub fn bin_ratio_by_episode(
    labeled: &[f32],
    mixture: &[f32],
    threshold: f64,
    episodes: EpisodesOf,
) -> Option<BinByEpisode> {
    let mismatched =
        episodes.labeled.len() != labeled.len() || episodes.mixture.len() != mixture.len();
    if labeled.is_empty() || mixture.is_empty() || mismatched {
        return None;
    }
    let in_bin = |scores: &[f32]| -> Vec<f64> {
        scores.iter().map(|&c| f64::from(u8::from(c as f64 >= threshold))).collect()
    };
    let (bin_n, bin_u) = (in_bin(labeled), in_bin(mixture));
    let share = |bin: &[f64]| bin.iter().sum::<f64>() / bin.len() as f64;
    let (q_n, q_u) = (share(&bin_n), share(&bin_u));
    let (var_n, var_u) = (sample_variance(&bin_n, q_n), sample_variance(&bin_u, q_u));
    let correlation = intra_episode_correlation(&[
        (&bin_n, episodes.labeled, q_n, var_n),
        (&bin_u, episodes.mixture, q_u, var_u),
    ]);
    let design_effect = |ids: &[u32]| 1.0 + (row_weighted_episode_length(ids) - 1.0) * correlation;
    let (d_n, d_u) = (design_effect(episodes.labeled), design_effect(episodes.mixture));
    let (n_lo, n_hi) = wilson_interval(q_n, labeled.len() as f64 / d_n);
    let (u_lo, u_hi) = wilson_interval(q_u, mixture.len() as f64 / d_u);
    let lower = if n_hi > 0.0 { u_lo / n_hi } else { 0.0 };
    let upper = if n_lo > 0.0 { u_hi / n_lo } else { f64::INFINITY };
    Some(BinByEpisode { lower, upper, design_effect_labeled: d_n, design_effect_mixture: d_u })
}

/// Wilson's score interval of a share `p` observed on `draws` independent draws (a fractional
/// count: rows over a design effect), at [`Z_SHARE`]. Unlike `p ± z·se` it does not shrink to a
/// point at a share of 0 or 1, which one held-out D^N episode falling wholly in the bin gives.
fn wilson_interval(p: f64, draws: f64) -> (f64, f64) {
    let z2 = Z_SHARE * Z_SHARE / draws;
    let centre = (p + z2 / 2.0) / (1.0 + z2);
    let half = Z_SHARE / (1.0 + z2) * (p * (1.0 - p) / draws + z2 / (4.0 * draws)).sqrt();
    // At a share of exactly 0 or 1 the end is exact; `centre ∓ half` may miss it by a rounding.
    let lower = if p == 0.0 { 0.0 } else { (centre - half).max(0.0) };
    let upper = if p == 1.0 { 1.0 } else { (centre + half).min(1.0) };
    (lower, upper)
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::algo::safedice::mixture::best_bin_estimate;
    use crate::algo::safedice::mixture::tests::{known_mixture, standard_normal};

    /// `P(X ≥ x)` for `X ~ N(0, 1)` (Abramowitz and Stegun 7.1.26, error below 1e-7).
    fn normal_tail(x: f64) -> f64 {
        let z = x.abs() / std::f64::consts::SQRT_2;
        let t = 1.0 / (1.0 + 0.327_591_1 * z);
        let poly = t
            * (0.254_829_592
                + t * (-0.284_496_736
                    + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
        let erfc = poly * (-z * z).exp();
        if x >= 0.0 {
            erfc / 2.0
        } else {
            1.0 - erfc / 2.0
        }
    }

    /// Episodes of `length` rows sharing an `N(0, 1)` offset, rows `N(0, noise²)` around it,
    /// shifted by `mu` for the labeled class; the mixture's episodes are labeled-class ones with
    /// probability `share`. Returns the scores and each row's episode.
    fn episodes_of_a_mixture(
        rng: &mut ChaCha8Rng,
        (mu, share, noise): (f64, f64, f64),
        episodes: usize,
        length: usize,
    ) -> (Vec<f32>, Vec<u32>) {
        let mut scores = Vec::with_capacity(episodes * length);
        for _ in 0..episodes {
            let shift = if rng.random::<f64>() < share { mu } else { 0.0 };
            let offset = shift + standard_normal(rng);
            scores.extend((0..length).map(|_| (offset + noise * standard_normal(rng)) as f32));
        }
        (scores, (0..episodes * length).map(|row| (row / length) as u32).collect())
    }

    /// At a fixed threshold the bin's population ratio has a closed form (both classes normal
    /// with variance `1 + noise²`). With 4 held-out D^N episodes of 50 rows whose rows fall in
    /// the bin together, the interval counting episodes covers it in 199 of 200 draws (nominal
    /// 90%; the test asks for 85%); the same interval counting rows (each row its own episode)
    /// misses it most of the time (it covers 58 of 200). Both sides share one correlation here;
    /// where held-out D^N's rows move together more than D^U's, the pooled `ρ` understates D^N's
    /// design effect (docs/algorithm.md).
    #[test]
    fn counting_episodes_covers_the_bins_ratio_where_counting_rows_does_not() {
        let (mu, share, noise, threshold) = (2.0, 0.5, 0.5, 1.5);
        let sd = (1.0f64 + noise * noise).sqrt();
        let (tail_n, tail_p) = (normal_tail((threshold - mu) / sd), normal_tail(threshold / sd));
        let truth = share + (1.0 - share) * tail_p / tail_n;
        let (mut by_episode, mut by_row, trials) = (0, 0, 200);
        for trial in 0..trials {
            let mut rng = ChaCha8Rng::seed_from_u64(7000 + trial);
            let (l, l_ids) = episodes_of_a_mixture(&mut rng, (mu, 1.0, noise), 4, 50);
            let (m, m_ids) = episodes_of_a_mixture(&mut rng, (mu, share, noise), 40, 50);
            let episodes = EpisodesOf { labeled: &l_ids, mixture: &m_ids };
            let b = bin_ratio_by_episode(&l, &m, threshold, episodes).unwrap();
            by_episode += usize::from(b.lower <= truth && truth <= b.upper);
            assert!(b.design_effect_labeled > 10.0, "{b:?}");
            let (rows_l, rows_m): (Vec<u32>, Vec<u32>) =
                ((0..l.len() as u32).collect(), (0..m.len() as u32).collect());
            let rows = EpisodesOf { labeled: &rows_l, mixture: &rows_m };
            let r = bin_ratio_by_episode(&l, &m, threshold, rows).unwrap();
            assert_eq!((r.design_effect_labeled, r.design_effect_mixture), (1.0, 1.0));
            by_row += usize::from(r.lower <= truth && truth <= r.upper);
        }
        assert!(by_episode * 100 >= trials as usize * 85, "episodes: covered {by_episode}");
        assert!(by_row * 100 <= trials as usize * 50, "rows: covered {by_row}");
    }

    /// Wilson's interval against a textbook value (30 of 100 at 95%: [0.219, 0.396]), and exact
    /// ends at shares of 0 and 1 for any count of draws, fractional ones included.
    #[test]
    fn wilson_interval_matches_its_closed_form_and_keeps_exact_ends() {
        let (lower, upper) = wilson_interval(0.3, 100.0);
        assert!((lower - 0.2189).abs() < 1e-3 && (upper - 0.3959).abs() < 1e-3, "{lower}, {upper}");
        for draws in [1.0, 2.5, 11.0, 37.3, 1e5] {
            assert_eq!(wilson_interval(0.0, draws).0, 0.0, "{draws}");
            assert_eq!(wilson_interval(1.0, draws).1, 1.0, "{draws}");
            let (lower, upper) = wilson_interval(0.4, draws);
            assert!(lower < 0.4 && 0.4 < upper, "{draws}: {lower}, {upper}");
        }
    }

    /// With independent rows the interval sits around BBE's ratio at BBE's threshold and is
    /// narrower than BBE's bound, which holds over every threshold at once; mismatched episode
    /// lists give none.
    #[test]
    fn independent_rows_bracket_the_bins_ratio() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        let (l, m) = known_mixture(&mut rng, 4.0, 0.5, 8000, 8000);
        let bbe = best_bin_estimate(&l, &m).unwrap();
        let (l_ids, m_ids): (Vec<u32>, Vec<u32>) = ((0..8000).collect(), (0..8000).collect());
        let episodes = EpisodesOf { labeled: &l_ids, mixture: &m_ids };
        let b = bin_ratio_by_episode(&l, &m, bbe.threshold, episodes).unwrap();
        assert_eq!((b.design_effect_labeled, b.design_effect_mixture), (1.0, 1.0));
        assert!(b.lower <= bbe.value && bbe.value <= b.upper, "{b:?} vs {bbe:?}");
        assert!(b.upper - b.lower < bbe.upper - bbe.lower, "{b:?} vs {bbe:?}");
        assert!(bin_ratio_by_episode(&l[..10], &m, bbe.threshold, episodes).is_none());
        let nothing_in_bin = bin_ratio_by_episode(&l, &m, 1e9, episodes).unwrap();
        assert_eq!((nothing_in_bin.lower, nothing_in_bin.upper), (0.0, f64::INFINITY));
    }
}
