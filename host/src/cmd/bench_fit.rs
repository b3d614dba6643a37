//! `subsurf bench fit-scale`: how `subsurf fit` grows with frames, vertices and image size.
//! Parsing, the spinner and printing only; the measurement is `subsurf::bench::fit_scale`.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use subsurf::bench::fit_scale::{FitScaleSettings, growth, measure_grid, plot, read_rows, table};
use subsurf::progress::Progress;

/// Simulate, fit and tabulate `subsurf fit` over a grid of vertex and frame counts.
#[derive(Debug, clap::Args)]
pub struct FitScaleBench {
    /// Approximate vertex counts of the simulated sphere (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = [10_000usize, 20_000])]
    vertices: Vec<usize>,
    /// Frame counts (comma-separated); each is rounded down to whole turntable angles of
    /// `raster × raster` laser positions.
    #[arg(long, value_delimiter = ',', default_values_t = [1250usize, 2500, 5000])]
    frames: Vec<usize>,
    /// Image widths and heights, pixels (comma-separated). Every frame is decoded once (the
    /// `extract` stage), so the table's `fit / extract` column is the fit's cost beyond one
    /// decode of the frames.
    #[arg(long, value_delimiter = ',', default_values_t = [256u32])]
    size: Vec<u32>,
    /// Laser raster per axis and turntable angle.
    #[arg(long, default_value_t = 5)]
    raster: usize,
    /// Scratch directory for the datasets, models and reports (each dataset is deleted after
    /// its fit).
    #[arg(long, default_value = "/tmp/subsurf-fit-scale")]
    dir: PathBuf,
    /// Write time and peak RSS against frames as a PNG here.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Write every row as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Draw `--plot` from this JSON of an earlier run (`--json`) instead of measuring.
    #[arg(long)]
    replot: Option<PathBuf>,
    /// Extra arguments passed to `subsurf fit` (e.g. `--fit-args=--preset,balanced`).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    fit_args: Vec<String>,
}

/// The spinner as the library's progress receiver (drawn as it always was: no plain lines).
struct Spinner(indicatif::ProgressBar);

impl Progress for Spinner {
    fn set_message(&self, msg: &str) {
        self.0.set_message(msg.to_string());
    }
    fn inc(&self, n: u64) {
        self.0.inc(n);
    }
}

pub fn bench_fit_scale(b: FitScaleBench) -> Result<()> {
    if b.vertices.is_empty() || b.frames.is_empty() || b.size.is_empty() {
        bail!("--vertices, --frames and --size need at least one value each");
    }
    if let Some(json) = &b.replot {
        let rows = read_rows(json)?;
        let p = b.plot.as_deref().context("--replot needs --plot")?;
        plot(p, &rows)?;
        println!("wrote {}", p.display());
        return Ok(());
    }
    let exe = std::env::current_exe().context("locating the subsurf binary")?;
    std::fs::create_dir_all(&b.dir).with_context(|| format!("creating {}", b.dir.display()))?;
    if cfg!(debug_assertions) {
        println!("warning: debug build; figures for BENCHMARKS.md come from --release");
    }
    println!(
        "fit-scale: sphere, 1 camera, EXR frames of {0:?} px, {1}x{1} laser raster per angle, {2} rayon threads",
        b.size,
        b.raster,
        rayon::current_num_threads()
    );
    let total = b.size.len() * b.vertices.len() * b.frames.len();
    // Children run with captured output; this bar shows which one is running.
    let bar = indicatif::ProgressBar::new(2 * total as u64).with_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{pos}/{len} runs, {elapsed}]")
            .context("progress style")?,
    );
    bar.enable_steady_tick(std::time::Duration::from_millis(250));
    let settings = FitScaleSettings {
        vertices: b.vertices.clone(),
        frames: b.frames.clone(),
        size: b.size.clone(),
        raster: b.raster,
        dir: b.dir.clone(),
        fit_args: b.fit_args.clone(),
    };
    let spinner = Spinner(bar);
    let rows = measure_grid(&settings, &exe, &spinner, &mut |text| {
        spinner.0.suspend(|| print!("{text}"))
    })?;
    spinner.0.finish_and_clear();
    print!("{}", table(&rows));
    print!("{}", growth(&rows));
    if let Some(p) = &b.json {
        std::fs::write(p, serde_json::to_string_pretty(&rows)?)
            .with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    if let Some(p) = &b.plot {
        plot(p, &rows)?;
        println!("wrote {}", p.display());
    }
    Ok(())
}
