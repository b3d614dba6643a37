//! `subsurf bench one-pass`: `subsurf fit` against one decode pass of its frames
//! ([`subsurf::bench::one_pass`]).
use std::path::PathBuf;

use anyhow::{Context, Result};
use subsurf::bench::one_pass::{OnePassSetup, bench_one_pass as measure};

use super::progress::StageBars;

/// Time `subsurf fit` against one decode pass over the same frames.
#[derive(Debug, clap::Args)]
pub struct OnePassBench {
    /// The scan dataset.
    #[arg(long)]
    scan: PathBuf,
    /// Frames to use (default: all).
    #[arg(long)]
    frames: Option<String>,
    /// Where the model and report go.
    #[arg(long, default_value = "/tmp/subsurf-one-pass")]
    dir: PathBuf,
    /// Extra arguments for `subsurf fit` (e.g. `--fit-args=--alpha-rounds,0`). The bench gives
    /// `--scan`, `--out`, `--report`, `--cache off` (the fit must decode the frames itself) and
    /// `--no-pictures` itself; the first four are refused here, the last accepted.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    fit_args: Vec<String>,
    /// Write the figures as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

pub fn bench_one_pass(b: OnePassBench) -> Result<()> {
    let setup = OnePassSetup {
        scan: b.scan,
        frames: b.frames,
        dir: b.dir,
        fit_args: b.fit_args,
        exe: std::env::current_exe().context("finding the subsurf executable")?,
    };
    let f = measure(&setup, &StageBars("{msg:>12} {bar:40} {pos}/{len} {eta}"))?;
    if let Some(p) = &b.json {
        std::fs::write(p, serde_json::to_string_pretty(&f)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
