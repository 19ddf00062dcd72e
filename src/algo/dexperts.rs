//! DExperts (paper Appendix C.4). Discrete actions: π^U and π^N are behaviour-cloned on D^U and
//! D^N (Eq. 42, 43) and combined at decoding time, `π = π^U − α π^N` (Eq. 44, see
//! [`super::policy::Decoder::Dexperts`]). Continuous actions: one policy trained with
//! `−E_U[log π] + α E_N[log π]` (Eq. 45).

use super::bc::bc_loss;
use super::hyperparams::{AlgorithmConfig, DexpertsConfig};
use super::optim::Adam;
use super::policy::{Decoder, PolicyArtifact, PolicyNet};
use super::run::RunData;
use super::{Progress, ResolvedConfig, TrainError, Trainer, TrainingData};
use crate::data::ActionSpace;

/// Eq. 45: `−E_{D^U}[log π] + α E_{D^N}[log π]`.
pub fn contrastive_bc_loss(
    log_prob_u: &candle_core::Tensor,
    log_prob_n: &candle_core::Tensor,
    alpha: f64,
) -> candle_core::Result<candle_core::Tensor> {
    log_prob_u.mean_all()?.neg()? + (log_prob_n.mean_all()? * alpha)?
}

pub struct DexpertsTrainer {
    run: RunData,
    cfg: DexpertsConfig,
    /// π^U (discrete) or the single Eq. 45 policy (continuous).
    policy: PolicyNet,
    policy_opt: Adam,
    /// π^N, discrete actions only.
    expert_n: Option<(PolicyNet, Adam)>,
}

impl DexpertsTrainer {
    pub fn new(
        config: &ResolvedConfig,
        data: &TrainingData,
    ) -> Result<DexpertsTrainer, TrainError> {
        let AlgorithmConfig::Dexperts(cfg) = &config.specific else {
            return Err(TrainError::Other("not a DExperts config".into()));
        };
        let mut run = RunData::new(config, data)?;
        let lr = config.common.lr_actor;
        let policy = run.new_policy("policy")?;
        let expert_n = match run.space {
            ActionSpace::Discrete { .. } => {
                let net = run.new_policy("policy_n")?;
                let opt = Adam::new(net.mlp().named_vars(), lr)?;
                Some((net, opt))
            }
            ActionSpace::Continuous { .. } => None,
        };
        Ok(DexpertsTrainer {
            policy_opt: Adam::new(policy.mlp().named_vars(), lr)?,
            cfg: cfg.clone(),
            run,
            policy,
            expert_n,
        })
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<DexpertsTrainer, TrainError> {
        let mut t = DexpertsTrainer::new(config, data)?;
        let restored = t.run.restore(bytes)?;
        restored.restore("policy", &mut t.policy_opt)?;
        if let Some((_, opt)) = &mut t.expert_n {
            restored.restore("policy_n", opt)?;
        }
        Ok(t)
    }
}

impl Trainer for DexpertsTrainer {
    fn progress(&self) -> Progress {
        Progress { step: self.run.step, total: self.run.total(), phase: "policy" }
    }

    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.run.ensure_running()?;
        let idx_u = self.run.sample_u()?;
        let idx_n = self.run.sample_n()?;
        let (u, n) = (&self.run.u, self.run.non_preferred());
        let (obs_u, act_u) = (u.obs.index_select(&idx_u, 0)?, u.actions.select(&idx_u)?);
        let (obs_n, act_n) = (n.obs.index_select(&idx_n, 0)?, n.actions.select(&idx_n)?);
        let mut metrics = Vec::new();
        match &mut self.expert_n {
            Some((expert_n, opt_n)) => {
                // Eq. 42 and 43: two behaviour-cloned experts.
                let loss_u = bc_loss(&self.policy, &obs_u, &act_u)?;
                let loss_n = bc_loss(expert_n, &obs_n, &act_n)?;
                let value_u = self.run.checked(
                    &loss_u,
                    "the pi^U BC loss (Eq. 42)",
                    "Try a lower lr_actor.",
                )?;
                let value_n = self.run.checked(
                    &loss_n,
                    "the pi^N BC loss (Eq. 43)",
                    "Try a lower lr_actor.",
                )?;
                self.policy_opt.minimize(&loss_u)?;
                opt_n.minimize(&loss_n)?;
                metrics.extend([("policy_loss", value_u), ("policy_n_loss", value_n)]);
            }
            None => {
                let loss = contrastive_bc_loss(
                    &self.policy.log_prob(&obs_u, &act_u)?,
                    &self.policy.log_prob(&obs_n, &act_n)?,
                    self.cfg.alpha,
                )?;
                let value = self.run.checked(
                    &loss,
                    "the DExperts loss (Eq. 45)",
                    "Its α term rewards making D^N actions unlikely without bound: try a smaller alpha.",
                )?;
                self.policy_opt.minimize(&loss)?;
                metrics.push(("policy_loss", value));
            }
        }
        self.run.step += 1;
        Ok(if record { metrics } else { Vec::new() })
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        let mut optimizers = vec![("policy", &self.policy_opt)];
        if let Some((_, opt)) = &self.expert_n {
            optimizers.push(("policy_n", opt));
        }
        self.run.checkpoint(&optimizers)
    }

    fn alpha_hat(&self) -> Option<f64> {
        None
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        match &self.expert_n {
            Some((expert_n, _)) => PolicyArtifact::new(
                self.run.policy_spec(Decoder::Dexperts { alpha: self.cfg.alpha }),
                &[&self.policy, expert_n],
            ),
            None => PolicyArtifact::new(self.run.policy_spec(Decoder::Single), &[&self.policy]),
        }
    }
}
