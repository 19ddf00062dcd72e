//! How much memory a training job needs, from its configuration and the shapes of its datasets
//! alone (nothing is loaded), so that `POST /v1/jobs` can refuse a job that would not fit
//! (`--max-job-memory`) instead of letting it take the machine down once a worker starts it.
//!
//! The estimate adds what a run holds at its peak:
//!
//! - **data**: each dataset as decoded ([`crate::data::Dataset`]) and as training tensors
//!   ([`super::columns::Columns`]), plus SafeDICE's flow table, scores and rewards over D^U;
//! - **networks**: every parameter with its gradient, Adam moments, the fused engine's copy and
//!   the checkpoint being encoded;
//! - **step**: the per-step buffers. SafeDICE on the CPU runs its fused engine, whose
//!   workspaces are allocated once for `4B`, `5B` and `B` rows (discriminator, ν, policy) and
//!   are counted exactly. The other algorithms run candle autograd, whose graph keeps a few
//!   tensors per layer and row, more with a gradient penalty (a second backward pass);
//! - a fixed **overhead** per job (the worker thread, allocator arenas);
//! - and 10% on top of the sum, for the allocator's slack.
//!
//! Measured peaks (resident set above the one at start, of a process that loads the datasets
//! from their canonical bytes, builds the trainer and runs steps of every phase, with a
//! checkpoint; debug build of this crate, optimised dependencies, 2-core x86-64, `cargo test
//! --test learning memory_estimate -- --ignored --nocapture`) against this estimate; every
//! estimate is an upper bound, within 2.5x of the measured peak:
//!
//! | case | measured MiB | estimate MiB | estimate / measured |
//! |---|---|---|---|
//! | SafeDICE defaults (B 512, [256, 256]), D^U 100k x 17-dim obs, 6-dim actions | 107 | 168 | 1.56 |
//! | SafeDICE B 65536, [256, 256], same data (the configuration of the 3.5 GB report) | 2978 | 3916 | 1.32 |
//! | SafeDICE B 4096, [1024, 1024, 1024], D^U 50k x 64-dim obs, 8-dim actions | 1393 | 1805 | 1.30 |
//! | SafeDICE B 512, [256, 256], D^U 1M x 64-dim obs, 8-dim actions | 1973 | 2340 | 1.19 |
//! | SafeDICE `absorbing`, 16 discrete actions, B 8192, D^U 200k x 32-dim obs | 612 | 830 | 1.35 |
//! | BC B 65536, [256, 256], D^U 100k x 17-dim obs | 1009 | 1291 | 1.28 |
//! | DWBC B 16384, [256, 256], same data | 1089 | 2181 | 2.00 |
//! | PPL 256 pairs x 200-step segments, B 4096, [256, 256] | 1347 | 2171 | 1.61 |
//! | DExperts, 16 discrete actions, B 16384, [256, 256] | 402 | 704 | 1.75 |
//!
//! (D^N is a tenth of D^U in every case.) The defaults sit far below the default limit of
//! 4 GiB; the SafeDICE and BC step buffers grow linearly with the batch size, SafeDICE's fused
//! workspaces with `4B + 5B + B` rows of every layer width.
//!
//! On a CUDA build the step buffers live in GPU memory; the estimate still counts them, as
//! host memory, which keeps it an upper bound of the host's share.

use super::hyperparams::ResolvedConfig;
use crate::data::ActionSpace;

pub(super) const F32: u64 = 4;
/// Per parameter: the value, its gradient, Adam's two moments, the fused engine's copy and
/// gradient, and the checkpoint's encoded value and moments (twice: the buffer and its copy
/// bound to the database write).
const BYTES_PER_PARAMETER: u64 = 13 * F32;
/// Floats per row and unit of layer width that a candle forward and backward pass keeps (the
/// matmul, bias and activation outputs, then their gradients).
pub(super) const AUTOGRAD_FLOATS: u64 = 8;
/// The same with an input-gradient penalty: the gradient graph is differentiated once more.
pub(super) const PENALTY_FLOATS: u64 = 24;
/// The worker's thread, its allocator arena and candle's per-run state.
const JOB_OVERHEAD: u64 = 48 << 20;

/// What the estimate needs to know of a dataset: the columns of its stored record.
#[derive(Clone, Debug, PartialEq)]
pub struct DataShape {
    pub transitions: u64,
    pub obs_dim: u64,
    pub action_space: ActionSpace,
    /// Length of the dataset's longest episode (PPL's segments are at most that long).
    pub longest_episode: u64,
}

impl DataShape {
    /// The shape of a dataset in memory.
    pub fn of(dataset: &crate::data::Dataset) -> DataShape {
        let longest = dataset.episode_ranges().iter().map(|r| r.len()).max().unwrap_or(0);
        DataShape {
            transitions: dataset.len() as u64,
            obs_dim: dataset.obs_dim() as u64,
            action_space: dataset.action_space().clone(),
            longest_episode: longest as u64,
        }
    }

    /// Values stored per transition for the action: the continuous vector, or one index.
    fn action_values(&self) -> u64 {
        match self.action_space {
            ActionSpace::Continuous { dim, .. } => dim as u64,
            ActionSpace::Discrete { .. } => 1,
        }
    }

    /// Width of the action as a network input: the vector, or a one-hot.
    fn action_width(&self) -> u64 {
        self.action_space.input_width() as u64
    }

    /// Bytes of the decoded dataset and of its training columns.
    fn bytes(&self) -> u64 {
        let (n, d, a, c) =
            (self.transitions, self.obs_dim, self.action_width(), self.action_values());
        // Decoded: observations and next observations, actions, rewards and costs, episode ids,
        // terminal flags.
        let decoded = n * (F32 * (2 * d + c + 3) + 1);
        // Columns: both observation tensors, the action input, the log-likelihood's form of
        // the action (pre-tanh values and Jacobian, or the index), the row bookkeeping; and
        // the f64 values the continuous form is computed through.
        let columns = n * (F32 * (2 * d + a + c + 3) + 1 + 8 * c);
        decoded + columns
    }
}

/// A job's estimated peak memory, in bytes, and its parts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryEstimate {
    pub total: u64,
    pub data: u64,
    pub networks: u64,
    pub step: u64,
}

/// Parameters of a fully connected network with layer widths `dims`; the last layer has a
/// bias when `last_bias`.
fn parameters(dims: &[u64], last_bias: bool) -> u64 {
    let layers = dims.len() - 1;
    dims.windows(2)
        .enumerate()
        .map(|(i, w)| w[0] * w[1] + if i + 1 < layers || last_bias { w[1] } else { 0 })
        .sum()
}

/// Floats of a fused-engine workspace for `rows` rows (see `fused_mlp::Workspace::new`).
pub(super) fn workspace_floats(dims: &[u64], rows: u64) -> u64 {
    let widest = dims.iter().copied().max().unwrap_or(0);
    rows * (2 * dims.iter().sum::<u64>() + dims[0] + widest)
}

/// With `threads` above one, the fused engine's shards each keep a gradient of every network
/// (`fused_mlp::shards`); their workspaces split the rows, so they add only one row per shard
/// and the gathered rows, which the 10% added on top of the sum covers.
fn shard_bytes(config: &ResolvedConfig, parameters: u64) -> u64 {
    match config.common.threads as u64 {
        0 | 1 => 0,
        shards => shards * parameters * F32,
    }
}

/// Floats a candle forward and backward pass over `rows` rows keeps.
pub(super) fn autograd_floats(dims: &[u64], rows: u64, per_width: u64) -> u64 {
    rows * per_width * dims.iter().sum::<u64>()
}

/// What an algorithm's share of the estimate is computed from: the run's configuration, its
/// datasets' shapes and the networks' layer widths they give. Each algorithm's module answers
/// it with its `memory` (the registry points at it), beside its `step_flops`.
pub struct MemoryShape<'a> {
    pub config: &'a ResolvedConfig,
    pub unlabeled: &'a DataShape,
    /// D^N, for the algorithms that use it (`None` for the others).
    pub non_preferred: Option<&'a DataShape>,
}

impl MemoryShape<'_> {
    pub fn batch(&self) -> u64 {
        self.config.common.batch_size as u64
    }

    pub fn obs_dim(&self) -> u64 {
        self.unlabeled.obs_dim
    }

    /// The action as a network input: its width, or a one-hot.
    pub fn action_width(&self) -> u64 {
        self.unlabeled.action_width()
    }

    pub fn discrete_actions(&self) -> bool {
        matches!(self.unlabeled.action_space, ActionSpace::Discrete { .. })
    }

    /// Layer widths of a network from `input` columns through the hidden layers to `output`.
    pub fn net(&self, input: u64, output: u64) -> Vec<u64> {
        let hidden = self.config.common.hidden_sizes.iter().map(|&h| h as u64);
        std::iter::once(input).chain(hidden).chain([output]).collect()
    }

    /// The policy: observations to its head (mean and log-std per action, or a logit each).
    pub fn policy(&self) -> Vec<u64> {
        let head = match self.unlabeled.action_space {
            ActionSpace::Continuous { dim, .. } => 2 * dim as u64,
            ActionSpace::Discrete { n } => n as u64,
        };
        self.net(self.obs_dim(), head)
    }

    /// A scalar critic of the state-action and `extra` more columns (a discriminator, a
    /// reward model).
    pub fn critic(&self, extra: u64) -> Network {
        Network {
            dims: self.net(self.obs_dim() + self.action_width() + extra, 1),
            last_bias: false,
        }
    }
}

/// A network a run trains: its layer widths, and whether its last layer has a bias (the
/// policy's does, the scalar critics' do not).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Network {
    pub dims: Vec<u64>,
    pub last_bias: bool,
}

impl Network {
    pub fn policy(shape: &MemoryShape) -> Network {
        Network { dims: shape.policy(), last_bias: true }
    }

    pub fn parameters(&self) -> u64 {
        parameters(&self.dims, self.last_bias)
    }
}

/// One algorithm's share of a run's peak memory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Footprint {
    /// Every network it trains (each parameter is counted [`BYTES_PER_PARAMETER`] times).
    pub networks: Vec<Network>,
    /// Bytes of its per-step buffers at their peak.
    pub step: u64,
    /// Bytes it keeps over the training data beyond the datasets' own (SafeDICE's flow table).
    pub data: u64,
}

/// Estimates the peak memory of a run of `config` on datasets of these shapes (`non_preferred`
/// is ignored by the algorithms that do not use it).
pub fn estimate_job_memory(
    config: &ResolvedConfig,
    unlabeled: &DataShape,
    non_preferred: Option<&DataShape>,
) -> MemoryEstimate {
    let spec = config.algorithm().spec();
    let non_preferred = non_preferred.filter(|_| spec.needs_non_preferred);
    let shape = MemoryShape { config, unlabeled, non_preferred };
    let footprint = (spec.memory)(&shape);
    let data = unlabeled.bytes() + non_preferred.map_or(0, DataShape::bytes) + footprint.data;
    let parameter_count = footprint.networks.iter().map(Network::parameters).sum::<u64>();
    let networks = parameter_count * BYTES_PER_PARAMETER + shard_bytes(config, parameter_count);
    let step = footprint.step;
    let sum = data + networks + step + JOB_OVERHEAD;
    MemoryEstimate { total: sum + sum / 10, data, networks, step }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::algo::{resolve_config, Algorithm};

    fn continuous(dim: usize) -> ActionSpace {
        ActionSpace::Continuous { dim, low: vec![-1.0; dim], high: vec![1.0; dim] }
    }

    type Measured = (Algorithm, serde_json::Value, (u64, u64), u64, ActionSpace, f64);

    /// The cases of the module's table as `tests/learning/memory_estimate.rs` measured them:
    /// (algorithm, config, D^U (transitions, episode length), obs dim, action space, measured
    /// peak in MiB); D^N has a tenth of D^U's transitions.
    fn measured() -> Vec<Measured> {
        let sd = |batch: u64, hidden: serde_json::Value| {
            json!({"batch_size": batch, "hidden_sizes": hidden, "discriminator_iterations": 2,
                   "iterations": 2})
        };
        let plain =
            |batch: u64| json!({"batch_size": batch, "hidden_sizes": [256, 256], "iterations": 2});
        vec![
            (
                Algorithm::Safedice,
                sd(512, json!([256, 256])),
                (100_000, 500),
                17,
                continuous(6),
                107.0,
            ),
            (
                Algorithm::Safedice,
                sd(65_536, json!([256, 256])),
                (100_000, 500),
                17,
                continuous(6),
                2978.0,
            ),
            (
                Algorithm::Safedice,
                sd(4096, json!([1024, 1024, 1024])),
                (50_000, 1000),
                64,
                continuous(8),
                1393.0,
            ),
            (
                Algorithm::Safedice,
                sd(512, json!([256, 256])),
                (1_000_000, 1000),
                64,
                continuous(8),
                1973.0,
            ),
            (
                Algorithm::Safedice,
                {
                    let mut c = sd(8192, json!([256, 256]));
                    c["terminal_handling"] = json!("absorbing");
                    c
                },
                (200_000, 50),
                32,
                ActionSpace::Discrete { n: 16 },
                612.0,
            ),
            (Algorithm::Bc, plain(65_536), (100_000, 500), 17, continuous(6), 1009.0),
            (Algorithm::Dwbc, plain(16_384), (100_000, 500), 17, continuous(6), 1089.0),
            (
                Algorithm::Ppl,
                json!({"batch_size": 4096, "hidden_sizes": [256, 256], "iterations": 2,
                       "reward_model_iterations": 2, "pairs_per_batch": 256, "segment_length": 200}),
                (100_000, 200),
                17,
                continuous(6),
                1347.0,
            ),
            (
                Algorithm::Dexperts,
                plain(16_384),
                (100_000, 500),
                17,
                ActionSpace::Discrete { n: 16 },
                402.0,
            ),
        ]
    }

    /// The estimate bounds every measured peak from above, and not by more than 2.5x (a looser
    /// estimate would refuse jobs that fit).
    #[test]
    fn the_estimate_is_an_upper_bound_of_measured_peaks_within_2_5x() {
        for (algorithm, config, (transitions, episode), obs_dim, action_space, mib) in measured() {
            let config = resolve_config(algorithm, &config).unwrap();
            let shape = |transitions: u64| DataShape {
                transitions,
                obs_dim,
                action_space: action_space.clone(),
                longest_episode: episode,
            };
            let estimate =
                estimate_job_memory(&config, &shape(transitions), Some(&shape(transitions / 10)));
            let ratio = estimate.total as f64 / (mib * (1 << 20) as f64);
            assert!(
                (1.0..=2.5).contains(&ratio),
                "{algorithm}: {estimate:?} vs {mib} MiB measured"
            );
        }
    }

    /// Batch size and widths drive the step buffers; transitions and widths of the data drive
    /// the data term; D^N is not counted for BC, which never loads it.
    #[test]
    fn the_estimate_grows_with_what_a_run_allocates() {
        let config = |algorithm, batch: u64| {
            resolve_config(algorithm, &json!({"batch_size": batch})).unwrap()
        };
        let shape = |transitions: u64, obs_dim: u64| DataShape {
            transitions,
            obs_dim,
            action_space: continuous(4),
            longest_episode: 100,
        };
        let small = shape(10_000, 8);
        let estimate =
            |c: &ResolvedConfig, u: &DataShape, n: Option<&DataShape>| estimate_job_memory(c, u, n);
        let sd = config(Algorithm::Safedice, 512);
        let base = estimate(&sd, &small, Some(&small));
        let big_batch = estimate(&config(Algorithm::Safedice, 8192), &small, Some(&small));
        assert!(big_batch.step > 15 * base.step && big_batch.data == base.data);
        // D^U a hundred times larger (D^N unchanged): the data term grows about fifty-fold.
        let big_data = estimate(&sd, &shape(1_000_000, 8), Some(&small));
        assert!(big_data.data > 40 * base.data && big_data.step == base.step);
        let bc = config(Algorithm::Bc, 512);
        assert_eq!(estimate(&bc, &small, Some(&shape(1_000_000, 64))), estimate(&bc, &small, None));
    }

    #[test]
    fn parameters_count_weights_and_biases() {
        // 3x4 + 4, then 4x1 without (or with) the last bias.
        assert_eq!(parameters(&[3, 4, 1], false), 20);
        assert_eq!(parameters(&[3, 4, 1], true), 21);
    }
}
