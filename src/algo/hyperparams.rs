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
//!   a service (100k iterations). `safedice/config.rs` has the measurements behind them.
//!
//! The baselines are not in the authors' repository, so for them `authors-code` equals `paper`.
//!
//! Each algorithm's own keys, their presets and checks live in its module's `config.rs`
//! ([`knobs::AlgorithmKnobs`]); this file holds the common keys, lists the algorithms' configs
//! (`algorithm_configs!`) and merges a user's keys over a preset.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::bc::config::BcConfig;
pub use super::dexperts::config::{DexpertsConfig, NonPreferredTerm};
pub use super::dwbc::config::DwbcConfig;
pub use super::ppl::config::{PplConfig, PplWeight};
pub use super::safedice::config::{
    AlphaEstimator, AlphaHatPoint, AucInterval, BbeUnlabeledRows, SafediceConfig, TerminalHandling,
    TopBin, UndefinedReward,
};
use super::Algorithm;

pub mod knobs;
use knobs::{in_range, learning_rate, AlgorithmKnobs};
pub use knobs::{HyperparamError, Preset};

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

/// Lists each algorithm's own config, by its [`Algorithm`] variant: the tagged enum of the flat
/// JSON and its dispatch to [`AlgorithmKnobs`] follow from the list.
macro_rules! algorithm_configs {
    ($($variant:ident($config:ty)),+ $(,)?) => {
        /// The algorithm-specific part, tagged by "algorithm" in the flat JSON.
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        #[serde(tag = "algorithm", rename_all = "lowercase")]
        pub enum AlgorithmConfig {
            $($variant($config)),+
        }

        impl AlgorithmConfig {
            pub fn algorithm(&self) -> Algorithm {
                match self {
                    $(AlgorithmConfig::$variant(_) => Algorithm::$variant),+
                }
            }

            /// What the algorithm's own config knows of itself.
            pub fn knobs(&self) -> &dyn AlgorithmKnobs {
                match self {
                    $(AlgorithmConfig::$variant(config) => config),+
                }
            }

            fn preset(algorithm: Algorithm, preset: Preset, pretraining: u64) -> Self {
                match algorithm {
                    $(Algorithm::$variant => {
                        AlgorithmConfig::$variant(<$config>::preset(preset, pretraining))
                    }),+
                }
            }

            fn lr_actor(algorithm: Algorithm, preset: Preset) -> Option<f64> {
                match algorithm {
                    $(Algorithm::$variant => <$config>::lr_actor(preset)),+
                }
            }

            fn pretraining_default(algorithm: Algorithm, preset: Preset, iterations: u64) -> u64 {
                match algorithm {
                    $(Algorithm::$variant => <$config>::pretraining_default(preset, iterations)),+
                }
            }
        }
    };
}

algorithm_configs!(
    Safedice(SafediceConfig),
    Bc(BcConfig),
    Dwbc(DwbcConfig),
    Ppl(PplConfig),
    Dexperts(DexpertsConfig),
);

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
        self.specific.algorithm()
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
        self.specific.knobs().pretraining_steps()
    }

    /// The defaults of `preset` for `algorithm`.
    pub fn preset(algorithm: Algorithm, preset: Preset) -> ResolvedConfig {
        let paper_like = preset.paper_like();
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
        let pretraining = pretraining_default(algorithm, preset, common.iterations);
        let lr_actor = AlgorithmConfig::lr_actor(algorithm, preset).unwrap_or(common.lr_actor);
        ResolvedConfig {
            common: CommonConfig { lr_actor, ..common },
            specific: AlgorithmConfig::preset(algorithm, preset, pretraining),
        }
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
        self.specific.knobs().validate()
    }
}

/// Keys whose default follows `iterations` unless the user sets them.
const PHASE_KEYS: [&str; 2] = ["discriminator_iterations", "reward_model_iterations"];

/// The default length of the phase before policy learning (SafeDICE's discriminator, PPL's
/// reward model) for a run of `iterations` policy iterations: the algorithm's rule
/// ([`AlgorithmKnobs::pretraining_default`]).
pub fn pretraining_default(algorithm: Algorithm, preset: Preset, iterations: u64) -> u64 {
    AlgorithmConfig::pretraining_default(algorithm, preset, iterations)
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
    Ok(stored_form(config))
}

/// The config as it reads back from its JSON text. serde_json's default number parser is not
/// always correctly rounded, so a float written as text can come back an ulp away (an `lr`
/// sent with 20 digits did on about one value in ten); one more trip through text lands on a
/// value that reads back as itself. The job then trains with, checkpoints and reports the same
/// bits the request's response showed, instead of a neighbour picked up by the first trip
/// through the database. The crate enables serde_json's `float_roundtrip` (Cargo.toml), under
/// which the first trip already lands there; the loop keeps the guarantee if that ever changes.
fn stored_form(mut config: ResolvedConfig) -> ResolvedConfig {
    const MAX_TRIPS: usize = 4;
    for _ in 0..MAX_TRIPS {
        let text = serde_json::to_string(&config).expect("config serializes");
        let back: ResolvedConfig = serde_json::from_str(&text).expect("config reads back");
        if back == config {
            break;
        }
        config = back;
    }
    config
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
