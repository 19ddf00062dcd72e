//! What the benchmark's ablation report reads off a trained SafeDICE run (`bench --ablations`):
//! Eq. 12's weights and advantages on every row of D^U with the current ν, and the share of
//! the policy step's weight spread evenly. Read-only: nothing here moves the run.

use candle_core::Tensor;

use super::trainer::{SafediceTrainer, SCORING_CHUNK};
use crate::algo::TrainError;

impl SafediceTrainer {
    /// Eq. 12's weights `w = exp(A − 1)` on every row of D^U with the current ν
    /// (`A = r + γ' ν(s') − ν(s)` on the flow table), self-normalised to mean 1 over D^U: the
    /// whole-dataset version of Eq. 37's per-batch weights (absorbing-state rows, which carry no
    /// action, are left out as there). None before the main phase.
    pub fn unlabeled_weights(&self) -> Result<Option<Vec<f64>>, TrainError> {
        let Some(advantages) = self.unlabeled_advantages()? else { return Ok(None) };
        // n · softmax(A): the constant e^{−1} cancels, as in `losses::self_normalized_weights`.
        let n = advantages.len();
        let max = advantages.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let exp: Vec<f64> = advantages.iter().map(|a| (a - max).exp()).collect();
        let total: f64 = exp.iter().sum();
        Ok(Some(exp.iter().map(|e| e * n as f64 / total).collect()))
    }

    /// `A = r + γ' ν(s') − ν(s)` (Eq. 12's log-weight plus 1) on every row of D^U with the
    /// current ν; None before the main phase. Whole-dataset weights from these can be ruled by
    /// a handful of rows far outside the minibatches' usual range; Eq. 37 normalises per batch.
    pub fn unlabeled_advantages(&self) -> Result<Option<Vec<f64>>, TrainError> {
        let Some(flow) = &self.flow else { return Ok(None) };
        let n = flow.real_rows;
        let mut advantages = Vec::with_capacity(n);
        for start in (0..n).step_by(SCORING_CHUNK) {
            let rows = SCORING_CHUNK.min(n - start);
            let s = flow.obs.narrow(0, start, rows)?;
            let s_next = flow.next_obs.narrow(0, start, rows)?;
            let values = self.nu.forward(&Tensor::cat(&[&s, &s_next], 0)?)?.squeeze(1)?;
            let (nu_s, nu_next) = (values.narrow(0, 0, rows)?, values.narrow(0, rows, rows)?);
            let reward = flow.reward.narrow(0, start, rows)?;
            let discount = flow.discount.narrow(0, start, rows)?;
            let a = ((reward + (discount * nu_next)?)? - nu_s)?;
            advantages.extend(a.to_vec1::<f32>()?.into_iter().map(f64::from));
        }
        Ok(Some(advantages))
    }

    /// Eq. 10's reward (standardised and scaled as the ν step reads it) on every row of D^U;
    /// None before the main phase.
    pub fn unlabeled_rewards(&self) -> Result<Option<Vec<f64>>, TrainError> {
        let Some(flow) = &self.flow else { return Ok(None) };
        let reward = flow.reward.narrow(0, 0, flow.real_rows)?.to_vec1::<f32>()?;
        Ok(Some(reward.into_iter().map(f64::from).collect()))
    }

    /// The share of each policy step's weight spread evenly (`policy_uniform_share`).
    pub fn policy_uniform_share(&self) -> f64 {
        self.cfg.policy_uniform_share
    }
}
