//! One module per subcommand. Each owns its `Args` and a `run` that returns `anyhow::Result`.
use clap::{Parser, Subcommand};

mod ports;

/// Capture real translucent objects and turn them into compact, renderable models.
#[derive(Debug, Parser)]
#[command(name = "subsurf", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List serial ports.
    Ports(ports::Args),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Ports(args) => ports::run(args),
    }
}
