//! SafeDICE (Jang et al., NeurIPS 2023), Algorithm 1 of the paper, top to bottom:
//!
//! 1. pretrain the discriminator `c(s, a)` on D^N against D^U (Eq. 9), then freeze it;
//! 2. set α to alpha-hat, the minimum of Eq. 15 over every sample of D^U;
//! 3. compute the reward of Eq. 10 for every row of D^U once (the discriminator is frozen);
//! 4. each iteration, update ν by Eq. 36 and the policy by the weighted BC of Eq. 37, both on the
//!    same minibatch and with the pre-update ν.
//!
//! Where the paper is silent we follow the authors' code: the discriminator's interpolated
//! gradient penalty, ν's zero-centred one, the clipping margins of alpha-hat. Our additions are
//! options ([`TerminalHandling`], reward standardisation, the alpha-hat quantile diagnostic) with
//! the faithful behaviour available through the presets. docs/algorithm.md lists every choice
//! and where it departs from the paper.
//!
//! This file is the reference: every loss is written here once, as candle tensor code with its
//! equation number, and candle autograd differentiates it. On the CPU the two hot loops run on
//! the fused engine instead ([`super::safedice_fused`]: the same losses with hand-derived
//! gradients, checked against this file in its tests). Both engines take their minibatch from
//! `discriminator_draws` and `main_draws` below, so they consume the run's random numbers
//! identically.
//!
//! The file is longer than our usual ~600 lines on purpose: it is the one reference for the
//! algorithm, in the paper's order, with the unit tests of its equations at the end.

use candle_core::{DType, Tensor};
use rand::seq::SliceRandom;
use rand::Rng;

use super::checkpoint::Extra;
use super::columns::{uniform_column, ActionColumn, Columns};
use super::discriminator_stop::{classification_loss, Decision, EarlyStop, Holdout};
use super::hyperparams::{AlgorithmConfig, SafediceConfig};
use super::losses::{
    ess_fraction, interpolate, neg_log_one_minus_sigmoid, neg_log_sigmoid, self_normalized_weights,
    unit_gradient_penalty, weighted_nll, zero_gradient_penalty,
};
use super::mlp::Mlp;
use super::optim::Adam;
use super::policy::{Decoder, PolicyArtifact, PolicyNet};
use super::run::RunData;
use super::safedice_fused::FusedSafedice;
use super::{Progress, ResolvedConfig, TerminalHandling, TrainError, Trainer, TrainingData};
use crate::data::Dataset;

/// Alpha-hat's margin below the minimum and its cap, as in the authors' code.
const ALPHA_MARGIN: f64 = 1e-5;
/// Rows per forward pass when scoring all of D^U.
const SCORING_CHUNK: usize = 8192;
/// Added to the mean of the masked policy weights before dividing by it (a batch of
/// absorbing-state rows only has no weight left to renormalise); shared with the fused engine.
pub(super) const MASK_RENORM_EPS: f64 = 1e-12;
/// Floor of `1 − α e^c` inside Eq. 10's log; reached only with the quantile diagnostic.
const REWARD_LOG_FLOOR: f64 = 1e-8;
/// Names and hints of the non-finite guard, shared by the candle and the fused paths.
pub(super) const DISC_LOSS: (&str, &str) =
    ("the discriminator loss (Eq. 9)", "Try a lower lr_discriminator.");
pub(super) const NU_LOSS: (&str, &str) = (
    "the nu loss (Eq. 36)",
    "Episodes that end in terminal states make Eq. 36 unbounded below: try terminal_handling \"reset\", standardize_reward true, or a lower lr_nu (the authors' code uses 1e-4).",
);
pub(super) const POLICY_LOSS: (&str, &str) = (
    "the policy loss (Eq. 37)",
    "Try a lower lr_actor, or check the weight statistics (ess_fraction) for degeneracy.",
);

/// Eq. 9's loss for a batch of discriminator logits: `−mean log σ(c_N) − mean log(1 − σ(c_U))`
/// (σ(c) is the probability that (s, a) is non-preferred).
pub fn discriminator_loss(logits_n: &Tensor, logits_u: &Tensor) -> candle_core::Result<Tensor> {
    neg_log_sigmoid(logits_n)?.mean_all()? + neg_log_one_minus_sigmoid(logits_u)?.mean_all()?
}

/// Eq. 36: `log E_{D^U}[exp A] + (1 − γ) E_{p0}[ν(s0)]`, with `A = r + γ' ν(s') − ν(s)` already
/// formed (γ' per row, see [`TerminalHandling`]). The log-mean-exp is computed stably.
pub fn nu_loss(
    advantages: &Tensor,
    nu_initial: &Tensor,
    gamma: f64,
) -> candle_core::Result<Tensor> {
    let b = advantages.dim(0)? as f64;
    let log_mean_exp = (advantages.log_sum_exp(0)? - b.ln())?;
    log_mean_exp + (nu_initial.mean_all()? * (1.0 - gamma))?
}

/// Eq. 37: `−mean(w̃ log π) / mean(w̃)` with self-normalised, detached weights (optionally
/// masked: absorbing-state rows have no action).
pub fn policy_loss(log_prob: &Tensor, weights: &Tensor) -> candle_core::Result<Tensor> {
    weighted_nll(log_prob, weights)
}

/// Eq. 10 written with the discriminator logit `c` (σ(c) = c* of the paper):
/// `log((1 − (1+α)σ) / ((1−α)(1−σ))) = log(1 − α e^c) − log(1 − α)`, exact and free of the
/// cancellations of the sigmoid form. Returns the reward and whether `1 − α e^c` had to be
/// floored (impossible with the paper's alpha-hat, which makes it positive on all of D^U).
pub fn reward_from_logit(c: f64, alpha: f64) -> (f64, bool) {
    let inside = 1.0 - alpha * c.exp();
    let clipped = inside < REWARD_LOG_FLOOR;
    ((inside.max(REWARD_LOG_FLOOR)).ln() - (1.0 - alpha).ln(), clipped)
}

/// alpha-hat (Eq. 15, Algorithm 1 step 2) and where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct AlphaHat {
    /// The α used: the statistic below minus 1e-5, kept in [0, 1 − 1e-5].
    pub value: f64,
    /// `min over D^U of (1/c(s,a) − 1) = min e^{−logit}` (the paper's statistic).
    pub min_ratio: f64,
    /// Row of D^U (and its episode id) where that minimum is reached.
    pub argmin_row: usize,
    pub argmin_episode: u32,
    /// The 1% quantile of the same ratio: a diagnostic only, NOT the paper. Far above
    /// `min_ratio` means one rare sample sets alpha-hat.
    pub quantile_01: f64,
}

/// alpha-hat from the discriminator logits of every row of D^U. `quantile = 0` is the paper's
/// minimum; `quantile > 0` replaces it by that quantile (diagnostic option, not the paper).
pub fn alpha_hat_from_logits(logits: &[f32], episode_ids: &[u32], quantile: f64) -> AlphaHat {
    assert!(!logits.is_empty(), "D^U is never empty");
    let (argmin_row, max_logit) = logits
        .iter()
        .enumerate()
        .fold((0, f32::NEG_INFINITY), |best, (i, &c)| if c > best.1 { (i, c) } else { best });
    let mut ratios: Vec<f64> = logits.iter().map(|&c| (-(c as f64)).exp()).collect();
    ratios.sort_by(f64::total_cmp);
    let at =
        |q: f64| ratios[((q * (ratios.len() - 1) as f64).round() as usize).min(ratios.len() - 1)];
    let min_ratio = (-(max_logit as f64)).exp();
    let statistic = if quantile > 0.0 { at(quantile) } else { min_ratio };
    AlphaHat {
        value: (statistic - ALPHA_MARGIN).clamp(0.0, 1.0 - ALPHA_MARGIN),
        min_ratio,
        argmin_row,
        argmin_episode: episode_ids[argmin_row],
        quantile_01: at(0.01),
    }
}

/// Probability floor of the oracle discriminator ([`oracle_logits`]) on preferred rows:
/// `σ(c) = 1e-6` instead of 0, so their logit stays finite (`ln(1e-6 / (1 − 1e-6))` ≈ −13.8).
pub const ORACLE_PROB_FLOOR: f64 = 1e-6;

/// The optimal discriminator of Eq. 9, `c* = d^N / (d^U + d^N)`, as logits
/// `log(d^N / d^U)`, for a D^U whose rows are known to come from the non-preferred (`true`) or
/// the preferred (`false`) policy, with the two policies taken to share no state-action pair.
/// With α the non-preferred share of the rows, `d^U = α d^N` on non-preferred rows, so
/// `c* = 1/(1 + α)` and the logit is `−ln α`; `d^N = 0` on preferred rows, so `c* = 0`,
/// floored at [`ORACLE_PROB_FLOOR`].
///
/// Why not the labels themselves (`σ(c)` = 1 on non-preferred rows): Eq. 10 divides by
/// `1 − c*`, and Eq. 15's `min (1/c* − 1)` would be 0, so alpha-hat would be 0 and the reward 0
/// everywhere, i.e. no filtering at all. With these logits Eq. 15 returns α itself (minus its
/// 1e-5 margin), and Eq. 10 gives `−ln(1 − α̂)` on preferred rows and
/// `ln(1 − α̂/α) − ln(1 − α̂)` (≈ ln(1e-5/α), finite thanks to the margin) on non-preferred
/// ones. Without non-preferred rows every logit is the floor and the reward is constant.
/// A diagnostic of how well SafeDICE does with a perfect discriminator: a learner never has
/// these labels.
pub fn oracle_logits(non_preferred: &[bool]) -> Vec<f32> {
    let share =
        non_preferred.iter().filter(|&&np| np).count() as f64 / non_preferred.len().max(1) as f64;
    let floor = (ORACLE_PROB_FLOOR / (1.0 - ORACLE_PROB_FLOOR)).ln() as f32;
    let on_non_preferred = -(share.ln()) as f32;
    non_preferred.iter().map(|&np| if np { on_non_preferred } else { floor }).collect()
}

/// Replacements for what Algorithm 1 estimates, for ablations that measure what each estimate
/// costs (the benchmark's `--ablations`). Not part of a [`ResolvedConfig`], so a user's config
/// cannot set them, and not saved in checkpoints: [`SafediceTrainer::resume`] runs without.
/// Both act where the discriminator phase ends (alpha-hat and the Eq. 10 reward are computed
/// once there), before either engine's main loop reads the reward, so the candle and the fused
/// paths see the same values. The discriminator is still trained, drawing the same random
/// numbers, so a run with overrides and one without share their minibatches.
#[derive(Clone, Debug, Default)]
pub struct SafediceOverrides {
    /// α of Eq. 10 in place of alpha-hat (Eq. 15), kept in `[0, 1 − 1e-5]`. Eq. 15 estimates
    /// the α* of `d^U = (1 − α*) d^P + α* d^N` (Appendix A, Eq. 18), where `d^U` is the
    /// distribution of D^U's transitions (the trainer samples its rows uniformly); the true
    /// value is therefore the share of D^U's **transitions** (not episodes) that are
    /// non-preferred. Rows where `1 − α e^c` falls below the floor are floored and counted
    /// (`reward_clipped_rows`), as with the quantile diagnostic. The recorded `alpha_hat` is
    /// this value; `alpha_hat_eq15` records what Eq. 15 gave.
    pub alpha: Option<f64>,
    /// Discriminator logits for every row of D^U in place of the trained discriminator's
    /// (e.g. [`oracle_logits`]); Eq. 15 (unless `alpha` is set) and Eq. 10 read these.
    pub unlabeled_logits: Option<Vec<f32>>,
}

/// The table the ν step samples from: D^U's rows with the reward and the per-row discount that
/// the terminal handling dictates (plus absorbing-state rows for `absorbing`).
struct FlowColumns {
    obs: Tensor,
    next_obs: Tensor,
    /// γ, or γ(1 − done) with `mask` (`M`).
    discount: Tensor,
    /// Eq. 10 reward, standardised if asked (`M`).
    reward: Tensor,
    /// Rows of the initial-state set p0.
    starts: Vec<u32>,
    /// Rows `0..real_rows` are D^U; the rest are absorbing-state rows (no action).
    real_rows: usize,
    rows: usize,
}

impl FlowColumns {
    /// `b` rows of the flow table and `b` initial states of p0, both uniform with replacement.
    fn sample_batch(&self, rng: &mut impl Rng, b: usize) -> (Vec<u32>, Vec<u32>) {
        let rows = (0..b).map(|_| rng.random_range(0..self.rows as u32)).collect();
        let initial = (0..b).map(|_| self.starts[rng.random_range(0..self.starts.len())]).collect();
        (rows, initial)
    }

    /// The policy's rows for flow rows `rows`: D^U rows as they are, absorbing-state rows (only
    /// with `absorbing`; they carry no action) replaced by a placeholder row and reported in the
    /// mask (None when every row has an action).
    fn policy_rows(&self, rows: &[u32]) -> (Vec<u32>, Option<Vec<bool>>) {
        let real = self.real_rows as u32;
        let has_action: Vec<bool> = rows.iter().map(|&r| r < real).collect();
        let policy_rows = rows.iter().map(|&r| r.min(real - 1)).collect();
        (policy_rows, has_action.contains(&false).then_some(has_action))
    }

    fn build(
        u: &Columns,
        rewards: Vec<f32>,
        cfg: &SafediceConfig,
    ) -> candle_core::Result<FlowColumns> {
        let device = u.obs.device();
        let n = u.len;
        let gamma = cfg.gamma as f32;
        let terminal_rows: Vec<usize> = (0..n).filter(|&i| u.terminals[i]).collect();
        // Without terminal rows there is nothing to absorb: the flow is D^U as it is.
        let handling = match cfg.terminal_handling {
            TerminalHandling::Absorbing if terminal_rows.is_empty() => TerminalHandling::None,
            other => other,
        };
        let (obs, next_obs, rows, reward, discount) = match handling {
            TerminalHandling::None | TerminalHandling::Mask => {
                let discount: Vec<f32> = match handling {
                    TerminalHandling::Mask => {
                        u.terminals.iter().map(|&t| if t { 0.0 } else { gamma }).collect()
                    }
                    _ => vec![gamma; n],
                };
                (u.obs.clone(), u.next_obs.clone(), n, rewards, discount)
            }
            TerminalHandling::Reset => {
                // Row i of cat(next_obs, obs) for a non-terminal row, its episode's start otherwise.
                let source: Vec<u32> = (0..n)
                    .map(|i| if u.terminals[i] { (n as u32) + u.start_of_row[i] } else { i as u32 })
                    .collect();
                let both = Tensor::cat(&[&u.next_obs, &u.obs], 0)?;
                let next = both.index_select(&Tensor::from_vec(source, n, device)?, 0)?;
                (u.obs.clone(), next, n, rewards, vec![gamma; n])
            }
            TerminalHandling::Absorbing => {
                let k = terminal_rows.len();
                let flag = |rows: usize, value: f32| Tensor::full(value, (rows, 1), device);
                let absorbing_state = Tensor::cat(
                    &[Tensor::zeros((1, u.obs_dim), DType::F32, device)?, flag(1, 1.0)?],
                    1,
                )?;
                let absorbing = absorbing_state.broadcast_as((k, u.obs_dim + 1))?.contiguous()?;
                let obs = Tensor::cat(
                    &[Tensor::cat(&[&u.obs, &flag(n, 0.0)?], 1)?, absorbing.clone()],
                    0,
                )?;
                let real_next = Tensor::cat(&[&u.next_obs, &flag(n, 0.0)?], 1)?;
                // Terminal rows lead to the absorbing state; absorbing rows loop on it.
                let source: Vec<u32> =
                    (0..n).map(|i| if u.terminals[i] { n as u32 } else { i as u32 }).collect();
                let both = Tensor::cat(&[&real_next, &absorbing_state], 0)?;
                let next_real = both.index_select(&Tensor::from_vec(source, n, device)?, 0)?;
                let next = Tensor::cat(&[next_real, absorbing], 0)?;
                let mut reward = rewards;
                reward.extend(std::iter::repeat_n(0.0, k));
                (obs, next, n + k, reward, vec![gamma; n + k])
            }
        };
        Ok(FlowColumns {
            obs: obs.contiguous()?,
            next_obs: next_obs.contiguous()?,
            discount: Tensor::from_vec(discount, rows, device)?,
            reward: Tensor::from_vec(reward, rows, device)?,
            starts: u.episode_starts.clone(),
            real_rows: n,
            rows,
        })
    }
}

/// One discriminator step's minibatch, drawn once from the run's RNG for whichever engine runs
/// the step.
pub(super) struct DiscDraws {
    /// `cat(s, a)` of `B` rows of D^N and of D^U.
    pub x_n: Tensor,
    pub x_u: Tensor,
    /// `(u1, u2, perm)` of the penalty's points `u1 x_N + (1−u1) x_U` and
    /// `u2 x_U[perm] + (1−u2) x_U` (`B × 1` each); None without a penalty.
    pub penalty: Option<(Tensor, Tensor, Vec<u32>)>,
}

/// One main-loop iteration's minibatch, drawn once from the run's RNG for whichever engine runs
/// the step.
pub(super) struct MainDraws {
    /// `s`, `s'` of `B` flow rows and `B` initial states `s0`.
    pub s: Tensor,
    pub s_next: Tensor,
    pub s0: Tensor,
    /// Eq. 10 reward and γ' of the same rows.
    pub reward: Tensor,
    pub discount: Tensor,
    /// ν's penalty: interpolation weights `u` (`B × 1`) of the points `u s0 + (1−u) s` and
    /// `u s' + (1−u) s`; None without a penalty.
    pub penalty_u: Option<Tensor>,
    /// The policy's observations and dataset actions (D^U rows).
    pub policy_obs: Tensor,
    pub actions: ActionColumn,
    /// Rows with an action (all but absorbing-state rows); None when all have one.
    pub has_action: Option<Vec<bool>>,
}

pub struct SafediceTrainer {
    pub(super) run: RunData,
    pub(super) cfg: SafediceConfig,
    /// c(s, a): logit of "non-preferred"; trained in phase 1, frozen after.
    pub(super) disc: Mlp,
    pub(super) disc_opt: Adam,
    pub(super) nu: Mlp,
    pub(super) nu_opt: Adam,
    pub(super) policy: PolicyNet,
    pub(super) policy_opt: Adam,
    /// Set once the discriminator phase ends.
    alpha: Option<AlphaHat>,
    flow: Option<FlowColumns>,
    /// Metrics of the alpha-hat/reward computation, reported with the step that made them.
    phase_metrics: Vec<(&'static str, f64)>,
    /// The fused CPU engine for both hot loops (None on other devices: the candle path runs).
    pub(super) fused: Option<FusedSafedice>,
    /// Ablation replacements of alpha-hat and the discriminator's outputs (none by default).
    overrides: SafediceOverrides,
    /// With `discriminator_early_stopping`: the held-out rows and the stopping rule.
    disc_stop: Option<DiscValidation>,
}

/// Early stopping of the discriminator on held-out rows ([`super::discriminator_stop`]).
struct DiscValidation {
    n: Holdout,
    u: Holdout,
    rule: EarlyStop,
    /// The discriminator's weights at the best held-out loss so far, by variable name.
    best: std::collections::HashMap<String, Tensor>,
    last_loss: f64,
}

impl DiscValidation {
    /// Held-out rows of D^N and D^U chosen from the run's seed (a stream of its own, so the
    /// training draws are those of a run without early stopping); None when a set is a single row.
    fn new(run: &RunData, budget: u64) -> Option<DiscValidation> {
        let seed = run.config.seed();
        let n = Holdout::split(&run.non_preferred().episode_ids, seed ^ 0x5afe_d1ce_0000_0001)?;
        let u = Holdout::split(&run.u.episode_ids, seed ^ 0x5afe_d1ce_0000_0002)?;
        let best = std::collections::HashMap::new();
        Some(DiscValidation { n, u, rule: EarlyStop::new(budget), best, last_loss: f64::NAN })
    }

    fn stopped(&self) -> bool {
        self.rule.stopped_at.is_some()
    }
}

/// `batch` of `rows`, uniform with replacement.
fn pick_rows(
    rng: &mut impl Rng,
    rows: &[u32],
    batch: usize,
    device: &candle_core::Device,
) -> candle_core::Result<Tensor> {
    let picks: Vec<u32> = (0..batch).map(|_| rows[rng.random_range(0..rows.len())]).collect();
    Tensor::from_vec(picks, batch, device)
}

impl SafediceTrainer {
    pub fn new(
        config: &ResolvedConfig,
        data: &TrainingData,
    ) -> Result<SafediceTrainer, TrainError> {
        Self::with_overrides(config, data, SafediceOverrides::default())
    }

    /// A run whose alpha-hat and/or discriminator outputs are replaced ([`SafediceOverrides`]);
    /// for ablations, not reachable from the service's API.
    pub fn with_overrides(
        config: &ResolvedConfig,
        data: &TrainingData,
        overrides: SafediceOverrides,
    ) -> Result<SafediceTrainer, TrainError> {
        if let Some(a) = overrides.alpha {
            if !(0.0..1.0).contains(&a) {
                return Err(TrainError::Other(format!("alpha override {a} is not in [0, 1)")));
            }
        }
        if let Some(logits) = &overrides.unlabeled_logits {
            if logits.len() != data.unlabeled.len() || logits.iter().any(|c| c.is_nan()) {
                return Err(TrainError::Other(format!(
                    "{} logits for {} rows of D^U (or a NaN among them)",
                    logits.len(),
                    data.unlabeled.len()
                )));
            }
        }
        let AlgorithmConfig::Safedice(cfg) = &config.specific else {
            return Err(TrainError::Other("not a SafeDICE config".into()));
        };
        let mut run = RunData::new(config, data)?;
        let nu_input =
            run.obs_dim + usize::from(cfg.terminal_handling == TerminalHandling::Absorbing);
        let disc = run.new_critic("discriminator", run.state_action_dim())?;
        let nu = run.new_critic("nu", nu_input)?;
        let policy = run.new_policy("policy")?;
        let disc_stop = if cfg.discriminator_early_stopping {
            let validation = DiscValidation::new(&run, cfg.discriminator_iterations);
            if validation.is_none() {
                tracing::warn!("discriminator early stopping needs two rows in D^N and in D^U; training the full budget");
            }
            validation
        } else {
            None
        };
        let fused = match run.device {
            candle_core::Device::Cpu => {
                Some(FusedSafedice::new(&disc, &nu, policy.mlp(), run.batch())?)
            }
            _ => None,
        };
        Ok(SafediceTrainer {
            fused,
            disc_opt: Adam::new(disc.named_vars(), cfg.lr_discriminator)?,
            nu_opt: Adam::new(nu.named_vars(), cfg.lr_nu)?,
            policy_opt: Adam::new(policy.mlp().named_vars(), config.common.lr_actor)?,
            cfg: cfg.clone(),
            run,
            disc,
            nu,
            policy,
            alpha: None,
            flow: None,
            phase_metrics: Vec::new(),
            overrides,
            disc_stop,
        })
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<SafediceTrainer, TrainError> {
        let mut t = SafediceTrainer::new(config, data)?;
        let restored = t.run.restore(bytes)?;
        restored.restore("discriminator", &mut t.disc_opt)?;
        restored.restore("nu", &mut t.nu_opt)?;
        restored.restore("policy", &mut t.policy_opt)?;
        if let Some(v) = t.disc_stop.as_mut() {
            v.rule.restore(&restored.extra_scalars);
            v.best = restored.extra_tensors();
        }
        if t.run.step >= t.cfg.discriminator_iterations {
            // Deterministic from the frozen discriminator: the same alpha-hat and rewards.
            t.finish_discriminator_phase()?;
            t.phase_metrics.clear();
        }
        Ok(t)
    }

    /// Rows per minibatch of every step.
    pub fn batch_size(&self) -> usize {
        self.run.batch()
    }

    /// alpha-hat with where it came from, once the discriminator phase is over.
    pub fn alpha_details(&self) -> Option<&AlphaHat> {
        self.alpha.as_ref()
    }

    /// The discriminator's logits `c(s, a)` on every row of `columns`, in chunks.
    /// The discriminator's logits on `rows` of `columns`.
    fn score_rows(&self, columns: &Columns, rows: &[u32]) -> Result<Vec<f32>, TrainError> {
        let mut logits = Vec::with_capacity(rows.len());
        for chunk in rows.chunks(SCORING_CHUNK) {
            let idx = Tensor::from_slice(chunk, chunk.len(), &self.run.device)?;
            let x = columns.state_action(&idx)?;
            logits.extend(self.disc.forward(&x)?.flatten_all()?.to_vec1::<f32>()?);
        }
        Ok(logits)
    }

    fn score(&self, columns: &Columns) -> Result<Vec<f32>, TrainError> {
        let mut logits = Vec::with_capacity(columns.len);
        for start in (0..columns.len).step_by(SCORING_CHUNK) {
            let rows = SCORING_CHUNK.min(columns.len - start);
            let idx = Tensor::arange(start as u32, (start + rows) as u32, &self.run.device)?;
            let x = columns.state_action(&idx)?;
            logits.extend(self.disc.forward(&x)?.flatten_all()?.to_vec1::<f32>()?);
        }
        Ok(logits)
    }

    /// The trained discriminator's logits (σ(c) = probability of "non-preferred") on every row
    /// of D^U, whatever [`SafediceOverrides`] the run uses.
    pub fn discriminator_logits_unlabeled(&self) -> Result<Vec<f32>, TrainError> {
        self.score(&self.run.u)
    }

    /// The trained discriminator's logits on every row of another dataset of the same spaces
    /// (normalised and encoded as the run's own data).
    pub fn discriminator_logits(&self, data: &Dataset) -> Result<Vec<f32>, TrainError> {
        if data.obs_dim() != self.run.obs_dim
            || !data.action_space().compatible_with(&self.run.space)
        {
            return Err(TrainError::Other("the dataset's spaces differ from the run's".into()));
        }
        let device = &self.run.device;
        self.score(&Columns::new(data, &self.run.space, self.run.normalizer.as_ref(), device)?)
    }

    /// Eq. 12's weights `w = exp(A − 1)` on every row of D^U with the current ν
    /// (`A = r + γ' ν(s') − ν(s)` on the flow table), self-normalised to mean 1 over D^U: the
    /// whole-dataset version of Eq. 37's per-batch weights (absorbing-state rows, which carry no
    /// action, are left out as there). None before the main phase.
    pub fn unlabeled_weights(&self) -> Result<Option<Vec<f64>>, TrainError> {
        let Some(advantages) = self.unlabeled_advantages()? else { return Ok(None) };
        // n · softmax(A): the constant e^{−1} cancels, as in `losses::self_normalized_weights`.
        let n = advantages.len();
        let max = advantages.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let exp: Vec<f64> = advantages.iter().map(|a| (a - max).exp()).collect();
        let total: f64 = exp.iter().sum();
        Ok(Some(exp.iter().map(|e| e * n as f64 / total).collect()))
    }

    /// `A = r + γ' ν(s') − ν(s)` (Eq. 12's log-weight plus 1) on every row of D^U with the
    /// current ν; None before the main phase. Whole-dataset weights from these can be ruled by
    /// a handful of rows far outside the minibatches' usual range; Eq. 37 normalises per batch.
    pub fn unlabeled_advantages(&self) -> Result<Option<Vec<f64>>, TrainError> {
        let Some(flow) = &self.flow else { return Ok(None) };
        let n = flow.real_rows;
        let mut advantages = Vec::with_capacity(n);
        for start in (0..n).step_by(SCORING_CHUNK) {
            let rows = SCORING_CHUNK.min(n - start);
            let s = flow.obs.narrow(0, start, rows)?;
            let s_next = flow.next_obs.narrow(0, start, rows)?;
            let values = self.nu.forward(&Tensor::cat(&[&s, &s_next], 0)?)?.squeeze(1)?;
            let (nu_s, nu_next) = (values.narrow(0, 0, rows)?, values.narrow(0, rows, rows)?);
            let reward = flow.reward.narrow(0, start, rows)?;
            let discount = flow.discount.narrow(0, start, rows)?;
            let a = ((reward + (discount * nu_next)?)? - nu_s)?;
            advantages.extend(a.to_vec1::<f32>()?.into_iter().map(f64::from));
        }
        Ok(Some(advantages))
    }

    /// Algorithm 1 step 1, one step: Eq. 9 plus the interpolated gradient penalty
    /// `λ mean((‖∇c(x̂)‖ − 1)²)` at `x̂ = u x_N + (1−u) x_U` and `x̂ = u shuffle(x_U) + (1−u) x_U`.
    fn discriminator_step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let batch = self.discriminator_draws()?;
        if self.fused.is_some() {
            return self.discriminator_step_fused(&batch, record);
        }
        let b = self.run.batch();
        let (x_n, x_u) = (&batch.x_n, &batch.x_u);
        let logits = self.disc.forward(&Tensor::cat(&[x_n, x_u], 0)?)?.squeeze(1)?;
        let (c_n, c_u) = (logits.narrow(0, 0, b)?, logits.narrow(0, b, b)?);
        let classification = discriminator_loss(&c_n, &c_u)?;
        let mut loss = classification.clone();
        let mut penalty_value = 0.0;
        if let Some((u1, u2, perm)) = &batch.penalty {
            let perm = Tensor::from_slice(perm, b, x_u.device())?;
            let shuffled = x_u.index_select(&perm, 0)?;
            let points =
                Tensor::cat(&[interpolate(x_n, x_u, u1)?, interpolate(&shuffled, x_u, u2)?], 0)?;
            let penalty = unit_gradient_penalty(&self.disc, &points)?;
            if record {
                penalty_value = super::losses::scalar(&penalty)?;
            }
            loss = (loss + (penalty * self.cfg.discriminator_gp)?)?;
        }
        let value = self.run.checked(&loss, DISC_LOSS.0, DISC_LOSS.1)?;
        self.disc_opt.minimize(&loss)?;
        self.end_discriminator_step()?;
        if !record {
            return Ok(Vec::new());
        }
        let mean_prob = |c: &Tensor| -> Result<f64, TrainError> {
            Ok(super::losses::scalar(&candle_nn::ops::sigmoid(c)?.mean_all()?)?)
        };
        let classification = super::losses::scalar(&classification)?;
        let (prob_n, prob_u) = (mean_prob(&c_n)?, mean_prob(&c_u)?);
        Ok(self.discriminator_metrics([value, classification, penalty_value, prob_n, prob_u]))
    }

    /// A discriminator minibatch: `B` rows of D^N and of D^U, and the penalty's draws.
    fn discriminator_draws(&mut self) -> Result<DiscDraws, TrainError> {
        let b = self.run.batch();
        let (idx_n, idx_u) = match &self.disc_stop {
            Some(v) => {
                let device = self.run.device.clone();
                let idx_n = pick_rows(&mut self.run.rng, &v.n.train, b, &device)?;
                (idx_n, pick_rows(&mut self.run.rng, &v.u.train, b, &device)?)
            }
            None => (self.run.sample_n()?, self.run.sample_u()?),
        };
        let x_n = self.run.non_preferred().state_action(&idx_n)?;
        let x_u = self.run.u.state_action(&idx_u)?;
        let penalty = if self.cfg.discriminator_gp > 0.0 {
            let device = self.run.device.clone();
            let u1 = uniform_column(&mut self.run.rng, b, &device)?;
            let u2 = uniform_column(&mut self.run.rng, b, &device)?;
            let mut perm: Vec<u32> = (0..b as u32).collect();
            perm.shuffle(&mut self.run.rng);
            Some((u1, u2, perm))
        } else {
            None
        };
        Ok(DiscDraws { x_n, x_u, penalty })
    }

    pub(super) fn end_discriminator_step(&mut self) -> Result<(), TrainError> {
        self.run.step += 1;
        self.measure_held_out()?;
        if self.run.step == self.cfg.discriminator_iterations {
            if let Some(v) = self.disc_stop.as_ref().filter(|v| !v.best.is_empty()) {
                self.disc.load(&v.best)?;
                tracing::info!(
                    best_step = v.rule.best_step,
                    stopped_at = v.rule.stopped_at,
                    heldout_loss = v.rule.best_loss,
                    "SafeDICE discriminator: kept the weights of its best held-out loss"
                );
            }
            self.finish_discriminator_phase()?;
        }
        Ok(())
    }

    /// With early stopping, the held-out Eq. 9 loss after this step when the rule measures it;
    /// keeps the weights of a new best.
    fn measure_held_out(&mut self) -> Result<(), TrainError> {
        let step = self.run.step;
        let Some(v) = self.disc_stop.as_ref().filter(|v| v.rule.measures_at(step)) else {
            return Ok(());
        };
        let logits_n = self.score_rows(self.run.non_preferred(), &v.n.validation)?;
        let logits_u = self.score_rows(&self.run.u, &v.u.validation)?;
        let loss = classification_loss(&logits_n, &logits_u);
        let best = match self.disc_stop.as_ref().map(|v| v.rule.best_loss) {
            Some(best) if loss < best => Some(snapshot(&self.disc)?),
            _ => None,
        };
        let v = self.disc_stop.as_mut().expect("checked above");
        v.last_loss = loss;
        if v.rule.observe(step, loss) == Decision::Improved {
            v.best = best.expect("a lower loss is an improvement");
        }
        Ok(())
    }

    /// A step after the discriminator stopped early: nothing trains; the phase still ends at
    /// its step budget, so step counts and checkpoints are those of any other run.
    fn idle_discriminator_step(&mut self) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.end_discriminator_step()?;
        Ok(std::mem::take(&mut self.phase_metrics))
    }

    /// `[loss, classification loss, penalty, mean σ(c) on D^N, mean σ(c) on D^U]` as named
    /// metrics, plus the alpha-hat metrics if this step ended the phase.
    pub(super) fn discriminator_metrics(&mut self, values: [f64; 5]) -> Vec<(&'static str, f64)> {
        let names = [
            "discriminator_loss",
            "discriminator_classification_loss",
            "discriminator_gp",
            "discriminator_prob_non_preferred_on_dn",
            "discriminator_prob_non_preferred_on_du",
        ];
        let mut metrics: Vec<(&'static str, f64)> = names.into_iter().zip(values).collect();
        if let Some(v) = &self.disc_stop {
            metrics.push(("discriminator_heldout_loss", v.last_loss));
            metrics.push(("discriminator_best_step", v.rule.best_step as f64));
            metrics
                .push(("discriminator_stopped_at", v.rule.stopped_at.map_or(-1.0, |s| s as f64)));
        }
        metrics.append(&mut self.phase_metrics);
        metrics
    }

    /// Algorithm 1 step 2 and the reward of Eq. 10 over all of D^U, with the frozen discriminator.
    fn finish_discriminator_phase(&mut self) -> Result<(), TrainError> {
        let logits = match &self.overrides.unlabeled_logits {
            Some(given) => given.clone(),
            None => self.score(&self.run.u)?,
        };
        let u = &self.run.u;
        let mut alpha = alpha_hat_from_logits(&logits, &u.episode_ids, self.cfg.alpha_hat_quantile);
        let eq15 = alpha.value;
        if let Some(a) = self.overrides.alpha {
            alpha.value = a.clamp(0.0, 1.0 - ALPHA_MARGIN);
        }
        let mut clipped = 0usize;
        let mut rewards: Vec<f64> = logits
            .iter()
            .map(|&c| {
                let (r, was_clipped) = reward_from_logit(c as f64, alpha.value);
                clipped += was_clipped as usize;
                r
            })
            .collect();
        let (mean, std) = mean_std(&rewards);
        if self.cfg.standardize_reward {
            rewards.iter_mut().for_each(|r| *r = (*r - mean) / (std + 1e-8));
        }
        if let Some(bad) = rewards.iter().position(|r| !r.is_finite()) {
            return Err(TrainError::Diverged {
                step: self.run.step,
                message: format!(
                    "the Eq. 10 reward of D^U row {bad} is not finite (alpha-hat {})",
                    alpha.value
                ),
            });
        }
        tracing::info!(
            alpha_hat = alpha.value,
            argmin_row = alpha.argmin_row,
            argmin_episode = alpha.argmin_episode,
            quantile_01 = alpha.quantile_01,
            "SafeDICE alpha-hat (Eq. 15) computed over all of D^U"
        );
        self.phase_metrics = vec![
            ("alpha_hat", alpha.value),
            ("alpha_hat_min_ratio", alpha.min_ratio),
            ("alpha_hat_argmin_row", alpha.argmin_row as f64),
            ("alpha_hat_argmin_episode", alpha.argmin_episode as f64),
            ("alpha_hat_q01_diagnostic_not_paper", alpha.quantile_01),
            ("reward_mean", mean),
            ("reward_std", std),
            ("reward_clipped_rows", clipped as f64),
        ];
        if self.overrides.alpha.is_some() {
            self.phase_metrics.push(("alpha_hat_eq15", eq15));
        }
        if self.overrides.unlabeled_logits.is_some() {
            self.phase_metrics.push(("discriminator_outputs_given", 1.0));
        }
        let rewards: Vec<f32> = rewards.iter().map(|&r| r as f32).collect();
        self.flow = Some(FlowColumns::build(u, rewards, &self.cfg)?);
        self.alpha = Some(alpha);
        Ok(())
    }

    /// Algorithm 1 steps 4-5: the ν step (Eq. 36, ν on cat(s, s', s0) in one forward) and the
    /// policy step (Eq. 37) on the same batch with the pre-update ν.
    fn main_step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        let batch = self.main_draws()?;
        if self.fused.is_some() {
            return self.main_step_fused(&batch, record);
        }
        let b = self.run.batch();
        let (s, s_next, s0) = (&batch.s, &batch.s_next, &batch.s0);
        let values = self.nu.forward(&Tensor::cat(&[s, s_next, s0], 0)?)?.squeeze(1)?;
        let (nu_s, nu_next, nu_0) =
            (values.narrow(0, 0, b)?, values.narrow(0, b, b)?, values.narrow(0, 2 * b, b)?);
        // A = r + γ' ν(s') − ν(s)
        let advantages = ((&batch.reward + (&batch.discount * nu_next)?)? - nu_s)?;
        let mut loss_nu = nu_loss(&advantages, &nu_0, self.cfg.gamma)?;
        let mut gp_value = 0.0;
        if let Some(u) = &batch.penalty_u {
            let points = Tensor::cat(&[interpolate(s0, s, u)?, interpolate(s_next, s, u)?], 0)?;
            let penalty = zero_gradient_penalty(&self.nu, &points)?;
            if record {
                gp_value = super::losses::scalar(&penalty)?;
            }
            loss_nu = (loss_nu + (penalty * self.cfg.nu_gp)?)?;
        }

        // Eq. 37's weights; rows without an action (absorbing states) get none, and the rest are
        // renormalised to mean 1.
        let mut weights = self_normalized_weights(&advantages)?;
        if let Some(has_action) = &batch.has_action {
            let mask: Vec<f32> = has_action.iter().map(|&k| k as u8 as f32).collect();
            let masked = (weights * Tensor::from_vec(mask, b, s.device())?)?;
            let mean = masked.mean_all()?;
            weights = masked.broadcast_div(&(mean + MASK_RENORM_EPS)?)?;
        }
        let log_prob = self.policy.log_prob(&batch.policy_obs, &batch.actions)?;
        let loss_pi = policy_loss(&log_prob, &weights)?;

        let nu_value = self.run.checked(&loss_nu, NU_LOSS.0, NU_LOSS.1)?;
        let pi_value = self.run.checked(&loss_pi, POLICY_LOSS.0, POLICY_LOSS.1)?;
        self.nu_opt.minimize(&loss_nu)?;
        self.policy_opt.minimize(&loss_pi)?;
        self.run.step += 1;
        if !record {
            return Ok(Vec::new());
        }
        let w = weights.to_vec1::<f32>()?;
        let adv = advantages.to_vec1::<f32>()?;
        let nu_initial = super::losses::scalar(&nu_0.mean_all()?)?;
        Ok(self.main_metrics([nu_value, gp_value, pi_value, nu_initial], &w, &adv))
    }

    /// A main-loop minibatch: `B` rows of the flow table and `B` initial states of p0 (uniform,
    /// with replacement), ν's penalty draws, and the policy's rows of D^U.
    fn main_draws(&mut self) -> Result<MainDraws, TrainError> {
        let flow = self.flow.as_ref().expect("set when the discriminator phase ends");
        let b = self.run.batch();
        let device = self.run.device.clone();
        let (rows, initial) = flow.sample_batch(&mut self.run.rng, b);
        let idx = Tensor::from_slice(&rows, b, &device)?;
        let penalty_u = if self.cfg.nu_gp > 0.0 {
            Some(uniform_column(&mut self.run.rng, b, &device)?)
        } else {
            None
        };
        let (policy_rows, has_action) = flow.policy_rows(&rows);
        let pidx = Tensor::from_vec(policy_rows, b, &device)?;
        Ok(MainDraws {
            s: flow.obs.index_select(&idx, 0)?,
            s_next: flow.next_obs.index_select(&idx, 0)?,
            s0: flow.obs.index_select(&Tensor::from_vec(initial, b, &device)?, 0)?,
            reward: flow.reward.index_select(&idx, 0)?,
            discount: flow.discount.index_select(&idx, 0)?,
            penalty_u,
            policy_obs: self.run.u.obs.index_select(&pidx, 0)?,
            actions: self.run.u.actions.select(&pidx)?,
            has_action,
        })
    }

    /// The main step's metrics from `[nu loss, nu penalty, policy loss, mean ν(s0)]`, the policy
    /// weights and the advantages.
    pub(super) fn main_metrics(
        &self,
        values: [f64; 4],
        w: &[f32],
        adv: &[f32],
    ) -> Vec<(&'static str, f64)> {
        let [nu_value, gp_value, pi_value, nu_initial] = values;
        let b = w.len();
        let ess = ess_fraction(w);
        let degenerate = ess < self.cfg.ess_warning_fraction;
        if degenerate {
            tracing::warn!(
                step = self.run.step,
                ess_fraction = ess,
                "SafeDICE weights are degenerate: a few samples carry the batch"
            );
        }
        let max_share = w.iter().fold(0f32, |m, &x| m.max(x)) as f64 / b as f64;
        vec![
            ("nu_loss", nu_value),
            ("nu_gp", gp_value),
            ("policy_loss", pi_value),
            ("alpha_hat", self.alpha.as_ref().map_or(f64::NAN, |a| a.value)),
            ("advantage_mean", adv.iter().map(|&a| a as f64).sum::<f64>() / b as f64),
            ("advantage_max", adv.iter().fold(f32::NEG_INFINITY, |m, &a| m.max(a)) as f64),
            ("nu_initial_mean", nu_initial),
            ("ess_fraction", ess),
            ("weight_max_share", max_share),
            ("weight_degenerate", degenerate as u8 as f64),
        ]
    }
}

/// An independent copy of a network's weights, by variable name.
fn snapshot(net: &Mlp) -> candle_core::Result<std::collections::HashMap<String, Tensor>> {
    net.named_vars().into_iter().map(|(name, var)| Ok((name, var.as_tensor().copy()?))).collect()
}

fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

impl Trainer for SafediceTrainer {
    fn progress(&self) -> Progress {
        let phase = if self.run.step < self.cfg.discriminator_iterations {
            "discriminator"
        } else {
            "policy"
        };
        Progress { step: self.run.step, total: self.run.total(), phase }
    }

    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.run.ensure_running()?;
        if self.run.step < self.cfg.discriminator_iterations {
            if self.disc_stop.as_ref().is_some_and(DiscValidation::stopped) {
                return self.idle_discriminator_step();
            }
            self.discriminator_step(record)
        } else {
            self.main_step(record)
        }
    }

    fn checkpoint(&self) -> Result<Vec<u8>, TrainError> {
        let mut extra = Extra::default();
        if let Some(v) = &self.disc_stop {
            extra.scalars = v.rule.to_scalars().iter().map(|(k, x)| (k.to_string(), *x)).collect();
            extra.tensors = v.best.iter().map(|(k, t)| (k.clone(), t.clone())).collect();
            extra.tensors.sort_by(|a, b| a.0.cmp(&b.0));
        }
        self.run.checkpoint_with(
            &[
                ("discriminator", &self.disc_opt),
                ("nu", &self.nu_opt),
                ("policy", &self.policy_opt),
            ],
            &extra,
        )
    }

    fn alpha_hat(&self) -> Option<f64> {
        self.alpha.as_ref().map(|a| a.value)
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        PolicyArtifact::new(self.run.policy_spec(Decoder::Single), &[&self.policy])
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With the optimal discriminator c* = d^N/(d^U + d^N), i.e. logit log(d^N/d^U), alpha-hat
    /// is min d^U/d^N (Eq. 15) minus the margin, found at the row that attains it.
    #[test]
    fn alpha_hat_of_a_known_discriminator() {
        let d_u = [0.30f64, 0.25, 0.15, 0.30];
        let d_n = [0.05f64, 0.10, 0.60, 0.25];
        let logits: Vec<f32> = d_u.iter().zip(&d_n).map(|(u, n)| (n / u).ln() as f32).collect();
        let a = alpha_hat_from_logits(&logits, &[4, 4, 9, 9], 0.0);
        assert!((a.min_ratio - 0.25).abs() < 1e-6, "{a:?}");
        assert!((a.value - (0.25 - ALPHA_MARGIN)).abs() < 1e-6);
        assert_eq!((a.argmin_row, a.argmin_episode), (2, 9));
        // Eq. 10 is then finite on every row (Appendix A.3) and most negative at the argmin.
        let rewards: Vec<f64> = logits
            .iter()
            .map(|&c| reward_from_logit(c as f64, a.value))
            .map(|(r, clipped)| {
                assert!(!clipped);
                r
            })
            .collect();
        assert!(rewards.iter().all(|r| r.is_finite()));
        let worst =
            rewards
                .iter()
                .enumerate()
                .fold((0, f64::INFINITY), |b, (i, &r)| if r < b.1 { (i, r) } else { b });
        assert_eq!(worst.0, 2);
    }

    /// Eq. 10 in its logit form equals the paper's sigmoid form.
    #[test]
    fn reward_logit_form_equals_eq_10() {
        for (c, alpha) in [(-2.0f64, 0.3), (0.5, 0.1), (1.2, 0.2), (-0.3, 0.6)] {
            let sigma = 1.0 / (1.0 + (-c).exp());
            let paper = ((1.0 - (1.0 + alpha) * sigma) / ((1.0 - alpha) * (1.0 - sigma))).ln();
            let (ours, clipped) = reward_from_logit(c, alpha);
            assert!(!clipped);
            assert!((ours - paper).abs() < 1e-10, "c={c}: {ours} vs {paper}");
        }
        assert!(reward_from_logit(3.0, 0.5).1, "1 − α e^c < 0 is floored and reported");
    }

    /// A two-action task on one state: preferred episodes take action 0, non-preferred ones
    /// action 1. D^U: 6 preferred + 4 non-preferred episodes of 4 steps (α = 0.4 of the
    /// transitions); D^N: 3 non-preferred episodes. Returns the data and D^U's true flags.
    fn one_state_task() -> (TrainingData, Vec<bool>) {
        use crate::data::{ActionSpace, Actions, DatasetParts};
        let episodes = |kinds: &[bool]| {
            let len = 4;
            let n = kinds.len() * len;
            let actions = kinds.iter().flat_map(|&np| vec![np as u32; len]).collect();
            Dataset::new(DatasetParts {
                obs_dim: 1,
                action_space: ActionSpace::Discrete { n: 2 },
                observations: vec![0.5; n],
                actions: Actions::Discrete(actions),
                next_observations: vec![0.5; n],
                terminals: vec![false; n],
                episode_ids: (0..n).map(|i| (i / len) as u32).collect(),
                rewards: None,
                costs: None,
            })
            .unwrap()
        };
        let kinds = [false, true, false, false, true, false, true, false, false, true];
        let flags = kinds.iter().flat_map(|&np| [np; 4]).collect();
        let data = TrainingData {
            unlabeled: std::sync::Arc::new(episodes(&kinds)),
            non_preferred: Some(std::sync::Arc::new(episodes(&[true; 3]))),
        };
        (data, flags)
    }

    fn tiny_config() -> ResolvedConfig {
        super::super::resolve_config(
            super::super::Algorithm::Safedice,
            &serde_json::json!({
                "seed": 3, "batch_size": 8, "hidden_sizes": [8, 8], "iterations": 3,
                "discriminator_iterations": 2, "standardize_reward": false,
            }),
        )
        .unwrap()
    }

    /// Steps through the discriminator phase; returns the scalars of the step that ended it.
    fn finish_phase(t: &mut SafediceTrainer) -> Vec<(&'static str, f64)> {
        let mut last = Vec::new();
        while t.progress().phase == "discriminator" {
            last = t.step(true).unwrap();
        }
        last
    }

    fn metric(scalars: &[(&'static str, f64)], name: &str) -> f64 {
        scalars.iter().find(|(n, _)| *n == name).map(|&(_, v)| v).unwrap_or(f64::NAN)
    }

    /// Oracle logits make Eq. 15 return the true share (minus its margin), and the weights of
    /// Eq. 12 on non-preferred rows are the closed form: every row has the same state, so ν
    /// cancels and `w_np / w_p = exp(r_np − r_p)` ≈ 1e-5/α, i.e. practically 0.
    #[test]
    fn oracle_logits_give_the_true_alpha_and_near_zero_weight_on_non_preferred_rows() {
        let (data, flags) = one_state_task();
        let overrides =
            SafediceOverrides { unlabeled_logits: Some(oracle_logits(&flags)), alpha: None };
        let mut t = SafediceTrainer::with_overrides(&tiny_config(), &data, overrides).unwrap();
        assert!(t.unlabeled_weights().unwrap().is_none(), "no weights before the main phase");
        let scalars = finish_phase(&mut t);
        let alpha = 0.4 - ALPHA_MARGIN;
        assert!((metric(&scalars, "alpha_hat") - alpha).abs() < 1e-6, "{scalars:?}");
        assert_eq!(metric(&scalars, "reward_clipped_rows"), 0.0);
        assert_eq!(metric(&scalars, "discriminator_outputs_given"), 1.0);
        for _ in 0..3 {
            t.step(false).unwrap();
        }
        let w = t.unlabeled_weights().unwrap().unwrap();
        assert!((w.iter().sum::<f64>() / w.len() as f64 - 1.0).abs() < 1e-9, "mean 1");
        // The α the trainer used (Eq. 15 on f32 logits): `1 − α̂ e^c` ≈ 2.5e-5 on non-preferred
        // rows is sensitive to its last digits.
        let used = t.alpha_hat().unwrap();
        let logits = oracle_logits(&flags);
        let reward = |row: usize| reward_from_logit(logits[row] as f64, used).0;
        let (np, p) =
            (flags.iter().position(|&f| f).unwrap(), flags.iter().position(|&f| !f).unwrap());
        let expected = (reward(np) - reward(p)).exp();
        assert!(expected < 1e-4, "{expected}");
        assert!(((w[np] / w[p]) / expected - 1.0).abs() < 1e-3, "{} vs {expected}", w[np] / w[p]);
        let share: f64 = w.iter().zip(&flags).filter(|(_, &f)| f).map(|(w, _)| w).sum::<f64>()
            / w.iter().sum::<f64>();
        assert!(share < 1e-4, "weight share on non-preferred rows {share}");
    }

    /// An α override is the α the trainer uses: the recorded `alpha_hat` (at the end of the
    /// discriminator phase and in every main step) and [`Trainer::alpha_hat`], with Eq. 15's own
    /// value kept as `alpha_hat_eq15`.
    #[test]
    fn alpha_override_is_the_alpha_the_trainer_uses() {
        let (data, _) = one_state_task();
        let overrides = SafediceOverrides { alpha: Some(0.4), unlabeled_logits: None };
        let mut t = SafediceTrainer::with_overrides(&tiny_config(), &data, overrides).unwrap();
        let scalars = finish_phase(&mut t);
        assert_eq!(metric(&scalars, "alpha_hat"), 0.4);
        assert!(metric(&scalars, "alpha_hat_eq15").is_finite(), "{scalars:?}");
        assert_eq!(t.alpha_hat(), Some(0.4));
        let main = t.step(true).unwrap();
        assert_eq!(metric(&main, "alpha_hat"), 0.4);
        // The trained discriminator is untouched: the same seed without overrides trains the
        // same one (the overrides act after it).
        let mut plain = SafediceTrainer::new(&tiny_config(), &data).unwrap();
        finish_phase(&mut plain);
        assert_eq!(
            plain.discriminator_logits_unlabeled().unwrap(),
            t.discriminator_logits_unlabeled().unwrap()
        );
        assert_eq!(
            t.discriminator_logits(&data.unlabeled).unwrap(),
            t.discriminator_logits_unlabeled().unwrap()
        );
        let bad = SafediceOverrides { alpha: Some(1.0), unlabeled_logits: None };
        assert!(SafediceTrainer::with_overrides(&tiny_config(), &data, bad).is_err());
        let bad = SafediceOverrides { alpha: None, unlabeled_logits: Some(vec![0.0; 3]) };
        assert!(SafediceTrainer::with_overrides(&tiny_config(), &data, bad).is_err());
    }

    #[test]
    fn nu_loss_is_log_mean_exp_plus_initial_term() {
        let dev = candle_core::Device::Cpu;
        let a = Tensor::new(&[0.5f32, -1.0, 2.0, 100.0], &dev).unwrap();
        let nu0 = Tensor::new(&[1.0f32, 3.0], &dev).unwrap();
        let got = super::super::losses::scalar(&nu_loss(&a, &nu0, 0.99).unwrap()).unwrap();
        let lme = 100.0 + ((0.5f64 - 100.0).exp() + (-101f64).exp() + (-98f64).exp() + 1.0).ln()
            - 4f64.ln();
        assert!((got - (lme + 0.01 * 2.0)).abs() < 1e-4, "{got} vs {}", lme + 0.02);
    }
}
