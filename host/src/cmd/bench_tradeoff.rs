//! `subsurf bench tradeoff`: the speed/accuracy curve of the whole chain (parsing and printing
//! only; the measurement is `subsurf::bench::tradeoff`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use subsurf::bench::tradeoff::{TradeoffSettings, bench_tradeoff as run_bench, write_section};

use super::progress::StageBars;

/// Scan, fit and render settings of the whole chain against the exact result.
#[derive(Debug, clap::Args)]
pub struct TradeoffBench {
    /// Small sizes (one plan density, two presets, two render qualities) so the whole chain
    /// runs in seconds; for tests and a first look.
    #[arg(long)]
    quick: bool,
    /// Scratch folder for the simulated scans (created; removed at the end unless --keep).
    #[arg(long, default_value = "/tmp/subsurf-bench-tradeoff")]
    work: PathBuf,
    /// Keep the simulated scans in --work.
    #[arg(long)]
    keep: bool,
    /// Tessellation of the built-in sphere (rings pole to pole; vertices ≈ 2·rings²). Finer than
    /// the scan default so the render stage has work worth approximating. Default 64 (16 with
    /// --quick).
    #[arg(long)]
    rings: Option<usize>,
    /// Camera image size of the simulated scans (pixels per side). Default 96 (40 with --quick).
    #[arg(long)]
    scan_px: Option<u32>,
    /// Write the time-vs-error plot here.
    #[arg(long, default_value = "docs/bench/tradeoff.png")]
    plot: PathBuf,
    /// Replace the generated part of this BENCHMARKS.md's tradeoff section (between its
    /// `bench-tradeoff` markers; the section is appended when the markers are missing).
    #[arg(long)]
    write_benchmarks: Option<PathBuf>,
}

pub fn bench_tradeoff(b: TradeoffBench) -> Result<()> {
    let settings = TradeoffSettings {
        quick: b.quick,
        work: b.work.clone(),
        keep: b.keep,
        rings: b.rings,
        scan_px: b.scan_px,
        plot: b.plot.clone(),
    };
    let text = run_bench(
        &settings,
        &StageBars("{msg:>14} {bar:40} {pos}/{len} {elapsed}"),
    )?;
    println!("{text}");
    if let Some(md) = &b.write_benchmarks {
        write_section(md, &text).with_context(|| format!("updating {}", md.display()))?;
        println!("updated {}", md.display());
    }
    Ok(())
}
