//! DExperts (paper Appendix C.4). Discrete actions: π^U and π^N are behaviour-cloned on D^U and
//! D^N (Eq. 42, 43) and combined at decoding time, `π = π^U − α π^N` (Eq. 44, see
//! [`super::policy::Decoder::Dexperts`]). Continuous actions: one policy trained with
//! `−E_U[log π] + α E_N[log π]` (Eq. 45), or with the D^N term bounded
//! ([`NonPreferredTerm::Kernel`]).

pub mod config;

use candle_core::Tensor;

use config::{DexpertsConfig, NonPreferredTerm};

use super::bc::bc_loss;
use super::columns::ActionColumn;
use super::fused_policy::{
    fused_policy_step, fused_policy_update, host, host_scalar, FusedPolicyStep, LossName,
    OwnedActions,
};
use super::hyperparams::AlgorithmConfig;
use super::optim::Adam;
use super::policy::{gaussian_kernel, Decoder, PolicyArtifact, PolicyNet};
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

/// Eq. 45 with its D^N term bounded: `−E_{D^U}[log π] + α E_{D^N}[k]`, `k` the D^N action's
/// Gaussian kernel under the policy ([`gaussian_kernel`], in (0, 1]). Eq. 45's term rewards
/// making D^N's actions unlikely without limit, and its push on the mean grows with the
/// distance, so the policy leaves D^U's actions too (the degeneration the paper reports for
/// DExperts); the kernel's push fades once a D^N action is a few standard deviations from the
/// policy's mean. The term moves the mean only: the spread is read as a constant there (it
/// stays D^U's to fit), since narrowing it lowers `k` as surely as moving away and would be
/// the cheaper way.
pub fn bounded_contrastive_loss(
    policy: &PolicyNet,
    (obs_u, act_u): (&Tensor, &ActionColumn),
    (obs_n, act_n): (&Tensor, &ActionColumn),
    alpha: f64,
) -> candle_core::Result<Tensor> {
    let ActionColumn::Continuous { pretanh, .. } = act_n else {
        candle_core::bail!("the bounded DExperts term needs continuous actions")
    };
    let (mean, log_std) = policy.gaussian(obs_n)?;
    let kernel = gaussian_kernel(&mean, &log_std.detach(), pretanh)?;
    policy.log_prob(obs_u, act_u)?.mean_all()?.neg()? + (kernel.mean_all()? * alpha)?
}

pub struct DexpertsTrainer {
    run: RunData,
    cfg: DexpertsConfig,
    /// π^U (discrete) or the single Eq. 45 policy (continuous).
    policy: PolicyNet,
    policy_opt: Adam,
    /// π^N, discrete actions only.
    expert_n: Option<(PolicyNet, Adam)>,
    /// The fused CPU engine's policy step, shared by both experts (None on other devices).
    fused: Option<FusedPolicyStep>,
}

const LOSS_U: LossName = ("the pi^U BC loss (Eq. 42)", "Try a lower lr_actor.");
const LOSS_N: LossName = ("the pi^N BC loss (Eq. 43)", "Try a lower lr_actor.");
const LOSS_BOUNDED: LossName =
    ("the DExperts loss with its D^N term bounded", "Try a lower lr_actor.");
const LOSS_CONTRASTIVE: LossName = (
    "the DExperts loss (Eq. 45)",
    "Its α term rewards making D^N actions unlikely without bound: try a smaller alpha, or \
     non_preferred_term: kernel.",
);

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
        // Eq. 45 trains on a D^U batch and a D^N batch together: room for both.
        let mut fused = fused_policy_step(&run, policy.mlp())?;
        if expert_n.is_none() && fused.is_some() {
            fused = Some(FusedPolicyStep::new(policy.mlp(), 2 * run.batch(), &run.threads)?);
        }
        Ok(DexpertsTrainer {
            fused,
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

impl DexpertsTrainer {
    /// Eq. 42 and 43: two behaviour-cloned experts.
    fn two_experts_step(
        &mut self,
        obs_u: &Tensor,
        act_u: &ActionColumn,
        obs_n: &Tensor,
        act_n: &ActionColumn,
    ) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let (expert_n, opt_n) = self.expert_n.as_mut().expect("discrete actions");
        let run = &self.run;
        let (value_u, value_n) = match &mut self.fused {
            Some(fused) => {
                let pi_u = self.policy.mlp();
                let value_u = fused_policy_update(
                    fused,
                    run,
                    pi_u,
                    &mut self.policy_opt,
                    obs_u,
                    act_u,
                    None,
                    LOSS_U,
                )?;
                let pi_n = expert_n.mlp();
                (value_u, fused_policy_update(fused, run, pi_n, opt_n, obs_n, act_n, None, LOSS_N)?)
            }
            None => {
                let loss_u = bc_loss(&self.policy, obs_u, act_u)?;
                let loss_n = bc_loss(expert_n, obs_n, act_n)?;
                let value_u = run.checked(&loss_u, LOSS_U.0, LOSS_U.1)?;
                let value_n = run.checked(&loss_n, LOSS_N.0, LOSS_N.1)?;
                self.policy_opt.minimize(&loss_u)?;
                opt_n.minimize(&loss_n)?;
                (value_u, value_n)
            }
        };
        Ok(vec![("policy_loss", value_u), ("policy_n_loss", value_n)])
    }

    /// Eq. 45 on one policy, its D^N term as written or bounded. On the fused engine it is
    /// one pass over the D^U batch and the D^N batch stacked (2B rows).
    fn contrastive_step(
        &mut self,
        obs_u: &Tensor,
        act_u: &ActionColumn,
        obs_n: &Tensor,
        act_n: &ActionColumn,
    ) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let alpha = self.cfg.alpha;
        let (run, policy, opt) = (&self.run, &self.policy, &mut self.policy_opt);
        let value = match (&mut self.fused, self.cfg.non_preferred_term) {
            (Some(fused), term) => {
                let obs = Tensor::cat(&[obs_u, obs_n], 0)?;
                let actions = ActionColumn::cat(act_u, act_n)?;
                match term {
                    NonPreferredTerm::LogLikelihood => {
                        eq45_fused(fused, run, policy, opt, (&obs, &actions), alpha)?
                    }
                    NonPreferredTerm::Kernel => {
                        let (obs_host, actions) =
                            (host(&obs)?, OwnedActions::from_column(&actions)?);
                        let (mlp, u_rows) = (policy.mlp(), obs_u.dim(0)?);
                        let loss = fused.bounded_contrastive_grads(
                            mlp,
                            &obs_host,
                            &actions.view(),
                            u_rows,
                            alpha as f32,
                        )?;
                        let (name, hint) = LOSS_BOUNDED;
                        let value = run.checked(&host_scalar(loss)?, name, hint)?;
                        opt.step_with_host_grads(&mlp.fused_grad_slices(&fused.grads)?)?;
                        value
                    }
                }
            }
            (None, term) => {
                let (loss, (name, hint)) = match term {
                    NonPreferredTerm::LogLikelihood => (
                        contrastive_bc_loss(
                            &policy.log_prob(obs_u, act_u)?,
                            &policy.log_prob(obs_n, act_n)?,
                            alpha,
                        )?,
                        LOSS_CONTRASTIVE,
                    ),
                    NonPreferredTerm::Kernel => (
                        bounded_contrastive_loss(policy, (obs_u, act_u), (obs_n, act_n), alpha)?,
                        LOSS_BOUNDED,
                    ),
                };
                let value = run.checked(&loss, name, hint)?;
                opt.minimize(&loss)?;
                value
            }
        };
        Ok(vec![("policy_loss", value)])
    }
}

/// Eq. 45 on the fused engine as one weighted NLL over the D^U batch and the D^N batch
/// stacked (2B rows): weights 2 on D^U rows and −2α on D^N rows make `−(1/2B) Σ w log π`
/// equal `−E_U[log π] + α E_N[log π]`.
fn eq45_fused(
    fused: &mut FusedPolicyStep,
    run: &RunData,
    policy: &PolicyNet,
    opt: &mut Adam,
    (obs, actions): (&Tensor, &ActionColumn),
    alpha: f64,
) -> Result<f64, TrainError> {
    let b = obs.dim(0)? / 2;
    let mut w = vec![2.0f32; b];
    w.extend(std::iter::repeat_n(-2.0 * alpha as f32, obs.dim(0)? - b));
    let w = Tensor::from_vec(w, obs.dim(0)?, obs.device())?;
    fused_policy_update(fused, run, policy.mlp(), opt, obs, actions, Some(&w), LOSS_CONTRASTIVE)
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
        let metrics = match self.expert_n.is_some() {
            true => self.two_experts_step(&obs_u, &act_u, &obs_n, &act_n)?,
            false => self.contrastive_step(&obs_u, &act_u, &obs_n, &act_n)?,
        };
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

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        match &self.expert_n {
            Some((expert_n, _)) => PolicyArtifact::new(
                self.run.policy_spec(Decoder::Dexperts { alpha: self.cfg.alpha }),
                &[&self.policy, expert_n],
            ),
            None => self.run.single_policy_artifact(&self.policy),
        }
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
    }
}

/// FLOPs of one step: two experts on B rows each (discrete actions) or one policy on 2B rows
/// (continuous, Eq. 45): the same count.
pub fn step_flops(shape: &super::flops::StepShape) -> u64 {
    super::flops::train_flops(&shape.policy(), 2 * shape.batch)
}

/// Its share of a run's memory: π^U and π^N (discrete actions) or the one policy, and the
/// candle graphs of its step on D^U and D^N.
pub fn memory(shape: &super::memory::MemoryShape) -> super::memory::Footprint {
    use super::memory::{autograd_floats, Footprint, Network, AUTOGRAD_FLOATS, F32};
    let policy = Network::policy(shape);
    let step = F32 * 2 * autograd_floats(&policy.dims, shape.batch(), AUTOGRAD_FLOATS);
    let experts = if shape.discrete_actions() { 2 } else { 1 };
    Footprint { networks: vec![policy; experts], step, data: 0 }
}
