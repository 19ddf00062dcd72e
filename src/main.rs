//! The `safedice` command line: thin wrappers over the library.

use clap::{Parser, Subcommand};
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
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
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
