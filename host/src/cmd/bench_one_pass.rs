//! `subsurf bench one-pass`: `subsurf fit` against the physical limit of processing a scan, one
//! decode of its frames, measured in the same run on the same (page-cached) files.
//!
//! The decode pass runs in this process (every frame read and decoded once, in parallel, and
//! dropped: `pipeline::extract::decode_pass`); the fit runs as a child process with its sample
//! cache off (so it decodes the frames itself) and reports its own peak RSS, CPU time and frame
//! reads. The decode pass runs before and after the fit; their mean is the reference.
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use subsurf::dataset::{Dataset, select_frames};

use super::progress::Bar;

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

/// The measured figures.
#[derive(Debug, serde::Serialize)]
struct Figures {
    frames: usize,
    pixels: u64,
    decode_s: [f64; 2],
    decode_cpu_s: [f64; 2],
    fit_s: f64,
    fit_cpu_s: Option<f64>,
    ratio: f64,
    fit_peak_rss_mib: Option<f64>,
    stages: serde_json::Value,
    frame_reads: serde_json::Value,
    sample_store: serde_json::Value,
}

pub fn bench_one_pass(b: OnePassBench) -> Result<()> {
    for own in ["--scan", "--out", "--report", "--cache"] {
        if b.fit_args
            .iter()
            .any(|a| a == own || a.starts_with(&format!("{own}=")))
        {
            bail!("--fit-args may not set {own}: the bench sets it (see --help)");
        }
    }
    let ds = Dataset::open(&b.scan).with_context(|| format!("opening {}", b.scan.display()))?;
    let frames = select_frames(ds.spec.frames.len(), b.frames.as_deref(), None)
        .map_err(|e| anyhow::anyhow!(e))?;
    std::fs::create_dir_all(&b.dir).with_context(|| format!("creating {}", b.dir.display()))?;
    let exe = std::env::current_exe().context("finding the subsurf executable")?;
    let bar = Bar::with_template("{msg:>12} {bar:40} {pos}/{len} {eta}");
    let decode = |bar: &Bar| {
        let (c0, t) = (subsurf::util::cpu_seconds(), Instant::now());
        let (n, px) = subsurf::pipeline::extract::decode_pass(&ds, &frames, bar);
        let cpu = subsurf::util::cpu_seconds()
            .zip(c0)
            .map_or(f64::NAN, |(a, b)| a - b);
        (n, px, t.elapsed().as_secs_f64(), cpu)
    };
    let (n, pixels, d0, c0) = decode(&bar);
    bar.finish_and_clear();
    println!("decode pass 1: {n} frames in {d0:.2} s ({c0:.1} s CPU)");
    let model = b.dir.join("model.ply");
    let report = b.dir.join("fit-report.json");
    let mut cmd = Command::new(&exe);
    cmd.arg("fit")
        .arg("--scan")
        .arg(&b.scan)
        .arg("--out")
        .arg(&model)
        .arg("--report")
        .arg(&report)
        .args(["--cache", "off"]);
    if !b.fit_args.iter().any(|a| a == "--no-pictures") {
        cmd.arg("--no-pictures");
    }
    if let Some(f) = &b.frames {
        cmd.args(["--frames", f]);
    }
    cmd.args(&b.fit_args);
    let t = Instant::now();
    let out = cmd.output().with_context(|| format!("running {cmd:?}"))?;
    let fit_s = t.elapsed().as_secs_f64();
    if !out.status.success() {
        bail!(
            "subsurf fit failed ({}):\n{}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    println!("subsurf fit: {fit_s:.2} s");
    let bar = Bar::with_template("{msg:>12} {bar:40} {pos}/{len} {eta}");
    let (_, _, d1, c1) = decode(&bar);
    bar.finish_and_clear();
    println!("decode pass 2: {d1:.2} s ({c1:.1} s CPU)");
    let rep: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&report).with_context(|| format!("reading {}", report.display()))?,
    )
    .with_context(|| format!("parsing {}", report.display()))?;
    let decode_mean = 0.5 * (d0 + d1);
    let f = Figures {
        frames: n,
        pixels,
        decode_s: [d0, d1],
        decode_cpu_s: [c0, c1],
        fit_s,
        fit_cpu_s: rep["process_cpu_s"].as_f64(),
        ratio: fit_s / decode_mean,
        fit_peak_rss_mib: rep["process_peak_rss_mib"].as_f64(),
        stages: rep["stage_seconds"].clone(),
        frame_reads: rep["frames"]["reads"].clone(),
        sample_store: rep["sample_store"].clone(),
    };
    println!(
        "one decode pass {decode_mean:.2} s (mean of {d0:.2} and {d1:.2}); subsurf fit {fit_s:.2} s \
         = {:.2} x one decode pass; fit CPU {} s against decode CPU {:.1} s",
        f.ratio,
        f.fit_cpu_s.map_or("-".into(), |c| format!("{c:.1}")),
        0.5 * (c0 + c1)
    );
    println!(
        "fit peak RSS {} MiB; frame reads {}; stages {}",
        f.fit_peak_rss_mib.map_or("-".into(), |m| format!("{m:.0}")),
        f.frame_reads,
        f.stages
    );
    if let Some(p) = &b.json {
        std::fs::write(p, serde_json::to_string_pretty(&f)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
