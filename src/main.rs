//! The `safedice` command line: thin wrappers over the library.

use clap::{Args, Parser, Subcommand};
use safedice::algo::speed::{self, Engine, SpeedConfig};

#[derive(Parser)]
#[command(name = "safedice", version, about = "Offline safe imitation learning service (SafeDICE)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Training-speed benchmark on synthetic data: SafeDICE main-loop iterations/s (nu step on
    /// s, s', s0 + policy step, discriminator frozen), discriminator steps/s (with its gradient
    /// penalty), and the achieved GFLOP/s of each.
    Speed(SpeedArgs),
}

#[derive(Args)]
struct SpeedArgs {
    #[arg(long, default_value_t = 17)]
    obs_dim: usize,
    /// Continuous action dimension (ignored with --discrete).
    #[arg(long, default_value_t = 6)]
    act_dim: usize,
    /// Use N discrete actions instead of continuous ones.
    #[arg(long, value_name = "N")]
    discrete: Option<usize>,
    #[arg(long, default_value_t = 512)]
    batch: usize,
    /// Hidden layer widths.
    #[arg(long, value_delimiter = ',', default_value = "256,256")]
    hidden: Vec<usize>,
    /// Timed iterations per repeat (after a warm-up of a tenth of them, at least 5).
    #[arg(long, default_value_t = 200)]
    iters: usize,
    /// Timed repeats; the median is reported.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Compute threads (GEMM; candle's pool via RAYON_NUM_THREADS). One per training job was
    /// fastest on a shared machine.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// `trainer`: the real SafeDICE trainer (fused CPU engine); `trainer-candle`: the same
    /// trainer on candle autograd; `fused` / `candle`: the two workloads alone on either engine.
    #[arg(long, value_enum, default_value_t = Engine::Trainer)]
    engine: Engine,
}

fn main() -> anyhow::Result<()> {
    // One compute thread per training job unless the operator says otherwise: candle's CPU ops
    // read RAYON_NUM_THREADS on every call, and on the shared machine its 2-thread pool
    // busy-waited against other processes (3x slower; bench/README.md "Threads"). Set before
    // any thread exists.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let cli = Cli::parse();
    match cli.command {
        Command::Speed(a) => {
            // Before anything touches rayon's global pool (candle's CPU ops and gemm use it).
            std::env::set_var("RAYON_NUM_THREADS", a.threads.to_string());
            let cfg = SpeedConfig {
                obs_dim: a.obs_dim,
                act_dim: a.act_dim,
                discrete: a.discrete,
                batch: a.batch,
                hidden: a.hidden,
                iters: a.iters,
                repeats: a.repeats,
                threads: a.threads,
                seed: a.seed,
                engine: a.engine,
            };
            let results = speed::run(&cfg)?;
            print!("{}", speed::report(&cfg, &results));
            Ok(())
        }
    }
}
