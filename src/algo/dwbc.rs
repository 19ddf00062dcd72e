//! DWBC adapted to non-preferred data (paper Appendix C.2): a discriminator `d(s, a, log π)`
//! trained by negative-unlabeled learning (Eq. 38), and behaviour cloning on D^U weighted by
//! `1 − d(s, a)` (Eq. 39). Discriminator and policy are trained together, one step each per
//! iteration, as in DWBC.

use candle_core::Tensor;

use super::columns::uniform_column;
use super::hyperparams::{AlgorithmConfig, DwbcConfig};
use super::losses::{
    interpolate, neg_log_one_minus_sigmoid, neg_log_sigmoid, unit_gradient_penalty, weighted_nll,
};
use super::mlp::Mlp;
use super::optim::Adam;
use super::policy::{Decoder, PolicyArtifact, PolicyNet};
use super::run::RunData;
use super::{Progress, ResolvedConfig, TrainError, Trainer, TrainingData};

/// `d` is kept in [0.1, 0.9] (its logit in ±ln 9): Eq. 38's third term, `−η E_N[−log(1 − d)]`,
/// is unbounded below otherwise (together with the first it is linear in the logit).
const LOGIT_CLIP: f64 = 2.197_224_577_336_219_6; // ln 9

/// Eq. 38: `η E_N[−log d] + E_U[−log(1 − d)] − η E_N[−log(1 − d)]` on clipped logits.
pub fn negative_unlabeled_loss(
    logits_n: &Tensor,
    logits_u: &Tensor,
    eta: f64,
) -> candle_core::Result<Tensor> {
    let (x_n, x_u) =
        (logits_n.clamp(-LOGIT_CLIP, LOGIT_CLIP)?, logits_u.clamp(-LOGIT_CLIP, LOGIT_CLIP)?);
    let negatives = (neg_log_sigmoid(&x_n)?.mean_all()? * eta)?;
    let unlabeled = neg_log_one_minus_sigmoid(&x_u)?.mean_all()?;
    let correction = (neg_log_one_minus_sigmoid(&x_n)?.mean_all()? * eta)?;
    (negatives + unlabeled)? - correction
}

/// Eq. 39's weights `1 − d(s, a)`, detached.
pub fn preference_weights(logits_u: &Tensor) -> candle_core::Result<Tensor> {
    let d = candle_nn::ops::sigmoid(&logits_u.clamp(-LOGIT_CLIP, LOGIT_CLIP)?)?;
    Ok(d.affine(-1.0, 1.0)?.detach())
}

pub struct DwbcTrainer {
    run: RunData,
    cfg: DwbcConfig,
    disc: Mlp,
    disc_opt: Adam,
    policy: PolicyNet,
    policy_opt: Adam,
}

impl DwbcTrainer {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<DwbcTrainer, TrainError> {
        let AlgorithmConfig::Dwbc(cfg) = &config.specific else {
            return Err(TrainError::Other("not a DWBC config".into()));
        };
        let mut run = RunData::new(config, data)?;
        let disc = run.new_critic("discriminator", run.state_action_dim() + 1)?;
        let policy = run.new_policy("policy")?;
        Ok(DwbcTrainer {
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
        let log_prob_u =
            self.policy.log_prob(&u.obs.index_select(&idx_u, 0)?, &u.actions.select(&idx_u)?)?;
        let log_prob_n =
            self.policy.log_prob(&n.obs.index_select(&idx_n, 0)?, &n.actions.select(&idx_n)?)?;
        // d(s, a, log π): the policy's log-likelihood is an input, not a path for gradients.
        let x_n = Tensor::cat(&[n.state_action(&idx_n)?, log_prob_n.detach().unsqueeze(1)?], 1)?;
        let x_u = Tensor::cat(&[u.state_action(&idx_u)?, log_prob_u.detach().unsqueeze(1)?], 1)?;
        let logits = self.disc.forward(&Tensor::cat(&[&x_n, &x_u], 0)?)?.squeeze(1)?;
        let (c_n, c_u) = (logits.narrow(0, 0, b)?, logits.narrow(0, b, b)?);
        let mut loss_d = negative_unlabeled_loss(&c_n, &c_u, self.cfg.eta)?;
        if self.cfg.discriminator_gp > 0.0 {
            let mix = uniform_column(&mut self.run.rng, b, &self.run.device)?;
            let penalty = unit_gradient_penalty(&self.disc, &interpolate(&x_n, &x_u, &mix)?)?;
            loss_d = (loss_d + (penalty * self.cfg.discriminator_gp)?)?;
        }
        let weights = preference_weights(&c_u)?;
        let loss_pi = weighted_nll(&log_prob_u, &weights)?;
        let d_value = self.run.checked(
            &loss_d,
            "the DWBC discriminator loss (Eq. 38)",
            "Try a lower lr_discriminator.",
        )?;
        let pi_value =
            self.run.checked(&loss_pi, "the DWBC policy loss (Eq. 39)", "Try a lower lr_actor.")?;
        self.disc_opt.minimize(&loss_d)?;
        self.policy_opt.minimize(&loss_pi)?;
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        Ok(vec![
            ("discriminator_loss", d_value),
            ("policy_loss", pi_value),
            ("weight_mean", super::losses::scalar(&weights.mean_all()?)?),
        ])
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        self.run.checkpoint(&[("discriminator", &self.disc_opt), ("policy", &self.policy_opt)])
    }

    fn alpha_hat(&self) -> Option<f64> {
        None
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        PolicyArtifact::new(self.run.policy_spec(Decoder::Single), &[&self.policy])
    }
}
