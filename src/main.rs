//! The `safedice` command line: thin wrappers over the library.

use std::path::PathBuf;

use clap::{Parser, Subcommand, ValueEnum};
use safedice::config::ServeConfig;
use safedice::server::{self, Server};

#[derive(Parser)]
#[command(name = "safedice", version, about = "Offline safe imitation learning service (SafeDICE)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the HTTP service.
    Serve(ServeConfig),
    /// Print the HTTP API's OpenAPI description (YAML, as committed in api/openapi.yaml).
    Openapi,
    /// Generate demonstration data from a built-in environment's scripted demonstrators: an
    /// unlabeled set mixing preferred and non-preferred episodes (shuffled), a labeled set of
    /// fresh non-preferred episodes, and manifest.json (counts, seed, data profile, reference
    /// statistics), in an upload format.
    Datagen(DatagenArgs),
    /// Train every algorithm on every built-in environment, evaluate with the paper's metrics
    /// and write results.md (mean ± standard error over seeds), results.json and SVG plots.
    Bench(safedice::bench::BenchArgs),
    /// Start the service in-process on a temporary directory, generate a small dataset, train
    /// SafeDICE and BC through the HTTP API, and print their metrics side by side with the curl
    /// commands used.
    Demo(safedice::bench::demo::DemoArgs),
}

#[derive(clap::Args)]
struct DatagenArgs {
    /// Environment: six-rooms, point-goal or cartpole-slider.
    #[arg(long)]
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
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_enum, default_value_t = DataFormat::Npz)]
    format: DataFormat,
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

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Datagen(args) => datagen(args),
        Command::Demo(args) => safedice::bench::demo::run_cli(&args),
        Command::Bench(args) => {
            server::init_logging(safedice::config::LogFormat::Pretty);
            let command: Vec<String> = std::env::args().collect();
            safedice::bench::run_cli(&args, &command.join(" "))
        }
        Command::Serve(config) => serve(config),
        Command::Openapi => {
            print!("{}", safedice::http::openapi::yaml()?);
            Ok(())
        }
    }
}

fn serve(config: ServeConfig) -> anyhow::Result<()> {
    server::init_logging(config.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async {
        let server = Server::start(config).await?;
        let stop = server.shutdown_token();
        tokio::spawn(async move {
            server::shutdown_signal().await;
            stop.cancel();
        });
        server.wait().await
    })
}
