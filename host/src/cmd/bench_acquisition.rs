//! `subsurf bench acquisition`: the planners' learning curves (parsing and printing only; the
//! measurement is `subsurf::bench::acquisition`).
use anyhow::{Context, bail};
use std::path::PathBuf;

use subsurf::bench::acquisition::{BenchOptions, bench_replay, record_sim_dense};

use super::plan::AdaptiveArgs;
use super::progress::Bar;

/// Learning curves (held-out error on test frames no planner may pick, against frames and rig
/// time) of the dense, coverage, random and adaptive planners, on a recorded dataset replayed
/// or on a dense scan of the simulated rig.
#[derive(Debug, clap::Args)]
pub struct AcquisitionBench {
    /// A recorded dataset to replay (its test frames: --test-frames).
    #[arg(long, conflicts_with = "sim")]
    replay: Option<PathBuf>,
    /// Frames no planner may pick, judged after every fit (e.g. `96-103`).
    #[arg(long, requires = "replay")]
    test_frames: Option<String>,
    /// The simulated rig: a dense scan of the built-in object (recorded into --work, every
    /// third angle's frames the test frames), replayed.
    #[arg(long)]
    sim: bool,
    /// Turntable angles of the simulated rig's dense scan.
    #[arg(long, default_value_t = 12)]
    angles: usize,
    /// Galvo raster points per axis of the simulated rig's dense scan.
    #[arg(long, default_value_t = 4)]
    raster: usize,
    /// Working directory (the replays, the sample store; kept, resumed by a second run).
    #[arg(long)]
    work: PathBuf,
    /// Seeds of the random planner's orders, each judged on its own.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    random_seeds: Vec<u64>,
    /// The adaptive planner's start sets (`--start-seed` of each run).
    #[arg(long, value_delimiter = ',', default_value = "0,1,2")]
    start_seeds: Vec<u64>,
    /// Draw the curves here (PNG).
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Write the figures here (JSON).
    #[arg(long)]
    json: Option<PathBuf>,
    #[command(flatten)]
    adaptive: AdaptiveArgs,
}

pub fn bench_acquisition(a: AcquisitionBench) -> anyhow::Result<()> {
    let bar = Bar::with_template("{msg:>16} {bar:30} {pos}/{len} {eta}");
    let (src, test) = match (&a.replay, a.sim) {
        (Some(src), false) => {
            let test = subsurf::dataset::parse_frame_list(a.test_frames.as_deref().unwrap_or(""))
                .map_err(anyhow::Error::msg)?;
            (src.clone(), test)
        }
        (None, true) => {
            let dir = a.work.join("sim-dense");
            let test = record_sim_dense(&dir, a.angles, a.raster, &bar)
                .context("recording the simulated rig's dense scan")?;
            (dir, test)
        }
        _ => bail!("say what to replay: --replay DATASET --test-frames F, or --sim"),
    };
    let b = bench_replay(
        &src,
        &test,
        &a.work,
        &a.adaptive.settings(),
        &BenchOptions {
            start_seeds: a.start_seeds.clone(),
            random_seeds: a.random_seeds.clone(),
            margin: subsurf::bench::acquisition::MARGIN,
        },
        &bar,
        &mut |line| bar.suspend(|| println!("{line}")),
    )
    .with_context(|| format!("benchmarking the planners on {}", src.display()))?;
    bar.finish_and_clear();
    println!(
        "{} ({} pool frames, test frames {}; {:.0} s)\n",
        b.dataset,
        b.pool,
        subsurf::dataset::format_frame_list(&b.test_frames),
        b.seconds
    );
    println!("{}", b.table());
    if let Some(p) = &a.plot {
        b.plot(p)
            .with_context(|| format!("drawing {}", p.display()))?;
        println!("plot: {}", p.display());
    }
    if let Some(j) = &a.json {
        std::fs::write(j, serde_json::to_string_pretty(&b)? + "\n")
            .with_context(|| format!("writing {}", j.display()))?;
    }
    Ok(())
}
