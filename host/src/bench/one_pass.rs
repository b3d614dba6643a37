//! `subsurf bench one-pass`: `subsurf fit` against the physical limit of processing a scan, one
//! decode of its frames, measured in the same run on the same (page-cached) files.
//!
//! The decode pass runs in this process (every frame read and decoded once, in parallel, and
//! dropped: [`crate::pipeline::extract::decode_pass`]); the fit runs as a child process with its
//! sample cache off (so it decodes the frames itself) and reports its own peak RSS, CPU time and
//! frame reads. The decode pass runs before and after the fit; their mean is the reference.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use crate::dataset::{Dataset, DatasetError, select_frames};
use crate::progress::Stages;

/// What the bench measures.
#[derive(Debug, Clone)]
pub struct OnePassSetup {
    /// The scan dataset.
    pub scan: PathBuf,
    /// Frames to use (`--frames` syntax; `None`: all).
    pub frames: Option<String>,
    /// Where the model and report go.
    pub dir: PathBuf,
    /// Extra arguments for `subsurf fit`; it may not set `--scan`, `--out`, `--report` or
    /// `--cache` (the bench does).
    pub fit_args: Vec<String>,
    /// The `subsurf` executable that runs the fit.
    pub exe: PathBuf,
}

/// Why the bench could not measure.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OnePassError {
    /// `fit_args` sets what the bench sets.
    #[error("--fit-args may not set {0}: the bench sets it (see --help)")]
    Owned(String),
    /// The frame selection is invalid.
    #[error("{0}")]
    Frames(String),
    /// The scan cannot be opened.
    #[error("opening {path}: {source}")]
    Dataset {
        /// The scan.
        path: String,
        /// Why.
        source: DatasetError,
    },
    /// A file or the child process failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// Why.
        source: std::io::Error,
    },
    /// The fit failed or its report is unreadable.
    #[error("{0}")]
    Fit(String),
}

/// The measured figures.
#[derive(Debug, serde::Serialize)]
pub struct OnePassFigures {
    /// Frames decoded per pass.
    pub frames: usize,
    /// Pixels decoded per pass.
    pub pixels: u64,
    /// Wall time of the two decode passes, s.
    pub decode_s: [f64; 2],
    /// CPU time of the two decode passes, s.
    pub decode_cpu_s: [f64; 2],
    /// Wall time of `subsurf fit`, s.
    pub fit_s: f64,
    /// CPU time of `subsurf fit` (its report), s.
    pub fit_cpu_s: Option<f64>,
    /// `fit_s` over the mean decode pass.
    pub ratio: f64,
    /// Peak RSS of `subsurf fit` (its report), MiB.
    pub fit_peak_rss_mib: Option<f64>,
    /// The fit report's stage times.
    pub stages: serde_json::Value,
    /// The fit report's frame reads.
    pub frame_reads: serde_json::Value,
    /// The fit report's sample store.
    pub sample_store: serde_json::Value,
}

fn io(what: String) -> impl FnOnce(std::io::Error) -> OnePassError {
    move |source| OnePassError::Io { what, source }
}

/// Runs the bench: a decode pass, `subsurf fit`, a decode pass; says each result as it comes.
pub fn bench_one_pass(b: &OnePassSetup, ui: &impl Stages) -> Result<OnePassFigures, OnePassError> {
    for own in ["--scan", "--out", "--report", "--cache"] {
        if b.fit_args
            .iter()
            .any(|a| a == own || a.starts_with(&format!("{own}=")))
        {
            return Err(OnePassError::Owned(own.into()));
        }
    }
    let ds = Dataset::open(&b.scan).map_err(|source| OnePassError::Dataset {
        path: b.scan.display().to_string(),
        source,
    })?;
    let frames = select_frames(ds.spec.frames.len(), b.frames.as_deref(), None)
        .map_err(OnePassError::Frames)?;
    std::fs::create_dir_all(&b.dir).map_err(io(format!("creating {}", b.dir.display())))?;
    let decode = |name: &str| {
        let bar = ui.stage(frames.len() as u64, name);
        let (c0, t) = (crate::util::cpu_seconds(), Instant::now());
        let (n, px) = crate::pipeline::extract::decode_pass(&ds, &frames, &bar);
        let cpu = crate::util::cpu_seconds()
            .zip(c0)
            .map_or(f64::NAN, |(a, b)| a - b);
        ui.finish(bar);
        (n, px, t.elapsed().as_secs_f64(), cpu)
    };
    let (n, pixels, d0, c0) = decode("decode pass 1");
    ui.say(&format!(
        "decode pass 1: {n} frames in {d0:.2} s ({c0:.1} s CPU)"
    ));
    let (fit_s, rep) = run_fit(b)?;
    ui.say(&format!("subsurf fit: {fit_s:.2} s"));
    let (_, _, d1, c1) = decode("decode pass 2");
    ui.say(&format!("decode pass 2: {d1:.2} s ({c1:.1} s CPU)"));
    let decode_mean = 0.5 * (d0 + d1);
    let f = OnePassFigures {
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
    ui.say(&format!(
        "one decode pass {decode_mean:.2} s (mean of {d0:.2} and {d1:.2}); subsurf fit {fit_s:.2} s \
         = {:.2} x one decode pass; fit CPU {} s against decode CPU {:.1} s",
        f.ratio,
        f.fit_cpu_s.map_or("-".into(), |c| format!("{c:.1}")),
        0.5 * (c0 + c1)
    ));
    ui.say(&format!(
        "fit peak RSS {} MiB; frame reads {}; stages {}",
        f.fit_peak_rss_mib.map_or("-".into(), |m| format!("{m:.0}")),
        f.frame_reads,
        f.stages
    ));
    Ok(f)
}

/// `subsurf fit` in a child process, its sample cache off: its wall time and its report.
fn run_fit(b: &OnePassSetup) -> Result<(f64, serde_json::Value), OnePassError> {
    let model = b.dir.join("model.ply");
    let report: &Path = &b.dir.join("fit-report.json");
    let mut cmd = Command::new(&b.exe);
    cmd.arg("fit")
        .arg("--scan")
        .arg(&b.scan)
        .arg("--out")
        .arg(&model)
        .arg("--report")
        .arg(report)
        .args(["--cache", "off"]);
    if !b.fit_args.iter().any(|a| a == "--no-pictures") {
        cmd.arg("--no-pictures");
    }
    if let Some(f) = &b.frames {
        cmd.args(["--frames", f]);
    }
    cmd.args(&b.fit_args);
    let t = Instant::now();
    let out = cmd.output().map_err(io(format!("running {cmd:?}")))?;
    let fit_s = t.elapsed().as_secs_f64();
    if !out.status.success() {
        return Err(OnePassError::Fit(format!(
            "subsurf fit failed ({}):\n{}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    let bytes = std::fs::read(report).map_err(io(format!("reading {}", report.display())))?;
    let rep = serde_json::from_slice(&bytes)
        .map_err(|e| OnePassError::Fit(format!("parsing {}: {e}", report.display())))?;
    Ok((fit_s, rep))
}
