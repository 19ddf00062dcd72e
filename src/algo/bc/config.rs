//! BC's configuration: the common keys only.

use serde::{Deserialize, Serialize};

use crate::algo::hyperparams::knobs::{AlgorithmKnobs, HyperparamError, Preset};

/// BC has no knobs of its own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BcConfig {}

impl AlgorithmKnobs for BcConfig {
    fn preset(_preset: Preset, _pretraining: u64) -> Self {
        BcConfig {}
    }

    fn validate(&self) -> Result<(), HyperparamError> {
        Ok(())
    }
}
