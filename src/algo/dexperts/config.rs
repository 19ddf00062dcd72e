//! DExperts' knobs (Eq. 44 for discrete actions, Eq. 45 for continuous ones) and their defaults.

use serde::{Deserialize, Serialize};

use crate::algo::hyperparams::knobs::{in_range, AlgorithmKnobs, HyperparamError, Preset};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DexpertsConfig {
    /// α of Eq. 44/45: how strongly the non-preferred expert is subtracted.
    pub alpha: f64,
    /// Continuous actions: Eq. 45's D^N term as written or bounded (discrete actions decode
    /// with Eq. 44 and ignore it).
    #[serde(default)]
    pub non_preferred_term: NonPreferredTerm,
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

impl AlgorithmKnobs for DexpertsConfig {
    fn preset(preset: Preset, _pretraining: u64) -> Self {
        let non_preferred_term = if preset.paper_like() {
            NonPreferredTerm::LogLikelihood
        } else {
            NonPreferredTerm::Kernel
        };
        DexpertsConfig { alpha: 0.2, non_preferred_term }
    }

    fn validate(&self) -> Result<(), HyperparamError> {
        in_range("alpha", self.alpha, 0.0, 10.0)
    }
}
