//! SafeDICE's two hot loops on the fused CPU engine ([`super::fused_mlp`]): the discriminator
//! step (Eq. 9 with its gradient penalty) and the main step (Eq. 36 with ν's penalty, then the
//! policy step of Eq. 37). `safedice.rs` is the reference: it writes every loss once as candle
//! tensor code, and this file computes the same losses with hand-derived gradients (checked
//! against candle autograd on that code in the tests) and every buffer reused between steps.
//! docs/performance.md explains why and what it gains.
//!
//! The networks stay candle [`Mlp`]s (checkpoints, export and the optimiser are unchanged): each
//! step copies their parameters in and hands gradients back to [`super::optim::Adam`]. The
//! trainer's minibatches come from `safedice.rs` ([`DiscDraws`], [`MainDraws`]), so both engines
//! consume the run's random numbers identically.

use candle_core::Result;

use super::fused_mlp::{FusedMlp, Workspace};
pub use super::fused_policy::HostActions;
use super::fused_policy::{host, host_scalar, FusedPolicyStep, OwnedActions};
use super::losses::GRAD_NORM_EPS;
use super::mlp::Mlp;
use super::safedice::{
    DiscDraws, MainDraws, SafediceTrainer, DISC_LOSS, MASK_RENORM_EPS, NU_LOSS, POLICY_LOSS,
};
use super::TrainError;

/// `log(1 + eˣ)` without overflow (one value; the tensor form is `losses::softplus`).
pub(super) fn softplus_f32(x: f32) -> f32 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

pub(super) fn sigmoid_f32(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `u·a + (1 − u)·b` row by row (`u` one value per row).
pub fn interpolate_rows(dst: &mut [f32], a: &[f32], b: &[f32], u: &[f32], dim: usize) {
    let rows = dst.chunks_exact_mut(dim).zip(a.chunks_exact(dim)).zip(b.chunks_exact(dim));
    for (((out, x), y), &t) in rows.zip(u) {
        for ((o, &xv), &yv) in out.iter_mut().zip(x).zip(y) {
            *o = t * xv + (1.0 - t) * yv;
        }
    }
}

/// `mean((‖g_r‖ − 1)²)` over the rows `g_r` (width `d`) of the penalty points' input-gradients
/// (losses::unit_gradient_penalty), and `λ ·` its derivative with respect to `g` into `dp`.
pub(super) fn unit_penalty_and_grad(g: &[f32], dp: &mut [f32], d: usize, lambda: f32) -> f32 {
    let inv_rows = 1.0 / (g.len() / d) as f32;
    let mut total = 0.0;
    for (gr, dr) in g.chunks_exact(d).zip(dp.chunks_exact_mut(d)) {
        let norm = (gr.iter().map(|v| v * v).sum::<f32>() + GRAD_NORM_EPS as f32).sqrt();
        total += (norm - 1.0) * (norm - 1.0);
        let k = lambda * inv_rows * 2.0 * (norm - 1.0) / norm;
        for (o, &gv) in dr.iter_mut().zip(gr) {
            *o = k * gv;
        }
    }
    total * inv_rows
}

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
    ws_disc: Workspace,
    ws_nu: Workspace,
    pub disc_grads: Vec<f32>,
    pub nu_grads: Vec<f32>,
    pub policy: FusedPolicyStep,
    /// `A` of the last main step and the policy weights `w̃ / mean(w̃)` (length B).
    pub advantages: Vec<f32>,
    pub weights: Vec<f32>,
}

impl FusedSafedice {
    /// Buffers for batch size `batch`; one compute thread (one per training job: see
    /// bench/README.md).
    pub fn new(disc: &Mlp, nu: &Mlp, policy: &Mlp, batch: usize) -> Result<Self> {
        let (disc, nu) = (disc.to_fused()?, nu.to_fused()?);
        Ok(Self {
            ws_disc: Workspace::new(disc.shape(), 4 * batch, 1),
            ws_nu: Workspace::new(nu.shape(), 5 * batch, 1),
            disc_grads: vec![0.0; disc.num_params()],
            nu_grads: vec![0.0; nu.num_params()],
            policy: FusedPolicyStep::new(policy, batch)?,
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
        let penalty = self.disc.train_pass(
            &mut self.ws_disc,
            2 * b,
            penalty_rows,
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
        let penalty = self.nu.train_pass(
            &mut self.ws_nu,
            3 * b,
            penalty_rows,
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
        // carry no action (as losses::self_normalized_weights and safedice.rs).
        weights.iter_mut().for_each(|w| *w *= b as f32);
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

/// The trainer's steps on this engine: the minibatch `safedice.rs` drew, copied to the host, then
/// the same guard, optimiser step and metrics as the candle path.
impl SafediceTrainer {
    /// [`SafediceTrainer`]'s discriminator step (Eq. 9 + penalty) with fused gradients.
    pub(super) fn discriminator_step_fused(
        &mut self,
        batch: &DiscDraws,
        record: bool,
    ) -> std::result::Result<Vec<(&'static str, f64)>, TrainError> {
        let (x_n, x_u) = (host(&batch.x_n)?, host(&batch.x_u)?);
        let penalty = match &batch.penalty {
            Some((u1, u2, perm)) => Some((host(u1)?, host(u2)?, perm)),
            None => None,
        };
        let fused = self.fused.as_mut().expect("fused path");
        let out = fused.disc_grads(
            &self.disc,
            &HostDiscBatch {
                x_n: &x_n,
                x_u: &x_u,
                penalty: penalty.as_ref().map(|(u1, u2, p)| (&u1[..], &u2[..], &p[..])),
                penalty_coef: self.cfg.discriminator_gp as f32,
            },
        )?;
        let value = self.run.checked(&host_scalar(out.loss)?, DISC_LOSS.0, DISC_LOSS.1)?;
        self.disc_opt.step_with_grads(&self.disc.grads_from_fused(&fused.disc_grads)?)?;
        self.end_discriminator_step()?;
        if !record {
            return Ok(Vec::new());
        }
        let values = [out.loss, out.classification, out.penalty, out.prob_n, out.prob_u];
        let mut values = values.map(|v| v as f64);
        values[0] = value;
        Ok(self.discriminator_metrics(values))
    }

    /// [`SafediceTrainer`]'s main step (Eq. 36 + ν's penalty, Eq. 37) with fused gradients.
    pub(super) fn main_step_fused(
        &mut self,
        batch: &MainDraws,
        record: bool,
    ) -> std::result::Result<Vec<(&'static str, f64)>, TrainError> {
        let (s, s_next, s0) = (host(&batch.s)?, host(&batch.s_next)?, host(&batch.s0)?);
        let (reward, discount) = (host(&batch.reward)?, host(&batch.discount)?);
        let u = batch.penalty_u.as_ref().map(host).transpose()?;
        let policy_obs = host(&batch.policy_obs)?;
        let actions = OwnedActions::from_column(&batch.actions)?;
        let fused = self.fused.as_mut().expect("fused path");
        let out = fused.main_grads(
            &self.nu,
            self.policy.mlp(),
            &HostMainBatch {
                s: &s,
                s_next: &s_next,
                s0: &s0,
                reward: &reward,
                discount: &discount,
                gamma: self.cfg.gamma as f32,
                penalty: u.as_deref().map(|u| (u, self.cfg.nu_gp as f32)),
                policy_obs: &policy_obs,
                actions: actions.view(),
                has_action: batch.has_action.as_deref(),
            },
        )?;
        let nu_value = self.run.checked(&host_scalar(out.nu_loss)?, NU_LOSS.0, NU_LOSS.1)?;
        let pi_value =
            self.run.checked(&host_scalar(out.policy_loss)?, POLICY_LOSS.0, POLICY_LOSS.1)?;
        self.nu_opt.step_with_grads(&self.nu.grads_from_fused(&fused.nu_grads)?)?;
        let policy_grads = self.policy.mlp().grads_from_fused(&fused.policy.grads)?;
        self.policy_opt.step_with_grads(&policy_grads)?;
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        let (w, adv) = (fused.weights.clone(), fused.advantages.clone());
        let values = [nu_value, out.nu_penalty as f64, pi_value, out.nu_initial_mean as f64];
        Ok(self.main_metrics(values, &w, &adv))
    }
}

#[cfg(test)]
mod tests;
