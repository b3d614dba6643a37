//! One module per subcommand. Each owns its `Args` and a `run` that returns `anyhow::Result`.
use clap::{Parser, Subcommand};

mod ports;
mod simulate;

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
    /// Write a simulated scan dataset with ground truth.
    Simulate(simulate::Args),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Ports(args) => ports::run(args),
        Command::Simulate(a) => simulate::run(a),
    }
}
