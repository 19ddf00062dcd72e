//! Preference-based policy learning (paper Appendix C.3): a Bradley–Terry reward model trained
//! on pairs where every D^U trajectory is preferred over every D^N trajectory (Eq. 40), then
//! behaviour cloning on D^U weighted by the learned reward (Eq. 41).

pub mod config;

use candle_core::{Device, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use config::{PplConfig, PplWeight};

use super::columns::Columns;
use super::fused_policy::{fused_policy_step, fused_policy_update, FusedPolicyStep, LossName};
use super::hyperparams::AlgorithmConfig;
use super::losses::{softplus, weighted_nll};
use super::mlp::Mlp;
use super::optim::Adam;
use super::policy::{PolicyArtifact, PolicyNet};
use super::run::RunData;
use super::{Progress, ResolvedConfig, TrainError, Trainer, TrainingData};

/// Eq. 40 for a batch of pairs: `−mean log σ(S_i − S_j) = mean softplus(S_j − S_i)`, where
/// `S = Σ_{(s,a) ∈ τ} R(s, a)` of the preferred (i) and non-preferred (j) segments.
pub fn bradley_terry_loss(
    preferred_sums: &Tensor,
    rejected_sums: &Tensor,
) -> candle_core::Result<Tensor> {
    softplus(&(rejected_sums - preferred_sums)?)?.mean_all()
}

/// Random segments of at most `length` steps from random episodes of `columns`: their rows and
/// a `pairs × rows` 0/1 matrix that sums each segment's rewards.
fn sample_segments(
    columns: &Columns,
    pairs: usize,
    length: usize,
    rng: &mut ChaCha8Rng,
    device: &Device,
) -> candle_core::Result<(Tensor, Tensor)> {
    let episodes = columns.episode_ranges();
    let mut rows = Vec::new();
    let mut owner = Vec::new();
    for p in 0..pairs {
        let episode = &episodes[rng.random_range(0..episodes.len())];
        let take = length.min(episode.len());
        let start = episode.start + rng.random_range(0..=episode.len() - take);
        rows.extend((start..start + take).map(|r| r as u32));
        owner.extend(std::iter::repeat_n(p, take));
    }
    let mut sum = vec![0f32; pairs * rows.len()];
    for (col, &p) in owner.iter().enumerate() {
        sum[p * rows.len() + col] = 1.0;
    }
    let n = rows.len();
    Ok((Tensor::from_vec(rows, n, device)?, Tensor::from_vec(sum, (pairs, n), device)?))
}

pub struct PplTrainer {
    run: RunData,
    cfg: PplConfig,
    reward: Mlp,
    reward_opt: Adam,
    policy: PolicyNet,
    policy_opt: Adam,
    /// The fused CPU engine's policy step (None on other devices); the reward model (Eq. 40)
    /// stays on candle autograd.
    fused: Option<FusedPolicyStep>,
}

const POLICY_LOSS: LossName = (
    "the PPL policy loss (Eq. 41)",
    "With ppl_weight \"raw\" negative rewards push log-probabilities down without bound: try \"sigmoid\".",
);

impl PplTrainer {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<PplTrainer, TrainError> {
        let AlgorithmConfig::Ppl(cfg) = &config.specific else {
            return Err(TrainError::Other("not a PPL config".into()));
        };
        let mut run = RunData::new(config, data)?;
        let reward = run.new_critic("reward_model", run.state_action_dim())?;
        let policy = run.new_policy("policy")?;
        Ok(PplTrainer {
            fused: fused_policy_step(&run, policy.mlp())?,
            reward_opt: Adam::new(reward.named_vars(), cfg.lr_reward_model)?,
            policy_opt: Adam::new(policy.mlp().named_vars(), config.common.lr_actor)?,
            cfg: cfg.clone(),
            run,
            reward,
            policy,
        })
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<PplTrainer, TrainError> {
        let mut t = PplTrainer::new(config, data)?;
        let restored = t.run.restore(bytes)?;
        restored.restore("reward_model", &mut t.reward_opt)?;
        restored.restore("policy", &mut t.policy_opt)?;
        Ok(t)
    }

    fn segment_sums(&mut self, preferred: bool) -> Result<Tensor, TrainError> {
        let (pairs, length) = (self.cfg.pairs_per_batch, self.cfg.segment_length);
        let device = self.run.device.clone();
        let columns = if preferred {
            &self.run.u
        } else {
            self.run.n.as_ref().expect("check_data guarantees D^N")
        };
        let (rows, sum) = sample_segments(columns, pairs, length, &mut self.run.rng, &device)?;
        let rewards = self.reward.forward(&columns.state_action(&rows)?)?;
        Ok(sum.matmul(&rewards)?.squeeze(1)?)
    }

    /// Eq. 40, one step.
    fn reward_model_step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let preferred = self.segment_sums(true)?;
        let rejected = self.segment_sums(false)?;
        let loss = bradley_terry_loss(&preferred, &rejected)?;
        let value = self.run.checked(
            &loss,
            "the reward-model loss (Eq. 40)",
            "Try a lower lr_reward_model.",
        )?;
        self.reward_opt.minimize(&loss)?;
        self.run.step += 1;
        Ok(if record { vec![("reward_model_loss", value)] } else { Vec::new() })
    }

    /// Eq. 41, one step.
    fn policy_step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let idx = self.run.sample_u()?;
        let u = &self.run.u;
        let r = self.reward.forward(&u.state_action(&idx)?)?.squeeze(1)?.detach();
        let weights = match self.cfg.ppl_weight {
            PplWeight::Raw => r,
            PplWeight::Sigmoid => candle_nn::ops::sigmoid(&r)?,
        };
        let (obs, actions) = (u.obs.index_select(&idx, 0)?, u.actions.select(&idx)?);
        let value = match &mut self.fused {
            Some(fused) => {
                let (run, policy, opt) = (&self.run, self.policy.mlp(), &mut self.policy_opt);
                let w = Some(&weights);
                fused_policy_update(fused, run, policy, opt, &obs, &actions, w, POLICY_LOSS)?
            }
            None => {
                let loss = weighted_nll(&self.policy.log_prob(&obs, &actions)?, &weights)?;
                let value = self.run.checked(&loss, POLICY_LOSS.0, POLICY_LOSS.1)?;
                self.policy_opt.minimize(&loss)?;
                value
            }
        };
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        Ok(vec![
            ("policy_loss", value),
            ("weight_mean", super::losses::scalar(&weights.mean_all()?)?),
        ])
    }
}

impl Trainer for PplTrainer {
    fn progress(&self) -> Progress {
        let phase = if self.run.step < self.cfg.reward_model_iterations {
            "reward_model"
        } else {
            "policy"
        };
        Progress { step: self.run.step, total: self.run.total(), phase }
    }

    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.run.ensure_running()?;
        if self.run.step < self.cfg.reward_model_iterations {
            self.reward_model_step(record)
        } else {
            self.policy_step(record)
        }
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        self.run.checkpoint(&[("reward_model", &self.reward_opt), ("policy", &self.policy_opt)])
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        self.run.single_policy_artifact(&self.policy)
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
    }
}

/// FLOPs of one policy step (the reward model frozen): the reward model's forward on B rows and
/// the policy trained on B.
pub fn step_flops(shape: &super::flops::StepShape) -> u64 {
    use super::flops::{forward_flops, train_flops};
    forward_flops(&shape.critic(0), shape.batch) + train_flops(&shape.policy(), shape.batch)
}

/// Its share of a run's memory: the reward model and the policy; the larger of its two phases'
/// candle graphs (the reward model on both sides' segments, or the policy step).
pub fn memory(shape: &super::memory::MemoryShape) -> super::memory::Footprint {
    use super::memory::{autograd_floats, Footprint, Network, AUTOGRAD_FLOATS, F32};
    let AlgorithmConfig::Ppl(config) = &shape.config.specific else {
        unreachable!("the registry asks PPL's memory for PPL runs only")
    };
    let (reward, policy) = (shape.critic(0), Network::policy(shape));
    let pairs = config.pairs_per_batch as u64;
    // Each segment is at most as long as the longest episode it is cut from.
    let longest = shape
        .unlabeled
        .longest_episode
        .max(shape.non_preferred.map_or(0, |n| n.longest_episode))
        .max(1);
    let rows = pairs * (config.segment_length as u64).min(longest);
    // Per side: the segment rows through the reward model, and the pairs x rows 0/1 matrix
    // that sums them (with its gradient).
    let reward_phase =
        2 * (autograd_floats(&reward.dims, rows, AUTOGRAD_FLOATS) + 2 * pairs * rows);
    let policy_phase = autograd_floats(&reward.dims, shape.batch(), AUTOGRAD_FLOATS)
        + autograd_floats(&policy.dims, shape.batch(), AUTOGRAD_FLOATS);
    let step = F32 * reward_phase.max(policy_phase);
    Footprint { networks: vec![reward, policy], step, data: 0 }
}
