//! The `safedice` command line: thin wrappers over the library.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};
use safedice::algo::Algorithm;
use safedice::bench::speed::{self, Engine, SpeedConfig};
use safedice::config::{ServeConfig, WorkerConfig};
use safedice::server::{self, Server};

#[derive(Parser)]
#[command(name = "safedice", version = safedice::VERSION, about = "Offline safe imitation learning service (SafeDICE)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the HTTP service (and, unless --workers 0, training workers).
    Serve(ServeConfig),
    /// Run training workers without the HTTP API, on the database the API nodes use
    /// (--database-url), to spread jobs over processes and machines.
    Worker(WorkerConfig),
    /// Print the HTTP API's OpenAPI description (YAML, as committed in api/openapi.yaml).
    Openapi,
    /// Generate demonstration data from a built-in environment's scripted demonstrators: an
    /// unlabeled set mixing preferred and non-preferred episodes (shuffled), a labeled set of
    /// fresh non-preferred episodes, and manifest.json (counts, seed, data profile, reference
    /// statistics), in an upload format.
    Datagen(DatagenArgs),
    /// Training-speed benchmark on synthetic data: SafeDICE's main-loop iterations/s (nu step
    /// on s, s', s0 + policy step, discriminator frozen) and discriminator steps/s (with its
    /// gradient penalty), or with --algorithm a baseline's policy-learning steps/s; the
    /// achieved GFLOP/s of each and their fraction of the GEMM peak measured after them.
    Speed(SpeedArgs),
    /// Train every algorithm on every built-in environment, evaluate with the paper's metrics
    /// and write results.md (mean ± standard error over seeds), results.json and SVG plots.
    Bench(safedice::bench::BenchArgs),
    /// Convert a policy file (downloaded from GET /v1/policies/{id}/weights) into an ONNX model
    /// (opset 13): observations in the dataset's units to the deterministic action, the same
    /// actions as /act; also GET /v1/policies/{id}/export?format=onnx.
    Export(ExportArgs),
    /// Start the service in-process on a temporary directory, generate a small dataset, train
    /// SafeDICE and BC through the HTTP API, and print their metrics side by side with the curl
    /// commands used.
    Demo(safedice::demo::DemoArgs),
}

#[derive(clap::Args)]
struct DatagenArgs {
    /// Built-in environment.
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(safedice::envs::names()))]
    env: String,
    /// Preferred episodes in the unlabeled set.
    #[arg(long, default_value_t = 1000)]
    preferred: usize,
    /// Non-preferred episodes in the unlabeled set.
    #[arg(long, default_value_t = 1000)]
    non_preferred: usize,
    /// Episodes in the labeled non-preferred set (0: none written).
    #[arg(long, default_value_t = 50)]
    labeled: usize,
    /// Seed of the demonstrators' episodes (the same seed gives the same files).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// File format of the written sets (all upload formats but HDF5).
    #[arg(long, value_enum, default_value_t = DataFormat::Npz)]
    format: DataFormat,
}

#[derive(clap::Args)]
struct ExportArgs {
    /// The policy file (safetensors with the policy's spec in its metadata).
    policy: PathBuf,
    /// Where the model goes.
    #[arg(long)]
    out: PathBuf,
    /// The model format.
    #[arg(long, value_enum, default_value_t = ExportFormat::Onnx)]
    format: ExportFormat,
}

#[derive(Clone, Copy, ValueEnum)]
enum ExportFormat {
    Onnx,
}

fn export(args: ExportArgs) -> anyhow::Result<()> {
    let ExportFormat::Onnx = args.format;
    let model = safedice::algo::onnx::export_portable(std::fs::read(&args.policy)?)?;
    std::fs::write(&args.out, &model)?;
    println!(
        "wrote {} ({} bytes, ONNX opset {})",
        args.out.display(),
        model.len(),
        safedice::algo::onnx::OPSET
    );
    Ok(())
}

#[derive(Clone, Copy, ValueEnum)]
enum DataFormat {
    Npz,
    Jsonl,
    Csv,
}

fn datagen(args: DatagenArgs) -> anyhow::Result<()> {
    use safedice::envs::{generate, write_generated, DatagenSpec};
    let spec = DatagenSpec {
        env: args.env,
        preferred: args.preferred,
        non_preferred: args.non_preferred,
        labeled: args.labeled,
        seed: args.seed,
    };
    let generated = generate(&spec)?;
    let format = match args.format {
        DataFormat::Npz => safedice::data::Format::Npz,
        DataFormat::Jsonl => safedice::data::Format::Jsonl,
        DataFormat::Csv => safedice::data::Format::Csv,
    };
    let manifest = write_generated(&generated, &args.out, format)?;
    let groups = [
        ("unlabeled preferred", &manifest.unlabeled_preferred),
        ("unlabeled non-preferred", &manifest.unlabeled_non_preferred),
        ("labeled non-preferred", &manifest.labeled_non_preferred),
    ];
    for (name, g) in groups {
        println!(
            "{name:>24}: {:>6} episodes {:>9} transitions  mean return {:>9.3}  mean cost {:>8.3}",
            g.episodes, g.transitions, g.mean_return, g.mean_cost
        );
    }
    for file in &manifest.files {
        println!("wrote {}", args.out.join(file).display());
    }
    Ok(())
}

#[derive(Args)]
struct SpeedArgs {
    /// Observation width of the synthetic data.
    #[arg(long, default_value_t = 17)]
    obs_dim: usize,
    /// Continuous action dimension (ignored with --discrete).
    #[arg(long, default_value_t = 6)]
    act_dim: usize,
    /// Use N discrete actions instead of continuous ones.
    #[arg(long, value_name = "N")]
    discrete: Option<usize>,
    /// Minibatch size (the job config's `batch_size`).
    #[arg(long = "batch-size", alias = "batch", default_value_t = 512)]
    batch: usize,
    /// Hidden layer widths, comma-separated (the job config's `hidden_sizes`).
    #[arg(
        long = "hidden-sizes",
        alias = "hidden",
        value_delimiter = ',',
        default_value = "256,256"
    )]
    hidden: Vec<usize>,
    /// Timed iterations per repeat (after a warm-up of a tenth of them, at least 5).
    #[arg(long = "iterations", alias = "iters", default_value_t = 200)]
    iters: usize,
    /// Timed repeats; the median is reported.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Threads of the job (its `threads`: the fused engine splits each step's rows over them),
    /// comma-separated to measure several counts one after another and print their scaling,
    /// e.g. `1,2`. The candle path's threads are candle's pool (RAYON_NUM_THREADS).
    #[arg(long, value_delimiter = ',', default_value = "1")]
    threads: Vec<usize>,
    /// Seed of the synthetic data and the networks' initialisation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Which path of the trainer runs the hot loops: `fused` (the fused CPU engine, what
    /// training uses on a CPU) or `candle` (candle autograd, the reference path).
    #[arg(long, value_enum, default_value_t = Engine::Fused)]
    engine: Engine,
    /// Whose steps to time: SafeDICE's two hot loops, or a baseline's policy-learning step.
    #[arg(long, default_value = "safedice", value_parser = algorithm_name())]
    algorithm: Algorithm,
}

/// `--algorithm`: the algorithm table's names, listed in `--help`.
fn algorithm_name() -> impl clap::builder::TypedValueParser<Value = Algorithm> {
    use clap::builder::{PossibleValuesParser, TypedValueParser};
    PossibleValuesParser::new(Algorithm::names())
        .map(|name| Algorithm::from_name(&name).expect("one of the listed names"))
}

fn main() -> anyhow::Result<()> {
    // candle's own CPU ops on one thread unless the operator says otherwise: they read
    // RAYON_NUM_THREADS on every call, and on the shared machine its 2-thread pool busy-waited
    // against other processes (3x slower; docs/performance.md, "Threads of one job"). A job's
    // compute threads are its own pool (its `threads`). Set before any thread exists.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let cli = Cli::parse();
    match cli.command {
        Command::Datagen(args) => datagen(args),
        Command::Speed(a) => speed_cli(a),
        Command::Demo(args) => safedice::demo::run_cli(&args),
        Command::Export(args) => export(args),
        Command::Bench(args) => {
            let _logging = safedice::logging::init(safedice::config::LogFormat::Pretty);
            let command: Vec<String> = std::env::args().collect();
            safedice::bench::run_cli(&args, &command.join(" "))
        }
        Command::Serve(config) => serve(config),
        Command::Worker(config) => worker(config),
        Command::Openapi => {
            print!("{}", safedice::http::openapi::yaml()?);
            Ok(())
        }
    }
}

fn speed_cli(a: SpeedArgs) -> anyhow::Result<()> {
    let most = a.threads.iter().copied().max().unwrap_or(1);
    if a.threads.iter().any(|&t| !(1..=safedice::algo::MAX_JOB_THREADS).contains(&t)) {
        anyhow::bail!(
            "--threads: 1 to {} each, got {:?}",
            safedice::algo::MAX_JOB_THREADS,
            a.threads
        );
    }
    // The candle path computes on candle's pool: set before anything touches rayon's global
    // pool. The fused engine runs a job's own pool and keeps candle's small ops (draws, Adam)
    // on one thread as a worker does (main above). The counts asked for run on as many
    // threads, whatever the machine has.
    if a.engine == Engine::Candle {
        std::env::set_var("RAYON_NUM_THREADS", most.to_string());
    }
    safedice::algo::set_job_thread_cap(most);
    let mut measured = Vec::new();
    for &threads in &a.threads {
        let cfg = SpeedConfig {
            obs_dim: a.obs_dim,
            act_dim: a.act_dim,
            discrete: a.discrete,
            batch: a.batch,
            hidden: a.hidden.clone(),
            iters: a.iters,
            repeats: a.repeats,
            threads,
            seed: a.seed,
            engine: a.engine,
            algorithm: a.algorithm,
        };
        let results = speed::run(&cfg)?;
        print!("{}", speed::report(&cfg, &results));
        measured.push((threads, results));
    }
    if measured.len() > 1 {
        print!("{}", speed::scaling_report(&measured));
    }
    Ok(())
}

fn worker(config: WorkerConfig) -> anyhow::Result<()> {
    let _logging = safedice::logging::init(config.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async {
        let shutdown = tokio_util::sync::CancellationToken::new();
        let stop = shutdown.clone();
        let signal = server::shutdown_listener();
        tokio::spawn(async move {
            let signal = signal.await;
            stop.cancel();
            tracing::info!("{signal} received, stopping the workers");
        });
        safedice::worker::run(config, shutdown).await
    })
}

fn serve(config: ServeConfig) -> anyhow::Result<()> {
    let _logging = safedice::logging::init(config.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async {
        // Listening before the server says it is ready: a SIGTERM right after stops it cleanly.
        let signal = server::shutdown_listener();
        let server = Server::start(config).await?;
        let stop = server.shutdown_token();
        tokio::spawn(async move {
            let signal = signal.await;
            stop.cancel();
            tracing::info!("{signal} received, shutting down");
        });
        server.wait().await
    })
}
