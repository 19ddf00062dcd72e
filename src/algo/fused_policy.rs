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
}

impl FusedPolicyStep {
    /// Buffers for batches of up to `batch` rows, steps on the job's `threads`.
    pub fn new(policy: &Mlp, batch: usize, threads: &EngineThreads) -> Result<Self> {
        let net = policy.to_fused()?;
        Ok(Self {
            ws: TrainingWorkspace::new(net.shape(), batch, threads),
            grads: vec![0.0; net.num_params()],
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
        self.mean_row_loss_grads(policy, obs, |i, b, out, grad| {
            let logp = log_prob_and_grad(out, actions, i, grad);
            let scale = weights.map_or(1.0, |w| w[i]) / b;
            for g in grad.iter_mut() {
                *g *= -scale;
            }
            -(scale * logp)
        })
    }

    /// Eq. 45 with its D^N term bounded, over `obs` = the D^U batch's `u_rows` rows then the
    /// D^N batch's: `mean_U(−log π) + α · mean_N(k)`, where `k` is the D^N action's Gaussian
    /// kernel under the policy ([`gaussian_kernel_and_grad`], in (0, 1]). Both halves have the
    /// same size, so each row's share of the mean over all rows is doubled. Continuous
    /// actions only (discrete DExperts decodes with Eq. 44 instead).
    pub fn bounded_contrastive_grads(
        &mut self,
        policy: &Mlp,
        obs: &[f32],
        actions: &HostActions,
        u_rows: usize,
        alpha: f32,
    ) -> Result<f32> {
        let HostActions::Continuous { pretanh, .. } = actions else {
            candle_core::bail!("the bounded DExperts term needs continuous actions")
        };
        self.mean_row_loss_grads(policy, obs, |i, b, out, grad| {
            let d = out.len() / 2;
            let (value, scale) = match i < u_rows {
                true => (-log_prob_and_grad(out, actions, i, grad), -2.0 / b),
                false => {
                    let a_n = &pretanh[i * d..(i + 1) * d];
                    (alpha * gaussian_kernel_and_grad(out, a_n, grad), 2.0 * alpha / b)
                }
            };
            for g in grad.iter_mut() {
                *g *= scale;
            }
            2.0 * value / b
        })
    }

    /// `Σ_i loss_i / B` over the `B` rows of `obs`, with `row_loss(i, B, head_i, grad)` giving
    /// row i's share of it and writing that share's gradient with respect to the head into
    /// `grad`; the gradient with respect to the parameters goes to [`Self::grads`].
    fn mean_row_loss_grads(
        &mut self,
        policy: &Mlp,
        obs: &[f32],
        row_loss: impl Fn(usize, f32, &[f32], &mut [f32]) -> f32 + Sync,
    ) -> Result<f32> {
        policy.copy_into_fused(&mut self.net)?;
        let b = obs.len() / self.net.shape().input();
        let k = self.net.shape().output();
        let mut loss = 0.0;
        self.ws.input_mut()[..obs.len()].copy_from_slice(obs);
        self.grads.fill(0.0);
        self.ws.train_pass(
            &self.net,
            (b, 0),
            &mut self.grads,
            |out, dout| {
                for (i, (o, dg)) in out.chunks_exact(k).zip(dout.chunks_exact_mut(k)).enumerate() {
                    loss += row_loss(i, b as f32, o, dg);
                }
            },
            |_, _| 0.0,
        );
        Ok(loss)
    }
}

/// `log π(a_i|s_i)` of row i's dataset action from the raw head, its gradient in `grad`.
fn log_prob_and_grad(out: &[f32], actions: &HostActions, i: usize, grad: &mut [f32]) -> f32 {
    match actions {
        HostActions::Continuous { pretanh, log_jacobian } => {
            let d = out.len() / 2;
            tanh_gaussian_log_prob_and_grad(
                out,
                &pretanh[i * d..(i + 1) * d],
                log_jacobian[i],
                grad,
            )
        }
        HostActions::Discrete { index } => {
            categorical_log_prob_and_grad(out, index[i] as usize, grad)
        }
    }
}

/// The pre-tanh Gaussian's kernel at a dataset action, `k = exp(−½ Σ_j z_j²)` with
/// `z = (u − mean) / std` (see `policy::gaussian_kernel`): the action's density relative to the
/// policy's mode, in (0, 1]. Its gradient with respect to the raw head goes to `grad`:
/// `k · z / std` for the mean (zero outside the clip) and none for log_std, which the kernel
/// reads as a constant (see `dexperts::bounded_contrastive_loss`).
fn gaussian_kernel_and_grad(out: &[f32], pretanh: &[f32], grad: &mut [f32]) -> f32 {
    let d = pretanh.len();
    let (mean_clip, ls_min, ls_max) = (MEAN_CLIP as f32, LOG_STD_MIN as f32, LOG_STD_MAX as f32);
    let mut half_sq = 0.0;
    for j in 0..d {
        let (m_raw, s_raw) = (out[j], out[d + j]);
        let inv_std = (-s_raw.clamp(ls_min, ls_max)).exp();
        let z = (pretanh[j] - m_raw.clamp(-mean_clip, mean_clip)) * inv_std;
        half_sq += 0.5 * z * z;
        grad[j] = if m_raw.abs() <= mean_clip { z * inv_std } else { 0.0 };
        grad[d + j] = 0.0;
    }
    let kernel = (-half_sq).exp();
    for g in grad.iter_mut() {
        *g *= kernel;
    }
    kernel
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
            assert_same_step(fused, policy, ours, &loss);
        }
    }

    /// The fused step's loss and gradients against candle autograd's, to 1e-5 of the largest.
    fn assert_same_step(fused: &FusedPolicyStep, policy: &PolicyNet, ours: f32, loss: &Tensor) {
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

    /// DExperts' bounded Eq. 45 (D^U rows then D^N rows) on the fused engine against
    /// `dexperts::bounded_contrastive_loss` on candle autograd, on one thread and on shards.
    #[test]
    fn bounded_contrastive_matches_candle_autograd() {
        use crate::algo::dexperts::bounded_contrastive_loss;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (obs_dim, dim, dev) = (5, 3, Device::Cpu);
        let space = ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] };
        let policy = PolicyNet::new("policy", obs_dim, &[12, 10], &space, &dev, &mut rng).unwrap();
        let obs = normals(&mut rng, B * obs_dim);
        let pretanh = normals(&mut rng, B * dim);
        let log_jacobian = normals(&mut rng, B);
        let half = |v: &[f32], width: usize, part: usize| {
            let rows = &v[part * B / 2 * width..(part + 1) * B / 2 * width];
            let shape: &[usize] = if width == 1 { &[B / 2] } else { &[B / 2, width] };
            Tensor::from_slice(rows, shape, &dev).unwrap()
        };
        let column = |part| ActionColumn::Continuous {
            pretanh: half(&pretanh, dim, part),
            log_jacobian: half(&log_jacobian, 1, part),
        };
        let (u, n) = ((half(&obs, obs_dim, 0), column(0)), (half(&obs, obs_dim, 1), column(1)));
        let actions = HostActions::Continuous { pretanh: &pretanh, log_jacobian: &log_jacobian };
        for (shards, threads) in [(1, 1), (3, 2)] {
            let threads = EngineThreads::new(shards, threads).unwrap();
            let mut fused = FusedPolicyStep::new(policy.mlp(), B, &threads).unwrap();
            let ours =
                fused.bounded_contrastive_grads(policy.mlp(), &obs, &actions, B / 2, 0.7).unwrap();
            let loss = bounded_contrastive_loss(&policy, (&u.0, &u.1), (&n.0, &n.1), 0.7).unwrap();
            assert_same_step(&fused, &policy, ours, &loss);
        }
    }

    /// The kernel is the Gaussian density's ratio to its value at the mean, and its gradient
    /// with respect to the mean matches central finite differences.
    #[test]
    fn gaussian_kernel_is_the_density_ratio_and_its_gradient_matches_differences() {
        let (out, a) = ([0.3f32, -0.2, -0.4, 0.1], [0.9f32, -1.1]);
        let mut grad = [0.0f32; 4];
        let k = gaussian_kernel_and_grad(&out, &a, &mut grad);
        let density = |x: f32, m: f32, log_std: f32| {
            let s = log_std.exp();
            (-0.5 * ((x - m) / s).powi(2)).exp() / s
        };
        let ratio = density(0.9, 0.3, -0.4) / density(0.3, 0.3, -0.4) * density(-1.1, -0.2, 0.1)
            / density(-0.2, -0.2, 0.1);
        assert!((k - ratio).abs() < 1e-6, "{k} vs {ratio}");
        assert_eq!(&grad[2..], &[0.0, 0.0], "log_std is read as a constant");
        for j in 0..2 {
            let (mut up, mut down) = (out, out);
            up[j] += 1e-3;
            down[j] -= 1e-3;
            let mut scratch = [0.0f32; 4];
            let fd = (gaussian_kernel_and_grad(&up, &a, &mut scratch)
                - gaussian_kernel_and_grad(&down, &a, &mut scratch))
                / 2e-3;
            assert!((fd - grad[j]).abs() < 1e-3, "head[{j}]: {} vs {fd}", grad[j]);
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

    /// DExperts with Eq. 45's D^N term as written (the paper's presets; the service preset's
    /// bounded term is in the test above) on both engines.
    #[test]
    fn dexperts_eq45_as_written_agrees_on_both_engines() {
        use crate::algo::Algorithm;
        use crate::bench::speed::engines::{assert_engines_agree, tiny};
        use crate::bench::speed::synthetic_baseline_with;
        let cfg = tiny(Algorithm::Dexperts, None);
        let as_written = serde_json::json!({"non_preferred_term": "log_likelihood"});
        let as_written = as_written.as_object().unwrap();
        let make = || synthetic_baseline_with(&cfg, (400, 200), 8, as_written).unwrap();
        assert_engines_agree("dexperts, Eq. 45 as written", make, 7);
    }
}
