//! Behaviour cloning on D^U: the baseline that cannot tell preferred from non-preferred.

pub mod config;

use candle_core::Tensor;

use super::columns::ActionColumn;
use super::fused_policy::{fused_policy_step, fused_policy_update, FusedPolicyStep, LossName};
use super::optim::Adam;
use super::policy::{PolicyArtifact, PolicyNet};
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

/// What a failing BC loss is called in the run's error, and what to try.
const BC_LOSS: LossName = ("the BC loss", "Try a lower lr_actor.");

pub struct BcTrainer {
    run: RunData,
    policy: PolicyNet,
    opt: Adam,
    /// The fused CPU engine's policy step (None on other devices: candle autograd runs).
    fused: Option<FusedPolicyStep>,
}

impl BcTrainer {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<BcTrainer, TrainError> {
        let mut run = RunData::new(config, data)?;
        let policy = run.new_policy("policy")?;
        let opt = Adam::new(policy.mlp().named_vars(), config.common.lr_actor)?;
        let fused = fused_policy_step(&run, policy.mlp())?;
        Ok(BcTrainer { run, policy, opt, fused })
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
        let actions = self.run.u.actions.select(&idx)?;
        let value = match &mut self.fused {
            Some(fused) => {
                let policy = self.policy.mlp();
                let run = &self.run;
                fused_policy_update(
                    fused,
                    run,
                    policy,
                    &mut self.opt,
                    &obs,
                    &actions,
                    None,
                    BC_LOSS,
                )?
            }
            None => {
                let loss = bc_loss(&self.policy, &obs, &actions)?;
                let value = self.run.checked(&loss, BC_LOSS.0, BC_LOSS.1)?;
                self.opt.minimize(&loss)?;
                value
            }
        };
        self.run.step += 1;
        Ok(if record { vec![("policy_loss", value)] } else { Vec::new() })
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        self.run.checkpoint(&[("policy", &self.opt)])
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        self.run.single_policy_artifact(&self.policy)
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
    }
}

/// FLOPs of one step: the policy trained on B rows.
pub fn step_flops(shape: &super::flops::StepShape) -> u64 {
    super::flops::train_flops(&shape.policy(), shape.batch)
}

/// Its share of a run's memory: the policy and its candle graph over B rows.
pub fn memory(shape: &super::memory::MemoryShape) -> super::memory::Footprint {
    use super::memory::{autograd_floats, Footprint, Network, AUTOGRAD_FLOATS, F32};
    let policy = Network::policy(shape);
    let step = F32 * autograd_floats(&policy.dims, shape.batch(), AUTOGRAD_FLOATS);
    Footprint { networks: vec![policy], step, data: 0 }
}
