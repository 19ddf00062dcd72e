//! `safedice speed`: how fast the product's trainers train, on synthetic data.
//!
//! For SafeDICE (the default) it times the trainer's two hot loops, step by step through
//! [`Trainer::step`]:
//! - discriminator step: Eq. 9 on `B` non-preferred and `B` unlabeled pairs, the interpolated
//!   gradient penalty on `2B` points, one Adam step;
//! - main loop: one ν step (Eq. 36 on `cat(s, s', s0)` plus ν's zero-centred penalty on `2B`
//!   interpolated states) and one policy step (Eq. 37), discriminator frozen.
//!
//! The trainer runs the `authors-code` preset (both penalties on) on either of its paths: the
//! fused CPU engine (`--engine fused`, what the service runs on a CPU) or candle autograd
//! (`--engine candle`, the reference path). Rates come with FLOPs per step (matrix products
//! only) and the fraction of this machine's GEMM peak, measured after the workloads.
//! docs/performance.md explains the engine and the numbers; `bench/pytorch_reference.py` times
//! the same workloads in PyTorch.
//!
//! With `--algorithm bc|dwbc|ppl|dexperts` it times that trainer's policy-learning step (service
//! preset) the same way, on either engine: their policy step runs on the fused engine on a CPU
//! (`algo::fused_policy`); DWBC's discriminator and PPL's reward model stay on candle.

use std::sync::Arc;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::algo::flops::StepShape;
use crate::algo::fused_mlp::peak_gemm_gflops;
use crate::algo::safedice;
use crate::algo::safedice::SafediceTrainer;
use crate::algo::{build_trainer, resolve_config, Algorithm, Trainer, TrainingData};
use crate::data::{ActionSpace, Actions, Dataset, DatasetParts};

/// Which path of [`SafediceTrainer`] runs the hot loops.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Engine {
    /// The fused CPU engine (the trainer's default on a CPU).
    #[value(alias = "trainer")]
    Fused,
    /// The trainer forced onto its candle autograd path (the reference implementation).
    #[value(alias = "trainer-candle")]
    Candle,
}

#[derive(Clone, Debug)]
pub struct SpeedConfig {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `Some(n)`: n discrete actions (one-hot into the discriminator) instead of `act_dim`.
    pub discrete: Option<usize>,
    pub batch: usize,
    pub hidden: Vec<usize>,
    pub iters: usize,
    pub repeats: usize,
    pub threads: usize,
    pub seed: u64,
    pub engine: Engine,
    pub algorithm: Algorithm,
}

impl SpeedConfig {
    fn act_input(&self) -> usize {
        self.discrete.unwrap_or(self.act_dim)
    }

    fn policy_output(&self) -> usize {
        self.discrete.unwrap_or(2 * self.act_dim)
    }

    /// The networks' sizes, as the algorithms count their FLOPs.
    pub fn step_shape(&self) -> StepShape {
        StepShape {
            obs_dim: self.obs_dim,
            act_input: self.act_input(),
            policy_output: self.policy_output(),
            hidden: self.hidden.clone(),
            batch: self.batch,
        }
    }
}

/// FLOPs of one main-loop iteration (SafeDICE's step in the registry).
pub fn main_loop_flops(cfg: &SpeedConfig) -> u64 {
    safedice::step_flops(&cfg.step_shape())
}

/// FLOPs of one discriminator step.
pub fn disc_step_flops(cfg: &SpeedConfig) -> u64 {
    safedice::discriminator_step_flops(&cfg.step_shape())
}

/// FLOPs of one policy-learning step of `cfg.algorithm`, as its module counts them.
pub fn baseline_step_flops(cfg: &SpeedConfig) -> u64 {
    (cfg.algorithm.spec().step.flops)(&cfg.step_shape())
}

// ---------------------------------------------------------------------------------------------
// Synthetic data

/// Transitions in the synthetic D^U and D^N.
const UNLABELED: usize = 20_000;
const NON_PREFERRED: usize = 4_000;

/// A synthetic dataset for the trainer: `episodes` episodes of `len` steps, no terminals (as the
/// authors' 1000-step data), standard-normal observations, uniform actions.
fn synthetic_dataset(
    cfg: &SpeedConfig,
    episodes: usize,
    len: usize,
    rng: &mut ChaCha8Rng,
) -> Dataset {
    let n = episodes * len;
    let mut normals =
        |k: usize| -> Vec<f32> { (0..k).map(|_| StandardNormal.sample(&mut *rng)).collect() };
    let observations = normals(n * cfg.obs_dim);
    let next_observations = normals(n * cfg.obs_dim);
    let (action_space, actions) = match cfg.discrete {
        Some(k) => (
            ActionSpace::Discrete { n: k },
            Actions::Discrete((0..n).map(|_| rng.random_range(0..k as u32)).collect()),
        ),
        None => (
            ActionSpace::Continuous {
                dim: cfg.act_dim,
                low: vec![-1.0; cfg.act_dim],
                high: vec![1.0; cfg.act_dim],
            },
            Actions::Continuous(
                (0..n * cfg.act_dim).map(|_| rng.random_range(-1.0..=1.0)).collect(),
            ),
        ),
    };
    Dataset::new(DatasetParts {
        obs_dim: cfg.obs_dim,
        action_space,
        observations,
        actions,
        next_observations,
        terminals: vec![false; n],
        episode_ids: (0..n).map(|i| (i / len) as u32).collect(),
        rewards: None,
        costs: None,
    })
    .unwrap()
}

/// Synthetic D^U and D^N of `unlabeled` and `non_preferred` transitions.
fn synthetic_data(cfg: &SpeedConfig, (unlabeled, non_preferred): (usize, usize)) -> TrainingData {
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let episode = 1000.min(unlabeled).min(non_preferred);
    TrainingData {
        unlabeled: Arc::new(synthetic_dataset(cfg, unlabeled / episode, episode, &mut rng)),
        non_preferred: Some(Arc::new(synthetic_dataset(
            cfg,
            non_preferred / episode,
            episode,
            &mut rng,
        ))),
    }
}

/// A SafeDICE trainer (`authors-code` preset: both gradient penalties on) on synthetic data with
/// `unlabeled` and `non_preferred` transitions, on its fused path (call
/// [`Trainer::use_candle_autograd`] for the other).
pub fn synthetic_trainer(
    cfg: &SpeedConfig,
    sizes: (usize, usize),
    disc_steps: usize,
    iterations: usize,
) -> anyhow::Result<SafediceTrainer> {
    let config = resolve_config(
        Algorithm::Safedice,
        &serde_json::json!({
            "preset": "authors-code",
            "seed": cfg.seed,
            "batch_size": cfg.batch,
            "hidden_sizes": cfg.hidden,
            "iterations": iterations,
            "discriminator_iterations": disc_steps,
            "threads": cfg.threads,
        }),
    )?;
    Ok(SafediceTrainer::new(&config, &synthetic_data(cfg, sizes))?)
}

/// A baseline's trainer (service preset) on synthetic data, `iterations` policy steps long; PPL's
/// reward-model phase is one step (done by [`run_baseline`] before timing).
pub fn synthetic_baseline(
    cfg: &SpeedConfig,
    sizes: (usize, usize),
    iterations: usize,
) -> anyhow::Result<Box<dyn Trainer>> {
    synthetic_baseline_with(cfg, sizes, iterations, &serde_json::Map::new())
}

/// [`synthetic_baseline`] with further knobs set (`overrides` win).
pub fn synthetic_baseline_with(
    cfg: &SpeedConfig,
    sizes: (usize, usize),
    iterations: usize,
    overrides: &serde_json::Map<String, serde_json::Value>,
) -> anyhow::Result<Box<dyn Trainer>> {
    let mut knobs = serde_json::json!({
        "seed": cfg.seed,
        "batch_size": cfg.batch,
        "hidden_sizes": cfg.hidden,
        "iterations": iterations,
        "threads": cfg.threads,
    });
    if cfg.algorithm == Algorithm::Ppl {
        knobs["reward_model_iterations"] = 1.into();
    }
    for (key, value) in overrides {
        knobs[key] = value.clone();
    }
    let config = resolve_config(cfg.algorithm, &knobs)?;
    Ok(build_trainer(&config, &synthetic_data(cfg, sizes), None)?)
}

// ---------------------------------------------------------------------------------------------
// Timing

/// One workload's measurement.
#[derive(Clone, Debug)]
pub struct Measurement {
    pub name: &'static str,
    pub unit: &'static str,
    /// Steps per second of every repeat, and their median.
    pub rates: Vec<f64>,
    pub median: f64,
    /// Steps per second of process CPU time (Linux), median over repeats: less sensitive than
    /// wall-clock time to other processes taking the cores.
    pub cpu_median: Option<f64>,
    pub flops_per_step: u64,
}

impl Measurement {
    pub fn gflops(&self) -> f64 {
        self.median * self.flops_per_step as f64 / 1e9
    }
}

/// What [`run`] measured: the two workloads and the machine's GEMM peak.
#[derive(Clone, Debug)]
pub struct SpeedResults {
    pub workloads: Vec<Measurement>,
    /// Best GFLOP/s of a square f32 GEMM on `threads` threads through the kernels the fused
    /// engine calls (see [`peak_gemm_gflops`]): the ceiling the fractions are taken of.
    pub peak_gflops: f64,
}

fn measure(
    name: &'static str,
    unit: &'static str,
    flops_per_step: u64,
    cfg: &SpeedConfig,
    mut step: impl FnMut() -> anyhow::Result<()>,
) -> anyhow::Result<Measurement> {
    for _ in 0..(cfg.iters / 10).max(5) {
        step()?;
    }
    let (mut rates, mut cpu_rates) = (Vec::new(), Vec::new());
    for _ in 0..cfg.repeats.max(1) {
        let (t, cpu) = (Instant::now(), process_cpu_seconds());
        for _ in 0..cfg.iters {
            step()?;
        }
        rates.push(cfg.iters as f64 / t.elapsed().as_secs_f64());
        if let (Some(start), Some(end)) = (cpu, process_cpu_seconds()) {
            cpu_rates.push(cfg.iters as f64 / (end - start).max(0.01));
        }
    }
    let cpu_median = (cpu_rates.len() == rates.len()).then(|| median(&cpu_rates));
    Ok(Measurement { name, unit, median: median(&rates), rates, cpu_median, flops_per_step })
}

fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted[sorted.len() / 2]
}

/// User + system CPU seconds of this process from `/proc/self/stat` (10 ms resolution); None
/// where that file does not exist.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name start at field 3; utime and stime are 14, 15.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Time the configured algorithm's steps on the configured engine (see the module docs); a step
/// whose loss goes non-finite stops the run with the trainer's own error.
pub fn run(cfg: &SpeedConfig) -> anyhow::Result<SpeedResults> {
    if cfg.algorithm != Algorithm::Safedice {
        return run_baseline(cfg);
    }
    run_safedice(cfg)
}

/// A baseline's policy-learning steps.
fn run_baseline(cfg: &SpeedConfig) -> anyhow::Result<SpeedResults> {
    let steps = (cfg.iters / 10).max(5) + cfg.iters * cfg.repeats.max(1) + 1;
    let mut trainer = synthetic_baseline(cfg, (UNLABELED, NON_PREFERRED), steps)?;
    if cfg.engine == Engine::Candle {
        trainer.use_candle_autograd();
    }
    if cfg.algorithm == Algorithm::Ppl {
        trainer.step(false)?; // the reward model's one step
    }
    let step = || -> anyhow::Result<()> {
        trainer.step(false)?;
        Ok(())
    };
    let name = cfg.algorithm.spec().step.label;
    let main = measure(name, "steps/s", baseline_step_flops(cfg), cfg, step)?;
    let peak_gflops = peak_gemm_gflops(cfg.threads);
    Ok(SpeedResults { workloads: vec![main], peak_gflops })
}

/// SafeDICE's discriminator steps, then its main-loop iterations.
fn run_safedice(cfg: &SpeedConfig) -> anyhow::Result<SpeedResults> {
    let warmup = (cfg.iters / 10).max(5);
    let timed = cfg.iters * cfg.repeats.max(1);
    // One untimed step after the timed discriminator steps ends the phase (alpha-hat and the
    // rewards over all of D^U), so no timed step includes it.
    let disc_steps = warmup + timed + 1;
    let mut trainer =
        synthetic_trainer(cfg, (UNLABELED, NON_PREFERRED), disc_steps, warmup + timed)?;
    if cfg.engine == Engine::Candle {
        trainer.use_candle_autograd();
    }
    let mut step = || -> anyhow::Result<()> {
        trainer.step(false)?;
        Ok(())
    };
    let disc =
        measure("discriminator step (with GP)", "steps/s", disc_step_flops(cfg), cfg, &mut step)?;
    step()?;
    let main = measure(
        Algorithm::Safedice.spec().step.label,
        "iterations/s",
        main_loop_flops(cfg),
        cfg,
        &mut step,
    )?;
    // The peak last: freeing its large buffers raises glibc's mmap threshold, which would
    // otherwise speed up the candle path's first timed steps.
    let peak_gflops = peak_gemm_gflops(cfg.threads);
    Ok(SpeedResults { workloads: vec![main, disc], peak_gflops })
}

/// Each workload's rate at every thread count measured, beside the first count's (the
/// speed-up) and that divided by the added threads (the parallel efficiency).
pub fn scaling_report(measured: &[(usize, SpeedResults)]) -> String {
    let mut out = String::from("scaling (median rates):\n");
    let Some((base_threads, base)) = measured.first() else { return out };
    for (i, workload) in base.workloads.iter().enumerate() {
        for (threads, results) in measured {
            let rate = results.workloads[i].median;
            let speedup = rate / workload.median;
            let efficiency = speedup * *base_threads as f64 / *threads as f64;
            out += &format!(
                "  {:44} threads {threads:>2}  {rate:8.1} {}  {speedup:5.2}x of {base_threads} thread(s)  efficiency {:4.0}%\n",
                workload.name,
                workload.unit,
                100.0 * efficiency,
            );
        }
    }
    out
}

/// The benchmark's printed report.
pub fn report(cfg: &SpeedConfig, results: &SpeedResults) -> String {
    let actions = match cfg.discrete {
        Some(n) => format!("{n} discrete actions"),
        None => format!("act {}", cfg.act_dim),
    };
    let engine = match cfg.engine {
        Engine::Fused => "fused CPU engine",
        Engine::Candle => "candle autograd",
    };
    let peak = results.peak_gflops;
    let mut out = format!(
        "safedice speed: {} trainer on the {engine}, threads {}, batch {}, hidden {:?}, obs {}, {}, {} iters x {} repeats\n\
         measured peak: {peak:.1} GFLOP/s (square f32 GEMM on {} thread(s), this machine)\n",
        cfg.algorithm, cfg.threads, cfg.batch, cfg.hidden, cfg.obs_dim, actions, cfg.iters, cfg.repeats, cfg.threads
    );
    for m in &results.workloads {
        let runs: Vec<String> = m.rates.iter().map(|r| format!("{r:.1}")).collect();
        out += &format!(
            "{:44} {:8.1} {:12} (runs {}; per CPU-second {})  {:7.1} MFLOP each  {:6.1} GFLOP/s  {:5.1}% of measured peak\n",
            m.name,
            m.median,
            m.unit,
            runs.join(", "),
            m.cpu_median.map_or("n/a".to_string(), |c| format!("{c:.1}")),
            m.flops_per_step as f64 / 1e6,
            m.gflops(),
            100.0 * m.gflops() / peak,
        );
    }
    out
}

/// Test support: a tiny configuration, and a check that a trainer on the fused engine and the
/// same trainer on candle autograd record the same values step by step (to 1e-3 relative: they
/// drift apart only by float rounding).
#[cfg(test)]
pub(crate) mod engines {
    use super::*;

    pub fn tiny(algorithm: Algorithm, discrete: Option<usize>) -> SpeedConfig {
        SpeedConfig {
            obs_dim: 5,
            act_dim: 3,
            discrete,
            batch: 16,
            hidden: vec![12, 10],
            iters: 1,
            repeats: 1,
            threads: 1,
            seed: 7,
            engine: Engine::Fused,
            algorithm,
        }
    }

    pub fn assert_engines_agree(
        what: &str,
        mut make: impl FnMut() -> Box<dyn Trainer>,
        steps: usize,
    ) {
        let (mut fused, mut candle) = (make(), make());
        candle.use_candle_autograd();
        for step in 0..steps {
            let (a, b) = (fused.step(true).unwrap(), candle.step(true).unwrap());
            assert_eq!(a.len(), b.len());
            for ((name, x), (other, y)) in a.iter().zip(&b) {
                assert_eq!(name, other);
                assert!(
                    (x - y).abs() <= 1e-3 * y.abs().max(1.0) || (x.is_nan() && y.is_nan()),
                    "{what} step {step} {name}: fused {x}, candle {y}"
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flop_counts_match_the_hand_count() {
        let cfg = SpeedConfig {
            obs_dim: 17,
            act_dim: 6,
            discrete: None,
            batch: 512,
            hidden: vec![256, 256],
            iters: 1,
            repeats: 1,
            threads: 1,
            seed: 7,
            engine: Engine::Fused,
            algorithm: Algorithm::Safedice,
        };
        // nu: 1536 rows train + 1024 rows penalty; policy 512 rows; see docs/performance.md.
        let fwd = |d: u64, o: u64| 2 * (d * 256 + 256 * 256 + 256 * o);
        let nu_train = 1536 * (2 * fwd(17, 1) + 2 * (256 * 256 + 256));
        let nu_gp = 1024 * (fwd(17, 1) + 3 * 2 * (17 * 256 + 256 * 256));
        let pi_train = 512 * (2 * fwd(17, 12) + 2 * (256 * 256 + 256 * 12));
        assert_eq!(main_loop_flops(&cfg), nu_train + nu_gp + pi_train);
        let d_train = 1024 * (2 * fwd(23, 1) + 2 * (256 * 256 + 256));
        let d_gp = 1024 * (fwd(23, 1) + 3 * 2 * (23 * 256 + 256 * 256));
        assert_eq!(disc_step_flops(&cfg), d_train + d_gp);
    }
}
