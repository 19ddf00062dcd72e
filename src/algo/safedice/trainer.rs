//! The reference trainer: Algorithm 1 in candle, every loss from [`super::objectives`] and
//! differentiated by candle autograd. On the CPU the two hot loops run on the fused engine
//! instead ([`super::fused`], wired in by [`super::fused_steps`]); both engines take their
//! minibatch from `discriminator_draws` and `main_draws` below, so they consume the run's random
//! numbers identically.

use candle_core::Tensor;
use rand::seq::SliceRandom;
use rand::Rng;

use super::ablation::SafediceOverrides;
use super::draws::{DiscDraws, FlowColumns, MainDraws};
use super::folds::CrossFit;
use super::fused::FusedSafedice;
use super::heldout::HeldOut;
use super::objectives::{
    discriminator_loss, nu_loss, policy_loss, AlphaHat, DISC_LOSS, MASK_RENORM_EPS, NU_LOSS,
    POLICY_LOSS,
};
use crate::algo::checkpoint::Extra;
use crate::algo::columns::{uniform_column, Columns};
use crate::algo::discriminator_stop::{classification_loss, Decision, EarlyStop, Holdout};
use crate::algo::fused_policy::FusedPolicyStep;
use crate::algo::hyperparams::{AlgorithmConfig, AlphaEstimator, SafediceConfig};
use crate::algo::losses::{
    ess_fraction, interpolate, scalar, self_normalized_weights, unit_gradient_penalty,
    zero_gradient_penalty,
};
use crate::algo::mlp::Mlp;
use crate::algo::optim::Adam;
use crate::algo::policy::{Decoder, PolicyArtifact, PolicyNet};
use crate::algo::run::RunData;
use crate::algo::safety::{self, SafetySpec};
use crate::algo::{Progress, ResolvedConfig, TerminalHandling, TrainError, Trainer, TrainingData};
use crate::data::Dataset;

/// Rows per forward pass when scoring all of D^U.
pub(super) const SCORING_CHUNK: usize = 8192;

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
    pub(super) alpha: Option<AlphaHat>,
    pub(super) flow: Option<FlowColumns>,
    /// Metrics of the alpha-hat/reward computation, reported with the step that made them.
    pub(super) phase_metrics: Vec<(&'static str, f64)>,
    /// The fused CPU engine for both hot loops (None on other devices: the candle path runs).
    pub(super) fused: Option<FusedSafedice>,
    /// Ablation replacements of alpha-hat and the discriminator's outputs (none by default).
    pub(super) overrides: SafediceOverrides,
    /// With `discriminator_early_stopping` or the `bbe` estimator: the held-out rows (and the
    /// stopping rule).
    pub(super) disc_stop: Option<DiscValidation>,
    /// Set when the weighting falls back to uniform (`uniform_fallback`): the main loop is BC.
    pub(super) uniform: Option<UniformWeights>,
    /// The held-out statistics alpha-hat came from (`bbe`), once the phase is over.
    pub(super) heldout: Option<HeldOut>,
    /// With `cross_fit`: D^U's folds (and D^N's) and the finished parts' scores.
    pub(super) cross_fit: Option<CrossFit>,
}

/// The main loop with uniform weights: BC's step, since the held-out data cannot tell D^N from
/// D^U (`uniform_fallback`).
pub(super) struct UniformWeights {
    pub(super) reason: String,
    pub(super) fused: Option<FusedPolicyStep>,
}

/// Held-out rows of D^N and D^U: for early stopping of the discriminator
/// ([`crate::algo::discriminator_stop`]) and for the `bbe` estimator of alpha-hat.
pub(super) struct DiscValidation {
    pub(super) n: Holdout,
    pub(super) u: Holdout,
    /// Whether the stopping rule runs (`discriminator_early_stopping`).
    early_stopping: bool,
    pub(super) rule: EarlyStop,
    /// The discriminator's weights at the best held-out loss so far, by variable name.
    pub(super) best: std::collections::HashMap<String, Tensor>,
    pub(super) last_loss: f64,
}

impl DiscValidation {
    /// Held-out rows of D^N and D^U chosen from the run's seed (a stream of its own, so the
    /// training draws are those of a run without early stopping); None when a set is a single row.
    fn new(run: &RunData, budget: u64, early_stopping: bool) -> Option<DiscValidation> {
        let seed = run.config.seed();
        let n = Holdout::split(&run.non_preferred().episode_ids, seed ^ 0x5afe_d1ce_0000_0001)?;
        let u = Holdout::split(&run.u.episode_ids, seed ^ 0x5afe_d1ce_0000_0002)?;
        let best = std::collections::HashMap::new();
        let rule = EarlyStop::new(budget);
        Some(DiscValidation { n, u, early_stopping, rule, best, last_loss: f64::NAN })
    }

    fn stopped(&self) -> bool {
        self.early_stopping && self.rule.stopped_at.is_some()
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
        let bbe = cfg.alpha_hat_estimator == AlphaEstimator::Bbe;
        let disc_stop = if cfg.discriminator_early_stopping || bbe {
            let early = cfg.discriminator_early_stopping;
            let validation = DiscValidation::new(&run, cfg.discriminator_iterations, early);
            if validation.is_none() {
                tracing::warn!("held-out rows need two rows in D^N and in D^U: no early stopping, and alpha-hat from the paper's minimum");
            }
            validation
        } else {
            None
        };
        let k = cfg.cross_fit_folds as usize;
        let cross_fit = match &disc_stop {
            Some(_) if bbe && cfg.cross_fit && cfg.discriminator_iterations >= k as u64 => {
                let labeled =
                    (cfg.cross_fit_labeled || k > 2).then(|| &run.non_preferred().episode_ids[..]);
                CrossFit::new(k, &run.u.episode_ids, labeled, run.config.seed())
            }
            _ => None,
        };
        if bbe && cfg.cross_fit && disc_stop.is_some() && cross_fit.is_none() {
            tracing::warn!(
                folds = k,
                discriminator_iterations = cfg.discriminator_iterations,
                unlabeled_rows = run.u.len,
                "cross-fitting needs at least as many discriminator steps and rows of D^U as folds: one discriminator scores D^U"
            );
        }
        let fused = match run.device {
            candle_core::Device::Cpu => {
                Some(FusedSafedice::new(&disc, &nu, policy.mlp(), run.batch(), &run.threads)?)
            }
            _ => None,
        };
        let mut trainer = SafediceTrainer {
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
            uniform: None,
            heldout: None,
            cross_fit,
        };
        trainer.enter_part(0);
        Ok(trainer)
    }

    pub fn resume(
        config: &ResolvedConfig,
        data: &TrainingData,
        bytes: &[u8],
    ) -> Result<SafediceTrainer, TrainError> {
        let mut t = SafediceTrainer::new(config, data)?;
        let restored = t.run.restore(bytes)?;
        // The optimisers carry the parameters: restored first, so the phase end below reads
        // the checkpoint's discriminator.
        restored.restore("discriminator", &mut t.disc_opt)?;
        restored.restore("nu", &mut t.nu_opt)?;
        restored.restore("policy", &mut t.policy_opt)?;
        t.enter_part(t.run.step);
        let mut tensors = restored.extra_tensors();
        if let Some(cf) = t.cross_fit.as_mut() {
            let held_out = t.disc_stop.as_ref().map_or(&[][..], |v| &v.n.validation[..]);
            cf.restore(&mut tensors, held_out)?;
        }
        t.check_finished_parts()?;
        if let Some(v) = t.disc_stop.as_mut() {
            v.rule.restore(&restored.extra_scalars);
            v.best = tensors;
        }
        if t.run.step >= t.cfg.discriminator_iterations {
            // Deterministic from the frozen discriminator: the same alpha-hat and rewards.
            t.finish_discriminator_phase()?;
            t.phase_metrics.clear();
            if t.uniform.is_some() {
                // The fallback's optimiser has BC's learning rate; its state is the checkpoint's.
                t.policy_opt = Adam::new(t.policy.mlp().named_vars(), t.fallback_lr_actor())?;
                restored.restore("policy", &mut t.policy_opt)?;
            }
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

    /// The discriminator's logits `c(s, a)` on `rows` of `columns`.
    pub(super) fn score_rows(
        &self,
        columns: &Columns,
        rows: &[u32],
    ) -> Result<Vec<f32>, TrainError> {
        logits_of(&self.disc, columns, rows)
    }

    /// The discriminator's logits on every row of `columns`.
    pub(super) fn score(&self, columns: &Columns) -> Result<Vec<f32>, TrainError> {
        let every_row: Vec<u32> = (0..columns.len as u32).collect();
        self.score_rows(columns, &every_row)
    }

    /// The trained discriminator's logits (σ(c) = probability of "non-preferred") on every row
    /// of D^U, whatever [`SafediceOverrides`] the run uses.
    pub fn discriminator_logits_unlabeled(&self) -> Result<Vec<f32>, TrainError> {
        self.score(&self.run.u)
    }

    /// The trained discriminator's logits on every row of another dataset of the same spaces
    /// (normalised and encoded as the run's own data).
    pub fn discriminator_logits(&self, data: &Dataset) -> Result<Vec<f32>, TrainError> {
        self.score(&self.columns_of(data)?)
    }

    /// Another dataset of the run's spaces, normalised and encoded as the run's own data.
    pub(super) fn columns_of(&self, data: &Dataset) -> Result<Columns, TrainError> {
        if data.obs_dim() != self.run.obs_dim
            || !data.action_space().compatible_with(&self.run.space)
        {
            return Err(TrainError::Other("the dataset's spaces differ from the run's".into()));
        }
        let device = &self.run.device;
        Ok(Columns::new(data, &self.run.space, self.run.normalizer.as_ref(), device)?)
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
                penalty_value = scalar(&penalty)?;
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
            Ok(scalar(&candle_nn::ops::sigmoid(c)?.mean_all()?)?)
        };
        let classification = scalar(&classification)?;
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
        if self.ends_a_part(self.run.step) {
            self.end_part()?;
        }
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
            if self.uniform.is_some() {
                self.restart_policy_as_bc()?;
            }
        }
        Ok(())
    }

    /// With early stopping, the held-out Eq. 9 loss after this step when the rule measures it;
    /// keeps the weights of a new best.
    fn measure_held_out(&mut self) -> Result<(), TrainError> {
        let step = self.steps_into_part(self.run.step);
        let measures = |v: &&DiscValidation| v.early_stopping && v.rule.measures_at(step);
        let Some(v) = self.disc_stop.as_ref().filter(measures) else {
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
    /// Its metrics say where the rule stopped, so the phase's last recorded values (what a
    /// job's page and the benchmarks read) name the stop rather than the last trained step's
    /// "not stopped".
    fn idle_discriminator_step(&mut self) -> Result<Vec<(&'static str, f64)>, TrainError> {
        self.end_discriminator_step()?;
        let mut metrics = self.stop_metrics();
        metrics.append(&mut self.phase_metrics);
        Ok(metrics)
    }

    /// The early-stopping rule's state as metrics (none without early stopping).
    fn stop_metrics(&self) -> Vec<(&'static str, f64)> {
        let Some(v) = self.disc_stop.as_ref().filter(|v| v.early_stopping) else {
            return Vec::new();
        };
        vec![
            ("discriminator_heldout_loss", v.last_loss),
            ("discriminator_best_step", v.rule.best_step as f64),
            ("discriminator_stopped_at", v.rule.stopped_at.map_or(-1.0, |s| s as f64)),
        ]
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
        metrics.extend(self.stop_metrics());
        metrics.append(&mut self.phase_metrics);
        metrics
    }

    /// Algorithm 1 steps 4-5: the ν step (Eq. 36, ν on cat(s, s', s0) in one forward) and the
    /// policy step (Eq. 37) on the same batch with the pre-update ν.
    fn main_step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError> {
        if self.uniform.is_some() {
            return self.uniform_step(record);
        }
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
                gp_value = scalar(&penalty)?;
            }
            loss_nu = (loss_nu + (penalty * self.cfg.nu_gp)?)?;
        }

        // Eq. 37's weights, with `policy_uniform_share` of them spread evenly
        // (`objectives::with_uniform_share`); rows without an action (absorbing states) get none,
        // and the rest are renormalised to mean 1.
        let mut weights = self_normalized_weights(&advantages)?;
        let share = self.cfg.policy_uniform_share;
        if share > 0.0 {
            weights = weights.affine(1.0 - share, share)?;
        }
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
        let nu_initial = scalar(&nu_0.mean_all()?)?;
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

impl SafediceTrainer {
    /// The safety head the policy file carries: the discriminator as Eq. 10 read it
    /// (recalibrated when the run recalibrated it; with cross-fitting, every part's
    /// discriminator) and D^U's reference states.
    fn safety_head(&self) -> Result<(SafetySpec, Vec<(String, Tensor)>), TrainError> {
        let heldout = self.heldout.as_ref();
        let recalibration = heldout
            .and_then(|h| h.calibration)
            .map_or(safety::Recalibration::NONE, |(logit_scale, logit_shift)| {
                safety::Recalibration { logit_scale, logit_shift }
            });
        let own = safety::Member { weights: snapshot(&self.disc)?, recalibration };
        let members: Vec<safety::Member> =
            std::iter::once(own).chain(self.finished_part_members()).collect();
        let observations = self.run.u.obs.flatten_all()?.to_vec1::<f32>()?;
        safety::build(
            &members,
            self.run.hidden(),
            heldout.map(|h| h.auc.value),
            &observations,
            self.run.obs_dim,
        )
    }
}

/// A discriminator's logits on `rows` of `columns`, in chunks.
pub(super) fn logits_of(
    net: &Mlp,
    columns: &Columns,
    rows: &[u32],
) -> Result<Vec<f32>, TrainError> {
    let mut logits = Vec::with_capacity(rows.len());
    for chunk in rows.chunks(SCORING_CHUNK) {
        let idx = Tensor::from_slice(chunk, chunk.len(), columns.obs.device())?;
        let x = columns.state_action(&idx)?;
        logits.extend(net.forward(&x)?.flatten_all()?.to_vec1::<f32>()?);
    }
    Ok(logits)
}

/// An independent copy of a network's weights, by variable name.
pub(super) fn snapshot(
    net: &Mlp,
) -> candle_core::Result<std::collections::HashMap<String, Tensor>> {
    net.named_vars().into_iter().map(|(name, var)| Ok((name, var.as_tensor().copy()?))).collect()
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
            extra.tensors.extend(self.cross_fit.iter().flat_map(CrossFit::checkpoint_tensors));
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

    fn alpha_hat_detail(&self) -> Option<String> {
        self.describe_alpha_hat()
    }

    fn uniform_weighting_reason(&self) -> Option<String> {
        self.uniform.as_ref().map(|u| u.reason.clone())
    }

    fn export_policy(&self) -> Result<PolicyArtifact, TrainError> {
        let mut spec = self.run.policy_spec(Decoder::Single);
        let (safety, tensors) = self.safety_head()?;
        spec.safety = Some(safety);
        PolicyArtifact::with_tensors(spec, &[&self.policy], tensors)
    }

    fn use_candle_autograd(&mut self) {
        self.fused = None;
        if let Some(u) = self.uniform.as_mut() {
            u.fused = None;
        }
    }
}
