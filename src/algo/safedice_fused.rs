//! SafeDICE's two hot loops (the discriminator step of Eq. 9 with its gradient penalty, and the
//! ν step of Eq. 36 with the policy step of Eq. 37) on the fused CPU engine
//! ([`super::fused_mlp`]): the same losses as the candle path in `safedice.rs`, with
//! hand-derived gradients (checked against candle autograd in the tests below) and every buffer
//! reused between steps. The networks stay candle [`Mlp`]s (checkpoints, export and the
//! optimiser are unchanged): each step copies their parameters in and hands gradients back.

use candle_core::Result;

use super::fused_mlp::{FusedMlp, Workspace};
use super::mlp::Mlp;
use super::policy::{LOG_STD_MAX, LOG_STD_MIN, MEAN_CLIP};

/// `log(1 + eˣ)` without overflow.
pub fn softplus(x: f32) -> f32 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `u·a + (1 − u)·b` row by row (`u` one value per row).
pub fn interpolate_rows(dst: &mut [f32], a: &[f32], b: &[f32], u: &[f32], dim: usize) {
    let rows = dst.chunks_exact_mut(dim).zip(a.chunks_exact(dim)).zip(b.chunks_exact(dim));
    for (((out, x), y), &t) in rows.zip(u) {
        for ((o, &xv), &yv) in out.iter_mut().zip(x).zip(y) {
            *o = t * xv + (1.0 - t) * yv;
        }
    }
}

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

/// Tanh-Gaussian `log π(a|s)` (see `policy::tanh_gaussian_log_prob`) from the raw head
/// `[mean | log_std]`, and its gradient with respect to the raw head (zero outside the clips).
pub fn tanh_gaussian_log_prob(
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

/// `log softmax(logits)[a]` and its gradient with respect to the logits.
pub fn categorical_log_prob(logits: &[f32], a: usize, grad: &mut [f32]) -> f32 {
    let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let lse = max + logits.iter().map(|&l| (l - max).exp()).sum::<f32>().ln();
    for (g, &l) in grad.iter_mut().zip(logits) {
        *g = -(l - lse).exp();
    }
    grad[a] += 1.0;
    logits[a] - lse
}

/// One discriminator step's inputs: `B` rows of D^N and of D^U (`cat(s, a)`), and the penalty's
/// interpolation draws (None without a penalty).
pub struct DiscBatch<'a> {
    pub x_n: &'a [f32],
    pub x_u: &'a [f32],
    /// `(u1, u2, perm)`: points `u1·x_N + (1−u1)·x_U` and `u2·x_U[perm] + (1−u2)·x_U`.
    pub penalty: Option<(&'a [f32], &'a [f32], &'a [u32])>,
    /// λ of the penalty.
    pub penalty_coef: f32,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct DiscOutcome {
    /// Classification loss + λ · penalty.
    pub loss: f32,
    pub classification: f32,
    /// The penalty before λ.
    pub penalty: f32,
    pub prob_n: f32,
    pub prob_u: f32,
}

/// One main-loop iteration's inputs (host rows gathered by the trainer).
pub struct MainBatch<'a> {
    pub s: &'a [f32],
    pub s_next: &'a [f32],
    pub s0: &'a [f32],
    pub reward: &'a [f32],
    /// γ' per row (γ, or 0 on masked terminal rows).
    pub discount: &'a [f32],
    pub gamma: f32,
    /// ν's zero-centred penalty: interpolation weights (`B`, shared by the two point sets
    /// `u·s0 + (1−u)·s` and `u·s' + (1−u)·s`) and λ; None without a penalty.
    pub penalty: Option<(&'a [f32], f32)>,
    /// Policy observations (`B × obs_dim`) and actions.
    pub policy_obs: &'a [f32],
    pub actions: HostActions<'a>,
    /// Rows with an action (all but absorbing-state rows); None when all have one.
    pub has_action: Option<&'a [bool]>,
}

#[derive(Clone, Debug, Default)]
pub struct MainOutcome {
    /// Eq. 36 + λ · penalty.
    pub nu_loss: f32,
    /// The penalty before λ.
    pub nu_penalty: f32,
    pub policy_loss: f32,
    pub nu_initial_mean: f32,
}

/// Fused copies of the three networks with their buffers, gradients and per-batch scratch.
pub struct FusedSafedice {
    disc: FusedMlp,
    nu: FusedMlp,
    policy: FusedMlp,
    ws_disc: Workspace,
    ws_nu: Workspace,
    ws_policy: Workspace,
    pub disc_grads: Vec<f32>,
    pub nu_grads: Vec<f32>,
    pub policy_grads: Vec<f32>,
    /// `A` of the last main step and the policy weights `w̃ / mean(w̃)` (length B).
    pub advantages: Vec<f32>,
    pub weights: Vec<f32>,
    head_grad: Vec<f32>,
}

impl FusedSafedice {
    /// Buffers for batch size `batch`; one compute thread (one per training job: see
    /// bench/README.md).
    pub fn new(disc: &Mlp, nu: &Mlp, policy: &Mlp, batch: usize) -> Result<Self> {
        let (disc, nu, policy) = (disc.to_fused()?, nu.to_fused()?, policy.to_fused()?);
        Ok(Self {
            ws_disc: Workspace::new(disc.shape(), 4 * batch, 1),
            ws_nu: Workspace::new(nu.shape(), 5 * batch, 1),
            ws_policy: Workspace::new(policy.shape(), batch, 1),
            disc_grads: vec![0.0; disc.num_params()],
            nu_grads: vec![0.0; nu.num_params()],
            policy_grads: vec![0.0; policy.num_params()],
            advantages: vec![0.0; batch],
            weights: vec![0.0; batch],
            head_grad: vec![0.0; policy.shape().output()],
            disc,
            nu,
            policy,
        })
    }

    /// Eq. 9's loss `mean softplus(−c_N) + mean softplus(c_U)` plus `λ mean((‖∇ₓc(x̂)‖ − 1)²)`,
    /// its gradient into `disc_grads` (parameters copied from `net` first).
    pub fn disc_grads(&mut self, net: &Mlp, batch: &DiscBatch) -> Result<DiscOutcome> {
        net.copy_into_fused(&mut self.disc)?;
        let d = self.disc.shape().input();
        let b = batch.x_n.len() / d;
        let input = self.ws_disc.input_mut();
        input[..b * d].copy_from_slice(batch.x_n);
        input[b * d..2 * b * d].copy_from_slice(batch.x_u);
        let penalty_rows = match batch.penalty {
            Some((u1, u2, perm)) => {
                let (loss_rows, points) = input.split_at_mut(2 * b * d);
                let (x_n, x_u) = loss_rows.split_at(b * d);
                interpolate_rows(&mut points[..b * d], x_n, x_u, u1, d);
                for (r, &p) in perm.iter().enumerate() {
                    let p = p as usize;
                    let (t, out) = (u2[r], &mut points[(b + r) * d..(b + r + 1) * d]);
                    let (shuffled, own) = (&x_u[p * d..(p + 1) * d], &x_u[r * d..(r + 1) * d]);
                    for ((o, &x), &y) in out.iter_mut().zip(shuffled).zip(own) {
                        *o = t * x + (1.0 - t) * y;
                    }
                }
                2 * b
            }
            None => 0,
        };
        let mut outcome = DiscOutcome::default();
        let lambda = batch.penalty_coef;
        self.disc_grads.fill(0.0);
        let penalty = self.disc.train_pass(
            &mut self.ws_disc,
            2 * b,
            penalty_rows,
            &mut self.disc_grads,
            |out, dout| {
                let inv_b = 1.0 / b as f32;
                for i in 0..b {
                    let (c_n, c_u) = (out[i], out[b + i]);
                    outcome.classification += (softplus(-c_n) + softplus(c_u)) * inv_b;
                    outcome.prob_n += sigmoid(c_n) * inv_b;
                    outcome.prob_u += sigmoid(c_u) * inv_b;
                    dout[i] = -sigmoid(-c_n) * inv_b;
                    dout[b + i] = sigmoid(c_u) * inv_b;
                }
            },
            |g, dp| {
                let inv_rows = 1.0 / penalty_rows as f32;
                let mut total = 0.0;
                for (gr, dr) in g.chunks_exact(d).zip(dp.chunks_exact_mut(d)) {
                    // 1e-12 keeps the norm's derivative finite (as losses::unit_gradient_penalty).
                    let norm = (gr.iter().map(|v| v * v).sum::<f32>() + 1e-12).sqrt();
                    total += (norm - 1.0) * (norm - 1.0);
                    let k = lambda * inv_rows * 2.0 * (norm - 1.0) / norm;
                    for (o, &gv) in dr.iter_mut().zip(gr) {
                        *o = k * gv;
                    }
                }
                total * inv_rows
            },
        );
        outcome.penalty = penalty;
        outcome.loss = outcome.classification + lambda * penalty;
        Ok(outcome)
    }

    /// Eq. 36 (+ ν's zero-centred penalty) into `nu_grads` and Eq. 37 into `policy_grads`, with
    /// the pre-update ν; `advantages` and `weights` hold the batch's A and policy weights after.
    pub fn main_grads(&mut self, nu: &Mlp, policy: &Mlp, batch: &MainBatch) -> Result<MainOutcome> {
        nu.copy_into_fused(&mut self.nu)?;
        policy.copy_into_fused(&mut self.policy)?;
        let d = self.nu.shape().input();
        let b = batch.reward.len();
        let input = self.ws_nu.input_mut();
        input[..b * d].copy_from_slice(batch.s);
        input[b * d..2 * b * d].copy_from_slice(batch.s_next);
        input[2 * b * d..3 * b * d].copy_from_slice(batch.s0);
        let (penalty_rows, lambda) = match batch.penalty {
            Some((u, lambda)) => {
                let points = &mut input[3 * b * d..5 * b * d];
                let (first, second) = points.split_at_mut(b * d);
                interpolate_rows(first, batch.s0, batch.s, u, d);
                interpolate_rows(second, batch.s_next, batch.s, u, d);
                (2 * b, lambda)
            }
            None => (0, 0.0),
        };
        let mut outcome = MainOutcome::default();
        let (adv, weights) = (&mut self.advantages, &mut self.weights);
        let gamma = batch.gamma;
        self.nu_grads.fill(0.0);
        let penalty = self.nu.train_pass(
            &mut self.ws_nu,
            3 * b,
            penalty_rows,
            &mut self.nu_grads,
            |out, dout| {
                // A = r + γ' ν(s') − ν(s); d/dA of log-mean-exp(A) is softmax(A).
                for i in 0..b {
                    adv[i] = batch.reward[i] + batch.discount[i] * out[b + i] - out[i];
                }
                let max = adv.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let mut sum = 0.0;
                for (w, &a) in weights.iter_mut().zip(adv.iter()) {
                    *w = (a - max).exp();
                    sum += *w;
                }
                weights.iter_mut().for_each(|w| *w /= sum);
                outcome.nu_initial_mean = out[2 * b..3 * b].iter().sum::<f32>() / b as f32;
                outcome.nu_loss =
                    max + sum.ln() - (b as f32).ln() + (1.0 - gamma) * outcome.nu_initial_mean;
                for i in 0..b {
                    dout[i] = -weights[i];
                    dout[b + i] = batch.discount[i] * weights[i];
                }
                dout[2 * b..3 * b].fill((1.0 - gamma) / b as f32);
            },
            |g, dp| {
                let inv_rows = 1.0 / penalty_rows as f32;
                let mut total = 0.0;
                for (o, &gv) in dp.iter_mut().zip(g) {
                    total += gv * gv;
                    *o = 2.0 * lambda * inv_rows * gv;
                }
                total * inv_rows
            },
        );
        outcome.nu_penalty = penalty;
        outcome.nu_loss += lambda * penalty;

        // Eq. 37's weights w̃/mean(w̃) = B·softmax(A), masked and renormalised where rows
        // carry no action (as losses::self_normalized_weights and safedice.rs).
        weights.iter_mut().for_each(|w| *w *= b as f32);
        if let Some(has_action) = batch.has_action {
            for (w, &keep) in weights.iter_mut().zip(has_action) {
                if !keep {
                    *w = 0.0;
                }
            }
            let mean = weights.iter().sum::<f32>() / b as f32;
            weights.iter_mut().for_each(|w| *w /= mean + 1e-12);
        }
        let weights = &self.weights;
        let head_grad = &mut self.head_grad;
        let k = head_grad.len();
        let mut policy_loss = 0.0;
        self.ws_policy.input_mut()[..batch.policy_obs.len()].copy_from_slice(batch.policy_obs);
        self.policy_grads.fill(0.0);
        self.policy.train_pass(
            &mut self.ws_policy,
            b,
            0,
            &mut self.policy_grads,
            |out, dout| {
                // −mean(w · log π): d/d head = −w/B · d log π / d head.
                for (i, (o, dg)) in out.chunks_exact(k).zip(dout.chunks_exact_mut(k)).enumerate() {
                    let logp = match &batch.actions {
                        HostActions::Continuous { pretanh, log_jacobian } => {
                            let a = &pretanh[i * k / 2..(i + 1) * k / 2];
                            tanh_gaussian_log_prob(o, a, log_jacobian[i], head_grad)
                        }
                        HostActions::Discrete { index } => {
                            categorical_log_prob(o, index[i] as usize, head_grad)
                        }
                    };
                    let scale = weights[i] / b as f32;
                    policy_loss -= scale * logp;
                    for (x, &h) in dg.iter_mut().zip(head_grad.iter()) {
                        *x = -scale * h;
                    }
                }
            },
            |_, _| 0.0,
        );
        outcome.policy_loss = policy_loss;
        Ok(outcome)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::backprop::GradStore;
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    use super::*;
    use crate::algo::columns::ActionColumn;
    use crate::algo::losses::{
        interpolate, self_normalized_weights, unit_gradient_penalty, zero_gradient_penalty,
    };
    use crate::algo::policy::PolicyNet;
    use crate::algo::safedice::{discriminator_loss, nu_loss, policy_loss};
    use crate::data::ActionSpace;

    const B: usize = 16;

    fn normals(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.sample::<f32, _>(StandardNormal)).collect()
    }

    fn uniforms(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.random::<f32>()).collect()
    }

    fn tensor(values: &[f32], rows: usize) -> Tensor {
        Tensor::from_slice(values, (rows, values.len() / rows), &Device::Cpu).unwrap()
    }

    /// Fused gradients against candle autograd, parameter by parameter, to 1e-5 of the largest.
    fn assert_grads_match(what: &str, net: &Mlp, fused: &[f32], store: &GradStore) {
        let ours = net.grads_from_fused(fused).unwrap();
        for ((name, var), g) in net.named_vars().iter().zip(ours) {
            let ours = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let theirs = store.get(var.as_tensor()).expect("autograd gradient");
            let theirs = theirs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let scale = theirs.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
            for (i, (a, b)) in ours.iter().zip(&theirs).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-5 * scale,
                    "{what} {name}[{i}]: fused {a}, autograd {b}"
                );
            }
        }
    }

    fn assert_close(what: &str, a: f32, b: f32) {
        assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{what}: fused {a}, candle {b}");
    }

    #[test]
    fn discriminator_step_matches_candle_autograd() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let d = 7;
        let disc =
            Mlp::new("discriminator", &[d, 12, 10, 1], false, &Device::Cpu, &mut rng).unwrap();
        let nu = Mlp::new("nu", &[5, 12, 10, 1], false, &Device::Cpu, &mut rng).unwrap();
        let policy = Mlp::new("policy", &[5, 12, 10, 6], true, &Device::Cpu, &mut rng).unwrap();
        let (x_n, x_u) = (normals(&mut rng, B * d), normals(&mut rng, B * d));
        let (u1, u2) = (uniforms(&mut rng, B), uniforms(&mut rng, B));
        let mut perm: Vec<u32> = (0..B as u32).collect();
        perm.reverse();
        let lambda = 10.0;
        let mut fused = FusedSafedice::new(&disc, &nu, &policy, B).unwrap();
        let out = fused
            .disc_grads(
                &disc,
                &DiscBatch {
                    x_n: &x_n,
                    x_u: &x_u,
                    penalty: Some((&u1, &u2, &perm)),
                    penalty_coef: lambda,
                },
            )
            .unwrap();

        let (tn, tu) = (tensor(&x_n, B), tensor(&x_u, B));
        let logits =
            disc.forward(&Tensor::cat(&[&tn, &tu], 0).unwrap()).unwrap().squeeze(1).unwrap();
        let classification =
            discriminator_loss(&logits.narrow(0, 0, B).unwrap(), &logits.narrow(0, B, B).unwrap())
                .unwrap();
        let idx = Tensor::from_slice(&perm, B, &Device::Cpu).unwrap();
        let shuffled = tu.index_select(&idx, 0).unwrap();
        let points = Tensor::cat(
            &[
                interpolate(&tn, &tu, &tensor(&u1, B)).unwrap(),
                interpolate(&shuffled, &tu, &tensor(&u2, B)).unwrap(),
            ],
            0,
        )
        .unwrap();
        let penalty = unit_gradient_penalty(&disc, &points).unwrap();
        let loss = (&classification + (&penalty * lambda as f64).unwrap()).unwrap();
        let scalar = |t: &Tensor| t.to_scalar::<f32>().unwrap();
        assert_close("classification", out.classification, scalar(&classification));
        assert_close("penalty", out.penalty, scalar(&penalty));
        assert_close("loss", out.loss, scalar(&loss));
        assert_grads_match("discriminator", &disc, &fused.disc_grads, &loss.backward().unwrap());
    }

    fn check_main_step(space: ActionSpace, masked_rows: bool) {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let (obs, gamma, lambda) = (5, 0.99f32, 0.3f32);
        let dev = Device::Cpu;
        let disc = Mlp::new("discriminator", &[9, 12, 10, 1], false, &dev, &mut rng).unwrap();
        let nu = Mlp::new("nu", &[obs, 12, 10, 1], false, &dev, &mut rng).unwrap();
        let policy = PolicyNet::new("policy", obs, &[12, 10], &space, &dev, &mut rng).unwrap();
        let (s, s_next, s0) =
            (normals(&mut rng, B * obs), normals(&mut rng, B * obs), normals(&mut rng, B * obs));
        let reward = normals(&mut rng, B);
        let discount: Vec<f32> = (0..B).map(|i| if i % 5 == 0 { 0.0 } else { gamma }).collect();
        let u = uniforms(&mut rng, B);
        let policy_obs = normals(&mut rng, B * obs);
        let has_action: Vec<bool> = (0..B).map(|i| !masked_rows || i % 4 != 1).collect();
        let (pretanh, log_jacobian) = (normals(&mut rng, B * 3), normals(&mut rng, B));
        let index: Vec<u32> = (0..B as u32).map(|i| i % 4).collect();
        let (actions, column) = match space {
            ActionSpace::Continuous { .. } => (
                HostActions::Continuous { pretanh: &pretanh, log_jacobian: &log_jacobian },
                ActionColumn::Continuous {
                    pretanh: tensor(&pretanh, B),
                    log_jacobian: Tensor::from_slice(&log_jacobian, B, &dev).unwrap(),
                },
            ),
            ActionSpace::Discrete { .. } => (
                HostActions::Discrete { index: &index },
                ActionColumn::Discrete { index: Tensor::from_slice(&index, B, &dev).unwrap() },
            ),
        };
        let mut fused = FusedSafedice::new(&disc, &nu, policy.mlp(), B).unwrap();
        let out = fused
            .main_grads(
                &nu,
                policy.mlp(),
                &MainBatch {
                    s: &s,
                    s_next: &s_next,
                    s0: &s0,
                    reward: &reward,
                    discount: &discount,
                    gamma,
                    penalty: Some((&u, lambda)),
                    policy_obs: &policy_obs,
                    actions,
                    has_action: masked_rows.then_some(&has_action[..]),
                },
            )
            .unwrap();

        // The candle formulation of safedice.rs's main step.
        let (ts, tn, t0) = (tensor(&s, B), tensor(&s_next, B), tensor(&s0, B));
        let values =
            nu.forward(&Tensor::cat(&[&ts, &tn, &t0], 0).unwrap()).unwrap().squeeze(1).unwrap();
        let (v, v_next, v0) = (
            values.narrow(0, 0, B).unwrap(),
            values.narrow(0, B, B).unwrap(),
            values.narrow(0, 2 * B, B).unwrap(),
        );
        let r = Tensor::from_slice(&reward, B, &dev).unwrap();
        let g = Tensor::from_slice(&discount, B, &dev).unwrap();
        let adv = ((r + (g * v_next).unwrap()).unwrap() - v).unwrap();
        let tu = tensor(&u, B);
        let points = Tensor::cat(
            &[interpolate(&t0, &ts, &tu).unwrap(), interpolate(&tn, &ts, &tu).unwrap()],
            0,
        )
        .unwrap();
        let penalty = zero_gradient_penalty(&nu, &points).unwrap();
        let loss_nu = (nu_loss(&adv, &v0, gamma as f64).unwrap()
            + (&penalty * lambda as f64).unwrap())
        .unwrap();
        let mut weights = self_normalized_weights(&adv).unwrap();
        if masked_rows {
            let mask: Vec<f32> = has_action.iter().map(|&k| k as u8 as f32).collect();
            let masked = (weights * Tensor::from_vec(mask, B, &dev).unwrap()).unwrap();
            let mean = masked.mean_all().unwrap();
            weights = masked.broadcast_div(&(mean + 1e-12).unwrap()).unwrap();
        }
        let log_prob = policy.log_prob(&tensor(&policy_obs, B), &column).unwrap();
        let loss_pi = policy_loss(&log_prob, &weights).unwrap();
        let scalar = |t: &Tensor| t.to_scalar::<f32>().unwrap();
        assert_close("nu loss", out.nu_loss, scalar(&loss_nu));
        assert_close("nu penalty", out.nu_penalty, scalar(&penalty));
        assert_close("policy loss", out.policy_loss, scalar(&loss_pi));
        let w = weights.to_vec1::<f32>().unwrap();
        for (a, b) in fused.weights.iter().zip(&w) {
            assert_close("weight", *a, *b);
        }
        let grads = (&loss_nu + &loss_pi).unwrap().backward().unwrap();
        assert_grads_match("nu", &nu, &fused.nu_grads, &grads);
        assert_grads_match("policy", policy.mlp(), &fused.policy_grads, &grads);
    }

    #[test]
    fn main_step_matches_candle_autograd_continuous() {
        let space = ActionSpace::Continuous { dim: 3, low: vec![-1.0; 3], high: vec![1.0; 3] };
        check_main_step(space, false);
    }

    #[test]
    fn main_step_matches_candle_autograd_discrete_with_actionless_rows() {
        check_main_step(ActionSpace::Discrete { n: 4 }, true);
    }

    /// The penalty's weight gradient (double backprop) against central finite differences of
    /// the fused loss itself, in f32 on a small net (hence the 5% tolerance; the 1e-5 check is
    /// the autograd comparison above).
    #[test]
    fn discriminator_penalty_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let (d, dev) = (7, Device::Cpu);
        let disc = Mlp::new("discriminator", &[d, 12, 10, 1], false, &dev, &mut rng).unwrap();
        let nu = Mlp::new("nu", &[5, 12, 10, 1], false, &dev, &mut rng).unwrap();
        let policy = Mlp::new("policy", &[5, 12, 10, 6], true, &dev, &mut rng).unwrap();
        let (x_n, x_u) = (normals(&mut rng, B * d), normals(&mut rng, B * d));
        let (u1, u2) = (uniforms(&mut rng, B), uniforms(&mut rng, B));
        let perm: Vec<u32> = (0..B as u32).map(|i| (i * 5 + 3) % B as u32).collect();
        let batch = DiscBatch {
            x_n: &x_n,
            x_u: &x_u,
            penalty: Some((&u1, &u2, &perm)),
            penalty_coef: 10.0,
        };
        let mut fused = FusedSafedice::new(&disc, &nu, &policy, B).unwrap();
        let loss = |fused: &mut FusedSafedice| fused.disc_grads(&disc, &batch).unwrap().loss;
        let center = loss(&mut fused);
        let analytic = disc.grads_from_fused(&fused.disc_grads).unwrap();
        let h = 2e-3;
        let mut checked = 0;
        // Weights of layers 1, 2 and 3 (biases get no gradient from the penalty; their loss
        // gradient is covered against autograd). The input-gradient jumps where a ReLU mask
        // flips, so a difference that straddles a flip (one-sided slopes disagree) is skipped.
        for ((name, var), grad) in disc.named_vars().iter().zip(&analytic) {
            if !name.ends_with("weight") {
                continue;
            }
            let grad = grad.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let values = var.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let set = |values: &[f32]| {
                let t = Tensor::from_slice(values, var.as_tensor().dims(), &dev).unwrap();
                var.set(&t).unwrap();
            };
            for i in [0usize, 3, 7, 9] {
                let mut moved = values.clone();
                moved[i] = values[i] + h;
                set(&moved);
                let up = loss(&mut fused);
                moved[i] = values[i] - h;
                set(&moved);
                let down = loss(&mut fused);
                set(&values);
                let (right, left) = ((up - center) / h, (center - down) / h);
                if (right - left).abs() > 0.1 * right.abs().max(left.abs()).max(0.1) {
                    continue;
                }
                checked += 1;
                let numeric = (up - down) / (2.0 * h);
                assert!(
                    (numeric - grad[i]).abs() < 5e-2 * grad[i].abs().max(0.1),
                    "{name}[{i}]: {numeric} vs {}",
                    grad[i]
                );
            }
        }
        assert!(checked >= 8, "only {checked} parameters away from a ReLU kink");
    }

    /// The trainer's fused path and its candle autograd path draw the same batches and report
    /// the same losses, step after step, through the discriminator phase, alpha-hat and the main
    /// loop (they drift apart only by float rounding).
    #[test]
    fn trainer_fused_and_candle_paths_agree() {
        use crate::algo::Trainer;
        use crate::bench::speed::{synthetic_trainer, Engine, SpeedConfig};
        for discrete in [None, Some(4)] {
            let cfg = SpeedConfig {
                obs_dim: 5,
                act_dim: 3,
                discrete,
                batch: 16,
                hidden: vec![12, 10],
                iters: 1,
                repeats: 1,
                threads: 1,
                seed: 7,
                engine: Engine::Fused,
            };
            let make = || synthetic_trainer(&cfg, (400, 200), 4, 3).unwrap();
            let (mut fused, mut candle) = (make(), make());
            candle.use_candle_autograd();
            for step in 0..7 {
                let (a, b) = (fused.step(true).unwrap(), candle.step(true).unwrap());
                assert_eq!(a.len(), b.len());
                for ((name, x), (other, y)) in a.iter().zip(&b) {
                    assert_eq!(name, other);
                    let tol = 1e-3 * y.abs().max(1.0);
                    assert!(
                        (x - y).abs() <= tol || (x.is_nan() && y.is_nan()),
                        "step {step} {name}: fused {x}, candle {y}"
                    );
                }
            }
        }
    }
}
