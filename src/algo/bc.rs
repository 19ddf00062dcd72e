//! Behaviour cloning on D^U: the baseline that cannot tell preferred from non-preferred.

use candle_core::Tensor;

use super::columns::ActionColumn;
use super::optim::Adam;
use super::policy::{Decoder, PolicyArtifact, PolicyNet};
use super::run::RunData;
use super::{Progress, ResolvedConfig, TrainError, Trainer, TrainingData};

/// `−E_{D^U}[log π(a|s)]` (Eq. 42 of the DExperts section is the same loss).
pub fn bc_loss(
    policy: &PolicyNet,
    obs: &Tensor,
    actions: &ActionColumn,
) -> candle_core::Result<Tensor> {
    policy.log_prob(obs, actions)?.mean_all()?.neg()
}

pub struct BcTrainer {
    run: RunData,
    policy: PolicyNet,
    opt: Adam,
}

impl BcTrainer {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<BcTrainer, TrainError> {
        let mut run = RunData::new(config, data)?;
        let policy = run.new_policy("policy")?;
        let opt = Adam::new(policy.mlp().named_vars(), config.common.lr_actor)?;
        Ok(BcTrainer { run, policy, opt })
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<BcTrainer, TrainError> {
        let mut t = BcTrainer::new(config, data)?;
        t.run.restore(bytes)?.restore("policy", &mut t.opt)?;
        Ok(t)
    }
}

impl Trainer for BcTrainer {
    fn progress(&self) -> Progress {
        Progress { step: self.run.step, total: self.run.total(), phase: "policy" }
    }

    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.run.ensure_running()?;
        let idx = self.run.sample_u()?;
        let obs = self.run.u.obs.index_select(&idx, 0)?;
        let loss = bc_loss(&self.policy, &obs, &self.run.u.actions.select(&idx)?)?;
        let value = self.run.checked(&loss, "the BC loss", "Try a lower lr_actor.")?;
        self.opt.minimize(&loss)?;
        self.run.step += 1;
        Ok(if record { vec![("policy_loss", value)] } else { Vec::new() })
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        self.run.checkpoint(&[("policy", &self.opt)])
    }

    fn alpha_hat(&self) -> Option<f64> {
        None
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        PolicyArtifact::new(self.run.policy_spec(Decoder::Single), &[&self.policy])
    }
}
