//! `subsurf bench …`: performance figures for BENCHMARKS.md (run with `--release`).

use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use subsurf::link::SerialLink;
use subsurf::rig::{ClientConfig, RigClient};
use subsurf_protocol::{Command, EventKind, GalvoPoint, ProgramHeader};

/// Measure parts of subsurf; each subcommand prints its figures.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: Bench,
}

#[derive(Debug, clap::Subcommand)]
enum Bench {
    /// Rig link: request/reply round trips per second and capture events per second, against the
    /// simulated rig served on a pseudo-terminal (or a real rig with --port).
    Rig(RigArgs),
    /// Rendering: hierarchical against exact transport on the built-in marble torus (speed-up and
    /// pixel error along the error-bound curve).
    Render(super::bench_render::RenderBench),
    /// The whole chain: simulated scan density × fit preset × render quality → wall time per
    /// stage and error against the exact result, with the Pareto front.
    Tradeoff(super::bench_tradeoff::TradeoffBench),
    /// Scan processing at scale: `subsurf fit` on simulated scans over a grid of vertex and
    /// frame counts (stage times, peak RSS, growth), one dataset on disk at a time.
    FitScale(super::bench_fit::FitScaleBench),
    /// One read of the frames: `subsurf fit` wall time against one decode pass over the same
    /// frames, measured in the same run, with the ratio, peak RSS and frame reads.
    OnePass(super::bench_one_pass::OnePassBench),
    /// Acquisition planners: learning curves of dense, coverage, random and adaptive
    /// planning, held-out error on test frames against frames and rig time.
    Acquisition(super::bench_acquisition::AcquisitionBench),
    /// The default fit against `--preset reference`: time and the equivalence of
    /// predictions and choices, per scan.
    Equivalence(super::bench_equivalence::EquivalenceBench),
}

#[derive(Debug, clap::Args)]
struct RigArgs {
    /// Round trips to time.
    #[arg(long, default_value_t = 20_000)]
    round_trips: u32,
    /// Captures to stream (queued capture programs, one event each).
    #[arg(long, default_value_t = 20_000)]
    captures: u32,
    /// Benchmark the rig on this serial port instead of the simulated rig.
    #[arg(long)]
    port: Option<String>,
    /// Baud rate for --port.
    #[arg(long, default_value_t = 115_200)]
    baud: u32,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.what {
        Bench::Rig(a) => rig(a),
        Bench::Render(a) => super::bench_render::bench_render(a),
        Bench::Tradeoff(a) => super::bench_tradeoff::bench_tradeoff(a),
        Bench::FitScale(a) => super::bench_fit::bench_fit_scale(a),
        Bench::OnePass(a) => super::bench_one_pass::bench_one_pass(a),
        Bench::Acquisition(a) => super::bench_acquisition::bench_acquisition(a),
        Bench::Equivalence(a) => super::bench_equivalence::bench_equivalence(a),
    }
}

fn rig(args: RigArgs) -> anyhow::Result<()> {
    // The simulated rig is served by a thread on a pseudo-terminal, exactly as `rig serve-sim`
    // does, and the client opens the device path like any serial client.
    let mut _server = None;
    let mut _device = None;
    let (path, what) = match &args.port {
        Some(p) => (p.clone(), format!("rig on {p}")),
        None => {
            let (controller, device) = SerialLink::pty_pair().context("creating a pty")?;
            let path = device.path().context("pty without a path")?;
            _server = Some(
                subsurf::sim::spawn(controller, subsurf::sim::SimParams::default())
                    .context("starting the simulated rig")?,
            );
            _device = Some(device);
            (
                path.clone(),
                format!("simulated rig on pseudo-terminal {path}"),
            )
        }
    };
    let link = SerialLink::open(&path, args.baud)?;
    let mut rig = RigClient::connect(link, ClientConfig::default())
        .with_context(|| format!("connecting to the {what}"))?;
    println!("bench rig: {what}");

    // Round trips: Heartbeat (smallest request and reply) and Status (largest reply).
    for (name, command) in [
        ("heartbeat", Command::Heartbeat),
        ("status", Command::Status),
    ] {
        let start = Instant::now();
        for _ in 0..args.round_trips {
            rig.call(command.clone())
                .with_context(|| format!("{name} round trip"))?;
        }
        let secs = start.elapsed().as_secs_f64();
        println!(
            "round trips ({name}): {} in {:.3} s = {:.0} /s ({:.1} us each)",
            args.round_trips,
            secs,
            f64::from(args.round_trips) / secs,
            secs * 1e6 / f64::from(args.round_trips)
        );
    }

    // Capture events: queued programs with the shortest timings the rig accepts, so the figure
    // is the event path (rig → link → decoder → client), not the optics.
    let caps = rig.hello().capabilities;
    let per_program = u32::from(caps.max_program_points).max(1);
    let galvo_max = u32::from(caps.galvo_max).max(1);
    rig.arm().context("arming for the capture benchmark")?;
    let mut received = 0u32;
    let mut lost = 0u32;
    let mut rig_time_us = 0u64;
    let start = Instant::now();
    let mut remaining = args.captures;
    while remaining > 0 {
        let len = remaining.min(per_program);
        let points: Vec<GalvoPoint> = (0..len)
            .map(|i| GalvoPoint {
                x: u16::try_from(i % galvo_max).unwrap_or(0),
                y: 0,
            })
            .collect();
        let header = ProgramHeader {
            len: u16::try_from(len).context("program length")?,
            channel: 0,
            settle_us: Some(1),
            exposure_us: 1,
            trigger_us: 1,
            interval_us: 1,
        };
        rig.load_program(header, &points)
            .context("loading a program")?;
        rig.run_program().context("running a program")?;
        let mut got = 0u32;
        let mut first_us = None;
        loop {
            let Some(event) = rig.next_event(Duration::from_secs(10))? else {
                bail!("no event for 10 s while streaming captures");
            };
            match event.kind {
                EventKind::Captured(c) => {
                    got += 1;
                    first_us.get_or_insert(c.triggered_at_us);
                }
                EventKind::ProgramDone { completed, .. } => {
                    lost += u32::from(completed).saturating_sub(got);
                    rig_time_us += event
                        .timestamp_us
                        .saturating_sub(first_us.unwrap_or(event.timestamp_us));
                    break;
                }
                EventKind::Halted { reason } => bail!("rig halted: {reason:?}"),
                _ => {}
            }
        }
        received += got;
        remaining -= len;
    }
    let secs = start.elapsed().as_secs_f64();
    rig.disarm().context("disarming")?;
    println!(
        "capture events: {received} in {secs:.3} s = {:.0} /s (programs of {per_program} points, \
         upload included; {lost} lost; rig clock span {:.3} s)",
        f64::from(received) / secs,
        rig_time_us as f64 / 1e6
    );
    let stats = rig.stats();
    println!(
        "client: {} requests, {} retransmits, {} decoder drops",
        stats.requests,
        stats.retransmits,
        stats.decoder.dropped()
    );
    Ok(())
}
