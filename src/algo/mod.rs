//! The learning core: SafeDICE (NeurIPS 2023) and the paper's four baselines on candle.
//!
//! No HTTP or SQL here. The caller resolves a user's config ([`resolve_config`]), checks it
//! against the datasets ([`check_data`]), builds a [`Trainer`] ([`build_trainer`]) and advances
//! it one step at a time, so it can cancel, checkpoint and record metrics when it likes. The
//! result is a [`PolicyArtifact`] (safetensors weights + a JSON [`PolicySpec`]) that
//! [`Policy::load`] turns back into a policy without the training datasets.
//!
//! Files: one module per algorithm ([`safedice`] and [`dwbc`] are folders: the paper's
//! equations, the reference trainer, the fused CPU engine on [`fused_mlp`]; [`bc`], [`ppl`],
//! [`dexperts`] one file each), the shared
//! networks ([`mlp`]) and loss pieces ([`losses`]), policy heads and artefacts ([`policy`]), the
//! optimiser ([`optim`]), the training tensors built from a [`Dataset`] ([`columns`]), the state
//! every trainer shares ([`run`]), checkpoints ([`checkpoint`]), the hyperparameters with their
//! presets ([`hyperparams`]), and a run's memory estimate ([`memory`]). docs/algorithm.md
//! describes SafeDICE as implemented.

pub mod bc;
pub mod checkpoint;
pub mod columns;
pub mod dexperts;
pub mod discriminator_stop;
pub mod dwbc;
pub mod flops;
pub mod fused_mlp;
pub mod fused_ops;
pub mod fused_policy;
pub mod hyperparams;
pub mod losses;
pub mod memory;
pub mod mlp;
pub mod onnx;
pub mod optim;
pub mod policy;
pub mod ppl;
pub mod registry;
pub mod run;
pub mod safedice;
pub mod safety;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::data::{ActionSpace, Dataset};
use memory::DataShape;
use registry::AlgorithmSpec;

pub use hyperparams::{
    config_keys, resolve_config, AlphaEstimator, HyperparamError, NonPreferredTerm, Preset,
    ResolvedConfig, TerminalHandling, UndefinedReward, MAX_JOB_THREADS, MAX_SEED,
};
pub use policy::{portable_file, Policy, PolicyArtifact, PolicySpec, PortableMetadata};

/// The algorithms the service trains.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Algorithm {
    Safedice,
    Bc,
    Dwbc,
    Ppl,
    Dexperts,
}

impl Algorithm {
    pub const ALL: [Algorithm; 5] =
        [Algorithm::Safedice, Algorithm::Bc, Algorithm::Dwbc, Algorithm::Ppl, Algorithm::Dexperts];

    /// Its entry in the algorithm table ([`registry::SPECS`]).
    pub fn spec(self) -> &'static AlgorithmSpec {
        &registry::SPECS[self as usize]
    }

    /// Whether a run needs the labeled non-preferred dataset D^N (every algorithm but BC).
    pub fn needs_non_preferred(self) -> bool {
        self.spec().needs_non_preferred
    }

    pub fn as_str(self) -> &'static str {
        self.spec().name
    }

    /// The algorithm of an API name (`safedice`, `bc`, ...).
    pub fn from_name(name: &str) -> Option<Algorithm> {
        Algorithm::ALL.into_iter().find(|a| a.as_str() == name)
    }

    /// Every API name, in the table's order.
    pub fn names() -> [&'static str; 5] {
        Algorithm::ALL.map(Algorithm::as_str)
    }

    /// The name as the paper writes it.
    pub fn display_name(self) -> &'static str {
        self.spec().label
    }
}

impl std::fmt::Display for Algorithm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The datasets a run trains on (Arc so a worker thread can own them).
#[derive(Clone, Debug)]
pub struct TrainingData {
    /// D^U: abundant, unlabeled demonstrations (preferred and non-preferred mixed).
    pub unlabeled: Arc<Dataset>,
    /// D^N: the few demonstrations labeled non-preferred.
    pub non_preferred: Option<Arc<Dataset>>,
}

/// Why a run stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Losses went non-finite; message says at which step, which loss, and what to try.
    #[error("training diverged at step {step}: {message}")]
    Diverged { step: u64, message: String },
    /// A checkpoint that does not belong to this config/data or is corrupt.
    #[error("bad checkpoint: {0}")]
    BadCheckpoint(String),
    #[error("tensor error: {0}")]
    Candle(#[from] candle_core::Error),
    #[error("{0}")]
    Other(String),
}

/// Where a run is. `phase` is "discriminator", "reward_model" or "policy".
#[derive(Clone, Debug, Serialize)]
pub struct Progress {
    pub step: u64,
    pub total: u64,
    pub phase: &'static str,
}

/// A training run, advanced one step at a time by the caller (so the caller can cancel between
/// steps, checkpoint when it likes, and record metrics at the rate it likes).
pub trait Trainer: Send {
    fn progress(&self) -> Progress;
    fn is_finished(&self) -> bool {
        let p = self.progress();
        p.step >= p.total
    }
    /// One step of the current phase. With `record`, returns the step's named scalars
    /// (losses, alpha_hat, weight statistics such as ESS, ...); else an empty vector.
    fn step(&mut self, record: bool) -> Result<Vec<(&'static str, f64)>, TrainError>;
    /// Everything needed to continue this exact run: weights, optimiser state, step, RNG state.
    fn checkpoint(&self) -> Result<Vec<u8>, TrainError>;
    /// SafeDICE's alpha-hat once computed; None otherwise.
    fn alpha_hat(&self) -> Option<f64> {
        None
    }
    /// How alpha-hat was estimated, in words for the job log (its interval, the held-out AUC),
    /// once computed; None otherwise.
    fn alpha_hat_detail(&self) -> Option<String> {
        None
    }
    /// Why the run's weighting fell back to uniform (BC), if it did.
    fn uniform_weighting_reason(&self) -> Option<String> {
        None
    }
    /// The current policy as an artefact.
    fn export_policy(&self) -> Result<PolicyArtifact, TrainError>;
    /// Run every step on candle autograd even on the CPU, instead of the fused engine (the
    /// reference path; `safedice speed --engine candle` and the tests that compare both).
    fn use_candle_autograd(&mut self);
}

/// Check the datasets fit the config ([`check_fit`]); a [`Dataset`](crate::data::Dataset) is
/// consistent by construction.
pub fn check_data(config: &ResolvedConfig, data: &TrainingData) -> Result<(), HyperparamError> {
    let non_preferred = data.non_preferred.as_deref().map(DataShape::of);
    check_fit(config, &DataShape::of(&data.unlabeled), non_preferred.as_ref())
}

/// Check datasets of these shapes fit the config (non-preferred present when needed, spaces
/// agree, a usable action box). Shapes are the stored datasets' metadata, so a job is checked
/// without loading its data.
pub fn check_fit(
    config: &ResolvedConfig,
    unlabeled: &DataShape,
    non_preferred: Option<&DataShape>,
) -> Result<(), HyperparamError> {
    let algorithm = config.algorithm();
    let bad = |key: &str, message: String| HyperparamError { key: key.to_string(), message };
    if non_preferred.is_none() && algorithm.needs_non_preferred() {
        return Err(bad(
            "non_preferred",
            format!("algorithm {algorithm} needs a labeled non-preferred dataset"),
        ));
    }
    if let Some(n) = non_preferred {
        if n.obs_dim != unlabeled.obs_dim {
            return Err(bad(
                "non_preferred",
                format!(
                    "non-preferred observations have {} dimensions, unlabeled ones {}",
                    n.obs_dim, unlabeled.obs_dim
                ),
            ));
        }
        if !n.action_space.compatible_with(&unlabeled.action_space) {
            return Err(bad(
                "non_preferred",
                format!(
                    "non-preferred action space {:?} does not match the unlabeled one {:?}",
                    n.action_space, unlabeled.action_space
                ),
            ));
        }
    }
    if let ActionSpace::Continuous { low, high, .. } = &unlabeled.action_space {
        if low.iter().zip(high).any(|(l, h)| h.partial_cmp(l) != Some(std::cmp::Ordering::Greater))
        {
            return Err(bad("unlabeled", "action box has a dimension with high <= low".into()));
        }
    }
    Ok(())
}

/// Start a run, or resume it from `checkpoint` bytes made by [`Trainer::checkpoint`].
pub fn build_trainer(
    config: &ResolvedConfig,
    data: &TrainingData,
    checkpoint: Option<&[u8]>,
) -> Result<Box<dyn Trainer>, TrainError> {
    check_data(config, data).map_err(|e| TrainError::Other(e.message))?;
    if let Some(bytes) = checkpoint {
        return resume(config, data, bytes);
    }
    (config.algorithm().spec().build)(config, data)
}

fn resume(
    config: &ResolvedConfig,
    data: &TrainingData,
    bytes: &[u8],
) -> Result<Box<dyn Trainer>, TrainError> {
    (config.algorithm().spec().resume)(config, data, bytes)
}

/// The most threads one training job of this process computes on (`--job-threads`); 0 until
/// set, which means the machine's cores.
static JOB_THREAD_CAP: AtomicUsize = AtomicUsize::new(0);

/// Sets [`job_thread_cap`] for every job this process trains from now on.
pub fn set_job_thread_cap(threads: usize) {
    JOB_THREAD_CAP.store(threads.max(1), Ordering::Relaxed);
}

/// The most threads a job of this process runs on: `--job-threads`, or the machine's cores.
/// A job's `threads` above it runs its shards on fewer threads, with the same arithmetic.
pub fn job_thread_cap() -> usize {
    match JOB_THREAD_CAP.load(Ordering::Relaxed) {
        0 => available_cores(),
        n => n,
    }
}

/// Multiply-adds of one step's policy forward pass per thread below which another thread
/// costs more than it gains: a step's threads meet a dozen times (`fused_mlp::shards`), tens
/// of microseconds each. Measured (`safedice speed --threads 1,2`, docs/performance.md,
/// "Threads of one job"): [256, 256] at batch 128 (9M) gained 1.47x from a second thread,
/// [64, 64] at batch 256 (1.5M) lost 0.71x.
const MACS_PER_THREAD: usize = 4_000_000;

/// The most threads a job of `config` on `obs_dim`-wide observations gains from: one per
/// [`MACS_PER_THREAD`] multiply-adds of its batch through a network of its hidden sizes.
pub fn worthwhile_threads(config: &ResolvedConfig, obs_dim: usize) -> usize {
    let shape = fused_mlp::MlpShape::new(obs_dim, &config.common.hidden_sizes, 1, false);
    let macs = shape.forward_flops_per_row() as usize / 2 * config.common.batch_size;
    (macs / MACS_PER_THREAD).clamp(1, MAX_JOB_THREADS)
}

/// `--job-threads`: as `configured`, or this machine's cores shared by the `workers` jobs that
/// run at once (an API-only node, 0 workers, counts one), at least 1.
pub fn job_threads(configured: Option<u16>, workers: usize) -> usize {
    configured.map_or_else(|| (available_cores() / workers.max(1)).max(1), usize::from)
}

/// The cores this process may use.
pub fn available_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The device training runs on: the CPU, or the first CUDA GPU when built with `cuda`.
pub fn device() -> candle_core::Device {
    #[cfg(feature = "cuda")]
    {
        if let Ok(d) = candle_core::Device::new_cuda(0) {
            return d;
        }
    }
    candle_core::Device::Cpu
}
