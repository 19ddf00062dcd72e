//! What every algorithm's configuration shares: the presets, the error a wrong value gives, the
//! range checks, and [`AlgorithmKnobs`], which each algorithm's own config implements in its
//! module. A leaf: the algorithms' configs import it, [`super`] dispatches to them.

use serde::{Deserialize, Serialize};

/// A config the user got wrong; `message` names the key and what is allowed.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct HyperparamError {
    pub key: String,
    pub message: String,
}

impl HyperparamError {
    pub fn new(key: &str, message: impl Into<String>) -> Self {
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

    /// `paper` and `authors-code` keep the paper's behaviour; `service` adds what measurement
    /// favoured.
    pub fn paper_like(self) -> bool {
        self != Preset::Service
    }
}

/// An algorithm's own configuration (the keys beside the common ones): its defaults under each
/// preset and its checks. Each algorithm's module implements it for its config;
/// `hyperparams::AlgorithmConfig` lists the configs and dispatches to them.
pub trait AlgorithmKnobs {
    /// The defaults of `preset`, `pretraining` being the default length of the phase before
    /// policy learning ([`AlgorithmKnobs::pretraining_default`]) for algorithms that have one.
    fn preset(preset: Preset, pretraining: u64) -> Self
    where
        Self: Sized;

    /// The actor's learning rate under `preset` where it differs from the common default.
    fn lr_actor(_preset: Preset) -> Option<f64>
    where
        Self: Sized,
    {
        None
    }

    /// The default length of the phase before policy learning for a run of `iterations`
    /// policy iterations: a tenth (the authors' ratio), at least one step.
    fn pretraining_default(_preset: Preset, iterations: u64) -> u64
    where
        Self: Sized,
    {
        a_tenth_of(iterations)
    }

    /// Steps of the phase before policy learning (a discriminator, a reward model); 0 if none.
    fn pretraining_steps(&self) -> u64 {
        0
    }

    /// Range checks and combinations the types do not hold, naming the key that fails.
    fn validate(&self) -> Result<(), HyperparamError>;
}

/// The authors' length of a pretraining phase: a tenth of the policy iterations, at least one.
pub fn a_tenth_of(iterations: u64) -> u64 {
    (iterations / 10).max(1)
}

pub fn in_range(key: &str, value: f64, low: f64, high: f64) -> Result<(), HyperparamError> {
    if value.is_finite() && value >= low && value <= high {
        Ok(())
    } else {
        Err(HyperparamError::new(
            key,
            format!("config.{key}: must be between {low} and {high}, got {value}"),
        ))
    }
}

pub fn learning_rate(key: &str, value: f64) -> Result<(), HyperparamError> {
    if value.is_finite() && value > 0.0 && value <= 1.0 {
        Ok(())
    } else {
        Err(HyperparamError::new(
            key,
            format!("config.{key}: must be a learning rate in (0, 1], got {value}"),
        ))
    }
}
