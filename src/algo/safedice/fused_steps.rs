//! The reference trainer's two hot loops on the fused engine: the minibatch the trainer drew
//! ([`DiscDraws`], [`MainDraws`]) copied to the host, the engine's gradients, then the same
//! non-finite guard, optimiser step and metrics as the candle path of [`super::trainer`].

use super::draws::{DiscDraws, MainDraws};
use super::fused::{HostDiscBatch, HostMainBatch};
use super::objectives::{DISC_LOSS, NU_LOSS, POLICY_LOSS};
use super::trainer::SafediceTrainer;
use crate::algo::fused_policy::{host, host_scalar, OwnedActions};
use crate::algo::TrainError;

impl SafediceTrainer {
    /// [`SafediceTrainer`]'s discriminator step (Eq. 9 + penalty) with fused gradients.
    pub(super) fn discriminator_step_fused(
        &mut self,
        batch: &DiscDraws,
        record: bool,
    ) -> Result<Vec<(&'static str, f64)>, TrainError> {
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
        self.disc_opt.step_with_host_grads(&self.disc.fused_grad_slices(&fused.disc_grads)?)?;
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
    ) -> Result<Vec<(&'static str, f64)>, TrainError> {
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
                uniform_share: self.cfg.policy_uniform_share as f32,
            },
        )?;
        let nu_value = self.run.checked(&host_scalar(out.nu_loss)?, NU_LOSS.0, NU_LOSS.1)?;
        let pi_value =
            self.run.checked(&host_scalar(out.policy_loss)?, POLICY_LOSS.0, POLICY_LOSS.1)?;
        self.nu_opt.step_with_host_grads(&self.nu.fused_grad_slices(&fused.nu_grads)?)?;
        let policy_grads = self.policy.mlp().fused_grad_slices(&fused.policy.grads)?;
        self.policy_opt.step_with_host_grads(&policy_grads)?;
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        let (w, adv) = (fused.weights.clone(), fused.advantages.clone());
        let values = [nu_value, out.nu_penalty as f64, pi_value, out.nu_initial_mean as f64];
        Ok(self.main_metrics(values, &w, &adv))
    }
}
