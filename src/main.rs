//! The `safedice` command line: thin wrappers over the library.

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "safedice", version, about = "Offline safe imitation learning service (SafeDICE)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {}
}
