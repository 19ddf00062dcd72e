//! PPL's knobs (Eq. 40, 41) and their defaults.

use serde::{Deserialize, Serialize};

use crate::algo::hyperparams::knobs::{
    in_range, learning_rate, AlgorithmKnobs, HyperparamError, Preset,
};

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

/// How PPL turns its learned reward `R_θ(s, a)` into behaviour-cloning weights.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PplWeight {
    /// `R_θ(s, a)` itself (Eq. 41 literally; negative weights push log-probabilities down).
    Raw,
    /// `σ(R_θ(s, a))`, in (0, 1).
    Sigmoid,
}

impl AlgorithmKnobs for PplConfig {
    fn preset(preset: Preset, pretraining: u64) -> Self {
        PplConfig {
            reward_model_iterations: pretraining,
            lr_reward_model: 3e-4,
            pairs_per_batch: 16,
            segment_length: 32,
            ppl_weight: if preset.paper_like() { PplWeight::Raw } else { PplWeight::Sigmoid },
        }
    }

    fn pretraining_steps(&self) -> u64 {
        self.reward_model_iterations
    }

    fn validate(&self) -> Result<(), HyperparamError> {
        in_range("reward_model_iterations", self.reward_model_iterations as f64, 1.0, 1e8)?;
        learning_rate("lr_reward_model", self.lr_reward_model)?;
        in_range("pairs_per_batch", self.pairs_per_batch as f64, 1.0, 4096.0)?;
        in_range("segment_length", self.segment_length as f64, 1.0, 100_000.0)
    }
}
