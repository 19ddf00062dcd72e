//! `safedice bench`: the paper's comparison (Tables 5-9) on the built-in environments.
//!
//! For every environment the benchmark generates one dataset with a fixed data seed (the
//! unlabeled set D^U mixing preferred and non-preferred episodes, and the labeled
//! non-preferred set D^N), trains every algorithm on it for every seed in-process through
//! [`crate::algo::build_trainer`] with the service defaults, evaluates each policy with
//! [`crate::envs::evaluate`], and writes `results.md` (mean ± standard error over seeds, the
//! exact command, date, commit, iterations and wall time), `results.json` (every run) and one
//! SVG plot per environment (average cost against normalized return, with error bars).
//!
//! With `--ablations` ([`ablation`]) every environment gets three more rows (BC on the
//! preferred episodes only, SafeDICE with the true α, SafeDICE with oracle labels) and every
//! SafeDICE run its discriminator's ROC AUC and the weight it puts on non-preferred data.
//!
//! Files: [`runner`] (data, training, evaluation, the worker threads), [`summary`]
//! (aggregation over seeds), [`report`] (the markdown, JSON and console outputs), [`plot`] (the
//! SVG), [`ablation`] (the ablation rows' pieces). Beside it: [`speed`] (`safedice speed`, the training speed of the SafeDICE trainer).

pub mod ablation;
pub mod plot;
pub mod report;
pub mod runner;
pub mod speed;
pub mod summary;

use std::path::PathBuf;

use serde::Serialize;

use crate::algo::Algorithm;

pub use ablation::Variant;
pub use report::write_outputs;
pub use runner::{run, BenchError, BenchResults, RunResult};
pub use summary::{summarize, Summary};

/// Episode counts of the generated data.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct DataSize {
    /// Preferred episodes in D^U.
    pub preferred: usize,
    /// Non-preferred episodes in D^U.
    pub non_preferred: usize,
    /// Episodes in D^N.
    pub labeled: usize,
}

impl DataSize {
    /// The paper's Safety-Gym proportions (1000 + 1000 unlabeled, 50 labeled).
    pub const PAPER: DataSize = DataSize { preferred: 1000, non_preferred: 1000, labeled: 50 };
    /// Scaled down for `--quick`, same 1:1 mix and a labeled set of ~1/8 of the unlabeled one.
    pub const QUICK: DataSize = DataSize { preferred: 40, non_preferred: 40, labeled: 10 };
}

/// Everything one benchmark run does.
#[derive(Clone, Debug, Serialize)]
pub struct BenchConfig {
    pub envs: Vec<String>,
    pub algorithms: Vec<Algorithm>,
    /// Training seeds `0..seeds`.
    pub seeds: u64,
    /// Policy-learning iterations of every algorithm; pretraining phases (SafeDICE's
    /// discriminator, PPL's reward model) add their service default on top (as many steps for
    /// SafeDICE, 10% for PPL).
    pub iterations: u64,
    pub data: DataSize,
    /// Seed of the generated data (the same for every training seed, as in the paper).
    pub data_seed: u64,
    /// Evaluation episodes per trained policy (paper: 500).
    pub eval_episodes: usize,
    /// Evaluate `tanh(mean)` / argmax instead of sampling from the policy.
    pub deterministic_eval: bool,
    /// Trainings run side by side, one thread each.
    pub threads: usize,
    /// Config keys applied to every algorithm on top of the service preset (e.g.
    /// `batch_size`, `hidden_sizes` for a tiny smoke run). Empty in the documented modes.
    pub overrides: serde_json::Map<String, serde_json::Value>,
    /// Record the trainers' scalars (alpha-hat, ESS, losses) every this many steps.
    pub record_every: u64,
    /// Add the ablation rows ([`ablation`]): BC (preferred only), SafeDICE (true α), SafeDICE
    /// (oracle labels), whatever `algorithms` holds, and the discriminator AUCs of every
    /// SafeDICE run.
    pub ablations: bool,
}

/// DWBC's η and DExperts' α: the service defaults, kept fixed. The paper picked them per task
/// by a search over {0.01, ..., 0.8}; the benchmark does not search (nor does SafeDICE need to).
pub const BASELINE_KNOBS: &str =
    "DWBC eta = 0.2, DExperts alpha = 0.2 (service defaults, not searched)";

impl BenchConfig {
    /// The paper-size benchmark: 1M iterations, 5 seeds, 500 evaluation episodes.
    pub fn full() -> BenchConfig {
        BenchConfig {
            envs: crate::envs::names().iter().map(|s| s.to_string()).collect(),
            algorithms: Algorithm::ALL.to_vec(),
            seeds: 5,
            iterations: 1_000_000,
            data: DataSize::PAPER,
            data_seed: 0,
            eval_episodes: 500,
            deterministic_eval: false,
            threads: 2,
            overrides: serde_json::Map::new(),
            record_every: 1000,
            ablations: false,
        }
    }

    /// A smoke run that finishes in a few minutes on 2 cores: few iterations, little data,
    /// and 64-64 networks with batch 256 (the service's 256-256/512 is ~5x slower per step).
    pub fn quick() -> BenchConfig {
        let mut overrides = serde_json::Map::new();
        overrides.insert("batch_size".into(), 256.into());
        overrides.insert("hidden_sizes".into(), serde_json::json!([64, 64]));
        BenchConfig {
            overrides,
            seeds: 2,
            iterations: 300,
            data: DataSize::QUICK,
            eval_episodes: 50,
            record_every: 100,
            ..BenchConfig::full()
        }
    }

    /// The table's rows in order: every configured algorithm, then with `ablations` the
    /// ablation rows ([`Variant::ABLATIONS`]): BC (preferred only) always, the SafeDICE ones
    /// when SafeDICE is among the algorithms (`--algorithms bc --ablations` is the quick
    /// check of whether an environment can be imitated at the budget).
    pub fn rows(&self) -> Vec<(Algorithm, Variant)> {
        let standard = self.algorithms.iter().map(|&a| (a, Variant::Standard));
        let ablations = Variant::ABLATIONS.iter().copied().filter(|&(algorithm, variant)| {
            self.ablations
                && (variant == Variant::PreferredOnly || self.algorithms.contains(&algorithm))
        });
        standard.chain(ablations).collect()
    }

    /// The JSON `config` handed to [`crate::algo::resolve_config`] for one training of
    /// `algorithm`: the overrides this algorithm has (a `--config` key of SafeDICE's leaves the
    /// BC rows alone), the seed and the iterations.
    pub fn training_config(&self, algorithm: Algorithm, seed: u64) -> serde_json::Value {
        let known = crate::algo::config_keys(algorithm);
        let mut config = self.overrides.clone();
        config.retain(|key, _| known.contains(key));
        config.insert("seed".into(), seed.into());
        config.insert("iterations".into(), self.iterations.into());
        serde_json::Value::Object(config)
    }
}

/// `safedice bench` arguments.
#[derive(Clone, Debug, clap::Args)]
pub struct BenchArgs {
    /// Environments: `all` or a comma-separated list (six-rooms, point-goal, cartpole-slider).
    #[arg(long, default_value = "all")]
    pub envs: String,
    /// Algorithms: `all` or a comma-separated list (safedice, bc, dwbc, ppl, dexperts).
    #[arg(long, default_value = "all")]
    pub algorithms: String,
    /// Training seeds per algorithm (0..N). Default: 5 (2 with --quick).
    #[arg(long)]
    pub seeds: Option<u64>,
    /// Small smoke-test run (300 iterations, 40+40/10 episodes of data, 50 evaluation
    /// episodes, 64-64 networks with batch 256): a few minutes on 2 cores.
    #[arg(long)]
    pub quick: bool,
    /// Output directory for results.md, results.json and the plots.
    #[arg(long, default_value = "bench")]
    pub out: PathBuf,
    /// Policy-learning iterations per training. Default: 1000000 (300 with --quick).
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Evaluation episodes per policy. Default: 500 (50 with --quick).
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Preferred episodes in the unlabeled set. Default: 1000 (40 with --quick).
    #[arg(long)]
    pub preferred: Option<usize>,
    /// Non-preferred episodes in the unlabeled set. Default: 1000 (40 with --quick).
    #[arg(long)]
    pub non_preferred: Option<usize>,
    /// Labeled non-preferred episodes. Default: 50 (10 with --quick).
    #[arg(long)]
    pub labeled: Option<usize>,
    /// Seed of the generated data.
    #[arg(long, default_value_t = 0)]
    pub data_seed: u64,
    /// Trainings run in parallel, one thread each.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Evaluate deterministic actions (tanh(mean) / argmax) instead of sampling.
    #[arg(long)]
    pub deterministic: bool,
    /// Override the service default minibatch size (512) of every algorithm.
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Override the service default hidden layer widths (256,256) of every network.
    #[arg(long, value_delimiter = ',')]
    pub hidden_sizes: Option<Vec<usize>>,
    /// Further config keys, as a JSON object (e.g. '{"discriminator_iterations": 500}'); each
    /// training takes the keys its algorithm has (every row of an ablation run too); for
    /// diagnostics.
    #[arg(long)]
    pub config: Option<String>,
    /// Also train, per environment and seed, the ablation rows that use the generator's ground
    /// truth: BC on the preferred episodes of D^U only, SafeDICE with α set to the true
    /// non-preferred share of D^U's transitions, and SafeDICE with the optimal discriminator of
    /// the true labels; and report every SafeDICE run's discriminator ROC AUC (held-out labeled
    /// set and D^U) and the share of its weights on non-preferred transitions.
    #[arg(long)]
    pub ablations: bool,
}

impl BenchArgs {
    /// The configuration these arguments describe.
    pub fn to_config(&self) -> Result<BenchConfig, BenchError> {
        let base = if self.quick { BenchConfig::quick() } else { BenchConfig::full() };
        let envs = parse_list(&self.envs, &base.envs, |name| {
            crate::envs::make(name, 0).map(|_| name.to_string()).map_err(|e| e.to_string())
        })?;
        let algorithms = parse_list(&self.algorithms, &base.algorithms, |name| {
            serde_json::from_value(serde_json::Value::String(name.to_string())).map_err(|_| {
                format!("unknown algorithm `{name}` (known: safedice, bc, dwbc, ppl, dexperts)")
            })
        })?;
        let data = DataSize {
            preferred: self.preferred.unwrap_or(base.data.preferred),
            non_preferred: self.non_preferred.unwrap_or(base.data.non_preferred),
            labeled: self.labeled.unwrap_or(base.data.labeled),
        };
        let mut overrides = base.overrides.clone();
        if let Some(b) = self.batch_size {
            overrides.insert("batch_size".into(), b.into());
        }
        if let Some(h) = &self.hidden_sizes {
            overrides.insert("hidden_sizes".into(), h.clone().into());
        }
        if let Some(text) = &self.config {
            match serde_json::from_str(text) {
                Ok(serde_json::Value::Object(extra)) => overrides.extend(extra),
                _ => {
                    return Err(BenchError::Config(format!(
                        "--config must be a JSON object, got {text}"
                    )))
                }
            }
        }
        let unknown_to_all = |key: &String| {
            let rows = [Algorithm::Bc].into_iter().chain(algorithms.iter().copied());
            !rows.map(crate::algo::config_keys).any(|keys| keys.contains(key))
        };
        if let Some(key) = overrides.keys().find(|&k| unknown_to_all(k)) {
            return Err(BenchError::Config(format!(
                "--config key `{key}` belongs to none of the selected algorithms"
            )));
        }
        let config = BenchConfig {
            envs,
            overrides,
            algorithms,
            seeds: self.seeds.unwrap_or(base.seeds),
            iterations: self.iterations.unwrap_or(base.iterations),
            data,
            data_seed: self.data_seed,
            eval_episodes: self.episodes.unwrap_or(base.eval_episodes),
            deterministic_eval: self.deterministic,
            threads: self.threads,
            ablations: self.ablations,
            ..base
        };
        config.validate()?;
        Ok(config)
    }
}

impl BenchConfig {
    /// Rejects configurations that cannot produce a table.
    pub fn validate(&self) -> Result<(), BenchError> {
        let bad = |m: &str| Err(BenchError::Config(m.to_string()));
        if self.seeds == 0 {
            return bad("--seeds must be at least 1");
        }
        if self.threads == 0 {
            return bad("--threads must be at least 1");
        }
        if self.data.labeled == 0 && self.algorithms.iter().any(|a| a.needs_non_preferred()) {
            return bad("--labeled must be at least 1: every algorithm but BC needs D^N");
        }
        if self.ablations && (self.data.preferred == 0 || self.data.labeled == 0) {
            return bad("--ablations needs preferred episodes (BC on them) and --labeled >= 1");
        }
        if self.data.preferred + self.data.non_preferred == 0 {
            return bad("the unlabeled set needs at least one episode");
        }
        if self.eval_episodes == 0 || self.eval_episodes > crate::envs::metrics::MAX_EPISODES {
            return bad("--episodes must be between 1 and 100000");
        }
        Ok(())
    }
}

/// `all` or a comma-separated list, each item checked by `parse`.
fn parse_list<T: Clone>(
    text: &str,
    all: &[T],
    parse: impl Fn(&str) -> Result<T, String>,
) -> Result<Vec<T>, BenchError> {
    if text.trim() == "all" {
        return Ok(all.to_vec());
    }
    let items: Vec<T> = text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| parse(s).map_err(BenchError::Config))
        .collect::<Result<_, _>>()?;
    if items.is_empty() {
        return Err(BenchError::Config(format!("empty list `{text}`")));
    }
    Ok(items)
}

/// `safedice bench`: runs the configured benchmark and writes its outputs; `command` is the
/// command line recorded in results.md.
pub fn run_cli(args: &BenchArgs, command: &str) -> anyhow::Result<()> {
    let config = args.to_config()?;
    // One thread per training: candle's own pools collapse under load (docs/performance.md,
    // "Threads"), and the benchmark already runs `threads` trainings side by side.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let results = run(&config)?;
    let summary = summarize(&results);
    let written = write_outputs(&results, &summary, &args.out, command)?;
    print!("{}", report::console_table(&summary));
    for path in written {
        println!("wrote {}", path.display());
    }
    Ok(())
}
