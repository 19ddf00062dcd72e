//! The discriminator's evidence pooled over an episode (`pool_scores_by_episode`).
//!
//! Every episode of D^U comes from one demonstrator, so the label Eq. 10 wants to weigh out is
//! shared by all its rows. A row's own logit estimates `log d^N(s, a) / d^U(s, a)`, the evidence
//! of one step; where the two demonstrators act alike on most steps (the non-preferred one
//! differs only near the cost), most rows of a non-preferred episode look preferred. The mean
//! logit over the episode reads all its steps at once. Recalibrated on held-out episodes (Platt
//! scaling, as the row logits are), it is `log p(m | N) / p(m | U)` for the episode's mean `m`,
//! and Eq. 10 on it reweights D^U to the preferred share exactly as the row-level reward does:
//! `E_U[(1 − α p(m|N)/p(m|U)) / (1 − α) · f] = E_P[f]` for any statistic `m` of the episode, since
//! the mixture's share holds at every value of `m`. Where the episodes separate, the weights are
//! the episode labels themselves (the benchmark's oracle ablation); where they do not, the mean
//! is as uninformative as the rows.
//!
//! Only Eq. 10 reads the means. alpha-hat is one number, the mixture's share whatever the
//! statistic, and Best Bin Estimation stays on the rows: on means, held-out D^N (one to a few
//! episodes on long tasks) gives a step function of as many steps, the row-counted bound is far
//! too narrow for it, and the bin with the lowest bound is then the one noise put lowest (on the
//! development split, alpha-hat fell to a median 0.34 of the true share). The fallback's AUC
//! stays on the rows for the same reason.

use std::collections::HashMap;

/// Replaces every score by the mean score of its episode, `episodes[i]` naming row `i`'s; sums
/// run in row order, so the result is the same on every run.
pub(super) fn pool_by_episode(scores: &mut [f32], episodes: &[u32]) {
    assert_eq!(scores.len(), episodes.len(), "one episode per scored row");
    let mut sums: HashMap<u32, (f64, u32)> = HashMap::new();
    for (&score, &episode) in scores.iter().zip(episodes) {
        let entry = sums.entry(episode).or_insert((0.0, 0));
        entry.0 += score as f64;
        entry.1 += 1;
    }
    for (score, episode) in scores.iter_mut().zip(episodes) {
        let (sum, rows) = sums[episode];
        *score = (sum / rows as f64) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::safedice::mixture::roc_auc;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn every_row_reads_its_episodes_mean() {
        let mut scores = [1.0, 3.0, 10.0, -2.0, 5.0];
        pool_by_episode(&mut scores, &[7, 7, 2, 7, 2]);
        let third = (1.0f32 + 3.0 - 2.0) / 3.0;
        assert_eq!(scores, [third, third, 7.5, third, 7.5]);
    }

    /// Rows whose logit carries a small shift for the non-preferred demonstrator under unit
    /// noise: one row barely ranks the classes (AUC ≈ 0.56), the mean of fifty rows nearly
    /// separates them (the shift grows √50-fold against the noise).
    #[test]
    fn pooled_scores_separate_what_single_rows_barely_do() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let rows = |shift: f32, episodes: u32, first: u32, rng: &mut ChaCha8Rng| {
            let mut scores = Vec::new();
            let mut ids = Vec::new();
            for e in 0..episodes {
                for _ in 0..50 {
                    let noise: f32 = (0..12).map(|_| rng.random::<f32>()).sum::<f32>() - 6.0;
                    scores.push(shift + noise);
                    ids.push(first + e);
                }
            }
            (scores, ids)
        };
        let (mut n, n_ids) = rows(0.2, 40, 0, &mut rng);
        let (mut p, p_ids) = rows(0.0, 40, 1000, &mut rng);
        let row_auc = roc_auc(&n, &p).unwrap().value;
        assert!((0.52..0.62).contains(&row_auc), "{row_auc}");
        pool_by_episode(&mut n, &n_ids);
        pool_by_episode(&mut p, &p_ids);
        let pooled_auc = roc_auc(&n, &p).unwrap().value;
        assert!(pooled_auc > 0.8, "{pooled_auc}");
    }
}
