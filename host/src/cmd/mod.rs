//! One module per subcommand. Each owns its `Args` and a `run` that returns `anyhow::Result`.
use clap::{Parser, Subcommand};

mod bench;
mod render;

/// Capture real translucent objects and turn them into compact, renderable models.
#[derive(Debug, Parser)]
#[command(name = "subsurf", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Benchmarks (release mode) whose output goes into BENCHMARKS.md.
    Bench(bench::Args),
    /// Relight a fitted model under point, spot and directional lights: PNG (+ linear EXR).
    Render(render::Args),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Bench(a) => bench::run(a),
        Command::Render(a) => render::run(a),
    }
}
