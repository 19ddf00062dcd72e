//! The policy step every algorithm shares, on the fused CPU engine: the weighted negative
//! log-likelihood `−mean_i(w_i · log π(a_i|s_i))` (losses::weighted_nll; `w = 1` is behaviour
//! cloning, Eq. 42/43) and its gradient with respect to the policy's parameters, by hand as in
//! [`super::safedice::fused`], instead of candle autograd. SafeDICE's policy step (Eq. 37), BC,
//! both DExperts experts, DWBC's policy (Eq. 39) and PPL's (Eq. 41) run through it on a CPU.
//!
//! The network stays a candle [`Mlp`] (checkpoints, export and the optimiser are unchanged):
//! each step copies its parameters in, and [`fused_policy_update`] hands the gradients to
//! [`Adam::step_with_host_grads`]. The trainers draw their minibatches on the candle path as before,
//! so both engines consume the run's random numbers identically.

use candle_core::{Result, Tensor};

use super::columns::ActionColumn;
use super::fused_mlp::{EngineThreads, FusedMlp, TrainingWorkspace};
use super::mlp::Mlp;
use super::optim::Adam;
use super::policy::{LOG_STD_MAX, LOG_STD_MIN, MEAN_CLIP};
use super::run::RunData;
use super::TrainError;

/// Dataset actions of a policy batch, on the host.
pub enum HostActions<'a> {
    /// `pretanh` (`B × dim`) and `log_jacobian` (`B`), as in `columns::ActionColumn`.
    Continuous {
        pretanh: &'a [f32],
        log_jacobian: &'a [f32],
    },
    Discrete {
        index: &'a [u32],
    },
}

/// Host copies of an [`ActionColumn`]'s values (what [`HostActions`] borrows).
pub enum OwnedActions {
    Continuous { pretanh: Vec<f32>, log_jacobian: Vec<f32> },
    Discrete { index: Vec<u32> },
}

impl OwnedActions {
    pub fn from_column(column: &ActionColumn) -> Result<Self> {
        Ok(match column {
            ActionColumn::Continuous { pretanh, log_jacobian } => OwnedActions::Continuous {
                pretanh: host(pretanh)?,
                log_jacobian: host(log_jacobian)?,
            },
            ActionColumn::Discrete { index } => {
                OwnedActions::Discrete { index: index.to_vec1::<u32>()? }
            }
        })
    }

    pub fn view(&self) -> HostActions<'_> {
        match self {
            OwnedActions::Continuous { pretanh, log_jacobian } => {
                HostActions::Continuous { pretanh, log_jacobian }
            }
            OwnedActions::Discrete { index } => HostActions::Discrete { index },
        }
    }
}

/// Tanh-Gaussian `log π(a|s)` (see `policy::tanh_gaussian_log_prob`) from the raw head
/// `[mean | log_std]`, and its gradient with respect to the raw head (zero outside the clips).
fn tanh_gaussian_log_prob_and_grad(
    out: &[f32],
    pretanh: &[f32],
    log_jacobian: f32,
    grad: &mut [f32],
) -> f32 {
    let d = pretanh.len();
    let (mean_clip, ls_min, ls_max) = (MEAN_CLIP as f32, LOG_STD_MIN as f32, LOG_STD_MAX as f32);
    let half_log_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
    let mut logp = -log_jacobian;
    for j in 0..d {
        let (m_raw, s_raw) = (out[j], out[d + j]);
        let mean = m_raw.clamp(-mean_clip, mean_clip);
        let log_std = s_raw.clamp(ls_min, ls_max);
        let inv_std = (-log_std).exp();
        let z = (pretanh[j] - mean) * inv_std;
        logp += -0.5 * z * z - log_std - half_log_2pi;
        grad[j] = if m_raw.abs() <= mean_clip { z * inv_std } else { 0.0 };
        grad[d + j] = if (ls_min..=ls_max).contains(&s_raw) { z * z - 1.0 } else { 0.0 };
    }
    logp
}

/// Categorical `log softmax(logits)[a]` and its gradient with respect to the logits.
fn categorical_log_prob_and_grad(logits: &[f32], a: usize, grad: &mut [f32]) -> f32 {
    let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let lse = max + logits.iter().map(|&l| (l - max).exp()).sum::<f32>().ln();
    for (g, &l) in grad.iter_mut().zip(logits) {
        *g = -(l - lse).exp();
    }
    grad[a] += 1.0;
    logits[a] - lse
}

/// A fused copy of a policy network with its buffers; one serves every policy of the same
/// shape (DExperts' two experts), since each step copies the parameters in.
pub struct FusedPolicyStep {
    net: FusedMlp,
    ws: TrainingWorkspace,
    /// The last step's gradient, flat in [`FusedMlp`] order.
    pub grads: Vec<f32>,
    head_grad: Vec<f32>,
}

impl FusedPolicyStep {
    /// Buffers for batches of up to `batch` rows, steps on the job's `threads`.
    pub fn new(policy: &Mlp, batch: usize, threads: &EngineThreads) -> Result<Self> {
        let net = policy.to_fused()?;
        Ok(Self {
            ws: TrainingWorkspace::new(net.shape(), batch, threads),
            grads: vec![0.0; net.num_params()],
            head_grad: vec![0.0; net.shape().output()],
            net,
        })
    }

    /// `−mean_i(w_i · log π(a_i|s_i))` over the `B` rows of `obs` (`B × obs_dim`), `w = 1`
    /// without weights; its gradient goes to [`Self::grads`] (parameters copied from `policy`
    /// first). d/d head of row i is `−w_i/B · d log π / d head`.
    pub fn weighted_nll_grads(
        &mut self,
        policy: &Mlp,
        obs: &[f32],
        actions: &HostActions,
        weights: Option<&[f32]>,
    ) -> Result<f32> {
        policy.copy_into_fused(&mut self.net)?;
        let b = obs.len() / self.net.shape().input();
        let head_grad = &mut self.head_grad;
        let k = head_grad.len();
        let mut loss = 0.0;
        self.ws.input_mut()[..obs.len()].copy_from_slice(obs);
        self.grads.fill(0.0);
        self.ws.train_pass(
            &self.net,
            (b, 0),
            &mut self.grads,
            |out, dout| {
                for (i, (o, dg)) in out.chunks_exact(k).zip(dout.chunks_exact_mut(k)).enumerate() {
                    let logp = match actions {
                        HostActions::Continuous { pretanh, log_jacobian } => {
                            let a = &pretanh[i * k / 2..(i + 1) * k / 2];
                            tanh_gaussian_log_prob_and_grad(o, a, log_jacobian[i], head_grad)
                        }
                        HostActions::Discrete { index } => {
                            categorical_log_prob_and_grad(o, index[i] as usize, head_grad)
                        }
                    };
                    let scale = weights.map_or(1.0, |w| w[i]) / b as f32;
                    loss -= scale * logp;
                    for (x, &h) in dg.iter_mut().zip(head_grad.iter()) {
                        *x = -scale * h;
                    }
                }
            },
            |_, _| 0.0,
        );
        Ok(loss)
    }
}

/// The fused policy step on a CPU, None elsewhere (the candle path runs there).
pub fn fused_policy_step(run: &RunData, policy: &Mlp) -> Result<Option<FusedPolicyStep>> {
    match run.device {
        candle_core::Device::Cpu => {
            Ok(Some(FusedPolicyStep::new(policy, run.batch(), &run.threads)?))
        }
        _ => Ok(None),
    }
}

/// What a failing policy loss is called in the run's error, and what to try.
pub type LossName = (&'static str, &'static str);

/// One optimiser step of `−mean(w · log π(a|s))` on the fused engine: the batch copied to the
/// host, the loss checked like the candle path's ([`RunData::checked`]), Adam stepped with the
/// fused gradient. Returns the loss.
#[allow(clippy::too_many_arguments)]
pub fn fused_policy_update(
    fused: &mut FusedPolicyStep,
    run: &RunData,
    policy: &Mlp,
    opt: &mut Adam,
    obs: &Tensor,
    actions: &ActionColumn,
    weights: Option<&Tensor>,
    name: LossName,
) -> std::result::Result<f64, TrainError> {
    let obs = host(obs)?;
    let actions = OwnedActions::from_column(actions)?;
    let weights = weights.map(host).transpose()?;
    let loss = fused.weighted_nll_grads(policy, &obs, &actions.view(), weights.as_deref())?;
    let value = run.checked(&host_scalar(loss)?, name.0, name.1)?;
    opt.step_with_host_grads(&policy.fused_grad_slices(&fused.grads)?)?;
    Ok(value)
}

/// A tensor's values on the host, flattened (row-major).
pub fn host(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

/// A host loss as a scalar tensor for `RunData::checked`.
pub fn host_scalar(value: f32) -> Result<Tensor> {
    Tensor::new(value, &candle_core::Device::Cpu)
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    use super::*;
    use crate::algo::losses::weighted_nll;
    use crate::algo::policy::PolicyNet;
    use crate::data::ActionSpace;

    const B: usize = 16;

    fn normals(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.sample::<f32, _>(StandardNormal)).collect()
    }

    /// The fused loss and gradient against candle autograd on `weighted_nll(log_prob)`, with
    /// and without weights, to 1e-5 of the largest gradient.
    fn check(space: ActionSpace) {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (obs_dim, dev) = (5, Device::Cpu);
        let policy = PolicyNet::new("policy", obs_dim, &[12, 10], &space, &dev, &mut rng).unwrap();
        let obs = normals(&mut rng, B * obs_dim);
        let obs_t = Tensor::from_slice(&obs, (B, obs_dim), &dev).unwrap();
        let actions = match &space {
            ActionSpace::Discrete { n } => {
                let index: Vec<u32> = (0..B).map(|_| rng.random_range(0..*n as u32)).collect();
                ActionColumn::Discrete { index: Tensor::from_slice(&index, B, &dev).unwrap() }
            }
            ActionSpace::Continuous { dim, .. } => {
                let pretanh = normals(&mut rng, B * dim);
                let log_jacobian = normals(&mut rng, B);
                ActionColumn::Continuous {
                    pretanh: Tensor::from_slice(&pretanh, (B, *dim), &dev).unwrap(),
                    log_jacobian: Tensor::from_slice(&log_jacobian, B, &dev).unwrap(),
                }
            }
        };
        let host_actions = OwnedActions::from_column(&actions).unwrap();
        let w: Vec<f32> = (0..B).map(|_| rng.random_range(0.0f32..3.0)).collect();
        // One thread, and three shards on two (16 rows do not split evenly in three).
        for (shards, threads) in [(1, 1), (3, 2)] {
            let threads = EngineThreads::new(shards, threads).unwrap();
            let mut fused = FusedPolicyStep::new(policy.mlp(), B, &threads).unwrap();
            check_step(&mut fused, &policy, (&obs, &obs_t), (&actions, &host_actions), &w);
        }
    }

    fn check_step(
        fused: &mut FusedPolicyStep,
        policy: &PolicyNet,
        (obs, obs_t): (&[f32], &Tensor),
        (actions, host_actions): (&ActionColumn, &OwnedActions),
        w: &[f32],
    ) {
        let dev = Device::Cpu;
        for weights in [None, Some(w)] {
            let ours =
                fused.weighted_nll_grads(policy.mlp(), obs, &host_actions.view(), weights).unwrap();
            let ones = vec![1.0f32; B];
            let w_t = Tensor::from_slice(weights.unwrap_or(&ones), B, &dev).unwrap();
            let loss = weighted_nll(&policy.log_prob(obs_t, actions).unwrap(), &w_t).unwrap();
            let theirs = loss.to_scalar::<f32>().unwrap();
            assert!((ours - theirs).abs() <= 1e-5 * theirs.abs().max(1.0), "{ours} vs {theirs}");
            let store = loss.backward().unwrap();
            let grads = policy.mlp().grads_from_fused(&fused.grads).unwrap();
            for ((name, var), g) in policy.mlp().named_vars().iter().zip(grads) {
                let ours = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let theirs = store.get(var.as_tensor()).unwrap();
                let theirs = theirs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let scale = theirs.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
                    assert!((a - b).abs() <= 1e-5 * scale, "{name}[{i}]: fused {a}, candle {b}");
                }
            }
        }
    }

    #[test]
    fn weighted_nll_matches_candle_autograd_continuous() {
        check(ActionSpace::Continuous { dim: 3, low: vec![-1.0; 3], high: vec![1.0; 3] });
    }

    #[test]
    fn weighted_nll_matches_candle_autograd_discrete() {
        check(ActionSpace::Discrete { n: 4 });
    }

    /// Every baseline's trainer on the fused engine against itself on candle autograd, step by
    /// step on the same draws: the recorded losses agree to 1e-3 (relative) over 7 steps, both
    /// action spaces (DExperts trains two experts on discrete actions, Eq. 45 on continuous).
    #[test]
    fn baseline_trainers_agree_on_both_engines() {
        use crate::algo::Algorithm;
        use crate::bench::speed::engines::{assert_engines_agree, tiny};
        use crate::bench::speed::synthetic_baseline;
        for algorithm in [Algorithm::Bc, Algorithm::Dwbc, Algorithm::Ppl, Algorithm::Dexperts] {
            for discrete in [None, Some(4)] {
                let cfg = tiny(algorithm, discrete);
                let make = || synthetic_baseline(&cfg, (400, 200), 8).unwrap();
                assert_engines_agree(&format!("{algorithm} {discrete:?}"), make, 7);
            }
        }
    }
}
