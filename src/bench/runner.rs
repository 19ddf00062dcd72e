//! Data generation, training and evaluation of every (environment, algorithm, seed), spread over
//! a few worker threads.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::ablation::{self, SafediceAblation, Variant};
use super::resume;
use super::BenchConfig;
use super::DataSize;
use crate::algo::flops::StepShape;
use crate::algo::safedice::{oracle_logits, SafediceOverrides, SafediceTrainer};
use crate::algo::{self, Algorithm, Policy, TrainError, Trainer, TrainingData};
use crate::data::Dataset;
use crate::envs::{self, DatagenSpec, GroupProfile, Metrics, ReferenceStats, Task};

/// Why the benchmark stopped.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("{0}")]
    Config(String),
    #[error("{env}: data generation failed: {message}")]
    Datagen { env: String, message: String },
    #[error("{env}/{label}/seed {seed}: {message}")]
    Run { env: String, label: String, seed: u64, message: String },
}

/// The generated data of one environment, as the report describes it.
#[derive(Clone, Debug, Serialize)]
pub struct EnvData {
    pub env: String,
    pub unlabeled_preferred: GroupProfile,
    pub unlabeled_non_preferred: GroupProfile,
    pub labeled_non_preferred: GroupProfile,
    pub reference: ReferenceStats,
    pub datagen_seconds: f64,
    /// With `--ablations`: the ground truth the ablation rows use.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ablation: Option<AblationData>,
}

/// The ground truth of one environment's ablations (`--ablations`).
#[derive(Clone, Debug, Serialize)]
pub struct AblationData {
    /// Non-preferred share of D^U's transitions: the α* that Eq. 15 estimates, used by the
    /// "SafeDICE (true α)" row.
    pub true_alpha: f64,
    /// The same share counted in episodes (for comparison only; not what Eq. 15 estimates).
    pub non_preferred_episode_share: f64,
    /// The held-out labeled set of the discriminator's AUC: its data seed and its
    /// preferred / non-preferred transitions.
    pub heldout_seed: u64,
    pub heldout_preferred_transitions: usize,
    pub heldout_non_preferred_transitions: usize,
}

/// Where SafeDICE's alpha-hat came from (Eq. 15), from the trainer's recorded scalars.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AlphaDiagnostics {
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub alpha_hat: f64,
    /// `min over D^U of e^{-logit}`: the statistic alpha-hat is (the minimum minus 1e-5).
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub min_ratio: f64,
    /// The 1% quantile of the same ratio (diagnostic, not the paper).
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub quantile_01: f64,
    /// D^U episode holding the minimum, and whether it is a non-preferred one (ground truth the
    /// learner never sees, from the data generator's manifest).
    pub argmin_episode: u32,
    pub argmin_episode_is_non_preferred: bool,
    /// Effective sample size of the policy weights as a fraction of the batch, averaged over
    /// the recorded policy steps, and at the last one.
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub ess_fraction_mean: f64,
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub ess_fraction_last: f64,
    /// Rows of D^U whose Eq. 10 reward is undefined (floored or excluded; 0 with the paper's
    /// alpha-hat).
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub reward_clipped_rows: f64,
    /// With the `bbe` estimator (NaN otherwise): alpha-hat's confidence interval, the
    /// discriminator's held-out AUC, and whether the weighting fell back to uniform (1).
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub alpha_hat_lower: f64,
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub alpha_hat_upper: f64,
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub heldout_auc: f64,
    #[serde(deserialize_with = "resume::nan_if_null")]
    pub weighting_uniform: f64,
}

/// One trained and evaluated policy (a line of `runs.jsonl`, read back by [`resume`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunResult {
    pub env: String,
    pub algorithm: Algorithm,
    /// `standard`, or the ablation this run is (`--ablations`).
    pub variant: Variant,
    pub seed: u64,
    /// Training steps, every phase included.
    pub steps: u64,
    pub train_seconds: f64,
    pub eval_seconds: f64,
    pub metrics: Metrics,
    pub mean_episode_length: f64,
    /// SafeDICE only.
    pub alpha: Option<AlphaDiagnostics>,
    /// SafeDICE runs with `--ablations`: discriminator AUCs and the weights' non-preferred share.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ablation: Option<SafediceAblation>,
    /// The trainer's last recorded scalars (losses and the like).
    #[serde(deserialize_with = "resume::nan_if_null_values")]
    pub last_recorded: BTreeMap<String, f64>,
}

impl RunResult {
    pub fn steps_per_second(&self) -> f64 {
        self.steps as f64 / self.train_seconds.max(1e-9)
    }

    /// The row's name ("SafeDICE", "SafeDICE (true α)", ...).
    pub fn label(&self) -> String {
        self.variant.label(self.algorithm)
    }
}

/// Everything a benchmark run produced.
#[derive(Clone, Debug, Serialize)]
pub struct BenchResults {
    pub config: BenchConfig,
    pub data: Vec<EnvData>,
    /// In (env, algorithm, seed) order of the configuration.
    pub runs: Vec<RunResult>,
    pub started: chrono::DateTime<chrono::Utc>,
    /// `git rev-parse --short=12 HEAD` when the run started ("unknown" outside a checkout).
    pub git_commit: String,
    /// The commit the running binary was built from ([`crate::BUILD_COMMIT`]); differs from
    /// `git_commit` when the tree moved on after the build.
    pub build_commit: String,
    /// The CPU the run trained on ([`machine`]); speed ratios change with it.
    pub machine: String,
    /// This invocation's wall time (a resumed run's earlier part not counted).
    pub wall_seconds: f64,
    /// Trainings kept from an earlier invocation's runs log (`--resume`), not trained again.
    pub resumed_runs: usize,
}

/// A generated dataset and the ground truth the diagnostics need.
struct Prepared {
    data: TrainingData,
    non_preferred_ids: Vec<u32>,
    /// With `--ablations`.
    truth: Option<Truth>,
}

/// What the ablation rows know and a learner never does.
struct Truth {
    /// Per row of D^U: whether the non-preferred demonstrator made it.
    unlabeled_non_preferred: Vec<bool>,
    true_alpha: f64,
    /// D^U's preferred episodes alone (and D^N, unused by BC).
    preferred_only: TrainingData,
    /// Fresh preferred and non-preferred episodes with their per-row flags.
    heldout: Dataset,
    heldout_non_preferred: Vec<bool>,
}

/// One training to do.
#[derive(Clone, Copy)]
struct Job {
    env: usize,
    algorithm: Algorithm,
    variant: Variant,
    seed: u64,
}

impl Job {
    /// Whether `run` is this job's training (environments named by `names`, in job order).
    fn trains(&self, names: &[String], run: &RunResult) -> bool {
        names.get(self.env) == Some(&run.env)
            && (run.algorithm, run.variant, run.seed) == (self.algorithm, self.variant, self.seed)
    }
}

/// One environment of a run: where its episodes come from, the statistics its metrics are
/// normalised with, and how much data to generate.
pub struct BenchTask {
    pub task: Box<dyn Task>,
    pub reference: ReferenceStats,
    pub data: DataSize,
    /// Policy iterations of this task's trainings, in place of the configuration's.
    pub iterations: Option<u64>,
}

impl BenchTask {
    /// A built-in environment with the configuration's data size.
    pub fn registered(name: &str, data: DataSize) -> Result<BenchTask, BenchError> {
        let datagen = |e: envs::UnknownEnv| BenchError::Datagen {
            env: name.to_string(),
            message: e.to_string(),
        };
        let task = envs::Registered::get(name).map_err(datagen)?;
        let reference = envs::reference_stats(name).map_err(datagen)?;
        Ok(BenchTask { task: Box::new(task), reference, data, iterations: None })
    }
}

/// Generates the data, then trains and evaluates every (environment, algorithm, seed) on
/// `config.threads` threads. The first failing run stops the benchmark.
pub fn run(config: &BenchConfig) -> Result<BenchResults, BenchError> {
    let tasks = config
        .envs
        .iter()
        .map(|env| BenchTask::registered(env, config.data))
        .collect::<Result<Vec<_>, _>>()?;
    run_tasks(config, &tasks)
}

/// [`run`] over any tasks (`config.envs` is not read: the tasks name themselves).
pub fn run_tasks(config: &BenchConfig, tasks: &[BenchTask]) -> Result<BenchResults, BenchError> {
    config.validate()?;
    let started = chrono::Utc::now();
    let git_commit = git_commit();
    let clock = Instant::now();
    let mut prepared = Vec::new();
    let mut data = Vec::new();
    for task in tasks {
        let (p, d) = prepare(config, task)?;
        prepared.push(p);
        data.push(d);
    }
    let names: Vec<String> = tasks.iter().map(|t| t.task.name()).collect();
    let earlier: Vec<RunResult> = resume::earlier_runs(config).map_err(BenchError::Config)?;
    let is_done = |job: &Job| earlier.iter().any(|r| job.trains(&names, r));
    let (done, jobs): (Vec<Job>, Vec<Job>) =
        schedule(config, tasks.len()).into_iter().partition(is_done);
    if !done.is_empty() {
        tracing::info!(kept = done.len(), left = jobs.len(), "bench: resuming from the runs log");
    }
    let kept: Vec<RunResult> =
        earlier.into_iter().filter(|r| done.iter().any(|j| j.trains(&names, r))).collect();
    let resumed_runs = kept.len();
    let mut runs = run_jobs(config, tasks, &prepared, &jobs)?;
    runs.extend(kept);
    sort_runs(config, &names, &mut runs);
    Ok(BenchResults {
        config: config.clone(),
        data,
        runs,
        started,
        git_commit,
        build_commit: crate::BUILD_COMMIT.to_string(),
        machine: machine(),
        wall_seconds: clock.elapsed().as_secs_f64(),
        resumed_runs,
    })
}

/// Runs in the table's order: environment, row, seed.
fn sort_runs(config: &BenchConfig, names: &[String], runs: &mut [RunResult]) {
    let env_index = |name: &str| names.iter().position(|e| e == name);
    let rows = config.rows();
    let row_index = |r: &RunResult| rows.iter().position(|&row| row == (r.algorithm, r.variant));
    runs.sort_by_key(|r| (env_index(&r.env), row_index(r), r.seed));
}

/// This machine's CPU as `lscpu` names it (model name, family, model), its core count, from
/// /proc/cpuinfo, and the GEMM kernels it runs (results are bit-identical only between runs on
/// the same kernels); "unknown" where that file does not exist.
pub fn machine() -> String {
    let Ok(info) = std::fs::read_to_string("/proc/cpuinfo") else {
        return "unknown".to_string();
    };
    let field = |key: &str| {
        info.lines()
            .find(|l| l.split(':').next().is_some_and(|k| k.trim() == key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
            .unwrap_or_else(|| "?".to_string())
    };
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    format!(
        "{}, CPU family {} model {}, {cores} cores, {} GEMM kernels",
        field("model name"),
        field("cpu family"),
        field("model"),
        crate::algo::fused_mlp::gemm_kernels()
    )
}

/// The commit checked out where the benchmark runs: `git rev-parse`, else `.git/HEAD` read
/// directly (git refuses a checkout owned by another user, as in a container), else "unknown".
fn git_commit() -> String {
    git_rev_parse().or_else(head_from_git_dir).unwrap_or_else(|| "unknown".to_string())
}

fn git_rev_parse() -> Option<String> {
    std::process::Command::new("git")
        .args(["rev-parse", "--short=12", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
}

/// HEAD from the nearest `.git` directory up from the working directory: a detached hash, or
/// the branch's ref file, or its line in `packed-refs`.
fn head_from_git_dir() -> Option<String> {
    let cwd = std::env::current_dir().ok()?;
    let git = cwd.ancestors().map(|dir| dir.join(".git")).find(|git| git.is_dir())?;
    let head = std::fs::read_to_string(git.join("HEAD")).ok()?;
    let hash = match head.trim().strip_prefix("ref: ") {
        None => head.trim().to_string(),
        Some(name) => match std::fs::read_to_string(git.join(name)) {
            Ok(hash) => hash.trim().to_string(),
            Err(_) => std::fs::read_to_string(git.join("packed-refs"))
                .ok()?
                .lines()
                .find_map(|l| l.strip_suffix(name)?.strip_suffix(' ').map(str::to_string))?,
        },
    };
    let short = hash.get(..12)?;
    short.chars().all(|c| c.is_ascii_hexdigit()).then(|| short.to_string())
}

fn prepare(config: &BenchConfig, task: &BenchTask) -> Result<(Prepared, EnvData), BenchError> {
    let clock = Instant::now();
    let name = task.task.name();
    let env = name.as_str();
    let spec = DatagenSpec {
        env: name.clone(),
        preferred: task.data.preferred,
        non_preferred: task.data.non_preferred,
        labeled: task.data.labeled,
        seed: config.data_seed,
    };
    let generated = envs::generate_task(task.task.as_ref(), &spec, task.reference.clone())
        .map_err(|e| BenchError::Datagen { env: name.clone(), message: e.to_string() })?;
    let m = generated.manifest;
    tracing::info!(
        env,
        preferred_cost = m.unlabeled_preferred.mean_cost,
        non_preferred_cost = m.unlabeled_non_preferred.mean_cost,
        transitions = generated.unlabeled.len(),
        "bench: data generated"
    );
    let non_preferred = generated.labeled_non_preferred.map(Arc::new);
    let data = TrainingData { unlabeled: Arc::new(generated.unlabeled), non_preferred };
    let ids = m.unlabeled_non_preferred_episode_ids;
    let (truth, ablation) = if config.ablations || config.preferred_only_row {
        let (truth, summary) = ground_truth(config, task, &data, &ids)?;
        (Some(truth), Some(summary))
    } else {
        (None, None)
    };
    let prepared = Prepared { data, non_preferred_ids: ids, truth };
    let summary = EnvData {
        env: env.to_string(),
        unlabeled_preferred: m.unlabeled_preferred,
        unlabeled_non_preferred: m.unlabeled_non_preferred,
        labeled_non_preferred: m.labeled_non_preferred,
        reference: m.reference,
        datagen_seconds: clock.elapsed().as_secs_f64(),
        ablation,
    };
    Ok((prepared, summary))
}

/// The ablations' ground truth: D^U's per-row flags and true α, its preferred episodes as a
/// dataset, and the held-out labeled set (see [`ablation::HELDOUT_STREAM`]).
fn ground_truth(
    config: &BenchConfig,
    task: &BenchTask,
    data: &TrainingData,
    non_preferred_ids: &[u32],
) -> Result<(Truth, AblationData), BenchError> {
    let env = task.task.name();
    let datagen = |message: String| BenchError::Datagen { env: env.clone(), message };
    let u = &data.unlabeled;
    let flags = ablation::row_flags(u, non_preferred_ids);
    let true_alpha = flags.iter().filter(|&&f| f).count() as f64 / flags.len() as f64;
    let keep: Vec<bool> = flags.iter().map(|f| !f).collect();
    let preferred = ablation::select_rows(u, &keep)
        .ok_or_else(|| datagen("no preferred episode in D^U".into()))?;
    let episodes = task.data.labeled.max(ablation::HELDOUT_MIN_EPISODES);
    let heldout_seed = envs::derive_seed(config.data_seed, ablation::HELDOUT_STREAM, 0);
    let spec = DatagenSpec {
        env: env.clone(),
        preferred: episodes,
        non_preferred: episodes,
        labeled: 0,
        seed: heldout_seed,
    };
    let heldout = envs::generate_task(task.task.as_ref(), &spec, task.reference.clone())
        .map_err(|e| datagen(e.to_string()))?;
    let heldout_flags = ablation::row_flags(
        &heldout.unlabeled,
        &heldout.manifest.unlabeled_non_preferred_episode_ids,
    );
    let summary = AblationData {
        true_alpha,
        non_preferred_episode_share: non_preferred_ids.len() as f64 / u.episodes() as f64,
        heldout_seed,
        heldout_preferred_transitions: heldout.manifest.unlabeled_preferred.transitions,
        heldout_non_preferred_transitions: heldout.manifest.unlabeled_non_preferred.transitions,
    };
    let truth = Truth {
        unlabeled_non_preferred: flags,
        true_alpha,
        preferred_only: TrainingData {
            unlabeled: Arc::new(preferred),
            non_preferred: data.non_preferred.clone(),
        },
        heldout: heldout.unlabeled,
        heldout_non_preferred: heldout_flags,
    };
    Ok((truth, summary))
}

/// Every job, the costliest rows first so the last ones to finish are short. A row's cost is
/// its steps (a pretraining phase included) times its policy step's FLOPs as the algorithm's
/// module counts them, on a nominal task (the tasks' own sizes only scale every row alike).
fn schedule(config: &BenchConfig, envs: usize) -> Vec<Job> {
    let cost = |algorithm: Algorithm, variant: Variant| -> u64 {
        let training = config.training_config(algorithm, variant, 0);
        let Ok(resolved) = algo::resolve_config(algorithm, &training) else { return 0 };
        let shape = StepShape {
            obs_dim: 8,
            act_input: 2,
            policy_output: 4,
            hidden: resolved.common.hidden_sizes.clone(),
            batch: resolved.common.batch_size,
        };
        resolved.total_steps().saturating_mul((algorithm.spec().step.flops)(&shape))
    };
    let rows = config.rows();
    let mut jobs: Vec<Job> = (0..envs)
        .flat_map(|env| {
            rows.iter().flat_map(move |&(algorithm, variant)| {
                (0..config.seeds).map(move |seed| Job { env, algorithm, variant, seed })
            })
        })
        .collect();
    let costs: std::collections::HashMap<(Algorithm, Variant), u64> =
        rows.iter().map(|&(a, v)| ((a, v), cost(a, v))).collect();
    jobs.sort_by_key(|j| (std::cmp::Reverse(costs[&(j.algorithm, j.variant)]), j.seed, j.env));
    jobs
}

fn run_jobs(
    config: &BenchConfig,
    tasks: &[BenchTask],
    prepared: &[Prepared],
    jobs: &[Job],
) -> Result<Vec<RunResult>, BenchError> {
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let runs_log = resume::RunsLog::open(config.runs_log.as_deref());
    let results: Mutex<Vec<Result<RunResult, BenchError>>> = Mutex::new(Vec::new());
    let failed = std::sync::atomic::AtomicBool::new(false);
    std::thread::scope(|scope| {
        for _ in 0..config.threads.min(jobs.len()) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                if i >= jobs.len() || failed.load(Ordering::SeqCst) {
                    break;
                }
                let job = jobs[i];
                let result = train_and_evaluate(config, &tasks[job.env], &prepared[job.env], job);
                if let Ok(r) = &result {
                    runs_log.append(r);
                    tracing::info!(
                        "bench: [{}/{}] {}/{}/seed {}: normalized return {:.1}, average cost {:.2} ({:.0} s, {:.1} steps/s)",
                        done.fetch_add(1, Ordering::SeqCst) + 1,
                        jobs.len(),
                        r.env,
                        r.label(),
                        r.seed,
                        r.metrics.normalized_return,
                        r.metrics.average_cost,
                        r.train_seconds + r.eval_seconds,
                        r.steps_per_second()
                    );
                } else {
                    failed.store(true, Ordering::SeqCst);
                }
                results.lock().unwrap_or_else(|p| p.into_inner()).push(result);
            });
        }
    });
    results.into_inner().unwrap_or_else(|p| p.into_inner()).into_iter().collect()
}

/// Trains one policy to the end and evaluates it.
fn train_and_evaluate(
    config: &BenchConfig,
    task: &BenchTask,
    prepared: &Prepared,
    job: Job,
) -> Result<RunResult, BenchError> {
    let name = task.task.name();
    let env = name.as_str();
    let fail = |message: String| BenchError::Run {
        env: env.to_string(),
        label: job.variant.label(job.algorithm),
        seed: job.seed,
        message,
    };
    let train_error = |e: TrainError| fail(e.to_string());
    let mut training = config.training_config(job.algorithm, job.variant, job.seed);
    if let Some(iterations) = task.iterations {
        training["iterations"] = iterations.into();
    }
    let share = config.discriminator_share.filter(|_| job.variant != Variant::PaperPreset);
    if let (Some(share), Algorithm::Safedice) = (share, job.algorithm) {
        let iterations = training["iterations"].as_u64().unwrap_or(config.iterations);
        training["discriminator_iterations"] =
            ((iterations as f64 * share).round().max(1.0) as u64).into();
    }
    let resolved = algo::resolve_config(job.algorithm, &training).map_err(|e| fail(e.message))?;
    let truth = || prepared.truth.as_ref().ok_or_else(|| fail("ablation without truth".into()));
    let data = match job.variant {
        Variant::PreferredOnly => &truth()?.preferred_only,
        _ => &prepared.data,
    };
    let clock = Instant::now();
    // SafeDICE is built as itself, for the overrides of its ablations and the diagnostics read
    // from it after training; every other algorithm through the service's constructor.
    let (mut safedice, mut other) = if job.algorithm == Algorithm::Safedice {
        let overrides = match job.variant {
            Variant::TrueAlpha => {
                SafediceOverrides { alpha: Some(truth()?.true_alpha), ..Default::default() }
            }
            Variant::OracleLabels => SafediceOverrides {
                unlabeled_logits: Some(oracle_logits(&truth()?.unlabeled_non_preferred)),
                ..Default::default()
            },
            Variant::Standard => {
                SafediceOverrides { alpha: config.fixed_alpha, ..Default::default() }
            }
            _ => SafediceOverrides::default(),
        };
        algo::check_data(&resolved, data).map_err(|e| fail(e.message))?;
        let t = SafediceTrainer::with_overrides(&resolved, data, overrides).map_err(train_error)?;
        (Some(t), None)
    } else {
        (None, Some(algo::build_trainer(&resolved, data, None).map_err(train_error)?))
    };
    let trainer: &mut dyn Trainer = match (safedice.as_mut(), other.as_mut()) {
        (Some(t), _) => t,
        (None, Some(t)) => t.as_mut(),
        (None, None) => unreachable!("one of the two is built"),
    };
    let pretraining = resolved.pretraining_steps();
    let total = resolved.total_steps();
    let mut recorder = Recorder::default();
    while !trainer.is_finished() {
        let step = trainer.progress().step;
        // Always record the last pretraining step: it carries the alpha-hat computation.
        let record = step.is_multiple_of(config.record_every)
            || step + 1 == pretraining
            || step + 1 == total;
        let scalars = trainer.step(record).map_err(train_error)?;
        recorder.add(&scalars);
    }
    let artifact = trainer.export_policy().map_err(train_error)?;
    let train_seconds = clock.elapsed().as_secs_f64();
    let policy = Policy::load(&artifact.spec, &artifact.weights).map_err(train_error)?;
    let clock = Instant::now();
    let act = |obs: &[f32], det: bool, rng: &mut ChaCha8Rng| policy.act(obs, det, rng);
    // The evaluation seed is the training seed: every algorithm meets the same initial states.
    let report = envs::evaluate_task(
        task.task.as_ref(),
        &task.reference,
        act,
        config.eval_episodes,
        job.seed,
        config.deterministic_eval,
    )
    .map_err(|e| fail(e.to_string()))?;
    let alpha = trainer.alpha_hat().map(|value| recorder.alpha(value, &prepared.non_preferred_ids));
    let ablation = match (&safedice, &prepared.truth) {
        (Some(t), Some(truth)) => Some(safedice_ablation(t, truth).map_err(train_error)?),
        _ => None,
    };
    Ok(RunResult {
        env: env.to_string(),
        algorithm: job.algorithm,
        variant: job.variant,
        seed: job.seed,
        steps: total,
        train_seconds,
        eval_seconds: clock.elapsed().as_secs_f64(),
        metrics: report.metrics,
        mean_episode_length: report.mean_episode_length,
        alpha,
        ablation,
        last_recorded: recorder.last,
    })
}

/// A trained SafeDICE run's discriminator AUCs (held-out set, D^U) and the non-preferred share
/// of its weights on D^U.
fn safedice_ablation(t: &SafediceTrainer, truth: &Truth) -> Result<SafediceAblation, TrainError> {
    let heldout = t.discriminator_logits(&truth.heldout)?;
    let unlabeled = t.discriminator_logits_unlabeled()?;
    let flags = &truth.unlabeled_non_preferred;
    let share_of = |log_weights: Option<Vec<f64>>| {
        log_weights.map_or(f64::NAN, |w| {
            let seed = ablation::WEIGHT_SHARE_SEED;
            ablation::batch_weight_share(&w, flags, t.batch_size(), seed, t.policy_uniform_share())
        })
    };
    let share = share_of(t.unlabeled_advantages()?);
    let reward_only_share = share_of(t.unlabeled_rewards()?);
    Ok(SafediceAblation {
        auc_heldout: ablation::roc_auc(&heldout, &truth.heldout_non_preferred).unwrap_or(f64::NAN),
        auc_unlabeled: ablation::roc_auc(&unlabeled, flags).unwrap_or(f64::NAN),
        non_preferred_weight_share: share,
        reward_only_weight_share: reward_only_share,
    })
}

/// The trainer's recorded scalars: the last value of each, and the ESS history.
#[derive(Default)]
struct Recorder {
    last: BTreeMap<String, f64>,
    ess: Vec<f64>,
}

impl Recorder {
    fn add(&mut self, scalars: &[(&'static str, f64)]) {
        for &(name, value) in scalars {
            if name == "ess_fraction" {
                self.ess.push(value);
            }
            self.last.insert(name.to_string(), value);
        }
    }

    fn get(&self, name: &str) -> f64 {
        self.last.get(name).copied().unwrap_or(f64::NAN)
    }

    fn alpha(&self, alpha_hat: f64, non_preferred_ids: &[u32]) -> AlphaDiagnostics {
        let argmin_episode = self.get("alpha_hat_argmin_episode");
        let argmin = if argmin_episode.is_finite() { argmin_episode as u32 } else { u32::MAX };
        let mean = self.ess.iter().sum::<f64>() / self.ess.len().max(1) as f64;
        AlphaDiagnostics {
            alpha_hat,
            min_ratio: self.get("alpha_hat_min_ratio"),
            quantile_01: self.get("alpha_hat_q01_diagnostic_not_paper"),
            argmin_episode: argmin,
            argmin_episode_is_non_preferred: non_preferred_ids.contains(&argmin),
            ess_fraction_mean: if self.ess.is_empty() { f64::NAN } else { mean },
            ess_fraction_last: self.ess.last().copied().unwrap_or(f64::NAN),
            reward_clipped_rows: self.get("reward_clipped_rows"),
            alpha_hat_lower: self.get("alpha_hat_lower"),
            alpha_hat_upper: self.get("alpha_hat_upper"),
            heldout_auc: self.get("discriminator_heldout_auc"),
            weighting_uniform: self.get("weighting_uniform"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The binary names the commit it was built from: the tests are built from this checkout
    /// (cargo reruns build.rs when HEAD moves), so it is HEAD, with `+modified` at most.
    #[test]
    fn the_build_commit_is_the_checkouts_head() {
        let Some(head) = git_rev_parse() else { return };
        assert_eq!(crate::BUILD_COMMIT.trim_end_matches("+modified"), head);
        assert!(crate::VERSION.contains(crate::BUILD_COMMIT), "{}", crate::VERSION);
    }

    /// Reading `.git` directly gives what git itself says, where both can answer.
    #[test]
    fn the_commit_read_from_the_git_directory_is_gits_own() {
        let in_checkout =
            std::env::current_dir().unwrap().ancestors().any(|dir| dir.join(".git").is_dir());
        let read = head_from_git_dir();
        assert_eq!(read.is_some(), in_checkout, "{read:?}");
        if let (Some(read), Some(git)) = (read, git_rev_parse()) {
            assert_eq!(read, git);
        }
    }
}
