//! DWBC's knobs (Eq. 38, 39) and their defaults, the same in every preset (the baselines are
//! not in the authors' repository).

use serde::{Deserialize, Serialize};

use crate::algo::hyperparams::knobs::{
    in_range, learning_rate, AlgorithmKnobs, HyperparamError, Preset,
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DwbcConfig {
    /// η of Eq. 38: the assumed share of non-preferred samples in D^U.
    pub eta: f64,
    pub lr_discriminator: f64,
    /// Interpolated gradient penalty of the discriminator (paper Table 2: 0.1).
    pub discriminator_gp: f64,
}

impl AlgorithmKnobs for DwbcConfig {
    fn preset(_preset: Preset, _pretraining: u64) -> Self {
        DwbcConfig { eta: 0.2, lr_discriminator: 3e-4, discriminator_gp: 0.1 }
    }

    fn validate(&self) -> Result<(), HyperparamError> {
        in_range("eta", self.eta, 0.0, 0.99)?;
        learning_rate("lr_discriminator", self.lr_discriminator)?;
        in_range("discriminator_gp", self.discriminator_gp, 0.0, 1e6)
    }
}
