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
pub mod resume;
pub mod robustness;
pub mod runner;
pub mod speed;
pub mod summary;
pub mod tabular;

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
    /// Add a "SafeDICE (paper preset)" row (the robustness suite reports it beside the service
    /// defaults).
    pub paper_preset_row: bool,
    /// Add the "BC (preferred only)" row (and the ground truth it needs) without the other
    /// ablation rows; the robustness suite's ceiling.
    pub preferred_only_row: bool,
    /// SafeDICE's discriminator steps as a share of each training's policy iterations, in
    /// place of the preset's (for comparing candidate defaults across tasks of different
    /// lengths); None keeps the preset's.
    pub discriminator_share: Option<f64>,
    /// SafeDICE's α in place of alpha-hat in its standard rows (the estimate is still made and
    /// recorded as `alpha_hat_estimated`): a study of the weighting at one α across tasks;
    /// None estimates it as the service does.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fixed_alpha: Option<f64>,
    /// Where each finished training's result is appended as a JSON line as it ends (so a run
    /// cut short still leaves its data): `runs.jsonl` in the output directory.
    #[serde(skip)]
    pub runs_log: Option<PathBuf>,
    /// Keep the trainings `runs_log` already holds from an earlier invocation cut short, after
    /// checking its recorded configuration ([`resume`]), and train the rest; a fresh start
    /// empties the log instead.
    #[serde(skip)]
    pub resume: bool,
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
            paper_preset_row: false,
            preferred_only_row: false,
            discriminator_share: None,
            fixed_alpha: None,
            runs_log: None,
            resume: false,
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
            let preferred_only = variant == Variant::PreferredOnly;
            (self.ablations && (preferred_only || self.algorithms.contains(&algorithm)))
                || (self.preferred_only_row && preferred_only)
        });
        let paper = (self.paper_preset_row && self.algorithms.contains(&Algorithm::Safedice))
            .then_some((Algorithm::Safedice, Variant::PaperPreset));
        standard.chain(paper).chain(ablations).collect()
    }

    /// The JSON `config` handed to [`crate::algo::resolve_config`] for one training of
    /// `algorithm`: the overrides this algorithm has (a `--config` key of SafeDICE's leaves the
    /// BC rows alone), the seed and the iterations; the `paper` preset for
    /// [`Variant::PaperPreset`] rows (which take only the network and batch overrides).
    pub fn training_config(
        &self,
        algorithm: Algorithm,
        variant: Variant,
        seed: u64,
    ) -> serde_json::Value {
        let known = crate::algo::config_keys(algorithm);
        let mut config = self.overrides.clone();
        config.retain(|key, _| known.contains(key));
        if variant == Variant::PaperPreset {
            config.retain(|key, _| key == "batch_size" || key == "hidden_sizes");
            config.insert("preset".into(), "paper".into());
        }
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
    /// How many training seeds per algorithm (seeds 0..N). Default: 5 (2 with --quick).
    /// (`--seeds` is its former name.)
    #[arg(long = "seed-count", alias = "seeds", value_name = "N")]
    pub seeds: Option<u64>,
    /// Small smoke-test run (300 iterations, 40+40/10 episodes of data, 50 evaluation
    /// episodes, 64-64 networks with batch 256): a few minutes on 2 cores.
    #[arg(long)]
    pub quick: bool,
    /// Output directory for results.md, results.json and the plots. Default: `bench-results`
    /// (`bench-results/robustness` with --suite). A directory that already holds files is
    /// refused unless --force (the committed results in `bench/` are not overwritten by
    /// accident).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write into --out even if it already holds files (replacing the results there).
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// Go on with a run cut short in --out: keep the trainings its runs.jsonl holds and train
    /// the rest, with the same options (checked against the bench-config.json it recorded;
    /// only --parallel may differ, and --seed-count may grow: the seeds it adds are trained).
    /// Not with --suite tabular.
    #[arg(long)]
    pub resume: bool,
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
    /// Trainings run side by side, one thread each (`speed --threads` is compute threads of
    /// one training; `--threads` here is this option's former name).
    #[arg(long = "parallel", alias = "threads", value_name = "N", default_value_t = 2)]
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
    /// Run a generated task suite instead of the built-in environments: `robustness` (the
    /// suite defaults are chosen on; see docs/algorithm.md). Its own defaults: 5000
    /// iterations, 2 seeds, 100 evaluation episodes, 64-64 networks, batch 256, and the rows
    /// SafeDICE, SafeDICE (paper preset), BC, BC (preferred only), DWBC and PPL.
    #[arg(long, value_enum)]
    pub suite: Option<SuiteName>,
    /// With --suite: which split(s) to run. Choose defaults on `dev`; report `test` once.
    #[arg(long, value_enum, default_value = "dev")]
    pub split: SplitArg,
    /// With --suite: tasks per split (at most 24; up to 96 on the development split alone, an
    /// extended split for studying a family on more draws, never for reporting).
    #[arg(long, default_value_t = crate::envs::suite::TASKS_PER_SPLIT)]
    pub tasks: usize,
    /// With --suite: only these task families (e.g. `grid-continuing,pace`), for a study of one
    /// family on the development split; every family by default.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub families: Vec<FamilyArg>,
    /// With --suite: leave out the "SafeDICE (paper preset)" row (e.g. when comparing
    /// candidate defaults on the development split).
    #[arg(long)]
    pub no_paper_row: bool,
    /// SafeDICE's discriminator steps as a share of each training's policy iterations (e.g.
    /// 0.1), in place of the preset's: a candidate default on the suite's tasks of different
    /// lengths.
    #[arg(long)]
    pub discriminator_share: Option<f64>,
    /// SafeDICE's α, fixed in place of alpha-hat in its rows (e.g. 0.000001, the limit as α goes
    /// to 0): a study of the weighting stage at one α on every task, never a default.
    #[arg(long)]
    pub fixed_alpha: Option<f64>,
}

/// The generated suites of `--suite`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SuiteName {
    /// The generated task suite defaults are chosen on (bench/robustness/).
    Robustness,
    /// The paper's tabular check on six-rooms (Appendix G), solved exactly.
    Tabular,
}

/// `--families`: the generated suite's task families.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FamilyArg {
    Grid,
    GridContinuing,
    Nav,
    Pace,
}

impl FamilyArg {
    /// The family's name in task ids (`dev-01-grid-continuing`).
    pub fn name(self) -> &'static str {
        match self {
            FamilyArg::Grid => "grid",
            FamilyArg::GridContinuing => "grid-continuing",
            FamilyArg::Nav => "nav",
            FamilyArg::Pace => "pace",
        }
    }
}

/// `--split`: one half of the suite, or both.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SplitArg {
    Dev,
    Test,
    Both,
}

impl SplitArg {
    pub fn splits(self) -> Vec<crate::envs::suite::Split> {
        use crate::envs::suite::Split;
        match self {
            SplitArg::Dev => vec![Split::Dev],
            SplitArg::Test => vec![Split::Test],
            SplitArg::Both => vec![Split::Dev, Split::Test],
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            SplitArg::Dev => "dev",
            SplitArg::Test => "test",
            SplitArg::Both => "both",
        }
    }
}

impl BenchArgs {
    /// The robustness suite's configuration: its defaults, overlaid with the arguments given.
    pub fn to_suite_config(&self) -> Result<BenchConfig, BenchError> {
        let base = robustness::default_config();
        let most = self.split.splits().iter().map(|s| s.max_tasks()).min().unwrap_or(0);
        if self.tasks == 0 || self.tasks > most {
            return Err(BenchError::Config(format!(
                "--tasks must be between 1 and {most} with --split {} (only the development \
                 split extends beyond {})",
                self.split.as_str(),
                crate::envs::suite::TASKS_PER_SPLIT
            )));
        }
        let algorithms = if self.algorithms.trim() == "all" {
            base.algorithms.clone()
        } else {
            parse_list(&self.algorithms, &base.algorithms, parse_algorithm)?
        };
        let mut overrides = base.overrides.clone();
        self.extend_overrides(&mut overrides, &algorithms)?;
        let config = BenchConfig {
            algorithms,
            overrides,
            seeds: self.seeds.unwrap_or(base.seeds),
            iterations: self.iterations.unwrap_or(base.iterations),
            eval_episodes: self.episodes.unwrap_or(base.eval_episodes),
            deterministic_eval: self.deterministic,
            threads: self.threads,
            ablations: self.ablations,
            paper_preset_row: !self.no_paper_row,
            discriminator_share: self.discriminator_share,
            fixed_alpha: self.fixed_alpha,
            ..base
        };
        config.validate()?;
        Ok(config)
    }

    /// `--batch-size`, `--hidden-sizes` and `--config` into `overrides`; a `--config` key no
    /// selected algorithm (nor BC) has is refused.
    fn extend_overrides(
        &self,
        overrides: &mut serde_json::Map<String, serde_json::Value>,
        algorithms: &[Algorithm],
    ) -> Result<(), BenchError> {
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
        Ok(())
    }

    /// The configuration these arguments describe.
    pub fn to_config(&self) -> Result<BenchConfig, BenchError> {
        let base = if self.quick { BenchConfig::quick() } else { BenchConfig::full() };
        let envs = parse_list(&self.envs, &base.envs, |name| {
            crate::envs::make(name, 0).map(|_| name.to_string()).map_err(|e| e.to_string())
        })?;
        let algorithms = parse_list(&self.algorithms, &base.algorithms, parse_algorithm)?;
        let data = DataSize {
            preferred: self.preferred.unwrap_or(base.data.preferred),
            non_preferred: self.non_preferred.unwrap_or(base.data.non_preferred),
            labeled: self.labeled.unwrap_or(base.data.labeled),
        };
        let mut overrides = base.overrides.clone();
        self.extend_overrides(&mut overrides, &algorithms)?;
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
            discriminator_share: self.discriminator_share,
            fixed_alpha: self.fixed_alpha,
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
            return bad("--seed-count must be at least 1");
        }
        if self.discriminator_share.is_some_and(|s| !(s > 0.0 && s <= 100.0)) {
            return bad("--discriminator-share must be in (0, 100]");
        }
        if self.fixed_alpha.is_some_and(|a| !(0.0..1.0).contains(&a)) {
            return bad("--fixed-alpha must be in [0, 1)");
        }
        if self.threads == 0 {
            return bad("--parallel must be at least 1");
        }
        if self.data.labeled == 0 && self.algorithms.iter().any(|a| a.needs_non_preferred()) {
            return bad("--labeled must be at least 1: every algorithm but BC needs D^N");
        }
        if (self.ablations || self.preferred_only_row)
            && (self.data.preferred == 0 || self.data.labeled == 0)
        {
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

fn parse_algorithm(name: &str) -> Result<Algorithm, String> {
    Algorithm::from_name(name).ok_or_else(|| {
        format!("unknown algorithm `{name}` (known: {})", Algorithm::names().join(", "))
    })
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

/// Refuses an output directory that already holds files unless `force`: a run from the
/// repository's root with `--out bench` would otherwise replace the committed results.
fn check_out(out: &std::path::Path, force: bool) -> anyhow::Result<()> {
    let mut files: Vec<String> = match std::fs::read_dir(out) {
        Ok(entries) => entries
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect(),
        Err(_) => return Ok(()),
    };
    if files.is_empty() || force {
        return Ok(());
    }
    files.sort();
    let shown = files.iter().take(4).cloned().collect::<Vec<_>>().join(", ");
    anyhow::bail!(
        "{} already holds files ({shown}{}); pass --force to replace the results there, or \
         choose another --out",
        out.display(),
        if files.len() > 4 { ", ..." } else { "" }
    )
}

/// `safedice bench`: runs the configured benchmark and writes its outputs; `command` is the
/// command line recorded in results.md.
pub fn run_cli(args: &BenchArgs, command: &str) -> anyhow::Result<()> {
    // One thread per training: candle's own pools collapse under load (docs/performance.md,
    // "Threads of one job"), and the benchmark already runs `threads` trainings side by side
    // (each at the presets' `threads`: 1).
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let default_out = match args.suite {
        Some(_) => "bench-results/robustness",
        None => "bench-results",
    };
    let out = args.out.clone().unwrap_or_else(|| PathBuf::from(default_out));
    if !args.resume {
        check_out(&out, args.force)?;
    }
    if let Some(SuiteName::Tabular) = args.suite {
        anyhow::ensure!(!args.resume, "--resume: the tabular check runs in seconds; run it afresh");
        let iterations = args.iterations.unwrap_or(5000);
        for path in tabular::run_cli(iterations, args.data_seed, &out, command)? {
            println!("wrote {}", path.display());
        }
        return Ok(());
    }
    let runs_log = Some(out.join("runs.jsonl"));
    if let Some(SuiteName::Robustness) = args.suite {
        let config = BenchConfig { runs_log, resume: args.resume, ..args.to_suite_config()? };
        let splits = args.split.splits();
        let families: Vec<&str> = args.families.iter().map(|f| f.name()).collect();
        let selection = robustness::Selection { splits: &splits, count: args.tasks, families };
        let written = robustness::run_cli(config, &selection, &out, command)?;
        for path in written {
            println!("wrote {}", path.display());
        }
        return Ok(());
    }
    let config = BenchConfig { runs_log, resume: args.resume, ..args.to_config()? };
    let results = run(&config)?;
    let summary = summarize(&results);
    let written = write_outputs(&results, &summary, &out, command)?;
    print!("{}", report::console_table(&summary));
    for path in written {
        println!("wrote {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_directory_with_files_is_only_written_with_force() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("results");
        check_out(&out, false).expect("a directory that does not exist yet");
        std::fs::create_dir(&out).unwrap();
        check_out(&out, false).expect("an empty directory");
        std::fs::write(out.join("results.md"), "earlier").unwrap();
        let refused = check_out(&out, false).unwrap_err().to_string();
        assert!(refused.contains("already holds files (results.md)"), "{refused}");
        assert!(refused.contains("--force"), "{refused}");
        check_out(&out, true).expect("--force");
    }

    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        bench: BenchArgs,
    }

    fn suite_config(args: &[&str]) -> Result<BenchConfig, BenchError> {
        use clap::Parser;
        let argv = ["bench", "--suite", "robustness"].iter().chain(args);
        Cli::try_parse_from(argv).expect("the arguments parse").bench.to_suite_config()
    }

    #[test]
    fn only_the_development_split_extends_beyond_its_standard_tasks() {
        suite_config(&["--split", "dev", "--tasks", "96"]).expect("the extended development split");
        for split in ["test", "both"] {
            suite_config(&["--split", split, "--tasks", "24"]).expect("the standard split");
            let Err(BenchError::Config(refused)) =
                suite_config(&["--split", split, "--tasks", "25"])
            else {
                panic!("--split {split} --tasks 25 is refused");
            };
            assert!(refused.contains("between 1 and 24 with --split"), "{refused}");
        }
        let Err(BenchError::Config(refused)) = suite_config(&["--tasks", "97"]) else {
            panic!("97 development tasks are refused");
        };
        assert!(refused.contains("between 1 and 96"), "{refused}");
    }
}
