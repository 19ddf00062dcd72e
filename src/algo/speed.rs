//! `safedice speed`: the training-speed benchmark of issue 6.
//!
//! Two workloads on synthetic data, each in two engines that compute the same thing:
//! - main loop: one SafeDICE iteration with the discriminator frozen (rewards precomputed):
//!   nu on `cat(s, s', s0)` (Eq. 36: log-mean-exp of `A = r + γν(s') - ν(s)` plus
//!   `(1-γ) mean ν(s0)`), a zero-centred nu gradient penalty on `2B` interpolated states
//!   (`u·s0 + (1-u)·s` and `u·s' + (1-u)·s`), the policy step of Eq. 37 (weights `softmax(A)`,
//!   detached: the self-normalised `exp(A - 1)`), and one Adam step for nu and one for the policy;
//! - discriminator: one step of Eq. 9 on `B` non-preferred and `B` unlabeled pairs plus the
//!   gradient penalty `λ mean((‖∇ₓc(x̂)‖ - 1)²)` on `2B` interpolates, and an Adam step.
//!
//! Engines: `fused` ([`super::fused_mlp`]: hand-derived backward, one GEMM per layer and pass,
//! in-place Adam) and `candle` (plain candle autograd with the input-gradient written as tensor
//! ops, the straightforward implementation; the "before"). The unit tests check that both give
//! the same losses and gradients. `bench/pytorch_reference.py` measures the same workloads in
//! PyTorch; bench/README.md has the commands and numbers.

use std::time::Instant;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use std::sync::Arc;

use super::fused_mlp::{Adam, FusedMlp, MlpShape, Workspace};
use super::safedice::SafediceTrainer;
use super::{resolve_config, Algorithm, Trainer, TrainingData};
use crate::data::{ActionSpace, Actions, Dataset};

pub const GAMMA: f32 = 0.99;
/// Discriminator gradient-penalty coefficient (the `authors-code` preset).
pub const DISC_GP: f32 = 10.0;
/// nu gradient-penalty coefficient (the `authors-code` preset).
pub const NU_GP: f32 = 1e-6;
/// Inside the square root of the penalty's gradient norm, so its derivative stays finite.
const NORM_EPS: f32 = 1e-12;
/// Dataset actions are clipped to `±(1 - ATANH_EPS)` before `atanh`.
const ATANH_EPS: f32 = 1e-6;
const MEAN_CLIP: (f32, f32) = (-7.0, 7.0);
const LOG_STD_CLIP: (f32, f32) = (-5.0, 2.0);
/// Peak FP32 of the 2-core machine (AVX-512 FMA, measured lower bound; candle-notes.md).
pub const PEAK_GFLOPS_2_CORES: f64 = 333.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Engine {
    /// The real `SafediceTrainer` (fused CPU engine) on a synthetic dataset.
    Trainer,
    /// The real `SafediceTrainer` forced onto its candle autograd path (the "before").
    TrainerCandle,
    /// The workloads alone on the fused engine (no trainer bookkeeping).
    Fused,
    /// The workloads alone on plain candle autograd.
    Candle,
}

#[derive(Clone, Debug)]
pub struct SpeedConfig {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `Some(n)`: n discrete actions (one-hot into the discriminator) instead of `act_dim`.
    pub discrete: Option<usize>,
    pub batch: usize,
    pub hidden: Vec<usize>,
    pub iters: usize,
    pub repeats: usize,
    pub threads: usize,
    pub seed: u64,
    pub engine: Engine,
}

impl SpeedConfig {
    fn act_input(&self) -> usize {
        self.discrete.unwrap_or(self.act_dim)
    }

    fn policy_output(&self) -> usize {
        self.discrete.unwrap_or(2 * self.act_dim)
    }

    pub fn nu_shape(&self) -> MlpShape {
        MlpShape::new(self.obs_dim, &self.hidden, 1, false)
    }

    pub fn policy_shape(&self) -> MlpShape {
        MlpShape::new(self.obs_dim, &self.hidden, self.policy_output(), true)
    }

    pub fn disc_shape(&self) -> MlpShape {
        MlpShape::new(self.obs_dim + self.act_input(), &self.hidden, 1, false)
    }
}

// ---------------------------------------------------------------------------------------------
// FLOP counts (matrix products only; element-wise work and Adam are not counted)

fn linear_flops(rows: usize, din: usize, dout: usize) -> u64 {
    2 * (rows * din * dout) as u64
}

/// Forward, weight gradients, and input gradients of every layer but the first.
fn train_flops(shape: &MlpShape, rows: usize) -> u64 {
    let fwd = shape.forward_flops_per_row() * rows as u64;
    let dx: u64 = shape.dims[1..].windows(2).map(|w| linear_flops(rows, w[0], w[1])).sum();
    2 * fwd + dx
}

/// Scalar critic's gradient penalty: forward, input-gradient through the hidden layers, and the
/// backward of that input-gradient (a weight gradient and a delta gradient per hidden layer).
fn penalty_flops(shape: &MlpShape, rows: usize) -> u64 {
    let fwd = shape.forward_flops_per_row() * rows as u64;
    let hidden_layers = &shape.dims[..shape.dims.len() - 1];
    let input_grad: u64 = hidden_layers.windows(2).map(|w| linear_flops(rows, w[0], w[1])).sum();
    fwd + 3 * input_grad
}

/// FLOPs of one main-loop iteration.
pub fn main_loop_flops(cfg: &SpeedConfig) -> u64 {
    let b = cfg.batch;
    train_flops(&cfg.nu_shape(), 3 * b)
        + penalty_flops(&cfg.nu_shape(), 2 * b)
        + train_flops(&cfg.policy_shape(), b)
}

/// FLOPs of one discriminator step.
pub fn disc_step_flops(cfg: &SpeedConfig) -> u64 {
    let b = cfg.batch;
    train_flops(&cfg.disc_shape(), 2 * b) + penalty_flops(&cfg.disc_shape(), 2 * b)
}

// ---------------------------------------------------------------------------------------------
// Synthetic data and minibatches

/// Column buffers of a synthetic dataset (row-major, one row per transition).
pub struct SyntheticData {
    obs_dim: usize,
    act_dim: usize,
    discrete: Option<usize>,
    states: Vec<f32>,
    next_states: Vec<f32>,
    initial_states: Vec<f32>,
    rewards: Vec<f32>,
    /// Continuous: `n x act_dim` in [-1, 1] (every 7th row on the bound); discrete: indices.
    actions: Vec<f32>,
    action_index: Vec<usize>,
    /// Discriminator inputs `cat(s, a)` (one-hot for discrete), unlabeled and non-preferred.
    disc_unlabeled: Vec<f32>,
    disc_non_preferred: Vec<f32>,
}

const UNLABELED: usize = 20_000;
const NON_PREFERRED: usize = 4_000;
const INITIAL: usize = 200;

impl SyntheticData {
    pub fn new(cfg: &SpeedConfig, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut normals =
            |n: usize| -> Vec<f32> { (0..n).map(|_| StandardNormal.sample(&mut rng)).collect() };
        let states = normals(UNLABELED * cfg.obs_dim);
        let next_states = normals(UNLABELED * cfg.obs_dim);
        let initial_states = normals(INITIAL * cfg.obs_dim);
        let rewards = normals(UNLABELED);
        let np_states = normals(NON_PREFERRED * cfg.obs_dim);
        let act_in = cfg.act_input();
        let (actions, action_index, np_actions) = match cfg.discrete {
            Some(n) => {
                let idx: Vec<usize> = (0..UNLABELED).map(|_| rng.random_range(0..n)).collect();
                let np: Vec<usize> = (0..NON_PREFERRED).map(|_| rng.random_range(0..n)).collect();
                (one_hot(&idx, n), idx, one_hot(&np, n))
            }
            None => {
                let mut acts: Vec<f32> =
                    (0..UNLABELED * cfg.act_dim).map(|_| rng.random_range(-1.0..1.0)).collect();
                for row in acts.chunks_exact_mut(cfg.act_dim).step_by(7) {
                    row.fill(1.0);
                }
                let np = (0..NON_PREFERRED * cfg.act_dim).map(|_| rng.random_range(-1.0..1.0));
                (acts, Vec::new(), np.collect())
            }
        };
        Self {
            obs_dim: cfg.obs_dim,
            act_dim: cfg.act_dim,
            discrete: cfg.discrete,
            disc_unlabeled: concat_columns(&states, cfg.obs_dim, &actions, act_in),
            disc_non_preferred: concat_columns(&np_states, cfg.obs_dim, &np_actions, act_in),
            states,
            next_states,
            initial_states,
            rewards,
            actions,
            action_index,
        }
    }

    fn disc_dim(&self) -> usize {
        self.obs_dim + self.discrete.unwrap_or(self.act_dim)
    }
}

fn one_hot(idx: &[usize], n: usize) -> Vec<f32> {
    let mut out = vec![0.0; idx.len() * n];
    for (row, &i) in out.chunks_exact_mut(n).zip(idx) {
        row[i] = 1.0;
    }
    out
}

fn concat_columns(a: &[f32], da: usize, b: &[f32], db: usize) -> Vec<f32> {
    a.chunks_exact(da)
        .zip(b.chunks_exact(db))
        .flat_map(|(x, y)| x.iter().chain(y).copied())
        .collect()
}

/// Copy rows `idx` of `src` (`? x dim`) into `dst` in order.
fn gather_rows(dst: &mut [f32], src: &[f32], dim: usize, idx: &[usize]) {
    for (out, &i) in dst.chunks_exact_mut(dim).zip(idx) {
        out.copy_from_slice(&src[i * dim..(i + 1) * dim]);
    }
}

/// `dst[r] = u[r]·a[r] + (1 - u[r])·b[r]` row by row.
fn interpolate_rows(dst: &mut [f32], a: &[f32], b: &[f32], u: &[f32], dim: usize) {
    let rows = dst.chunks_exact_mut(dim).zip(a.chunks_exact(dim)).zip(b.chunks_exact(dim));
    for (((out, x), y), &t) in rows.zip(u) {
        for ((o, &xv), &yv) in out.iter_mut().zip(x).zip(y) {
            *o = t * xv + (1.0 - t) * yv;
        }
    }
}

/// The random draws of one main-loop iteration (buffers reused between iterations).
#[derive(Clone, Debug, Default)]
pub struct MainBatch {
    pub idx: Vec<usize>,
    pub idx0: Vec<usize>,
    /// `2B` interpolation weights for the nu gradient penalty.
    pub u: Vec<f32>,
}

/// The random draws of one discriminator step.
#[derive(Clone, Debug, Default)]
pub struct DiscBatch {
    pub idx_n: Vec<usize>,
    pub idx_u: Vec<usize>,
    pub perm: Vec<usize>,
    pub u: Vec<f32>,
}

fn fill_indices(v: &mut Vec<usize>, n: usize, len: usize, rng: &mut ChaCha8Rng) {
    v.clear();
    v.extend((0..n).map(|_| rng.random_range(0..len)));
}

fn fill_uniform(v: &mut Vec<f32>, n: usize, rng: &mut ChaCha8Rng) {
    v.clear();
    v.extend((0..n).map(|_| rng.random::<f32>()));
}

impl MainBatch {
    pub fn sample(&mut self, b: usize, rng: &mut ChaCha8Rng) {
        fill_indices(&mut self.idx, b, UNLABELED, rng);
        fill_indices(&mut self.idx0, b, INITIAL, rng);
        fill_uniform(&mut self.u, 2 * b, rng);
    }
}

impl DiscBatch {
    pub fn sample(&mut self, b: usize, rng: &mut ChaCha8Rng) {
        fill_indices(&mut self.idx_n, b, NON_PREFERRED, rng);
        fill_indices(&mut self.idx_u, b, UNLABELED, rng);
        self.perm.clear();
        self.perm.extend(0..b);
        for i in (1..b).rev() {
            self.perm.swap(i, rng.random_range(0..=i));
        }
        fill_uniform(&mut self.u, 2 * b, rng);
    }
}

// ---------------------------------------------------------------------------------------------
// Loss heads shared by the fused engine (value and gradient with respect to the net's output)

fn softplus(x: f32) -> f32 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Tanh-Gaussian log-density of a dataset action and its gradient with respect to the raw head
/// outputs `[mean | log_std]` (clipped; no gradient outside the clip range).
fn tanh_gaussian_log_prob(out: &[f32], action: &[f32], grad: &mut [f32]) -> f32 {
    let d = action.len();
    let mut logp = 0.0;
    for j in 0..d {
        let (m_raw, s_raw) = (out[j], out[d + j]);
        let mean = m_raw.clamp(MEAN_CLIP.0, MEAN_CLIP.1);
        let log_std = s_raw.clamp(LOG_STD_CLIP.0, LOG_STD_CLIP.1);
        let a = action[j];
        let u = a.clamp(-1.0 + ATANH_EPS, 1.0 - ATANH_EPS).atanh();
        let inv_std = (-log_std).exp();
        let z = (u - mean) * inv_std;
        logp += -0.5 * z * z - log_std - 0.5 * (2.0 * std::f32::consts::PI).ln();
        logp -= (1.0 - a * a + ATANH_EPS).ln();
        let inside = |x: f32, (lo, hi): (f32, f32)| if (lo..=hi).contains(&x) { 1.0 } else { 0.0 };
        grad[j] = z * inv_std * inside(m_raw, MEAN_CLIP);
        grad[d + j] = (z * z - 1.0) * inside(s_raw, LOG_STD_CLIP);
    }
    logp
}

/// Categorical log-probability of action `a` and its gradient with respect to the logits.
fn categorical_log_prob(logits: &[f32], a: usize, grad: &mut [f32]) -> f32 {
    let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let sum: f32 = logits.iter().map(|&l| (l - max).exp()).sum();
    let lse = max + sum.ln();
    for (g, &l) in grad.iter_mut().zip(logits) {
        *g = -(l - lse).exp();
    }
    grad[a] += 1.0;
    logits[a] - lse
}

// ---------------------------------------------------------------------------------------------
// Fused engine

/// nu, policy and discriminator with their workspaces, gradients and optimisers.
pub struct FusedNets {
    pub nu: FusedMlp,
    pub policy: FusedMlp,
    pub disc: FusedMlp,
    pub nu_grads: Vec<f32>,
    pub policy_grads: Vec<f32>,
    pub disc_grads: Vec<f32>,
    ws_nu: Workspace,
    ws_policy: Workspace,
    ws_disc: Workspace,
    adam_nu: Adam,
    adam_policy: Adam,
    adam_disc: Adam,
    /// Per-sample policy weights `softmax(A)` and the policy's output gradient scratch.
    weights: Vec<f32>,
    head_grad: Vec<f32>,
}

/// Losses of one step, for the tests and to keep the work observable.
#[derive(Clone, Copy, Debug, Default)]
pub struct MainLosses {
    pub nu: f32,
    pub nu_penalty: f32,
    pub policy: f32,
}

impl FusedNets {
    pub fn new(cfg: &SpeedConfig, rng: &mut ChaCha8Rng) -> Self {
        let b = cfg.batch;
        let nu = FusedMlp::new_he(cfg.nu_shape(), rng);
        let policy = FusedMlp::new_he(cfg.policy_shape(), rng);
        let disc = FusedMlp::new_he(cfg.disc_shape(), rng);
        Self {
            ws_nu: Workspace::new(nu.shape(), 5 * b, cfg.threads),
            ws_policy: Workspace::new(policy.shape(), b, cfg.threads),
            ws_disc: Workspace::new(disc.shape(), 4 * b, cfg.threads),
            nu_grads: vec![0.0; nu.num_params()],
            policy_grads: vec![0.0; policy.num_params()],
            disc_grads: vec![0.0; disc.num_params()],
            adam_nu: Adam::new(nu.num_params(), 1e-4),
            adam_policy: Adam::new(policy.num_params(), 1e-5),
            adam_disc: Adam::new(disc.num_params(), 1e-4),
            weights: vec![0.0; b],
            head_grad: vec![0.0; policy.shape().output()],
            nu,
            policy,
            disc,
        }
    }

    /// Gradients of the main-loop losses (nu: Eq. 36 + penalty; policy: Eq. 37) into
    /// `nu_grads` and `policy_grads`.
    pub fn main_grads(&mut self, data: &SyntheticData, batch: &MainBatch) -> MainLosses {
        let b = batch.idx.len();
        let d = data.obs_dim;
        let input = self.ws_nu.input_mut();
        gather_rows(&mut input[..b * d], &data.states, d, &batch.idx);
        gather_rows(&mut input[b * d..2 * b * d], &data.next_states, d, &batch.idx);
        gather_rows(&mut input[2 * b * d..3 * b * d], &data.initial_states, d, &batch.idx0);
        {
            let (loss_rows, hat) = input.split_at_mut(3 * b * d);
            let (s, rest) = loss_rows.split_at(b * d);
            let (s_next, s0) = rest.split_at(b * d);
            interpolate_rows(&mut hat[..b * d], s0, s, &batch.u[..b], d);
            interpolate_rows(&mut hat[b * d..2 * b * d], s_next, s, &batch.u[b..], d);
        }
        let mut losses = MainLosses::default();
        let weights = &mut self.weights;
        self.nu_grads.fill(0.0);
        losses.nu_penalty = self.nu.train_pass(
            &mut self.ws_nu,
            3 * b,
            2 * b,
            &mut self.nu_grads,
            |out, dout| {
                // Eq. 36: A = r + γν(s') - ν(s); d logsumexp(A)/dA = softmax(A).
                for (i, w) in weights.iter_mut().enumerate() {
                    *w = data.rewards[batch.idx[i]] + GAMMA * out[b + i] - out[i];
                }
                let max = weights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let mut sum = 0.0;
                for w in weights.iter_mut() {
                    *w = (*w - max).exp();
                    sum += *w;
                }
                weights.iter_mut().for_each(|w| *w /= sum);
                let mean_v0 = out[2 * b..3 * b].iter().sum::<f32>() / b as f32;
                losses.nu = max + sum.ln() - (b as f32).ln() + (1.0 - GAMMA) * mean_v0;
                for (i, &p) in weights.iter().enumerate() {
                    dout[i] = -p;
                    dout[b + i] = GAMMA * p;
                }
                dout[2 * b..3 * b].fill((1.0 - GAMMA) / b as f32);
            },
            |g, dp| {
                // Zero-centred penalty λ mean ‖g‖² over the 2B interpolates.
                let scale = NU_GP / (2 * b) as f32;
                let mut total = 0.0;
                for (o, &gv) in dp.iter_mut().zip(g) {
                    total += gv * gv;
                    *o = 2.0 * scale * gv;
                }
                scale * total
            },
        );
        losses.nu += losses.nu_penalty;

        // Eq. 37 with the pre-update nu: loss = -Σ softmax(A)_i log π(a_i|s_i).
        let s_rows = &self.ws_nu.input_mut()[..b * d];
        self.ws_policy.input_mut()[..b * d].copy_from_slice(s_rows);
        let (weights, head_grad) = (&self.weights, &mut self.head_grad);
        let mut policy_loss = 0.0;
        self.policy_grads.fill(0.0);
        self.policy.train_pass(
            &mut self.ws_policy,
            b,
            0,
            &mut self.policy_grads,
            |out, dout| {
                let k = head_grad.len();
                for (i, (o, dg)) in out.chunks_exact(k).zip(dout.chunks_exact_mut(k)).enumerate() {
                    let row = batch.idx[i];
                    let logp = match data.discrete {
                        Some(_) => categorical_log_prob(o, data.action_index[row], head_grad),
                        None => {
                            let a = &data.actions[row * data.act_dim..(row + 1) * data.act_dim];
                            tanh_gaussian_log_prob(o, a, head_grad)
                        }
                    };
                    policy_loss -= weights[i] * logp;
                    for (x, &h) in dg.iter_mut().zip(head_grad.iter()) {
                        *x = -weights[i] * h;
                    }
                }
            },
            |_, _| 0.0,
        );
        losses.policy = policy_loss;
        losses
    }

    pub fn main_step(&mut self, data: &SyntheticData, batch: &MainBatch) -> MainLosses {
        let losses = self.main_grads(data, batch);
        self.adam_nu.step(&mut self.nu.params, &self.nu_grads);
        self.adam_policy.step(&mut self.policy.params, &self.policy_grads);
        losses
    }

    /// Gradient of the discriminator loss (Eq. 9 + penalty) into `disc_grads`; returns the loss.
    pub fn disc_grads(&mut self, data: &SyntheticData, batch: &DiscBatch) -> f32 {
        let b = batch.idx_n.len();
        let d = data.disc_dim();
        let input = self.ws_disc.input_mut();
        gather_rows(&mut input[..b * d], &data.disc_non_preferred, d, &batch.idx_n);
        gather_rows(&mut input[b * d..2 * b * d], &data.disc_unlabeled, d, &batch.idx_u);
        {
            let (loss_rows, hat) = input.split_at_mut(2 * b * d);
            let (x_n, x_u) = loss_rows.split_at(b * d);
            interpolate_rows(&mut hat[..b * d], x_n, x_u, &batch.u[..b], d);
            // u·x_U[perm] + (1-u)·x_U, row by row.
            for (r, &p) in batch.perm.iter().enumerate() {
                let t = batch.u[b + r];
                let out = &mut hat[(b + r) * d..(b + r + 1) * d];
                let (shuffled, own) = (&x_u[p * d..(p + 1) * d], &x_u[r * d..(r + 1) * d]);
                for ((o, &x), &y) in out.iter_mut().zip(shuffled).zip(own) {
                    *o = t * x + (1.0 - t) * y;
                }
            }
        }
        let mut loss = 0.0;
        self.disc_grads.fill(0.0);
        let penalty = self.disc.train_pass(
            &mut self.ws_disc,
            2 * b,
            2 * b,
            &mut self.disc_grads,
            |out, dout| {
                let inv_b = 1.0 / b as f32;
                for i in 0..b {
                    let (c_n, c_u) = (out[i], out[b + i]);
                    loss += (softplus(-c_n) + softplus(c_u)) * inv_b;
                    dout[i] = -sigmoid(-c_n) * inv_b;
                    dout[b + i] = sigmoid(c_u) * inv_b;
                }
            },
            |g, dp| {
                // λ mean (‖g‖ - 1)² over the 2B interpolates.
                let scale = DISC_GP / (2 * b) as f32;
                let mut total = 0.0;
                for (gr, dr) in g.chunks_exact(d).zip(dp.chunks_exact_mut(d)) {
                    let norm = (gr.iter().map(|v| v * v).sum::<f32>() + NORM_EPS).sqrt();
                    total += (norm - 1.0) * (norm - 1.0);
                    let k = scale * 2.0 * (norm - 1.0) / norm;
                    for (o, &gv) in dr.iter_mut().zip(gr) {
                        *o = k * gv;
                    }
                }
                scale * total
            },
        );
        loss + penalty
    }

    pub fn disc_step(&mut self, data: &SyntheticData, batch: &DiscBatch) -> f32 {
        let loss = self.disc_grads(data, batch);
        self.adam_disc.step(&mut self.disc.params, &self.disc_grads);
        loss
    }
}

// ---------------------------------------------------------------------------------------------
// Candle autograd engine (the straightforward implementation)

/// An MLP as candle `Var`s in the [`FusedMlp::to_tensors`] order.
pub struct CandleMlp {
    pub vars: Vec<Var>,
}

impl CandleMlp {
    pub fn from_fused(net: &FusedMlp, device: &Device) -> candle_core::Result<Self> {
        let vars = net
            .to_tensors(device)?
            .iter()
            .map(Var::from_tensor)
            .collect::<candle_core::Result<_>>()?;
        Ok(Self { vars })
    }

    /// `(weight, bias)` per layer: a rank-1 var after a weight is that layer's bias.
    fn layers(&self) -> Vec<(&Tensor, Option<&Tensor>)> {
        let mut out = Vec::new();
        let mut it = self.vars.iter().map(|v| v.as_tensor()).peekable();
        while let Some(w) = it.next() {
            let b = it.next_if(|t| t.rank() == 1);
            out.push((w, b));
        }
        out
    }

    /// Output and the hidden activations (for the penalty's masks).
    fn forward(&self, x: &Tensor) -> candle_core::Result<(Tensor, Vec<Tensor>)> {
        let layers = self.layers();
        let mut h = x.clone();
        let mut hidden = Vec::new();
        for (l, (w, b)) in layers.iter().enumerate() {
            h = h.matmul(w)?;
            if let Some(b) = b {
                h = h.broadcast_add(b)?;
            }
            if l + 1 < layers.len() {
                h = h.relu()?;
                hidden.push(h.clone());
            }
        }
        Ok((h, hidden))
    }

    /// Input-gradient of a scalar critic written as ordinary tensor ops (masks times weights,
    /// back to front), so first-order autograd differentiates it.
    fn input_grad(&self, hidden: &[Tensor]) -> candle_core::Result<Tensor> {
        let layers = self.layers();
        let mut delta: Option<Tensor> = None;
        for (l, (w, _)) in layers.iter().enumerate().rev() {
            delta = Some(match (l, delta) {
                (_, None) => {
                    hidden[l - 1].gt(0f32)?.to_dtype(DType::F32)?.broadcast_mul(&w.t()?)?
                }
                (0, Some(d)) => d.matmul(&w.t()?)?,
                (_, Some(d)) => {
                    (d.matmul(&w.t()?)? * hidden[l - 1].gt(0f32)?.to_dtype(DType::F32)?)?
                }
            });
        }
        Ok(delta.expect("at least one layer"))
    }
}

fn candle_softplus(x: &Tensor) -> candle_core::Result<Tensor> {
    x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?
}

fn rows_tensor(
    src: &[f32],
    dim: usize,
    idx: &[usize],
    device: &Device,
) -> candle_core::Result<Tensor> {
    let mut buf = vec![0.0; idx.len() * dim];
    gather_rows(&mut buf, src, dim, idx);
    Tensor::from_vec(buf, (idx.len(), dim), device)
}

pub struct CandleNets {
    pub nu: CandleMlp,
    pub policy: CandleMlp,
    pub disc: CandleMlp,
    opt_nu: AdamW,
    opt_policy: AdamW,
    opt_disc: AdamW,
    device: Device,
}

fn adam(vars: &[Var], lr: f64) -> candle_core::Result<AdamW> {
    AdamW::new(vars.to_vec(), ParamsAdamW { lr, weight_decay: 0.0, ..Default::default() })
}

/// Losses plus the gradient tensors (in var order) of one main-loop or discriminator step.
pub struct CandleStep {
    pub losses: MainLosses,
    pub grads: candle_core::backprop::GradStore,
}

impl CandleNets {
    pub fn from_fused(nets: &FusedNets, device: &Device) -> candle_core::Result<Self> {
        let nu = CandleMlp::from_fused(&nets.nu, device)?;
        let policy = CandleMlp::from_fused(&nets.policy, device)?;
        let disc = CandleMlp::from_fused(&nets.disc, device)?;
        Ok(Self {
            opt_nu: adam(&nu.vars, 1e-4)?,
            opt_policy: adam(&policy.vars, 1e-5)?,
            opt_disc: adam(&disc.vars, 1e-4)?,
            nu,
            policy,
            disc,
            device: device.clone(),
        })
    }

    fn policy_log_prob(
        &self,
        data: &SyntheticData,
        out: &Tensor,
        idx: &[usize],
    ) -> candle_core::Result<Tensor> {
        let dev = &self.device;
        match data.discrete {
            Some(_) => {
                let a: Vec<u32> = idx.iter().map(|&i| data.action_index[i] as u32).collect();
                let a = Tensor::from_vec(a, (idx.len(), 1), dev)?;
                candle_nn::ops::log_softmax(out, 1)?.gather(&a, 1)?.squeeze(1)
            }
            None => {
                let d = data.act_dim;
                let act = rows_tensor(&data.actions, d, idx, dev)?;
                let mean = out.narrow(1, 0, d)?.clamp(MEAN_CLIP.0, MEAN_CLIP.1)?;
                let log_std = out.narrow(1, d, d)?.clamp(LOG_STD_CLIP.0, LOG_STD_CLIP.1)?;
                let clipped = act.clamp(-1.0 + ATANH_EPS, 1.0 - ATANH_EPS)?;
                let u = (((&clipped + 1.0)?.log()? - (clipped.neg()? + 1.0)?.log()?)? * 0.5)?;
                let z = ((u - mean)? * log_std.neg()?.exp()?)?;
                let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
                let gauss = ((z.sqr()? * -0.5)? - log_std)?.affine(1.0, -half_log_2pi)?.sum(1)?;
                let jacobian = ((act.sqr()?.neg()? + 1.0)? + ATANH_EPS as f64)?.log()?.sum(1)?;
                gauss - jacobian
            }
        }
    }

    /// Main-loop losses and their gradients (no optimiser step).
    pub fn main_grads(
        &self,
        data: &SyntheticData,
        batch: &MainBatch,
    ) -> candle_core::Result<CandleStep> {
        let (b, d, dev) = (batch.idx.len(), data.obs_dim, &self.device);
        let s = rows_tensor(&data.states, d, &batch.idx, dev)?;
        let s_next = rows_tensor(&data.next_states, d, &batch.idx, dev)?;
        let s0 = rows_tensor(&data.initial_states, d, &batch.idx0, dev)?;
        let r: Vec<f32> = batch.idx.iter().map(|&i| data.rewards[i]).collect();
        let r = Tensor::from_vec(r, b, dev)?;
        let (v, _) = self.nu.forward(&Tensor::cat(&[&s, &s_next, &s0], 0)?)?;
        let v = v.squeeze(1)?;
        let adv = ((r + (v.narrow(0, b, b)? * GAMMA as f64)?)? - v.narrow(0, 0, b)?)?;
        let nu_main = ((adv.log_sum_exp(0)? - (b as f64).ln())?
            + (v.narrow(0, 2 * b, b)?.mean_all()? * (1.0 - GAMMA as f64))?)?;
        let u = Tensor::from_slice(&batch.u, (2 * b, 1), dev)?;
        let from = Tensor::cat(&[&s0, &s_next], 0)?;
        let to = Tensor::cat(&[&s, &s], 0)?;
        let hat = (from.broadcast_mul(&u)? + to.broadcast_mul(&(u.neg()? + 1.0)?)?)?;
        let (_, hidden) = self.nu.forward(&hat)?;
        let g = self.nu.input_grad(&hidden)?;
        let penalty = (g.sqr()?.sum(1)?.mean_all()? * NU_GP as f64)?;
        let nu_loss = (nu_main + &penalty)?;
        let w = candle_nn::ops::softmax(&adv.detach(), 0)?;
        let (out, _) = self.policy.forward(&s)?;
        let policy_loss = (w * self.policy_log_prob(data, &out, &batch.idx)?)?.sum_all()?.neg()?;
        let grads = (&nu_loss + &policy_loss)?.backward()?;
        let losses = MainLosses {
            nu: nu_loss.to_scalar()?,
            nu_penalty: penalty.to_scalar()?,
            policy: policy_loss.to_scalar()?,
        };
        Ok(CandleStep { losses, grads })
    }

    pub fn main_step(
        &mut self,
        data: &SyntheticData,
        batch: &MainBatch,
    ) -> candle_core::Result<MainLosses> {
        let step = self.main_grads(data, batch)?;
        self.opt_nu.step(&step.grads)?;
        self.opt_policy.step(&step.grads)?;
        Ok(step.losses)
    }

    pub fn disc_grads(
        &self,
        data: &SyntheticData,
        batch: &DiscBatch,
    ) -> candle_core::Result<(f32, candle_core::backprop::GradStore)> {
        let (b, d, dev) = (batch.idx_n.len(), data.disc_dim(), &self.device);
        let x_n = rows_tensor(&data.disc_non_preferred, d, &batch.idx_n, dev)?;
        let x_u = rows_tensor(&data.disc_unlabeled, d, &batch.idx_u, dev)?;
        let (c, _) = self.disc.forward(&Tensor::cat(&[&x_n, &x_u], 0)?)?;
        let c = c.squeeze(1)?;
        let loss = (candle_softplus(&c.narrow(0, 0, b)?.neg()?)?.mean_all()?
            + candle_softplus(&c.narrow(0, b, b)?)?.mean_all()?)?;
        let perm: Vec<u32> = batch.perm.iter().map(|&p| p as u32).collect();
        let shuffled = x_u.index_select(&Tensor::from_vec(perm, b, dev)?, 0)?;
        let u = Tensor::from_slice(&batch.u, (2 * b, 1), dev)?;
        let from = Tensor::cat(&[&x_n, &shuffled], 0)?;
        let to = Tensor::cat(&[&x_u, &x_u], 0)?;
        let hat = (from.broadcast_mul(&u)? + to.broadcast_mul(&(u.neg()? + 1.0)?)?)?;
        let (_, hidden) = self.disc.forward(&hat)?;
        let g = self.disc.input_grad(&hidden)?;
        let norm = (g.sqr()?.sum(1)? + NORM_EPS as f64)?.sqrt()?;
        let penalty = ((norm - 1.0)?.sqr()?.mean_all()? * DISC_GP as f64)?;
        let total = (loss + penalty)?;
        let grads = total.backward()?;
        Ok((total.to_scalar()?, grads))
    }

    pub fn disc_step(
        &mut self,
        data: &SyntheticData,
        batch: &DiscBatch,
    ) -> candle_core::Result<f32> {
        let (loss, grads) = self.disc_grads(data, batch)?;
        self.opt_disc.step(&grads)?;
        Ok(loss)
    }
}

// ---------------------------------------------------------------------------------------------
// The benchmark

/// One workload's measurement.
#[derive(Clone, Debug)]
pub struct Measurement {
    pub name: &'static str,
    pub unit: &'static str,
    /// Steps per second of every repeat, and their median.
    pub rates: Vec<f64>,
    pub median: f64,
    /// Steps per second of process CPU time (Linux), median over repeats: less sensitive than
    /// wall-clock time to other processes taking the cores.
    pub cpu_median: Option<f64>,
    pub flops_per_step: u64,
}

impl Measurement {
    pub fn gflops(&self) -> f64 {
        self.median * self.flops_per_step as f64 / 1e9
    }
}

fn measure(
    name: &'static str,
    unit: &'static str,
    flops_per_step: u64,
    cfg: &SpeedConfig,
    mut step: impl FnMut() -> anyhow::Result<f32>,
) -> anyhow::Result<Measurement> {
    let mut last = 0.0;
    for _ in 0..(cfg.iters / 10).max(5) {
        last = step()?;
    }
    let (mut rates, mut cpu_rates) = (Vec::new(), Vec::new());
    for _ in 0..cfg.repeats.max(1) {
        let (t, cpu) = (Instant::now(), process_cpu_seconds());
        for _ in 0..cfg.iters {
            last = step()?;
        }
        rates.push(cfg.iters as f64 / t.elapsed().as_secs_f64());
        if let (Some(start), Some(end)) = (cpu, process_cpu_seconds()) {
            cpu_rates.push(cfg.iters as f64 / (end - start).max(0.01));
        }
    }
    anyhow::ensure!(last.is_finite(), "{name}: loss went non-finite ({last})");
    let cpu_median = (cpu_rates.len() == rates.len()).then(|| median(&cpu_rates));
    Ok(Measurement { name, unit, median: median(&rates), rates, cpu_median, flops_per_step })
}

fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted[sorted.len() / 2]
}

/// User + system CPU seconds of this process from `/proc/self/stat` (10 ms resolution); None
/// where that file does not exist.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name start at field 3; utime and stime are 14, 15.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// A synthetic dataset for the trainer: `episodes` episodes of `len` steps, no terminals (as the
/// authors' 1000-step data), standard-normal observations, uniform actions.
fn synthetic_dataset(
    cfg: &SpeedConfig,
    episodes: usize,
    len: usize,
    rng: &mut ChaCha8Rng,
) -> Dataset {
    let n = episodes * len;
    let mut normals =
        |k: usize| -> Vec<f32> { (0..k).map(|_| StandardNormal.sample(&mut *rng)).collect() };
    let observations = normals(n * cfg.obs_dim);
    let next_observations = normals(n * cfg.obs_dim);
    let (action_space, actions) = match cfg.discrete {
        Some(k) => (
            ActionSpace::Discrete { n: k },
            Actions::Discrete((0..n).map(|_| rng.random_range(0..k as u32)).collect()),
        ),
        None => (
            ActionSpace::Continuous {
                dim: cfg.act_dim,
                low: vec![-1.0; cfg.act_dim],
                high: vec![1.0; cfg.act_dim],
            },
            Actions::Continuous(
                (0..n * cfg.act_dim).map(|_| rng.random_range(-1.0..=1.0)).collect(),
            ),
        ),
    };
    Dataset {
        obs_dim: cfg.obs_dim,
        action_space,
        observations,
        actions,
        next_observations,
        terminals: vec![false; n],
        episode_ids: (0..n).map(|i| (i / len) as u32).collect(),
        rewards: None,
        costs: None,
    }
}

/// A SafeDICE trainer (`authors-code` preset: both gradient penalties on) on synthetic data.
fn synthetic_trainer(
    cfg: &SpeedConfig,
    (unlabeled, non_preferred): (usize, usize),
    disc_steps: usize,
    iterations: usize,
) -> anyhow::Result<SafediceTrainer> {
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let episode = 1000.min(unlabeled).min(non_preferred);
    let data = TrainingData {
        unlabeled: Arc::new(synthetic_dataset(cfg, unlabeled / episode, episode, &mut rng)),
        non_preferred: Some(Arc::new(synthetic_dataset(
            cfg,
            non_preferred / episode,
            episode,
            &mut rng,
        ))),
    };
    let config = resolve_config(
        Algorithm::Safedice,
        &serde_json::json!({
            "preset": "authors-code",
            "seed": cfg.seed,
            "batch_size": cfg.batch,
            "hidden_sizes": cfg.hidden,
            "iterations": iterations,
            "discriminator_iterations": disc_steps,
        }),
    )?;
    Ok(SafediceTrainer::new(&config, &data)?)
}

/// The real trainer, timed phase by phase.
fn run_trainer(cfg: &SpeedConfig, candle_path: bool) -> anyhow::Result<Vec<Measurement>> {
    let warmup = (cfg.iters / 10).max(5);
    let timed = cfg.iters * cfg.repeats.max(1);
    // One untimed step after the timed discriminator steps ends the phase (alpha-hat and the
    // rewards over all of D^U), so no timed step includes it.
    let disc_steps = warmup + timed + 1;
    let mut trainer =
        synthetic_trainer(cfg, (UNLABELED, NON_PREFERRED), disc_steps, warmup + timed)?;
    if candle_path {
        trainer.use_candle_autograd();
    }
    let mut step = || -> anyhow::Result<f32> {
        trainer.step(false)?;
        Ok(0.0)
    };
    let disc =
        measure("discriminator step (with GP)", "steps/s", disc_step_flops(cfg), cfg, &mut step)?;
    step()?;
    let main = measure(
        "main loop (nu on s,s',s0 + nu GP + policy)",
        "iterations/s",
        main_loop_flops(cfg),
        cfg,
        &mut step,
    )?;
    Ok(vec![main, disc])
}

/// Run both workloads with the configured engine.
pub fn run(cfg: &SpeedConfig) -> anyhow::Result<Vec<Measurement>> {
    match cfg.engine {
        Engine::Trainer => return run_trainer(cfg, false),
        Engine::TrainerCandle => return run_trainer(cfg, true),
        Engine::Fused | Engine::Candle => {}
    }
    let data = SyntheticData::new(cfg, cfg.seed);
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed.wrapping_add(1));
    let mut fused = FusedNets::new(cfg, &mut rng);
    let mut main_batch = MainBatch::default();
    let mut disc_batch = DiscBatch::default();
    let b = cfg.batch;
    let (main_flops, disc_flops) = (main_loop_flops(cfg), disc_step_flops(cfg));
    let main_name = "main loop (nu on s,s',s0 + nu GP + policy)";
    let disc_name = "discriminator step (with GP)";
    match cfg.engine {
        Engine::Trainer | Engine::TrainerCandle => unreachable!("handled above"),
        Engine::Fused => Ok(vec![
            measure(main_name, "iterations/s", main_flops, cfg, || {
                main_batch.sample(b, &mut rng);
                Ok(fused.main_step(&data, &main_batch).nu)
            })?,
            measure(disc_name, "steps/s", disc_flops, cfg, || {
                disc_batch.sample(b, &mut rng);
                Ok(fused.disc_step(&data, &disc_batch))
            })?,
        ]),
        Engine::Candle => {
            let mut nets = CandleNets::from_fused(&fused, &Device::Cpu)?;
            let rng = &mut rng;
            Ok(vec![
                measure(main_name, "iterations/s", main_flops, cfg, || {
                    main_batch.sample(b, rng);
                    Ok(nets.main_step(&data, &main_batch)?.nu)
                })?,
                measure(disc_name, "steps/s", disc_flops, cfg, || {
                    disc_batch.sample(b, rng);
                    Ok(nets.disc_step(&data, &disc_batch)?)
                })?,
            ])
        }
    }
}

/// The benchmark's printed report.
pub fn report(cfg: &SpeedConfig, results: &[Measurement]) -> String {
    let actions = match cfg.discrete {
        Some(n) => format!("{n} discrete actions"),
        None => format!("act {}", cfg.act_dim),
    };
    let mut out = format!(
        "safedice speed: engine {:?}, threads {}, batch {}, hidden {:?}, obs {}, {}, {} iters x {} repeats\n",
        cfg.engine, cfg.threads, cfg.batch, cfg.hidden, cfg.obs_dim, actions, cfg.iters, cfg.repeats
    );
    for m in results {
        let runs: Vec<String> = m.rates.iter().map(|r| format!("{r:.1}")).collect();
        out += &format!(
            "{:44} {:8.1} {:12} (runs {}; per CPU-second {})  {:7.1} MFLOP each  {:6.1} GFLOP/s  {:4.1}% of {} GFLOP/s (2-core peak)\n",
            m.name,
            m.median,
            m.unit,
            runs.join(", "),
            m.cpu_median.map_or("n/a".to_string(), |c| format!("{c:.1}")),
            m.flops_per_step as f64 / 1e6,
            m.gflops(),
            100.0 * m.gflops() / PEAK_GFLOPS_2_CORES,
            PEAK_GFLOPS_2_CORES
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(discrete: Option<usize>) -> SpeedConfig {
        SpeedConfig {
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
        }
    }

    fn flat_grads(vars: &[Var], store: &candle_core::backprop::GradStore) -> Vec<f32> {
        vars.iter()
            .flat_map(|v| {
                store.get(v).expect("gradient").flatten_all().unwrap().to_vec1::<f32>().unwrap()
            })
            .collect()
    }

    fn assert_close(what: &str, a: &[f32], b: &[f32], tol: f32) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-3);
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= tol * scale,
                "{what}[{i}]: fused {x} vs autograd {y} (scale {scale})"
            );
        }
    }

    fn check_main(discrete: Option<usize>) {
        let cfg = small(discrete);
        let data = SyntheticData::new(&cfg, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut fused = FusedNets::new(&cfg, &mut rng);
        let candle = CandleNets::from_fused(&fused, &Device::Cpu).unwrap();
        let mut batch = MainBatch::default();
        batch.sample(cfg.batch, &mut rng);
        let ours = fused.main_grads(&data, &batch);
        let reference = candle.main_grads(&data, &batch).unwrap();
        assert!((ours.nu - reference.losses.nu).abs() < 1e-5, "{ours:?} vs {:?}", reference.losses);
        assert!((ours.nu_penalty - reference.losses.nu_penalty).abs() < 1e-9);
        assert!(
            (ours.policy - reference.losses.policy).abs()
                < 1e-4 * reference.losses.policy.abs().max(1.0)
        );
        let nu_ref = flat_grads(&candle.nu.vars, &reference.grads);
        assert_close("nu grads", &fused.nu_grads, &nu_ref, 1e-5);
        let pi_ref = flat_grads(&candle.policy.vars, &reference.grads);
        assert_close("policy grads", &fused.policy_grads, &pi_ref, 1e-5);
    }

    #[test]
    fn fused_main_loop_matches_candle_autograd_continuous() {
        check_main(None);
    }

    #[test]
    fn fused_main_loop_matches_candle_autograd_discrete() {
        check_main(Some(4));
    }

    #[test]
    fn fused_disc_step_matches_candle_autograd() {
        for discrete in [None, Some(4)] {
            let cfg = small(discrete);
            let data = SyntheticData::new(&cfg, 5);
            let mut rng = ChaCha8Rng::seed_from_u64(13);
            let mut fused = FusedNets::new(&cfg, &mut rng);
            let candle = CandleNets::from_fused(&fused, &Device::Cpu).unwrap();
            let mut batch = DiscBatch::default();
            batch.sample(cfg.batch, &mut rng);
            let ours = fused.disc_grads(&data, &batch);
            let (reference, store) = candle.disc_grads(&data, &batch).unwrap();
            assert!(
                (ours - reference).abs() < 1e-4 * reference.abs().max(1.0),
                "{ours} vs {reference}"
            );
            assert_close(
                "disc grads",
                &fused.disc_grads,
                &flat_grads(&candle.disc.vars, &store),
                1e-5,
            );
        }
    }

    /// The penalty's weight gradient (double backprop) against central finite differences of
    /// the fused loss itself, in f32 on a small net (hence the 5% tolerance; the 1e-5 check is
    /// the autograd comparison above).
    #[test]
    fn disc_penalty_gradient_matches_finite_differences() {
        let cfg = small(None);
        let data = SyntheticData::new(&cfg, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let mut fused = FusedNets::new(&cfg, &mut rng);
        let mut batch = DiscBatch::default();
        batch.sample(cfg.batch, &mut rng);
        fused.disc_grads(&data, &batch);
        let analytic = fused.disc_grads.clone();
        let center = fused.disc_grads(&data, &batch);
        let h = 2e-3;
        let mut checked = 0;
        // Weights of layers 1, 2 and 3 (biases get no gradient from the penalty; their loss
        // gradient is covered against autograd). The input-gradient jumps where a ReLU mask
        // flips, so a difference that straddles a flip (one-sided slopes disagree) is skipped.
        for i in [0usize, 7, 33, 70, 95, 120, 185, 190, 239, 245] {
            let keep = fused.disc.params[i];
            fused.disc.params[i] = keep + h;
            let up = fused.disc_grads(&data, &batch);
            fused.disc.params[i] = keep - h;
            let down = fused.disc_grads(&data, &batch);
            fused.disc.params[i] = keep;
            let (right, left) = ((up - center) / h, (center - down) / h);
            if (right - left).abs() > 0.1 * right.abs().max(left.abs()).max(0.1) {
                continue;
            }
            checked += 1;
            let numeric = (up - down) / (2.0 * h);
            assert!(
                (numeric - analytic[i]).abs() < 5e-2 * analytic[i].abs().max(0.1),
                "param {i}: {numeric} vs {}",
                analytic[i]
            );
        }
        assert!(checked >= 7, "only {checked} parameters away from a ReLU kink");
    }

    #[test]
    fn fused_adam_matches_candle_adamw_without_decay() {
        let cfg = small(None);
        let data = SyntheticData::new(&cfg, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(19);
        let mut fused = FusedNets::new(&cfg, &mut rng);
        let mut candle = CandleNets::from_fused(&fused, &Device::Cpu).unwrap();
        let mut batch = DiscBatch::default();
        for _ in 0..3 {
            batch.sample(cfg.batch, &mut rng);
            fused.disc_step(&data, &batch);
            candle.disc_step(&data, &batch).unwrap();
        }
        let theirs: Vec<f32> = candle
            .disc
            .vars
            .iter()
            .flat_map(|v| v.flatten_all().unwrap().to_vec1::<f32>().unwrap())
            .collect();
        assert_close("params after 3 Adam steps", &fused.disc.params, &theirs, 1e-5);
    }

    #[test]
    fn flop_counts_match_the_hand_count() {
        let cfg = SpeedConfig {
            obs_dim: 17,
            act_dim: 6,
            discrete: None,
            batch: 512,
            hidden: vec![256, 256],
            ..small(None)
        };
        // nu: 1536 rows train + 1024 rows penalty; policy 512 rows; see bench/README.md.
        let fwd = |d: u64, o: u64| 2 * (d * 256 + 256 * 256 + 256 * o);
        let nu_train = 1536 * (2 * fwd(17, 1) + 2 * (256 * 256 + 256));
        let nu_gp = 1024 * (fwd(17, 1) + 3 * 2 * (17 * 256 + 256 * 256));
        let pi_train = 512 * (2 * fwd(17, 12) + 2 * (256 * 256 + 256 * 12));
        assert_eq!(main_loop_flops(&cfg), nu_train + nu_gp + pi_train);
        let d_train = 1024 * (2 * fwd(23, 1) + 2 * (256 * 256 + 256));
        let d_gp = 1024 * (fwd(23, 1) + 3 * 2 * (23 * 256 + 256 * 256));
        assert_eq!(disc_step_flops(&cfg), d_train + d_gp);
    }

    /// The trainer's fused path and its candle autograd path draw the same batches and report
    /// the same losses, step after step (they drift apart only by float rounding).
    #[test]
    fn trainer_fused_and_candle_paths_agree() {
        for discrete in [None, Some(4)] {
            let cfg = small(discrete);
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

    #[test]
    fn fused_steps_are_deterministic() {
        let cfg = small(None);
        let run_once = || {
            let data = SyntheticData::new(&cfg, 3);
            let mut rng = ChaCha8Rng::seed_from_u64(23);
            let mut fused = FusedNets::new(&cfg, &mut rng);
            let mut batch = MainBatch::default();
            for _ in 0..3 {
                batch.sample(cfg.batch, &mut rng);
                fused.main_step(&data, &batch);
            }
            (fused.nu.params, fused.policy.params)
        };
        assert_eq!(run_once(), run_once());
    }
}
