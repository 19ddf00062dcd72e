//! What every trainer shares: the config, the datasets as tensors, the seeded RNG, the step
//! counter, checkpoint plumbing and the non-finite guard.

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::checkpoint::{self, Restored};
use super::columns::{fingerprint, Columns, ObsNormalizer};
use super::fused_mlp::EngineThreads;
use super::mlp::Mlp;
use super::optim::Adam;
use super::policy::{Decoder, PolicyArtifact, PolicyNet, PolicySpec, POLICY_FORMAT_VERSION};
use super::{device, ResolvedConfig, TrainError, TrainingData};
use crate::data::ActionSpace;

pub struct RunData {
    pub config: ResolvedConfig,
    pub u: Columns,
    pub n: Option<Columns>,
    pub normalizer: Option<ObsNormalizer>,
    pub space: ActionSpace,
    pub obs_dim: usize,
    pub fingerprint: String,
    pub device: Device,
    /// The fused engine's shards (`config.threads`) and the threads that run them.
    pub threads: EngineThreads,
    pub rng: ChaCha8Rng,
    /// Steps completed, every phase included.
    pub step: u64,
}

impl RunData {
    pub fn new(config: &ResolvedConfig, data: &TrainingData) -> Result<RunData, TrainError> {
        let device = device();
        let u = &data.unlabeled;
        let normalizer =
            config.common.normalize_observations.then(|| ObsNormalizer::from_dataset(u));
        let space = u.action_space().clone();
        let mut digest = fingerprint(u);
        let n = match &data.non_preferred {
            Some(n) if config.algorithm().needs_non_preferred() => {
                digest.push_str(&fingerprint(n));
                Some(Columns::new(n, &space, normalizer.as_ref(), &device)?)
            }
            _ => None,
        };
        Ok(RunData {
            config: config.clone(),
            u: Columns::new(u, &space, normalizer.as_ref(), &device)?,
            n,
            normalizer,
            space,
            obs_dim: u.obs_dim(),
            fingerprint: digest,
            device,
            threads: EngineThreads::new(config.common.threads, super::job_thread_cap()).map_err(
                |e| TrainError::Other(format!("could not start the job's threads: {e}")),
            )?,
            rng: ChaCha8Rng::seed_from_u64(config.seed()),
            step: 0,
        })
    }

    /// A freshly initialised policy network named `name`.
    pub fn new_policy(&mut self, name: &str) -> Result<PolicyNet, TrainError> {
        let hidden = self.config.common.hidden_sizes.clone();
        Ok(PolicyNet::new(name, self.obs_dim, &hidden, &self.space, &self.device, &mut self.rng)?)
    }

    /// A freshly initialised scalar critic (`input_dim → hidden → 1`, no last bias).
    pub fn new_critic(&mut self, name: &str, input_dim: usize) -> Result<Mlp, TrainError> {
        let dims: Vec<usize> = std::iter::once(input_dim)
            .chain(self.config.common.hidden_sizes.iter().copied())
            .chain(std::iter::once(1))
            .collect();
        Ok(Mlp::new(name, &dims, false, &self.device, &mut self.rng)?)
    }

    /// A minibatch of D^U row indices.
    pub fn sample_u(&mut self) -> Result<Tensor, TrainError> {
        let b = self.batch();
        Ok(self.u.sample(&mut self.rng, b)?)
    }

    /// A minibatch of D^N row indices.
    pub fn sample_n(&mut self) -> Result<Tensor, TrainError> {
        let b = self.batch();
        let n = self.n.as_ref().expect("check_data guarantees D^N");
        Ok(n.sample(&mut self.rng, b)?)
    }

    /// Width of an (s, a) network input.
    pub fn state_action_dim(&self) -> usize {
        self.obs_dim + self.space.input_width()
    }

    pub fn batch(&self) -> usize {
        self.config.common.batch_size
    }

    pub fn hidden(&self) -> &[usize] {
        &self.config.common.hidden_sizes
    }

    /// D^N (present whenever the algorithm needs it: `check_data` ran before).
    pub fn non_preferred(&self) -> &Columns {
        self.n.as_ref().expect("check_data guarantees D^N")
    }

    pub fn total(&self) -> u64 {
        self.config.total_steps()
    }

    pub fn ensure_running(&self) -> Result<(), TrainError> {
        if self.step >= self.total() {
            return Err(TrainError::Other("the run is already finished".into()));
        }
        Ok(())
    }

    pub fn policy_spec(&self, decoder: Decoder) -> PolicySpec {
        PolicySpec {
            format_version: POLICY_FORMAT_VERSION,
            algorithm: self.config.algorithm(),
            obs_dim: self.obs_dim,
            action_space: self.space.clone(),
            hidden_sizes: self.hidden().to_vec(),
            observation_normalization: self.normalizer.clone(),
            decoder,
            safety: None,
        }
    }

    /// The artefact of a run that trains one policy network.
    pub fn single_policy_artifact(&self, policy: &PolicyNet) -> Result<PolicyArtifact, TrainError> {
        PolicyArtifact::new(self.policy_spec(Decoder::Single), &[policy])
    }

    pub fn checkpoint(&self, optimizers: &[(&str, &Adam)]) -> Result<Vec<u8>, TrainError> {
        self.checkpoint_with(optimizers, &checkpoint::Extra::default())
    }

    /// [`Self::checkpoint`] with a trainer's own scalars and tensors.
    pub fn checkpoint_with(
        &self,
        optimizers: &[(&str, &Adam)],
        extra: &checkpoint::Extra,
    ) -> Result<Vec<u8>, TrainError> {
        checkpoint::encode(&self.config, self.step, &self.rng, &self.fingerprint, optimizers, extra)
    }

    /// Decodes `bytes`, checks they belong to this run, and takes over their step and RNG.
    pub fn restore(&mut self, bytes: &[u8]) -> Result<Restored, TrainError> {
        let restored = checkpoint::decode(bytes, &self.config, &self.fingerprint, &self.device)?;
        self.step = restored.step;
        self.rng = restored.rng.clone();
        Ok(restored)
    }

    /// Reads a scalar loss back and stops the run if it is not finite.
    pub fn checked(&self, loss: &Tensor, name: &str, hint: &str) -> Result<f64, TrainError> {
        let value = super::losses::scalar(loss)?;
        if value.is_finite() {
            Ok(value)
        } else {
            Err(TrainError::Diverged {
                step: self.step,
                message: format!("{name} became {value}. {hint}"),
            })
        }
    }
}
