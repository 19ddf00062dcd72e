//! alpha-hat as mixture proportion estimation: Eq. 15 asks for `min over (s, a) of d^U/d^N`,
//! which positive-unlabeled learning calls the mixture proportion of the labeled class (here
//! D^N) in the unlabeled mixture (D^U). The paper's point-wise minimum over D^U is set by the
//! single row with the largest logit; [`best_bin_estimate`] takes the ratio over the top *bin*
//! of held-out scores instead (Best Bin Estimation, Garg et al., NeurIPS 2021), which has a
//! finite-sample bound and converges to `α* + (1 − α*) min d^P/d^N`, the paper's Eq. 21.
//! [`roc_auc`] says whether the held-out scores separate the two sets at all.
//!
//! Both take *held-out* scores: rows whose episodes the discriminator never trained on, so the
//! top bin is not the set of rows it memorised. Rows within an episode are not independent;
//! BBE's bound and [`roc_auc`]'s interval count rows, so they are optimistic when episodes are
//! long (docs/algorithm.md); [`roc_auc_by_episode`] counts episodes.

use std::collections::BTreeMap;

/// Confidence level of the bounds: `1 − δ` (the BBE authors' δ).
pub const DELTA: f64 = 0.1;
/// The BBE authors' slack `γ` in the upper bound's `(1 + γ)` factor.
const SLACK: f64 = 0.01;
/// Two-sided normal quantile for the intervals at level `1 − δ` (z of 0.95).
pub(super) const Z_AUC: f64 = 1.6449;

/// A mixture proportion with its confidence interval and the bin it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct MixtureEstimate {
    /// `q_U(t) / q_N(t)` at the chosen threshold, kept in [0, 1].
    pub value: f64,
    /// `value ∓` the DKW width at the chosen threshold (the upper one is what BBE minimises).
    pub lower: f64,
    pub upper: f64,
    /// The chosen threshold on the score: the bin is every row scoring at least this.
    pub threshold: f64,
    /// Shares of the held-out D^N and D^U rows in the bin.
    pub share_n: f64,
    pub share_u: f64,
    pub rows_n: usize,
    pub rows_u: usize,
}

/// Best Bin Estimation of the share of the labeled class in the mixture: over thresholds `t`,
/// `q_N(t)` and `q_U(t)` are the shares of `labeled` and `mixture` scores `≥ t`; the estimate is
/// `q_U/q_N` at the `t` minimising its upper bound
/// `q_U/q_N + (1 + γ)/q_N · (√(ln(1/δ)/2n_U) + √(ln(1/δ)/2n_N))` (DKW on both sets).
/// Higher scores must mean "more like the labeled class". None when either set is empty.
pub fn best_bin_estimate(labeled: &[f32], mixture: &[f32]) -> Option<MixtureEstimate> {
    if labeled.is_empty() || mixture.is_empty() {
        return None;
    }
    let (n_n, n_u) = (labeled.len(), mixture.len());
    let eps = dkw(n_n) + dkw(n_u);
    let mut l: Vec<f32> = labeled.to_vec();
    let mut m: Vec<f32> = mixture.to_vec();
    l.sort_by(|a, b| b.total_cmp(a));
    m.sort_by(|a, b| b.total_cmp(a));
    // Candidate thresholds: every labeled score (the bins' edges that change q_N), descending;
    // q_U(t) counted with a pointer walking down the sorted mixture.
    let mut best: Option<MixtureEstimate> = None;
    let mut in_u = 0usize;
    for (i, &t) in l.iter().enumerate() {
        if i + 1 < n_n && l[i + 1] == t {
            continue; // the bin ends after the last tie
        }
        while in_u < n_u && m[in_u] >= t {
            in_u += 1;
        }
        let q_n = (i + 1) as f64 / n_n as f64;
        let q_u = in_u as f64 / n_u as f64;
        let ratio = q_u / q_n;
        let width = (1.0 + SLACK) * eps / q_n;
        if best.as_ref().is_none_or(|b| ratio + width < b.upper) {
            best = Some(MixtureEstimate {
                value: ratio.min(1.0),
                lower: (ratio - width).clamp(0.0, 1.0),
                upper: ratio + width,
                threshold: t as f64,
                share_n: q_n,
                share_u: q_u,
                rows_n: n_n,
                rows_u: n_u,
            });
        }
    }
    best
}

/// The DKW deviation `√(ln(1/δ) / 2n)` of an empirical distribution function of `n` draws.
fn dkw(n: usize) -> f64 {
    ((1.0 / DELTA).ln() / (2.0 * n as f64)).sqrt()
}

/// The held-out ROC AUC of a score (probability that a labeled row outscores a mixture row, ties
/// counted half) with a normal interval at level `1 − δ`: from the Hanley–McNeil variance with
/// every row an independent draw ([`roc_auc`]), or from DeLong's with episodes counted
/// ([`roc_auc_by_episode`], which says how dependent it found the rows).
#[derive(Clone, Debug, PartialEq)]
pub struct Auc {
    pub value: f64,
    pub lower: f64,
    pub upper: f64,
    pub episodes: Option<EpisodeDependence>,
}

/// [`Auc`] of `labeled` against `mixture` scores (higher = more like the labeled class).
pub fn roc_auc(labeled: &[f32], mixture: &[f32]) -> Option<Auc> {
    if labeled.is_empty() || mixture.is_empty() {
        return None;
    }
    // Mann–Whitney U from ranks of the pooled scores (average ranks for ties).
    let mut pooled: Vec<(f32, bool)> = labeled.iter().map(|&s| (s, true)).collect();
    pooled.extend(mixture.iter().map(|&s| (s, false)));
    pooled.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut rank_sum_labeled = 0.0;
    let mut i = 0;
    while i < pooled.len() {
        let mut j = i;
        while j + 1 < pooled.len() && pooled[j + 1].0 == pooled[i].0 {
            j += 1;
        }
        let average_rank = (i + j) as f64 / 2.0 + 1.0;
        rank_sum_labeled += average_rank * pooled[i..=j].iter().filter(|p| p.1).count() as f64;
        i = j + 1;
    }
    let (n1, n0) = (labeled.len() as f64, mixture.len() as f64);
    let a = ((rank_sum_labeled - n1 * (n1 + 1.0) / 2.0) / (n1 * n0)).clamp(0.0, 1.0);
    let (q1, q2) = (a / (2.0 - a), 2.0 * a * a / (1.0 + a));
    let variance =
        (a * (1.0 - a) + (n1 - 1.0) * (q1 - a * a) + (n0 - 1.0) * (q2 - a * a)) / (n1 * n0);
    let half = Z_AUC * variance.max(0.0).sqrt();
    Some(Auc { value: a, lower: (a - half).max(0.0), upper: (a + half).min(1.0), episodes: None })
}

/// Which episode each held-out row came from, on each side of [`roc_auc_by_episode`] (in the
/// order of its scores).
#[derive(Clone, Copy, Debug)]
pub struct EpisodesOf<'a> {
    pub labeled: &'a [u32],
    pub mixture: &'a [u32],
}

/// How much the rows of one episode move together, as [`roc_auc_by_episode`] measured it.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeDependence {
    /// The intra-episode correlation `ρ` of DeLong's per-row components (both sets, one value).
    pub correlation: f64,
    /// Kish's design effect `1 + (m̄ − 1)ρ` of the labeled and the mixture side: how many rows
    /// count as one independent draw.
    pub design_effect_labeled: f64,
    pub design_effect_mixture: f64,
}

/// [`Auc`] whose interval counts episodes rather than rows. DeLong's variance
/// `S₁₀/n_N + S₀₁/n_U` of the Mann–Whitney statistic is built from per-row components (a labeled
/// row's share of mixture rows it outscores, a mixture row's share of labeled rows above it);
/// each side's term is multiplied by Kish's design effect `1 + (m̄ − 1)ρ`, with `m̄` the side's
/// row-weighted mean episode length and `ρ` the intra-episode correlation of the components.
/// `ρ` is one value for both sides (the one-way ANOVA estimator over the episodes of both, each
/// side's components standardised) because D^N's held-out rows can be a single episode, whose
/// own between-episode variance cannot be measured; D^U has many. With every row its own
/// episode this is DeLong's interval. The interval is `[0, 1]` with fewer than two rows on a
/// side. None when either side is empty or the episode lists do not match the scores.
pub fn roc_auc_by_episode(labeled: &[f32], mixture: &[f32], episodes: EpisodesOf) -> Option<Auc> {
    let mismatched =
        episodes.labeled.len() != labeled.len() || episodes.mixture.len() != mixture.len();
    if labeled.is_empty() || mixture.is_empty() || mismatched {
        return None;
    }
    let (v10, v01) =
        (delong_components(labeled, mixture), delong_components_below(mixture, labeled));
    let a = v10.iter().sum::<f64>() / v10.len() as f64;
    let (s10, s01) = (sample_variance(&v10, a), sample_variance(&v01, a));
    let correlation = intra_episode_correlation(&[
        (&v10, episodes.labeled, a, s10),
        (&v01, episodes.mixture, a, s01),
    ]);
    let design_effect = |ids: &[u32]| 1.0 + (row_weighted_episode_length(ids) - 1.0) * correlation;
    let dependence = EpisodeDependence {
        correlation,
        design_effect_labeled: design_effect(episodes.labeled),
        design_effect_mixture: design_effect(episodes.mixture),
    };
    let (n1, n0) = (labeled.len() as f64, mixture.len() as f64);
    let variance = match (labeled.len() < 2, mixture.len() < 2) {
        (false, false) => {
            dependence.design_effect_labeled * s10 / n1
                + dependence.design_effect_mixture * s01 / n0
        }
        _ => f64::INFINITY,
    };
    let half = Z_AUC * variance.sqrt();
    let (lower, upper) = ((a - half).max(0.0), (a + half).min(1.0));
    Some(Auc { value: a, lower, upper, episodes: Some(dependence) })
}

/// For each of `rows`, the share of `others` it outscores, ties counted half (DeLong's
/// component of a labeled row when `rows` are labeled and `others` the mixture).
fn delong_components(rows: &[f32], others: &[f32]) -> Vec<f64> {
    let mut sorted = others.to_vec();
    sorted.sort_by(f32::total_cmp);
    let n = sorted.len() as f64;
    let below = |s: f32| sorted.partition_point(|&o| o < s);
    let at_most = |s: f32| sorted.partition_point(|&o| o <= s);
    rows.iter().map(|&s| (below(s) as f64 + 0.5 * (at_most(s) - below(s)) as f64) / n).collect()
}

/// For each of `rows`, the share of `others` that outscore it, ties counted half (DeLong's
/// component of a mixture row when `others` are labeled).
fn delong_components_below(rows: &[f32], others: &[f32]) -> Vec<f64> {
    delong_components(rows, others).into_iter().map(|v| 1.0 - v).collect()
}

/// `Σ (v − mean)² / (n − 1)`; 0 for fewer than two values.
pub(super) fn sample_variance(values: &[f64], mean: f64) -> f64 {
    if values.len() < 2 {
        return 0.0;
    }
    values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (values.len() - 1) as f64
}

/// The one-way ANOVA estimator of the intra-class correlation over the episodes of every side
/// (`(values, episode of each, mean, variance)`, values centred on their side's mean and scaled
/// by its deviation), kept in `[0, 1]`; 0 where no episode holds two rows.
pub(super) fn intra_episode_correlation(sides: &[(&[f64], &[u32], f64, f64)]) -> f64 {
    // Per episode (side, id): rows, sum and sum of squares of the standardised values. Ordered,
    // so the sums below add in the same order in every process: the same run records the same
    // bits (a hash map's order changes with its per-process seed).
    let mut episodes: BTreeMap<(usize, u32), (f64, f64, f64)> = BTreeMap::new();
    for (side, &(values, ids, mean, variance)) in sides.iter().enumerate() {
        let scale = if variance > 0.0 { variance.sqrt() } else { f64::INFINITY };
        for (&v, &id) in values.iter().zip(ids) {
            let z = (v - mean) / scale;
            let e = episodes.entry((side, id)).or_default();
            *e = (e.0 + 1.0, e.1 + z, e.2 + z * z);
        }
    }
    let groups = episodes.len() as f64;
    let rows: f64 = episodes.values().map(|e| e.0).sum();
    if groups < 2.0 || rows <= groups {
        return 0.0;
    }
    let grand = episodes.values().map(|e| e.1).sum::<f64>() / rows;
    let between: f64 = episodes.values().map(|&(m, sum, _)| m * (sum / m - grand).powi(2)).sum();
    let within: f64 = episodes.values().map(|&(m, sum, sq)| sq - sum * sum / m).sum();
    let (msb, msw) = (between / (groups - 1.0), within.max(0.0) / (rows - groups));
    let sizes_squared: f64 = episodes.values().map(|e| e.0 * e.0).sum();
    let m0 = (rows - sizes_squared / rows) / (groups - 1.0);
    let denominator = msb + (m0 - 1.0) * msw;
    if denominator <= 0.0 {
        return 0.0;
    }
    ((msb - msw) / denominator).clamp(0.0, 1.0)
}

/// `Σ m_e² / Σ m_e` over the episodes' row counts `m_e`: the episode length a random row sits
/// in, which is what a design effect reads when episodes differ in length.
pub(super) fn row_weighted_episode_length(episode_ids: &[u32]) -> f64 {
    let mut rows: BTreeMap<u32, f64> = BTreeMap::new();
    episode_ids.iter().for_each(|&id| *rows.entry(id).or_default() += 1.0);
    let total: f64 = rows.values().sum();
    if total == 0.0 {
        return 1.0;
    }
    rows.values().map(|m| m * m).sum::<f64>() / total
}

/// A logistic recalibration `c' = scale · c + shift` of a logit whose `σ(c)` should be
/// `P(labeled | x)` with the two classes weighted equally (as the discriminator's balanced
/// minibatches make it): fitted on held-out scores by Newton's method on the class-balanced
/// logistic loss (Platt scaling). Returns `(scale, shift)`; `(1, 0)` when the fit does not
/// converge or the sets are empty.
pub fn platt_scaling(labeled: &[f32], mixture: &[f32]) -> (f64, f64) {
    if labeled.is_empty() || mixture.is_empty() {
        return (1.0, 0.0);
    }
    let rows = labeled.iter().map(|&c| (c as f64, 1.0, 0.5 / labeled.len() as f64));
    let rows: Vec<(f64, f64, f64)> =
        rows.chain(mixture.iter().map(|&c| (c as f64, 0.0, 0.5 / mixture.len() as f64))).collect();
    let (mut scale, mut shift) = (1.0f64, 0.0f64);
    for _ in 0..50 {
        // Gradient and Hessian of the weighted loss Σ w (softplus(z) − y z), z = scale c + shift.
        let (mut g, mut h) = ([0.0f64; 2], [[0.0f64; 2]; 2]);
        for &(c, y, w) in &rows {
            let p = 1.0 / (1.0 + (-(scale * c + shift)).exp());
            let (r, v) = (w * (p - y), w * p * (1.0 - p));
            g = [g[0] + r * c, g[1] + r];
            h = [[h[0][0] + v * c * c, h[0][1] + v * c], [h[1][0] + v * c, h[1][1] + v]];
        }
        let det = h[0][0] * h[1][1] - h[0][1] * h[1][0];
        if det.abs() < 1e-18 {
            return (1.0, 0.0);
        }
        let step =
            [(h[1][1] * g[0] - h[0][1] * g[1]) / det, (h[0][0] * g[1] - h[1][0] * g[0]) / det];
        (scale, shift) = (scale - step[0], shift - step[1]);
        if step[0].abs().max(step[1].abs()) < 1e-10 {
            break;
        }
    }
    if scale.is_finite() && shift.is_finite() && scale > 0.0 {
        (scale, shift)
    } else {
        (1.0, 0.0)
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A draw of N(0, 1) by Box–Muller: enough for a test's draws.
    pub(in crate::algo::safedice) fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Scores of a known mixture: the labeled class ~ N(μ, 1), the other ~ N(0, 1); the mixture
    /// holds `share` of the labeled class. With a monotone score, BBE converges to `share`
    /// (min d^P/d^N → 0 in the far tail).
    pub(in crate::algo::safedice) fn known_mixture(
        rng: &mut ChaCha8Rng,
        mu: f32,
        share: f64,
        n_labeled: usize,
        n_mixture: usize,
    ) -> (Vec<f32>, Vec<f32>) {
        let mut normal = || standard_normal(rng) as f32;
        let labeled: Vec<f32> = (0..n_labeled).map(|_| mu + normal()).collect();
        let mut mixture = Vec::with_capacity(n_mixture);
        let mut rng2 = ChaCha8Rng::seed_from_u64(n_mixture as u64 ^ 77);
        for _ in 0..n_mixture {
            let from_labeled = rng2.random::<f64>() < share;
            mixture.push(if from_labeled { mu + normal() } else { normal() });
        }
        (labeled, mixture)
    }

    /// Over shares 0.2-0.8 and sizes 500-8,000, the true share lies within the reported
    /// interval in most draws, and the point estimate is close at the larger sizes.
    #[test]
    fn best_bin_recovers_known_mixture_shares() {
        let mut covered = 0;
        let mut trials = 0;
        for (k, &share) in [0.2, 0.5, 0.8].iter().enumerate() {
            for &(n_l, n_m) in &[(500, 2000), (2000, 4000), (8000, 8000)] {
                for rep in 0..4 {
                    let mut rng = ChaCha8Rng::seed_from_u64((k * 100 + rep) as u64 + n_l as u64);
                    let (l, m) = known_mixture(&mut rng, 4.0, share, n_l, n_m);
                    let e = best_bin_estimate(&l, &m).unwrap();
                    trials += 1;
                    covered += usize::from(e.lower <= share && share <= e.upper);
                    if n_l == 8000 {
                        assert!((e.value - share).abs() < 0.08, "share {share}: {e:?}");
                    }
                    assert!(e.lower <= e.value && e.value <= e.upper, "{e:?}");
                }
            }
        }
        assert!(covered * 10 >= trials * 8, "covered {covered} of {trials}");
    }

    /// The paper's minimum over the mixture is set by its most extreme row; the top bin is not:
    /// one planted outlier moves the minimum-based value to ~0 and BBE not at all.
    #[test]
    fn one_extreme_row_does_not_set_the_estimate() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (l, mut m) = known_mixture(&mut rng, 4.0, 0.5, 2000, 4000);
        let clean = best_bin_estimate(&l, &m).unwrap().value;
        m.push(40.0);
        let with_outlier = best_bin_estimate(&l, &m).unwrap().value;
        assert!((clean - with_outlier).abs() < 0.01, "{clean} vs {with_outlier}");
        let paper_min = m.iter().map(|&c| (-(c as f64)).exp()).fold(f64::INFINITY, f64::min);
        assert!(paper_min < 1e-10 && with_outlier > 0.35);
    }

    /// Scores that do not separate the sets: the estimate's interval covers 1 and the AUC's
    /// covers 0.5; the mixture proportion is not identifiable.
    #[test]
    fn inseparable_scores_cover_one_and_one_half() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (l, m) = known_mixture(&mut rng, 0.0, 0.5, 1000, 4000);
        let e = best_bin_estimate(&l, &m).unwrap();
        assert!(e.upper >= 1.0, "{e:?}");
        let auc = roc_auc(&l, &m).unwrap();
        assert!(auc.lower <= 0.5 && auc.upper >= 0.5, "{auc:?}");
    }

    /// AUC against its closed form for two unit normals `μ` apart: Φ(μ/√2).
    #[test]
    fn auc_of_two_normals_matches_the_closed_form() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (l, m) = known_mixture(&mut rng, 1.0, 0.0, 4000, 4000);
        let auc = roc_auc(&l, &m).unwrap();
        let expected = 0.760_249; // Φ(1/√2)
        assert!((auc.value - expected).abs() < 0.02, "{auc:?}");
        assert!(auc.lower < auc.value && auc.value < auc.upper);
        // Ties count half: identical scores give exactly 0.5.
        assert_eq!(roc_auc(&[1.0; 10], &[1.0; 20]).unwrap().value, 0.5);
    }

    /// Scores that are a calibrated logit shrunk by 3 and shifted by 1 are mapped back: for
    /// shifted normals the balanced log-odds is linear, so the fit recovers it.
    #[test]
    fn platt_scaling_undoes_a_known_distortion() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (l, m) = known_mixture(&mut rng, 2.0, 0.0, 20_000, 20_000);
        // Classes N(2, 1) and N(0, 1): balanced log-odds 2x − 2. Distorted scores s = x/3 + 1.
        let distort = |v: &[f32]| v.iter().map(|&x| x / 3.0 + 1.0).collect::<Vec<f32>>();
        let (scale, shift) = platt_scaling(&distort(&l), &distort(&m));
        // 2x − 2 = 2(3(s − 1)) − 2 = 6s − 8.
        assert!((scale - 6.0).abs() < 0.2 && (shift + 8.0).abs() < 0.3, "{scale}, {shift}");
        assert_eq!(platt_scaling(&[], &[1.0]), (1.0, 0.0));
    }

    /// Scores of episodes whose rows share an offset (`N(0, 1)` per episode, `N(0, noise²)` per
    /// row), the same law on both sides: the true AUC is 0.5.
    fn episodes_sharing_an_offset(
        rng: &mut ChaCha8Rng,
        episodes: usize,
        length: usize,
        noise: f64,
    ) -> (Vec<f32>, Vec<u32>) {
        let mut normal = || standard_normal(rng);
        let mut scores = Vec::with_capacity(episodes * length);
        for _ in 0..episodes {
            let offset = normal();
            scores.extend((0..length).map(|_| (offset + noise * normal()) as f32));
        }
        let ids = (0..episodes * length).map(|row| (row / length) as u32).collect();
        (scores, ids)
    }

    /// Where the rows of an episode move together, an interval that counts rows excludes the
    /// true 0.5 in most draws (4 labeled episodes of 50 rows look like 200 draws); counting
    /// episodes covers it at about the nominal 90%.
    #[test]
    fn counting_episodes_covers_the_true_auc_where_counting_rows_does_not() {
        let (mut by_episode, mut by_row, trials) = (0, 0, 200);
        for trial in 0..trials {
            let mut rng = ChaCha8Rng::seed_from_u64(1000 + trial);
            let (l, l_ids) = episodes_sharing_an_offset(&mut rng, 4, 50, 0.5);
            let (m, m_ids) = episodes_sharing_an_offset(&mut rng, 40, 50, 0.5);
            let episodes = EpisodesOf { labeled: &l_ids, mixture: &m_ids };
            let auc = roc_auc_by_episode(&l, &m, episodes).unwrap();
            by_episode += usize::from(auc.lower <= 0.5 && 0.5 <= auc.upper);
            let rows = roc_auc(&l, &m).unwrap();
            by_row += usize::from(rows.lower <= 0.5 && 0.5 <= rows.upper);
            assert!((auc.value - rows.value).abs() < 1e-12, "the same statistic");
            let d = auc.episodes.unwrap();
            assert!(d.correlation > 0.5 && d.design_effect_labeled > 20.0, "{d:?}");
        }
        assert!(by_episode * 100 >= trials as usize * 80, "episodes: covered {by_episode}");
        assert!(by_row * 100 <= trials as usize * 40, "rows: covered {by_row}");
    }

    /// With every row its own episode nothing is inflated: DeLong's interval, about as wide as
    /// Hanley–McNeil's on two normals, around the same value.
    #[test]
    fn independent_rows_give_delong_interval() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (l, m) = known_mixture(&mut rng, 1.0, 0.0, 2000, 3000);
        let (l_ids, m_ids): (Vec<u32>, Vec<u32>) = ((0..2000).collect(), (0..3000).collect());
        let episodes = EpisodesOf { labeled: &l_ids, mixture: &m_ids };
        let auc = roc_auc_by_episode(&l, &m, episodes).unwrap();
        let rows = roc_auc(&l, &m).unwrap();
        let d = auc.episodes.clone().unwrap();
        assert_eq!(
            (d.correlation, d.design_effect_labeled, d.design_effect_mixture),
            (0.0, 1.0, 1.0)
        );
        let ratio = (auc.upper - auc.lower) / (rows.upper - rows.lower);
        assert!((0.85..1.15).contains(&ratio), "{auc:?} vs {rows:?}");
        assert!((auc.value - 0.760_249).abs() < 0.02, "{auc:?}");
        let one = [1u32];
        let single = EpisodesOf { labeled: &one, mixture: &m_ids };
        let wide = roc_auc_by_episode(&l[..1], &m, single).unwrap();
        assert_eq!((wide.lower, wide.upper), (0.0, 1.0), "one labeled row says nothing");
        assert!(roc_auc_by_episode(&l, &m, single).is_none(), "episodes must match the rows");
    }

    #[test]
    fn empty_sets_have_no_estimate() {
        assert!(best_bin_estimate(&[], &[1.0]).is_none());
        assert!(roc_auc(&[1.0], &[]).is_none());
    }
}
