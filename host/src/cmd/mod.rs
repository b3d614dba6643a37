//! One module per subcommand. Each owns its `Args` and a `run` that returns `anyhow::Result`.
use clap::{Parser, Subcommand};

mod align;
mod bench;
mod bench_acquisition;
mod bench_equivalence;
mod bench_fit;
mod bench_one_pass;
mod bench_render;
mod bench_tradeoff;
mod calib;
mod demo;
mod evaluate;
mod export;
mod fit;
mod fit_curve;
mod flash;
mod models;
mod plan;
mod plot;
mod ports;
mod predict;
mod probes;
mod progress;
mod render;
mod rig;
mod scan;
mod simulate;

/// Capture real translucent objects and turn them into compact, renderable models.
#[derive(Debug, Parser)]
#[command(name = "subsurf", version, about)]
pub struct Cli {
    /// No progress display: only results, warnings and errors.
    #[arg(short, long, global = true, conflicts_with = "verbose")]
    quiet: bool,
    /// More progress off a terminal: each step's start and end, and its count now and then.
    #[arg(short, long, global = true)]
    verbose: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List serial ports.
    Ports(ports::Args),
    /// Flash the board firmware through a debug probe and confirm it runs.
    Flash(flash::Args),
    /// List debug probes (ST-LINK, CMSIS-DAP, J-Link).
    Probes(probes::Args),
    /// Fit one fall-off curve R_d(r) (sum of exponentials or dipole) from a CSV file.
    FitCurve(fit_curve::Args),
    /// Write a simulated scan dataset with ground truth.
    Simulate(simulate::Args),
    /// Plan a scan: frames, expected duration and predicted coverage, before anything moves.
    Plan(plan::Args),
    /// Scan an object into a dataset (resumable; `--sim --camera sim` needs no other files).
    Scan(scan::Args),
    /// Calibrate the camera, turntable axis and galvo into calib.json.
    Calib(calib::Args),
    /// Talk to the rig or the simulated rig.
    Rig(rig::Args),
    /// Measure performance (figures for BENCHMARKS.md).
    Bench(bench::Args),
    /// Relight a fitted model under point, spot and directional lights: PNG (+ linear EXR).
    Render(render::Args),
    /// Place the scan's mesh (any pose and unit) in the turntable frame from its laser spots.
    Align(align::Args),
    /// Fit the per-vertex model to a scan dataset (register, select, fit, interpolate).
    Fit(fit::Args),
    /// Render a model's prediction of one frame of a scan.
    Predict(predict::Args),
    /// Table-1 statistics (log E, Eq. 8) of a model on frames of a scan.
    Evaluate(evaluate::Args),
    /// Figures: fall-off (Figure 3), error maps (Figures 4/5), model viewer.
    Plot(plot::Args),
    /// The main job with no hardware and no arguments: simulated rig, scan, fit, render, pictures.
    Demo(demo::Args),
    /// Export a model for Blender's Cycles: per-vertex subsurface colour and radius, the scene.
    Export(export::Args),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    use subsurf::progress::Verbosity;
    let set_verbosity = progress::set_verbosity;
    set_verbosity(match (cli.quiet, cli.verbose) {
        (true, _) => Verbosity::Quiet,
        (false, true) => Verbosity::Verbose,
        (false, false) => Verbosity::Normal,
    });
    match cli.command {
        Command::Ports(args) => ports::run(args),
        Command::Flash(args) => flash::run(args),
        Command::Probes(args) => probes::run(args),
        Command::FitCurve(args) => fit_curve::run(args),
        Command::Simulate(a) => simulate::run(a),
        Command::Plan(args) => plan::run(args),
        Command::Scan(args) => scan::run(args),
        Command::Calib(args) => calib::run(args),
        Command::Rig(args) => rig::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Render(a) => render::run(a),
        Command::Align(a) => align::run(a),
        Command::Fit(a) => fit::run(a),
        Command::Predict(a) => predict::run(a),
        Command::Evaluate(a) => evaluate::run(a),
        Command::Plot(a) => plot::run(a),
        Command::Demo(a) => demo::run_cmd(a),
        Command::Export(a) => export::run(a),
    }
}

/// The dataset at `scan` and its frames chosen by `--frames` / `--exclude-frames`, with the
/// path in the error (the commands that read a scan's frames: align, evaluate, fit).
fn open_frames(
    scan: &std::path::Path,
    frames: Option<&str>,
    exclude: Option<&str>,
) -> anyhow::Result<(subsurf::dataset::Dataset, Vec<usize>)> {
    use anyhow::Context;
    let ds = subsurf::dataset::Dataset::open(scan)
        .with_context(|| format!("opening {}", scan.display()))?;
    let frames = subsurf::dataset::select_frames(ds.spec.frames.len(), frames, exclude)
        .map_err(|e| anyhow::anyhow!(e))?;
    Ok((ds, frames))
}
