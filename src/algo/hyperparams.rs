//! A training run's hyperparameters: presets (`service`, `paper`, `authors-code`), user
//! overrides, validation. (The service's own settings are `crate::config`.)
//!
//! A user's `config` object is a flat JSON map: `"preset"` plus any knob of the chosen algorithm.
//! [`resolve_config`] starts from the preset, overlays the user's keys, rejects unknown keys and
//! out-of-range values with a message naming the key, and returns a [`ResolvedConfig`] whose
//! JSON (flat, with "algorithm" and "preset") is what the API shows and what a resume reads back.
//!
//! ## Presets
//! - `paper`: the paper's Table 2/4 values (every learning rate 3e-4, discriminator gradient
//!   penalty 0.1, no nu penalty, batch 512, 1M iterations) and the authors' faithful behaviour
//!   (no terminal handling, raw reward, raw observations).
//! - `authors-code`: what the authors' published code runs (discriminator and nu lr 1e-4, actor
//!   lr 1e-5, discriminator GP 10, nu GP 1e-6, 100k discriminator steps + 1M iterations).
//! - `service` (the default when no preset is given): the authors' code's learning rates and
//!   penalties, plus the robustness options our measurements favoured, and a run length that fits
//!   a service (100k iterations). See [`SafediceConfig::service`] for the measurements.
//!
//! The baselines are not in the authors' repository, so for them `authors-code` equals `paper`.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::Algorithm;

mod safedice;
use safedice::check_alpha_estimator;
pub use safedice::{
    AlphaEstimator, AlphaHatPoint, BbeUnlabeledRows, SafediceConfig, TerminalHandling,
    UndefinedReward,
};

/// A config the user got wrong; `message` names the key and what is allowed.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct HyperparamError {
    pub key: String,
    pub message: String,
}

impl HyperparamError {
    fn new(key: &str, message: impl Into<String>) -> Self {
        HyperparamError { key: key.to_string(), message: message.into() }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    Service,
    Paper,
    AuthorsCode,
}

impl Preset {
    pub const ALL: [Preset; 3] = [Preset::Service, Preset::Paper, Preset::AuthorsCode];
}

/// What DExperts' continuous objective (Eq. 45) does with D^N's actions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NonPreferredTerm {
    /// `α E_N[log π(a|s)]`, Eq. 45 as written: unbounded below, so minimising it can push D^N's
    /// actions' likelihood down without end, dragging the policy off D^U's actions too. The
    /// default of a config without it.
    #[default]
    LogLikelihood,
    /// `α E_N[k(a|s)]`, with `k = exp(−½ Σ_j z_j²)` the D^N action's Gaussian kernel under the
    /// policy (its density relative to the policy's mode, in (0, 1]), moving the mean only:
    /// the push fades once a D^N action is a few standard deviations from the mean.
    Kernel,
}

/// How PPL turns its learned reward `R_θ(s, a)` into behaviour-cloning weights.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PplWeight {
    /// `R_θ(s, a)` itself (Eq. 41 literally; negative weights push log-probabilities down).
    Raw,
    /// `σ(R_θ(s, a))`, in (0, 1).
    Sigmoid,
}

/// Knobs every algorithm has.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CommonConfig {
    pub preset: Preset,
    /// Seed of every random choice of the run (initialisation, minibatches, interpolation).
    pub seed: u64,
    /// Policy-learning iterations (the main loop; pretraining phases come on top).
    pub iterations: u64,
    /// Minibatch size of every step (paper: 512).
    pub batch_size: usize,
    /// Hidden layer widths of every network (paper: [256, 256]).
    pub hidden_sizes: Vec<usize>,
    /// Adam learning rate of the policy (paper 3e-4, authors' code 1e-5).
    pub lr_actor: f64,
    /// Standardise observations with D^U's mean and std (+1e-3), as DemoDICE does. The stats
    /// travel in the policy artefact.
    pub normalize_observations: bool,
    /// Threads of one training step: the fused engine splits every batch's rows into this many
    /// parts and sums their gradients in a fixed order. The count is part of the arithmetic,
    /// like the seed (the same seed gives the same weights at the same `threads`, resumed or
    /// taken over on any machine); a worker runs the parts on at most its `--job-threads`.
    /// Unset, a job gets the server's `--job-threads`; stored configs without it ran on one.
    #[serde(default = "one_thread")]
    pub threads: usize,
}

/// The largest seed the API takes: seeds are described as 64-bit signed integers (`int64`), the
/// widest integer every JSON client and schema tool agrees on.
pub const MAX_SEED: u64 = i64::MAX as u64;

/// The most threads a job may ask for.
pub const MAX_JOB_THREADS: usize = 64;

fn one_thread() -> usize {
    1
}

/// DWBC's knobs (Eq. 38, 39).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DwbcConfig {
    /// η of Eq. 38: the assumed share of non-preferred samples in D^U.
    pub eta: f64,
    pub lr_discriminator: f64,
    /// Interpolated gradient penalty of the discriminator (paper Table 2: 0.1).
    pub discriminator_gp: f64,
}

/// PPL's knobs (Eq. 40, 41).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PplConfig {
    /// Bradley–Terry reward-model steps before policy learning (default 10% of `iterations`).
    pub reward_model_iterations: u64,
    pub lr_reward_model: f64,
    /// Trajectory pairs (τ_i ∈ D^U, τ_j ∈ D^N) per reward-model step.
    pub pairs_per_batch: usize,
    /// Eq. 40 sums R over whole trajectories; we sum over random segments of at most this many
    /// steps so a step's cost stays bounded (episodes shorter than this are used whole).
    pub segment_length: usize,
    pub ppl_weight: PplWeight,
}

/// DExperts' knobs (Eq. 44 for discrete actions, Eq. 45 for continuous ones).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DexpertsConfig {
    /// α of Eq. 44/45: how strongly the non-preferred expert is subtracted.
    pub alpha: f64,
    /// Continuous actions: Eq. 45's D^N term as written or bounded (discrete actions decode
    /// with Eq. 44 and ignore it).
    #[serde(default)]
    pub non_preferred_term: NonPreferredTerm,
}

/// BC has no knobs of its own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BcConfig {}

/// The algorithm-specific part, tagged by "algorithm" in the flat JSON.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "algorithm", rename_all = "lowercase")]
pub enum AlgorithmConfig {
    Safedice(SafediceConfig),
    Bc(BcConfig),
    Dwbc(DwbcConfig),
    Ppl(PplConfig),
    Dexperts(DexpertsConfig),
}

/// A validated configuration with every default filled in; its JSON is flat.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResolvedConfig {
    #[serde(flatten)]
    pub common: CommonConfig,
    #[serde(flatten)]
    pub specific: AlgorithmConfig,
}

impl ResolvedConfig {
    pub fn algorithm(&self) -> Algorithm {
        match self.specific {
            AlgorithmConfig::Safedice(_) => Algorithm::Safedice,
            AlgorithmConfig::Bc(_) => Algorithm::Bc,
            AlgorithmConfig::Dwbc(_) => Algorithm::Dwbc,
            AlgorithmConfig::Ppl(_) => Algorithm::Ppl,
            AlgorithmConfig::Dexperts(_) => Algorithm::Dexperts,
        }
    }

    pub fn seed(&self) -> u64 {
        self.common.seed
    }

    /// All steps of the run, every phase included.
    pub fn total_steps(&self) -> u64 {
        self.pretraining_steps() + self.common.iterations
    }

    /// Steps of the phase before policy learning (discriminator or reward model), 0 if none.
    pub fn pretraining_steps(&self) -> u64 {
        match &self.specific {
            AlgorithmConfig::Safedice(s) => s.discriminator_iterations,
            AlgorithmConfig::Ppl(p) => p.reward_model_iterations,
            _ => 0,
        }
    }

    /// The defaults of `preset` for `algorithm`.
    pub fn preset(algorithm: Algorithm, preset: Preset) -> ResolvedConfig {
        let paper_like = preset != Preset::Service;
        let common = CommonConfig {
            preset,
            seed: 0,
            iterations: if paper_like { 1_000_000 } else { 100_000 },
            batch_size: 512,
            hidden_sizes: vec![256, 256],
            lr_actor: 3e-4,
            normalize_observations: !paper_like,
            threads: 1,
        };
        let phase = pretraining_default(algorithm, preset, common.iterations);
        let (common, specific) = match algorithm {
            Algorithm::Safedice => {
                let s = match preset {
                    Preset::Paper => SafediceConfig::paper(phase),
                    Preset::AuthorsCode => SafediceConfig::authors_code(),
                    Preset::Service => SafediceConfig::service(phase),
                };
                let lr_actor = match preset {
                    Preset::Paper => 3e-4,
                    Preset::AuthorsCode => 1e-5,
                    Preset::Service => SafediceConfig::SERVICE_LR_ACTOR,
                };
                (CommonConfig { lr_actor, ..common }, AlgorithmConfig::Safedice(s))
            }
            Algorithm::Bc => (common, AlgorithmConfig::Bc(BcConfig {})),
            Algorithm::Dwbc => (
                common,
                AlgorithmConfig::Dwbc(DwbcConfig {
                    eta: 0.2,
                    lr_discriminator: 3e-4,
                    discriminator_gp: 0.1,
                }),
            ),
            Algorithm::Ppl => (
                common,
                AlgorithmConfig::Ppl(PplConfig {
                    reward_model_iterations: phase,
                    lr_reward_model: 3e-4,
                    pairs_per_batch: 16,
                    segment_length: 32,
                    ppl_weight: if paper_like { PplWeight::Raw } else { PplWeight::Sigmoid },
                }),
            ),
            Algorithm::Dexperts => {
                let non_preferred_term = match preset {
                    Preset::Service => NonPreferredTerm::Kernel,
                    Preset::Paper | Preset::AuthorsCode => NonPreferredTerm::LogLikelihood,
                };
                (
                    common,
                    AlgorithmConfig::Dexperts(DexpertsConfig { alpha: 0.2, non_preferred_term }),
                )
            }
        };
        ResolvedConfig { common, specific }
    }

    fn validate(&self) -> Result<(), HyperparamError> {
        let c = &self.common;
        in_range("iterations", c.iterations as f64, 1.0, 1e8)?;
        in_range("batch_size", c.batch_size as f64, 1.0, 65536.0)?;
        in_range("hidden_sizes", c.hidden_sizes.len() as f64, 1.0, 8.0).map_err(|_| {
            HyperparamError::new(
                "hidden_sizes",
                "config.hidden_sizes: must list 1 to 8 layer widths",
            )
        })?;
        for &width in &c.hidden_sizes {
            in_range("hidden_sizes", width as f64, 1.0, 4096.0)?;
        }
        learning_rate("lr_actor", c.lr_actor)?;
        in_range("threads", c.threads as f64, 1.0, MAX_JOB_THREADS as f64)?;
        if c.seed > MAX_SEED {
            return Err(HyperparamError::new(
                "seed",
                format!(
                    "config.seed: {} is above {}, the largest 64-bit signed integer (seeds are int64)",
                    c.seed,
                    MAX_SEED
                ),
            ));
        }
        match &self.specific {
            AlgorithmConfig::Safedice(s) => {
                in_range("discriminator_iterations", s.discriminator_iterations as f64, 1.0, 1e8)?;
                learning_rate("lr_discriminator", s.lr_discriminator)?;
                learning_rate("lr_nu", s.lr_nu)?;
                in_range("discriminator_gp", s.discriminator_gp, 0.0, 1e6)?;
                in_range("nu_gp", s.nu_gp, 0.0, 1e6)?;
                in_range("gamma", s.gamma, 0.0, 0.9999)?;
                in_range("alpha_hat_quantile", s.alpha_hat_quantile, 0.0, 0.5)?;
                in_range("ess_warning_fraction", s.ess_warning_fraction, 0.0, 1.0)?;
                in_range("reward_scale", s.reward_scale, 0.01, 100.0)?;
                check_alpha_estimator(s)?;
            }
            AlgorithmConfig::Bc(_) => {}
            AlgorithmConfig::Dwbc(d) => {
                in_range("eta", d.eta, 0.0, 0.99)?;
                learning_rate("lr_discriminator", d.lr_discriminator)?;
                in_range("discriminator_gp", d.discriminator_gp, 0.0, 1e6)?;
            }
            AlgorithmConfig::Ppl(p) => {
                in_range("reward_model_iterations", p.reward_model_iterations as f64, 1.0, 1e8)?;
                learning_rate("lr_reward_model", p.lr_reward_model)?;
                in_range("pairs_per_batch", p.pairs_per_batch as f64, 1.0, 4096.0)?;
                in_range("segment_length", p.segment_length as f64, 1.0, 100_000.0)?;
            }
            AlgorithmConfig::Dexperts(d) => in_range("alpha", d.alpha, 0.0, 10.0)?,
        }
        Ok(())
    }
}

fn in_range(key: &str, value: f64, low: f64, high: f64) -> Result<(), HyperparamError> {
    if value.is_finite() && value >= low && value <= high {
        Ok(())
    } else {
        Err(HyperparamError::new(
            key,
            format!("config.{key}: must be between {low} and {high}, got {value}"),
        ))
    }
}

fn learning_rate(key: &str, value: f64) -> Result<(), HyperparamError> {
    if value.is_finite() && value > 0.0 && value <= 1.0 {
        Ok(())
    } else {
        Err(HyperparamError::new(
            key,
            format!("config.{key}: must be a learning rate in (0, 1], got {value}"),
        ))
    }
}

/// Keys whose default follows `iterations` unless the user sets them.
const PHASE_KEYS: [&str; 2] = ["discriminator_iterations", "reward_model_iterations"];

/// The default length of the phase before policy learning (SafeDICE's discriminator, PPL's
/// reward model) for a run of `iterations` policy iterations: as many steps in SafeDICE's
/// `service` preset ([`SafediceConfig::service`] says why), a tenth otherwise (the authors'
/// ratio); at least one step.
pub fn pretraining_default(algorithm: Algorithm, preset: Preset, iterations: u64) -> u64 {
    match (algorithm, preset) {
        (Algorithm::Safedice, Preset::Service) => iterations.max(1),
        _ => (iterations / 10).max(1),
    }
}

/// The keys a `config` object of `algorithm` may hold besides "preset" (the same in every preset).
pub fn config_keys(algorithm: Algorithm) -> Vec<String> {
    let defaults = ResolvedConfig::preset(algorithm, Preset::Service);
    let Value::Object(map) = serde_json::to_value(&defaults).expect("config serializes") else {
        unreachable!("a struct serializes to an object")
    };
    map.into_iter().map(|(k, _)| k).filter(|k| k != "algorithm" && k != "preset").collect()
}

/// Parse a user's `config` object for `algorithm` ("preset" plus overrides). Unknown keys and
/// out-of-range values are errors.
pub fn resolve_config(
    algorithm: Algorithm,
    raw: &Value,
) -> Result<ResolvedConfig, HyperparamError> {
    let empty = Map::new();
    let user = match raw {
        Value::Null => &empty,
        Value::Object(map) => map,
        _ => return Err(HyperparamError::new("config", "config: must be a JSON object")),
    };
    let preset = match user.get("preset") {
        None => Preset::Service,
        Some(v) => serde_json::from_value(v.clone()).map_err(|_| {
            HyperparamError::new(
                "preset",
                format!(
                    "config.preset: must be \"service\", \"paper\" or \"authors-code\", got {v}"
                ),
            )
        })?,
    };
    let defaults = ResolvedConfig::preset(algorithm, preset);
    let Value::Object(default_map) = serde_json::to_value(&defaults).expect("config serializes")
    else {
        unreachable!("a struct serializes to an object")
    };
    let mut merged = default_map.clone();
    for (key, value) in user {
        if key == "preset" {
            continue;
        }
        if key == "algorithm" || !default_map.contains_key(key) {
            let mut known: Vec<&str> =
                default_map.keys().map(String::as_str).filter(|k| *k != "algorithm").collect();
            known.sort_unstable();
            return Err(HyperparamError::new(
                key,
                format!(
                    "config.{key}: unknown key for algorithm {algorithm} (known: {})",
                    known.join(", ")
                ),
            ));
        }
        check_type(key, value, &default_map)?;
        merged.insert(key.clone(), value.clone());
    }
    if let Some(Value::Number(iterations)) = merged.get("iterations").cloned() {
        let phase = pretraining_default(algorithm, preset, iterations.as_u64().unwrap_or(0));
        for key in PHASE_KEYS {
            if merged.contains_key(key) && !user.contains_key(key) {
                merged.insert(key.to_string(), Value::from(phase));
            }
        }
    }
    let config: ResolvedConfig = serde_json::from_value(Value::Object(merged))
        .map_err(|e| HyperparamError::new("config", format!("config: {e}")))?;
    config.validate()?;
    Ok(config)
}

/// Rejects a value whose JSON type differs from the default's, naming the key.
fn check_type(
    key: &str,
    value: &Value,
    defaults: &Map<String, Value>,
) -> Result<(), HyperparamError> {
    let mut probe = defaults.clone();
    probe.insert(key.to_string(), value.clone());
    let wrong = |e: serde_json::Error| {
        let expected = match &defaults[key] {
            Value::Bool(_) => "true or false".to_string(),
            Value::Number(n) if n.is_u64() => "a non-negative integer".to_string(),
            Value::Number(_) => "a number".to_string(),
            Value::Array(_) => "an array of positive integers".to_string(),
            Value::String(_) => format!("one of the allowed names ({e})"),
            _ => e.to_string(),
        };
        HyperparamError::new(key, format!("config.{key}: must be {expected}, got {value}"))
    };
    serde_json::from_value::<ResolvedConfig>(Value::Object(probe)).map(|_| ()).map_err(wrong)
}

#[cfg(test)]
mod tests;
