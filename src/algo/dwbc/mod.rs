//! DWBC adapted to non-preferred data (paper Appendix C.2): a discriminator `d(s, a, log π)`
//! trained by negative-unlabeled learning (Eq. 38), and behaviour cloning on D^U weighted by
//! `1 − d(s, a)` (Eq. 39). Discriminator and policy are trained together, one step each per
//! iteration, as in DWBC.

pub mod config;
pub mod fused;
pub mod objectives;

use candle_core::Tensor;

use crate::algo::columns::uniform_column;
use crate::algo::fused_policy::{
    fused_policy_update, host, host_scalar, FusedPolicyStep, LossName,
};
use crate::algo::hyperparams::AlgorithmConfig;
use crate::algo::losses::{interpolate, unit_gradient_penalty, weighted_nll};
use crate::algo::mlp::Mlp;
use crate::algo::optim::Adam;
use crate::algo::policy::{PolicyArtifact, PolicyNet};
use crate::algo::run::RunData;
use crate::algo::{Progress, ResolvedConfig, TrainError, Trainer, TrainingData};
use config::DwbcConfig;
use fused::{DwbcDiscBatch, FusedDwbcDisc};
pub use objectives::{negative_unlabeled_loss, preference_weights, LOGIT_CLIP};

pub struct DwbcTrainer {
    run: RunData,
    cfg: DwbcConfig,
    disc: Mlp,
    disc_opt: Adam,
    policy: PolicyNet,
    policy_opt: Adam,
    /// The fused CPU engine's discriminator and policy steps (None on other devices).
    fused: Option<(FusedDwbcDisc, FusedPolicyStep)>,
}

const DISC_LOSS: LossName =
    ("the DWBC discriminator loss (Eq. 38)", "Try a lower lr_discriminator.");
const POLICY_LOSS: LossName = ("the DWBC policy loss (Eq. 39)", "Try a lower lr_actor.");

impl DwbcTrainer {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<DwbcTrainer, TrainError> {
        let AlgorithmConfig::Dwbc(cfg) = &config.specific else {
            return Err(TrainError::Other("not a DWBC config".into()));
        };
        let mut run = RunData::new(config, data)?;
        let disc = run.new_critic("discriminator", run.state_action_dim() + 1)?;
        let policy = run.new_policy("policy")?;
        let fused = match run.device {
            candle_core::Device::Cpu => Some((
                FusedDwbcDisc::new(&disc, run.batch(), &run.threads)?,
                FusedPolicyStep::new(policy.mlp(), run.batch(), &run.threads)?,
            )),
            _ => None,
        };
        Ok(DwbcTrainer {
            fused,
            disc_opt: Adam::new(disc.named_vars(), cfg.lr_discriminator)?,
            policy_opt: Adam::new(policy.mlp().named_vars(), config.common.lr_actor)?,
            cfg: cfg.clone(),
            run,
            disc,
            policy,
        })
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<DwbcTrainer, TrainError> {
        let mut t = DwbcTrainer::new(config, data)?;
        let restored = t.run.restore(bytes)?;
        restored.restore("discriminator", &mut t.disc_opt)?;
        restored.restore("policy", &mut t.policy_opt)?;
        Ok(t)
    }
}

impl DwbcTrainer {
    /// Eq. 38 (+ penalty) and Eq. 39 on candle autograd; the losses and the weights' mean.
    fn candle_updates(
        &mut self,
        x_n: &Tensor,
        x_u: &Tensor,
        mix: Option<&Tensor>,
        log_prob_u: &Tensor,
    ) -> Result<(f64, f64, f64), TrainError> {
        let b = x_n.dim(0)?;
        let logits = self.disc.forward(&Tensor::cat(&[x_n, x_u], 0)?)?.squeeze(1)?;
        let (c_n, c_u) = (logits.narrow(0, 0, b)?, logits.narrow(0, b, b)?);
        let mut loss_d = negative_unlabeled_loss(&c_n, &c_u, self.cfg.eta)?;
        if let Some(mix) = mix {
            let penalty = unit_gradient_penalty(&self.disc, &interpolate(x_n, x_u, mix)?)?;
            loss_d = (loss_d + (penalty * self.cfg.discriminator_gp)?)?;
        }
        let weights = preference_weights(&c_u)?;
        let loss_pi = weighted_nll(log_prob_u, &weights)?;
        let d_value = self.run.checked(&loss_d, DISC_LOSS.0, DISC_LOSS.1)?;
        let pi_value = self.run.checked(&loss_pi, POLICY_LOSS.0, POLICY_LOSS.1)?;
        self.disc_opt.minimize(&loss_d)?;
        self.policy_opt.minimize(&loss_pi)?;
        Ok((d_value, pi_value, super::losses::scalar(&weights.mean_all()?)?))
    }

    /// The same updates on the fused engine: the discriminator's gradient and Eq. 39's weights
    /// from one fused pass, then the shared policy step.
    fn fused_updates(
        &mut self,
        x_n: &Tensor,
        x_u: &Tensor,
        mix: Option<&Tensor>,
        obs_u: &Tensor,
        act_u: &super::columns::ActionColumn,
    ) -> Result<(f64, f64, f64), TrainError> {
        let (disc, policy_step) = self.fused.as_mut().expect("fused path");
        let (x_n, x_u, mix) = (host(x_n)?, host(x_u)?, mix.map(host).transpose()?);
        let loss = disc.grads(
            &self.disc,
            &DwbcDiscBatch {
                x_n: &x_n,
                x_u: &x_u,
                penalty: mix.as_deref(),
                penalty_coef: self.cfg.discriminator_gp as f32,
                eta: self.cfg.eta as f32,
            },
        )?;
        let d_value = self.run.checked(&host_scalar(loss)?, DISC_LOSS.0, DISC_LOSS.1)?;
        let weights = disc.preference_weights();
        let weight_mean = weights.iter().map(|&w| f64::from(w)).sum::<f64>() / weights.len() as f64;
        let weights = Tensor::from_vec(
            weights,
            x_u.len() / self.disc.fused_shape().input(),
            &candle_core::Device::Cpu,
        )?;
        let (run, policy, opt) = (&self.run, self.policy.mlp(), &mut self.policy_opt);
        let pi_value = fused_policy_update(
            policy_step,
            run,
            policy,
            opt,
            obs_u,
            act_u,
            Some(&weights),
            POLICY_LOSS,
        )?;
        self.disc_opt.step_with_host_grads(&self.disc.fused_grad_slices(&disc.grads)?)?;
        Ok((d_value, pi_value, weight_mean))
    }
}

impl Trainer for DwbcTrainer {
    fn progress(&self) -> Progress {
        Progress { step: self.run.step, total: self.run.total(), phase: "policy" }
    }

    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.run.ensure_running()?;
        let b = self.run.batch();
        let idx_n = self.run.sample_n()?;
        let idx_u = self.run.sample_u()?;
        let (n, u) = (self.run.non_preferred(), &self.run.u);
        let (obs_u, act_u) = (u.obs.index_select(&idx_u, 0)?, u.actions.select(&idx_u)?);
        let log_prob_u = self.policy.log_prob(&obs_u, &act_u)?;
        let log_prob_n =
            self.policy.log_prob(&n.obs.index_select(&idx_n, 0)?, &n.actions.select(&idx_n)?)?;
        // d(s, a, log π): the policy's log-likelihood is an input, not a path for gradients.
        let x_n = Tensor::cat(&[n.state_action(&idx_n)?, log_prob_n.detach().unsqueeze(1)?], 1)?;
        let x_u = Tensor::cat(&[u.state_action(&idx_u)?, log_prob_u.detach().unsqueeze(1)?], 1)?;
        let mix = match self.cfg.discriminator_gp > 0.0 {
            true => Some(uniform_column(&mut self.run.rng, b, &self.run.device)?),
            false => None,
        };
        let (d_value, pi_value, weight_mean) = match self.fused.is_some() {
            true => self.fused_updates(&x_n, &x_u, mix.as_ref(), &obs_u, &act_u)?,
            false => self.candle_updates(&x_n, &x_u, mix.as_ref(), &log_prob_u)?,
        };
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        Ok(vec![
            ("discriminator_loss", d_value),
            ("policy_loss", pi_value),
            ("weight_mean", weight_mean),
        ])
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        self.run.checkpoint(&[("discriminator", &self.disc_opt), ("policy", &self.policy_opt)])
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        self.run.single_policy_artifact(&self.policy)
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
    }
}

/// FLOPs of one step (discriminator penalty on): log π on the D^U and D^N batches (two
/// forwards), the discriminator (input `s, a, log π`) trained on 2B rows with its penalty on B
/// interpolated rows, and the policy trained on B.
pub fn step_flops(shape: &super::flops::StepShape) -> u64 {
    use super::flops::{forward_flops, penalty_flops, train_flops};
    let (b, policy, disc) = (shape.batch, shape.policy(), shape.critic(1));
    2 * forward_flops(&policy, b)
        + train_flops(&disc, 2 * b)
        + penalty_flops(&disc, b)
        + train_flops(&policy, b)
}

/// Its share of a run's memory: the discriminator (input `s, a, log π`) and the policy, with
/// the candle graphs of a step on 2B rows and the penalty's second backward pass on B.
pub fn memory(shape: &super::memory::MemoryShape) -> super::memory::Footprint {
    use super::memory::{
        autograd_floats, Footprint, Network, AUTOGRAD_FLOATS, F32, PENALTY_FLOATS,
    };
    let (b, policy, disc) = (shape.batch(), Network::policy(shape), shape.critic(1));
    let step = autograd_floats(&policy.dims, 2 * b, AUTOGRAD_FLOATS)
        + autograd_floats(&disc.dims, 2 * b, AUTOGRAD_FLOATS)
        + autograd_floats(&disc.dims, b, PENALTY_FLOATS);
    Footprint { networks: vec![disc, policy], step: F32 * step, data: 0 }
}
