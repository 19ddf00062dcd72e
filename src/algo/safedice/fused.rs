//! SafeDICE's two hot loops on the fused CPU engine ([`crate::algo::fused_mlp`]): the
//! discriminator step (Eq. 9 with its gradient penalty) and the main step (Eq. 36 with ν's
//! penalty, then the policy step of Eq. 37). [`super::objectives`] is the reference: it writes
//! every loss once as candle tensor code, and this file computes the same losses with
//! hand-derived gradients (checked against candle autograd on that code in the tests) and every
//! buffer reused between steps. docs/performance.md explains why and what it gains.
//!
//! The networks stay candle [`Mlp`]s (checkpoints, export and the optimiser are unchanged): each
//! step copies their parameters in and hands gradients back to [`crate::algo::optim::Adam`].
//! The engine knows nothing of the trainer: [`super::fused_steps`] hands it the minibatch the
//! trainer drew, so both engines consume the run's random numbers identically.

use candle_core::Result;

use super::objectives::{with_uniform_share, MASK_RENORM_EPS};
use crate::algo::fused_mlp::{EngineThreads, FusedMlp, TrainingWorkspace};
use crate::algo::fused_ops::{interpolate_rows, sigmoid_f32, softplus_f32, unit_penalty_and_grad};
use crate::algo::fused_policy::FusedPolicyStep;
pub use crate::algo::fused_policy::HostActions;
use crate::algo::mlp::Mlp;

/// One discriminator step's inputs: `B` rows of D^N and of D^U (`cat(s, a)`), and the penalty's
/// interpolation draws (None without a penalty).
pub struct HostDiscBatch<'a> {
    pub x_n: &'a [f32],
    pub x_u: &'a [f32],
    /// `(u1, u2, perm)`: points `u1·x_N + (1−u1)·x_U` and `u2·x_U[perm] + (1−u2)·x_U`.
    pub penalty: Option<(&'a [f32], &'a [f32], &'a [u32])>,
    /// λ of the penalty.
    pub penalty_coef: f32,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct DiscOutcome {
    /// Classification loss + λ · penalty.
    pub loss: f32,
    pub classification: f32,
    /// The penalty before λ.
    pub penalty: f32,
    pub prob_n: f32,
    pub prob_u: f32,
}

/// One main-loop iteration's inputs (host rows gathered by the trainer).
pub struct HostMainBatch<'a> {
    pub s: &'a [f32],
    pub s_next: &'a [f32],
    pub s0: &'a [f32],
    pub reward: &'a [f32],
    /// γ' per row (γ, or 0 on masked terminal rows).
    pub discount: &'a [f32],
    pub gamma: f32,
    /// ν's zero-centred penalty: interpolation weights (`B`, shared by the two point sets
    /// `u·s0 + (1−u)·s` and `u·s' + (1−u)·s`) and λ; None without a penalty.
    pub penalty: Option<(&'a [f32], f32)>,
    /// Policy observations (`B × obs_dim`) and actions.
    pub policy_obs: &'a [f32],
    pub actions: HostActions<'a>,
    /// Rows with an action (all but absorbing-state rows); None when all have one.
    pub has_action: Option<&'a [bool]>,
    /// The share of the policy weights spread evenly (`policy_uniform_share`).
    pub uniform_share: f32,
}

#[derive(Clone, Debug, Default)]
pub struct MainOutcome {
    /// Eq. 36 + λ · penalty.
    pub nu_loss: f32,
    /// The penalty before λ.
    pub nu_penalty: f32,
    pub policy_loss: f32,
    pub nu_initial_mean: f32,
}

/// Fused copies of the three networks with their buffers, gradients and per-batch scratch (the
/// policy's in the step all algorithms share, [`FusedPolicyStep`]).
pub struct FusedSafedice {
    disc: FusedMlp,
    nu: FusedMlp,
    ws_disc: TrainingWorkspace,
    ws_nu: TrainingWorkspace,
    pub disc_grads: Vec<f32>,
    pub nu_grads: Vec<f32>,
    pub policy: FusedPolicyStep,
    /// `A` of the last main step and the policy weights `w̃ / mean(w̃)` (length B).
    pub advantages: Vec<f32>,
    pub weights: Vec<f32>,
}

impl FusedSafedice {
    /// Buffers for batch size `batch`, steps on the job's `threads`.
    pub fn new(
        disc: &Mlp,
        nu: &Mlp,
        policy: &Mlp,
        batch: usize,
        threads: &EngineThreads,
    ) -> Result<Self> {
        let (disc, nu) = (disc.to_fused()?, nu.to_fused()?);
        Ok(Self {
            ws_disc: TrainingWorkspace::new(disc.shape(), 4 * batch, threads),
            ws_nu: TrainingWorkspace::new(nu.shape(), 5 * batch, threads),
            disc_grads: vec![0.0; disc.num_params()],
            nu_grads: vec![0.0; nu.num_params()],
            policy: FusedPolicyStep::new(policy, batch, threads)?,
            advantages: vec![0.0; batch],
            weights: vec![0.0; batch],
            disc,
            nu,
        })
    }

    /// Eq. 9's loss `mean softplus(−c_N) + mean softplus(c_U)` plus `λ mean((‖∇ₓc(x̂)‖ − 1)²)`,
    /// its gradient into `disc_grads` (parameters copied from `net` first).
    pub fn disc_grads(&mut self, net: &Mlp, batch: &HostDiscBatch) -> Result<DiscOutcome> {
        net.copy_into_fused(&mut self.disc)?;
        let d = self.disc.shape().input();
        let b = batch.x_n.len() / d;
        let input = self.ws_disc.input_mut();
        input[..b * d].copy_from_slice(batch.x_n);
        input[b * d..2 * b * d].copy_from_slice(batch.x_u);
        let penalty_rows = match batch.penalty {
            Some((u1, u2, perm)) => {
                let (loss_rows, points) = input.split_at_mut(2 * b * d);
                let (x_n, x_u) = loss_rows.split_at(b * d);
                interpolate_rows(&mut points[..b * d], x_n, x_u, u1, d);
                for (r, &p) in perm.iter().enumerate() {
                    let p = p as usize;
                    let (t, out) = (u2[r], &mut points[(b + r) * d..(b + r + 1) * d]);
                    let (shuffled, own) = (&x_u[p * d..(p + 1) * d], &x_u[r * d..(r + 1) * d]);
                    for ((o, &x), &y) in out.iter_mut().zip(shuffled).zip(own) {
                        *o = t * x + (1.0 - t) * y;
                    }
                }
                2 * b
            }
            None => 0,
        };
        let mut outcome = DiscOutcome::default();
        let lambda = batch.penalty_coef;
        self.disc_grads.fill(0.0);
        let penalty = self.ws_disc.train_pass(
            &self.disc,
            (2 * b, penalty_rows),
            &mut self.disc_grads,
            |out, dout| {
                let inv_b = 1.0 / b as f32;
                for i in 0..b {
                    let (c_n, c_u) = (out[i], out[b + i]);
                    outcome.classification += (softplus_f32(-c_n) + softplus_f32(c_u)) * inv_b;
                    outcome.prob_n += sigmoid_f32(c_n) * inv_b;
                    outcome.prob_u += sigmoid_f32(c_u) * inv_b;
                    dout[i] = -sigmoid_f32(-c_n) * inv_b;
                    dout[b + i] = sigmoid_f32(c_u) * inv_b;
                }
            },
            |g, dp| unit_penalty_and_grad(g, dp, d, lambda),
        );
        outcome.penalty = penalty;
        outcome.loss = outcome.classification + lambda * penalty;
        Ok(outcome)
    }

    /// Eq. 36 (+ ν's zero-centred penalty) into `nu_grads` and Eq. 37 into `policy.grads`, with
    /// the pre-update ν; `advantages` and `weights` hold the batch's A and policy weights after.
    pub fn main_grads(
        &mut self,
        nu: &Mlp,
        policy: &Mlp,
        batch: &HostMainBatch,
    ) -> Result<MainOutcome> {
        nu.copy_into_fused(&mut self.nu)?;
        let d = self.nu.shape().input();
        let b = batch.reward.len();
        let input = self.ws_nu.input_mut();
        input[..b * d].copy_from_slice(batch.s);
        input[b * d..2 * b * d].copy_from_slice(batch.s_next);
        input[2 * b * d..3 * b * d].copy_from_slice(batch.s0);
        let (penalty_rows, lambda) = match batch.penalty {
            Some((u, lambda)) => {
                let points = &mut input[3 * b * d..5 * b * d];
                let (first, second) = points.split_at_mut(b * d);
                interpolate_rows(first, batch.s0, batch.s, u, d);
                interpolate_rows(second, batch.s_next, batch.s, u, d);
                (2 * b, lambda)
            }
            None => (0, 0.0),
        };
        let mut outcome = MainOutcome::default();
        let (adv, weights) = (&mut self.advantages, &mut self.weights);
        let gamma = batch.gamma;
        self.nu_grads.fill(0.0);
        let penalty = self.ws_nu.train_pass(
            &self.nu,
            (3 * b, penalty_rows),
            &mut self.nu_grads,
            |out, dout| {
                // A = r + γ' ν(s') − ν(s); d/dA of log-mean-exp(A) is softmax(A).
                for i in 0..b {
                    adv[i] = batch.reward[i] + batch.discount[i] * out[b + i] - out[i];
                }
                let max = adv.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let mut sum = 0.0;
                for (w, &a) in weights.iter_mut().zip(adv.iter()) {
                    *w = (a - max).exp();
                    sum += *w;
                }
                weights.iter_mut().for_each(|w| *w /= sum);
                outcome.nu_initial_mean = out[2 * b..3 * b].iter().sum::<f32>() / b as f32;
                outcome.nu_loss =
                    max + sum.ln() - (b as f32).ln() + (1.0 - gamma) * outcome.nu_initial_mean;
                for i in 0..b {
                    dout[i] = -weights[i];
                    dout[b + i] = batch.discount[i] * weights[i];
                }
                dout[2 * b..3 * b].fill((1.0 - gamma) / b as f32);
            },
            |g, dp| {
                let inv_rows = 1.0 / penalty_rows as f32;
                let mut total = 0.0;
                for (o, &gv) in dp.iter_mut().zip(g) {
                    total += gv * gv;
                    *o = 2.0 * lambda * inv_rows * gv;
                }
                total * inv_rows
            },
        );
        outcome.nu_penalty = penalty;
        outcome.nu_loss += lambda * penalty;

        // Eq. 37's weights w̃/mean(w̃) = B·softmax(A), masked and renormalised where rows
        // carry no action (as losses::self_normalized_weights and trainer.rs).
        weights.iter_mut().for_each(|w| *w *= b as f32);
        if batch.uniform_share > 0.0 {
            let share = batch.uniform_share;
            weights.iter_mut().for_each(|w| *w = with_uniform_share(*w, share));
        }
        if let Some(has_action) = batch.has_action {
            for (w, &keep) in weights.iter_mut().zip(has_action) {
                if !keep {
                    *w = 0.0;
                }
            }
            let mean = weights.iter().sum::<f32>() / b as f32;
            weights.iter_mut().for_each(|w| *w /= mean + MASK_RENORM_EPS as f32);
        }
        outcome.policy_loss = self.policy.weighted_nll_grads(
            policy,
            batch.policy_obs,
            &batch.actions,
            Some(&self.weights),
        )?;
        Ok(outcome)
    }
}

#[cfg(test)]
mod tests;
